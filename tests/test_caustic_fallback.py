"""A DOE plane near the rays' focus (issue 47): the a-priori estimate of the geometric-optics field's error there
(raywave.hybrid.coherent.exit_pupil.go_phase_error) and the fallback it triggers (the field built on an earlier plane
and carried to the DOE plane by the angular spectrum).

Physics: the accurate construction builds the field on the DOE plane from rays (geometric optics). Its first
neglected term, the diffraction term of the eikonal ``(1/2k) ∇⊥²A/A`` integrated along each ray, grows as the plane
nears the rays' focus, where their density varies fast on the scale of a Fresnel zone. With a blank DOE and the
stop's edge at the exit pupil the PSF does not depend on where the DOE sits (docs/ray-wave.md), so a plane far from
focus is an independent check of one near it. The bundled singlet (f ≈ 100 mm, spherical aberration) on axis: the
DOE 80 mm after the lens (estimate ~1e-5 rad) and 93.5 mm, 5 mm before focus (~1e-3 rad).
"""

import math
import warnings

import pytest
import torch

import raywave.hybrid.coherent.exit_pupil as ep
from raywave.assembly.build import load_hybrid
from raywave.hybrid import HybridLens
from raywave.hybrid.coherent import StopEdgeWarning
from raywave.hybrid.coherent.settings import Source
from raywave.doe import BlankDOE
from raywave.lens.build import ideal_lens

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")

NEAR, FAR, PITCH = 93.5, 80.0, 2e-3


def _singlet(d, size=None):
    return load_hybrid("singlet", doe_distance=d, doe_size=size, fields=[[0.0, 0.0]], sensor_pitch=PITCH)


def _estimate(hl, d=None):
    lens = hl.lens
    wl = lens.primary_wavelength
    z = hl.doe_z() if d is None else float(lens.vertex_z()[-1].detach()) + d
    with torch.no_grad():
        zs, err = ep.go_phase_error(lens, Source((0.0, 0.0), wl, None, lens.field_type), hl.exit_pupil_z(wl), z)
    return zs, err


def test_the_estimate_grows_towards_focus_and_is_zero_for_a_sphere():
    """The singlet: below the tolerance at 80 mm, above it 5 mm before focus, rising monotonically on the planes
    between (from the exit pupil); an ideal lens (a perfect sphere: uniform ray density) ~0."""
    hl = _singlet(FAR)
    assert float(_estimate(hl)[1][-1]) < 0.2 * ep.GO_PHASE_TOL
    zs, err = _estimate(hl, NEAR)
    assert float(err[-1]) > 4 * ep.GO_PHASE_TOL
    late = err[len(err) // 2:]
    assert bool((late[1:] >= late[:-1]).all())
    lens = ideal_lens(20.0, f_number=4, wavelengths=(0.55,))
    sphere = HybridLens(lens, BlankDOE(2000, 1e-3), 15.0, sensor_pitch=PITCH)
    with torch.no_grad():
        _, e = ep.go_phase_error(lens, Source((0.0, 0.0), 0.55, None, lens.field_type), sphere.exit_pupil_z(0.55),
                                 sphere.doe_z())
    assert float(e[-1]) < 1e-9


def test_the_estimate_of_many_sources_is_each_sources_own():
    """A call estimates every built source at once (one trace of all their stop grids): each source's planes and
    errors are those of its own estimate (the batched aiming converges each ray as its own does, to rounding)."""
    hl = _singlet(NEAR)
    lens = hl.lens
    fields = torch.tensor([[0.0, 0.0], [0.0, 0.6 * float(max(lens.fields))]], dtype=torch.float64)
    wls = [0.5, lens.primary_wavelength]
    z_xps = [hl.exit_pupil_z(w) for w in wls]
    with torch.no_grad():
        zs, err = ep.go_phase_errors(lens, fields, wls, None, lens.field_type, (z_xps, hl.doe_z()))
        for i in range(2):
            for j, wl in enumerate(wls):
                z1, e1 = ep.go_phase_error(lens, Source(tuple(fields[i].tolist()), wl, None, lens.field_type),
                                           z_xps[j], hl.doe_z())
                assert torch.equal(zs[j], z1)
                torch.testing.assert_close(err[i, j], e1, rtol=1e-9, atol=1e-15)
    assert float(err[0, 1, -1]) > ep.GO_PHASE_TOL  # the case triggers the fallback


def _near_psfs():
    """``(far, fallback, warnings)``: the PSF with the DOE far from focus and the default's near it (2 mm wide, so
    that its aperture keeps the edge's ripples)."""
    with torch.no_grad():
        far = _singlet(FAR).psf_result((0.0, 0.0), ks=32).psf[0, 0]
        near = _singlet(NEAR, size=2.0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fb = near.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    return far, fb, near, [str(w.message) for w in caught if issubclass(w.category, StopEdgeWarning)]


def _huygens(hl, ks=32):
    """The converged Huygens exit-pupil PSF (raywave.models.exit_pupil: no DOE plane, no rays to it) on the crop of
    ``hl``'s on-axis PSF."""
    from raywave.models.exit_pupil import huygens_psf

    with torch.no_grad():
        r = hl.psf_result((0.0, 0.0), ks=ks)
        ref = huygens_psf(hl.lens, (0.0, 0.0), hl.lens.primary_wavelength, ks=ks, pitch=hl.sensor_pitch,
                          center=tuple(float(c) for c in r.center[0, 0]), n_pupil="auto", max_n_pupil=512,
                          sensor_z=float(hl.sensor_z()))
    assert ref.error_estimate < 1e-6
    return ref.psf


def test_near_focus_the_fallback_gives_the_psf_of_a_plane_far_from_focus():
    """The DOE 5 mm before focus: the default warns and builds the field on an earlier plane. Against the converged
    Huygens PSF its PSF is within 1e-3 (measured 6.8e-4), like the PSF with the DOE far from focus (5.7e-4); the
    two engine PSFs agree to 8.6e-4."""
    far, fb, near, msgs = _near_psfs()
    assert any("angular spectrum" in m and "near the rays' focus" in m for m in msgs), msgs
    ref = _huygens(near)
    err_fb, err_far = float((fb - ref).abs().sum()), float((far - ref).abs().sum())
    print(f"from the Huygens PSF: fallback {err_fb:.3g}, far plane {err_far:.3g}")
    assert err_fb < 1e-3
    assert err_far < 1e-3


@pytest.mark.slow  # ~30 s: the construction on the plane near focus is the slow one
def test_near_focus_the_field_built_on_the_plane_itself_is_off(monkeypatch):
    """Without the fallback the same plane's PSF is 1.8e-2 from the converged Huygens PSF."""
    far, fb, near, _ = _near_psfs()
    monkeypatch.setattr(ep, "GO_PHASE_TOL", math.inf)  # the construction on the plane itself
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", StopEdgeWarning)
        plain = near.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    ref = _huygens(near)
    err_fb, err_plain = float((fb - ref).abs().sum()), float((plain - ref).abs().sum())
    print(f"from the Huygens PSF: fallback {err_fb:.3g}, on the plane itself {err_plain:.3g}")
    assert err_plain > 10 * err_fb


def test_the_fallback_is_differentiable():
    """The fallback's PSF carries gradients to the lens (the construction and the angular spectrum both do)."""
    hl = _singlet(NEAR, size=2.0)
    curv = hl.lens.surfaces[0].geometry.curvature
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StopEdgeWarning)
        psf = hl.psf_result((0.0, 0.0), ks=16).psf[0, 0]
    (g,) = torch.autograd.grad((psf * torch.linspace(0, 1, 16, dtype=psf.dtype)[:, None]).sum(), curv)
    assert torch.isfinite(g) and float(g.abs()) > 0


def test_a_fallback_too_large_for_its_grid_warns_and_keeps_the_plane(monkeypatch):
    """Where the beam on the earlier plane would span more than MAX_XP_SAMPLES samples the field stays on the DOE
    plane (no fallback plane), with a warning that says so and what to do; within the limit the plane is kept and
    the warning names the fallback."""
    hl = _singlet(NEAR, size=2.0)
    lens, wl = hl.lens, hl.lens.primary_wavelength
    src = Source((0.0, 0.0), wl, None, lens.field_type)
    with torch.no_grad():
        z_from, est = ep.go_fallback_plane(lens, src, hl.exit_pupil_z(wl), hl.doe_z())
    assert z_from is not None and hl.exit_pupil_z(wl) < z_from < hl.doe_z() and est > ep.GO_PHASE_TOL
    with pytest.warns(StopEdgeWarning, match="carried to it by the angular spectrum"):
        assert ep._fallback_fits(lens, src, z_from, hl.doe_z(), hl.doe.pitch, est) == z_from
    monkeypatch.setattr(ep, "MAX_XP_SAMPLES", 10)
    with pytest.warns(StopEdgeWarning, match="built on the plane itself; move the DOE towards the lens"):
        assert ep._fallback_fits(lens, src, z_from, hl.doe_z(), hl.doe.pitch, est) is None
