"""The band convolution of the window-to-window angular spectrum alone (issue 43): time and peak memory of its forward
(no autograd) and of forward + backward, for two source trees A/B in one run (each case in its own process, rounds
interleaved A, B, A, B, …; CPU seconds, ``process_time``). The case is a map batch's: B fields of Ny × Nx samples on an
My × Mx FFT grid, the band one wrapped run of rows and of columns (as a carrier's band on the ``fftfreq`` grid), a
213² output window. Prints one JSON object (``-o`` writes it too).

    OMP_NUM_THREADS=1 python benchmarks/band_convolution.py --a /path/to/old/tree --b . [--rounds 3]

A tree from before the band module (2026-11-29) is read through ``raywave.wave.propagation.window``'s
``_convolve_band`` / ``_BandConvolve``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

_CHILD = r"""
import json, resource, sys, time
import torch
torch.set_num_threads(1)
sys.path.insert(0, sys.argv[1])
try:
    from raywave.wave.propagation.band import BandConvolve as Fn, convolve_band as plain
except ImportError:  # before the band module
    from raywave.wave.propagation.window import _BandConvolve as Fn, _convolve_band as plain
b, ny, nx, my, mx, mode = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]), sys.argv[7]
g = torch.Generator().manual_seed(0)
u = torch.randn(b, ny, nx, dtype=torch.complex128, generator=g)
r_keep, c_keep = int(0.9 * my), int(0.9 * mx)
rows = torch.cat([torch.arange(0, r_keep // 2), torch.arange(my - (r_keep - r_keep // 2), my)])
cols = torch.cat([torch.arange(0, c_keep // 2), torch.arange(mx - (c_keep - c_keep // 2), mx)])
h = torch.randn(b, rows.numel(), cols.numel(), dtype=torch.complex128, generator=g)
go = torch.randn(b, 213, 213, dtype=torch.complex128, generator=g)

def run():
    if mode == "forward":
        with torch.no_grad():
            return plain(u, h, (my, mx), rows, cols, 213, 213)
    uu = u.clone().requires_grad_()
    out = Fn.apply(uu, h, (my, mx), rows, cols, 213, 213)
    return torch.autograd.grad(out, (uu,), go)[0]

base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
ref = run()
peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024
t = time.process_time()
for _ in range(3):
    run()
print(json.dumps({"cpu_s": (time.process_time() - t) / 3, "peak_mb_above": peak,
                  "checksum": float(ref.abs().sum())}))
"""


def _run(tree: str, case: list[int], mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, tree, *map(str, case), mode], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="tree A (the baseline)")
    ap.add_argument("--b", default=".", help="tree B")
    ap.add_argument("--case", default="4,1000,1000,1440,1440", help="B,Ny,Nx,My,Mx")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("-o", "--output")
    args = ap.parse_args()
    case = [int(v) for v in args.case.split(",")]
    result = {"benchmark": "band_convolution", "case": dict(zip(("B", "Ny", "Nx", "My", "Mx"), case)),
              "band": "90 % of the FFT grid's rows and columns, one wrapped run each; output 213²",
              "a": args.a, "b": args.b, "threads": 1}
    for mode in ("forward", "forward_backward"):
        runs = {"a": [], "b": []}
        for _ in range(args.rounds):
            for key, tree in (("a", args.a), ("b", args.b)):
                runs[key].append(_run(tree, case, mode))
        med = {k: {"cpu_s": statistics.median(r["cpu_s"] for r in v),
                   "peak_mb_above": statistics.median(r["peak_mb_above"] for r in v)} for k, v in runs.items()}
        ca, cb = runs["a"][0]["checksum"], runs["b"][0]["checksum"]
        result[mode] = {"median": med, "speedup_cpu": med["a"]["cpu_s"] / med["b"]["cpu_s"],
                        "peak_ratio_b_over_a": med["b"]["peak_mb_above"] / max(med["a"]["peak_mb_above"], 1e-9),
                        "checksum_rel_diff": abs(ca - cb) / abs(ca)}
    emit_json(result, args.output)


if __name__ == "__main__":
    main()
