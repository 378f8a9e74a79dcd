"""The paper's comparison models (raywave.models: paraxial, pupil, raytrace, exit_pupil, raywave) against ground
truths they do not compute themselves (the Debye focus, the grating equation, Malus–Dupin) and against each
other where the paper says they agree or part (Table S.I, Secs. 1.4–1.6)."""

import math
import warnings

import pytest
import torch

from raywave.doe import BlankDOE, FresnelDOE, PixelDOE
from raywave.hybrid import HybridLens, PSFResult
from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens
from raywave.models.debye import debye_psf
from raywave.models.interface import MODEL_NAMES, ModelPSFResult, PSFModel, make_model, relative_l1
from raywave.models.local_grating import DiscontinuousPhaseWarning
from raywave.models.pupil import fit_zernike, zernike_basis
from raywave.surfaces.interaction import Diffraction, linear_grating_phase

LAM = 0.55
F, FNUM, DIST = 5.0, 4.0, 1.0  # ideal lens f = 5 mm at F/4, DOE 1 mm behind: 4 mm to focus, 1 mm beam
P = 1e-3
R_DOE = 0.5 * F / FNUM * (1 - DIST / F)  # beam radius on the DOE plane (0.5 mm)


def ideal_hybrid(doe=None, sensor_distance=None, sensor_pitch=1e-3, n=1100):
    lens = ideal_lens(F, f_number=FNUM, wavelengths=(LAM,), sensor_distance=sensor_distance)
    return HybridLens(lens, BlankDOE(n, P) if doe is None else doe, DIST, sensor_pitch=sensor_pitch)


def refocusing_phase(z1, n=1100):
    """A DOE that turns the wave converging to z0 = 4 mm behind the DOE into a perfect sphere converging to z1."""
    z0 = F - DIST
    c = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * P
    r2 = c[None, :] ** 2 + c[:, None] ** 2
    k = 2 * math.pi / (LAM * 1e-3)
    return k * ((torch.sqrt(r2 + z0**2) - z0) - (torch.sqrt(r2 + z1**2) - z1))


# ------------------------------------------------------------------ the common interface
def test_every_model_answers_the_same_call_with_the_engine_conventions():
    hl = ideal_hybrid(n=1100)
    fields = [(0.0, 0.0), (0.0, 2.0)]
    for name in MODEL_NAMES:
        m = make_model(name, hl, **({"n_pupil": 64} if name == "exit_pupil" else {}))
        assert isinstance(m, PSFModel) and isinstance(m, torch.nn.Module)
        r = m.psf_result(fields, [LAM], ks=16)
        assert isinstance(r, PSFResult) and isinstance(r, ModelPSFResult) and r.model == name
        assert r.psf.shape == (2, 1, 16, 16) and r.psf.dtype == torch.float64
        assert r.center.shape == (2, 1, 2) and r.energy_outside.shape == (2, 1)
        assert torch.allclose(r.psf.detach().sum((-2, -1)), torch.ones(2, 1, dtype=torch.float64), atol=1e-9)
        # the ideal lens images the 2° chief ray at f·tan θ: every model centres its crop there
        assert float(r.center[1, 0, 1].detach()) == pytest.approx(F * math.tan(math.radians(2.0)), rel=1e-6)
        assert m.psf(fields[0], LAM, ks=16).shape == (1, 1, 16, 16)
        if name != "exit_pupil":  # a near object (500 mm): every model runs, finite, normalised
            near = m.psf(fields[1], LAM, ks=16, depth=500.0).detach()
            assert bool(torch.isfinite(near).all()) and float(near.sum()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="unknown model"):
        make_model("zemax", hl)
    with pytest.raises(ValueError, match="ks"):
        make_model("paraxial", hl).psf_result((0, 0), LAM, ks=0)


# ------------------------------------------------------------------ ideal paraxial hybrid lens: known ground truth
@pytest.mark.parametrize("z1", [None, 4.5])
def test_raywave_and_paraxial_match_the_debye_focus_of_an_ideal_hybrid_lens(z1):
    """Blank DOE (truth: Debye focus of the F/4 cone) and a refocusing DOE (truth: the Debye focus of the new
    cone, NA = sin atan(0.5/z1), sensor at the new focus). Measured L1: ray-wave 7.8e-4 / 5.3e-4, paraxial
    7.7e-4 / 5.1e-4."""
    if z1 is None:
        hl, na = ideal_hybrid(), math.sin(math.atan(0.5 / FNUM))
    else:
        hl = ideal_hybrid(PixelDOE(refocusing_phase(z1), P), sensor_distance=DIST + z1)
        na = math.sin(math.atan(R_DOE / z1))
    ref = debye_psf(na, LAM, 48, 1e-3, oversample=15).psf
    errs = {}
    for name in ("raywave", "paraxial"):
        psf = make_model(name, hl).psf((0, 0), LAM, ks=48)[0, 0].detach()
        errs[name] = float(relative_l1(psf, ref))
    print(f"ideal hybrid lens (z1={z1}): relative L1 to Debye {errs}")
    assert errs["raywave"] < 1e-3 and errs["paraxial"] < 1e-3


def test_paraxial_model_is_differentiable_with_respect_to_the_doe():
    """d(peak)/d(Fresnel focal length) by autograd against central differences (used to design the EDoF DOE)."""
    doe = FresnelDOE(60.0, 700, P, wavelength=LAM)
    m = make_model("paraxial", ideal_hybrid(doe))
    peak = m.psf((0, 0), LAM, ks=12)[0, 0].max()
    (g,) = torch.autograd.grad(peak, doe.focal_length)
    h = 0.5
    with torch.no_grad():
        vals = []
        for s in (1, -1):
            doe.focal_length.add_(s * h)
            vals.append(float(m.psf((0, 0), LAM, ks=12)[0, 0].max()))
            doe.focal_length.sub_(s * h)
    fd = (vals[0] - vals[1]) / (2 * h)
    assert abs(fd) > 1e-5
    assert float(g) == pytest.approx(fd, rel=2e-3)


# ------------------------------------------------------------------ local grating ray tracing (Sec. 1.5)
def test_linear_grating_bends_rays_by_exactly_the_wavefront_tilt():
    """A grating φ = 2πx/Λ between media n1, n2: n2 sinθ2 − n1 sinθ1 = λ/Λ, and the OPL after it is constant on
    planes normal to the new direction (the wavefront tilts by exactly the angle the rays bend)."""
    period, wl = 0.01, 0.55  # 10 µm period, sin θ = 0.055 in air
    grating = Diffraction(linear_grating_phase(period))
    x = torch.linspace(-0.2, 0.2, 9, dtype=torch.float64)
    y = torch.zeros_like(x)
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    for n1, n2, theta1 in ((1.0, 1.0, 0.0), (1.0, 1.5, 10.0), (1.5, 1.0, -5.0), (1.33, 1.7, 3.0)):
        s1 = math.sin(math.radians(theta1))
        d1 = (torch.full_like(x, s1), zero, torch.full_like(x, math.cos(math.radians(theta1))))
        opl_in = n1 * x * s1  # the incoming plane wavefront through the origin
        dx, dy, dz, extra, ok = grating(x, y, *d1, zero, zero, one, torch.full_like(x, n1), torch.full_like(x, n2),
                                        torch.full_like(x, wl))
        assert bool(ok.all())
        assert torch.allclose(n2 * dx - n1 * s1, torch.full_like(x, wl * 1e-3 / period), atol=1e-15)
        assert torch.allclose(dx**2 + dy**2 + dz**2, one, atol=1e-15)
        # OPL to the plane through the origin normal to the outgoing direction: the same for every ray
        opl_out = opl_in + extra + n2 * (-(x * dx))
        assert float((opl_out - opl_out[0]).abs().max()) < 1e-15
        if n1 == n2 and theta1 == 0.0:
            assert float(dx[0]) == pytest.approx(wl * 1e-3 / period, abs=1e-15)
    # no phase: exactly Snell's law from n1 to n2 (not as if both sides were air)
    flat = Diffraction(lambda x, y, w: (torch.zeros_like(x),) * 3)
    s1 = math.sin(math.radians(20.0))
    dx, *_ = flat(x[:1], y[:1], torch.full((1,), s1, dtype=torch.float64), zero[:1],
                  torch.full((1,), math.cos(math.radians(20.0)), dtype=torch.float64), zero[:1], zero[:1], one[:1],
                  torch.ones(1, dtype=torch.float64), torch.full((1,), 1.5, dtype=torch.float64),
                  torch.full((1,), wl, dtype=torch.float64))
    assert float(dx) == pytest.approx(s1 / 1.5, abs=1e-15)
    # evanescent order: flagged, finite
    steep = Diffraction(linear_grating_phase(0.0004))  # λ/Λ = 1.4
    *d, extra, ok = steep(x, y, zero, zero, one, zero, zero, one, one, one, torch.full_like(x, wl))
    assert not bool(ok.any()) and all(bool(torch.isfinite(t).all()) for t in d)


def test_local_grating_model_shifts_the_focus_by_the_grating_equation():
    x = torch.arange(1100, dtype=torch.float64)
    ramp = torch.remainder(2 * math.pi * x / 64, 2 * math.pi)[None, :].expand(1100, 1100).clone()  # wrapped kinoform
    hl = ideal_hybrid(PixelDOE(ramp, P))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DiscontinuousPhaseWarning)  # 2π wraps are not discontinuities
        psf = make_model("raytrace", hl).psf((0, 0), LAM, ks=96)[0, 0]
    c = torch.arange(96, dtype=torch.float64) - 48
    cx = float((psf.sum(0) * c).sum())
    expected = (F - DIST) * math.tan(math.asin(LAM * 1e-3 / (64 * P))) / 1e-3
    assert cx == pytest.approx(expected, abs=0.5)  # nearest-pixel binning of a geometric point


def test_local_grating_is_right_for_a_smooth_doe_and_wrong_for_a_binary_one():
    """A smooth Fresnel lens that defocuses the ideal lens by ~10 waves (geometric blur): ray tracing and
    ray-wave agree (measured L1 0.23: Fresnel ripples the rays cannot have). The same lens fabricated as a
    binary (2-level) kinoform: the local grating model sends the light into one focus while the true field
    splits into the ±1 orders and leaks ~20 % into the zero order: measured L1 1.94, and a warning says where."""
    out = {}
    for levels in (None, 2):
        doe = FresnelDOE(22.7, 1100, P, wavelength=LAM)
        if levels:
            doe.fabricate(levels=levels, wavelength=LAM)
        hl = ideal_hybrid(doe, sensor_pitch=5e-3)
        rw = make_model("raywave", hl).psf((0, 0), LAM, ks=64)[0, 0].detach()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rt = make_model("raytrace", hl).psf_result((0, 0), LAM, ks=64)
        msgs = [str(w.message) for w in caught if issubclass(w.category, DiscontinuousPhaseWarning)]
        out[levels] = (float(relative_l1(rt.psf[0, 0], rw)), msgs, rt.info["discontinuity"][0][0])
    print(f"local grating vs ray-wave: smooth L1 {out[None][0]:.3f}, binary L1 {out[2][0]:.3f}")
    assert out[None][0] < 0.3 and not out[None][1]
    assert out[2][0] > 1.5
    assert len(out[2][1]) == 1 and "discontinuous" in out[2][1][0] and "radii" in out[2][1][0]
    rep = out[2][2]
    assert rep["fraction_on_discontinuity"] > 0.05 and rep["doe_pixels"] > 0 and rep["doe_r_max"] <= 0.8


# ------------------------------------------------------------------ exit-pupil diffraction (Sec. 1.6)
def test_exit_pupil_and_raywave_agree_on_a_clear_aperture_on_and_off_axis():
    """Measured L1: 4.1e-4 on axis and 4.8e-4 at 5° (ideal lens, a DOE plane larger than the beam). A DOE that
    clips the beam (1.1 mm square at 5°: L1 0.028) is warned about."""
    hl = ideal_hybrid(n=1400)
    fields = [(0.0, 0.0), (0.0, 5.0)]
    rw = make_model("raywave", hl).psf(fields, LAM, ks=24).detach()
    ep = make_model("exit_pupil", hl, n_pupil=192).psf(fields, LAM, ks=24)
    err = relative_l1(ep, rw).flatten().tolist()
    print(f"exit pupil vs ray-wave (clear aperture): {err}")
    assert max(err) < 1e-2
    with pytest.warns(RuntimeWarning, match="ignores the DOE aperture"):
        make_model("exit_pupil", ideal_hybrid(n=1100), n_pupil=32).psf((0.0, 5.0), LAM, ks=4)


def test_exit_pupil_model_refuses_a_doe():
    hl = ideal_hybrid(FresnelDOE(50.0, 300, P))
    with pytest.raises(ValueError, match="cannot simulate a DOE"):
        make_model("exit_pupil", hl).psf((0, 0), LAM, ks=8)


# ------------------------------------------------------------------ pupil aberration model (Sec. 1.4)
def test_zernike_fit_recovers_known_noll_coefficients():
    g = torch.linspace(-1, 1, 41, dtype=torch.float64)
    x, y = torch.meshgrid(g, g, indexing="xy")
    keep = x**2 + y**2 <= 1
    x, y = 2.0 * x[keep] + 0.3, 2.0 * y[keep] - 0.1  # a 2 mm pupil centred at (0.3, -0.1)
    c = torch.zeros(37, dtype=torch.float64)
    c[[3, 4, 7, 10, 21]] = torch.tensor([0.5, -0.2, 0.1, 0.05, -0.03], dtype=torch.float64)
    u, v = (x - 0.3) / 2.0, (y + 0.1) / 2.0
    w = zernike_basis(torch.sqrt(u * u + v * v), torch.atan2(v, u), 37) @ c
    fit = fit_zernike(x, y, w, 37, center=(0.3, -0.1), radius=2.0)
    assert torch.allclose(fit.coefficients, c, atol=1e-12) and fit.residual_rms < 1e-13


@pytest.fixture(scope="module")
def asphere_compare():
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    hl = HybridLens(lens, BlankDOE(3000, 1e-3), 0.3, sensor_pitch=1e-3)
    fields = [(0.0, 0.0), (0.0, 14.0)]
    rw = make_model("raywave", hl, rays=48).psf(fields, 0.53, ks=40).detach()
    pu = make_model("pupil", hl).psf_result(fields, 0.53, ks=40)
    return rw, pu


def test_pupil_model_agrees_on_axis_and_departs_off_axis(asphere_compare):
    """Bundled asphere, 37 Noll terms: fit residual 2e-7 λ RMS on axis, 6e-6 λ at 14°; L1 to ray-wave 0.0075 on
    axis, 0.106 at 14° (a circular, uniform pupil instead of the real footprint and ray density)."""
    rw, pu = asphere_compare
    err = relative_l1(pu.psf, rw).flatten().tolist()
    res = pu.info["residual_rms_waves"]
    print(f"pupil model vs ray-wave: L1 {err}, Zernike residual (waves RMS) {res.flatten().tolist()}")
    assert res.shape == (2, 1) and bool((res < 1e-3).all())
    assert pu.info["zernike_waves"].shape == (2, 1, 37)
    assert err[0] < 0.015
    assert err[1] > 0.05 and err[1] > 5 * err[0]


def test_diffraction_is_one_more_interaction_of_a_lens_surface():
    """A plane grating surface behind an ideal lens, traced by the ordinary tracer: the chief ray leaves at
    sin θ = λ/Λ and the focus moves by d·tan θ (the wavelength reaches the interaction with the bundle's shape)."""
    from raywave.lens.lens import Lens
    from raywave.lens.sources import chief_ray
    from raywave.materials import Air
    from raywave.surfaces.aperture import CircularAperture
    from raywave.surfaces.geometry import Plane
    from raywave.surfaces.interaction import IdealLens
    from raywave.surfaces.surface import Surface

    period, d = 0.02, 3.0
    lens = Lens([Surface(Plane(), Air(), F - d, aperture=CircularAperture(0.6), interaction=IdealLens(F), is_stop=True),
                 Surface(Plane(), Air(), d, interaction=Diffraction(linear_grating_phase(period)))],
                wavelengths=(0.45, LAM), primary=1)
    assert float(lens.paraxial(LAM).efl) == pytest.approx(F)  # the grating adds no paraxial power
    for wl in (0.45, LAM):
        out = lens.trace_to_image(chief_ray(lens, (0.0, 0.0), wl))
        s = wl * 1e-3 / period
        out = out.replace(o=out.o.detach(), d=out.d.detach())
        assert float(out.d[..., 0].reshape(())) == pytest.approx(s, abs=1e-14)
        assert float(out.o[..., 0].reshape(())) == pytest.approx(d * math.tan(math.asin(s)), abs=1e-12)
    # a lens file cannot hold a ray-tracing phase: writing one is an error, never a silent loss of the phase
    from raywave.lens.build import lens_to_spec

    with pytest.raises(ValueError, match="diffraction.*interaction has no lens-file form"):
        lens_to_spec(lens)


def test_paraxial_thin_lens_plane_choices():
    """'principal': the ideal lens's own plane (a sensor 40 µm behind the focus stays defocused); 'sensor': the thin
    lens moves so that the sensor is in focus (the PSF equals the in-focus one)."""
    from raywave.models.paraxial import ParaxialModel

    defocused = ideal_hybrid(sensor_distance=F + 0.04)
    p_principal = ParaxialModel(defocused, plane="principal")
    p_sensor = ParaxialModel(defocused, plane="sensor")
    assert p_principal.thin_lens()[0] == pytest.approx(0.0, abs=1e-12)
    assert p_sensor.thin_lens()[0] == pytest.approx(0.04, abs=1e-12)
    focus = make_model("paraxial", ideal_hybrid()).psf((0, 0), LAM, ks=16)[0, 0]
    assert float(relative_l1(p_sensor.psf((0, 0), LAM, ks=16)[0, 0], focus)) < 2e-3  # DOE 40 µm closer: ~same
    assert float(relative_l1(p_principal.psf((0, 0), LAM, ks=16)[0, 0], focus)) > 0.1
    with pytest.raises(ValueError, match="plane"):
        ParaxialModel(defocused, plane="front")
