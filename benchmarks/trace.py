"""Ray-tracing throughput and memory: 1e6 rays through the bundled Cooke triplet.

Prints one JSON object: ray-surface intersections per second in float64 and float32, forward only and
forward + backward (gradients w.r.t. every lens parameter), and the peak memory per ray of each case.
Each case runs in a fresh subprocess so that its peak resident memory is its own.

    python benchmarks/trace.py [--rays 1000000] [--threads 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time

from _memory import peak_mb, reset_peak, rss_mb  # noqa: E402  (benchmarks/ is on sys.path)


def run_case(dtype_name: str, mode: str, n_rays: int, threads: int, repeat: int) -> dict:
    import torch

    from raywave.lens.build import bundled_lens_path, load_lens
    from raywave.lens.sources import point_source_rays

    torch.set_num_threads(threads)
    dtype = {"float64": torch.float64, "float32": torch.float32}[dtype_name]
    lens = load_lens(bundled_lens_path("cooke_triplet")).to(dtype)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        rays = point_source_rays(lens, (0.0, 14.0), lens.primary_wavelength, pupil=("random", n_rays),
                                 aim="paraxial", generator=gen, dtype=dtype)
    rays = rays.replace(wavelength=torch.as_tensor(rays.wavelength, dtype=dtype))
    n_surf = len(lens.surfaces)

    def once():
        if mode == "forward":
            with torch.no_grad():
                out = lens.trace(rays)
            return out
        lens.zero_grad(set_to_none=True)
        out = lens.trace(rays)
        loss = (out.o[..., :2].pow(2).sum(-1) * out.valid).sum()
        loss.backward()
        return out

    base = rss_mb()  # rays and lens in memory; the peak counts what tracing adds on top
    reset_peak()
    out = once()  # warm-up
    valid_fraction = float(out.valid.double().mean())
    del out
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        once()
        times.append(time.perf_counter() - t0)
    best = min(times)
    peak = peak_mb() - base
    return {
        "dtype": dtype_name, "mode": mode, "rays": n_rays, "surfaces": n_surf,
        "seconds": best, "ray_surfaces_per_s": n_rays * n_surf / best,
        "peak_extra_memory_mb": peak, "peak_bytes_per_ray": peak * 2**20 / n_rays,
        "valid_fraction": valid_fraction,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--case", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        dtype_name, mode = args.case.split(",")
        print(json.dumps(run_case(dtype_name, mode, args.rays, args.threads, args.repeat)))
        return
    import torch

    results = []
    for dtype_name in ("float64", "float32"):
        for mode in ("forward", "forward_backward"):
            cmd = [sys.executable, __file__, "--case", f"{dtype_name},{mode}", "--rays", str(args.rays),
                   "--threads", str(args.threads), "--repeat", str(args.repeat)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    summary = {
        "benchmark": "trace", "lens": "cooke_triplet (bundled, dispersive glasses)", "field_deg": 14.0,
        "threads": args.threads, "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
        "goal_float64_forward_ray_surfaces_per_s": 2e7,
        "results": results,
    }
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
