"""Forward + backward of the first model calls of the bundled ``hybrid_asphere``'s N×N×3 map in two source trees
(issue 43, xxviii): as ``psf_ab.py --modes grad``'s child (8 field points × 3 λ a call, the backward of a weighted
sum of the PSFs, ks 64, default edge), one fresh process per tree. Reports per call the forward's and the backward's
wall seconds and the compiled loops' recompilations, and between the trees every PSF's relative L1 difference and
the largest relative difference of the accumulated gradients of every lens and DOE parameter (``max |gA − gB| /
max |gA|`` per parameter). Prints JSON; ``-o`` writes it.

    python benchmarks/grad_ab.py --a /path/to/base --b . [--grid 10] [--calls 3] [--threads 1] [-o out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

_CHILD = r"""
import json, sys, time, warnings
import torch
torch.set_num_threads(int(sys.argv[3]))
from torch._dynamo.utils import counters
from raywave.assembly.build import load_hybrid
from raywave.lens.build import bundled_lens_path
from raywave.imaging import psf_map
from raywave.imaging.psfmap import field_grid
n, calls, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[4]
wls = [0.66, 0.53, 0.47]
hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
warnings.simplefilter("ignore")
psf_map(hl, (1, 1), wavelengths=wls[:1], ks=64)
f = field_grid(hl, (n, n)).reshape(-1, 2)
hl.psf_result(f[:1], wls[:1], ks=64).psf.sum().backward()
params = dict(hl.named_parameters())
for p in params.values():
    p.grad = None
w = torch.rand((n * n, 3, 64, 64), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
rows, parts = [], []
for c in range(calls):
    s = 8 * c
    g0 = counters["stats"]["unique_graphs"]
    t0 = time.perf_counter()
    r = hl.psf_result(f[s:s + 8], wls, ks=64)
    t1 = time.perf_counter()
    (r.psf * w[s:s + 8]).sum().backward()
    t2 = time.perf_counter()
    rows.append({"start": s, "forward_s": t1 - t0, "backward_s": t2 - t1,
                 "new_graphs": counters["stats"]["unique_graphs"] - g0})
    parts.append(r.psf.detach())
grads = {k: p.grad.detach().clone() for k, p in params.items() if p.grad is not None}
torch.save({"psf": torch.cat(parts), "grads": grads}, out)
import raywave
print(json.dumps({"calls": rows, "raywave": raywave.__file__, "params_with_grad": sorted(grads)}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True)
    ap.add_argument("--b", default=".")
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--calls", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--scratch", default="/tmp")
    ap.add_argument("-o", "--output")
    args = ap.parse_args()
    import torch

    res, files = {}, {}
    for key in ("a", "b"):
        tree = os.path.abspath(getattr(args, key))
        files[key] = os.path.join(args.scratch, f"raywave_grad_ab_{os.getpid()}_{key}.pt")
        env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS=str(args.threads))
        p = subprocess.run([sys.executable, "-c", _CHILD, str(args.grid), str(args.calls), str(args.threads),
                            files[key]], capture_output=True, text=True, env=env, cwd=tree)
        if p.returncode != 0:
            raise RuntimeError(p.stderr[-3000:])
        res[key] = json.loads(p.stdout.strip().splitlines()[-1])
        print(key, res[key], file=sys.stderr, flush=True)
    a, b = (torch.load(files[k]) for k in ("a", "b"))
    rel_l1 = (a["psf"] - b["psf"]).abs().sum((-2, -1)) / a["psf"].abs().sum((-2, -1)).clamp_min(1e-300)
    grads = {}
    for k, ga in a["grads"].items():
        gb = b["grads"].get(k)
        grads[k] = None if gb is None else float((ga - gb).abs().max() / ga.abs().max().clamp_min(1e-300))
    out = {"benchmark": "grad_ab", "lens": "hybrid_asphere", "grid": args.grid, "calls": args.calls,
           "threads": args.threads, "a": res["a"], "b": res["b"],
           "max_rel_l1_per_psf": float(rel_l1.max()), "psf_bitwise_equal": bool(torch.equal(a["psf"], b["psf"])),
           "grad_max_rel_diff": grads, "grad_max_rel_diff_overall": max((v for v in grads.values() if v is not None),
                                                                        default=None),
           "load_average": os.getloadavg()}
    for f in files.values():
        os.remove(f)
    emit_json(out, args.output)


if __name__ == "__main__":
    main()
