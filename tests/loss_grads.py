"""A weighted-PSF loss and its gradients for the batched-stage tests (tests/test_batched_field_stage.py,
tests/test_batched_node_maps.py): each compares a stage's batched and per-construction paths through them."""

import warnings

import torch


def loss_and_grads(hl, fields, wavelengths) -> tuple:
    """``(loss, grads)``: a fixed random weighting of the PSFs of ``hl`` (a HybridLens) at ``fields`` × ``wavelengths``
    (ks 24, 24 nodes), and its gradients with respect to the DOE's trainable parameters and the first surface's
    curvature (detached copies)."""
    params = [p for p in hl.doe.parameters() if p.requires_grad] + [hl.lens.surfaces[1].geometry.curvature]
    hl.zero_grad()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = hl.psf_result(fields, wavelengths, ks=24, rays=24)
    w = torch.rand(r.psf.shape, dtype=r.psf.dtype, generator=torch.Generator().manual_seed(0))
    loss = (r.psf * w).sum()
    loss.backward()
    return float(loss.detach()), [p.grad.detach().clone() for p in params]
