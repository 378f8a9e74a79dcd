"""Issue 47: the adaptive edge step's error estimate (:func:`raywave.hybrid.coherent.exit_pupil.fresnel_step_holds`)
against measured errors. Lens A (ideal lens f 10 mm, F/12.5, 0.55 µm, the stop on it, 2 µm sensor pixels), a 1 mm DOE
of 1 µm pixels ``10 − d`` mm before the focus, on axis, with a zero-phase :class:`~raywave.doe.PixelDOE` (not blank:
the adaptive default does not take the DOE-plane cut, which is exact only for a blank DOE on a sphere) and, for scale,
the blank DOE (the default takes the cut there). Per distance and crop (``ks`` pixels): the estimate's quantities
(the crop's reach over the far-edge radius, the curvature ratio), the step the default takes, and the relative L1 of
the whole crop (both scaled to unit sum) and ring by ring (:func:`far_tails.rings`) against the converged
Rayleigh–Sommerfeld integral (:func:`wave_truth_doe.airy_reference`) for the default, ``edge_step="fresnel"`` and
``"asm"``; also the time of one PSF with the default against ``"fresnel"`` (A/B in this process, warm, best of 3).

With ``--asphere 64,96,128``: the bundled hybrid_asphere's step per crop and its Fresnel step's distance from the
exact construction there (:func:`asphere`).

Usage: ``RAYWAVE_COMPILE=0 python benchmarks/edge_estimate.py [--distances 9,8,7,5] [--ks 32,64,128] [--time]
[--asphere 64,96,128] [--edges default,fresnel,asm,blank_default] [--out F]``
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import wave_truth_doe as W  # noqa: E402
from far_tails import PITCH, PS, WL, rings  # noqa: E402

from raywave.doe import PixelDOE  # noqa: E402
from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.hybrid.coherent import stop_rim_images  # noqa: E402
from raywave.hybrid.coherent.exit_pupil import fresnel_step_estimates  # noqa: E402
from raywave.lens.lens import Lens  # noqa: E402
from raywave.materials import get_material  # noqa: E402
from raywave.surfaces.aperture import CircularAperture  # noqa: E402
from raywave.surfaces.geometry import Plane  # noqa: E402
from raywave.surfaces.interaction import IdealLens  # noqa: E402
from raywave.surfaces.surface import Surface  # noqa: E402

N = 1000


def lens_a() -> Lens:
    stop = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                   is_stop=True)
    return Lens([stop], wavelengths=(WL,), primary=0)


def psf(hl: HybridLens, ks: int):
    """``(psf (ks, ks), the edge step taken, warnings)`` of lens A on axis."""
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        r = hl.psf_result([(0.0, 0.0)], WL, ks=ks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        info = hl.doe_fields([(0.0, 0.0)], WL, crop_reach=hl.crop_reach(ks))[0][0].info
    return r.psf[0, 0].detach().numpy(), getattr(info, "edge_step", None), sorted({str(x.message)[:160] for x in w})


def estimate(lens: Lens, d: float, ks: int) -> dict:
    """:func:`~raywave.hybrid.coherent.exit_pupil.fresnel_step_estimates` of lens A on axis (its rim images)."""
    hl = HybridLens(lens, PixelDOE(torch.zeros(N, N, dtype=torch.float64), PITCH), d, sensor_pitch=PS)
    rim = stop_rim_images(hl.optics, (0.0, 0.0), WL, None)
    zones, zones_max, curv = fresnel_step_estimates([rim], (WL, 1.0), (hl.doe_z(), hl.sensor_z()), hl.crop_reach(ks),
                                                    PITCH / hl.oversample)[0]
    return {"zones": zones, "zones_max": zones_max, "curvature": curv}


def whole(e: np.ndarray, ref: np.ndarray) -> float:
    e, ref = e / e.sum(), ref / ref.sum()
    return float(np.abs(e - ref).sum())


def timed(hl: HybridLens, ks: int, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hl.psf_result([(0.0, 0.0)], WL, ks=ks)
        best = min(best, time.perf_counter() - t0)
    return best


def asphere(kss: list[int]) -> dict:
    """The bundled hybrid_asphere (0.53 µm, 0° / 12.25° / 17.5°): per crop the step the default takes, the Fresnel
    step's and the default's whole-crop rel L1 from the exact construction (the arbiter where it fits), and the CPU
    time of one warm PSF per edge."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    out = {}
    for ks in kss:
        for f in (0.0, 12.25, 17.5):
            r = {}
            for name, kw in (("default", {}), ("fresnel", {"edge_step": "fresnel"}), ("asm", {"edge_step": "asm"})):
                hl = load_hybrid(bundled_lens_path("hybrid_asphere"), **kw)
                with warnings.catch_warnings(), torch.no_grad():
                    warnings.simplefilter("ignore")
                    hl.psf_result((0.0, f), 0.53, ks=ks)
                    t0 = time.process_time()
                    p = hl.psf_result((0.0, f), 0.53, ks=ks).psf[0, 0].numpy()
                    t = time.process_time() - t0
                    step = hl.doe_fields((0.0, f), 0.53, crop_reach=hl.crop_reach(ks))[0][0].info.edge_step
                r[name] = (p, t, step)
            row = {"step": r["default"][2], "fresnel_vs_asm": whole(r["fresnel"][0], r["asm"][0]),
                   "default_vs_asm": whole(r["default"][0], r["asm"][0]),
                   "cpu_s": {k: v[1] for k, v in r.items()}}
            out[f"ks{ks}_field{f:g}"] = row
            print("asphere", ks, f, row, file=sys.stderr, flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distances", default="9,8,7,5")
    ap.add_argument("--ks", default="32,64,128")
    ap.add_argument("--edges", default="default,fresnel,asm,blank_default")
    ap.add_argument("--time", action="store_true", help="time the default against edge_step='fresnel'")
    ap.add_argument("--asphere", default=None, help="also the bundled asphere on these crops (e.g. 64,96,128)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    lens = lens_a()
    sys_ = W.TwoLensSystem()
    out = {"issue": 47, "what": __doc__.split("\n\n")[0], "command": "RAYWAVE_COMPILE=0 python "
           "benchmarks/edge_estimate.py " + " ".join(argv if argv is not None else sys.argv[1:]), "cases": {}}
    kss = [int(v) for v in a.ks.split(",")]
    refs = {ks: W.airy_reference(sys_, PS, ks) for ks in kss}
    for d in (float(v) for v in a.distances.split(",")):
        for ks in kss:
            case = {"doe_plane_before_focus_mm": 10.0 - d, "ks": ks, "estimate": estimate(lens, d, ks)}
            for name in a.edges.split(","):
                doe = BlankDOE(N, PITCH) if name.startswith("blank") else PixelDOE(
                    torch.zeros(N, N, dtype=torch.float64), PITCH)
                kw = {} if name.endswith("default") else {"edge_step": name}
                hl = HybridLens(lens, doe, d, sensor_pitch=PS, **kw)
                e, step, warns = psf(hl, ks)
                row = {"whole": whole(e, refs[ks]), "step": step, "warnings": warns}
                if ks == 128:
                    row["rings"] = rings(e, refs[ks])
                case[name] = row
                print(d, ks, name, {k: v for k, v in row.items() if k != "warnings"}, warns, file=sys.stderr,
                      flush=True)
            if a.time:
                hd = HybridLens(lens, PixelDOE(torch.zeros(N, N, dtype=torch.float64), PITCH), d, sensor_pitch=PS)
                hf = HybridLens(lens, PixelDOE(torch.zeros(N, N, dtype=torch.float64), PITCH), d, sensor_pitch=PS,
                                edge_step="fresnel")
                timed(hd, ks, 1), timed(hf, ks, 1)  # warm
                case["seconds"] = {"default": timed(hd, ks), "fresnel": timed(hf, ks)}
                print(d, ks, case["seconds"], file=sys.stderr, flush=True)
            out["cases"][f"d{10 - d:g}mm_ks{ks}"] = case
    if a.asphere:
        out["hybrid_asphere"] = asphere([int(v) for v in a.asphere.split(",")])
    emit_json(out, a.out, indent=1)


if __name__ == "__main__":
    main()
