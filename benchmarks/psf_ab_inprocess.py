"""A/B timing of the PSF map per PSF in ONE process: tree A's ``raywave`` imported as ``raywave_a`` (a renamed copy)
beside this tree's, their maps alternated (A, B, B, A, …), CPU and wall seconds per PSF.

On a shared machine whose load moves from minute to minute, two trees timed in alternating processes
(``benchmarks/psf_ab.py``) see different loads; here both see the same within seconds, so the ratio of their medians
is steadier (each tree warmed first: compiled loops, :mod:`raywave.utils.fused`, compile on first use). The PSFs of
the warm-up calls are compared (max |ΔPSF|, max relative L1 per PSF).

    python benchmarks/psf_ab_inprocess.py --a /tmp/x21/base [--grid 4] [--modes map,grad] [--repeat 4] [--threads 1]
        [-o out.json]

The copy of tree A (``--scratch``, default a temporary folder) has every ``raywave`` name in its Python files renamed
``raywave_a`` (the lens-file format tag kept): A's code, unchanged otherwise. ``--a-env NAME=VALUE`` sets an
environment variable during A's calls alone: ``--a . --a-env RAYWAVE_COMPILE=0`` times this tree's eager loops
against its compiled ones (:mod:`raywave.utils.fused` reads the variable at every call).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from _report import emit_json  # benchmarks/ is on sys.path

WLS = (0.66, 0.53, 0.47)


def renamed_copy(tree: str, scratch: str) -> str:
    """Tree ``tree``'s ``raywave/`` copied to ``scratch/raywave_a`` with its imports renamed; returns ``scratch``."""
    dst = Path(scratch) / "raywave_a"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(Path(tree) / "raywave", dst, ignore=shutil.ignore_patterns("__pycache__"))
    for f in dst.rglob("*.py"):
        text = re.sub(r"\braywave\b", "raywave_a", f.read_text())
        f.write_text(text.replace("raywave_a-", "raywave-"))  # the lens files' format tag ("raywave-lens")
    return scratch


def _engine(pkg: str):
    build = __import__(pkg + ".assembly.build", fromlist=["load_hybrid"])
    lenses = __import__(pkg + ".lens.build", fromlist=["bundled_lens_path"])
    imaging = __import__(pkg + ".imaging", fromlist=["psf_map"])
    psfmap = __import__(pkg + ".imaging.psfmap", fromlist=["field_grid"])
    return build.load_hybrid(lenses.bundled_lens_path("hybrid_asphere")), imaging.psf_map, psfmap.field_grid


def _run(engine, n: int, mode: str) -> torch.Tensor:
    """One N×N×3 map (``map``: no autograd; ``grad``: 8 field points × 3 λ a call, each with its backward)."""
    hl, psf_map, field_grid = engine
    if mode != "grad":
        return psf_map(hl, (n, n), wavelengths=WLS, ks=64).psf.reshape(-1, 64, 64)
    f = field_grid(hl, (n, n)).reshape(-1, 2)
    w = torch.rand((n * n, 3, 64, 64), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    parts = []
    for s in range(0, f.shape[0], 8):
        r = hl.psf_result(f[s:s + 8], list(WLS), ks=64)
        (r.psf * w[s:s + 8]).sum().backward()
        parts.append(r.psf.detach())
    return torch.cat(parts).transpose(0, 1).reshape(-1, 64, 64)


def _timed(engines: dict, key: str, a_env: dict, job: tuple):
    """``(PSFs, CPU s, wall s)`` of one map of tree ``key`` (``job`` = ``(grid, mode)``), with ``a_env`` set in the
    environment for tree A's."""
    saved = {name: os.environ.get(name) for name in a_env}
    if key == "a":
        os.environ.update(a_env)
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        psf = _run(engines[key], *job)
        return psf, time.process_time() - c0, time.perf_counter() - t0
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="tree A (the baseline)")
    ap.add_argument("--grid", type=int, default=4)
    ap.add_argument("--modes", default="map")
    ap.add_argument("--repeat", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--scratch", default=None)
    ap.add_argument("--a-env", action="append", default=[], metavar="NAME=VALUE",
                    help="an environment variable set during tree A's calls alone (repeatable)")
    ap.add_argument("-o", "--output")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    scratch = args.scratch or tempfile.mkdtemp(prefix="raywave_ab_")
    sys.path.insert(0, renamed_copy(args.a, scratch))
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    engines = {"a": _engine("raywave_a"), "b": _engine("raywave")}
    a_env = dict(item.split("=", 1) for item in args.a_env)
    out = {"benchmark": "psf_ab_inprocess", "lens": "hybrid_asphere", "grid": [args.grid, args.grid], "wavelengths": 3,
           "ks": 64, "threads": args.threads, "a": os.path.abspath(args.a),
           "b": str(Path(__file__).resolve().parents[1]), "a_env": a_env}
    k = 3 * args.grid * args.grid
    for mode in args.modes.split(","):
        psf = {key: _timed(engines, key, a_env, (args.grid, mode))[0] for key in engines}  # warm-up; PSFs compared
        runs = {"a": [], "b": []}
        for r in range(args.repeat):
            for key in ("a", "b") if r % 2 == 0 else ("b", "a"):
                _, cpu, wall = _timed(engines, key, a_env, (args.grid, mode))
                runs[key].append({"cpu_per_psf": cpu / k, "wall_per_psf": wall / k})
                print(mode, key, r, runs[key][-1], file=sys.stderr, flush=True)
        med = {key: {m: statistics.median(x[m] for x in v) for m in ("wall_per_psf", "cpu_per_psf")}
               for key, v in runs.items()}
        a, b = psf["a"], psf["b"]
        rel_l1 = (a - b).abs().sum((-2, -1)) / a.abs().sum((-2, -1)).clamp_min(1e-300)
        out[mode] = {"runs": runs, "median": med, "speedup_cpu": med["a"]["cpu_per_psf"] / med["b"]["cpu_per_psf"],
                     "speedup_wall": med["a"]["wall_per_psf"] / med["b"]["wall_per_psf"],
                     "max_abs_psf_diff": float((a - b).abs().max()), "max_rel_l1_per_psf": float(rel_l1.max())}
    emit_json(out, args.output)


if __name__ == "__main__":
    main()
