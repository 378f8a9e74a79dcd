"""The example scripts run and write their figures."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_lens_analysis_example(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "examples" / "lens_analysis.py"), "-o", str(tmp_path)], check=True,
                   capture_output=True)
    assert (tmp_path / "double_gauss_layout.png").stat().st_size > 10_000
    assert "Effective focal length" in (tmp_path / "singlet.txt").read_text()


def test_precision_study_example(tmp_path):
    import json

    subprocess.run([sys.executable, str(ROOT / "examples" / "precision_study.py"), "-o", str(tmp_path), "--rays",
                    "60000"], check=True, capture_output=True)
    assert (tmp_path / "precision_study.png").stat().st_size > 30_000
    report = json.loads((tmp_path / "precision_study.json").read_text())
    assert report["float32_phase_error_rms_rad"] > 0.1  # float32 breaks the phase at a 1 m object


@pytest.mark.slow  # CI time (README: Slow suite)
def test_compare_examples_quick(tmp_path):
    """Figs. S3–S5 in their quick modes (~5–10 s each)."""
    import json

    for name in ("compare_fields", "compare_raytrace", "compare_exit_pupil"):
        out = tmp_path / name
        subprocess.run([sys.executable, str(ROOT / "examples" / f"{name}.py"), "-o", str(out), "--quick"], check=True,
                       capture_output=True)
        assert (out / f"{name}.json").is_file()
        assert all(p.stat().st_size > 20_000 for p in out.glob("*.png")) and len(list(out.glob("*.png"))) >= 1
    fields = json.loads((tmp_path / "compare_fields" / "compare_fields.json").read_text())
    assert fields["l1_vs_raywave"]["pupil"][0][0] < 0.02 < fields["l1_vs_raywave"]["pupil"][-1][0]
    ray = json.loads((tmp_path / "compare_raytrace" / "compare_raytrace.json").read_text())["doe"]
    assert ray["high (4 levels)"]["l1_raytrace_vs_raywave"][-1] > 2 * ray["low"]["l1_raytrace_vs_raywave"][-1]
    ep = json.loads((tmp_path / "compare_exit_pupil" / "compare_exit_pupil.json").read_text())
    assert max(ep["ideal_f4"]["l1_exit_pupil_vs_raywave"]) < 1e-2


@pytest.mark.slow  # CI time (README: Slow suite)
def test_render_demo_example(tmp_path):
    import json

    subprocess.run([sys.executable, str(ROOT / "examples" / "render_demo.py"), "--quick", "-o", str(tmp_path)],
                   check=True, capture_output=True)
    for name in ("input.png", "psf_map.png", "rendered.png", "rendered_noisy.png", "rendered_rgbd.png",
                 "comparison.png"):
        assert (tmp_path / name).stat().st_size > 20_000
    assert json.loads((tmp_path / "render_demo.json").read_text())["grid"] == [3, 3]
