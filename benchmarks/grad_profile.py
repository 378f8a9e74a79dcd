"""Where forward + backward of one model call goes on a CPU (issue 43): torch.profiler over one call of 8 field
points × 3 λ of the bundled ``hybrid_asphere``'s N×N map (ks 64, default edge), as ``psf_ab.py --modes grad``'s
child and the replay run it. Reports the forward's and the backward's wall seconds and the top aten ops (self CPU
time) of each, with input shapes, and the top autograd nodes of the backward. Prints JSON; ``-o`` writes it.

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/grad_profile.py [--grid 10] [--start 0] [-o out.json]
"""

from __future__ import annotations

import argparse
import time
import warnings

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

WAVELENGTHS = [0.66, 0.53, 0.47]


def _top(prof, n: int, shapes: bool) -> list:
    ev = prof.key_averages(group_by_input_shape=shapes)
    ev = sorted(ev, key=lambda e: -e.self_cpu_time_total)[:n]
    return [{"op": e.key, "calls": e.count, "self_ms": round(e.self_cpu_time_total / 1e3, 2),
             **({"shapes": str(e.input_shapes)[:300]} if shapes else {})} for e in ev]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--start", type=int, default=0, help="first field point of the call in the map's row order")
    ap.add_argument("--count", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch
    from torch.profiler import ProfilerActivity, profile

    from raywave.assembly.build import load_hybrid
    from raywave.imaging.psfmap import field_grid

    torch.set_num_threads(args.threads)
    hl = load_hybrid("hybrid_asphere")
    warnings.simplefilter("ignore")
    f = field_grid(hl, (args.grid, args.grid)).reshape(-1, 2)
    sl = slice(args.start, args.start + args.count)
    hl.psf_result(f[sl][:1], WAVELENGTHS, ks=64).psf.sum().backward()  # warm-up (compiled loops)
    w = torch.rand((args.count, 3, 64, 64), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as pf:
        t0 = time.perf_counter()
        r = hl.psf_result(f[sl], WAVELENGTHS, ks=64)
        loss = (r.psf * w).sum()
        t1 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as pb:
        t2 = time.perf_counter()
        loss.backward()
        t3 = time.perf_counter()
    nodes = [e for e in pb.key_averages() if "Backward" in e.key or "backward" in e.key]
    nodes = sorted(nodes, key=lambda e: -e.cpu_time_total)[:args.top]
    out = {"benchmark": "grad_profile", "torch": torch.__version__, "threads": args.threads, "grid": args.grid,
           "start": args.start, "count": args.count, "psfs": args.count * 3,
           "forward_s": t1 - t0, "backward_s": t3 - t2,
           "forward_top_ops": _top(pf, args.top, False), "backward_top_ops": _top(pb, args.top, False),
           "backward_top_ops_shapes": _top(pb, args.top, True),
           "backward_nodes_total": [{"node": e.key, "calls": e.count, "total_ms": round(e.cpu_time_total / 1e3, 2)}
                                    for e in nodes]}
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    main()
