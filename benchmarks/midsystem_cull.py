"""Issue 46: can a mid-system DOE's orders that land far outside the PSF crop be left out at equal accuracy?

System: the two-lens system of tests/wave_truth_doe.py (ideal lens A f 10 mm F/12.5, the DOE 3 mm after it, lens B
perfect for the beam, the sensor), a binary (0/π) grating DOE (1 mm, 1 µm pixels) of ``--periods`` (µm), 32×32
crop of 2 µm pixels, λ 0.55 µm, fields 0° and 1.5°. Per case and field:

* ``landing_um``: each kept order's chief ray on the sensor, µm from the crop's centre (order −1, the first of the
  two strongest);
* ``leave_out``: the relative L1 change of the PSF (against the PSF with every order of ≥ 1 %) when orders are left
  out, and the bound :func:`raywave.hybrid.midsystem.cull_orders` gives for that set (None: not a set it would
  consider: a kept order in or next to the crop);
* ``vs_reference``: relative L1 of the mid-system PSF (every order of ≥ 1 %, of ≥ 0.1 %; and with the far orders
  left out) against the independent wave reference fed the fabricated grating (every order), with ``--reference``;
* ``tail_over_envelope``: the largest ratio of order −5's intensity (alone, a 512 µm crop) to
  :func:`~raywave.hybrid.midsystem.tail_envelope` beyond 10 µm of its footprint (50 µm period only).

Usage: ``python benchmarks/midsystem_cull.py [--periods 50 20 100] [--reference] [--out FILE]`` (prints JSON).
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.midsystem as ms  # noqa: E402
from raywave.doe.params import GratingDOE  # noqa: E402

N, PITCH, PS, KS, WL = 1000, 1e-3, 2e-3, 32, 0.55


def _lens(period_um: float, field, keep=None, min_efficiency=0.01):
    doe = GratingDOE(period_um * 1e-3, N, PITCH)
    doe.fabricate(2)
    sys_ = W.TwoLensSystem(field=field)
    ml = ms.MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=N * PITCH,
                          final_pitch=PITCH, sensor_pitch=PS, orders=ms.Orders(keep=keep, min_efficiency=min_efficiency))
    return sys_, doe, ml


def _psf(ml, field, ks=KS):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ml.psf_result([field], WL, ks=ks)


def _rel(a, b) -> float:
    return float(((a - b).abs().sum() / b.abs().sum()).detach())


def case(period_um: float, field, reference: bool) -> dict:
    sys_, doe, ml = _lens(period_um, field)
    res = _psf(ml, field)
    full = res.psf[0, 0]
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        orders = ml.source_orders(field, WL, None, pms)
    land = ml.order_landings(field, WL, None, pms, orders)
    c0 = land[0][2]
    h = (0.5 * KS + 1) * PS
    crop = (c0[0] - h, c0[0] + h, c0[1] - h, c0[1] + h)
    row = {"period_um": period_um, "field_deg": list(field), "orders": [s for s, _ in orders],
           "efficiency": [round(abs(c) ** 2, 5) for _, c in orders],
           "landing_um": {f"{s:g}": [round(1e3 * (ld[2][0] - c0[0]), 1), round(1e3 * (ld[2][1] - c0[1]), 1)]
                          for (s, _), ld in zip(orders, land)}, "leave_out": []}
    eff = {s: abs(c) ** 2 for s, c in orders}
    far = sorted([s for s, _ in orders[1:]], key=lambda s: -abs(land[[o for o, _ in orders].index(s)][2][0] - c0[0]))
    sets = [far[:k] for k in range(1, len(far))]
    for left in sets:
        keep = [int(s) for s, _ in orders if s not in left]
        psf = _psf(_lens(period_um, field, keep)[2], field).psf[0, 0]
        sub = [(s, c) for s, c in orders if s in left]
        idx = [0] + [[o for o, _ in orders].index(s) for s in left]
        land_sub = [land[i] for i in idx]
        kept_all = [orders[0]] + sub
        # the bound for this set: cull_orders with a tolerance that admits everything it can bound
        kept, culled, bound = ms.cull_orders(kept_all, land_sub, crop, WL, 0.999999)
        bound = bound if len(culled) == len(sub) else None
        row["leave_out"].append({"orders": left, "efficiency": round(sum(eff[s] for s in left), 5),
                                 "rel_l1_vs_all": _rel(psf, full), "bound": bound})
    if reference:
        ref = torch.as_tensor(W.sensor_psf(sys_, N, PITCH, doe.phase(WL).detach().numpy(),
                                           res.center[0, 0].detach().numpy(), PS, KS))
        row["vs_reference"] = {"all_1e-2": _rel(full, ref)}
        fine = _psf(_lens(period_um, field, None, 1e-3)[2], field).psf[0, 0]
        row["vs_reference"]["all_1e-3"] = _rel(fine, ref)
        for left in sets:
            keep = [int(s) for s, _ in orders if s not in left]
            psf = _psf(_lens(period_um, field, keep)[2], field).psf[0, 0]
            row["vs_reference"]["without " + " ".join(f"{s:g}" for s in left)] = _rel(psf, ref)
    return row


def tail_check() -> float:
    """max over pixels ≥ 10 µm beyond order −5's footprint of its intensity / tail_envelope (50 µm grating, 0°)."""
    _, _, ml = _lens(50.0, (0.0, 0.0), [-5])
    res = _psf(ml, (0.0, 0.0), ks=256)
    p = res.psf[0, 0] * (1 - res.energy_outside[0, 0])
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    (box, na, c), = ml.order_landings((0.0, 0.0), WL, None, pms, ml.orders(WL))
    idx = torch.arange(256, dtype=torch.float64) - 128
    x, y = torch.meshgrid(res.center[0, 0, 0].detach() + idx * PS, res.center[0, 0, 1].detach() + idx * PS,
                          indexing="xy")
    gx = torch.clamp(torch.maximum(box[0] - (x + PS / 2), (x - PS / 2) - box[1]), min=0)
    gy = torch.clamp(torch.maximum(box[2] - (y + PS / 2), (y - PS / 2) - box[3]), min=0)
    rho = torch.sqrt(gx ** 2 + gy ** 2)
    sel = rho > 0.01
    return float((p.detach()[sel] / PS ** 2 / ms.tail_envelope(rho[sel], na, WL)).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=float, nargs="*", default=[50.0, 20.0, 100.0])
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = [case(p, f, a.reference) for p in a.periods for f in [(0.0, 0.0), (0.0, 1.5)]]
    out = {"issue": 46, "what": __doc__.split("\n\n")[1], "command": "python benchmarks/midsystem_cull.py "
           + " ".join(argv if argv is not None else sys.argv[1:]), "rows": rows}
    if 50.0 in a.periods:
        out["tail_over_envelope_order-5"] = tail_check()
    emit_json(out, a.out, indent=1)


if __name__ == "__main__":
    main()
