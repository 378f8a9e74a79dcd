"""Issue 47: the knife-edge factor's Fresnel integrals, scipy (cephes, on the host: ``_fresnel_threads``) against
torch (:func:`raywave.utils.fresnel.fresnel`), A/B in one process, runs interleaved (A, B, A, B, …; medians), on
the bundled ``hybrid_asphere`` (default stop edge, ks 64), at ``torch.set_num_threads`` 1 and 2:

* ``kernel``: the two evaluations alone on the knife-edge factor's real inputs: the band values ν of a
  ``--grid``×``--grid``×3 map (captured once from the map itself, every ``--every``-th call kept), ns per value;
* ``psf``: a single warm PSF (12.25°, 0.53 µm) and a ``--map-grid``×``--map-grid``×3 map per PSF, with
  :data:`raywave.hybrid.coherent.stop_edge.FRESNEL_CPU` switched between "scipy" and "torch";
* ``change``: how far the PSFs move: max over a 3×3×3 map's PSFs of the relative L1 ``Σ|torch − scipy| / Σ|scipy|``
  (and the Fresnel integrals' own max difference on the captured band).

Prints one JSON object (and writes it with ``-o``).

    PYTHONPATH=. python benchmarks/fresnel_ab.py [--parts kernel,psf,change] [--grid 10] [--map-grid 6]
        [--repeat 3] [--threads 1,2] [-o F]
"""

import argparse
import statistics
import time
import warnings

import numpy as np
import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

WAVELENGTHS = (0.66, 0.53, 0.47)


def _parser():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="kernel,psf,change")
    ap.add_argument("--grid", type=int, default=10, help="the map whose band values the kernel timing uses")
    ap.add_argument("--every", type=int, default=5, help="keep every k-th captured call (memory)")
    ap.add_argument("--map-grid", type=int, default=6, help="the timed map's N×N fields")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--singles", type=int, default=5, help="single-PSF timings per backend per repetition")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("-o", "--output")
    return ap


def _capture(hl, grid: int, every: int) -> list:
    """The band values ν of every knife-edge factor of a grid×grid×3 map (every ``every``-th call)."""
    from raywave.hybrid.coherent import stop_edge as se
    from raywave.imaging import psf_map

    got, orig = [], se._fresnel_integrals

    def spy(v):
        got.append(v.detach().clone())
        return orig(v)

    se._fresnel_integrals = spy
    try:
        psf_map(hl, (grid, grid), wavelengths=WAVELENGTHS, ks=64, progress=False)
    finally:
        se._fresnel_integrals = orig
    return got[::every]


def _kernel(vals: list, repeat: int) -> dict:
    from raywave.hybrid.coherent.stop_edge import _fresnel_threads
    from raywave.utils.fresnel import fresnel

    arrs = [v.numpy() for v in vals]
    n = sum(a.size for a in arrs)

    def run_scipy():
        for a in arrs:
            c_, s_ = _fresnel_threads(a)
            torch.from_numpy(c_), torch.from_numpy(s_)

    def run_torch():
        for v in vals:
            fresnel(v)

    res = {"scipy": ([], []), "torch": ([], [])}
    for _ in range(repeat):
        for k, f in (("scipy", run_scipy), ("torch", run_torch)):
            t0, c0 = time.perf_counter(), time.process_time()
            f()
            res[k][0].append((time.perf_counter() - t0) / n * 1e9)
            res[k][1].append((time.process_time() - c0) / n * 1e9)
    out = {"values": n, "calls": len(arrs), "unit": "ns per value (median)"}
    for k, (w, c) in res.items():
        out[k] = {"wall": statistics.median(w), "cpu": statistics.median(c)}
    out["torch_over_scipy_wall"] = out["torch"]["wall"] / out["scipy"]["wall"]
    out["torch_over_scipy_cpu"] = out["torch"]["cpu"] / out["scipy"]["cpu"]
    return out


def _psf(hl, a) -> dict:
    from raywave.hybrid.coherent import stop_edge as se
    from raywave.imaging import psf_map

    n_map = a.map_grid ** 2 * len(WAVELENGTHS)

    def single():
        hl.psf_result((0.0, 12.25), 0.53, ks=64)

    def one_map():
        psf_map(hl, (a.map_grid, a.map_grid), wavelengths=WAVELENGTHS, ks=64, progress=False)

    res = {k: {"single_wall": [], "single_cpu": [], "map_wall": [], "map_cpu": []} for k in ("scipy", "torch")}
    for k in res:  # warm
        se.FRESNEL_CPU = k
        single()
        one_map()
    try:
        for _ in range(a.repeat):
            for k in res:
                se.FRESNEL_CPU = k
                for _ in range(a.singles):
                    t0, c0 = time.perf_counter(), time.process_time()
                    single()
                    res[k]["single_wall"].append(time.perf_counter() - t0)
                    res[k]["single_cpu"].append(time.process_time() - c0)
                t0, c0 = time.perf_counter(), time.process_time()
                one_map()
                res[k]["map_wall"].append((time.perf_counter() - t0) / n_map)
                res[k]["map_cpu"].append((time.process_time() - c0) / n_map)
    finally:
        se.FRESNEL_CPU = "scipy"
    out = {"unit": "s (median; map: per PSF)", "map": f"{a.map_grid}x{a.map_grid}x3"}
    for k, r in res.items():
        out[k] = {m: statistics.median(v) for m, v in r.items()}
    out["torch_over_scipy"] = {m: out["torch"][m] / out["scipy"][m] for m in res["scipy"]}
    return out


def _change(hl, vals: list) -> dict:
    from raywave.hybrid.coherent import stop_edge as se
    from raywave.imaging import psf_map
    from raywave.utils.fresnel import fresnel

    maps = {}
    for k in ("scipy", "torch"):
        se.FRESNEL_CPU = k
        maps[k] = psf_map(hl, (3, 3), wavelengths=WAVELENGTHS, ks=64, progress=False).psf.detach()
    se.FRESNEL_CPU = "scipy"
    ref, new = maps["scipy"].flatten(-2), maps["torch"].flatten(-2)
    rel = (new - ref).abs().sum(-1) / ref.abs().sum(-1)
    dc = ds = 0.0
    for v in vals:
        c_t, s_t = fresnel(v)
        c_s, s_s = se._fresnel_threads(v.numpy())
        dc = max(dc, float((c_t - torch.from_numpy(c_s)).abs().max()))
        ds = max(ds, float((s_t - torch.from_numpy(s_s)).abs().max()))
    return {"map": "3x3x3", "max_rel_l1": float(rel.max()), "median_rel_l1": float(rel.median()),
            "band_max_abs_dC": dc, "band_max_abs_dS": ds}


def main(argv=None):
    a = _parser().parse_args(argv)
    parts = a.parts.split(",")
    torch.set_grad_enabled(False)
    warnings.simplefilter("ignore")
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    torch.set_num_threads(1)
    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    out = {"case": "hybrid_asphere ks 64, default stop edge", "torch": torch.__version__}
    vals = _capture(hl, a.grid, a.every) if ("kernel" in parts or "change" in parts) else []
    if vals:
        out["band"] = {"map": f"{a.grid}x{a.grid}x3", "every": a.every, "min": float(min(v.min() for v in vals)),
                       "max": float(max(v.max() for v in vals))}
    if "change" in parts:
        out["change"] = _change(hl, vals)
    for th in (int(t) for t in a.threads.split(",")):
        torch.set_num_threads(th)
        if "kernel" in parts:
            out[f"kernel_threads{th}"] = _kernel(vals, a.repeat)
        if "psf" in parts:
            out[f"psf_threads{th}"] = _psf(hl, a)
    emit_json(out, a.output)
    return out


if __name__ == "__main__":
    main()
