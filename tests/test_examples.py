"""The example scripts run and write their figures."""

import subprocess
import sys
from pathlib import Path

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
