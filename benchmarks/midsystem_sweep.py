"""Issue 46: where the mid-system DOE's accuracy claims hold, away from the one system the tests use. Each case is
the two-lens system of tests/wave_truth_doe.py (ideal lens A the stop, gap1, the DOE, gap2, lens B perfect for the
beam it receives, the sensor) with one thing changed (field direction and angle, lens A's and B's focal lengths and
F-number, the DOE's place, the wavelength, the Fresnel DOE's focal length, the 16-level DOE with its weak orders,
a conformal DOE's curvature), against that independent reference (relative L1 of the 32×32 PSF crop, 2 µm pixels),
with the reference's own convergence (padding ``pad`` → ``2·pad``; the conformal reference's slice step halved) where
asked; and the grating in the Cooke triplet at another period / wavelength (order angles against the grating
equation, efficiencies against the staircase formula). The settings are the tests' (tests/test_midsystem_accuracy.py,
tests/test_midsystem_two_does.py, tests/test_midsystem_grating.py).

Usage: ``python benchmarks/midsystem_sweep.py [--cases NAME ...] [--list] [--out FILE]`` (prints one JSON line a
case, then the whole report; ``--out`` is rewritten after every case, so an interrupted run keeps its rows);
``--diagnose CASE --edges ...``: a 16-level case with its orders kept in subsets, each against the reference fed the
same orders; ``--power-vs-plane``: the grating's field power against the engine's plane's distance and the
pitch; ``--gradients``: the finite-difference check at other fields and seeds. One thread;
2–10 s a case (every case: ~3.5 min, < 3 GB).
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import (DOEPhaseSurface, MidSystemLens, order_coefficients,  # noqa: E402
                                      sampling_report)

PITCH, PS, KS = 1e-3, 2e-3, 32
ASM = {"stop_edge": "exit_pupil", "edge_step": "asm"}
#: the bars (issue 46): 1e-3 for blank / Fresnel / 16 levels, 5e-3 for the conformal DOE
BAR = {"blank": 1e-3, "fresnel": 1e-3, "16-level": 1e-3, "conformal": 5e-3}


def _case(name, kind, field=(0.0, 0.0), edge="default", conv=False, **sys_kw):
    return name, {"kind": kind, "field": field, "edge": edge, "conv": conv, "sys": sys_kw}


def _diag(theta):
    t = math.degrees(math.atan(math.tan(math.radians(theta)) / math.sqrt(2)))
    return (t, t)


#: name → case. ``sys``: TwoLensSystem's fields (lengths mm, λ µm) plus ``n`` (the DOE's pixels a side, 1 µm) and
#: ``f_design`` (the Fresnel DOE's focal length; ``f_doe`` follows it). ``edge``: "default" (MidSystemLens's
#: default: ``stop_edge="auto"`` since 2026-12-01, the row's ``edge_chosen``), "cut" (``stop_edge="doe"``, the default
#: before), "asm" (the exact edge), "asm_weak" (the exact edge, min_efficiency 1e-3), "asm_weak_doe" (the same,
#: weak_edge doe).
CASES = dict([
    # field directions and angles (the tests: (0, 0), (0, 1.5))
    _case("fresnel_x1.5", "fresnel", (1.5, 0.0), f_design=50.0),
    _case("fresnel_diag1.5", "fresnel", _diag(1.5), f_design=50.0),
    _case("fresnel_y3", "fresnel", (0.0, 3.0), f_design=50.0, conv=True),
    _case("fresnel_diag3", "fresnel", _diag(3.0), f_design=50.0),
    _case("blank_y3", "blank", (0.0, 3.0)),
    _case("blank_diag3", "blank", _diag(3.0)),
    _case("fresnel_asm_diag2.5", "fresnel", _diag(2.5), edge="asm", f_design=50.0),
    # F-number, focal lengths
    _case("fresnel_F8_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, radius_a=0.625, n=1200),
    _case("fresnel_fA20_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, f_a=20.0, radius_a=0.8, gap1=6.0, gap2=6.0,
          f_b=20.0, n=1600, conv=True),
    _case("fresnel_asm_fA20_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=50.0, f_a=20.0, radius_a=0.8,
          gap1=6.0, gap2=6.0, f_b=20.0, n=1600),
    _case("fresnel_asm_F8_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=50.0, radius_a=0.625, n=1200),
    _case("blank_fA5_F6_y2", "blank", (0.0, 2.0), f_a=5.0, radius_a=0.4, gap1=1.5, gap2=1.5, f_b=5.0, n=800),
    _case("fresnel_fB6_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, f_b=6.0),
    # the DOE's place
    _case("fresnel_nearA_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, gap1=1.0, gap2=5.0),
    _case("fresnel_asm_nearA_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=50.0, gap1=1.0, gap2=5.0),
    _case("fresnel_nearB_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, gap1=5.0, gap2=1.0),
    # wavelengths (the DOE designed for the wavelength: f_doe holds there)
    _case("fresnel_0.45_y1.5", "fresnel", (0.0, 1.5), f_design=50.0, wavelength=0.45),
    _case("fresnel_0.65_x1.5", "fresnel", (1.5, 0.0), f_design=50.0, wavelength=0.65),
    # the Fresnel DOE's power
    _case("fresnel_f200_y1.5", "fresnel", (0.0, 1.5), f_design=200.0),
    _case("fresnel_f20_y1.5", "fresnel", (0.0, 1.5), f_design=20.0),
    _case("fresnel_fm30_y1.5", "fresnel", (0.0, 1.5), f_design=-30.0),
    _case("fresnel_f10_y1.5", "fresnel", (0.0, 1.5), f_design=10.0),
    _case("fresnel_asm_f20_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=20.0),
    _case("fresnel_asm_fm30_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=-30.0),
    _case("fresnel_asm_f10_y1.5", "fresnel", (0.0, 1.5), edge="asm", f_design=10.0),
    # the 16-level DOE with its weak orders (the tests' settings)
    _case("16_weak_x1.5", "16-level", (1.5, 0.0), edge="asm_weak", f_design=50.0),
    _case("16_weak_diag1.5", "16-level", _diag(1.5), edge="asm_weak", f_design=50.0),
    _case("16_weak_y2.5", "16-level", (0.0, 2.5), edge="asm_weak", f_design=50.0),
    _case("16_weakdoe_diag1.5", "16-level", _diag(1.5), edge="asm_weak_doe", f_design=50.0),
    _case("16_weak_0.45_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=50.0, wavelength=0.45),
    _case("16_weak_f100_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=100.0),
    _case("16_weakdoe_f100_y1.5", "16-level", (0.0, 1.5), edge="asm_weak_doe", f_design=100.0),
    _case("16_weakdoe_f100_y1.5_fd0.5", "16-level", (0.0, 1.5), edge="asm_weak_doe", f_design=100.0,
          final_distance=0.5),
    _case("16_weakdoe_f100_y1.5_fd1", "16-level", (0.0, 1.5), edge="asm_weak_doe", f_design=100.0,
          final_distance=1.0),
    _case("16_weakdoe_f100_y0_fd1", "16-level", (0.0, 0.0), edge="asm_weak_doe", f_design=100.0,
          final_distance=1.0),
    _case("16_weak_f100_y1.5_fd1", "16-level", (0.0, 1.5), edge="asm_weak", f_design=100.0, final_distance=1.0),
    _case("16_xpweak_f100_y1.5", "16-level", (0.0, 1.5), edge="xp_weak", f_design=100.0),
    _case("16_weakdoe_f100_y0", "16-level", (0.0, 0.0), edge="asm_weak_doe", f_design=100.0),
    _case("16_defweak_f100_y1.5", "16-level", (0.0, 1.5), edge="default_weak", f_design=100.0),
    _case("16_weak_0.65_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=50.0, wavelength=0.65),
    _case("16_weak_nearA_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=50.0, gap1=1.0, gap2=5.0),
    _case("16_weak_F8_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=50.0, radius_a=0.625, n=1200),
    _case("16_weak_nearB_y1.5", "16-level", (0.0, 1.5), edge="asm_weak", f_design=50.0, gap1=5.0, gap2=1.0),
    # conformal (the test: R 10 mm, Fresnel f 10 mm, 3°)
    _case("conformal_R10_y0", "conformal", (0.0, 0.0), f_design=10.0, doe_radius=10.0),
    _case("conformal_R20_y3", "conformal", (0.0, 3.0), f_design=10.0, doe_radius=20.0, conv=True),
    _case("conformal_Rm10_y3", "conformal", (0.0, 3.0), f_design=10.0, doe_radius=-10.0),
    _case("conformal_R10_diag3", "conformal", _diag(3.0), f_design=10.0, doe_radius=10.0),
    _case("conformal_Rinf_y3", "conformal", (0.0, 3.0), f_design=10.0, doe_radius=math.inf),
    _case("conformal_asm_Rinf_y3", "conformal", (0.0, 3.0), edge="asm", f_design=10.0, doe_radius=math.inf),
    _case("conformal_asm_R10_y3", "conformal", (0.0, 3.0), edge="asm", f_design=10.0, doe_radius=10.0),
    _case("conformal_asm_R20_y3", "conformal", (0.0, 3.0), edge="asm", f_design=10.0, doe_radius=20.0),
    _case("conformal_asm_Rm10_y3", "conformal", (0.0, 3.0), edge="asm", f_design=10.0, doe_radius=-10.0,
          conv=True),
    _case("conformal_R10_f50_y1.5", "conformal", (0.0, 1.5), f_design=50.0, doe_radius=10.0),
])
XP_FRESNEL = {"stop_edge": "exit_pupil", "edge_step": "fresnel"}
#: name → (period mm, wavelength µm, DOE pixels a side, pitch mm, final plane size mm[, its distance after the last
#: vertex mm (default 41.5, the test's), the stop edge's keywords]): the test's 100 µm grating has 1000 pixels of
#: 12 µm (8.3 a period); the final plane holds orders ±1 (deflected by λ/Λ, ~EFL·λ/Λ on the sensor)
GRATINGS = {"grating_50um_0.65": (0.05, 0.65, 2400, 0.005, 2.0), "grating_200um_0.55": (0.2, 0.55, 1000, 0.012, 1.0),
            "grating_100um_0.65": (0.1, 0.65, 1000, 0.012, 1.6), "grating_50um_0.45": (0.05, 0.45, 2400, 0.005, 1.6),
            "grating_25um_0.45": (0.025, 0.45, 2400, 0.005, 2.4), "grating_100um_0.45": (0.1, 0.45, 1000, 0.012, 0.8),
            # the engine's plane 40 mm after the last vertex (2.4 mm before the sensor) instead of the test's 41.5
            "grating_50um_0.65_fd40": (0.05, 0.65, 2400, 0.005, 2.0, 40.0),
            "grating_25um_0.45_fd40": (0.025, 0.45, 2400, 0.005, 2.4, 40.0),
            "grating_50um_0.45_fd40": (0.05, 0.45, 2400, 0.005, 1.6, 40.0),
            # (a 1.6 mm plane: with the exit-pupil edge that "auto" takes here, 0.8 mm cut the ±1 orders' ripple band,
            # 0.4 % of their power, 1.41e-3 in efficiency; 4.2e-6 on 1.6 mm, 2026-12-01)
            "grating_100um_0.45_fd40": (0.1, 0.45, 1000, 0.012, 1.6, 40.0),
            # the test's plane (41.5 mm) with the exit-pupil edge (the Fresnel step: the exact one's lattice is too big)
            "grating_50um_0.65_xp": (0.05, 0.65, 2400, 0.005, 2.0, 41.5, XP_FRESNEL),
            "grating_25um_0.45_xp": (0.025, 0.45, 2400, 0.005, 2.4, 41.5, XP_FRESNEL),
            "grating_100um_0.45_xp": (0.1, 0.45, 1000, 0.012, 0.8, 41.5, XP_FRESNEL),
            "grating_20um_0.55_undersampled": (0.02, 0.55, 1000, 0.012, 0.8)}
COARSE = ["fresnel_x1.5", "fresnel_diag1.5", "fresnel_y3", "blank_diag3", "fresnel_fA20_y1.5", "fresnel_F8_y1.5",
          "fresnel_nearA_y1.5", "fresnel_nearB_y1.5", "fresnel_0.45_y1.5", "fresnel_0.65_x1.5", "fresnel_f200_y1.5",
          "fresnel_f20_y1.5", "16_weak_diag1.5", "16_weak_x1.5", "conformal_R20_y3", "conformal_Rm10_y3",
          "grating_50um_0.65", "grating_200um_0.55"]


def _edge_kw(edge):
    return {"default": {}, "cut": {"stop_edge": "doe"}, "asm": dict(ASM), "asm_weak": dict(ASM, min_efficiency=1e-3),
            "asm_weak_doe": dict(ASM, min_efficiency=1e-3, weak_edge="doe"),
            "xp_weak": {"stop_edge": "exit_pupil", "min_efficiency": 1e-3},
            "xp_fresnel_weak": {"stop_edge": "exit_pupil", "edge_step": "fresnel", "min_efficiency": 1e-3},
            "default_weak": {"min_efficiency": 1e-3}}[edge]


def run_case(name: str, spec: dict) -> dict:
    """One reference comparison: the row of the report."""
    kw = dict(spec["sys"])
    n = kw.pop("n", 1000)
    f_design = kw.pop("f_design", None)
    final_distance = kw.pop("final_distance", 0.01)
    wl = kw.get("wavelength", 0.55)
    kind, field = spec["kind"], tuple(spec["field"])
    if kind == "blank":
        doe, f_doe = BlankDOE(n, PITCH), math.inf
    else:
        doe, f_doe = FresnelDOE(f_design, n, PITCH, wavelength=wl), f_design
        if kind == "16-level":
            doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=f_doe, field=field, **kw)
    conformal = kind == "conformal"
    lens = M.two_lens_split(sys_) if conformal else M.two_lens(sys_)
    ml = MidSystemLens(lens, doe, 1 if conformal else 0, None if conformal else sys_.gap1,
                       final_distance=final_distance,
                       final_size=n * PITCH, final_pitch=PITCH, sensor_pitch=PS, **_edge_kw(spec["edge"]))
    t0 = time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = ml.psf_result([field], wl, ks=KS)
        orders = [round(float(s), 6) for s, _ in ml.orders(wl)]
    t_engine = time.process_time() - t0
    edges = [list(e) for e in ml.edges([field], wl)]
    center = res.center[0, 0].detach().numpy()
    phase = None if kind == "blank" else doe.phase(wl).detach().numpy()
    t0 = time.process_time()
    extra = {"sag_step": 5e-4} if conformal else {}
    ref = W.sensor_psf(sys_, n, PITCH, phase, center, PS, KS, **extra)
    t_ref = time.process_time() - t0
    psf = res.psf[0, 0].detach().numpy()
    row = {"case": name, "kind": kind, "field_deg": [round(v, 9) for v in field], "edge": spec["edge"],
           "system": dict(sys_.__dict__, n_doe=n, doe_radius=str(sys_.doe_radius), f_doe=str(sys_.f_doe),
                          f_doe2=str(sys_.f_doe2), field=None),
           "orders": orders, "edge_chosen": edges, "rel_l1": W.rel_l1(psf, ref), "bar": BAR[kind],
           "center_vs_image_mm": float(np.abs(center - sys_.image()[:2]).max()),
           "warnings": sorted({f"{w.category.__name__}: {str(w.message)[:160]}" for w in caught
                                if not issubclass(w.category, DeprecationWarning)}),
           "cpu_engine_s": round(t_engine, 1), "cpu_reference_s": round(t_ref, 1)}
    if kind == "16-level":
        # the reference fed only the orders the engine kept (Σ c_m e^{imφ0} on the DOE's samples): how far leaving
        # the others out moves the truth, and the engine against that truncated truth (the method's own error)
        kept = [s for s, _ in sampling_report(doe, ml.orders(wl), box=ml.lit_box(field, wl))["kept"]]
        phi0 = DOEPhaseSurface(doe).phase_map()[2:-2, 2:-2].detach().numpy()
        cs = order_coefficients(16, True, 1.0, [int(round(m)) for m in kept])
        trunc = W.sensor_psf(sys_, n, PITCH, sum(c * np.exp(1j * m * phi0) for m, c in cs.items()), center, PS, KS)
        row["kept_orders"] = [int(round(m)) for m in kept]
        row["orders_diagnosis"] = {"ref_kept_orders_vs_ref_fabricated": W.rel_l1(trunc, ref),
                                   "rel_l1_vs_ref_kept_orders": W.rel_l1(psf, trunc)}
    if spec["conv"]:
        t0 = time.process_time()
        if conformal:
            fine = W.sensor_psf(sys_, n, PITCH, phase, center, PS, KS, sag_step=2.5e-4)
            row["reference_convergence"] = {"what": "sag_step 0.5 -> 0.25 um", "ref_change": W.rel_l1(ref, fine),
                                            "rel_l1_vs_finer": W.rel_l1(psf, fine)}
        else:
            fine = W.sensor_psf(sys_, n, PITCH, phase, center, PS, KS, pad=800)
            row["reference_convergence"] = {"what": "pad 400 -> 800", "ref_change": W.rel_l1(ref, fine),
                                            "rel_l1_vs_finer": W.rel_l1(psf, fine)}
        row["cpu_convergence_s"] = round(time.process_time() - t0, 1)
    row["max_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return row


def diagnose_orders(name: str, subsets, edges=("asm_weak_doe",)) -> list:
    """The 16-level case ``name`` with only the orders of each subset kept (``orders=[...]``), each against the
    reference fed those orders (``Σ c_m e^{imφ0}`` on the DOE's samples): which order's model error it is."""
    spec = CASES[name]
    kw = dict(spec["sys"])
    n, f_design = kw.pop("n", 1000), kw.pop("f_design")
    wl, field = kw.get("wavelength", 0.55), tuple(spec["field"])
    doe = FresnelDOE(f_design, n, PITCH, wavelength=wl)
    doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=f_design, field=field, **kw)
    phi0 = DOEPhaseSurface(doe).phase_map()[2:-2, 2:-2].detach().numpy()
    rows = []
    for subset in subsets:
        cs = order_coefficients(16, True, 1.0, subset)
        for edge in edges:
            opts = dict(_edge_kw(edge), min_efficiency=0.0)  # the subset decides
            t0 = time.process_time()
            try:
                ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=n * PITCH,
                                   final_pitch=PITCH, sensor_pitch=PS, orders=list(subset), **opts)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = ml.psf_result([field], wl, ks=KS)
            except ValueError as exc:
                rows.append({"case": name, "orders": list(subset), "edge": edge, "refused": str(exc)[:200]})
                print(json.dumps(rows[-1]), flush=True)
                continue
            center = res.center[0, 0].detach().numpy()
            ref = W.sensor_psf(sys_, n, PITCH, sum(c * np.exp(1j * m * phi0) for m, c in cs.items()), center, PS, KS)
            rows.append({"case": name, "orders": list(subset), "edge": edge,
                         "rel_l1_vs_ref_of_those_orders": W.rel_l1(res.psf[0, 0].detach().numpy(), ref),
                         "cpu_s": round(time.process_time() - t0, 1)})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def run_grating(name: str, period: float, wl: float, n: int, pitch: float, final_size: float,
                final_distance: float = 41.5, edge: dict | None = None) -> dict:
    """The grating in the Cooke triplet (tests/test_midsystem_grating.py's checks) at another period / wavelength:
    order angles against the grating equation (max |Δθ| rad, on axis and at (3°, 5°)), each order's efficiency
    against the staircase formula."""
    import raywave
    from raywave.doe.efficiency import detuning, staircase_efficiency
    from raywave.doe.params import GratingDOE
    from raywave.hybrid.midsystem import doe_orders, insert_doe
    from raywave.lens.sources import point_source_rays

    after, dist = 1, 3.0
    lens = raywave.load_lens("cooke_triplet")
    doe = GratingDOE(period, n, pitch, material="FUSED_SILICA")
    doe.fabricate(2)
    try:  # the library's sampling check (the psf path runs it): an under-sampled grating is refused there
        sampling = {k: v for k, v in sampling_report(doe, doe_orders(doe, wl)).items() if k in ("max_step", "kept")}
        sampling = json.loads(json.dumps(sampling, default=str))
    except ValueError as exc:
        sampling = {"refused": str(exc)[:300]}
    edge = dict(edge or {})
    ml = MidSystemLens(lens, doe, after, dist, final_distance=final_distance, final_size=final_size, final_pitch=1e-3,
                       sensor_pitch=2e-3, min_efficiency=0.05, **edge)
    t0 = time.process_time()
    orders = ml.orders(wl)
    lam_mm = wl * 1e-3
    angle_err = {}
    for field in [(0.0, 0.0), (3.0, 5.0)]:
        for scale, _ in orders:
            lm = insert_doe(lens, after, dist, DOEPhaseSurface(doe, scale), 1.0, doe)
            rays = point_source_rays(lm, torch.tensor([field], dtype=torch.float64), [wl], pupil=(
                torch.tensor([0.0, 0.5, -0.3, 0.0]), torch.tensor([0.0, 0.2, 0.6, -0.8])), aim="full")
            before, after_ = lm.trace(rays, stop=after + 1), lm.trace(rays, stop=after + 2)
            n_med = float(lm.surfaces[after].material.n(torch.tensor(wl, dtype=torch.float64)))
            d1, d2 = before.d[0, 0], after_.d[0, 0]
            expected = torch.asin((n_med * d1[:, 0] + scale * lam_mm / period) / n_med)
            err = float((torch.asin(d2[:, 0]) - expected).abs().max().detach())
            err_y = float((d2[:, 1] - d1[:, 1]).abs().max().detach())
            angle_err[f"{field}:{round(scale)}"] = [err, err_y, bool(after_.valid.all())]
    alpha = detuning("FUSED_SILICA", wl, 0.55)
    blank = MidSystemLens(lens, BlankDOE(n, pitch), after, dist, final_distance, final_size, 1e-3, sensor_pitch=2e-3,
                          **edge)
    # the orders and the blank through the same edge: the blank's (the default "auto" decides it on axis)
    chosen = blank.edges([(0.0, 0.0)], wl)[0]
    blank, ml = blank.with_edge(*chosen), ml.with_edge(*chosen)
    p_blank = float((blank.source_field((0.0, 0.0), wl)[0].envelope.abs() ** 2).sum())
    eff = {}
    for scale, c in orders:
        fd = ml.order_lens(scale, False).doe_fields([(0.0, 0.0)], [wl])[0][0]
        eta = abs(c) ** 2 * float((fd.envelope.abs() ** 2).sum()) / p_blank
        eff[str(round(scale))] = [eta, staircase_efficiency(int(round(scale)), 2, alpha)]
    return {"case": name, "kind": "grating", "period_mm": period, "wavelength": wl, "alpha": alpha,
            "doe_pixels": n, "doe_pitch_mm": pitch, "final_distance_mm": final_distance, "edge": edge,
            "edge_chosen": list(chosen),
            "final_size_mm": final_size, "sampling_report": sampling,
            "orders": [round(float(s), 6) for s, _ in orders],
            "max_angle_err_rad": max(v[0] for v in angle_err.values()), "angle_err": angle_err,
            "max_eff_err": max(abs(a - b) for a, b in eff.values()), "efficiency_vs_staircase": eff,
            "bar": {"angle_rad": 1e-9, "efficiency": 1e-3}, "cpu_s": round(time.process_time() - t0, 1)}


def power_vs_plane(distances=(38.0, 40.0, 41.0, 41.5, 42.0)) -> list:
    """The 50 µm binary grating at 0.65 µm in the Cooke triplet: the power of the field on the engine's plane (its
    envelope's Σ|u|², 1 µm samples) for a blank DOE and for order +1 (c = 1) against the plane's distance after the
    last vertex (the sensor at 42.38 mm): the field's power is not conserved near the focus, and not by the same
    factor for the two beams, which moves the efficiencies read there; with the exit-pupil edge (Fresnel step) at
    38 and 41.5 mm, which conserves it. (No ray crosses before 41.5 mm: ``raywave.lens.analysis.beam_folds`` on
    32² … 256² stop cells reads 0 there, 0.47–0.49 at 42 mm.)"""
    import raywave
    from raywave.doe.params import GratingDOE

    lens = raywave.load_lens("cooke_triplet")
    doe = GratingDOE(0.05, 2400, 0.005, material="FUSED_SILICA")
    doe.fabricate(2)
    rows = []
    for dist, edge in [(d, {"stop_edge": "doe"}) for d in distances] + [(d, XP_FRESNEL) for d in (38.0, 41.5)]:
        ml = MidSystemLens(lens, doe, 1, 3.0, final_distance=dist, final_size=2.0, final_pitch=1e-3,
                           sensor_pitch=2e-3, min_efficiency=0.05, **edge)
        blank = MidSystemLens(lens, BlankDOE(2400, 0.005), 1, 3.0, dist, 2.0, 1e-3, sensor_pitch=2e-3, **edge)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fb = blank.source_field((0.0, 0.0), 0.65)[0]
            fo = ml.order_lens(1.0, False).doe_fields([(0.0, 0.0)], [0.65])[0][0]
        pb, po = float((fb.envelope.abs() ** 2).sum()), float((fo.envelope.abs() ** 2).sum())
        rows.append({"final_distance_mm": dist, "edge": edge, "blank_power": pb,
                     "order1_power": po, "order1_over_blank_minus_1": po / pb - 1,
                     "beam_samples": int(fb.envelope.shape[0]),
                     "warnings": sorted({str(w.message)[:160] for w in caught
                                         if not issubclass(w.category, DeprecationWarning)})})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def power_vs_pitch() -> list:
    """The blank of :func:`power_vs_plane` (default cut) on the planes 38 and 41.5 mm sampled at 1, 0.5, 0.25 µm:
    Σ|u|²·p² converges to first order in the pitch, and the loss at 1 µm is what the cut's amplitude coverage
    predicts: a ramp ``c = clamp(0.5 + d/p, 0, 1)`` on the amplitude has Σc² short of the area by p/6 a unit of rim
    length, so the loss is ``p · 2πR · I_rim / 6 / P`` (R the beam's radius, I_rim its irradiance just inside the
    rim, from the finest sampling)."""
    import raywave

    lens = raywave.load_lens("cooke_triplet")
    rows = []
    for dist, size in ((38.0, 2.0), (41.5, 0.4)):
        for pitch in (1e-3, 5e-4, 2.5e-4):
            blank = MidSystemLens(lens, BlankDOE(2400, 0.005), 1, 3.0, dist, size, pitch, sensor_pitch=2e-3)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fd = blank.order_lens(0.0, False).doe_fields([(0.0, 0.0)], [0.65])[0][0]
            inten = (fd.envelope.abs() ** 2).detach().numpy()
            power = float(inten.sum()) * (pitch / 1e-3) ** 2
            row = {"final_distance_mm": dist, "pitch_mm": pitch, "blank_power_per_um2": power}
            if pitch == 2.5e-4:
                x, y = (c.numpy() for c in fd.grid.coordinates())
                cx = float((inten.sum(0) * x).sum() / inten.sum())
                cy = float((inten.sum(1) * y).sum() / inten.sum())
                r = np.hypot(x[None, :] - cx, y[:, None] - cy)
                rad = float(r[inten > 0].max())
                i_rim = float(inten[(r > rad - 3e-3) & (r < rad - 1.5e-3)].mean())
                p_tot = float(inten.sum()) * pitch * pitch
                row.update({"beam_radius_um": rad * 1e3, "rim_over_mean_irradiance": i_rim * math.pi * rad ** 2 / p_tot,
                            "predicted_loss_at_1um": 1e-3 * 2 * math.pi * rad * i_rim / 6 / p_tot})
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def gradient_checks() -> list:
    """tests/test_midsystem_accuracy.py's finite-difference check (Σ w·PSF, 16×16, the Fresnel DOE on 800 1 µm
    pixels, the default cut) at other fields, weights' seeds and DOE powers: the autograd derivative with respect to
    the DOE's focal length and lens A's against central differences at relative steps 1e-5 / 1e-6 / 1e-7."""
    rows = []
    cases = [((1.0, 0.0), 7, 50.0), (_diag(1.0), 11, 50.0), (_diag(1.0), 3, 50.0), ((0.0, 1.0), 5, 20.0),
             ((0.0, 0.0), 13, -30.0)]
    for field, seed, f in cases:
        sys_ = W.TwoLensSystem(f_doe=f, field=field)
        doe = FresnelDOE(f, 800, PITCH, wavelength=0.55)
        lens = M.two_lens(sys_)
        ml = MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=0.8, final_pitch=PITCH,
                           sensor_pitch=PS)
        w = torch.rand(16, 16, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)

        def loss():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return (ml.psf([field], 0.55, ks=16)[0, 0] * w).sum()

        params = {"doe focal length": doe.focal_length,
                  "lens A focal length": lens.surfaces[0].interaction.focal_length}
        for name, step, g, fd in M.central_differences(loss, params, (1e-5, 1e-6, 1e-7)):
            rows.append({"field_deg": list(field), "seed": seed, "f_doe": f, "param": name, "step": step,
                         "autograd": g, "central_difference": fd, "rel_err": abs(g - fd) / abs(fd)})
            print(json.dumps(rows[-1]), flush=True)
    rows += _conformal_two_doe_gradients()
    return rows


def _conformal_two_doe_gradients() -> list:
    """tests/test_midsystem_two_does.py's gradient check (the error against ``Σ|w·∂PSF|``, the central differences'
    terms) at 1° along (1, 1)/√2 with the weights' seed 9: the conformal surface's curvature and its DOE's focal
    length, the second of two DOEs' focal length."""
    field = _diag(1.0)
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    sys_c = W.TwoLensSystem(f_doe=10.0, field=field, doe_radius=10.0)
    lens_c = M.two_lens_split(sys_c)
    doe_c = FresnelDOE(10.0, 800, PITCH, wavelength=0.55)
    conf = MidSystemLens(lens_c, doe_c, 1, None, final_distance=0.01, final_size=0.8, final_pitch=PITCH,
                         sensor_pitch=PS)
    sys_t = W.TwoLensSystem(f_doe=50.0, f_doe2=-80.0, gap1=3.0, gap12=1.0, gap2=2.0, field=field)
    d1, d2 = FresnelDOE(50.0, 800, PITCH, wavelength=0.55), FresnelDOE(-80.0, 800, PITCH, wavelength=0.55)
    two = MidSystemLens(M.two_lens(sys_t), [d1, d2], 0, [3.0, 4.0], final_distance=0.01, final_size=0.8,
                        final_pitch=PITCH, sensor_pitch=PS)
    rows = []
    for label, ml, prm in [("conformal curvature", conf, lens_c.surfaces[1].geometry.curvature),
                           ("conformal DOE focal length", conf, doe_c.focal_length),
                           ("second DOE focal length", two, d2.focal_length)]:
        def psf():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return ml.psf([field], 0.55, ks=16)[0, 0]

        g = float(torch.autograd.grad((psf() * w).sum(), prm)[0])
        for step in (1e-6, 1e-7):
            terms = M.central_difference_terms(psf, w, prm, step)
            rows.append({"field_deg": list(field), "seed": 9, "param": label, "step": step, "autograd": g,
                         "central_difference": float(terms.sum()),
                         "err_over_sum_abs_terms": abs(g - float(terms.sum())) / float(terms.abs().sum())})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=None, help="case names (default: the coarse selection)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--out", default=None, help="JSON file: rows already there are kept (a case run again replaces "
                    "its row)")
    ap.add_argument("--diagnose", default=None, help="a 16-level case: its orders kept in subsets (see "
                    "diagnose_orders), rows added to --out's 'diagnosis'")
    ap.add_argument("--edges", nargs="*", default=["asm_weak_doe"])
    ap.add_argument("--power-vs-plane", action="store_true", help="the grating's power against the engine's "
                    "plane's distance (power_vs_plane), into --out's 'power_vs_plane'")
    ap.add_argument("--gradients", action="store_true", help="the FD gradient check at other fields and seeds "
                    "(gradient_checks), into --out's 'gradient_checks'")
    args = ap.parse_args(argv)
    if args.gradients:
        torch.set_num_threads(1)
        rows = gradient_checks()
        if args.out:
            report = json.loads(Path(args.out).read_text())
            report["gradient_checks"] = rows
            Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        return
    if args.power_vs_plane:
        torch.set_num_threads(1)
        rows, pitch_rows = power_vs_plane(), power_vs_pitch()
        if args.out:
            report = json.loads(Path(args.out).read_text())
            report["power_vs_plane"], report["power_vs_pitch"] = rows, pitch_rows
            Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        return
    if args.diagnose:
        torch.set_num_threads(1)
        subsets = [[1], [1, -15], [1, 17], [1, -31], [1, -15, 17, -31]]
        rows = diagnose_orders(args.diagnose, subsets, args.edges)
        if args.out:
            report = json.loads(Path(args.out).read_text())
            keep = [r for r in report.get("diagnosis", []) if r["case"] != args.diagnose or r["edge"] not in args.edges]
            report["diagnosis"] = keep + rows
            Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        return
    if args.list:
        print("\n".join(list(CASES) + list(GRATINGS)))
        return
    torch.set_num_threads(1)
    names = args.cases or COARSE
    unknown = [c for c in names if c not in CASES and c not in GRATINGS]
    if unknown:
        raise SystemExit(f"unknown cases {unknown}; --list names them")
    report = {"issue": 46, "what": __doc__.split("\n\n")[0].replace("\n", " "),
              "command": "OMP_NUM_THREADS=1 python benchmarks/midsystem_sweep.py --cases $(python "
                         "benchmarks/midsystem_sweep.py --list) --out FILE; then --diagnose 16_weakdoe_f100_y0 --edges "
                         "asm_weak_doe default_weak asm_weak --out FILE; --power-vs-plane --out FILE; --gradients "
                         "--out FILE",
              "rows": []}
    if args.out and Path(args.out).exists():
        report = json.loads(Path(args.out).read_text())
    for name in names:
        try:
            row = run_grating(name, *GRATINGS[name]) if name in GRATINGS else run_case(name, CASES[name])
        except ValueError as exc:  # a refusal (the library's own check) is a result too
            spec = CASES.get(name, {})
            row = {"case": name, "kind": spec.get("kind", "grating"), "edge": spec.get("edge"),
                   "field_deg": list(spec.get("field", ())), "system": spec.get("sys"),
                   "refused": f"{type(exc).__name__}: {exc}"[:400]}
        print(json.dumps(row), flush=True)
        report["rows"] = [r for r in report["rows"] if r["case"] != name] + [row]
        if args.out:
            Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    if not args.out:
        print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
