"""CPU time of a PSF map with the accurate construction's field stage per construction versus batched (issue 43:
``raywave.hybrid.coherent.accurate.BATCHED_FIELD_STAGE``, on an accelerator by default), A/B in one process,
interleaved.

The bundled ``hybrid_asphere`` (default edge), an N×M×W map (:func:`raywave.imaging.psf_map`, no autograd), ks 64.
Each pair runs both modes (the order alternating), timing the whole map and the field stage alone (the time spent in
``_fine_fields``); the PSFs of the two modes are compared (relative L1 per PSF). Prints one JSON object (``-o``:
also written)::

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/field_stage_ab.py [--map 10x10x3] [--pairs 2]
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

WAVELENGTHS = (0.66, 0.53, 0.47)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="10x10x3", metavar="NxMxW")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args()

    import torch

    import raywave.hybrid.coherent.accurate as acc
    from imaging import _lens  # noqa: E402
    from raywave.imaging import psf_map

    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    n, m, w = (int(v) for v in args.map.split("x"))
    wls = list(WAVELENGTHS[:w])
    hl = _lens()
    spent = [0.0]
    real = acc._fine_fields

    def timed(reqs):
        t = time.perf_counter()
        try:
            return real(reqs)
        finally:
            spent[0] += time.perf_counter() - t

    acc._fine_fields = timed
    with torch.no_grad():
        hl.psf_result((0.0, 0.0), wls[:1], ks=64)  # warm-up

    def run(batched: bool):
        acc.BATCHED_FIELD_STAGE = batched
        spent[0] = 0.0
        t = time.perf_counter()
        with torch.no_grad():
            psf = psf_map(hl, (n, m), wavelengths=wls, ks=64, progress=False).psf
        return time.perf_counter() - t, spent[0], psf

    rows, psfs = [], {}
    for k in range(args.pairs):
        for batched in ((False, True) if k % 2 == 0 else (True, False)):
            total, field, psf = run(batched)
            psfs[batched] = psf
            rows.append({"pair": k, "batched": batched, "map_s": round(total, 3), "field_stage_s": round(field, 3)})
            print(rows[-1], flush=True)
    a, b = psfs[False].flatten(-2), psfs[True].flatten(-2)
    rel = ((a - b).abs().sum(-1) / a.abs().sum(-1).clamp_min(1e-300)).flatten()

    def med(batched, key):
        return statistics.median(r[key] for r in rows if r["batched"] == batched)

    out = {"benchmark": "field_stage_ab", "lens": "hybrid_asphere", "map": [n, m, w], "ks": 64,
           "threads": args.threads, "torch": torch.__version__, "runs": rows,
           "median_map_s": {"per_construction": med(False, "map_s"), "batched": med(True, "map_s")},
           "median_field_stage_s": {"per_construction": med(False, "field_stage_s"),
                                    "batched": med(True, "field_stage_s")},
           "psf_rel_l1_max": float(rel.max()), "psf_rel_l1_median": float(rel.median())}
    out["map_ratio_batched_over_per_construction"] = round(out["median_map_s"]["batched"]
                                                           / out["median_map_s"]["per_construction"], 3)
    out["field_stage_ratio_batched_over_per_construction"] = round(
        out["median_field_stage_s"]["batched"] / out["median_field_stage_s"]["per_construction"], 3)
    emit_json(out, args.output)


if __name__ == "__main__":
    main()
