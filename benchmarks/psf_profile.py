"""Where a PSF map's time goes on a device: wall time against the time the device computes (torch.profiler).

The bundled ``hybrid_asphere`` (default stop edge unless ``--stop-edge``), an N×N map at the R, G, B centre
wavelengths, ks 64, no autograd, after a 1-PSF warm-up. Reports the wall time, the torch operators called, the
device kernels launched and their summed time, the device→host copies and synchronisations (each one stalls the
host until the device is idle), and the busy fraction = kernel time / wall time: near 1 the device is the limit,
near 0 the host (Python, launches, synchronisations) is. Prints JSON; ``-o`` writes it too.

    python benchmarks/psf_profile.py --device cuda [--grid 2] [--stop-edge doe] [-o profile.json]

Not yet run to the end on a GPU: the 2026-11-27 check gave it 40 s for a 3×3 map, too little for the profiler.
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

WAVELENGTHS = (0.66, 0.53, 0.47)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grid", type=int, default=2, help="N×N nodes (default 2: the profiler's own summary of the "
                    "~2·10⁴ operators per PSF takes ~1 s per PSF on a CPU)")
    ap.add_argument("--stop-edge", choices=("default", "doe", "exit_pupil"), default="default")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--top", type=int, default=12, help="operators listed by their host time")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch
    from torch.profiler import ProfilerActivity, profile

    from raywave.assembly.build import load_hybrid
    from raywave.imaging import psf_map

    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    hl = load_hybrid("hybrid_asphere", stop_edge=None if args.stop_edge == "default" else args.stop_edge).to(dev)
    warnings.simplefilter("ignore")
    psf_map(hl, (1, 1), wavelengths=WAVELENGTHS[:1], ks=64)  # warm-up
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        t0 = time.perf_counter()
        psf_map(hl, (args.grid, args.grid), wavelengths=WAVELENGTHS, ks=64)
        if cuda:
            torch.cuda.synchronize(dev)
        wall = time.perf_counter() - t0
    events = prof.key_averages()
    n_psf = args.grid * args.grid * len(WAVELENGTHS)
    ops = [e for e in events if e.key.startswith("aten::")]
    kernels = [e for e in events if e.device_type is not None and "CUDA" in str(e.device_type)]
    kernel_us = sum(e.self_device_time_total for e in kernels) if cuda else 0.0
    runtime = {e.key: e.count for e in events if e.key.startswith("cuda")}
    out = {
        "benchmark": "psf_profile", "device": str(dev),
        "device_name": torch.cuda.get_device_name(dev) if cuda else platform.processor(),
        "torch": torch.__version__, "stop_edge": hl.stop_edge, "grid": [args.grid, args.grid], "psfs": n_psf,
        "wall_seconds": wall, "wall_seconds_per_psf": wall / n_psf,
        "aten_calls_per_psf": sum(e.count for e in ops) / n_psf,
        "kernels_per_psf": sum(e.count for e in kernels) / n_psf if cuda else None,
        "kernel_seconds_per_psf": kernel_us * 1e-6 / n_psf if cuda else None,
        "device_busy_fraction": kernel_us * 1e-6 / wall if cuda else None,
        "runtime_calls_per_psf": {k: v / n_psf for k, v in sorted(runtime.items())},
        "top_ops_by_host_time": [{"op": e.key, "calls": e.count, "host_ms": e.self_cpu_time_total / 1e3}
                                 for e in sorted(ops, key=lambda e: -e.self_cpu_time_total)[:args.top]],
    }
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    main()
