"""Issue 43: the coarse start of many accurate constructions as one batched computation.

Each construction's Newton start (:func:`raywave.hybrid.coherent.accurate._coarse_start`: the solutions on every
4th node interpolated to all nodes, and the Jacobian of that interpolant) is a request
(:class:`~raywave.hybrid.coherent.accurate._CoarseRequest`) that :func:`~raywave.hybrid.coherent.run_batched` answers
for the constructions of a round together: on an accelerator as one padded batch (node grids of different sizes,
each with its own spacing and boundary differences), on a CPU one by one. Both must give the same starts, NaNs
(unconverged coarse nodes) included, and the PSFs must not move beyond the Newton tolerance's rounding."""

import warnings

import pytest
import torch

import raywave.hybrid.coherent.accurate as acc
import raywave.utils.devices as devices
from raywave.assembly.build import load_hybrid
from raywave.lens.build import bundled_lens_path

FIELDS = [(0.0, 0.0), (0.0, 6.0), (4.0, 3.0), (-7.0, -9.0)]
WLS = [0.66, 0.47]


@pytest.fixture(scope="module")
def asphere():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


def _psfs(hl):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            return hl.psf_result(FIELDS, WLS, ks=32).psf


def test_batched_coarse_start_equals_one_by_one(asphere, monkeypatch):
    """The padded batch's starts and Jacobians equal each construction's own (their node grids differ in size and
    spacing), to the products' rounding; NaN at the same nodes; and a map's PSFs with the batched starts stay within
    1e-10 of the one-by-one ones (the nodes converge on their own)."""
    seen = []
    real = acc._CoarseRequest.run_group

    def record(reqs):
        seen.append(list(reqs))
        return real(reqs)

    monkeypatch.setattr(acc._CoarseRequest, "run_group", staticmethod(record))
    ref = _psfs(asphere)
    reqs = max(seen, key=len)
    assert len(reqs) > 2 and len({r.nodes for r in reqs}) > 1 and len({r.h for r in reqs}) > 1
    # a coarse node that did not converge: its NaN must spread to the same nodes in both
    bad = reqs[1]
    reqs[1] = acc._CoarseRequest(bad.uv, bad.conv.clone().index_fill_(0, torch.tensor([5]), False), bad.coarse,
                                 bad.nodes, bad.h)
    batched = acc._coarse_batch(reqs)
    for r, (uv_b, jac_b) in zip(reqs, batched):
        uv_1, jac_1 = acc._coarse_one(r)
        assert uv_b.shape == uv_1.shape and jac_b.shape == jac_1.shape
        for b, one in ((uv_b, uv_1), (jac_b, jac_1)):
            assert torch.equal(torch.isnan(b), torch.isnan(one))
            ok = ~torch.isnan(one)
            assert float((b[ok] - one[ok]).abs().max()) <= 1e-12 * float(one[ok].abs().max())
    assert bool(torch.isnan(batched[1][0]).any())
    monkeypatch.setattr(devices, "accelerator", lambda x: True)  # the accelerator's plan: batched starts
    seen.clear()
    got = _psfs(asphere)
    assert max(len(g) for g in seen) > 2
    rel = (got - ref).abs().sum((-2, -1)) / ref.abs().sum((-2, -1))
    assert float(rel.max()) < 1e-7  # the accelerator's shared FFT sizes (≤ 3e-8); the batched starts alone: 7e-14
