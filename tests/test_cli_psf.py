"""Hybrid lens files (the "doe" section, .zmx diffractive surfaces), `raywave psf` and the PSF metrics."""

import json
import math
import warnings

import numpy as np
import pytest
import torch

from raywave.cli.main import main
from raywave.hybrid.metrics import psf_metrics
from raywave.io import LensFileError, LensFileWarning, read_hybrid_spec, read_json_spec, read_lens_spec, write_json_spec
from raywave.assembly.build import load_hybrid
from raywave.lens.build import bundled_lens_path

KS = 32
FAST = ["--ks", str(KS), "--rays", "24"]


def hybrid_spec(**doe):
    spec = json.loads(bundled_lens_path("hybrid_asphere").read_text())
    spec["doe"] = doe
    return spec


def write_spec(tmp_path, spec, name="h.json"):
    """Write ``spec`` as indented JSON without validation (to test the reader); returns (path, text)."""
    p = tmp_path / name
    text = json.dumps(spec, indent=2)
    p.write_text(text)
    return p, text


def line_of(text, needle):
    """Line of ``needle`` in the "doe" section of ``text``."""
    return text[: text.index(needle, text.index('"doe"'))].count("\n") + 1


def centroid_px(psf):
    ks = psf.shape[-1]
    c = np.arange(ks) - ks // 2
    return float((psf.sum(0) * c).sum() / psf.sum()), float((psf.sum(1) * c).sum() / psf.sum())


# ------------------------------------------------------------------ the "doe" section
def test_doe_section_round_trip_and_phase_map(tmp_path):
    phase = np.random.default_rng(1).uniform(-math.pi, math.pi, (20, 30))
    (tmp_path / "maps").mkdir()
    np.save(tmp_path / "maps" / "doe.npy", phase)
    spec = hybrid_spec(distance=0.7, pitch=0.002, size=[0.06, 0.04], aperture="circle", phase="maps/doe.npy",
                       design_wavelength=0.53, oversample=2)
    write_json_spec(spec, tmp_path / "h.json")
    assert read_json_spec(tmp_path / "h.json") == spec  # exact round trip, the path kept relative
    spec2, doe = read_hybrid_spec(tmp_path / "h.json")
    assert spec2 == spec
    assert doe.shape == (20, 30) and doe.pitch == 0.002 and doe.aperture == "circle" and doe.oversample == 2
    assert np.array_equal(doe.phase, phase) and doe.design_wavelength == 0.53

    hl = load_hybrid(tmp_path / "h.json")
    assert hl.doe.shape == (20, 30) and hl.doe.pitch == 0.002 and hl.doe.aperture == "circle"
    assert hl.doe_distance == 0.7 and hl.oversample == 2 and hl.doe_info["source"] == "file"
    assert torch.equal(hl.doe.phase_map.detach(), torch.as_tensor(phase))  # row iy = y, column ix = x

    # a .npz with its own pitch (the file's pitch may be left out)
    np.savez(tmp_path / "doe.npz", phase=phase, pitch=0.002)
    spec = hybrid_spec(distance=0.7, shape=[20, 30], phase="doe.npz")
    write_json_spec(spec, tmp_path / "z.json")
    _, doe = read_hybrid_spec(tmp_path / "z.json")
    assert doe.pitch == 0.002 and doe.shape == (20, 30)

    # convert to another folder keeps the phase map findable
    out = tmp_path / "elsewhere"
    out.mkdir()
    assert main(["convert", str(tmp_path / "h.json"), str(out / "h.json")]) == 0
    assert read_json_spec(out / "h.json")["doe"]["phase"] == "../maps/doe.npy"
    assert read_hybrid_spec(out / "h.json")[1].shape == (20, 30)


def test_bundled_hybrid_lens():
    spec, doe = read_hybrid_spec(bundled_lens_path("hybrid_asphere"))
    base = read_lens_spec(bundled_lens_path("asphere_hk51"))
    assert spec["surfaces"] == base["surfaces"]
    assert doe.distance == 0.7 and doe.pitch == 0.001 and doe.shape == (3000, 3000) and doe.phase is None


@pytest.mark.parametrize("doe, key, expected", [
    ({"distance": 0.7, "pitch": 0.001, "size": [1.0, 1.0], "oversampel": 2}, '"oversampel"',
     "doe.oversampel: unknown key 'oversampel' (did you mean 'oversample'?)"),
    ({"distance": 0.7, "pitch": 0.001, "size": [1.0, 1.0], "phase": "missing.npy"}, '"phase"',
     "doe.phase: phase map file"),
    ({"distance": 0.7, "pitch": 0.001, "shape": [10, 11], "phase": "map.npy"}, '"shape"',
     "doe.shape: [10, 11] disagrees with the phase map's shape [10, 12]"),
    ({"distance": 0.7, "pitch": 0.001, "size": [0.012, 0.011], "phase": "map.npy"}, '"size"',
     "doe.size: [0.012, 0.011] mm disagrees with the phase map"),
    ({"distance": 0.7, "pitch": 0.003, "size": [1.0, 1.0]}, "1.0", "doe.size[0]: the width 1.0 mm is not a whole "
     "number of 0.003 mm pixels"),
    ({"distance": 3.7, "pitch": 0.001, "size": [1.0, 1.0]}, '"distance"',
     "the DOE plane must lie between the last surface and the sensor"),
    ({"distance": 0.7, "pitch": -0.001}, '"pitch"', "doe.pitch: must be > 0"),
    ({"distance": 0.7, "pitch": 0.001, "size": [1.0, 1.0], "aperture": "round"}, '"aperture"',
     "doe.aperture: must be 'square' or 'circle'"),
    ({"distance": 0.7, "phase": "map.txt"}, '"phase"', "a phase map is a .npy file"),
    ({"distance": 0.7, "phase": "map3d.npy"}, '"phase"', "must be 2-D (ny, nx), got shape (2, 10, 12)"),
    ({"distance": 0.7, "pitch": 0.002, "phase": "map.npz"}, '"pitch"', "disagrees with the pitch 0.001 mm stored"),
    ({"pitch": 0.001}, '"doe"', "doe: missing 'distance'"),
])
def test_doe_section_strict_errors(tmp_path, doe, key, expected):
    np.save(tmp_path / "map.npy", np.zeros((10, 12)))
    np.save(tmp_path / "map3d.npy", np.zeros((2, 10, 12)))
    np.savez(tmp_path / "map.npz", phase=np.zeros((10, 12)), pitch=0.001)
    path, text = write_spec(tmp_path, hybrid_spec(**doe))
    with pytest.raises(LensFileError) as e:
        read_lens_spec(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}:{line_of(text, key)}: "), msg
    assert expected in msg


def test_non_finite_phase_map_is_reported_when_built(tmp_path):
    bad = np.zeros((10, 12))
    bad[3, 4] = np.nan
    np.save(tmp_path / "map.npy", bad)
    path, text = write_spec(tmp_path, hybrid_spec(distance=0.7, pitch=0.001, phase="map.npy"))
    read_lens_spec(path)  # reading the lens checks the header only
    with pytest.raises(LensFileError, match=r"h\.json:\d+: doe\.phase: .* contains NaN or inf \(first at \[3, 4\]\)"):
        load_hybrid(path)


# ------------------------------------------------------------------ .zmx: a diffractive last surface
TINY_ZMX = """VERS 190513 80 123457
MODE SEQ
NAME tiny hybrid
UNIT MM X W X CM MR CPMM
ENPD 4.0
FTYP 0 0 1 1 0 0 0
YFLN 0.0
WAVM 1 0.55 1
PWAV 1
SURF 0
  TYPE STANDARD
  CURV 0.0
  DISZ INFINITY
SURF 1
  STOP
  TYPE STANDARD
  CURV 0.05
  DISZ 2.0
  GLAS ___BLANK 1 0 1.5 0
SURF 2
  TYPE STANDARD
  CURV -0.05
  DISZ 3.0
SURF 3
  TYPE BINARY_2
  CURV 0.0
  DISZ 15.0
  CLAP 0 1.5 0
  PARM 0 1
  PARM 1 0
  XDAT 1 2 0 0 1 0 0 ""
  XDAT 2 2.0 0 0 1 0 0 ""
  XDAT 3 -100.0 0 0 1 0 0 ""
  XDAT 4 5.0 0 0 1 0 0 ""
SURF 4
  TYPE STANDARD
  CURV 0.0
  DISZ 0.0
"""


def test_zmx_binary2_last_surface_is_the_doe_plane(tmp_path, capsys):
    path = tmp_path / "tiny.zmx"
    path.write_text(TINY_ZMX)
    spec = read_lens_spec(path)
    assert len(spec["surfaces"]) == 2 and spec["surfaces"][-1]["thickness"] == 18.0  # 3 + 15: reaches the sensor
    assert spec["doe"] == {"distance": 3.0, "aperture": "circle", "size": [3.0, 3.0], "phase": None,
                           "phase_model": {"type": "binary_2", "order": 1.0, "norm_radius": 2.0,
                                           "coefficients": [-100.0, 5.0]}}
    hl = load_hybrid(path, doe_pitch=0.002)  # the BINARY_2 phase is applied (a Binary2DOE, below)
    assert hl.doe_distance == 3.0 and hl.doe_z() == pytest.approx(5.0) and hl.sensor_z() == pytest.approx(20.0)
    assert hl.doe.shape == (1500, 1500) and hl.doe.aperture == "circle" and type(hl.doe).__name__ == "Binary2DOE"
    assert hl.doe.coefficients.tolist() == [-100.0, 5.0] and hl.doe.norm_radius == 2.0 and hl.doe.order == 1.0

    # the file gives no pixel pitch: a one-line CLI error; the JSON copy keeps the DOE
    assert main(["psf", str(path)] + FAST) == 2
    err = capsys.readouterr().err
    assert "raywave: error:" in err and "no pixel pitch" in err and "--doe-pitch" in err and "Traceback" not in err
    assert main(["convert", str(path), str(tmp_path / "tiny.json")]) == 0
    assert read_json_spec(tmp_path / "tiny.json")["doe"] == spec["doe"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", LensFileWarning)  # a BINARY_2 DOE is written as a BINARY_2 surface
        assert main(["convert", str(tmp_path / "tiny.json"), str(tmp_path / "back.zmx")]) == 0
    assert read_lens_spec(tmp_path / "back.zmx") == spec


@pytest.mark.parametrize("edit, expected", [
    (lambda t: t.replace("SURF 3\n  TYPE BINARY_2\n  CURV 0.0", "SURF 3\n  TYPE BINARY_2\n  CURV 0.01"),
     "raywave's DOE is a thin phase element on a plane"),
    # (a curved BINARY_2 inside the lens is read as a conformal DOE since issue 46's second round:
    # tests/test_midsystem_zmx.py::test_curved_binary2_is_a_conformal_doe)
    (lambda t: t.replace("  PARM 1 0\n", "  PARM 1 0.001\n"), "aspheric substrate"),
    (lambda t: t.replace("  DISZ 15.0\n", "  DISZ 0.0\n"), "must lie before the image"),
])
def test_zmx_unsupported_diffractive_surfaces(tmp_path, edit, expected):
    path = tmp_path / "bad.zmx"
    path.write_text(edit(TINY_ZMX))
    with pytest.raises(LensFileError, match=expected):
        read_lens_spec(path)


# ------------------------------------------------------------------ raywave psf
def test_psf_on_the_bundled_hybrid_lens(tmp_path, capsys):
    out = tmp_path / "psf.npy"
    assert main(["psf", "hybrid_asphere", "-o", str(out), "--json"] + FAST) == 0
    s = json.loads(capsys.readouterr().out)
    psf = np.load(out)
    assert psf.shape == (KS, KS) and psf.dtype == np.float64
    assert psf.sum() == pytest.approx(1.0, abs=1e-12) and psf.min() >= 0
    cx, cy = centroid_px(psf)
    assert abs(cx) < 0.1 and abs(cy) < 0.1  # on axis the PSF is centred on pixel [ks//2, ks//2]
    assert np.unravel_index(psf.argmax(), psf.shape) == (KS // 2, KS // 2)

    for k in ("center_mm", "pitch_mm", "energy_outside", "rms_radius_um", "centroid_offset_um", "r50_um", "r80_um",
              "r90_um", "peak", "rays", "mode", "doe", "wavelength_um", "field_deg", "depth_mm"):
        assert k in s, k
    assert s["center_mm"] == [0.0, 0.0] and s["pitch_mm"] == pytest.approx(0.003) and s["mode"] == "accurate"
    assert s["wavelength_um"] == 0.53 and s["depth_mm"] == "inf" and s["rays"] > 24**2 / 2
    assert 0 < s["r50_um"] < s["r80_um"] < s["r90_um"] < KS * 3.0
    assert s["peak"] == pytest.approx(psf.max()) and 0 <= s["energy_outside"] < 0.05
    assert s["rms_radius_um"] == pytest.approx(psf_metrics(psf, 0.003)["rms_radius"] * 1e3)
    assert math.hypot(*s["centroid_offset_um"]) < 0.1 * 3.0
    assert s["doe"]["source"] == "file" and s["doe"]["shape"] == [3000, 3000] and s["doe"]["distance_mm"] == 0.7


def test_psf_off_axis_npz_png_and_default_doe(tmp_path, capsys):
    """A lens file without a DOE gets a default blank one; +y field images at +y; .npz and --png outputs."""
    npz, png = tmp_path / "psf.npz", tmp_path / "psf.png"
    assert main(["psf", "asphere_hk51", "--field", "0", "5", "--wavelength", "0.53", "--depth", "inf", "-o", str(npz),
                 "--png", str(png), "--log", "--doe-pitch", "0.0015", "--json"] + FAST) == 0
    s = json.loads(capsys.readouterr().out)
    z = np.load(npz)
    assert set(z.files) >= {"psf", "center", "pitch", "energy_outside"}
    assert z["psf"].shape == (KS, KS) and z["psf"].sum() == pytest.approx(1.0)
    assert z["center"][1] > 0.5 and abs(z["center"][0]) < 1e-12  # OpticStudio sign: +y angle -> +y image
    assert float(z["pitch"]) == pytest.approx(0.003) and list(z["center"]) == s["center_mm"]
    d = s["doe"]
    assert d["source"] == "default" and d["pitch_mm"] == 0.0015 and d["aperture"] == "square"
    assert d["distance_mm"] == pytest.approx(0.5 * 3.618234)  # half way from the last vertex to the sensor
    assert d["size_mm"][0] == d["size_mm"][1] > 2 * 0.8  # holds the beam at 5 degrees (y up to ~0.8 mm)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_psf_phase_map_from_the_lens_file_deflects_along_y(tmp_path, capsys):
    """A linear phase ramp along the rows (y) of a .npy map shifts the PSF toward +y by the grating equation."""
    pitch, n, period, wl = 0.0015, 800, 0.024, 0.53
    y = (np.arange(n) - (n - 1) / 2) * pitch
    np.save(tmp_path / "ramp.npy", np.repeat((2 * np.pi * y / period)[:, None], n, axis=1))
    path, _ = write_spec(tmp_path, hybrid_spec(distance=0.7, pitch=pitch, shape=[n, n], phase="ramp.npy"))
    out = tmp_path / "psf.npy"
    assert main(["psf", str(path), "--wavelength", str(wl), "--ks", "64", "--rays", "24", "-o", str(out)]) == 0
    capsys.readouterr()
    psf = np.load(out)
    cx, cy = centroid_px(psf)
    s = wl * 1e-3 / period
    shift = (3.618234 - 0.7) * s / math.sqrt(1 - s * s) / 0.003  # pixels
    assert abs(cx) < 0.1 and cy == pytest.approx(shift, abs=0.5)


@pytest.mark.parametrize("argv, expected", [
    (["psf", "no_such_lens"], "no_such_lens"),
    (["psf", "hybrid_asphere", "--depth", "far"], "--depth: 'far' is not a number"),
    (["psf", "hybrid_asphere", "--depth", "-5"], "--depth: must be > 0"),
    (["psf", "hybrid_asphere", "--ks", "0"], "--ks: must be >= 1"),
    (["psf", "hybrid_asphere", "--wavelength", "550"], "µm, not nm"),
    (["psf", "hybrid_asphere", "--field", "1", "2", "3"], "give one field per --field, Y or X,Y"),
    (["psf", "hybrid_asphere", "-o", "psf.txt"], "-o: the PSF is written as .npy"),
    (["psf", "hybrid_asphere", "--doe-distance", "9"], "the DOE distance must lie between"),
    (["psf", "hybrid_asphere", "--doe-size", "0"], "--doe-size: must be > 0"),
    (["psf", "hybrid_asphere", "--device", "cuda:x"], "--device: 'cuda:x' is not a torch device"),
])
def test_psf_bad_input_is_one_line(argv, expected, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("raywave: error:") and expected in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ metrics
def pixel_gaussian(ks, sigma, pitch, cx=0.0, cy=0.0):
    """A 2-D Gaussian integrated exactly over the pixels of a ks×ks grid (pixel [ks//2, ks//2] at the origin)."""
    e = (torch.arange(ks + 1, dtype=torch.float64) - ks // 2 - 0.5) * pitch

    def cdf(t, c):
        return 0.5 * (1 + torch.erf((t - c) / (sigma * math.sqrt(2))))

    gx, gy = torch.diff(cdf(e, cx)), torch.diff(cdf(e, cy))
    g = gy[:, None] * gx[None, :]
    return g / g.sum()


def test_psf_metrics_of_a_gaussian():
    pitch, sigma = 1e-3, 8e-3  # σ = 8 pixels
    g = pixel_gaussian(96, sigma, pitch, cx=0.3 * pitch, cy=-0.2 * pitch)
    m = psf_metrics(g, pitch)
    assert m["centroid"] == pytest.approx([0.3 * pitch, -0.2 * pitch], abs=1e-6 * pitch)  # tails cut at 6 σ
    assert m["total"] == pytest.approx(1.0) and m["peak_pixel"] == [48, 48]
    # RMS of the pixel-integrated PSF: each pixel adds its box variance pitch²/12 per axis
    assert m["rms_radius"] == pytest.approx(math.sqrt(2 * sigma**2 + pitch**2 / 6), rel=1e-6)  # tails cut at 6 σ
    assert m["rms_radius"] == pytest.approx(sigma * math.sqrt(2), rel=3e-3)
    # EE radius of a 2-D Gaussian: r_p = σ sqrt(-2 ln(1 - p)); pixels blur it by ~pitch²/(12 σ²) (0.13 %)
    sigma_eff = math.sqrt(sigma**2 + pitch**2 / 6)  # pixel integration + uniform spreading within the pixel
    for p in (0.5, 0.8, 0.9):
        r = m[f"r{round(100 * p)}"]
        assert r == pytest.approx(sigma * math.sqrt(-2 * math.log(1 - p)), rel=3e-3)
        assert r == pytest.approx(sigma_eff * math.sqrt(-2 * math.log(1 - p)), rel=5e-4)
    assert m["r50"] < m["r80"] < m["r90"]


def test_psf_metrics_single_pixel_and_bad_input():
    p = torch.zeros(9, 9, dtype=torch.float64)
    p[4, 4] = 1.0
    m = psf_metrics(p, 2.0)
    assert m["centroid"] == [0.0, 0.0] and m["rms_radius"] == 0.0 and m["peak"] == 1.0
    # energy spread uniformly over one pixel of side 2: EE(r) = π r² / 4 for r <= 1
    assert m["r50"] == pytest.approx(math.sqrt(0.5 * 4 / math.pi), rel=0.02)
    with pytest.raises(ValueError, match="all zeros"):
        psf_metrics(torch.zeros(4, 4), 1.0)
    with pytest.raises(ValueError, match="2-D"):
        psf_metrics(torch.ones(2, 4, 4), 1.0)


def test_psf_stop_edge_option(tmp_path):
    """--stop-edge exit_pupil reaches the engine (and a bad value is an argparse error)."""
    import numpy as np

    from raywave.cli.main import main

    outs = {}
    for edge in ("doe", "exit_pupil"):
        out = tmp_path / f"{edge}.npy"
        assert main(["psf", "hybrid_asphere", "--field", "0", "7", "--ks", "16", "--stop-edge", edge, "-o", str(out)]) == 0
        outs[edge] = np.load(out)
        assert abs(outs[edge].sum() - 1) < 1e-9
    assert np.abs(outs["doe"] - outs["exit_pupil"]).sum() > 1e-6  # the two models differ off axis
    with pytest.raises(SystemExit):
        main(["psf", "singlet", "--stop-edge", "pupil"])
