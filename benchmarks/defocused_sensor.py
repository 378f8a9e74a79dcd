"""Issue 47, a new class: the default edge on a strongly defocused sensor, against converged references.

Two systems, one source on axis, ks 32 at 2 µm, relative L1 of the PSF crop (each sums to 1):

* ``ideal``: tests/test_ideal_lens_truth.py's ideal lens (f 10 mm, F/8, a blank DOE of 1 µm pixels 1 mm behind it) with
  the sensor ``dz`` mm past the focus, against that file's wave-optics truth (tests/wave_truth.py: exact lens phase →
  plain angular spectrum; its padding ``margin`` mm raised until two levels agree, which the tests' 0.3 mm is not on a
  defocused sensor) and the rim-image Huygens reference;
* ``doublet``: the two-lens doublet of tests/test_midsystem_zmx.py without its DOE (focus ≈ 35 mm after its last
  vertex at 0.55 µm), its sensor at ``--sensor`` mm, a blank DOE of 2 µm pixels on planes ``--planes`` mm after the last
  vertex (None: the file's default plane, half the last gap), the default edge, ``edge_step="asm"`` and
  ``stop_edge="doe"``, against ``huygens_psf(sphere="rim_images", n_pupil="auto")`` (its own error beside it).

    PYTHONPATH=. python benchmarks/defocused_sensor.py [--dz 3 8] [--sensor 34.5 40] [--planes None 5 10 30] [-o F]
    PYTHONPATH=. python benchmarks/defocused_sensor.py --more [-o F]   # before the focus, off axis (MORE)
    PYTHONPATH=. python benchmarks/defocused_sensor.py --lenses [-o F]   # other lenses off focus (LENSES)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import torch

from _report import emit_json  # benchmarks/ is on sys.path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

WL, KS, PIXEL = 0.55, 32, 0.002


def _l1(a, b) -> float:
    return float((a - b).abs().sum() / b.abs().sum())


def ideal_rows(dz: float, margins=(0.3, 1.5, 3.0)) -> dict:
    """The ideal lens, sensor ``dz`` mm past focus: the default and the DOE-plane edge against the truth at each
    padding margin (mm) and against the Huygens reference."""
    import test_ideal_lens_truth as T
    from wave_truth import ideal_lens_doe_psf

    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens
    from raywave.models.exit_pupil import huygens_psf

    lens = T._single_lens(None, T.F1 + dz, WL)
    psf = {}
    for name, kw in (("default", {}), ("doe", {"stop_edge": "doe"})):
        hl = HybridLens(lens, BlankDOE(1600, 1e-3), T.DOE_DIST, sensor_pitch=PIXEL, **kw)
        with torch.no_grad():
            r = hl.psf_result((0.0, 0.0), WL, ks=KS)
        psf[name] = r.psf[0, 0]
    c = tuple(float(v) for v in r.center[0, 0])
    truths = {m: ideal_lens_doe_psf(T.F1, T.R1, WL, c, KS, PIXEL, T.F1 + dz, doe=BlankDOE(1600, 1e-3),
                                    doe_dist=T.DOE_DIST, margin=m) for m in margins}
    with torch.no_grad():
        h = huygens_psf(lens, (0.0, 0.0), WL, ks=KS, pitch=PIXEL, n_pupil="auto", sphere="rim_images")
    last = truths[margins[-1]]
    return {"system": "ideal", "dz_mm": dz, "defocus_waves_w20": round(dz / (8 * 8 ** 2) / (WL * 1e-3), 2),
            "truth_change_between_last_margins": _l1(truths[margins[-2]], last),
            "default_vs_truth_by_margin": {str(m): _l1(psf["default"], t) for m, t in truths.items()},
            "doe_edge_vs_truth": _l1(psf["doe"], last), "huygens_vs_truth": _l1(h.psf.squeeze(), last),
            "huygens_error_estimate": h.error_estimate}


def _run(hl, fy: float) -> tuple:
    """``(psf (ks, ks), seconds, warning class names, the crop's centre (x, y) mm)`` of ``hl`` at the field (0,
    ``fy``) °."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        with torch.no_grad():
            r = hl.psf_result(torch.tensor([[0.0, fy]], dtype=torch.float64), [WL], ks=KS)
        dt = time.perf_counter() - t0
    names = sorted({type(w.message).__name__ for w in caught if not issubclass(w.category, DeprecationWarning)})
    return r.psf.squeeze(), round(dt, 2), names, tuple(float(c) for c in r.center[0, 0])


def _reference(hl, fy: float) -> tuple:
    """``(psf, its own error estimate)``: the rim-image Huygens reference of ``hl`` at (0, ``fy``) °."""
    from raywave.models.exit_pupil import huygens_psf

    with torch.no_grad():
        h = huygens_psf(hl.lens, (0.0, fy), WL, ks=KS, pitch=PIXEL, n_pupil="auto", sphere="rim_images",
                        max_n_pupil=3072)
    return h.psf.squeeze(), h.error_estimate


def _edges_row(out: dict, sensor: float, plane, fy: float, edges, ref=None) -> tuple:
    """Fill ``out`` with each of ``edges`` ``((name, kw), …)``'s rel L1 from the reference (computed on first use
    unless given as ``ref``), its time and (the default) its warnings; returns ``(out, ref)``."""
    from test_edge_estimate import _doublet_on_sensor

    for name, kw in edges:
        hl = _doublet_on_sensor(sensor, plane, **kw)  # 2 µm DOE and sensor pixels (PIXEL)
        psf, dt, names, _ = _run(hl, fy)
        if ref is None:
            ref, out["reference_error_estimate"] = _reference(hl, fy)
        out["plane_mm"] = float(hl.doe_distance)
        out[name], out[name + "_s"] = _l1(psf, ref), dt
        if name == "default":
            out["default_warnings"] = names
    print(out, file=sys.stderr, flush=True)
    return out, ref


def doublet_rows(sensor: float, planes) -> list:
    """The doublet with its sensor at ``sensor`` mm: each plane's default / asm / DOE-plane edge against Huygens."""
    rows, ref = [], None
    edges = (("default", {}), ("asm", {"edge_step": "asm"}), ("doe", {"stop_edge": "doe"}))
    for plane in planes:
        out, ref = _edges_row({"system": "doublet", "sensor_mm": sensor, "plane_mm": plane}, sensor, plane, 0.0, edges,
                              ref)
        rows.append(out)
    return rows


#: ``--more``: other sensors, planes and fields of the doublet (sensor mm, DOE plane mm or None, field °): before the
#: focus, off axis, nearer the focus
MORE = ((30.0, None, 0.0), (30.0, 10.0, 0.0), (40.0, 10.0, 2.0), (40.0, None, 2.0), (37.0, None, 0.0),
        (37.0, None, 1.5))


def more_rows() -> list:
    """The doublet's :data:`MORE` cases: the default and the DOE-plane edge against the converged Huygens reference."""
    edges = (("default", {}), ("doe", {"stop_edge": "doe"}))
    return [_edges_row({"system": "doublet", "sensor_mm": sensor, "plane_mm": plane, "field_deg": fy}, sensor, plane,
                       fy, edges)[0] for sensor, plane, fy in MORE]


#: ``--lenses``: other lenses with the sensor moved ``dz`` mm along the axis (lens file, dz mm, field °, DOE and
#: sensor pitch mm or None: the file's default, the Nyquist pitch)
LENSES = (("raywave/data/lenses/cooke_triplet.json", 0.5, 0.0, 0.002),
          ("raywave/data/lenses/cooke_triplet.json", -0.5, 14.0, 0.002),
          ("raywave/data/lenses/cooke_triplet.json", 1.5, 0.0, 0.002),
          ("tests/data/real_lenses/singlet_nbk7_50.zmx", 1.0, 0.0, 0.002),
          ("tests/data/real_lenses/asphere_f13_nsf11.zmx", 0.15, 0.0, None),
          ("tests/data/real_lenses/asphere_f13_nsf11.zmx", 0.3, 0.0, None))


def lens_rows() -> list:
    """:data:`LENSES`: the default and the DOE-plane edge against the converged rim-image Huygens reference."""
    import copy
    import json

    from raywave.assembly.build import hybrid_from_spec
    from raywave.io.zmx import read_zmx
    from raywave.models.exit_pupil import huygens_psf

    rows = []
    for name, dz, fy, pitch in LENSES:
        path = ROOT / name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            spec = copy.deepcopy(json.loads(path.read_text()) if path.suffix == ".json" else read_zmx(path))
        spec["surfaces"][-1]["thickness"] = float(spec["surfaces"][-1]["thickness"]) + dz
        out, ref = {"lens": path.name, "dz_mm": dz, "field_deg": fy}, None
        for edge, kw in (("default", {}), ("doe", {"stop_edge": "doe"})):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                hl = hybrid_from_spec(spec, doe_pitch=pitch, sensor_pitch=pitch, **kw)
            psf, dt, names, center = _run(hl, fy)
            if ref is None:
                with torch.no_grad(), warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    h = huygens_psf(hl.lens, (0.0, fy), WL, ks=KS, pitch=float(hl.sensor_pitch), n_pupil="auto",
                                    sphere="rim_images", max_n_pupil=3072,
                                    center=center, sensor_z=float(hl.sensor_z()))
                ref, out["reference_error_estimate"] = h.psf.squeeze(), h.error_estimate
                out["pitch_mm"], out["doe_distance_mm"] = float(hl.sensor_pitch), float(hl.doe_distance)
            out[edge], out[edge + "_s"] = _l1(psf, ref), dt
            if edge == "default":
                out["default_warnings"] = names
        rows.append(out)
        print(out, file=sys.stderr, flush=True)
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dz", type=float, nargs="*", default=[3.0, 8.0])
    ap.add_argument("--sensor", type=float, nargs="*", default=[34.5, 40.0])
    ap.add_argument("--planes", nargs="*", default=["None", "5", "10", "30"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--more", action="store_true", help="only the MORE cases (other sensors, planes and fields)")
    ap.add_argument("--lenses", action="store_true", help="only the LENSES cases (other lenses off focus)")
    ap.add_argument("-o", "--output")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    planes = [None if p == "None" else float(p) for p in args.planes]
    if args.lenses:
        rows = lens_rows()
    elif args.more:
        rows = more_rows()
    else:
        rows = [ideal_rows(dz) for dz in args.dz]
        for s in args.sensor:
            rows += doublet_rows(s, planes if s == args.sensor[-1] else [None])
    out = {"benchmark": "defocused_sensor", "torch": torch.__version__, "threads": args.threads, "rows": rows}
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    main()
