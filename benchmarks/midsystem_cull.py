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

``--diagnose``: only where the 50 µm grating's error against the reference comes from (:func:`grating_diagnosis`).

Usage: ``python benchmarks/midsystem_cull.py [--periods 50 20 100] [--reference] [--diagnose] [--out FILE]`` (prints
JSON).
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402
from far_tails import rings  # noqa: E402  (the ring-by-ring relative L1)

import raywave.hybrid.midsystem as ms  # noqa: E402
from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.doe.params import GratingDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.lens.lens import Lens  # noqa: E402
from raywave.materials import get_material  # noqa: E402
from raywave.surfaces.aperture import CircularAperture  # noqa: E402
from raywave.surfaces.geometry import Plane  # noqa: E402
from raywave.surfaces.interaction import IdealLens  # noqa: E402
from raywave.surfaces.surface import Surface  # noqa: E402

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


def lens_a_tail() -> dict:
    """The engine's far tail of a plain focused beam: lens A alone (f 10 mm, F/12.5), a blank DOE plane 3 mm or 1 mm
    before its focus (the DOE-plane edge), a 256 µm crop, against the Rayleigh–Sommerfeld integral by quadrature
    (:func:`wave_truth_doe.airy_reference`), ring by ring."""
    sys_ = W.TwoLensSystem()
    a = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                is_stop=True)
    lens = Lens([a], wavelengths=(WL,), primary=0)
    ks = 128
    ref = W.airy_reference(sys_, PS, ks, n_rho=300, n_phi=512)
    out = {}
    for d in (7.0, 9.0):
        r = _psf(HybridLens(lens, BlankDOE(N, PITCH), d, sensor_pitch=PS, stop_edge="doe"), (0.0, 0.0), ks)
        out[f"doe_plane_{10 - d:g}mm_before_focus"] = rings(r.psf[0, 0].detach().numpy(), ref, ks)
    return out


def grating_diagnosis() -> dict:
    """Where the 50 µm grating's error against the wave reference comes from (0°): the six orders (DOE-plane edge, every
    order's exact edge) against the reference fed the fabricated grating; order −1 alone and ±1 against the
    reference fed those orders (``c_m e^{imφ0}``), the reference's padding 400 → 800, the best constant phase on
    ``c₊₁`` (12 values), the cross terms PSF(±1) − PSF(−1) of both (L1 norms, correlation), and order +1's own far
    tail (alone, a 256 µm crop, both PSFs scaled to the same power in their central 32 µm) ring by ring, with the
    DOE-plane edge and with the exact edge; and a plain focused beam's far tail (:func:`lens_a_tail`)."""
    field = (0.0, 0.0)
    sys_, doe, _ = _lens(50.0, field)
    phi0 = doe.design_phase_pixels(slice(None), slice(None)).detach().numpy()
    cs = ms.order_coefficients(2, True, 1.0, range(-1, 2))

    def eng(keep, ks=KS, **kw):
        ml = ms.MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=N * PITCH,
                              final_pitch=PITCH, sensor_pitch=PS, orders=keep, **kw)
        r = _psf(ml, field, ks)
        return r.psf[0, 0].detach().numpy() * (1 - float(r.energy_outside[0, 0])), r.center[0, 0].detach().numpy()

    def t(*ms_, phase=0.0):
        return sum(cs[m] * np.exp(1j * (m * phi0 + (phase if m == 1 else 0.0))) for m in ms_)

    e1, c = eng([-1])
    e2, _ = eng([-1, 1])
    e1, e2 = e1 / e1.sum(), e2 / e2.sum()
    r1 = W.sensor_psf(sys_, N, PITCH, t(-1), c, PS, KS)
    r2 = W.sensor_psf(sys_, N, PITCH, t(-1, 1), c, PS, KS)
    r2_pad = W.sensor_psf(sys_, N, PITCH, t(-1, 1), c, PS, KS, pad=800)
    scan = [float(np.abs(e2 - W.sensor_psf(sys_, N, PITCH, t(-1, 1, phase=2 * math.pi * j / 12), c, PS, KS)).sum())
            for j in range(12)]
    de, dr = e2 - e1, r2 - r1
    out = {"minus1_alone_vs_its_reference": float(np.abs(e1 - r1).sum()),
           "pm1_vs_its_reference": float(np.abs(e2 - r2).sum()),
           "reference_pad_400_vs_800": float(np.abs(r2 - r2_pad).sum()),
           "pm1_best_constant_phase_on_c+1": min(scan), "phase_scan": scan,
           "cross_term_l1_engine": float(np.abs(de).sum()), "cross_term_l1_reference": float(np.abs(dr).sum()),
           "cross_term_correlation": float((de * dr).sum() / np.sqrt((de ** 2).sum() * (dr ** 2).sum())),
           "order+1_far_tail_ring_l1": {}}
    out["lens_A_alone_far_tail_ring_l1_vs_rs_quadrature"] = lens_a_tail()
    full = W.sensor_psf(sys_, N, PITCH, doe.phase(WL).detach().numpy(), c, PS, KS)
    for name, kw in (("doe_edge", {}), ("exact_edge", {"stop_edge": "exit_pupil", "edge_step": "asm"})):
        e6, c6 = eng(None, **kw)
        assert np.allclose(c6, c)
        out[f"six_orders_{name}_vs_reference"] = float(np.abs(e6 / e6.sum() - full).sum())
    for name, kw in (("doe_edge", {}), ("exact_edge", {"stop_edge": "exit_pupil", "edge_step": "asm"})):
        ks = 128
        e, c1 = eng([1], ks, **kw)
        ref = W.sensor_psf(sys_, N, PITCH, np.exp(1j * phi0), c1, PS, ks)
        out["order+1_far_tail_ring_l1"][name] = rings(e, ref, ks, ((0, 10), (10, 30), (30, 60), (60, 90), (90, 130)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=float, nargs="*", default=[50.0, 20.0, 100.0])
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--diagnose", action="store_true", help="only grating_diagnosis() (the 50 µm grating's error)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.diagnose:
        emit_json({"issue": 46, "what": grating_diagnosis.__doc__, "command": "python benchmarks/midsystem_cull.py "
                   "--diagnose", "diagnosis": grating_diagnosis()}, a.out, indent=1)
        return
    rows = [case(p, f, a.reference) for p in a.periods for f in [(0.0, 0.0), (0.0, 1.5)]]
    out = {"issue": 46, "what": __doc__.split("\n\n")[1], "command": "python benchmarks/midsystem_cull.py "
           + " ".join(argv if argv is not None else sys.argv[1:]), "rows": rows}
    if 50.0 in a.periods:
        out["tail_over_envelope_order-5"] = tail_check()
    emit_json(out, a.out, indent=1)


if __name__ == "__main__":
    main()
