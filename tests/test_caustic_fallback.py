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
from pathlib import Path

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


DOUBLE_GAUSS = str(Path(__file__).parent / "data" / "zmx" / "double_gauss_ohara_cdgm_hoya.zmx")


def _double_gauss(**kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_hybrid(DOUBLE_GAUSS, fields=[[0.0, 0.0]], field_type="angle", **kw)


def test_the_default_plane_of_a_blank_doe_needs_no_fallback():
    """A lens file without a DOE (assembly.build.go_field_distance): the f/3 double Gauss on axis, whose beam fit
    puts the plane where the edge's Fresnel step would take the fallback (go_phase_error above GO_PHASE_TOL), gets
    the plane the fallback would build on: the error there within the tolerance for every source, before the
    caustic, the rule and the error it left reported. The DOE-plane edge (no fallback) keeps the beam fit's plane."""
    hl, doe_edge = _double_gauss(), _double_gauss(stop_edge="doe")
    info, old = hl.doe_info, doe_edge.doe_info
    assert old["distance_rule"] in ("beam_fit", "before_caustic")
    assert info["distance_rule"] == "go_field" and info["go_phase_error"] > ep.GO_PHASE_TOL
    assert info["distance"] < old["distance"] < info["caustic_distance"]
    lens = hl.lens

    def error(wl, z):
        with torch.no_grad():
            return float(ep.go_phase_error(lens, Source((0.0, 0.0), wl, None, "angle"), hl.exit_pupil_z(wl), z)[1][-1])

    assert max(error(wl, hl.doe_z()) for wl in lens.wavelengths) <= ep.GO_PHASE_TOL
    # the beam fit's plane: every wavelength over it (0.49 / 0.59 / 0.66 µm: 8.9e-5, 3.6e-4, 8.0e-4 rad), the
    # largest the one reported (the paraxial exit pupil there, the engine's real-ray one here)
    before = [error(wl, doe_edge.doe_z()) for wl in lens.wavelengths]
    assert max(before) == pytest.approx(info["go_phase_error"], rel=1e-3)
    # a lens whose default plane is far from focus keeps it (the bundled singlet, half way)
    assert load_hybrid("singlet").doe_info["distance_rule"] == "half_way"


def test_a_fallback_plane_inside_the_lens_keeps_the_default_plane():
    """The Zeiss Hologon 15 mm f/8 (4.5 mm from the last vertex to the sensor): its fallback would build the field
    on a virtual plane before the last vertex, where no DOE can sit, so the default plane stays half way (the
    engine's fallback then builds it there, as before) instead of a refused distance."""
    path = Path(__file__).parent / "data" / "opticsdatabase" / "Zeiss Hologon f8 15mm.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(path, fields=[[0.0, 0.0]], field_type="angle")
    info = hl.doe_info
    assert info["distance_rule"] == "half_way"
    assert 0 < info["distance"] < float(hl.lens.surfaces[-1].thickness.detach())


@pytest.mark.slow  # ~1 min: two double-Gauss PSFs, one through the fallback
def test_the_moved_default_plane_gives_the_fallbacks_psf_without_its_warning():
    """The double Gauss on axis: the PSF on the moved default plane equals the one on the beam fit's plane through
    the fallback (the same construction plane up to the fallback's plane grid; measured 4.1e-5 rel L1) and warns
    no StopEdgeWarning; the fallback's does."""
    hl, doe_edge = _double_gauss(), _double_gauss(stop_edge="doe")
    near = hl.with_doe(doe_edge.doe, doe_distance=doe_edge.doe_info["distance"])
    with torch.no_grad(), warnings.catch_warnings(record=True) as moved:
        warnings.simplefilter("always")
        psf = hl.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    with torch.no_grad(), warnings.catch_warnings(record=True) as fell:
        warnings.simplefilter("always")
        ref = near.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    assert not [w for w in moved if issubclass(w.category, StopEdgeWarning)]
    assert [w for w in fell if issubclass(w.category, StopEdgeWarning) and "angular spectrum" in str(w.message)]
    err = float((psf - ref).abs().sum())
    print(f"moved plane vs fallback: {err:.3g}")
    assert err < 1e-4


def test_the_fallback_planes_after_the_first_are_the_finite_ones_below_the_doe_planes_error_least_first():
    """Issue 47, class B (h47f): where the plane within GO_FALLBACK_FRACTION of the tolerance does not fit, the
    planes tried next are those nearer the DOE plane whose error is finite (no band fold) and below the DOE plane's
    own, the least error first (ties: the nearer the DOE plane first)."""
    zs = torch.linspace(0.0, 10.0, 11, dtype=torch.float64)
    err = torch.tensor([0, 1e-5, 4e-5, 3e-4, 2e-4, 2e-4, math.inf, 5e-4, math.inf, 9e-4, math.inf],
                       dtype=torch.float64)
    z_from, est, others = ep._fallback_planes(None, None, -1.0, 10.0, (zs, err))
    assert z_from == 2.0 and math.isinf(est)
    assert [z for z, _ in others] == [3.0, 4.0, 5.0, 7.0, 9.0]
    err[-1] = 4e-4  # a finite error on the DOE plane: only the planes below it
    z_from, est, others = ep._fallback_planes(None, None, -1.0, 10.0, (zs, err))
    assert z_from == 2.0 and est == 4e-4 and [z for z, _ in others] == [3.0, 4.0, 5.0]
    assert ep.go_fallback_plane(None, None, -1.0, 10.0, (zs, err)) == (2.0, 4e-4)


def test_a_fallback_too_large_takes_the_farthest_plane_that_fits(monkeypatch):
    """The singlet 5 mm before focus: with MAX_XP_SAMPLES just below the beam on the fallback's plane (7.6 mm
    before the DOE plane, 322 samples) the field is built on the next plane (6.0 mm before it, 280 samples, its
    geometric-optics error 5.3e-5 rad) with a warning that names it; against the converged Huygens PSF 6.8e-4
    (the fallback's own plane 4.8e-4, the plane itself 1.8e-2: the slow test above)."""
    hl = _singlet(NEAR, size=2.0)
    lens, wl = hl.lens, hl.lens.primary_wavelength
    src = Source((0.0, 0.0), wl, None, lens.field_type)
    with torch.no_grad():
        z_from, est, others = ep._fallback_planes(lens, src, hl.exit_pupil_z(wl), hl.doe_z())
        side = ep._plane_side(lens, src, z_from, hl.doe.pitch)[0]
    z_next = others[0][0]
    assert z_from < z_next < hl.doe_z() and others[0][1] < est
    monkeypatch.setattr(ep, "MAX_XP_SAMPLES", math.floor(side) - 1)
    with pytest.warns(StopEdgeWarning, match="where the geometric-optics field is off by"):
        assert ep._fallback_fits(lens, src, z_from, hl.doe_z(), hl.doe.pitch, est, others) == z_next
    with torch.no_grad(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        psf = hl.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    assert any(f"built {hl.doe_z() - z_next:.3g} mm before it" in str(w.message) for w in caught)
    err = float((psf - _huygens(hl)).abs().sum())
    print(f"from the Huygens PSF: the next plane {err:.3g}")
    assert err < 1e-3


def test_where_no_plane_fits_the_plain_carry_the_scaled_carry_builds_on_the_fallbacks_plane(monkeypatch):
    """The singlet 5 mm before focus with MAX_XP_SAMPLES 200 and no other plane to try: the fallback's plane (7.6 mm
    before the DOE plane, 322 samples a side at the DOE pitch) is built relative to the sphere converging on the
    chief ray's sensor point on a lattice 2.53× the DOE pitch (128 samples) and carried by the scaled angular
    spectrum (exit_pupil.scaled_carry; tests/test_scaled_carry.py): 7.8e-4 from the converged Huygens PSF (the plain
    carry from the same plane 4.8e-4, the plane itself 1.8e-2)."""
    hl = _singlet(NEAR, size=2.0)
    planes = ep._fallback_planes
    monkeypatch.setattr(ep, "_fallback_planes", lambda *a, **k: planes(*a, **k)[:2] + ((),))
    monkeypatch.setattr(ep, "MAX_XP_SAMPLES", 200)
    with torch.no_grad(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        psf = hl.psf_result((0.0, 0.0), ks=32).psf[0, 0]
    msgs = [str(w.message) for w in caught if issubclass(w.category, StopEdgeWarning)]
    assert any("scaled angular spectrum" in m and "128 samples a side" in m for m in msgs), msgs
    err = float((psf - _huygens(hl)).abs().sum())
    print(f"from the Huygens PSF: the scaled carry {err:.3g}")
    assert err < 1e-3
