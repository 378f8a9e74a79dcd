"""A/B timing of the PSF map per PSF (issue 17): two source trees, runs interleaved, one process per run.

Each run builds the bundled ``hybrid_asphere``, warms up with a 1-PSF map (``grad``: and one PSF's forward +
backward; compiled loops, :mod:`raywave.utils.fused`, compile on first use), then times one N×N×3 map (R, G, B
channel centres, ks = 64, accurate mode, no autograd) and reports wall and CPU seconds (``process_time``, all
threads) per PSF. The trees alternate A, B, A, B, … so that a machine shared with other work loads both alike;
the medians are reported. Prints one JSON object (and writes it with ``-o``).

    python benchmarks/psf_ab.py --a /path/to/old/tree --b . [--grid 5] [--repeat 3] [--threads 1]
        [--stop-edge doe|exit_pupil] [-o out.json]

``--modes map,grad`` (issue 43) also times forward + backward (one model call of 8 field points × 3 λ at a time,
each followed by the backward of a weighted sum of its PSFs) and reports every PSF's relative L1 difference between
the trees (``max_rel_l1_per_psf``): issue 43's A/B is
``git worktree add /tmp/base d9ddfa8`` then
``python benchmarks/psf_ab.py --a /tmp/base --grid 10 --repeat 2 --threads 2 --modes map,grad --warm``.
``--warm`` runs the timed map (grad: its first call) once untimed first, so that the times hold no compiles of the
compiled loops' off-axis windows (a tree's first run on a machine compiles them cold, ~15 s each: main's first of
three runs on 2026-12-02 read 0.120 s per PSF, the next two 0.067 / 0.057 s); without it, give ``--repeat`` ≥ 2 and
read the runs after the first.

``--b-set MODULE.NAME=VALUE`` (repeatable) sets a module constant in tree B's runs before they build the lens (VALUE
a Python literal): e.g. ``--b-set raywave.hybrid.coherent.accurate.RIM_FOURIER=False`` switches off issue 47's
deliberate numeric change of the rim images' interpolation, so that the PSF difference left is the refactor's own.

Issue 17's bar (the 10×10×3 map ≥ 3× faster per PSF than at 17ade15, where it was filed; the DOE-plane edge,
that tree's default): ``git worktree add /tmp/old 17ade15`` then
``python benchmarks/psf_ab.py --a /tmp/old --grid 10 --repeat 2 --threads 2 --stop-edge doe``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

from _report import emit_json  # benchmarks/ is on sys.path

_CHILD = r"""
import json, sys, time, warnings
import torch
torch.set_num_threads(int(sys.argv[2]))
try:
    from raywave.assembly.build import load_hybrid
except ImportError:  # trees from before the assembly layer (e.g. 17ade15, where issue 17 was filed)
    from raywave.hybrid.build import load_hybrid
from raywave.lens.build import bundled_lens_path
from raywave.imaging import psf_map
import ast, importlib
for item in json.loads(sys.argv[6]):  # --b-set: module constants of this tree's run
    target, value = item.split("=", 1)
    mod, name = target.rsplit(".", 1)
    setattr(importlib.import_module(mod), name, ast.literal_eval(value))
n = int(sys.argv[1])
wls = (0.66, 0.53, 0.47)
edge = sys.argv[4]
warm = sys.argv[7] == "1"
hl = load_hybrid(bundled_lens_path("hybrid_asphere"), **({} if edge == "default" else {"stop_edge": edge}))
warnings.simplefilter("ignore")
psf_map(hl, (1, 1), wavelengths=wls[:1], ks=64)
if sys.argv[5] == "grad":  # forward + backward, one model call (8 field points × 3 λ) at a time, as the replay does
    from raywave.imaging.psfmap import field_grid
    f = field_grid(hl, (n, n)).reshape(-1, 2)
    # a warm-up call with its backward (compiled loops: the backward's own graphs compile on first use)
    hl.psf_result(f[:1], list(wls[:1]), ks=64).psf.sum().backward()
    w = torch.rand((n * n, 3, 64, 64), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    first = None
    if warm:  # the first call of 8 field points once untimed (its off-axis windows' compiles)
        t0 = time.perf_counter()
        (hl.psf_result(f[:8], list(wls), ks=64).psf * w[:8]).sum().backward()
        first = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    parts = []
    for s in range(0, f.shape[0], 8):
        r = hl.psf_result(f[s:s + 8], list(wls), ks=64)
        (r.psf * w[s:s + 8]).sum().backward()
        parts.append(r.psf.detach())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    psf = torch.cat(parts).transpose(0, 1).reshape(3, n, n, 64, 64)[None]
else:
    first = None
    if warm:  # the same map once untimed (its off-axis windows' compiles)
        t0 = time.perf_counter()
        psf_map(hl, (n, n), wavelengths=wls, ks=64)
        first = (time.perf_counter() - t0) / (n * n * len(wls))
    t0, c0 = time.perf_counter(), time.process_time()
    m = psf_map(hl, (n, n), wavelengths=wls, ks=64)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    psf = m.psf
torch.save(psf, sys.argv[3])
k = n * n * len(wls)
import raywave
print(json.dumps({"wall_per_psf": wall / k, "cpu_per_psf": cpu / k, "raywave": raywave.__file__,
                  "warm_up_wall_s": first}))
"""


def _run(tree: str, n: int, threads: int, out: str, edge: str = "default", grad: bool = False,
         sets: list | None = None, warm: bool = False) -> dict:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(tree), OMP_NUM_THREADS=str(threads))
    # run in the tree itself: ``python -c`` puts the working directory ahead of PYTHONPATH on sys.path
    res = subprocess.run([sys.executable, "-c", _CHILD, str(n), str(threads), out, edge, "grad" if grad else "map",
                          json.dumps(sets or []), "1" if warm else "0"], capture_output=True, text=True, env=env, cwd=os.path.abspath(tree))
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="tree A (the baseline; its raywave/ is imported)")
    ap.add_argument("--b", default=".", help="tree B")
    ap.add_argument("--grid", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--stop-edge", default="default",
                    help="doe / exit_pupil for both trees (default: each tree's own default edge)")
    ap.add_argument("--modes", default="map",
                    help="map (no grad), grad (forward + backward, 8 field points × 3 λ per call) or map,grad")
    ap.add_argument("--scratch", default="/tmp", help="folder for the runs' PSF files (one per mode and tree)")
    ap.add_argument("--b-set", action="append", default=[], metavar="MODULE.NAME=VALUE",
                    help="set a module constant in tree B's runs (repeatable; VALUE a Python literal)")
    ap.add_argument("--warm", action="store_true",
                    help="time a warm engine: the map (grad: its first call of 8 field points) run once untimed "
                         "first, so that neither tree's time holds compiles of its off-axis windows (a tree run "
                         "for the first time on a machine compiles them cold: ~15 s each)")
    ap.add_argument("-o", "--output")
    args = ap.parse_args()
    import torch

    out = {"benchmark": "psf_ab", "lens": "hybrid_asphere", "grid": [args.grid, args.grid], "wavelengths": 3, "ks": 64,
           "threads": args.threads, "stop_edge": args.stop_edge, "a": os.path.abspath(args.a),
           "b": os.path.abspath(args.b), "b_set": args.b_set, "warm": args.warm}
    for mode in args.modes.split(","):
        runs = {"a": [], "b": []}
        for r in range(args.repeat):
            for key in ("a", "b"):
                out_pt = os.path.join(args.scratch, f"raywave_psf_ab_{mode}_{key}.pt")
                runs[key].append(_run(getattr(args, key), args.grid, args.threads, out_pt, args.stop_edge,
                                      mode == "grad", args.b_set if key == "b" else None, args.warm))
                print(mode, key, r, runs[key][-1], file=sys.stderr, flush=True)
        a, b = (torch.load(os.path.join(args.scratch, f"raywave_psf_ab_{mode}_{k}.pt")) for k in ("a", "b"))
        rel_l1 = (a - b).abs().sum((-2, -1)) / a.abs().sum((-2, -1)).clamp_min(1e-300)  # per PSF
        med = {k: {m: statistics.median(x[m] for x in v) for m in ("wall_per_psf", "cpu_per_psf")}
               for k, v in runs.items()}
        out[mode] = {"runs": runs, "median": med, "speedup_wall": med["a"]["wall_per_psf"] / med["b"]["wall_per_psf"],
                     "speedup_cpu": med["a"]["cpu_per_psf"] / med["b"]["cpu_per_psf"],
                     "max_abs_psf_diff": float((a - b).abs().max()), "max_rel_l1_per_psf": float(rel_l1.max()),
                     "median_rel_l1_per_psf": float(rel_l1.median())}
    emit_json(out, args.output)


if __name__ == "__main__":
    main()
