"""The training loop on a tiny ray-wave hybrid lens (ideal f = 2 mm lens + 128² pixel DOE): all stages run and
write the run folder; replay and full graph give the same update; the CLI trains and evaluates; a run killed
at a random moment resumes from its last checkpoint with the same results as an uninterrupted run."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from raywave.training.config import load_config
from raywave.training.trainer import Trainer

CFG = """name: tiny
seed: 1
dtype: float64
checkpoint_every: 2
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.256, doe_distance: 0.5}}
optics: {{grid: [2, 2], eval_grid: [3, 3], ks: 16, rays: 20}}
data: {{source: dead_leaves, patch_size: 32, dead_leaves_count: 8, eval_size: 48}}
network: {{kind: unet, width: 4, depth: 1}}
pre_stage: {{steps: 2}}
stage1: {{max_steps: {s1}, batch_size: 2, micro_batches: 2, warmup_steps: 1, lr_network: 0.001}}
stage2: {{max_steps: 2, batch_size: 2, warmup_steps: 0, lr_doe: 0.0, lr_lens: 0.0, noise: true}}
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, tiny_lens_file):
    """A tiny lens file (ideal f = 2 mm, F/8, 0.2 mm sensor of 2 µm pixels) and its config."""

    d = tmp_path_factory.mktemp("tiny")
    (d / "tiny.yaml").write_text(CFG.format(lens=tiny_lens_file, s1=3))
    (d / "tiny_long.yaml").write_text(CFG.format(lens=tiny_lens_file, s1=8))
    return d


def params(tr):
    return [p.detach().clone() for p in list(tr.hl.doe.parameters()) + list(tr.net.parameters())]


def test_all_stages_run_and_write_the_run_folder(tiny, tmp_path):
    cfg = load_config(tiny / "tiny.yaml")
    tr = Trainer(cfg, tmp_path / "run", progress=False)
    phase0 = tr.hl.doe.phase_map.detach().clone()
    assert tr.run() == {"stage": "done", "step": 0}
    recs = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in recs] == ["pre"] * 2 + ["stage1"] * 3 + ["stage2"] * 2
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in recs)
    assert not torch.equal(tr.hl.doe.phase_map.detach(), phase0)  # the DOE was trained
    m = tr.evaluate()
    assert set(m) == {"depth=inf/centre", "depth=inf/edge", "mean"}
    assert 0 < m["mean"]["ssim"] <= 1 and m["mean"]["psnr"] > 5
    final = tr.export()
    assert {p.name for p in final.iterdir()} >= {"lens.json", "doe_phase.npy", "doe.pt", "masks"}
    assert (final / "masks" / "masks.gds").is_file()
    report = json.loads((final / "masks" / "report.json").read_text())
    assert report["levels"] == 16 and report["evaluated_as_fabricated"] is False  # a continuous design
    from raywave.assembly.build import load_hybrid

    hl = load_hybrid(final / "lens.json")  # the exported lens file reads back with its DOE
    assert torch.allclose(hl.doe.phase(0.55, None, 1).detach(), tr.hl.doe.phase(0.55, None, 1).detach())
    assert load_config(tmp_path / "run" / "config.yaml") == cfg
    # a finished run run again (raywave train on its folder) holds the trained modules, not fresh ones
    again = Trainer(cfg, tmp_path / "run", progress=False)
    assert again.run() == {"stage": "done", "step": 0}
    for a, b in zip(params(again), params(tr)):
        assert torch.equal(a, b)
    assert len((tmp_path / "run" / "log.jsonl").read_text().splitlines()) == len(recs)  # nothing re-trained


@pytest.mark.parametrize("jitter", [0.0, 1.0])
def test_replay_and_full_graph_give_the_same_step(tiny, tmp_path, jitter):
    """One stage-1 step (two micro-batches) through the replay and through the full graph: same DOE and
    network after the Adam update (to 1e-9: Adam divides by √v, which amplifies rounding where g ≈ 0); also
    with jittered nodes (the replay recomputes the PSFs at the step's shifted nodes)."""
    cfg = load_config(tiny / "tiny.yaml")
    cfg.pre_stage.steps = 0
    cfg.stage1.max_steps = 1
    cfg.optics.field_jitter = jitter
    out = []
    for replay in (True, False):
        cfg.optics.replay = replay
        tr = Trainer(cfg, tmp_path / f"r{replay}", progress=False)
        tr.run(stop_after=1)
        out.append(params(tr))
    for a, b in zip(*out):
        assert torch.allclose(a, b, rtol=0, atol=1e-9)
    assert not torch.equal(out[0][0], torch.zeros_like(out[0][0]))


def test_config_errors_reach_the_cli(tiny, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("stage1: {lr_dOE: 0.1}\n")
    r = subprocess.run([sys.executable, "-m", "raywave.cli.main", "train", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown key 'stage1.lr_dOE'" in r.stderr and "bad.yaml" in r.stderr


def test_cli_overrides_and_a_missing_data_folder(tmp_path):
    """``--set`` reaches the config (a typo is named); the paper configs' DIV2K folder, when absent, is an error
    that names the folder (nothing is trained, no traceback)."""
    from pathlib import Path

    paper = Path(__file__).parent.parent / "configs" / "edof_paper.yaml"
    cmd = [sys.executable, "-m", "raywave.cli.main", "train", str(paper), "-o", str(tmp_path / "run")]
    r = subprocess.run(cmd + ["--set", "data.rot=/x"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown key 'data.rot'" in r.stderr
    missing = tmp_path / "no_DIV2K"
    r = subprocess.run(cmd + ["--set", f"data.root={missing}"], capture_output=True, text=True)
    assert r.returncode == 2 and str(missing) in r.stderr and "Traceback" not in r.stderr
    assert not list((tmp_path / "run").glob("checkpoints/*"))


def _cli(*args, **kw):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "raywave.cli.main", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


@pytest.mark.slow
def test_killed_run_resumes_with_identical_results(tiny, tmp_path):
    """Uninterrupted CLI run vs a run killed (SIGKILL) right after a stage-1 checkpoint and resumed."""
    cfg = str(tiny / "tiny_long.yaml")
    ref = _cli("train", cfg, "-o", str(tmp_path / "ref"), "--no-baseline", "--quiet")
    killed = _cli("train", cfg, "-o", str(tmp_path / "run"), "--no-baseline", "--quiet")
    ck = tmp_path / "run" / "checkpoints"
    t0 = time.time()
    while time.time() - t0 < 120:
        # global step 6 = stage-1 step 4 of 8 (the pre-stage has 2)
        if (ck / "step_000006.pt").exists():
            killed.send_signal(signal.SIGKILL)
            break
        if killed.poll() is not None:
            break
        time.sleep(0.02)
    killed.wait()
    assert killed.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    log = (tmp_path / "run" / "log.jsonl").read_text().splitlines()
    assert 6 <= len(log) < 12  # it died in stage 1 (possibly after more steps than the checkpoint holds)
    resumed = _cli("train", cfg, "-o", str(tmp_path / "run"), "--no-baseline", "--quiet")
    assert resumed.wait() == 0, resumed.stderr.read()
    assert ref.wait() == 0, ref.stderr.read()
    a = torch.load(sorted((tmp_path / "ref" / "checkpoints").glob("*.pt"))[-1], weights_only=True)
    b = torch.load(sorted((tmp_path / "run" / "checkpoints").glob("*.pt"))[-1], weights_only=True)
    diffs = {k: float((a["modules"][m][k] - b["modules"][m][k]).abs().max())
             for m in ("hybrid", "net") for k in a["modules"][m] if a["modules"][m][k].is_floating_point()}
    print("max |resumed − uninterrupted| per tensor:", max(diffs.values()))
    # CPU reductions may round differently between processes (SIMD paths depend on buffer alignment), so the
    # comparison allows last-bit differences; in practice they are 0 or ~1e-16
    assert max(diffs.values()) <= 1e-12
    ma = json.loads((tmp_path / "ref" / "metrics.json").read_text())
    mb = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert ma["designed"]["mean"]["psnr"] == pytest.approx(mb["designed"]["mean"]["psnr"], abs=1e-9)


@pytest.fixture(scope="module")
def straight_params(tiny, tmp_path_factory):
    """Parameters after an uninterrupted run of tiny.yaml (shared by the resume tests)."""
    tr = Trainer(load_config(tiny / "tiny.yaml"), tmp_path_factory.mktemp("straight"), progress=False)
    tr.run()
    return params(tr)


@pytest.mark.parametrize("stop", [2, 5])  # in-process: the fast counterpart of the killed-run test
def test_resume_in_process_at_a_stage_boundary_and_mid_stage(tiny, tmp_path, stop, straight_params):
    """Stop after ``stop`` steps (2: right at the end of the pre-stage; 5: stage-1 step 3, one step after its
    last checkpoint, which the resumed run redoes), resume in a fresh Trainer: same parameters as a straight run."""
    cfg = load_config(tiny / "tiny.yaml")
    first = Trainer(cfg, tmp_path / "b", progress=False)
    first.run(stop_after=stop)
    second = Trainer(cfg, tmp_path / "b", progress=False)
    second.run()
    for a, b in zip(straight_params, params(second)):
        assert torch.allclose(a, b, rtol=0, atol=1e-12)


def test_field_jitter_shifts_the_whole_grid_within_a_cell(tiny, tmp_path):
    """``optics.field_jitter``: each step's nodes are the cell centres shifted by one offset (within ±jitter/2
    of a cell), their field angles those of the shifted sensor points; the same generator state gives the same
    nodes (replayable); 0 gives the fixed grid; a value outside [0, 1] is an error naming the key."""
    from raywave.imaging.psfmap import fields_at, normalised_grid

    cfg = load_config(tiny / "tiny.yaml")
    fixed = Trainer(cfg, tmp_path / "fixed", progress=False)
    f0, p0 = fixed.step_nodes()
    assert torch.equal(f0, fixed.fields) and torch.equal(p0, fixed.positions)
    cfg.optics.field_jitter = 0.5
    tr = Trainer(cfg, tmp_path / "jit", progress=False)
    base = normalised_grid(tr.grid)
    seen = []
    for seed in range(6):
        fields, pos = tr.step_nodes(torch.Generator().manual_seed(seed))
        off = pos - base
        assert torch.allclose(off, off[:1, :1].expand_as(off), atol=1e-15)  # one shift for the whole grid
        assert float(off.abs().max()) <= 0.25 * 2 / 2  # ±jitter/2 of a cell (cells 1 wide on a 2×2 grid)
        half = torch.tensor([0.5 * tr.sensor_size[0], 0.5 * tr.sensor_size[1]], dtype=torch.float64)
        expect = fields_at(tr.hl, pos * half, depth=tr.depths[0]).reshape(-1, 2)
        assert torch.allclose(fields, expect, rtol=0, atol=1e-12)
        seen.append(off[0, 0])
        again, _ = tr.step_nodes(torch.Generator().manual_seed(seed))
        assert torch.equal(again, fields)
    assert len({tuple(o.tolist()) for o in seen}) == 6
    cfg.optics.field_jitter = 1.5
    with pytest.raises(ValueError, match="optics.field_jitter must be in"):
        Trainer(cfg, tmp_path / "bad", progress=False)


@pytest.mark.slow  # CI time (README: Slow suite)
def test_a_jittered_run_resumes_with_identical_results(tiny, tmp_path):
    """The node offsets come from the run's generator, so a run stopped mid-stage resumes exactly."""
    cfg = load_config(tiny / "tiny.yaml")
    cfg.optics.field_jitter = 1.0
    straight = Trainer(cfg, tmp_path / "a", progress=False)
    straight.run()
    first = Trainer(cfg, tmp_path / "b", progress=False)
    first.run(stop_after=5)
    second = Trainer(cfg, tmp_path / "b", progress=False)
    second.run()
    for a, b in zip(params(straight), params(second)):
        assert torch.allclose(a, b, rtol=0, atol=1e-12)


def test_auto_chunk_on_the_cpu_takes_four_field_points(tiny, tmp_path):
    """``optics.chunk: auto`` resolves once, when the Trainer is built: on the CPU to 4 field points (the tiny 2×2 map:
    one chunk), and the step's map is split into chunks of that size."""
    from raywave.training.config import apply_overrides

    cfg = apply_overrides(load_config(tiny / "tiny.yaml"), ["optics.chunk=auto"])
    tr = Trainer(cfg, tmp_path, progress=False)
    assert tr.chunk == 4 and tr.optics_step().n_chunks == 1
    tr1 = Trainer(apply_overrides(load_config(tiny / "tiny.yaml"), ["optics.chunk=1"]), tmp_path / "one",
                  progress=False)
    assert tr1.chunk == 1 and tr1.optics_step().n_chunks == 4
