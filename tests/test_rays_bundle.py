"""RayBundle: batch indexing and splitting."""

import torch

from raywave.rays.bundle import RayBundle


def test_unbind_gives_the_indexed_bundles():
    """``RayBundle.unbind(dim)``: the bundles of each index along a batch dimension, as indexing gives them (views
    from one unbind per field), with a broadcast wavelength."""
    g = torch.Generator().manual_seed(0)
    b = RayBundle.create(torch.randn(3, 2, 3, generator=g), torch.randn(3, 2, 3, generator=g), 0.5)
    for dim in (0, 1):
        parts = b.unbind(dim)
        assert len(parts) == b.shape[dim]
        for k, part in enumerate(parts):
            ref = b[k] if dim == 0 else b[:, k]
            assert part.shape == ref.shape
            for name in ("o", "d", "wavelength", "valid", "opl"):
                assert torch.equal(getattr(part, name), getattr(ref, name))
