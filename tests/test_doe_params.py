"""DOE parametrisations, dispersion (height maps), kinoform wrapping and quantisation, specs and files, BINARY_2
in .zmx files, and the diffraction efficiency of binary and 16-level gratings against scalar theory."""

import math

import numpy as np
import pytest
import torch

from raywave.doe import (Binary2DOE, BlankDOE, CubicDOE, FresnelDOE, GratingDOE, PixelDOE, RadialDOE, SumDOE,
                         ZernikeDOE, detuning, doe_from_phase_model, load_doe, noll_to_nm, period_efficiency,
                         save_doe, staircase_efficiency)
from raywave.hybrid import HybridLens
from raywave.lens.build import ideal_lens
from raywave.materials import GlassNotFoundError, get_material

SHAPE, PITCH = (7, 9), 0.01


def n_fs(w):
    return float(get_material("FUSED_SILICA").n(torch.tensor(w, dtype=torch.float64)))


def xy(doe):
    x, y = doe.pixel_xy()
    return x[None, :].expand(doe.shape), y[:, None].expand(doe.shape)


# ------------------------------------------------------------------ each parametrisation against its formula
def test_binary2_is_opticstudio_even_polynomial_times_the_order():
    doe = Binary2DOE([-100.0, 5.0, 0.3], norm_radius=0.02, shape=SHAPE, pitch=PITCH, order=2)
    x, y = xy(doe)
    rho2 = (x**2 + y**2) / 0.02**2
    want = 2 * (-100.0 * rho2 + 5.0 * rho2**2 + 0.3 * rho2**3)
    assert torch.allclose(doe.phase(0.55), want, rtol=1e-13, atol=1e-12)
    assert torch.equal(doe.phase(0.45), doe.phase(0.7))  # OpticStudio: the same phase (rad) at every λ
    assert float(doe.phase(0.55)[3, 4].detach()) == 0.0  # the centre pixel is on the axis


def test_zernike_noll_order_and_polynomials():
    assert [noll_to_nm(j) for j in range(1, 12)] == [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1),
                                                     (3, 1), (3, -3), (3, 3), (4, 0)]
    R = 0.04
    for j, f in [(2, lambda r, t: 2 * r * torch.cos(t)), (3, lambda r, t: 2 * r * torch.sin(t)),
                 (4, lambda r, t: math.sqrt(3) * (2 * r**2 - 1)), (5, lambda r, t: math.sqrt(6) * r**2 * torch.sin(2 * t)),
                 (6, lambda r, t: math.sqrt(6) * r**2 * torch.cos(2 * t)),
                 (7, lambda r, t: math.sqrt(8) * (3 * r**3 - 2 * r) * torch.sin(t)),
                 (11, lambda r, t: math.sqrt(5) * (6 * r**4 - 6 * r**2 + 1)),
                 (12, lambda r, t: math.sqrt(10) * (4 * r**4 - 3 * r**2) * torch.cos(2 * t))]:
        c = [0.0] * j
        c[-1] = 0.7
        doe = ZernikeDOE(c, SHAPE, PITCH, radius=R)
        x, y = xy(doe)
        want = 0.7 * f(torch.sqrt(x**2 + y**2) / R, torch.atan2(y, x))
        assert torch.allclose(doe.phase(0.55), want, atol=1e-12), j
    # Noll normalisation: RMS 1 over the unit disk (fine grid)
    z = ZernikeDOE([0, 0, 0, 0, 0, 0, 1.0], 801, 1.0 / 400, radius=1.0).phase(0.55).detach()
    x, y = xy(BlankDOE(801, 1.0 / 400))
    inside = x**2 + y**2 < 1
    assert float(z[inside].pow(2).mean().sqrt()) == pytest.approx(1.0, rel=2e-3)


def test_fresnel_grating_cubic_and_radial_profiles():
    lam0 = 0.55
    f = FresnelDOE(25.0, SHAPE, PITCH, wavelength=lam0)
    x, y = xy(f)
    r2 = x**2 + y**2
    assert torch.allclose(f.phase(lam0), -(2 * math.pi / (lam0 * 1e-3)) * (torch.sqrt(r2 + 25.0**2) - 25.0),
                          rtol=1e-9, atol=1e-9)
    fn = FresnelDOE(-25.0, SHAPE, PITCH, wavelength=lam0)  # diverging: the opposite phase
    assert torch.allclose(fn.phase(lam0), -f.phase(lam0), rtol=1e-12)
    g = GratingDOE(0.05, SHAPE, PITCH, angle=30.0)
    t = math.radians(30.0)
    assert torch.allclose(g.phase(0.5), 2 * math.pi * (x * math.cos(t) + y * math.sin(t)) / 0.05, atol=1e-12)
    c = CubicDOE(3.0, SHAPE, PITCH, radius=0.04)
    assert torch.allclose(c.phase(0.5), 3.0 * ((x / 0.04) ** 3 + (y / 0.04) ** 3), atol=1e-12)
    rd = RadialDOE([0.0, 1.0, 4.0], SHAPE, PITCH, radius=0.04)  # samples at r = 0, 0.02, 0.04
    r = torch.sqrt(r2)
    want = torch.where(r < 0.02, r / 0.02, 1.0 + 3.0 * (r - 0.02) / 0.02).clamp(max=4.0)
    assert torch.allclose(rd.phase(0.5), want, atol=1e-12)


def test_parameters_are_differentiable():
    for doe, name in [(Binary2DOE([1.0, 2.0], 0.03, SHAPE, PITCH), "coefficients"),
                      (ZernikeDOE([0, 1.0, 0.5, 0.2], SHAPE, PITCH), "coefficients"),
                      (FresnelDOE(10.0, SHAPE, PITCH), "focal_length"), (GratingDOE(0.05, SHAPE, PITCH), "period"),
                      (CubicDOE(2.0, SHAPE, PITCH), "alpha"), (RadialDOE([0, 1.0, 2.0], SHAPE, PITCH), "profile")]:
        p = getattr(doe, name)
        assert isinstance(p, torch.nn.Parameter) and p.dtype == torch.float64
        doe.phase(0.55).pow(2).sum().backward()
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().sum()) > 0, name


# ------------------------------------------------------------------ dispersion and height maps
def test_height_map_phase_follows_the_index_of_fused_silica():
    ph0 = torch.linspace(0, 2 * math.pi, 63, dtype=torch.float64).reshape(7, 9)
    doe = PixelDOE(ph0, PITCH, design_wavelength=0.55, material="FUSED_SILICA")
    h = doe.height_pixels()  # µm
    assert torch.allclose(h, ph0 * 0.55 / (2 * math.pi * (n_fs(0.55) - 1)), rtol=1e-14)
    assert doe.height_2pi() == pytest.approx(0.55 / (n_fs(0.55) - 1)) and doe.height_2pi() == pytest.approx(1.196, abs=1e-3)
    for w in (0.45, 0.70):
        assert torch.allclose(doe.phase(w), 2 * math.pi * (n_fs(w) - 1) * h / w, rtol=1e-13)
    # back from the height map
    again = PixelDOE.from_height(h.detach(), PITCH, "FUSED_SILICA", 0.55)
    assert torch.allclose(again.phase(0.45), doe.phase(0.45), rtol=1e-13)
    # the dispersion-free models: "none" (same phase) and "air" (fixed optical path)
    assert torch.equal(PixelDOE(ph0, PITCH).phase(0.45), ph0)
    assert torch.allclose(PixelDOE(ph0, PITCH, design_wavelength=0.55).phase(0.7), ph0 * 0.55 / 0.7)


def test_fabricate_keeps_the_phase_at_the_new_design_wavelength():
    doe = PixelDOE(torch.full((2, 2), 1.0), PITCH, design_wavelength=0.5)  # air path: 0.5/0.55 at 0.55
    doe.fabricate(levels=None, wavelength=0.55, material="FUSED_SILICA", wrap=False)
    assert float(doe.phase(0.55)[0, 0]) == pytest.approx(0.5 / 0.55, rel=1e-14)
    assert float(doe.phase(0.45)[0, 0]) == pytest.approx(0.5 / 0.55 * detuning("FUSED_SILICA", 0.45, 0.55), rel=1e-13)


# ------------------------------------------------------------------ wrapping and quantisation
def test_levels_wrap_quantise_and_fold_level_L_to_zero():
    L = 16
    step = 2 * math.pi / L
    vals = torch.tensor([[0.0, 0.49 * step, 0.51 * step, 3 * step, -0.2 * step, 2 * math.pi - 0.4 * step,
                          2 * math.pi - 0.6 * step, 7 * math.pi + 0.1, -13.0]], dtype=torch.float64)
    doe = PixelDOE(vals, PITCH)
    lv = doe.levels(L, 0.55)
    assert lv.dtype == torch.long and lv.shape == (1, 9)
    assert lv[0, :7].tolist() == [0, 0, 1, 3, 0, 0, L - 1]  # 2π − 0.4 step rounds to level L: folded to 0
    assert int(lv.min()) >= 0 and int(lv.max()) < L
    w = torch.remainder(vals[0, 7:], 2 * math.pi)
    assert lv[0, 7:].tolist() == torch.remainder(torch.round(w / step), L).long().tolist()
    doe.fabricate(levels=L, wavelength=0.55)
    assert torch.allclose(doe.phase(0.55), lv.double() * step, atol=1e-15)  # forward: the fabricated profile
    # a window of the level map; levels of random maps stay in [0, L)
    big = PixelDOE(torch.randn(40, 50, dtype=torch.float64) * 30, PITCH)
    full = big.levels(8)
    assert torch.equal(big.levels(8, window=(3, 5, 10, 20)), full[3:13, 5:25])
    assert int(full.min()) >= 0 and int(full.max()) <= 7 and full.shape == (40, 50)


def test_straight_through_gradient_equals_the_unquantised_gradient():
    torch.manual_seed(0)
    c = torch.tensor([-40.0, 7.0, 1.5], dtype=torch.float64)
    weights = torch.randn(SHAPE, dtype=torch.float64)
    grads = []
    for levels in (None, 16, 2):
        doe = Binary2DOE(c, 0.05, SHAPE, PITCH, material="FUSED_SILICA")
        if levels:
            doe.fabricate(levels=levels)
        (doe.phase(0.48) * weights).sum().backward()
        grads.append(doe.coefficients.grad.clone())
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[0], grads[2])
    q = Binary2DOE(c, 0.05, SHAPE, PITCH).fabricate(levels=4)
    assert set(torch.unique(torch.round(q.phase(0.55).detach() / (math.pi / 2))).tolist()) <= {0.0, 1.0, 2.0, 3.0}


def test_bad_input_is_a_clear_error():
    doe = GratingDOE(0.05, SHAPE, PITCH)
    for bad in (0, -4, 1):
        with pytest.raises(ValueError, match="levels >= 2"):
            doe.fabricate(levels=bad)
    with pytest.raises(ValueError, match="integer number of phase levels"):
        doe.fabricate(levels=2.5)
    with pytest.raises(ValueError, match="integer number of phase levels"):
        doe.levels("16")
    with pytest.raises(ValueError, match="L must be an integer number of phase levels >= 2"):
        doe.levels(0)
    with pytest.raises(GlassNotFoundError, match="NOT_A_GLASS"):
        GratingDOE(0.05, SHAPE, PITCH, material="NOT_A_GLASS")
    with pytest.raises(GlassNotFoundError):
        doe.fabricate(material="NOT_A_GLASS")
    with pytest.raises(ValueError, match="normalisation radius must be > 0"):
        Binary2DOE([1.0], -2.0, SHAPE, PITCH)
    with pytest.raises(ValueError, match="focal length"):
        FresnelDOE(0.0, SHAPE, PITCH)
    with pytest.raises(ValueError, match="Noll index"):
        noll_to_nm(0)
    with pytest.raises(ValueError, match="wavelength in µm"):
        doe.levels(16, wavelength0=550.0)
    with pytest.raises(ValueError, match="share the grid"):
        SumDOE(doe, CubicDOE(1.0, (7, 8), PITCH))
    with pytest.raises(ValueError, match="different dispersion models"):
        SumDOE(GratingDOE(0.05, SHAPE, PITCH), CubicDOE(1.0, SHAPE, PITCH, material="FUSED_SILICA"))


# ------------------------------------------------------------------ sums, specs and files
def test_sum_of_does_adds_phases_and_heights():
    a = GratingDOE(0.05, SHAPE, PITCH, material="FUSED_SILICA")
    b = CubicDOE(2.0, SHAPE, PITCH, material="FUSED_SILICA")
    s = a + b
    for w in (0.45, 0.55, 0.7):
        assert torch.allclose(s.phase(w), a.phase(w) + b.phase(w), rtol=1e-13, atol=1e-13)
    assert torch.allclose(s.height_pixels(), a.height_pixels() + b.height_pixels(), rtol=1e-13, atol=1e-15)
    s.fabricate(levels=8)  # the total is quantised
    assert torch.allclose(s.phase(0.55), s.levels(8).double() * (2 * math.pi / 8), atol=1e-14)
    assert len(list(s.parameters())) == 3  # the grating's period and angle, the cubic's alpha


def test_save_and_load_round_trip(tmp_path):
    torch.manual_seed(1)
    does = [PixelDOE(torch.randn(SHAPE, dtype=torch.float64), PITCH, design_wavelength=0.6, aperture="circle"),
            Binary2DOE([-3.0, 1.0], 0.04, SHAPE, PITCH, order=-1).fabricate(16, 0.55, "FUSED_SILICA"),
            ZernikeDOE(torch.randn(10), SHAPE, PITCH, radius=0.05), FresnelDOE(12.0, SHAPE, PITCH, wavelength=0.6),
            RadialDOE([0.0, 2.0, 1.0, 5.0], SHAPE, PITCH), GratingDOE(0.03, SHAPE, PITCH, angle=-20.0).fabricate(2),
            GratingDOE(0.03, SHAPE, PITCH) + CubicDOE(1.5, SHAPE, PITCH), BlankDOE(SHAPE, PITCH)]
    for i, doe in enumerate(does):
        path = tmp_path / f"doe{i}.pt"
        save_doe(doe, path)
        back = load_doe(path)
        assert type(back) is type(doe) and back.to_spec() == doe.to_spec()
        for w in (0.45, 0.55):
            assert torch.equal(back.phase(w), doe.phase(w)), type(doe).__name__
    with pytest.raises(ValueError, match="not a raywave DOE file"):
        torch.save({"x": 1}, tmp_path / "other.pt")
        load_doe(tmp_path / "other.pt")


def test_lens_file_phase_models_build_their_does():
    shape, pitch = (9, 9), 0.01
    cases = [({"type": "binary_2", "order": 1.0, "norm_radius": 0.04, "coefficients": [-5.0, 1.0]}, Binary2DOE),
             ({"type": "zernike", "coefficients": [0.0, 1.0, 2.0], "radius": 0.04}, ZernikeDOE),
             ({"type": "fresnel", "focal_length": 20.0}, FresnelDOE), ({"type": "grating", "period": 0.03}, GratingDOE),
             ({"type": "cubic", "alpha": 3.0}, CubicDOE), ({"type": "radial", "radius": 0.04, "profile": [0, 1, 3]},
                                                          RadialDOE),
             ({"type": "sum", "terms": [{"type": "cubic", "alpha": 3.0}, {"type": "grating", "period": 0.03}]}, SumDOE)]
    for model, cls in cases:
        doe = doe_from_phase_model(model, shape, pitch, "circle")
        assert type(doe) is cls and doe.dispersion == "none" and doe.aperture == "circle"
        spec = doe.model_spec()
        assert spec["type"] == model["type"]
        for k, v in model.items():
            if k not in ("type", "terms"):
                assert spec[k] == (v if isinstance(v, list) else float(v)), (model["type"], k)
    fab = doe_from_phase_model(cases[0][0], shape, pitch, material="FUSED_SILICA", levels=16, design_wavelength=0.55)
    assert fab.dispersion == "material" and fab.quant_levels == 16 and fab.wrap


# ------------------------------------------------------------------ .zmx BINARY_2 round trip
def test_binary2_zmx_read_write_read_is_exact(tmp_path):
    import warnings

    from test_cli_psf import TINY_ZMX

    from raywave.io import read_lens_spec
    from raywave.io.zmx import write_zmx

    coeffs = [-123.456789012345, 5.0e-3, 1.0 / 3.0, -2.5e-7]
    text = TINY_ZMX.replace('  XDAT 1 2 0 0 1 0 0 ""', '  XDAT 1 4 0 0 1 0 0 ""').replace(
        '  XDAT 3 -100.0 0 0 1 0 0 ""\n  XDAT 4 5.0 0 0 1 0 0 ""\n',
        "".join(f'  XDAT {3 + i} {c!r} 0 0 1 0 0 ""\n' for i, c in enumerate(coeffs))).replace("PARM 0 1", "PARM 0 -2")
    src = tmp_path / "in.zmx"
    src.write_text(text)
    spec = read_lens_spec(src)
    assert spec["doe"]["phase_model"] == {"type": "binary_2", "order": -2.0, "norm_radius": 2.0, "coefficients": coeffs}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_zmx(spec, tmp_path / "out.zmx")
    again = read_lens_spec(tmp_path / "out.zmx")
    assert again == spec and again["doe"]["phase_model"]["coefficients"] == coeffs
    # a DOE designed here -> its OpticStudio description -> the same phase
    doe = Binary2DOE(coeffs, 2.0, (5, 5), 0.5, order=-2)
    m = doe.model_spec()
    assert m == spec["doe"]["phase_model"]
    assert torch.equal(doe_from_phase_model(m, (5, 5), 0.5).phase(0.55), doe.phase(0.55))


# ------------------------------------------------------------------ efficiency against scalar theory
def test_detuned_staircase_formula_matches_a_dft_of_one_period():
    for L in (2, 4, 16):
        for alpha in (1.0, 1.237, 0.83):
            per = 512 * L  # finely sampled continuous staircase
            k = np.arange(per) // 512
            for m in (-1, 0, 1, 2, 3):
                assert period_efficiency(2 * np.pi * k * alpha / L, m) == pytest.approx(
                    staircase_efficiency(m, L, alpha), abs=2e-6)
    assert staircase_efficiency(1, 16) == pytest.approx((math.sin(math.pi / 16) / (math.pi / 16)) ** 2)
    assert staircase_efficiency(1, 2) == pytest.approx(4 / math.pi**2)


F, FNUM, DIST, P, N, PERIOD = 5.0, 4.0, 1.0, 1e-3, 1600, 64e-3
ORDERS = list(range(-3, 4))


def _x_profile(doe, wl, pitch, ks):
    # the Fresnel edge step for the blank DOE too: the default ("adaptive", issue 47) cuts a blank DOE's edge on the
    # DOE plane (exact for this spherical wave), and the orders of the grating are copies of the beam its own
    # construction (the Fresnel step) forms: the unmixing needs the same edge model on both (1.3e-3 apart otherwise)
    hl = HybridLens(ideal_lens(F, f_number=FNUM, wavelengths=(wl,)), doe, DIST, sensor_pitch=pitch,
                    edge_step="fresnel")
    res = hl.psf_result((0, 0), wl, ks=ks, rays=48)
    return res.psf[0, 0].detach().sum(0) * (1 - float(res.energy_outside[0, 0].detach()))


@pytest.fixture(scope="module")
def order_strips():
    """Per wavelength: the sensor pitch that puts the orders K (odd) pixels apart, and the blank PSF's energy in
    K-pixel strips at whole multiples of K (the crosstalk of one order into its neighbours' strips)."""
    out = {}
    for wl in (0.55, 0.45):
        dx = (F - DIST) * math.tan(math.asin(wl * 1e-3 / PERIOD))
        K = 2 * round((dx / 1e-3 - 1) / 2) + 1
        b = _x_profile(BlankDOE(N, P), wl, dx / K, 13 * K)
        c = (13 * K) // 2
        strips = {j: float(b[c + j * K - K // 2: c + j * K + K // 2 + 1].sum()) for j in range(-6, 7)}
        out[wl] = (K, dx / K, torch.tensor([[strips[k - m] for m in ORDERS] for k in ORDERS], dtype=torch.float64))
    return out


@pytest.mark.parametrize("levels", [2, 16])
def test_quantised_grating_efficiency_at_and_away_from_the_design_wavelength(levels, order_strips):
    """A fused-silica grating quantised at 0.55 µm; at 0.45 µm its steps are α = 1.237 times too deep. The strip
    energies of orders −3..3 are unmixed with the blank PSF's crosstalk; each order within 0.1 % of
    η_m = sinc²(m/L)·[sin π(α−m) / (L sin(π(α−m)/L))]²."""
    doe = GratingDOE(PERIOD, N, P).fabricate(levels, 0.55, "FUSED_SILICA")
    for wl in (0.55, 0.45):
        K, pitch, W = order_strips[wl]
        g = _x_profile(doe, wl, pitch, 7 * K)
        c = (7 * K) // 2
        S = torch.tensor([float(g[c + k * K - K // 2: c + k * K + K // 2 + 1].sum()) for k in ORDERS],
                         dtype=torch.float64)
        eta = dict(zip(ORDERS, torch.linalg.solve(W, S).tolist()))
        alpha = detuning("FUSED_SILICA", wl, 0.55)
        for m in (-1, 0, 1, 2):
            assert eta[m] == pytest.approx(staircase_efficiency(m, levels, alpha), abs=1e-3), (levels, wl, m)


# ------------------------------------------------------------------ lens files and the CLI
def test_json_doe_section_with_phase_model_material_and_levels(tmp_path):
    import json

    from raywave.assembly.build import load_hybrid
    from raywave.io import LensFileError, read_json_spec, write_json_spec
    from raywave.lens.build import bundled_lens_path

    spec = read_json_spec(bundled_lens_path("hybrid_asphere"))
    spec["doe"] = dict(spec["doe"], phase_model={"type": "fresnel", "focal_length": 50.0}, material="FUSED_SILICA",
                       levels=8, design_wavelength=0.55)
    write_json_spec(spec, tmp_path / "h.json")
    hl = load_hybrid(tmp_path / "h.json")
    assert type(hl.doe) is FresnelDOE and hl.doe.quant_levels == 8 and hl.doe.material_name == "FUSED_SILICA"
    assert hl.doe_info["phase_model"] == "fresnel" and hl.doe_info["levels"] == 8
    bad = dict(spec)
    bad["doe"] = dict(spec["doe"], phase_model={"type": "fresnell", "focal_length": 50.0}, levels=1)
    (tmp_path / "bad.json").write_text(json.dumps(bad, indent=1))
    with pytest.raises(LensFileError, match="did you mean 'fresnel'") as e:
        read_json_spec(tmp_path / "bad.json")
    assert "doe.levels: must be an integer number of phase levels >= 2" in str(e.value)


def test_cli_psf_fabricates_the_doe_on_the_fly(tmp_path, capsys):
    import json

    from test_cli_psf import FAST, TINY_ZMX

    from raywave.cli.main import main

    path = tmp_path / "tiny.zmx"
    path.write_text(TINY_ZMX)
    base = ["psf", str(path), "--doe-pitch", "0.002", "--json"] + FAST
    assert main(base + ["--doe-levels", "16", "--doe-wavelength", "0.55", "--doe-material", "FUSED_SILICA"]) == 0
    d = json.loads(capsys.readouterr().out)["doe"]
    assert d["levels"] == 16 and d["material"] == "FUSED_SILICA" and d["phase_model"] == "binary_2"
    assert d["dispersion"] == "material" and d["design_wavelength_um"] == 0.55
    for args, msg in [(["--doe-levels", "1"], "--doe-levels: must be >= 2"),
                      (["--doe-levels", "2.5"], "--doe-levels: '2.5' is not an integer"),
                      (["--doe-material", "NOT_A_GLASS"], "unknown glass 'NOT_A_GLASS'"),
                      (["--doe-wavelength", "550"], "not a plausible wavelength")]:
        assert main(base + args) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err, (args, err)
