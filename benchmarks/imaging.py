"""Imaging benchmark: PSF maps of the bundled hybrid lens and spatially-varying rendering from them.

Cases (each in its own process: wall time and peak resident memory above the process's baseline):

* **PSF map**: the bundled ``hybrid_asphere`` (aspheric singlet + 3 mm blank DOE at 1 µm pitch, 3000² pixels, 3 µm
  sensor pixels), N×N nodes (3×3, 5×5, 10×10) × 3 wavelengths (the R, G, B channel centres 0.66 / 0.53 / 0.47 µm),
  distant object, ks = 64, accurate ray-wave mode, no autograd (the paper's first, non-differentiable pass);
  and (3×3) with the DOE-plane fields cached (frozen refractive lens: the second and later maps of a DOE-training
  run).
* **render**: a 1-megapixel RGB image (1344 × 756, 16:9 like the sensor, 4.29 µm pixels; the 3 µm PSFs resampled
  to it) through the N×N map, float32, forward and forward + backward (gradient w.r.t. the image and the PSFs);
  and the training batch 4 × 3 × 256² through a 5×5 map.

Wall time (median) and CPU time (``process_time``, all threads: less sensitive to other processes on a shared
machine). Prints one JSON object (and writes it with ``-o``).

    python benchmarks/imaging.py [--threads 2] [--quick] [-o imaging.json]

``--per-psf`` (issue 17, the batched engine): only the PSF-map cost per PSF at 1, 10, 100 and 300 PSFs (``--stop-edge
doe|exit_pupil``: that stop edge instead of the default; ``--device cuda``: the lens on a GPU)
(1×1×1λ, 2×5×1λ, 10×10×1λ and the 10×10×3λ map; no autograd, ks = 64), each in its own process; with ``--ops``
(issue 43) beside time and memory the aten ops dispatched per PSF (``TorchDispatchMode``: on a GPU each is a kernel
launch), no grad for the map and forward + backward for one call's worth of its PSFs (``--grids 4x4x3,10x10x3``:
other cases).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time

from _memory import reset_peak, status_mb  # noqa: E402  (benchmarks/ is on sys.path)
from _report import emit_json  # noqa: E402

KS = 64
WAVELENGTHS = (0.66, 0.53, 0.47)
MP_SHAPE = (756, 1344)


def _lens(stop_edge: str | None = None):
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    return load_hybrid(bundled_lens_path("hybrid_asphere"), stop_edge=stop_edge)


def map_case(n: int, threads: int, cached: bool) -> dict:
    import warnings

    import torch

    from raywave.imaging import DOEFieldCache, psf_map

    torch.set_num_threads(threads)
    hl = _lens()
    warnings.simplefilter("ignore")
    base = status_mb("VmRSS")
    reset_peak()
    cache = DOEFieldCache(max_bytes=None) if cached else None
    t0, c0 = time.perf_counter(), time.process_time()
    m = psf_map(hl, (n, n), wavelengths=WAVELENGTHS, ks=KS, cache=cache)
    first, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"case": "psf_map", "grid": [n, n], "wavelengths": list(WAVELENGTHS), "ks": KS, "psfs": n * n * 3,
           "seconds": first, "seconds_per_psf": first / (n * n * 3), "cpu_seconds": cpu,
           "peak_mb": status_mb("VmHWM") - base, "energy_outside_max": float(m.energy_outside.max()),
           "energy_outside_median": float(m.energy_outside.median())}
    if cached:
        t0, c0 = time.perf_counter(), time.process_time()
        m2 = psf_map(hl, (n, n), wavelengths=WAVELENGTHS, ks=KS, cache=cache)
        out["cached_seconds"] = time.perf_counter() - t0
        out["cached_cpu_seconds"] = time.process_time() - c0
        out["cache_mb"] = cache.nbytes / 1e6
        out["cached_max_diff"] = float((m2.psf - m.psf).abs().max())
        out["peak_mb"] = status_mb("VmHWM") - base
    torch.save(m, f"/tmp/raywave_bench_map_{n}.pt")
    return out


def count_ops(fn):
    """``(number of aten ops dispatched, fn())``: every op that reaches the dispatcher (the kernel launches of a GPU;
    ``torch.utils._python_dispatch.TorchDispatchMode``), forward and, when ``fn`` runs one, backward."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class _Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.n += 1
            return func(*args, **(kwargs or {}))

    with _Count() as c:
        out = fn()
    return c.n, out


def ops_case(hl, n: int, m: int, wavelengths) -> dict:
    """The aten ops per PSF of an n×m map at ``wavelengths``, counted on the map's first model call (the field points
    of its first chunk, in the order :func:`raywave.imaging.psf_map` computes them: mirror images together, so that a
    mirror-symmetric lens builds a quarter of the fields, as in the map; a map is ⌈N·M / chunk⌉ such calls): no
    autograd, and with autograd (forward + backward of a weighted sum of the PSFs into the lens, as the replay runs a
    chunk)."""
    import torch

    from raywave.imaging.psfmap import _map_chunks, _pair_order, field_grid, map_call_size

    order = _pair_order(n, m)
    flat = field_grid(hl, (n, m)).reshape(-1, 2)[order]
    s, e = _map_chunks(n * m, len(wavelengths), None, map_call_size(hl, False, None))[0]  # the map's own call
    f = flat[s:e]
    k0 = f.shape[0] * len(wavelengths)
    with torch.no_grad():
        n_ops, _ = count_ops(lambda: hl.psf_result(f, list(wavelengths), ks=KS))
    s, e = _map_chunks(n * m, len(wavelengths), None)[0]  # with autograd: psf_map(grad=True)'s call
    f = flat[s:e]
    k = f.shape[0] * len(wavelengths)

    def fwd_bwd():
        r = hl.psf_result(f, list(wavelengths), ks=KS)
        w = torch.rand(r.psf.shape, dtype=r.psf.dtype, generator=torch.Generator().manual_seed(0)).to(r.psf.device)
        (r.psf * w).sum().backward()

    g_ops, _ = count_ops(fwd_bwd)
    return {"ops_psfs": k0, "ops": n_ops, "ops_per_psf": n_ops / k0, "ops_psfs_grad": k, "ops_grad": g_ops,
            "ops_per_psf_grad": g_ops / k}


def psfs_case(n: int, m: int, n_wl: int, threads: int, stop_edge: str | None = None, device: str = "cpu",
              ops: bool = False) -> dict:
    """Time per PSF of an n×m map at the first ``n_wl`` of the R, G, B wavelengths (after a 1-PSF warm-up);
    ``stop_edge`` None: the lens's default edge; ``device``: the torch device of the lens (on CUDA the time is
    taken after a synchronisation, and the peak GPU memory of the timed map is reported)."""
    import warnings

    import torch

    from raywave.imaging import psf_map

    torch.set_num_threads(threads)
    dev = torch.device(device)
    hl = _lens(stop_edge).to(dev)
    warnings.simplefilter("ignore")

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    psf_map(hl, (1, 1), wavelengths=WAVELENGTHS[:1], ks=KS)  # warm-up (allocator, first-call costs)
    sync()
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    t0, c0 = time.perf_counter(), time.process_time()
    m_ = psf_map(hl, (n, m), wavelengths=WAVELENGTHS[:n_wl], ks=KS)
    sync()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    k = n * m * n_wl
    out = {"case": "psfs", "grid": [n, m], "wavelengths": list(WAVELENGTHS[:n_wl]), "psfs": k,
           "stop_edge": hl.stop_edge, "device": str(dev), "psf_device": str(m_.psf.device), "seconds": wall,
           "seconds_per_psf": wall / k, "cpu_seconds_per_psf": cpu / k}
    if dev.type == "cuda":
        out["cuda_peak_allocated_mb"] = torch.cuda.max_memory_allocated(dev) / 1e6
        out["device_name"] = torch.cuda.get_device_name(dev)
    if ops:  # counted in a second, untimed pass (the counting itself costs host time per op)
        out.update(ops_case(hl, n, m, WAVELENGTHS[:n_wl]))
    return out


def render_case(n: int, threads: int, repeat: int, training: bool) -> dict:
    import torch

    from raywave.imaging import render_map

    torch.set_num_threads(threads)
    m = torch.load(f"/tmp/raywave_bench_map_{n}.pt", weights_only=False)
    g = torch.Generator().manual_seed(0)
    shape = (4, 3, 256, 256) if training else (1, 3) + MP_SHAPE
    img = torch.rand(shape, generator=g, dtype=torch.float32)
    psf = m.psf[0].clone()
    extent = (-1.0, 1.0, -1.0, 1.0)
    if training:  # a 256² crop at the sensor's own pitch (3 µm) from the centre of the field
        w, h = m.sensor_size
        extent = (-256 * m.pitch / w, 256 * m.pitch / w, -256 * m.pitch / h, 256 * m.pitch / h)
    base = status_mb("VmRSS")

    def fwd():
        return render_map(img, m, 0, extent=extent)

    def fwd_bwd():
        x = img.clone().requires_grad_(True)
        p = psf.clone().requires_grad_(True)
        from raywave.imaging import render

        y = render(x, p, positions=m.positions, centers=m.centers[0], sensor_size=m.sensor_size, pitch=m.pitch,
                   extent=extent)
        y.square().mean().backward()
        return p.grad

    res = {"case": "render_training" if training else "render_1mp", "grid": list(m.grid), "image": list(shape),
           "dtype": "float32", "repeat": repeat}
    for name, fn in (("forward", fwd), ("forward_backward", fwd_bwd)):
        fn()  # warm-up
        reset_peak()
        times, cpus = [], []
        for _ in range(repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        res[f"{name}_seconds"] = sorted(times)[len(times) // 2]
        res[f"{name}_cpu_seconds"] = sorted(cpus)[len(cpus) // 2]
        res[f"{name}_peak_mb"] = status_mb("VmHWM") - base
    return res


def _run(args_list, threads, device="cpu", ops=False):
    cmd = [sys.executable, __file__, "--case", ",".join(str(a) for a in args_list), "--threads", str(threads),
           "--device", device] + (["--ops"] if ops else [])
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"case {args_list} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2, help="timed repetitions per render case (median reported)")
    ap.add_argument("--quick", action="store_true", help="3×3 and 5×5 maps only")
    ap.add_argument("-o", "--output", default=None)
    ap.add_argument("--per-psf", action="store_true", help="only the map's time per PSF at 1/10/100/300 PSFs")
    ap.add_argument("--max-psfs", type=int, default=300, help="--per-psf: skip the cases with more PSFs")
    ap.add_argument("--stop-edge", choices=("default", "doe", "exit_pupil"), default="default",
                    help="--per-psf: the lens's stop edge (default: the library's default, the exit pupil)")
    ap.add_argument("--device", default="cpu", help="--per-psf: the torch device of the lens (cpu, cuda)")
    ap.add_argument("--ops", action="store_true",
                    help="--per-psf: also count the aten ops dispatched per PSF on the map's first model call (no grad, "
                         "and forward + backward), in a second untimed pass")
    ap.add_argument("--grids", default=None,
                    help="--per-psf: the cases as NxMxW,… (default 1x1x1,2x5x1,10x10x1,10x10x3)")
    ap.add_argument("--ops-only", default=None, metavar="NxMxW",
                    help="only count the ops per PSF of that map's first call (no timing), in this process")
    ap.add_argument("--case", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.ops_only:
        import warnings

        import torch

        torch.set_num_threads(args.threads)
        warnings.simplefilter("ignore")
        n, m, w = (int(v) for v in args.ops_only.split("x"))
        hl = _lens(None if args.stop_edge == "default" else args.stop_edge)
        with torch.no_grad():
            hl.psf_result((0.0, 0.0), list(WAVELENGTHS[:1]), ks=KS)  # warm-up (first-call costs)
        emit_json({"benchmark": "imaging_ops", "lens": "hybrid_asphere", "grid": [n, m], "wavelengths": list(
            WAVELENGTHS[:w]), "ks": KS, "stop_edge": hl.stop_edge, "torch": torch.__version__,
                   **ops_case(hl, n, m, WAVELENGTHS[:w])}, args.output)
        return
    if args.case:
        kind, *rest = args.case.split(",")
        if kind == "psfs":
            out = psfs_case(int(rest[0]), int(rest[1]), int(rest[2]), args.threads,
                            None if rest[3] == "default" else rest[3], args.device, args.ops)
        elif kind == "map":
            out = map_case(int(rest[0]), args.threads, rest[1] == "1")
        else:
            out = render_case(int(rest[0]), args.threads, int(rest[1]), kind == "train")
        print(json.dumps(out))
        return

    import torch

    if args.per_psf:
        grids = ((1, 1, 1), (2, 5, 1), (10, 10, 1), (10, 10, 3)) if args.grids is None else \
            tuple(tuple(int(v) for v in g.split("x")) for g in args.grids.split(","))
        cases = [c for c in grids if c[0] * c[1] * c[2] <= args.max_psfs]
        runs = [_run(["psfs", *c, args.stop_edge], args.threads, args.device, args.ops) for c in cases]
        summary = {"benchmark": "imaging_per_psf", "lens": "hybrid_asphere", "ks": KS, "threads": args.threads,
                   "device": args.device, "device_name": runs[0].get("device_name", platform.processor()),
                   "stop_edge": runs[0]["stop_edge"],
                   "torch": torch.__version__, "python": platform.python_version(), "machine": platform.machine(),
                   "runs": runs,
                   "seconds_per_psf": {str(r["psfs"]): r["seconds_per_psf"] for r in runs},
                   "cpu_seconds_per_psf": {str(r["psfs"]): r["cpu_seconds_per_psf"] for r in runs}}
        if args.ops:
            summary["ops_per_psf"] = {str(r["psfs"]): r["ops_per_psf"] for r in runs}
            summary["ops_per_psf_grad"] = {str(r["psfs"]): r["ops_per_psf_grad"] for r in runs}
        emit_json(summary, args.output)
        return

    grids = (3, 5) if args.quick else (3, 5, 10)
    maps = [_run(["map", n, 0], args.threads) for n in grids]
    cached = _run(["map", 3, 1], args.threads)
    renders = [_run(["render", n, args.repeat], args.threads) for n in grids]
    training = _run(["train", 5, args.repeat], args.threads)
    by = {m["grid"][0]: m for m in maps}
    big = max(grids)
    summary = {
        "benchmark": "imaging", "lens": "hybrid_asphere", "ks": KS, "wavelengths_um": list(WAVELENGTHS),
        "threads": args.threads, "torch": torch.__version__, "python": platform.python_version(),
        "machine": platform.machine(),
        "psf_maps": maps, "psf_map_cached_3x3": cached, "render_1mp": renders, "render_training_5x5": training,
        "scaling": {
            "map_seconds_per_psf": {f"{n}x{n}": by[n]["seconds_per_psf"] for n in grids},
            "map_cpu_seconds_per_psf": {f"{n}x{n}": by[n]["cpu_seconds"] / (3 * n * n) for n in grids},
            "map_seconds_ratio_vs_nodes": {f"{n}x{n}": by[n]["seconds"] / by[grids[0]]["seconds"] for n in grids},
            "nodes_ratio": {f"{n}x{n}": n * n / grids[0] ** 2 for n in grids},
            "render_forward_seconds": {f"{r['grid'][0]}x{r['grid'][1]}": r["forward_seconds"] for r in renders},
        },
        "headline": {
            f"psf_map_{big}x{big}x3_seconds": by[big]["seconds"], f"psf_map_{big}x{big}x3_peak_mb": by[big]["peak_mb"],
            f"render_1mp_{big}x{big}_forward_seconds": renders[-1]["forward_seconds"],
            f"render_1mp_{big}x{big}_forward_peak_mb": renders[-1]["forward_peak_mb"],
        },
    }
    emit_json(summary, args.output)


if __name__ == "__main__":
    main()
