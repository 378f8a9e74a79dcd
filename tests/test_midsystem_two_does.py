"""Two DOEs in one lens and a conformal DOE (issue 46) against the independent wave-optics reference of
tests/wave_truth_doe.py: a second DOE 1 mm behind the first; the first on a sphere in air, its phase applied on the
sag by multi-slice angular spectrum in the reference (no rays there) and by the local grating on the curved surface
in raywave."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import MidSystemLens  # noqa: E402

N, PITCH, PS, KS = 1000, 1e-3, 2e-3, 32


def _two_does(field, levels=None):
    sys_ = W.TwoLensSystem(f_doe=50.0, f_doe2=-80.0, gap1=3.0, gap12=1.0, gap2=2.0, field=field)
    d1 = FresnelDOE(50.0, N, PITCH, wavelength=0.55)
    d2 = FresnelDOE(-80.0, N, PITCH, wavelength=0.55)
    if levels:
        d1.fabricate(levels), d2.fabricate(levels)
    ml = MidSystemLens(M.two_lens(sys_), [d1, d2], 0, [3.0, 4.0], final_distance=0.01, final_size=1.0,
                       final_pitch=1e-3, sensor_pitch=PS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fabricated: the weak orders' sampling warnings
        res = ml.psf_result([field], 0.55, ks=KS)
    center = res.center[0, 0].detach().numpy()
    np.testing.assert_allclose(center, sys_.image()[:2], atol=2e-5)
    ref = W.sensor_psf(sys_, N, PITCH, d1.phase(0.55).detach().numpy(), center, PS, KS,
                       doe2_phase=d2.phase(0.55).detach().numpy())
    return W.rel_l1(res.psf[0, 0].detach().numpy(), ref), ml


@pytest.mark.parametrize("field", [(0.0, 0.0), pytest.param((0.0, 1.5), marks=pytest.mark.slow)])
def test_two_does_against_the_reference(field):
    """Fresnel DOEs f = 50 mm and f = −80 mm, 1 mm apart (continuous): measured 4.3e-4 at 0°, 4.8e-4 at 1.5°
    relative L1."""
    err, ml = _two_does(field)
    assert len(ml.orders(0.55)) == 1
    assert err < 1e-3, err


@pytest.mark.slow
def test_conformal_doe_against_the_reference():
    """A Fresnel DOE (f 10 mm) on a sphere of radius 10 mm in air (10× the DOE's 1 mm aperture), 3 mm after lens A,
    at 3°: within 5e-3 of the reference with the DOE's phase applied on the sag (measured 2.8e-3; 2.6e-3 against the
    reference at half its 0.5 µm slice step, which moves it by 9.7e-4). The same DOE flat is 6.6e-3 from the
    curved reference: the test sees the sag."""
    field = (0.0, 3.0)
    sys_ = W.TwoLensSystem(f_doe=10.0, field=field, doe_radius=10.0)
    doe = FresnelDOE(10.0, N, PITCH, wavelength=0.55)
    ml = MidSystemLens(M.two_lens_split(sys_), doe, 1, None, final_distance=0.01, final_size=1.0, final_pitch=1e-3,
                       sensor_pitch=PS)
    res = ml.psf_result([field], 0.55, ks=KS)
    center = res.center[0, 0].detach().numpy()
    phase = doe.phase(0.55).detach().numpy()
    curved = W.sensor_psf(sys_, N, PITCH, phase, center, PS, KS, sag_step=5e-4)
    flat = W.sensor_psf(W.TwoLensSystem(f_doe=10.0, field=field), N, PITCH, phase, center, PS, KS)
    assert W.rel_l1(res.psf[0, 0].detach().numpy(), curved) < 5e-3
    assert W.rel_l1(flat, curved) > 5e-3


@pytest.mark.parametrize("radius,bar", [(10.0, 3e-3), (20.0, 2e-3), (-10.0, 3e-3)])
def test_conformal_doe_exact_edge(radius, bar):
    """The conformal DOE of the test above (Fresnel f 10 mm, 3°) on spheres of radius 10, 20 and −10 mm (10× and 20×
    its aperture), with the exact edge (``stop_edge="exit_pupil", edge_step="asm"``): measured 2.1e-3 / 1.2e-3 /
    2.2e-3 against the bar 5e-3 (benchmarks/midsystem_sweep.py). With the default cut on the engine's plane 2.8e-3 /
    4.7e-3 / 1.4e-2: that cut's own error for this strong DOE (the same DOE flat, on a plane surface: 7.7e-3 with
    the cut, 4.7e-4 with the exact edge) adds to the sag's, in either sign (docs/ray-wave.md)."""
    field = (0.0, 3.0)
    sys_ = W.TwoLensSystem(f_doe=10.0, field=field, doe_radius=radius)
    doe = FresnelDOE(10.0, N, PITCH, wavelength=0.55)
    ml = MidSystemLens(M.two_lens_split(sys_), doe, 1, None, final_distance=0.01, final_size=1.0, final_pitch=1e-3,
                       sensor_pitch=PS, stop_edge="exit_pupil", edge_step="asm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the 1 µm pixels' flat steps at the DOE's edge (1.1 %)
        res = ml.psf_result([field], 0.55, ks=KS)
    center = res.center[0, 0].detach().numpy()
    curved = W.sensor_psf(sys_, N, PITCH, doe.phase(0.55).detach().numpy(), center, PS, KS, sag_step=5e-4)
    assert W.rel_l1(res.psf[0, 0].detach().numpy(), curved) < bar


def test_conformal_doe_placement():
    """distance=None puts the phase on the surface itself (its sag, its index), keeping its thickness; a surface
    that does not refract is refused."""
    sys_ = W.TwoLensSystem(f_doe=10.0, doe_radius=10.0)
    doe = FresnelDOE(10.0, 200, PITCH, wavelength=0.55)
    lens = M.two_lens_split(sys_)
    ml = MidSystemLens(lens, doe, 1, None, final_distance=0.01, final_size=0.4, final_pitch=1e-3, sensor_pitch=PS)
    lm, idx = ml.build_lens([1.0])
    assert idx == [1] and len(lm.surfaces) == 3
    assert lm.surfaces[1].geometry is lens.surfaces[1].geometry
    assert lm.surfaces[1].interaction.kind == "diffraction"
    assert float(lm.surfaces[1].thickness) == float(lens.surfaces[1].thickness)
    with pytest.raises(ValueError, match="conformal DOE needs a refracting surface"):
        MidSystemLens(lens, doe, 0, None, final_distance=0.01, final_size=0.4, final_pitch=1e-3)


def test_conformal_and_two_doe_gradients_by_finite_differences():
    """d(Σ w·PSF) at 1°, against central differences of the PSF, the error measured against the size of the sum's
    terms ``Σ|w·∂PSF|`` (a relative error of the sum alone is ill-posed: Σ ∂PSF = 0, so a weighted sum of the
    derivatives can nearly cancel). Measured: the curvature of the conformal surface (R 10 mm) 1.8e-4, the focal
    length of its DOE 4.6e-5, of the second of two DOEs 8.6e-6 (relative to the sum itself: 5.2e-3, 2.4e-4,
    1.0e-4). The 5.2e-3 once reported for the curvature is that near-cancelling sum: with five other random weight
    maps the same derivative reads 1e-4 … 0.35 relative to the sum, but 1.1e-5 … 1.1e-4 of ``‖∂PSF/∂c‖₁``, as good
    as lens A's focal length in the same system (0.9e-4 … 1.5e-4 of its own); no term is missing, and the
    derivative is not node-limited (32 / 64 / 128 nodes: 5.1e-3 / 5.2e-3 / 5.8e-3 of the same sum)."""
    import torch

    field = (0.0, 1.0)
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    sys_c = W.TwoLensSystem(f_doe=10.0, field=field, doe_radius=10.0)
    lens_c = M.two_lens_split(sys_c)
    doe_c = FresnelDOE(10.0, 800, PITCH, wavelength=0.55)
    # the cut (stop_edge="doe"): the default "auto" takes the exact edge for this conformal DOE at 1° (its cut
    # estimate 1.3e-5 > CUT_MISMATCH_TOL), whose node mesh moves with the lens (central differences need it held:
    # tests/test_midsystem_weak_edge.py); the two DOEs keep the cut under "auto" (8.0e-7)
    conf = MidSystemLens(lens_c, doe_c, 1, None, final_distance=0.01, final_size=0.8, final_pitch=1e-3,
                         sensor_pitch=PS, stop_edge="doe")
    sys_t = W.TwoLensSystem(f_doe=50.0, f_doe2=-80.0, gap1=3.0, gap12=1.0, gap2=2.0, field=field)
    d1, d2 = FresnelDOE(50.0, 800, PITCH, wavelength=0.55), FresnelDOE(-80.0, 800, PITCH, wavelength=0.55)
    two = MidSystemLens(M.two_lens(sys_t), [d1, d2], 0, [3.0, 4.0], final_distance=0.01, final_size=0.8,
                        final_pitch=1e-3, sensor_pitch=PS)
    cases = [(conf, lens_c.surfaces[1].geometry.curvature, 5e-4), (conf, doe_c.focal_length, 5e-4),
             (two, d2.focal_length, 5e-4)]
    for ml, prm, tol in cases:
        def psf():
            return ml.psf([field], 0.55, ks=16)[0, 0]

        g = torch.autograd.grad((psf() * w).sum(), prm)[0]
        terms = M.central_difference_terms(psf, w, prm, 1e-6)
        fd = float(terms.sum())
        assert abs(float(g) - fd) <= tol * float(terms.abs().sum()), (float(g), fd, float(terms.abs().sum()))
