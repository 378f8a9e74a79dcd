"""Issue 47: why the Fresnel edge step's far tail was wrong on lens A (ideal lens F/12.5, 0.55 µm, a blank 1 mm
DOE of 1 µm pixels 3 mm / 1 mm before the focus, 2 µm pixels, a 128-pixel crop): the Fresnel step
(``stop_edge="exit_pupil", edge_step="fresnel"``) ring by ring against the converged Rayleigh–Sommerfeld integral
(:func:`wave_truth_doe.airy_reference`; :func:`far_tails.rings`), one thing varied at a time (module attributes
patched for the run, restored after): the node on the beam's centre put back into the inner tail's Fresnel scale
(``fresnel_centre_node_in_limit``: the behaviour before the fix), the ripple band's width (``RIPPLE_ZONES`` ×2,
×4), its outer roll-off (``ROLL_ZONES`` 4), the inner tail (``INNER_TAIL`` ×2), the scale of the inner tail's
anti-aliasing limit set to lens A's true one (``g_true``), the curved edge's terms (dropped: ``no_curvature``; the
spreading factor ``sqrt(1 + νκ/g)`` replaced by ``1/sqrt(1 − νκ/g)``: ``spread_1_over_sqrt``; ``same_arith_eager``:
the patched arithmetic unchanged, a check of the patch); the exact construction (``asm``) and the DOE-plane cut
(``doe_cut``) for scale. Per case also the DOE plane's Fresnel number ``N_F = a²/(λL)`` and the sensor radius whose
far-edge wave crosses the beam's centre on the DOE plane (``2·N_F·λ·F#``): beyond it the step's one-edge knife edge
(the nearest edge's wave only) cannot hold that wave.

Usage: ``RAYWAVE_COMPILE=0 python benchmarks/fresnel_tail.py [--out FILE] [--only NAME,...] [--distances 7,9]``
(prints JSON; eager, so that the patched band arithmetic is the one that runs).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import wave_truth_doe as W  # noqa: E402
from far_tails import KS_TAIL, N, PITCH, PS, WL, _psf, rings  # noqa: E402

import raywave.hybrid.coherent.accurate as AC  # noqa: E402
import raywave.hybrid.coherent.exit_pupil as XP  # noqa: E402
import raywave.hybrid.coherent.stop_edge as SE  # noqa: E402
from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.lens.lens import Lens  # noqa: E402
from raywave.materials import get_material  # noqa: E402
from raywave.surfaces.aperture import CircularAperture  # noqa: E402
from raywave.surfaces.geometry import Plane  # noqa: E402
from raywave.surfaces.interaction import IdealLens  # noqa: E402
from raywave.surfaces.surface import Surface  # noqa: E402

FRESNEL = dict(stop_edge="exit_pupil", edge_step="fresnel")


@contextlib.contextmanager
def patched(pairs):
    """Set ``(module, name, value)`` attributes for the block, restored after."""
    old = [(m, k, getattr(m, k)) for m, k, _ in pairs]
    try:
        for m, k, v in pairs:
            setattr(m, k, v)
        yield
    finally:
        for m, k, v in old:
            setattr(m, k, v)


def _values_spread(spread):
    """:meth:`_EdgeBand._values` with the curved edge's spreading factor ``spread(νκ/g)`` in place of
    ``sqrt(1 + clamp(νκ/g))`` (``spread`` None: the curvature's terms dropped)."""
    def values(v, kap, nb, c_, s_, nu_max, forward_edge):
        d_re = 0.5 * (c_ + 0.5) + 0.5 * (s_ + 0.5)
        d_im = (0.5 * (s_ + 0.5) - 0.5 * (c_ + 0.5)) * (1.0 if forward_edge else -1.0)
        w_out = SE._smoothstep((v + nu_max) / (SE.ROLL_ZONES * math.sqrt(2.0)))
        h = 0.5 * nb
        w = (1.0 - SE._smoothstep((v - h) / h)) * w_out
        step = (v > 0).to(v.dtype)
        if kap is None or spread is None:
            return (d_re - step) * w + w_out * step, d_im * w
        m = spread(v * kap) * w
        re, im = (d_re - step) * m + w_out * step, d_im * m
        b_re, b_im = SE.curved_edge_term(v, d_re, d_im, forward_edge)
        e = kap.clamp(-SE.KAPPA_MAX, SE.KAPPA_MAX) * -0.5 * w
        return re + b_re * e, im + b_im * e
    return values


def _limits_with_scale(g_fixed: float):
    """:func:`stop_edge._band_limits` with the Fresnel scale ``g`` replaced by ``g_fixed`` (1/mm)."""
    orig = SE._band_limits

    def limits(ripple_zones, g, pitch):
        return orig(ripple_zones, g_fixed, pitch)
    return limits


def lens_a_scale(d: float) -> float:
    """Lens A's Fresnel scale (1/mm) on the DOE plane ``d`` mm after the stop: ``sqrt(2/(λ L))``, ``L = d (f − d)/f``
    (the Fresnel scaling theorem; f = 10 mm)."""
    return math.sqrt(2.0 / (WL * 1e-3 * d * (10.0 - d) / 10.0))


def variants(d: float):
    rz = SE.RIPPLE_ZONES
    yield "fresnel", [], FRESNEL
    # before the fix (issue 47): the node on the beam's centre (its edge normal undefined) in the inner tail's scale
    yield "fresnel_centre_node_in_limit", [(AC, "_normal_defined", lambda nx_, ny_: torch.ones_like(
        nx_, dtype=torch.bool))], FRESNEL
    yield "asm", [], dict(stop_edge="exit_pupil", edge_step="asm")
    yield "doe_cut", [], dict(stop_edge="doe")
    yield "ripple_x2", [(SE, "RIPPLE_ZONES", 2 * rz), (XP, "RIPPLE_ZONES", 2 * rz)], FRESNEL
    yield "ripple_x4", [(SE, "RIPPLE_ZONES", 4 * rz), (XP, "RIPPLE_ZONES", 4 * rz),
                        (SE, "MAX_RIPPLE_ZONES", 4 * rz)], FRESNEL
    yield "roll_zones_4", [(SE, "ROLL_ZONES", 4.0)], FRESNEL
    yield "inner_tail_x2", [(SE, "INNER_TAIL", 2 * SE.INNER_TAIL)], FRESNEL
    yield "same_arith_eager", [(SE._EdgeBand, "_values", staticmethod(_values_spread(
        lambda x: torch.sqrt(x.clamp(-0.9, 3.0) + 1.0))))], FRESNEL
    yield "g_true", [(SE, "_band_limits", _limits_with_scale(lens_a_scale(d)))], FRESNEL
    yield "g_true_inner_tail_x2", [(SE, "_band_limits", _limits_with_scale(lens_a_scale(d))),
                                   (SE, "INNER_TAIL", 2 * SE.INNER_TAIL)], FRESNEL
    yield "g_true_spread_1_over_sqrt", [(SE, "_band_limits", _limits_with_scale(lens_a_scale(d))),
                                        (SE._EdgeBand, "_values", staticmethod(_values_spread(
                                            lambda x: 1.0 / torch.sqrt(1.0 - x.clamp(-3.0, 0.9)))))], FRESNEL
    yield "no_curvature", [(SE._EdgeBand, "_values", staticmethod(_values_spread(None)))], FRESNEL
    yield "spread_1_over_sqrt", [(SE._EdgeBand, "_values", staticmethod(_values_spread(
        lambda x: 1.0 / torch.sqrt(1.0 - x.clamp(-3.0, 0.9)))))], FRESNEL


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--only", default=None)
    ap.add_argument("--distances", default="7,9", help="stop → DOE plane (mm, comma-separated; the focus at 10)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    only = None if a.only is None else set(a.only.split(","))
    ref = W.airy_reference(W.TwoLensSystem(), PS, KS_TAIL)
    stop = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                   is_stop=True)
    lens = Lens([stop], wavelengths=(WL,), primary=0)
    out = {"issue": 47, "what": __doc__.split("\n\n")[0], "command": "RAYWAVE_COMPILE=0 python "
           "benchmarks/fresnel_tail.py " + " ".join(argv if argv is not None else sys.argv[1:]), "cases": {}}
    for d in (float(v) for v in a.distances.split(",")):
        case = {"doe_plane_before_focus_mm": 10.0 - d, "fresnel_scale_per_mm": lens_a_scale(d),
                "fresnel_number": lens_a_scale(d) ** 2 / 2.0 * (0.4 * (10.0 - d) / 10.0) ** 2,
                # the sensor radius whose far-edge wave crosses the beam's centre on the DOE plane: 2·N_F·λ·F#
                "far_edge_wave_crosses_centre_um": 0.4 * (10.0 - d) / d * 1e3, "rings": {}}
        for name, pairs, kw in variants(d):
            if only is not None and name not in only:
                continue
            t0 = time.perf_counter()
            with patched(pairs):
                e, _ = _psf(HybridLens(lens, BlankDOE(N, PITCH), d, sensor_pitch=PS, **kw), (0.0, 0.0), KS_TAIL)
            case["rings"][name] = rings(e, ref)
            case["rings"][name]["seconds"] = round(time.perf_counter() - t0, 1)
            print(d, name, case["rings"][name], file=sys.stderr, flush=True)
        out["cases"][f"doe_plane_{10 - d:g}mm_before_focus"] = case
    emit_json(out, a.out, indent=1)


if __name__ == "__main__":
    main()
