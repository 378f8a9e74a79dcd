"""Training with a DOE inside the lens (issue 46): the PSF map and its replay on a MidSystemLens, the Trainer's
stages, the export, and configs/midsystem_stop_doe.yaml. A tiny lens keeps it fast: an ideal f = 2 mm lens at F/8
(the stop), a plane air surface 0.3 mm after it, the sensor 2 mm behind the lens; the learned DOE at the stop."""

import json
from pathlib import Path

import pytest
import torch

from raywave.hybrid.midsystem import MidSystemLens
from raywave.imaging.psfmap import psf_map, psf_map_points
from raywave.training.config import load_config
from raywave.training.trainer import Trainer, build_hybrid

CFG = """name: stop_doe
seed: 1
dtype: float64
checkpoint_every: 2
lens: {{file: {lens}, doe_after: 0, doe_distance: 0.0, doe_pitch: 0.01, doe_size: 0.3}}
optics: {{grid: [2, 2], eval_grid: [2, 2], ks: 16, wavelengths: {{R: [0.6], G: [0.55], B: [0.5]}}}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 4, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1}}
pre_stage: {{steps: 1, lr_doe: 0.01}}
stage1: {{max_steps: 2, batch_size: 2, warmup_steps: 1, lr_doe: 0.005, lr_network: 0.001}}
stage2: {{max_steps: 1, batch_size: 2, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0}}
"""


@pytest.fixture(scope="module")
def stop_cfg(tmp_path_factory):
    from raywave.io import write_lens_spec
    from raywave.lens.build import ideal_lens, lens_to_spec

    d = tmp_path_factory.mktemp("stop_doe")
    lens = ideal_lens(2.0, f_number=8.0, wavelengths=(0.55,))
    lens.set_sensor((0.2, 0.2), (100, 100))
    spec = lens_to_spec(lens)
    spec["surfaces"][0]["thickness"] = 0.3
    spec["surfaces"].append({"type": "standard", "radius": "inf", "thickness": 1.7, "material": "air"})
    write_lens_spec(spec, d / "stop.json")
    (d / "stop.yaml").write_text(CFG.format(lens=d / "stop.json"))
    return d / "stop.yaml"


def test_build_hybrid_places_the_learned_doe_at_the_stop(stop_cfg):
    ml = build_hybrid(load_config(stop_cfg).lens)
    assert isinstance(ml, MidSystemLens) and (ml.after, ml.distance) == (0, 0.0)
    assert ml.doe.shape == (30, 30) and ml.doe.pitch == 0.01 and float(ml.doe.phase_map.detach().abs().max()) == 0.0
    assert ml.sensor_pitch == pytest.approx(0.002)  # the lens file's pixel
    assert not any(p.requires_grad for p in ml.lens.parameters())
    lc = load_config(stop_cfg).lens
    lc.doe, lc.doe_terms = "zernike", 6  # a smooth learned DOE: Noll j = 1..6 over the grid's inscribed disk
    zl = build_hybrid(lc)
    assert type(zl.doe).__name__ == "ZernikeDOE" and zl.doe.coefficients.shape == (6,) and zl.doe.shape == (30, 30)


def test_psf_map_and_its_replay_on_a_midsystem_lens(stop_cfg):
    """psf_map takes a MidSystemLens as any PSF model (fields from its lens, PSFs summing to 1, centres on the
    chief rays); psf_map_points recomputes a node with autograd and the DOE gets a gradient."""
    ml = build_hybrid(load_config(stop_cfg).lens)
    with torch.no_grad():  # a weak lens and a tilt (2 rad at the rim of the 0.125 mm stop): a PSF that is not flat
        x = (torch.arange(30, dtype=torch.float64) - 14.5) * 0.01
        ml.doe.phase_map.copy_(2.0 * (x[None, :] ** 2 + x[:, None] ** 2) / 0.125 ** 2 + 1.0 * x[None, :] / 0.125)
    pm = psf_map(ml, grid=(2, 2), wavelengths=[0.55], ks=16)
    assert pm.psf.shape == (1, 1, 2, 2, 16, 16)
    assert torch.allclose(pm.psf.sum((-1, -2)), torch.ones(1, 1, 2, 2, dtype=pm.psf.dtype), atol=1e-12)
    # the nodes sit at the sensor's cell centres (±0.05 mm) and the chief rays land there
    assert torch.allclose(pm.centers[0, 0].abs(), torch.full((2, 2, 2), 0.05, dtype=torch.float64), atol=2e-3)
    res = psf_map_points(ml, pm.flat_fields()[:1], [0.55], ks=16)
    assert torch.allclose(res.psf.detach(), pm.psf[0, :, 0, 0][None], atol=1e-12)  # the same PSF, now with a graph
    (res.psf * torch.linspace(0, 1, 16, dtype=torch.float64)).sum().backward()
    g = ml.doe.phase_map.grad
    assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().max()) > 0


@pytest.mark.slow  # ~90 s on a busy 2-core machine
def test_trainer_runs_and_exports_a_midsystem_doe(stop_cfg, tmp_path):
    from raywave.assembly.midsystem import load_midsystem

    cfg = load_config(stop_cfg)
    tr = Trainer(cfg, tmp_path / "run", progress=False)
    assert tr.cache is None  # the DOE inside the lens shapes the fields: nothing to cache
    phase0 = tr.hl.doe.phase_map.detach().clone()
    assert tr.run() == {"stage": "done", "step": 0}
    recs = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines() if '"stage"' in x]
    assert [r["stage"] for r in recs] == ["pre", "stage1", "stage1", "stage2"]
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in recs)
    assert not torch.equal(tr.hl.doe.phase_map.detach(), phase0)  # the DOE at the stop was trained
    final = tr.export()
    spec = json.loads((final / "lens.json").read_text())
    assert spec["surfaces"][0]["doe"]["distance"] == 0.0 and "doe" not in spec
    back = load_midsystem(final / "lens.json")  # the exported lens reads back with its DOE at the stop
    assert (back.after, back.distance) == (0, 0.0)
    assert torch.allclose(back.doe.phase(0.55, None, 1).detach(), tr.hl.doe.phase(0.55, None, 1).detach())


def test_replay_and_full_graph_give_the_same_step(stop_cfg, tmp_path):
    cfg = load_config(stop_cfg)
    cfg.pre_stage.steps = 0
    cfg.stage1.max_steps = 1
    cfg.optics.grid = [1, 2]
    out = []
    for replay in (True, False):
        cfg.optics.replay = replay
        tr = Trainer(cfg, tmp_path / f"r{replay}", progress=False)
        tr.run(stop_after=1)
        out.append([p.detach().clone() for p in list(tr.hl.doe.parameters()) + list(tr.net.parameters())])
    for a, b in zip(*out):
        assert torch.allclose(a, b, rtol=0, atol=1e-9)
    assert float(out[0][0].abs().max()) > 0


@pytest.mark.slow
def test_the_example_config_trains(tmp_path):
    """configs/midsystem_stop_doe.yaml (the bundled asphere, a pixel DOE at its stop) runs two steps."""
    cfg = load_config(Path(__file__).parent.parent / "configs" / "midsystem_stop_doe.yaml")
    cfg.optics.grid = [2, 2]
    cfg.optics.ks = 16
    cfg.data.patch_size = 32
    cfg.pre_stage.steps = 1
    cfg.stage1.max_steps = 1
    tr = Trainer(cfg, tmp_path / "run", progress=False)
    assert isinstance(tr.hl, MidSystemLens) and (tr.hl.after, tr.hl.distance) == (0, 0.0)
    c0 = tr.hl.doe.coefficients.detach().clone()  # 15 Zernike terms
    tr.run(stop_after=2)
    recs = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines() if '"stage"' in x]
    assert [r["stage"] for r in recs] == ["pre", "stage1"]
    assert not torch.equal(tr.hl.doe.coefficients.detach(), c0)


@pytest.mark.slow  # several minutes: two end-to-end designs on the bundled asphere
def test_the_doe_at_stop_example_runs(tmp_path):
    import subprocess
    import sys

    root = Path(__file__).parent.parent
    subprocess.run([sys.executable, str(root / "examples" / "doe_at_stop.py"), "-o", str(tmp_path), "--pre", "1",
                    "--stage1", "1", "--stage2", "1"], check=True, capture_output=True)
    report = json.loads((tmp_path / "doe_at_stop.json").read_text())
    assert report["DOE at the stop"]["doe"]["type"] == "MidSystemLens"
    assert report["DOE before the sensor"]["doe"]["type"] == "HybridLens"
    assert isinstance(report["psnr_difference_stop_minus_sensor_db"], float)
    assert (tmp_path / "figures" / "psf_map_depth0.png").stat().st_size > 10_000
    assert (tmp_path / "figures" / "reconstructions_centre.png").stat().st_size > 10_000
