"""The Trainer on two gloo processes (DistributedTrainer: micro-batches dealt to the ranks, ∂L/∂PSF summed,
PSF-map replay chunks split, gradients summed) makes the single-process optimizer steps, on a tiny ray-wave
hybrid lens (ideal f = 2 mm + 128² pixel DOE); only rank 0 writes the log and the checkpoints."""

import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raywave.training.config import load_config  # noqa: E402
from raywave.training.trainer import Trainer  # noqa: E402

CFG = """name: tiny_par
seed: 3
dtype: float64
checkpoint_every: 1
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.256, doe_distance: 0.5}}
optics: {{grid: [2, 2], eval_grid: [2, 2], ks: 16, rays: 20, chunk: 1,
          wavelengths: {{R: [0.62, 0.66], G: [0.50, 0.53], B: [0.45, 0.47]}}}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 8, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1}}
pre_stage: {{steps: 1}}
stage1: {{max_steps: 1, batch_size: 2, micro_batches: 2, warmup_steps: 0, lr_network: 0.001, loss: edof}}
stage2: {{max_steps: 1, batch_size: 3, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0, noise: true, loss: l1}}
"""
TOL = 1e-10


def params(tr):
    return [p.detach().clone() for p in list(tr.hl.doe.parameters()) + list(tr.net.parameters())]


def _worker(cfg_path, out):
    """One rank: a single stage-1 step, then a whole run (pre-stage, stage 1, stage 2)."""
    from raywave.training.parallel import DistributedTrainer

    out = Path(out)
    cfg = load_config(cfg_path)
    cfg.pre_stage.steps = 0
    tr = DistributedTrainer(cfg, out / "one", progress=False)
    tr.run(stop_after=1)
    torch.save(params(tr), out / f"one_{tr.rank}.pt")
    tr = DistributedTrainer(load_config(cfg_path), out / "full", progress=False)
    tr.run()
    torch.save(params(tr), out / f"full_{tr.rank}.pt")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, tiny_lens_file):
    from raywave.training.parallel import spawn

    d = tmp_path_factory.mktemp("par")
    (d / "tiny.yaml").write_text(CFG.format(lens=tiny_lens_file))
    spawn(2, _worker, str(d / "tiny.yaml"), str(d / "multi"))
    cfg = load_config(d / "tiny.yaml")
    cfg.pre_stage.steps = 0
    one = Trainer(cfg, d / "single_one", progress=False)
    one.run(stop_after=1)
    full = Trainer(load_config(d / "tiny.yaml"), d / "single_full", progress=False)
    full.run()
    return d, params(one), params(full)


def _maxdiff(a, b):
    return max(float((x - y).abs().max()) for x, y in zip(a, b))


def test_one_stage1_step_on_two_ranks_equals_one_process(runs):
    d, single, _ = runs
    r0, r1 = (torch.load(d / "multi" / f"one_{r}.pt", weights_only=True) for r in (0, 1))
    assert _maxdiff(r0, r1) == 0.0  # the ranks made the same step
    diff = _maxdiff(r0, single)
    print(f"one stage-1 step, 2 ranks vs 1 process: max |Δparam| = {diff:.3g}")
    assert diff <= TOL
    assert float(single[0].abs().max()) > 0  # the DOE moved


def test_whole_run_on_two_ranks_equals_one_process_and_rank0_writes(runs):
    d, _, single = runs
    r0, r1 = (torch.load(d / "multi" / f"full_{r}.pt", weights_only=True) for r in (0, 1))
    assert _maxdiff(r0, r1) == 0.0
    diff = _maxdiff(r0, single)
    print(f"pre-stage + stage 1 + stage 2 (noise), 2 ranks vs 1 process: max |Δparam| = {diff:.3g}")
    assert diff <= TOL
    log = [json.loads(x) for x in (d / "multi" / "full" / "log.jsonl").read_text().splitlines()]
    ref = [json.loads(x) for x in (d / "single_full" / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in log] == ["pre", "stage1", "stage2"]  # one writer: no duplicated lines
    for a, b in zip(log, ref):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-12, abs=1e-14)
    assert len(list((d / "multi" / "full" / "checkpoints").glob("step_*.pt"))) >= 1


@pytest.mark.slow
def test_cli_nproc_2_equals_one_process(runs, tmp_path):
    """``raywave train --nproc 2`` (designed + paraxial baseline, evaluation in the launching process) gives the
    single-process run's metrics and final parameters."""
    import os
    import subprocess

    d = runs[0]
    cfg = tmp_path / "cli.yaml"
    cfg.write_text((d / "tiny.yaml").read_text().replace("name: tiny_par", "name: tiny_par\nbaseline: paraxial\n"
                                                                                  "baseline_steps: 2"))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for out, extra in (("one", []), ("two", ["--nproc", "2"])):
        r = subprocess.run([sys.executable, "-m", "raywave.cli.main", "train", str(cfg), "-o", str(tmp_path / out),
                            "--quiet", *extra], capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stderr
    for sub in ("", "baseline"):
        a, b = (torch.load(sorted((tmp_path / o / sub / "checkpoints").glob("*.pt"))[-1], weights_only=True)["modules"]
                for o in ("one", "two"))
        assert max(float((a[m][k] - b[m][k]).abs().max()) for m in a for k in a[m]
                   if a[m][k].is_floating_point()) <= TOL
    ma, mb = (json.loads((tmp_path / o / "metrics.json").read_text()) for o in ("one", "two"))
    assert ma["baseline"]["mean"]["psnr"] == pytest.approx(mb["baseline"]["mean"]["psnr"], abs=1e-9)
    assert ma["designed"]["mean"]["psnr"] == pytest.approx(mb["designed"]["mean"]["psnr"], abs=1e-6)
