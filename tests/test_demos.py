"""The two shipped demo configs run to completion (issue 7's "must show") and their learned DOEs beat their
baselines on the held-out photos: the aberration-correction demo its blank DOE, the EDoF demo the DOE designed
with the paraxial wave model. Slow (about 9 and 26 minutes on 2 CPU cores): ``python -m pytest -m slow``.

Both demos' networks are small (width 12) and trained briefly: they change their inputs little, so the gains
are optical, and the tests check the unrestored sensor images as well (docs/training.md, "Demo results")."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

CONFIGS = Path(__file__).parent.parent / "configs"


def _train(name, run):
    r = subprocess.run([sys.executable, "-m", "raywave.cli.main", "train", str(CONFIGS / f"{name}.yaml"), "-o",
                        str(run), "--quiet"], capture_output=True, text=True, env={**os.environ})
    assert r.returncode == 0, r.stderr[-3000:]
    assert {p.name for p in (run / "figures").iterdir()} >= {"loss.png", "reconstructions_edge.png"}
    assert (run / "final" / "lens.json").is_file() and (run / "final" / "doe_masks.npy").is_file()
    return json.loads((run / "metrics.json").read_text())


@pytest.mark.slow
def test_aberration_demo_beats_its_baseline(tmp_path):
    m = _train("aberration_demo", tmp_path / "aberration_demo")
    assert m["gain_db"]["mean"] > 0, m["gain_db"]
    assert m["designed"]["mean"]["ssim"] > m["baseline"]["mean"]["ssim"]
    # the gain is optical: the unrestored sensor images gain too
    assert m["designed"]["mean"]["psnr_input"] > m["baseline"]["mean"]["psnr_input"]


@pytest.mark.slow
def test_edof_demo_beats_the_paraxially_designed_doe(tmp_path):
    """Measured: designed 19.82 dB / SSIM 0.523 vs paraxial 19.37 / 0.511 (+0.45 dB); the gain is off axis
    (edge +1.16, +1.02, +0.65 dB at 200 mm, 300 mm, 10 m; centre within ±0.08 dB), where the paraxial model
    cannot see the lens's aberrations."""
    m = _train("edof_demo", tmp_path / "edof_demo")
    keys = {f"depth={d}/{z}" for d in ("200", "300", "10000") for z in ("centre", "edge")} | {"mean"}
    assert set(m["designed"]) == keys and set(m["baseline"]) == keys
    assert (tmp_path / "edof_demo" / "baseline" / "baseline_design.json").is_file()
    assert m["gain_db"]["mean"] > 0, m["gain_db"]
    assert m["designed"]["mean"]["ssim"] > m["baseline"]["mean"]["ssim"]
    assert all(m["gain_db"][f"depth={d}/edge"] > 0 for d in ("200", "300", "10000")), m["gain_db"]
    assert m["designed"]["mean"]["psnr_input"] > m["baseline"]["mean"]["psnr_input"]  # optical
    for arm in ("designed", "baseline"):  # the fine-tuned networks do not make their inputs worse
        assert m[arm]["mean"]["psnr"] >= m[arm]["mean"]["psnr_input"], m[arm]["mean"]
