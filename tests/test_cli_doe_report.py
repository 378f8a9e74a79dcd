"""``raywave doe report``: the fabrication tolerance report (small DOEs, few samples)."""

import json
import math

import numpy as np
import pytest

from raywave.cli.main import main
from raywave.doe import staircase_efficiency
from raywave.doe import fabrication as fab


def _grating(tmp_path, L=16, period=16, periods=4, ny=4):
    """A linear ramp (whole periods, no rounding ties) as a .npz with its pitch."""
    i = np.arange(period * periods)
    ph = 2 * np.pi * (i + 0.5 - period / (2 * L)) / period
    path = tmp_path / "grating.npz"
    np.savez(path, phase=np.tile(ph, (ny, 1)), pitch=1e-3)
    return path


def test_report_of_a_grating(tmp_path, capsys):
    path = _grating(tmp_path)
    out = tmp_path / "rep"
    assert main(["doe", "report", str(path), "--levels", "16", "--material", "fused_silica", "--wavelength", "0.55",
                 "--depth-error", "5", "--misalignment", "0.1", "--samples", "12", "--seed", "3",
                 "--wavelengths", "0.45", "0.55", "--orders", "1", "0", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "16 levels = 4 masks" in text and "597.9 nm" in text and "order +1" in text
    assert "±2σ of a normal distribution" in text
    r = json.loads((out / "report.json").read_text())
    assert {p.name for p in out.iterdir()} == {"report.json", "efficiency_hist.png"}
    np.testing.assert_allclose(r["fabrication"]["depths_nm"], fab.etch_depths(16, "fused_silica", 0.55) * 1e6)
    assert r["fabrication"]["min_feature_um"] == pytest.approx(1.0)
    t = r["tolerance"]
    assert t["samples"] == 12 and t["levels"] == 16 and t["seed"] == 3 and t["wavelengths_um"] == [0.45, 0.55]
    e1 = [e for e in t["efficiency"] if e["order"] == 1 and e["wavelength_um"] == 0.55][0]
    assert e1["nominal"] == pytest.approx(np.sinc(1 / 16) ** 2, abs=1e-12)       # whole periods: the staircase
    assert e1["theory"] == pytest.approx(staircase_efficiency(1, 16), abs=1e-12)
    assert e1["p5"] <= e1["mean"] <= e1["max"] <= e1["nominal"] + 1e-12
    # reproducible: the same seed gives the same statistics
    assert main(["doe", "report", str(path), "--samples", "12", "--seed", "3", "--wavelengths", "0.45", "0.55",
                 "--orders", "1", "0", "-o", str(tmp_path / "rep2"), "--no-png", "--json"]) == 0
    r2 = json.loads(capsys.readouterr().out)
    assert r2["tolerance"]["efficiency"] == t["efficiency"]
    # the misalignment in µm: 0.1 µm at a 1 µm pitch is 0.1 px
    assert main(["doe", "report", str(path), "--samples", "12", "--seed", "3", "--wavelengths", "0.45", "0.55",
                 "--orders", "1", "0", "--misalignment", "0.1um", "-o", str(tmp_path / "rep3"), "--no-png",
                 "--json"]) == 0
    r3 = json.loads(capsys.readouterr().out)
    assert r3["tolerance"]["misalignment_px"] == pytest.approx(0.1)
    assert [e["mean"] for e in r3["tolerance"]["efficiency"]] == pytest.approx([e["mean"] for e in t["efficiency"]],
                                                                               rel=1e-12)


def test_report_with_a_lens_gives_psf_statistics(tmp_path, capsys):
    """An ideal lens (f = 5 mm, F/10) + a 4-level diffractive lens (f = 10 mm) 1 mm behind it, sensor at the
    combined focus; the DOE is a .npy with --pitch."""
    lam, f_doe, n, p = 0.55, 10.0, 480, 1e-3
    x = (np.arange(n) - (n - 1) / 2) * p
    np.save(tmp_path / "fresnel.npy", -math.pi * (x[None, :] ** 2 + x[:, None] ** 2) / (lam * 1e-3 * f_doe))
    spec = {"format": "raywave-lens", "version": 1, "system_aperture": {"epd": 0.5},
            "wavelengths": {"values": [lam], "primary": 0},
            "surfaces": [{"type": "paraxial", "focal_length": 5.0, "thickness": 1 + 1 / (1 / 4 + 1 / f_doe),
                          "stop": True}],
            "doe": {"distance": 1.0, "pitch": p, "size": [n * p, n * p]}}
    (tmp_path / "lens.json").write_text(json.dumps(spec))
    out = tmp_path / "rep"
    assert main(["doe", "report", str(tmp_path / "fresnel.npy"), "--pitch", str(p), "--levels", "4",
                 "--depth-error", "10", "--misalignment", "0.25", "--samples", "4", "--lens",
                 str(tmp_path / "lens.json"), "--ks", "24", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "peak_ratio" in text and "worst sample" in text
    assert {q.name for q in out.iterdir()} == {"report.json", "efficiency_hist.png", "psf_metrics_hist.png",
                                               "psf_nominal_vs_worst.png"}
    t = json.loads((out / "report.json").read_text())["tolerance"]
    peak = [e for e in t["psf"] if e["metric"] == "peak_ratio"][0]
    assert 0.5 < peak["min"] <= peak["max"] < 1.05 and peak["nominal"] == 1.0
    assert t["lens"]["doe_distance_mm"] == 1.0 and t["wavelengths_um"] == [lam]


@pytest.mark.parametrize("argv,msg", [
    (["--depth-error", "-1"], "--depth-error"),
    (["--misalignment", "-0.1"], "--misalignment"),
    (["--misalignment", "0.1mm"], "--misalignment"),
    (["--samples", "0"], "--samples"),
    (["--levels", "12"], "power of two"),
    (["--distribution", "cauchy"], "--distribution"),
    (["--orders", "1.5"], "--orders"),
    (["--wavelengths", "550"], "µm, not nm"),
    (["--depth-error", "60"], "not a small error"),
    (["--lens", "no_such_lens.json"], "--lens"),
])
def test_report_bad_inputs(tmp_path, capsys, argv, msg):
    path = _grating(tmp_path)
    assert main(["doe", "report", str(path), "--samples", "2", "-o", str(tmp_path / "o"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("raywave: error:") and msg in err and "\n" not in err, err
