"""Issue 43's device figures in one process, each row written as soon as it is measured (an interrupted run keeps
what it measured): the bundled ``hybrid_asphere`` at its default stop edge, ks 64.

Rows:

* ``map_10x10x3``: :func:`raywave.imaging.psf_map` of 10×10 nodes × R, G, B (300 PSFs), no autograd, twice (the
  first, ``cold``, pays the device's kernel, FFT-plan and allocator set-up; the second is the figure);
* ``fwd_bwd_10x10x3``: the same 300 PSFs forward + backward, one model call of 8 field points × 3 λ at a time, each
  followed by the backward of a random weighted sum of its PSFs into the lens (the replay's pattern), after one
  call's warm-up; target ≤ 1 s on a GPU;
* ``map_100x100x1``: the 10,000-PSF map (λ 0.55 µm) in calls of up to 512 field points, no autograd, stopped after
  ``--map-seconds``; target ≤ 10 s (the JSON gives the PSFs done and the projected time of all 10,000);
* ``ops_10x10x3`` (``--ops``): aten ops dispatched per PSF of the map's first call, no grad and forward + backward
  (on a GPU each op is a kernel launch).

    python benchmarks/gpu_issue43.py --device cuda [--map-seconds 90] [--ops] [--rows map,fwd_bwd,big_map]
        [--per-call 8] [-o rows.json]
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

KS = 64
RGB = [0.66, 0.53, 0.47]


def _sync(dev) -> None:
    import torch

    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _peak_mb(dev) -> float | None:
    import torch

    return torch.cuda.max_memory_allocated(dev) / 1e6 if dev.type == "cuda" else None


def _reset_peak(dev) -> None:
    import torch

    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)


def map_rows(hl, dev, n: int) -> list[dict]:
    """Two timed n×n×3 maps without autograd (cold, then warm)."""
    from raywave.imaging import psf_map

    rows = []
    for label in ("cold", "warm"):
        _reset_peak(dev)
        t0 = time.perf_counter()
        pm = psf_map(hl, (n, n), wavelengths=RGB, ks=KS, progress=False)
        _sync(dev)
        dt = time.perf_counter() - t0
        k = n * n * len(RGB)
        rows.append({"case": f"map_{n}x{n}x3", "run": label, "psfs": k, "seconds": dt, "seconds_per_psf": dt / k,
                     "peak_allocated_mb": _peak_mb(dev), "finite": bool(pm.psf.isfinite().all())})
    return rows


def fwd_bwd_row(hl, dev, n: int, per_call: int = 8) -> dict:
    """Forward + backward of an n×n×3 map, ``per_call`` field points a call, timed after one call's warm-up."""
    import torch

    from raywave.imaging.psfmap import field_grid

    f = field_grid(hl, (n, n)).reshape(-1, 2)
    w = torch.rand((f.shape[0], len(RGB), KS, KS), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0)).to(dev)

    def call(s: int) -> None:
        r = hl.psf_result(f[s:s + per_call], RGB, ks=KS)
        (r.psf * w[s:s + per_call]).sum().backward()

    call(0)  # warm-up
    _sync(dev)
    hl.zero_grad(set_to_none=True)
    _reset_peak(dev)
    t0 = time.perf_counter()
    for s in range(0, f.shape[0], per_call):
        call(s)
    _sync(dev)
    dt = time.perf_counter() - t0
    k = f.shape[0] * len(RGB)
    g = [p.grad for p in hl.parameters() if p.grad is not None]
    return {"case": f"fwd_bwd_{n}x{n}x3", "psfs": k, "field_points_per_call": per_call, "seconds": dt,
            "seconds_per_psf": dt / k, "target_seconds": 1.0, "peak_allocated_mb": _peak_mb(dev),
            "grads_finite": bool(all(x.isfinite().all() for x in g)), "parameters_with_grad": len(g)}


def big_map_row(hl, dev, n: int, seconds: float, per_call: int = 512) -> dict:
    """An n×n × 1λ map without autograd in calls of ``per_call`` field points, stopped after ``seconds``."""
    import torch

    from raywave.imaging.psfmap import field_grid

    f = field_grid(hl, (n, n)).reshape(-1, 2)
    done, finite = 0, True
    _reset_peak(dev)
    t0 = time.perf_counter()
    with torch.no_grad():
        for s in range(0, f.shape[0], per_call):
            r = hl.psf_result(f[s:s + per_call], [0.55], ks=KS)
            finite &= bool(r.psf.isfinite().all())
            done += r.psf.shape[0]
            if time.perf_counter() - t0 > seconds:
                break
    _sync(dev)
    dt = time.perf_counter() - t0
    total = f.shape[0]
    return {"case": f"map_{n}x{n}x1", "psfs": total, "psfs_done": done, "seconds": dt, "seconds_per_psf": dt / done,
            "projected_seconds_all": dt / done * total, "target_seconds": 10.0, "field_points_per_call": per_call,
            "peak_allocated_mb": _peak_mb(dev), "finite": finite}


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--grid", type=int, default=10, help="N of the N×N×3 map and its forward + backward")
    ap.add_argument("--big-grid", type=int, default=100, help="N of the N×N×1 map")
    ap.add_argument("--map-seconds", type=float, default=90.0, help="stop the N×N×1 map after this long")
    ap.add_argument("--ops", action="store_true", help="also the aten ops per PSF (TorchDispatchMode)")
    ap.add_argument("--rows", default="map,fwd_bwd,big_map", help="which rows (comma-separated: map, fwd_bwd, big_map)")
    ap.add_argument("--per-call", type=int, default=8, help="field points a call of the forward + backward row")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch

    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    warnings.simplefilter("ignore")
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    hl = load_hybrid(bundled_lens_path("hybrid_asphere")).to(dev)
    rows: list = []
    emit_row(rows, {"case": "env", "device": str(dev), "torch": torch.__version__, "python": platform.python_version(),
                    "device_name": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor(),
                    "threads": torch.get_num_threads(), "stop_edge": hl.stop_edge, "ks": KS}, args.output)
    wanted = set(args.rows.split(","))
    for row in map_rows(hl, dev, args.grid) if "map" in wanted else []:
        emit_row(rows, row, args.output)
    if "fwd_bwd" in wanted:
        emit_row(rows, fwd_bwd_row(hl, dev, args.grid, args.per_call), args.output)
    if "big_map" in wanted and args.map_seconds > 0:
        emit_row(rows, big_map_row(hl, dev, args.big_grid, args.map_seconds), args.output)
    if args.ops:
        from imaging import ops_case  # noqa: E402  (benchmarks/imaging.py)

        t0 = time.perf_counter()
        row = {"case": f"ops_{args.grid}x{args.grid}x3", **ops_case(hl, args.grid, args.grid, RGB)}
        row["count_seconds"] = time.perf_counter() - t0
        emit_row(rows, row, args.output)
    return rows


if __name__ == "__main__":
    main()
