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
