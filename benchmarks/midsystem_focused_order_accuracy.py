"""Issue 46 (diagnostic): order +17 of the 16-level Fresnel DOE (f 50 mm, 1000 × 1 µm pixels; it focuses 2.1 mm after
the DOE, before lens B) ALONE, with the exact stop edge (``stop_edge="exit_pupil", edge_step="asm"``), against the
independent wave reference of tests/wave_truth_doe.py fed the same order (transmission ``exp(17 i φ)`` of the
fabricated phase map), rel L1 of the 32² PSF crop, at the fields given. ``--old-nu``: the exact edge's Fresnel
parameter as it was before 2026-11-30 (h46d): the converging path difference's sign that holds with a focus between
the plane and the rim images (here ≤ 0 at every node, clamped: ν ≈ 0 over the plane).

Usage: ``python benchmarks/midsystem_focused_order_accuracy.py [--fields 0,1] [--old-nu] [--edge asm|doe] [--out
FILE]``."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.coherent.accurate as acc  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.coherent.stop_edge import _rim_cubic, _rim_fourier  # noqa: E402
from raywave.hybrid.coherent.tracing import _nearest_fill  # noqa: E402
from raywave.hybrid.midsystem import DOEPhaseSurface, MidSystemLens  # noqa: E402

N, PITCH, PS, KS = 1000, 1e-3, 2e-3, 32


def _old_nu(b, nd, stop_xy, good, edge):
    """``accurate._path_difference_nu`` before h46d: ``Δ = Φ_E − n|P − E| − Φ_P`` (≤ 0) on a plane before the rim's
    images, clamped: ν ≈ 0."""
    rim, z_doe, wavelength, n = b.given.stop_rim, b.z_doe, b.src.wavelength, b.n
    sx, sy = stop_xy
    phi, s_stop, g_s = edge
    interp = _rim_fourier if acc.RIM_FOURIER else _rim_cubic
    at_rim = interp(torch.cat([rim.points, rim.opl[:, None]], -1), sx, sy)
    ex, ey, ez, phi_e = nd.as_map(_nearest_fill(at_rim, good, nd.targets))
    dx, dy, dz = nd.tx - ex, nd.ty - ey, z_doe - ez
    sgn = 1.0 if bool((dz.detach() > 0).all()) else -1.0
    delta = phi_e + sgn * n * torch.sqrt(dx * dx + dy * dy + dz * dz) - phi
    s0 = 0.1 / g_s.detach()
    g2 = ((4.0 * delta / (wavelength * 1e-3) + g_s * g_s * s0 * s0) / (s_stop * s_stop + s0 * s0)).clamp_min(1e-300)
    return s_stop * torch.sqrt(g2)


def measure(field, edge: str = "asm") -> dict:
    doe = FresnelDOE(50.0, N, PITCH, wavelength=0.55)
    doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=1.0, final_pitch=PITCH,
                       sensor_pitch=PS, min_efficiency=1e-3, orders=[17],
                       **(dict(stop_edge="exit_pupil", edge_step="asm") if edge == "asm" else {}))
    t0 = time.perf_counter()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # order +17's pixel loss (named by the sampling report)
        res = ml.psf_result([field], 0.55, ks=KS)
        phi0 = DOEPhaseSurface(doe).phase_map()[2:-2, 2:-2].numpy()
    t = time.perf_counter() - t0
    center = res.center[0, 0].numpy()
    ref = W.sensor_psf(sys_, N, PITCH, np.exp(17j * phi0), center, PS, KS)
    return {"field": list(field), "rel_l1": W.rel_l1(res.psf[0, 0].numpy(), ref), "seconds": t}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fields", default="0,1", help="field angles (degrees, y)")
    ap.add_argument("--old-nu", action="store_true")
    ap.add_argument("--edge", default="asm", choices=["asm", "doe"], help="the exact edge, or the DOE-plane cut")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.old_nu:
        acc._path_difference_nu = _old_nu
    rows = []
    for f in a.fields.split(","):
        row = measure((0.0, float(f)), a.edge)
        row["nu"], row["edge"] = ("before h46d" if a.old_nu else "h46d"), a.edge
        emit_row(rows, row, a.out)


if __name__ == "__main__":
    main()
