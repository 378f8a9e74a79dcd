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


def test_symmetric_axes_follow_the_lens_and_its_apertures(hybrid):
    """Both axes for a rotationally symmetric lens; an obscuration decentred along x keeps only y; a diffractive
    surface (any phase) keeps neither."""
    import copy

    from raywave.hybrid.mirror import symmetric_axes
    from raywave.surfaces.aperture import CircularAperture, Obscuration
    from raywave.surfaces.interaction import Diffraction

    assert symmetric_axes(hybrid.lens, hybrid.doe, 1) == (True, True)
    lens = copy.deepcopy(hybrid.lens)
    stop = lens.surfaces[lens.stop_index]
    stop.aperture = CircularAperture(float(stop.aperture.radius), Obscuration("circle", radius=0.1, decenter=(0.2, 0)))
    assert symmetric_axes(lens, hybrid.doe, 1) == (False, True)
    lens = copy.deepcopy(hybrid.lens)
    lens.surfaces[1].interaction = Diffraction(lambda x, y, w: (x * 0, x * 0, x * 0))
    assert symmetric_axes(lens, hybrid.doe, 1) == (False, False)


def test_mirror_sources_pairs_exact_mirror_images_only():
    from raywave.hybrid.mirror import mirror_sources

    f = torch.tensor([[-3.0, 2.0], [3.0, 2.0], [3.0, -2.0], [-3.0, -2.0], [3.0 + 1e-9, 2.0], [0.0, 5.0], [0.0, -5.0],
                      [-3.0, 2.0 + 1e-14]], dtype=torch.float64)
    src = mirror_sources(f, (True, True))
    assert src[:4] == [None, (0, True, False), (0, True, True), (0, False, True)]
    assert src[4] is None  # 1e-9 away: another source
    assert src[5:] == [None, (5, False, True), (0, False, False)]  # within TWIN_TOL: the same source
    assert mirror_sources(f, (True, False))[2:4] == [None, (2, True, False)]  # no y symmetry: built


@pytest.mark.parametrize("edge", ["doe", "exit_pupil"])
def test_mirrored_fields_equal_the_fields_built_for_their_sources(hybrid, edge):
    """The four mirror images of a source in one call (one built, three mirrored) against each built alone
    (``mirror=False``): the same windows, carriers and chief-ray points, PSFs within 1e-12, whatever the DOE's phase
    (a random pixel map: the phase is applied after the field stage)."""
    from raywave.doe import PixelDOE

    gen = torch.Generator().manual_seed(3)
    doe = PixelDOE(torch.rand(hybrid.doe.shape, generator=gen, dtype=torch.float64) * 6.0, hybrid.doe.pitch)
    on = hybrid.with_doe(doe, stop_edge=edge)
    off = hybrid.with_doe(doe, stop_edge=edge, mirror=False)
    f = torch.tensor([[6.0, 3.5], [-6.0, 3.5], [6.0, -3.5], [-6.0, -3.5]], dtype=torch.float64)
    wls = (0.47, 0.66)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, b = on.doe_fields(f, wls, rays=32), off.doe_fields(f, wls, rays=32)
        pa, pb = on.psf(f, wls, ks=32, rays=32), off.psf(f, wls, ks=32, rays=32)
    for ra, rb in zip(a, b):
        for x, y in zip(ra, rb):
            assert x.box == y.box and x.carrier == pytest.approx(y.carrier, abs=1e-15)
            assert float(torch.stack(x.center).sub(torch.stack(y.center)).abs().max()) < 1e-14
            assert x.chief_tan == pytest.approx(y.chief_tan, abs=1e-15)
    assert float((pa - pb).abs().max()) < 1e-12
    assert float((pa[0, 0] - pa[1, 0].flip(-1)).abs().max()) > 1e-4  # the DOE is not symmetric: PSFs are not


def test_mirrored_fields_carry_the_lens_gradient(hybrid):
    """The gradient of a loss over mirror images with respect to a lens curvature and the sensor distance equals
    the one through fields built for each source."""
    import copy

    f = torch.tensor([[5.0, 2.0], [-5.0, 2.0], [-5.0, -2.0]], dtype=torch.float64)
    w = torch.linspace(0, 1, 16 * 16, dtype=torch.float64).reshape(16, 16)
    grads = []
    for mirror in (True, False):
        hl = copy.deepcopy(hybrid)
        hl.mirror = mirror
        params = [hl.lens.surfaces[1].geometry.curvature, hl.lens.surfaces[-1].thickness]
        for p_ in params:
            p_.requires_grad_(True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loss = (hl.psf(f, (0.53,), ks=16, rays=24) * w).sum()
        grads.append(torch.stack(torch.autograd.grad(loss, params)))
    assert torch.allclose(grads[0], grads[1], rtol=1e-8, atol=0.0)
