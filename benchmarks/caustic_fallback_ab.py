"""Issue 47: the caustic fallback's cost and accuracy, A/B in one process (single warm PSFs, ks 32, no autograd).

For each case of benchmarks/stop_edge_references.py: the default ("fallback", :func:`raywave.hybrid.coherent.
exit_pupil.go_fallback_plane` on) against the same call without the fallback ("plane": ``GO_PHASE_TOL`` = inf, the
field built on the DOE plane itself, the code before the fallback) and, for the estimate's own cost on sources that
do not trigger it, without the estimate at all ("no_estimate"); rel L1 from the converged references cached by
stop_edge_references.py (``--cache``). Times: the median of ``--repeat`` calls after one warm-up, alternating.

    PYTHONPATH=. python benchmarks/caustic_fallback_ab.py real:double_gauss:0 real:cooke_triplet:0.7 \
        --cache DIR [--repeat 3] [-o F]
"""

import argparse
import json
import math
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stop_edge_references as ser  # noqa: E402

import raywave.hybrid.coherent.exit_pupil as ep  # noqa: E402

ARMS = ("fallback", "plane", "no_estimate")


def _arm(name: str):
    """Set the module's switches for an arm; returns a function that restores them."""
    tol, plane = ep.GO_PHASE_TOL, ep.go_fallback_plane
    if name == "plane":
        ep.GO_PHASE_TOL = math.inf
    elif name == "no_estimate":
        ep.go_fallback_plane = lambda *a, **k: (None, 0.0)

    def restore():
        ep.GO_PHASE_TOL, ep.go_fallback_plane = tol, plane
    return restore


def one(hl, fld, wl, depth):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = time.perf_counter()
        r = hl.psf_result(fld, wl, ks=32, depth=depth)
        dt = time.perf_counter() - t
    fb = any("angular spectrum" in str(w.message) for w in caught)
    return r.psf[0, 0], dt, fb


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--arms", nargs="+", default=list(ARMS))
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    rows = []
    for case in a.cases:
        ref = torch.load(a.cache / f"ref_{case.replace(':', '_')}_ks32.pt", weights_only=False)["psf"]
        hl, fld, wl, depth = ser._hybrid(case, {})
        res = {arm: dict(times=[]) for arm in a.arms}
        for k in range(a.repeat + 1):  # the first round warms up
            for arm in a.arms:
                restore = _arm(arm)
                try:
                    psf, dt, fb = one(hl, fld, wl, depth)
                finally:
                    restore()
                if k:
                    res[arm]["times"].append(dt)
                res[arm].update(l1=float((psf - ref).abs().sum()), fallback=fb)
        for arm in a.arms:
            res[arm]["median_s"] = statistics.median(res[arm]["times"])
        base = res.get("plane", res[a.arms[0]])["median_s"]
        row = dict(case=case, **{arm: res[arm] for arm in a.arms},
                   ratios={arm: res[arm]["median_s"] / base for arm in a.arms})
        print(json.dumps(row), flush=True)
        rows.append(row)
        if a.output:
            Path(a.output).write_text(json.dumps(dict(
                command="OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/caustic_fallback_ab.py CASES --cache DIR",
                note="a shared 2-core machine (~4 agents, niced): ratios within one process, alternating arms",
                rows=rows), indent=1))
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
