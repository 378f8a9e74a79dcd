"""Issue 46: the 16-level mid-system DOE with its weak orders and the exact edge, against the independent wave
reference of tests/wave_truth_doe.py (relative L1 of the PSF crop), with each of this round's two fixes alone and
neither (for the record: the fixes are swapped out in this process only, by replacing the module's functions).

Usage: ``python benchmarks/midsystem_orders_accuracy.py [--out FILE]`` (prints JSON; ~4 min on one CPU thread).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import warnings
from pathlib import Path

import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.midsystem as ms  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402

N, PITCH, PS, KS = 1000, 1e-3, 2e-3, 32


@contextlib.contextmanager
def variant(name: str):
    """``both`` (the library as it is), ``phase_only`` (the traced rim images for every order), ``rims_only`` (each
    order's phase at its chief ray's point), ``neither``; ``weak_doe``: the library with ``weak_edge="doe"`` (set
    in :func:`case`)."""
    one, phase = ms._CropRims.one, ms._pupil_phase
    try:
        if name in ("phase_only", "neither"):
            ms._CropRims.one = lambda self, optics, field, wavelength, depth, rim: rim
        if name in ("rims_only", "neither"):
            ms._pupil_phase = ms._absolute_phase
        yield
    finally:
        ms._CropRims.one, ms._pupil_phase = one, phase


def case(field, min_efficiency: float, name: str) -> dict:
    doe = FresnelDOE(50.0, N, PITCH, wavelength=0.55)
    doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    weak = {"weak_edge": "doe"} if name == "weak_doe" else {}
    ml = ms.MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=1.0,
                          final_pitch=PITCH, sensor_pitch=PS, min_efficiency=min_efficiency, stop_edge="exit_pupil",
                          edge_step="asm", **weak)
    t0 = time.process_time()
    with variant(name), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = ml.psf_result([field], 0.55, ks=KS)
        kept = [s for s, _ in ms.sampling_report(doe, ml.orders(0.55), box=ml.lit_box(field, 0.55))["kept"]]
    cpu = time.process_time() - t0
    center = res.center[0, 0].detach().numpy()
    ref = W.sensor_psf(sys_, N, PITCH, doe.phase(0.55).detach().numpy(), center, PS, KS)
    return {"field_deg": list(field), "min_efficiency": min_efficiency, "variant": name, "orders": kept,
            "rel_l1": W.rel_l1(res.psf[0, 0].detach().numpy(), ref), "cpu_s": round(cpu, 2)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for field in [(0.0, 0.0), (0.0, 1.5)]:
        rows.append(case(field, 0.01, "both"))  # order 1 alone: the fixes do not enter
        for name in ("both", "phase_only", "rims_only", "neither", "weak_doe"):
            rows.append(case(field, 1e-3, name))
    for field in [(0.0, 0.75), (0.0, 3.0)]:  # fields the fixes were not looked at with
        rows.append(case(field, 0.01, "both"))
        for name in ("both", "neither", "weak_doe"):
            rows.append(case(field, 1e-3, name))
    out = {"issue": 46, "what": "16-level Fresnel DOE (f 50 mm) 3 mm after ideal lens A (F/12.5) of "
           "tests/wave_truth_doe.py, stop_edge='exit_pupil', edge_step='asm'; relative L1 of the 32x32 PSF crop "
           "(2 um pixels) against the reference fed the fabricated map; bar 1e-3. variant: both = this round's "
           "library (each order's phase read over the pupil, the weak orders' stop-rim images for the crop's "
           "centre); phase_only / rims_only: one fix; neither: before; weak_doe: the library with "
           "weak_edge='doe' (the weak orders with the DOE-plane edge in one engine call, order 1 with the exact "
           "edge). orders: those kept (at 3 deg "
           "+17 steps by more than pi/2 per 1 um pixel over the lit footprint: left out by the sampling report). "
           "CPU seconds of the PSF call (one thread, shared machine).", "command": "python benchmarks/midsystem_orders_accuracy.py", "rows": rows}
    emit_json(out, args.out, indent=1)


if __name__ == "__main__":
    main()
