"""The paper's stage-2 PSF map (issue 43): ``optics.eval_grid`` nodes × all wavelengths of a training config
(``configs/aberration_paper.yaml``: 40 × 40 × 9 = 14,400 PSFs of the bundled asphere with its 3000² DOE of 1 µm
pixels, ks 64), computed as :class:`raywave.training.trainer.Trainer` computes it, in chunks, resumable.

The optics are the config's (:func:`raywave.training.trainer.build_hybrid`: a zero-phase learned DOE; the map's cost
does not depend on the phase). With ``--checkpoint DIR`` each finished chunk is written to DIR and a run interrupted
and started again with the same DIR computes only the rest (``raywave psfmap --checkpoint`` does the same); the
JSON then counts the PSFs this run computed and their CPU and wall time. ``--grid N`` computes a smaller N×N map of
the same optics (the per-PSF figures of the full map, an estimate of its time). ``--cache`` computes it through a
:class:`~raywave.imaging.DOEFieldCache` as the trainer's frozen-lens maps do (2 field points per call) instead of
the engine's own groups (512 sources per call).

    OMP_NUM_THREADS=1 python benchmarks/stage2_map.py [configs/aberration_paper.yaml] [--grid N] \\
        [--checkpoint DIR] [--threads 1] [--device cpu] [-o stage2_map.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
import warnings
from pathlib import Path

from _memory import peak_mb, reset_peak, rss_mb  # noqa: E402  (benchmarks/ is on sys.path)
from _report import emit_json  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", nargs="?", default="configs/aberration_paper.yaml")
    ap.add_argument("--grid", type=int, default=None, help="N×N nodes (default: the config's optics.eval_grid)")
    ap.add_argument("--checkpoint", default=None, metavar="DIR", help="resumable: finished chunks kept in DIR")
    ap.add_argument("--cache", action="store_true", help="through a DOEFieldCache, as the trainer's maps")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--progress", action="store_true", help="a tqdm bar (PSFs)")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch

    from raywave.imaging import DOEFieldCache, psf_map
    from raywave.imaging.color import ColorSpec
    from raywave.imaging.map_checkpoint import KEY_FILE
    from raywave.training.config import load_config
    from raywave.training.trainer import build_hybrid

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    oc = cfg.optics
    hl = build_hybrid(cfg.lens).to(args.device)
    wl = oc.wavelengths
    wls = ColorSpec([list(wl["R"]), list(wl["G"]), list(wl["B"])]).all_wavelengths().tolist()
    grid = (args.grid, args.grid) if args.grid else tuple(int(v) for v in oc.eval_grid)
    ks = int(oc.eval_ks) if getattr(oc, "eval_ks", None) else int(oc.ks)
    depths = [math.inf if d is None else float(d) for d in oc.depths]
    n_psfs = len(depths) * len(wls) * grid[0] * grid[1]
    done_before = 0
    warnings.simplefilter("ignore")
    with torch.no_grad():
        psf_map(hl, (1, 1), depths[:1], wls[:1], ks=ks)  # warm-up
    reset_peak()
    base = rss_mb()
    t_cpu, t_wall = time.process_time(), time.perf_counter()
    kw = {"cache": DOEFieldCache()} if args.cache else {}
    if args.checkpoint:
        kw["checkpoint"] = args.checkpoint
        done_before = len(list(Path(args.checkpoint).glob("d*.pt")))
    pm = psf_map(hl, grid, depths, wls, ks=ks, progress=args.progress, **kw)
    cpu, wall = time.process_time() - t_cpu, time.perf_counter() - t_wall
    chunks_total = None
    if args.checkpoint:
        key = json.loads((Path(args.checkpoint) / KEY_FILE).read_text())
        chunks_total = len(key["chunks"]) * len(depths)
        per_chunk = n_psfs / chunks_total
        computed = round((chunks_total - done_before) * per_chunk)
    else:
        computed = n_psfs
    out = {
        "benchmark": "stage2_map", "config": args.config, "grid": list(grid), "wavelengths": wls, "depths": depths,
        "ks": ks, "doe": list(hl.doe.shape), "doe_pitch_mm": float(hl.doe.pitch), "psfs": n_psfs,
        "psfs_computed_this_run": computed, "chunks": chunks_total, "chunks_done_before": done_before,
        "cache": args.cache, "device": args.device, "threads": torch.get_num_threads(),
        "cpu_s": round(cpu, 2), "wall_s": round(wall, 2),
        "cpu_s_per_psf": round(cpu / max(computed, 1), 4), "wall_s_per_psf": round(wall / max(computed, 1), 4),
        "peak_rss_mb_above_start": round(peak_mb() - base, 1),
        "finite": bool(torch.isfinite(pm.psf).all()), "psf_sum_min": float(pm.psf.sum((-2, -1)).min()),
        "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
    }
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    main()
