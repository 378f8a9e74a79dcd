"""Training-step benchmark: steps per second and peak memory of a training config's stage 1 (or pre-stage).

Builds the config's :class:`~raywave.training.trainer.Trainer` (``--set`` overrides as in ``raywave train``), runs
``--steps`` optimizer steps of the chosen stage (or until ``--seconds`` have passed, whichever comes first) and reports:

* ``setup_seconds``: the Trainer's construction (lens, network, data);
* ``first_step_seconds``: the first step (it fills the frozen lens's DOE-plane field cache);
* ``step_seconds_median`` and ``steps_per_second`` over the later steps;
* peak memory: the process's resident peak (``VmHWM``) and, on CUDA, ``torch.cuda.max_memory_allocated`` /
  ``max_memory_reserved`` over the whole run and over the later steps only.

Checkpoints are not written (``checkpoint_every`` is raised past the run), the run folder is a temporary one.

    python benchmarks/train_steps.py configs/aberration_paper.yaml --set device=cuda --set data.source=samples \\
        --steps 300 --seconds 180 -o train_steps.json

The paper configs read DIV2K; ``--set data.source=samples`` uses the bundled photo pool instead (the step's cost
does not depend on the photos).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time

from _memory import reset_peak, status_mb  # noqa: E402  (benchmarks/ is on sys.path)
from _report import emit_json  # noqa: E402


class _Budget(Exception):
    """Raised from the step log once the step count or the time budget is reached."""


def _trainer_class(steps: int, seconds: float, times: list, cuda_sync, peaks: dict):
    from raywave.training.trainer import Trainer

    class TimedTrainer(Trainer):
        """A Trainer whose step log also records the step times and ends the run on the budget."""

        def _log(self, rec: dict) -> None:
            super()._log(rec)
            cuda_sync()
            times.append(float(rec["time_s"]))
            if len(times) == 1 and self.device.type == "cuda":
                import torch

                peaks["first_step_allocated_mb"] = torch.cuda.max_memory_allocated(self.device) / 1e6
                torch.cuda.reset_peak_memory_stats(self.device)  # the later steps' own peak
            if len(times) >= steps or sum(times) >= seconds:
                raise _Budget

    return TimedTrainer


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="a training config (YAML), e.g. configs/aberration_paper.yaml")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--stage", choices=("pre", "stage1"), default="stage1", help="the stage to time (default stage1)")
    ap.add_argument("--steps", type=int, default=20, help="steps to time (default 20)")
    ap.add_argument("--seconds", type=float, default=300.0, help="stop after this many seconds of steps (300)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch

    from raywave.training.config import apply_overrides, load_config

    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = apply_overrides(load_config(args.config), args.overrides)
    cfg.checkpoint_every = 10 ** 9
    if args.stage == "stage1":
        cfg.pre_stage.steps = 0
    cfg.stage1.max_steps = args.steps if args.stage == "stage1" else 0
    device = torch.device(cfg.device)
    cuda = device.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(device)

    times: list[float] = []
    peaks: dict = {}
    reset_peak()
    base_mb = status_mb("VmRSS")
    with tempfile.TemporaryDirectory() as run_dir:
        t0 = time.perf_counter()
        trainer = _trainer_class(args.steps, args.seconds, times, sync, peaks)(cfg, run_dir, progress=False)
        sync()
        setup = time.perf_counter() - t0
        chunk = trainer.chunk
        setup_cuda = torch.cuda.max_memory_allocated(device) / 1e6 if cuda else None
        t1 = time.perf_counter()
        try:
            trainer.run(resume=False)
        except _Budget:
            pass
        sync()
        wall = time.perf_counter() - t1
    later = times[1:]
    med = statistics.median(later) if later else None
    out = {
        "benchmark": "train_steps", "config": args.config, "overrides": args.overrides, "stage": args.stage,
        "device": str(device), "device_name": torch.cuda.get_device_name(device) if cuda else platform.processor(),
        "threads": torch.get_num_threads(), "torch": torch.__version__, "python": platform.python_version(),
        "grid": list(cfg.optics.grid), "wavelengths_per_psf_map": sum(len(v) for v in cfg.optics.wavelengths.values()),
        "ks": cfg.optics.ks, "batch_size": cfg.stage1.batch_size, "patch_size": cfg.data.patch_size,
        "replay": cfg.optics.replay, "chunk_setting": cfg.optics.chunk, "chunk_field_points": chunk,
        "steps": len(times), "setup_seconds": setup, "run_seconds": wall,
        "first_step_seconds": times[0] if times else None, "step_seconds_median": med,
        "step_seconds": times, "steps_per_second": 1.0 / med if med else None,
        "peak_rss_mb": status_mb("VmHWM") - base_mb,
    }
    if cuda:
        out["cuda_setup_peak_allocated_mb"] = setup_cuda
        out["cuda_first_step_peak_allocated_mb"] = peaks.get("first_step_allocated_mb")
        out["cuda_steps_peak_allocated_mb"] = torch.cuda.max_memory_allocated(device) / 1e6
        out["cuda_steps_peak_reserved_mb"] = torch.cuda.max_memory_reserved(device) / 1e6
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
