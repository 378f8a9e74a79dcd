"""Calibration of the vignetting guard (issue 47 class G) against an independent wave truth: tests/wave_truth.py's
two ideal lenses (the stop on A, f 80 mm, radius 0.6 mm; B, f 12 mm, 10 mm behind), a Fresnel-lens DOE (f 200 mm,
1 µm pixels) 5 mm behind B, at 2° field, with a circular clear aperture of radius R_B on lens B that vignettes the
off-axis beam (the beam meets B 0.349 mm off axis, 0.525 mm in radius). The truth cuts the field sharply at B (the
stop's edge and B's both diffract by the plain angular spectrum); the engine's default diffracts only the stop's edge
(from its rim images) and cuts B's on the DOE plane. Prints per R_B the engine's figures (vignetting edge length,
estimate), the default's and the DOE-plane edge's rel L1 from the truth.

    python benchmarks/vignetting_truth.py [--radii none 0.85 0.8 0.7 0.65] [--json OUT]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import torch

from _report import emit_row  # benchmarks/ is on sys.path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import wave_truth as wt  # noqa: E402

WL, PIXEL, KS, THETA = 0.55, 2e-3, 32, 2.0
SYSTEM = wt.TwoLenses()


def truth_psf(theta: float, center, b_radius, doe_phase, lattice, pitch: float = 1e-3, margin: float = 0.4):
    """wave_truth.two_ideal_lenses_psf with B's clear aperture (radius ``b_radius`` mm, None: none) cut sharply
    (area-weighted) on B's plane before B's phase, and the DOE 5 mm behind B."""
    s = SYSTEM
    if b_radius is None:
        return wt.two_ideal_lenses_psf(s, (0.0, theta), WL, center, KS, PIXEL, pitch=pitch, doe=doe_phase,
                                       doe_z=s.gap + 5.0, doe_lattice=lattice)
    calls = {"n": 0}
    # the mask: wrap asm so that the field arriving at B's plane (z = gap) is cut
    orig_asm = wt.asm

    def asm_cut(env, origin, p, wavelength, z, carrier, out_origin, out_shape, **kw):
        out = orig_asm(env, origin, p, wavelength, z, carrier, out_origin, out_shape, **kw)
        calls["n"] += 1
        if calls["n"] == 1:  # the first carry: the stop (A) to B
            x, y = wt.grid_xy(out_origin, out.shape, p)
            out = out * wt.circle_cover(x, y, b_radius, p).to(out.dtype)
        return out

    wt.asm = asm_cut
    try:
        return wt.two_ideal_lenses_psf(s, (0.0, theta), WL, center, KS, PIXEL, pitch=pitch, doe=doe_phase,
                                       doe_z=s.gap + 5.0, doe_lattice=lattice)
    finally:
        wt.asm = orig_asm


def engine_lens(theta: float, b_radius):
    """test_ideal_lens_truth.two_lens_engine_lens with B's clear aperture."""
    import test_ideal_lens_truth as t
    from raywave.surfaces.aperture import CircularAperture

    lens = t.two_lens_engine_lens(theta, SYSTEM)
    if b_radius is not None:
        lens.surfaces[1].aperture = CircularAperture(b_radius)
    return lens


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radii", nargs="+", default=["none", "0.65", "0.7", "0.8", "0.85", "0.86", "0.87", "0.873",
                                                  "0.8745", "0.88", "0.9", "0.95", "1.0", "1.2"])
    ap.add_argument("--theta", type=float, default=THETA)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    from raywave.doe import FresnelDOE
    from raywave.hybrid import HybridLens
    from raywave.hybrid.coherent.geometry import footprints_and_clippings

    doe = FresnelDOE(200.0, (2400, 2400), 1e-3, design_wavelength=WL)
    phase, lattice = wt.pixel_phase(doe, WL)
    rows = []
    for rtxt in a.radii:
        rb = None if rtxt == "none" else float(rtxt)
        lens = engine_lens(a.theta, rb)
        row = {"b_radius_mm": rb, "theta_deg": a.theta}
        psfs = {}
        for name, kw in (("default", {}), ("doe", {"stop_edge": "doe"})):
            hl = HybridLens(lens, doe, 5.0, sensor_pitch=PIXEL, **kw)
            t0 = time.perf_counter()
            with torch.no_grad(), warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                r = hl.psf_result((0.0, a.theta), WL, ks=KS)
            psfs[name] = (r.psf[0, 0], tuple(float(c) for c in r.center[0, 0]))
            row[f"{name}_s"] = round(time.perf_counter() - t0, 2)
            row[f"{name}_warnings"] = sorted({type(w.message).__name__ for w in caught})
            if name == "default":
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    _, _, edges = footprints_and_clippings(hl.optics, hl.doe,
                                                           torch.tensor([[0.0, a.theta]], dtype=torch.float64),
                                                           torch.tensor([WL], dtype=torch.float64), None, hl.doe_z(),
                                                           vignetting=True)
                e = edges.get((0, 0))
                row.update(lost=0.0 if e is None else e.lost, rim_lost=0.0 if e is None else e.rim_lost,
                           length=0.0 if e is None else e.length,
                           clearance_zones=None if e is None else e.clearance,
                           estimate=0.0 if e is None else e.estimate)
        truth = truth_psf(a.theta, psfs["default"][1], rb, phase, lattice)
        for name in psfs:
            row[f"{name}_l1"] = float((psfs[name][0] - truth).abs().sum())
        row["default_over_length"] = row["default_l1"] / row["length"] if row["length"] > 0 else None
        emit_row(rows, row, a.json)  # streamed: an interrupted run keeps its rows


if __name__ == "__main__":
    main()
