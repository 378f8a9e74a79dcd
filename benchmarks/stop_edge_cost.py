"""Issue 47: the default stop edge's cost against the DOE-plane edge (``stop_edge="doe"``), A/B in one process,
runs interleaved (A, B, A, B, …; medians), on the bundled ``hybrid_asphere`` (its blank 3 mm DOE at 1 µm, 0.7 mm
after the lens, 3 µm pixels): a single warm PSF (``psf_result`` of one field at one wavelength, ks 64; the lens and
its hybrid built and warmed once) and a PSF map (``psf_map``, N×N fields × the R, G, B channel centres, ks 64) per
PSF; also the Fresnel step alone (``edge_step="fresnel"``, the default before "adaptive"). Prints one JSON object (and writes it with ``-o``).

    PYTHONPATH=. python benchmarks/stop_edge_cost.py [--grid 3] [--repeat 3] [--threads 2] [--field 12.25] [-o F]
"""

import argparse
import json
import statistics
import time
import warnings

import torch

from raywave.assembly.build import load_hybrid
from raywave.imaging import psf_map
from raywave.lens.build import bundled_lens_path

EDGES = {"default": {}, "fresnel": {"edge_step": "fresnel"}, "doe": {"stop_edge": "doe"}}


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--field", type=float, default=12.25, help="field (deg) of the single PSF")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.set_grad_enabled(False)
    warnings.simplefilter("ignore")
    wls = (0.66, 0.53, 0.47)
    hls = {k: load_hybrid(bundled_lens_path("hybrid_asphere"), **kw) for k, kw in EDGES.items()}
    for hl in hls.values():  # warm: the lens's caches, the transfer functions, the thread pool
        hl.psf_result((0.0, a.field), 0.53, ks=64)
    single = {k: [] for k in hls}
    maps = {k: [] for k in hls}
    for _ in range(a.repeat):
        for k, hl in hls.items():
            single[k].append(timed(lambda: hl.psf_result((0.0, a.field), 0.53, ks=64)))
        for k, hl in hls.items():
            n = a.grid * a.grid * len(wls)
            maps[k].append(timed(lambda: psf_map(hl, (a.grid, a.grid), wavelengths=wls, ks=64, progress=False)) / n)
    med = {k: statistics.median(v) for k, v in single.items()}
    mmed = {k: statistics.median(v) for k, v in maps.items()}
    out = dict(case=f"hybrid_asphere, single PSF at {a.field} deg 0.53 um ks 64; map {a.grid}x{a.grid}x3 ks 64",
               threads=a.threads, repeat=a.repeat, single_s=single, map_s_per_psf=maps,
               single_ratio_vs_doe={k: med[k] / med["doe"] for k in med},
               map_ratio_vs_doe={k: mmed[k] / mmed["doe"] for k in mmed},
               steps={k: hl.edge_step for k, hl in hls.items()})
    print(json.dumps(out))
    if a.output:
        with open(a.output, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
