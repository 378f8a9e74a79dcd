"""DeepLens hybrid lens files (``HybridLens.write_lens_json``: refractive ``surfaces`` + a top-level ``"DOE"``):
each DOE type is imported into raywave's ``doe`` section and built by ``load_hybrid``; the grid, the position and
the phase are checked against DeepLens's own formulas (github.com/singer-yang/DeepLens,
``deeplens/optics/diffractive_surface/*.py`` and the legacy ``surfaces_diffractive.DOE``)."""

import json
import math

import numpy as np
import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.io import LensFileError, LensFileWarning, read_deeplens, read_hybrid_spec
from raywave.materials import get_material

RES, PS = 32, 0.01  # DeepLens res (pixels) and fab_ps (mm): a 0.32 mm DOE
LAST_T = 3.0  # the last thickness (to the sensor)


def lens(doe: dict) -> dict:
    """A DeepLens singlet (d_next layout, as HybridLens.write_lens_json) with the DOE ``doe``."""
    return {
        "info": "test singlet", "foclen": 10.0, "fnum": 5.0, "r_sensor": 0.5, "d_sensor": 5.1,
        "sensor_size": [0.7071, 0.7071], "sensor_res": [64, 64],
        "surfaces": [
            {"idx": 1, "type": "Aperture", "r": 0.5, "d": 0.0, "mat2": "air", "is_square": False, "d_next": 0.1},
            {"idx": 2, "type": "Spheric", "r": 2.0, "roc": 5.0, "d": 0.1, "mat2": "1.5168/64.17", "d_next": 2.0},
            {"idx": 3, "type": "Spheric", "r": 2.0, "roc": -20.0, "d": 2.1, "mat2": "air", "d_next": LAST_T},
        ],
        "DOE": doe,
    }


Z_LAST = 2.1  # z of the last vertex in DeepLens's frame (first vertex at 0)


def write(tmp_path, doe, name="hybrid.json"):
    p = tmp_path / name
    p.write_text(json.dumps(lens(doe), indent=4))
    return p


def base(kind, **kw):
    d = {"type": kind, "(size)": [RES * PS, RES * PS], "d": Z_LAST + 0.8, "wvln0": 0.55, "res": [RES, RES],
         "fab_ps": PS, "is_square": True}
    d.update(kw)
    return d


def xy(doe):
    x, y = doe.pixel_xy()
    return x[None, :].expand(doe.shape), y[:, None].expand(doe.shape)


def design_phase(doe):
    return doe.design_phase_pixels(slice(None), slice(None)).detach()


def n_fs(w):
    return float(get_material("fused_silica").n(torch.tensor(w, dtype=torch.float64)))


def deeplens_phase_map0(raw, levels=16):
    """DeepLens get_phase_map0: wrap to [0, 2π), round to `levels` (level L kept as 2π, raywave folds it to 0)."""
    step = 2 * math.pi / levels
    return torch.remainder(torch.round(torch.remainder(raw, 2 * math.pi) / step) * step, 2 * math.pi)


# ------------------------------------------------------------------------------------------------ each type
def test_binary2(tmp_path):
    a = {"alpha2": -120.0, "alpha4": 3.0, "alpha6": -0.5, "alpha8": 0.01, "alpha10": 0.0}
    p = write(tmp_path, base("Binary2", **a))
    spec, data = read_hybrid_spec(p)
    assert spec["doe"]["phase_model"]["type"] == "binary_2"
    assert data.shape == (RES, RES) and data.pitch == PS
    assert data.distance == pytest.approx(0.8, abs=1e-12)
    assert data.material == "fused_silica" and data.levels == 16 and data.design_wavelength == 0.55
    hl = load_hybrid(p)
    doe = hl.doe
    assert hl.doe_info["phase_model"] == "binary_2" and hl.doe_info["source"] == "file"
    assert doe.shape == (RES, RES) and doe.pitch == PS and hl.doe_distance == pytest.approx(0.8)
    x, y = xy(doe)
    r2 = x**2 + y**2
    want = math.pi * (a["alpha2"] * r2 + a["alpha4"] * r2**2 + a["alpha6"] * r2**3 + a["alpha8"] * r2**4)
    assert torch.allclose(design_phase(doe), want, rtol=1e-12, atol=1e-12)
    # DeepLens's phase at λ0: wrapped and quantised to fab_step = 16 levels
    assert torch.allclose(doe.phase(0.55).detach(), deeplens_phase_map0(want), atol=1e-9)
    # and at another wavelength the height map in fused silica: φ0 · (λ0/λ) (n(λ) − 1)/(n0 − 1)
    ratio = (0.55 / 0.45) * (n_fs(0.45) - 1) / (n_fs(0.55) - 1)
    assert torch.allclose(doe.phase(0.45).detach(), deeplens_phase_map0(want) * ratio, atol=1e-9)


def test_fresnel_and_fab_step(tmp_path):
    p = write(tmp_path, base("Fresnel", f0=50.0, wvln0=0.6, fab_step=8))
    spec, data = read_hybrid_spec(p)
    assert spec["doe"]["phase_model"]["type"] == "binary_2"  # DeepLens's Fresnel is the paraxial quadratic
    assert data.levels == 8 and data.design_wavelength == 0.6
    doe = load_hybrid(p).doe
    x, y = xy(doe)
    want = -2 * math.pi * (x**2 + y**2) / (2 * 50.0 * 0.6e-3)  # Fresnel.phase_func
    assert torch.allclose(design_phase(doe), want, rtol=1e-12, atol=1e-12)
    assert doe.quant_levels == 8


def test_thinlens_is_a_fixed_focal_length(tmp_path):
    p = write(tmp_path, base("ThinLens", f0=40.0))
    doe = load_hybrid(p).doe
    assert doe.dispersion == "air" and doe.quant_levels is None
    x, y = xy(doe)
    for w in (0.45, 0.55, 0.65):  # DeepLens ThinLens: −π r² / (f0 λ) at every λ
        want = -math.pi * (x**2 + y**2) / (40.0 * w * 1e-3)
        assert torch.allclose(doe.phase(w).detach(), want, rtol=1e-12, atol=1e-12)


def test_grating(tmp_path):
    theta, alpha = 0.3, 250.0
    p = write(tmp_path, base("Grating", theta=theta, alpha=alpha, norm_radii=RES * PS / 2))
    spec, _ = read_hybrid_spec(p)
    assert spec["doe"]["phase_model"]["type"] == "grating"
    doe = load_hybrid(p).doe
    x, y = xy(doe)
    want = alpha * (x * math.sin(theta) + y * math.cos(theta)) / (RES * PS / 2)  # Grating.phase_func
    assert torch.allclose(design_phase(doe), want, rtol=1e-10, atol=1e-10)
    # a negative slope turns the grating around
    p = write(tmp_path, base("Grating", theta=theta, alpha=-alpha), "neg.json")
    assert torch.allclose(design_phase(load_hybrid(p).doe), -want, rtol=1e-10, atol=1e-10)
    # alpha 0 (DeepLens's default): a blank DOE
    spec, _ = read_hybrid_spec(write(tmp_path, base("Grating"), "flat.json"))
    assert "phase_model" not in spec["doe"]


def test_zernike(tmp_path):
    c = [0.0] * 37
    c[1], c[2], c[3], c[4], c[10], c[12] = 1.5, -0.7, 2.0, 0.4, -0.9, 0.3
    p = write(tmp_path, base("Zernike", z_coeff=c, zernike_order=37))
    spec, _ = read_hybrid_spec(p)
    m = spec["doe"]["phase_model"]
    assert m["type"] == "zernike" and m["radius"] == pytest.approx(RES * PS / 2)
    assert m["coefficients"][1:3] == [-0.7, 1.5]  # DeepLens's Z2 (ρ sinθ) and Z3 (ρ cosθ) are Noll's j = 3 and 2
    doe = load_hybrid(p).doe
    x, y = xy(doe)
    u, v = x / (RES * PS / 2), y / (RES * PS / 2)
    r, a = torch.sqrt(u**2 + v**2), torch.atan2(v, u)
    want = (1.5 * 2 * r * torch.sin(a) - 0.7 * 2 * r * torch.cos(a) + 2.0 * math.sqrt(3) * (2 * r**2 - 1)
            + 0.4 * math.sqrt(6) * r**2 * torch.sin(2 * a) - 0.9 * math.sqrt(5) * (6 * r**4 - 6 * r**2 + 1)
            + 0.3 * math.sqrt(10) * (4 * r**4 - 3 * r**2) * torch.sin(2 * a))  # calculate_zernike_phase
    inside = r <= 1  # DeepLens zeroes the phase outside the unit disk; raywave extends the polynomials
    assert torch.allclose(design_phase(doe)[inside], want[inside], rtol=1e-10, atol=1e-10)
    # DeepLens's typo in terms 29 / 30 is reported
    c[28] = 0.1
    with pytest.warns(LensFileWarning, match="terms 29 and 30"):
        read_hybrid_spec(write(tmp_path, base("Zernike", z_coeff=c), "z29.json"))


@pytest.mark.parametrize("ext", [".pth", ".npy"])
def test_pixel2d_map_file(tmp_path, ext):
    rng = np.random.default_rng(3)
    pmap = rng.uniform(0, 2 * math.pi, (RES, RES))
    pmap[0, :] = 0.25  # DeepLens's row 0 is the top (+y) row
    f = tmp_path / f"hybrid_pixel2d{ext}"
    if ext == ".pth":
        torch.save(torch.tensor(pmap, dtype=torch.float32), f)
    else:
        np.save(f, pmap)
    # DeepLens records the path it saved to (relative to its working directory): found next to the lens
    p = write(tmp_path, base("Pixel2D", phase_map_path=f"./results/{f.name}"))
    spec, data = read_hybrid_spec(p)
    assert data.phase_path == str(f) and data.shape == (RES, RES)
    tol = 1e-6 if ext == ".pth" else 0
    assert np.allclose(data.phase, pmap[::-1], atol=tol)  # flipped: raywave's row 0 is at −y
    hl = load_hybrid(p)
    assert type(hl.doe).__name__ == "PixelDOE" and hl.doe.quant_levels == 16
    assert torch.allclose(design_phase(hl.doe)[-1], torch.full((RES,), 0.25, dtype=torch.float64), atol=tol)
    # the refractive-lens reader keeps the spec and says the map is not in it
    with pytest.warns(LensFileWarning, match="Pixel2D phase map"):
        assert read_deeplens(p)["doe"]["phase"] is None


def test_pixel2d_errors(tmp_path):
    p = write(tmp_path, base("Pixel2D", phase_map_path="missing.pth"))
    with pytest.raises(LensFileError, match="phase map file 'missing.pth' not found"):
        read_hybrid_spec(p)
    np.save(tmp_path / "small.npy", np.zeros((8, 8)))
    p = write(tmp_path, base("Pixel2D", phase_map_path="small.npy"), "small.json")
    with pytest.raises(LensFileError, match=r"shape \[8, 8\]"):
        read_hybrid_spec(p)
    p = write(tmp_path, base("Pixel2D"), "nomap.json")
    with pytest.raises(LensFileError, match="initialise it randomly"):
        read_hybrid_spec(p)


# ------------------------------------------------------------------------------- legacy "DOE" + param_model
def legacy(model, **kw):
    d = {"type": "DOE", "l": RES * PS, "d": Z_LAST + 0.5, "res": [2 * RES, 2 * RES], "fab_ps": PS,
         "is_square": True, "param_model": model, "doe_path": None}
    d.update(kw)
    return d


def test_legacy_binary2_and_cubic(tmp_path):
    o = {"order2": -30.0, "order4": 2.0, "order6": 0.5, "order8": -0.1}
    p = write(tmp_path, legacy("binary2", **o))
    spec, data = read_hybrid_spec(p)
    assert data.shape == (RES, RES) and data.oversample == 2 and data.distance == pytest.approx(0.5)
    assert data.wrap and data.levels is None and data.material == "fused_silica"
    hl = load_hybrid(p)
    assert hl.doe_info["oversample"] == 2
    x, y = xy(hl.doe)
    rho2 = (x**2 + y**2) / (RES * PS / math.sqrt(2)) ** 2  # legacy: ρ = r / (l/√2), no π factor
    want = sum(o[f"order{2 * i}"] * rho2**i for i in (1, 2, 3, 4))
    assert torch.allclose(design_phase(hl.doe), want, rtol=1e-12, atol=1e-12)
    # wrapped (legacy get_phase_map0), not quantised
    assert torch.allclose(hl.doe.phase(0.55).detach(), torch.remainder(want, 2 * math.pi), atol=1e-12)

    p = write(tmp_path, legacy("cubic", a3=7.0), "cubic.json")
    doe = load_hybrid(p).doe
    x, y = xy(doe)
    assert torch.allclose(design_phase(doe), 7.0 * (x**3 + y**3), rtol=1e-12, atol=1e-12)


def test_legacy_fresnel_matches_the_fmod_form(tmp_path):
    p = write(tmp_path, legacy("fresnel", f0=20.0), "fresnel.json")
    doe = load_hybrid(p).doe
    x, y = xy(doe)
    deeplens = -2 * math.pi * torch.fmod((x**2 + y**2) / (2 * 0.55e-3 * 20.0), 1)
    assert torch.allclose(doe.phase(0.55).detach(), torch.remainder(deeplens, 2 * math.pi), atol=1e-9)


def test_the_real_a489_example_file(tmp_path):
    """DeepLens's datasets/lenses/hybridlens/a489_doe.json (legacy layout, "(size)" scalar, absolute "d")."""
    data = {"info": "A489 with a DOE", "foclen": 7.7719, "fnum": 3.8859, "r_sensor": 2.1213, "d_sensor": 11.257,
            "(sensor_size)": [3.0, 3.0], "sensor_res": [3000, 3000],
            "surfaces": [
                {"idx": 1, "type": "Aperture", "r": 1.0, "(d)": 0.0, "mat2": "air", "is_square": False,
                 "diffraction": False, "d_next": 0.1},
                {"idx": 2, "type": "Aspheric", "r": 6.35, "(c)": 0.2104, "roc": 4.7531, "d": 0.1, "k": -1.2051,
                 "ai": [0.0, 0.000533, 1.12e-05, -3.75e-07, -7.63e-09, 1.36e-10], "mat2": "h-k51",
                 "(ai2)": 0.0, "(ai4)": 0.000533, "(ai6)": 1.12e-05, "(ai8)": -3.75e-07, "(ai10)": -7.63e-09,
                 "(ai12)": 1.36e-10, "d_next": 7.5},
                {"idx": 3, "type": "Spheric", "r": 6.35, "(c)": -0.0639, "roc": -15.65, "(d)": 7.6, "mat2": "air",
                 "d_next": 3.657}],
            "DOE": {"type": "DOE", "(size)": 3.0, "d": 8.3098, "res": [3000, 3000], "fab_ps": 0.001,
                    "is_square": True, "param_model": "binary2", "doe_path": None,
                    "order2": 0.0, "order4": 0.0, "order6": 0.0, "order8": 0.0}}
    p = tmp_path / "a489_doe.json"
    p.write_text(json.dumps(data, indent=4))
    spec, doe = read_hybrid_spec(p)
    assert doe.distance == pytest.approx(8.3098 - 7.6) and doe.shape == (3000, 3000) and doe.pitch == 0.001
    assert spec["doe"]["phase_model"] == {"type": "binary_2", "order": 1.0, "norm_radius": 3.0 / math.sqrt(2),
                                          "coefficients": [0.0, 0.0, 0.0, 0.0]}


# --------------------------------------------------------------------------------------------- position
def test_position_from_d_next(tmp_path):
    # the newest DeepLens writes the DOE's gap to the sensor, d_next, instead of its absolute z
    d = base("Binary2", alpha2=-10.0)
    del d["d"]
    d["d_next"] = 2.25
    _, data = read_hybrid_spec(write(tmp_path, d))
    assert data.distance == pytest.approx(LAST_T - 2.25)


def test_position_errors(tmp_path):
    with pytest.raises(LensFileError, match="between the last surface and the sensor"):
        read_hybrid_spec(write(tmp_path, base("Binary2", alpha2=1.0, d=Z_LAST - 0.1)))
    d = base("Binary2", alpha2=1.0)
    del d["d"]
    with pytest.raises(LensFileError, match="no position"):
        read_hybrid_spec(write(tmp_path, d, "nopos.json"))


# ------------------------------------------------------------------------------------------------- errors
def test_unknown_type_names_the_type_and_the_file(tmp_path):
    text = json.dumps(lens(base("Metasurface", alpha2=1.0)), indent=4)
    p = tmp_path / "meta.json"
    p.write_text(text)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if '"Metasurface"' in ln)
    with pytest.raises(LensFileError) as e:
        read_hybrid_spec(p)
    assert str(e.value).startswith(f"{p}:{line}: DOE.type: DeepLens DOE type 'Metasurface' is not supported")
    with pytest.raises(LensFileError, match="parameter model 'poly1d' is not supported"):
        read_hybrid_spec(write(tmp_path, legacy("poly1d"), "poly.json"))


def test_missing_parameters_and_unknown_keys(tmp_path):
    with pytest.raises(LensFileError, match="without 'f0'"):
        read_hybrid_spec(write(tmp_path, base("Fresnel")))
    with pytest.raises(LensFileError, match=r"DOE.res"):
        read_hybrid_spec(write(tmp_path, base("Binary2", alpha2=1.0, res="big"), "res.json"))
    with pytest.warns(LensFileWarning, match="DOE.colour"):
        read_hybrid_spec(write(tmp_path, base("Binary2", alpha2=1.0, colour="red"), "extra.json"))


def test_legacy_pixel2d_from_its_checkpoint(tmp_path):
    pmap = torch.linspace(0, 6, RES * RES, dtype=torch.float64).reshape(RES, RES)
    torch.save({"param_model": "pixel2d", "pmap": pmap}, tmp_path / "lens_doe.pth")
    p = write(tmp_path, legacy("pixel2d", doe_path="lens_doe.pth"), "legacy_pixel.json")
    _, data = read_hybrid_spec(p)
    assert np.array_equal(data.phase, pmap.numpy()[::-1]) and data.wrap


def test_converted_spec_round_trips_with_wrap(tmp_path):
    from raywave.io import read_json_spec, write_json_spec

    spec = read_deeplens(write(tmp_path, legacy("binary2", order2=-3.0)))
    assert spec["doe"]["wrap"] is True
    write_json_spec(spec, tmp_path / "converted.json")
    assert read_json_spec(tmp_path / "converted.json") == spec
    bad = dict(spec, doe=dict(spec["doe"], wrap="yes"))
    with pytest.raises(LensFileError, match="doe.wrap: must be true or false"):
        write_json_spec(bad, tmp_path / "bad.json")
