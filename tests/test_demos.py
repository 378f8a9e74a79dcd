"""The two shipped demo configs run to completion and their learned DOEs beat their baselines on the held-out
photos (issues 7 and 15). Slow: ``python -m pytest -m slow``.

* The aberration-correction demo (the README's main command) trains the DOE as the fabricated 16-level element,
  reconstructs with the PSF-aware multi-Wiener deconvolution + network and trains the ablation's plain networks;
  measured numbers in docs/training.md ("Demo results"); the tests assert issue 15's margins.
* The EDoF demo reconstructs with each depth's filter, blended by the depth the image's evidence favours
  (``deconv: wiener_select``), + network; the test asserts issue 15's +2 dB at every depth and its 0.5 dB over the
  paper's baseline pipeline (DOE and reconstruction built on the paraxial model; measured +2.58 / +1.85 / +2.13 dB
  at seeds 0 / 1 / 2: docs/training.md)."""

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
    names = {p.name for p in (run / "figures").iterdir()}
    assert "loss.png" in names, names
    for zone in ("edge", "centre"):  # one figure per zone, or per zone and depth (EDoF: _depth0, _depth1, ...)
        assert any(n.startswith(f"reconstructions_{zone}") for n in names), names
    assert (run / "final" / "lens.json").is_file() and (run / "final" / "masks" / "masks.gds").is_file()
    return json.loads((run / "metrics.json").read_text())


@pytest.fixture(scope="module")
def aberration(tmp_path_factory):
    run = tmp_path_factory.mktemp("demo") / "aberration_demo"
    return run, _train("aberration_demo", run)


@pytest.mark.slow
def test_aberration_demo_restores_and_beats_its_baseline(aberration):
    run, m = aberration
    d = m["designed"]["mean"]
    assert d["psnr"] > d["psnr_input"] + 2.0, d            # the PSF-aware reconstruction restores (+4.42 dB measured)
    assert d["psnr_deconv"] > d["psnr_input"] + 2.5, d
    assert d["psnr"] > d["psnr_network_only"] + 1.5, d     # the deconvolution is what restores, not the small network
    assert m["gain_db"]["mean"] > 0, m["gain_db"]           # designed 16-level DOE vs blank, same reconstruction
    assert m["gain_db"]["depth=inf/edge"] > 0.3, m["gain_db"]
    report = json.loads((run / "final" / "masks" / "report.json").read_text())
    assert report["levels"] == 16 and report["masks"] == 4 and report["evaluated_as_fabricated"] is True
    assert set(m["ablation"]["designed"]) == {"sensor image", "network only", "deconvolution only", "reconstruction"}


@pytest.mark.slow
def test_aberration_demo_reaches_the_issue_margins(aberration):
    """Issue 15: restored >= sensor image + 3 dB (measured +4.42 with the colour prior, 2026-11-27; +3.39
    without); the designed 16-level DOE, as exported, beats the blank DOE under the same reconstruction by
    >= 0.5 dB mean (+1.49) and >= 1 dB at the edge (+1.91)."""
    _, m = aberration
    d = m["designed"]["mean"]
    assert d["psnr"] >= d["psnr_input"] + 3.0
    assert m["gain_db"]["mean"] >= 0.5 and m["gain_db"]["depth=inf/edge"] >= 1.0


@pytest.mark.slow
def test_edof_demo_restores_every_depth_and_beats_the_paraxial_pipeline(tmp_path):
    """Measured (2026-11-28, the default exit-pupil stop edge, the colour prior, `deconv: wiener_select`: each
    depth's filter blended by the image's evidence): restored vs sensor image +3.42 / +3.66 / +2.76 dB at 200 mm /
    300 mm / 10 m (issue 15's bar: +2 dB at every depth); designed vs the paper's baseline (`baseline_reconstruction:
    paraxial`: the DOE designed, and the deconvolution and network built, with the paraxial model) +2.58 dB mean,
    at the edge +4.77 / +3.52 / +2.60 dB; seed 1: +3.37 / +3.62 / +2.83 and +1.85 dB; seed 2: +3.67 / +3.92 /
    +3.01 and +2.13 dB. The DOE alone (both deconvolved with their true PSFs, `psnr_deconv_true`) +0.50 / −0.11 /
    +0.21 dB at seeds 0 / 1 / 2: reported, not asserted (docs/training.md)."""
    run = tmp_path / "edof_demo"
    m = _train("edof_demo", run)
    keys = {f"depth={d}/{z}" for d in ("200", "300", "10000") for z in ("centre", "edge")} | {"mean"}
    assert set(m["designed"]) == keys and set(m["baseline"]) == keys
    assert (run / "baseline" / "baseline_design.json").is_file()
    d = m["designed"]
    for depth in ("200", "300", "10000"):
        gain = sum(d[f"depth={depth}/{z}"]["psnr"] - d[f"depth={depth}/{z}"]["psnr_input"]
                   for z in ("centre", "edge")) / 2
        assert gain >= 2.0, (depth, gain)                   # issue 15: restored >= sensor image + 2 dB, every depth
        assert m["gain_db"][f"depth={depth}/edge"] > 1.0, m["gain_db"]  # the paraxial model misplaces edge PSFs
    assert m["gain_db"]["mean"] >= 0.5, m["gain_db"]        # issue 15: designed vs the paraxial pipeline
    b = m["baseline"]["mean"]
    assert b["psnr_deconv_true"] > b["psnr_deconv"] + 1.0, b  # the paraxial PSFs, not the paraxial DOE, cost most
    assert "deconvolution only, true PSFs" in m["ablation"]["baseline"]
    assert d["mean"]["psnr_deconv"] > d["mean"]["psnr_network_only"] + 1.5, d["mean"]
    report = json.loads((run / "final" / "masks" / "report.json").read_text())
    assert report["levels"] == 16 and report["evaluated_as_fabricated"] is True
