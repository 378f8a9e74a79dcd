"""Mirror symmetry of the DOE-plane field (raywave.hybrid.mirror): a mirror-symmetric lens sends the source (−x, y)
the mirror image of the field of (x, y); HybridLens.doe_fields builds such pairs once."""

import warnings

import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.hybrid.coherent.geometry import footprints
from raywave.imaging.psfmap import field_grid
from raywave.lens.build import bundled_lens_path


@pytest.fixture(scope="module")
def hybrid():
    return load_hybrid(bundled_lens_path("hybrid_asphere"), stop_edge="doe")


def test_footprints_of_mirror_image_sources_are_mirror_images(hybrid):
    """The footprint's rim rays sit a hair inside the stop (RIM_INSET): a ray aimed exactly at the rim passed or was
    stopped by the rounding of its aim, and at this corner node of the 10×10 map the source (−x, y) lost one that
    (x, y) kept (its node spacing, hence its field, differed by 0.6 %)."""
    f = field_grid(hybrid, (10, 10))
    pair = torch.stack([f[8, 6], f[8, 3]])
    assert float((pair[0, 0] + pair[1, 0]).abs()) < 1e-11 and float((pair[0, 1] - pair[1, 1]).abs()) < 1e-11
    (a,), (b,) = footprints(hybrid.optics, pair, torch.tensor([0.66], dtype=torch.float64), None, hybrid.doe_z())
    assert b == pytest.approx((-a[1], -a[0], a[2], a[3]), abs=1e-12)
