"""Multi-process training (``raywave.training.parallel``): time per stage-1 step on 1 … N gloo CPU processes.

Case: a config (default: a small built-in one: ideal f = 4 mm lens at F/8 with a trainable 256² pixel DOE of
2 µm pixels 0.5 mm behind it, 2 µm sensor pixels, a 4×4 stage-1 map of ks = 32 at one depth, batch 4 in 4
micro-batches of 48² dead-leaves patches, UNet width 8), pre-stage and stage 2 skipped, ``--steps`` stage-1
steps. Each process count runs in fresh processes (``parallel.spawn``); the time per step is the median of the
logged ``time_s`` after the first step (rank 0's clock; every rank makes the same step). Also prints the largest
parameter difference from the one-process run (the split step equals the single-process step up to the order
of floating-point sums). Each rank uses one thread: give it as many free cores as ranks.

    OMP_NUM_THREADS=1 python benchmarks/parallel_training.py [--nproc 1 2 4] [--steps 4] [--config CFG] [-o out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path
from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

CFG = """name: bench_parallel
seed: 0
dtype: float32
checkpoint_every: 1000
lens: {{file: {lens}, doe_pitch: 0.002, doe_size: 0.512, doe_distance: 0.5}}
optics: {{grid: [4, 4], eval_grid: [2, 2], ks: 32, rays: 32, chunk: 1}}
data: {{source: dead_leaves, patch_size: 48, dead_leaves_count: 64, eval_size: 48}}
network: {{kind: unet, width: 8, depth: 2}}
pre_stage: {{steps: 0}}
stage1: {{max_steps: {steps}, batch_size: 4, micro_batches: 4, warmup_steps: 0, lr_network: 0.001}}
stage2: {{max_steps: 0}}
"""


def _default_config(folder: Path, steps: int) -> Path:
    from raywave.io import write_lens_spec
    from raywave.lens.build import ideal_lens, lens_to_spec

    lens = ideal_lens(4.0, f_number=8.0, wavelengths=(0.55,))
    lens.set_sensor((0.4, 0.4), (200, 200))
    write_lens_spec(lens_to_spec(lens), folder / "lens.json")
    (folder / "bench.yaml").write_text(CFG.format(lens=folder / "lens.json", steps=steps))
    return folder / "bench.yaml"


def _rank(cfg_path: str, run_dir: str, steps: int) -> None:
    import torch

    from raywave.training.config import load_config
    from raywave.training.parallel import DistributedTrainer

    torch.set_num_threads(1)
    cfg = load_config(cfg_path)
    cfg.pre_stage.steps, cfg.stage1.max_steps, cfg.stage2.max_steps = 0, steps, 0
    tr = DistributedTrainer(cfg, run_dir, progress=False)
    tr.run(stop_after=steps)
    if tr.rank == 0:
        torch.save([p.detach() for p in list(tr.hl.doe.parameters()) + list(tr.net.parameters())],
                   Path(run_dir) / "params.pt")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nproc", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--config", default=None, help="a training config (default: the built-in small case)")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from raywave.training.parallel import spawn

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cfg = Path(args.config) if args.config else _default_config(tmp, args.steps)
        ref = None
        for n in args.nproc:
            run = tmp / f"n{n}"
            spawn(n, _rank, str(cfg), str(run), args.steps)
            times = [json.loads(x)["time_s"] for x in (run / "log.jsonl").read_text().splitlines()]
            params = torch.load(run / "params.pt", weights_only=True)
            ref = params if ref is None else ref
            diff = max(float((a - b).abs().max()) for a, b in zip(params, ref))
            results.append({"nproc": n, "step_s": statistics.median(times[1:] or times), "steps": len(times),
                            "max_param_diff_vs_first": diff})
    base = results[0]["step_s"]
    for r in results:
        r["speedup"] = base / r["step_s"]
    out = {"benchmark": "parallel_training", "config": args.config or "built-in", "cpu_count": os.cpu_count(),
           "python": platform.python_version(), "torch": torch.__version__, "results": results}
    emit_json(out, args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
