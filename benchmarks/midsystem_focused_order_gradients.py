"""Issue 46 (diagnostic): the gradient of a mid-system DOE's order that focuses before the next surface, against central
differences. The 16-level Fresnel DOE (f 50 mm, 800 × 1 µm pixels) 3 mm after lens A of the two-lens system of
tests/wave_truth_doe.py, at 1°: order +17 focuses 2.1 mm after it, before lens B. ``d(Σ w·PSF)`` (ks 16, the weights
of tests/test_midsystem_weak_edge.py) with respect to the DOE's focal length and lens A's, analytic against central
differences at several relative steps, for: order +17 alone with the DOE-plane cut (``"17 doe"``) and with the exact
edge (``"17 exact"``), orders 1 and +17 with ``weak_edge="doe"`` and with the exact edge for both.
``--freeze-edge-plane`` / ``--freeze-nodes``: the exact edge's step plane (``exit_pupil._rim_step_plane``, chosen from
the rim images' detached z) / the accurate construction's node grid (``accurate._node_layout``: its spacing from the
footprint, centred on the chief ray's point), the construction's mesh, held in the differences as the gradient holds
them (tests/midsystem_systems.py ``FrozenMesh``: the first call's choices replayed in call order); ``--rim-nudge``:
the stop rim images' source nudge (``stop_edge.RIM_NUDGE``, the engine's 1e-5) for this run; ``--plane-shifts``:
instead of the gradients, ``dL/dz_edge`` (every step plane moved by ± each shift, the node grids held) and the planes'
derivatives with respect to both focal lengths.

What it shows (2026-11-30, h46d; docs/ray-wave.md "A DOE inside the lens";
benchmarks/results/midsystem_focused_order_gradients_2026-11-30_xvi_h46d.json): order +17's step plane lies before its
rim images with no focus of the beam between, where its stop edge was not formed (the converging path difference kept
the sign it has with a focus between: ≤ 0 at every node, clamped, ν ≈ 0 over the plane); with it fixed its derivative
with respect to the DOE's focal length is −2.21e-2 (it read −8.3e-5, against central differences' +2.27e-4), and with
the rim nudge 1e-3 the gradient agrees with central differences, nothing held, to 8.5e-4 / 8.3e-4 at the steps 1e-6 /
1e-5 (lens A's 7.1e-5 / 8.1e-5; orders 1 and +17 exact 1.7e-3 and ≤ 2.4e-6 at 1e-6 … 3e-6), and with the mesh held to
2.6e-5 / 4.4e-5 and 6.2e-5 / 6.9e-5 (1 and +17: ≤ 1.2e-5 and ≤ 3.7e-6). The mesh's share: dL/dz_edge = −1.84e-5 per
mm, the plane moving 0.599 mm per mm of the DOE's focal length. Lens A's 25 % (h46c, both held, the engine's nudge)
was that nudge's rounding of the rim images (~1e-10 of the loss). With the DOE-plane cut (h46c) the gradient agrees at
the step 1e-7 (2.5e-5 for order +17 alone); steps ≥ 1e-6 straddle the cut's coverage kinks (1.4 %).

Usage: ``python benchmarks/midsystem_focused_order_gradients.py [--configs "17 doe" ...] [--steps 1e-7,1e-6]
[--freeze-edge-plane] [--freeze-nodes] [--rim-nudge 1e-3] [--plane-shifts 1e-5,1e-4] [--out FILE]`` (prints JSON rows
as it goes; ~1 min per exact-edge row on one CPU thread).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.coherent.exit_pupil as xp  # noqa: E402
import raywave.hybrid.coherent.stop_edge as se  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import MidSystemLens  # noqa: E402

PITCH, PS, FIELD = 1e-3, 2e-3, (0.0, 1.0)
EXACT = dict(stop_edge="exit_pupil", edge_step="asm")
CONFIGS = {"17 doe": ([17], {}), "17 exact": ([17], EXACT),
           "1+17 weak_edge=doe": ([1, 17], dict(weak_edge="doe", **EXACT)), "1+17 exact": ([1, 17], EXACT)}


def system(orders, **kw):
    """``(doe, lens, MidSystemLens)`` of tests/test_midsystem_weak_edge.py's ``_lens`` with ``orders``."""
    sys_ = W.TwoLensSystem(f_doe=50.0, field=FIELD)
    doe = FresnelDOE(50.0, 800, PITCH, wavelength=0.55)
    doe.fabricate(16)
    lens = M.two_lens(sys_)
    return doe, lens, MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=0.8, final_pitch=PITCH,
                                    sensor_pitch=PS, min_efficiency=1e-3, orders=orders, **kw)


def measure(name: str, steps, freeze: bool, freeze_nodes: bool = False, rim_nudge: float | None = None) -> list:
    orders, kw = CONFIGS[name]
    doe, lens, ml = system(orders, **kw)
    loss = M.weighted_psf_loss(ml, FIELD)
    params = M.focal_lengths(doe, lens)
    rows = []
    with M.FrozenMesh(rim_nudge, plane=freeze, nodes=freeze_nodes) as mesh:
        t0 = time.perf_counter()
        diffs = M.central_differences(mesh.loss(loss), params, steps)
        t_all = time.perf_counter() - t0
    for pname, st, g, fd in diffs:
        rows.append({"config": name, "param": pname, "step": st, "analytic": g, "fd": fd, "rel": (g - fd) / abs(fd),
                     "freeze_edge_plane": freeze, "freeze_nodes": freeze_nodes,
                     "rim_nudge": se.RIM_NUDGE if rim_nudge is None else rim_nudge, "seconds": t_all})
    return rows


def plane_slope(name: str, shifts, rim_nudge: float | None = None) -> list:
    """``dL/dz_edge``: the loss with every exact-edge construction's step plane moved by ±``dz`` mm (each of
    ``shifts``), the node grids held (:class:`midsystem_systems.FrozenMesh`), central differences; and the planes."""
    orders, kw = CONFIGS[name]
    doe, lens, ml = system(orders, **kw)
    weighted = M.weighted_psf_loss(ml, FIELD)
    shift, planes = [0.0], []
    rows = []
    with M.FrozenMesh(rim_nudge) as mesh, torch.no_grad():
        held = xp._rim_step_plane

        def moved(*a):
            z_edge, z_far = held(*a)
            planes.append(z_edge)
            return (None if z_edge is None else z_edge + shift[0]), z_far

        xp._rim_step_plane = moved

        def loss():
            planes.clear()
            return float(weighted())

        lossm = mesh.loss(loss)
        lossm()
        z0 = list(planes)
        for dz in shifts:
            shift[0] = dz
            lp = lossm()
            shift[0] = -dz
            lm = lossm()
            shift[0] = 0.0
            rows.append({"config": name, "plane_shift": dz, "dL/dz_edge": (lp - lm) / (2 * dz), "z_edge": z0,
                         "rim_nudge": se.RIM_NUDGE})
        # the planes as the engine chooses them, at the parameters ± 1e-5 relative: their derivative
        engine = mesh.saved[0]

        def recorded(*a):
            out = engine(*a)
            planes.append(out[0])
            return out

        xp._rim_step_plane = recorded
        for pname, prm in (("doe focal length", doe.focal_length),
                           ("lens A focal length", lens.surfaces[0].interaction.focal_length)):
            h = 1e-5 * max(abs(float(prm)), 1.0)
            zs = []
            for sign in (1.0, -2.0):
                prm += sign * h
                planes.clear()
                mesh.recording, mesh.memo = True, {}  # (the node grids of these calls: their own)
                loss()
                zs.append(list(planes))
            prm += h
            rows.append({"config": name, "param": pname, "dz_edge/dparam": [(p_ - m_) / (2 * h) for p_, m_ in
                                                                           zip(*zs)], "rim_nudge": se.RIM_NUDGE})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument("--steps", default="1e-7,1e-6")
    ap.add_argument("--freeze-edge-plane", action="store_true")
    ap.add_argument("--freeze-nodes", action="store_true")
    ap.add_argument("--rim-nudge", type=float, default=None,
                    help="stop_edge.RIM_NUDGE for this run (default: the engine's 1e-5)")
    ap.add_argument("--plane-shifts", default=None,
                    help="instead of the gradients: dL/dz_edge from step planes moved by these ± mm (e.g. 1e-5,1e-4)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    steps = [float(s) for s in a.steps.split(",")]
    rows = []
    for name in a.configs:
        if a.plane_shifts:
            for row in plane_slope(name, [float(v) for v in a.plane_shifts.split(",")], a.rim_nudge):
                emit_row(rows, row, a.out)
            continue
        for row in measure(name, steps, a.freeze_edge_plane, a.freeze_nodes, a.rim_nudge):
            emit_row(rows, row, a.out)


if __name__ == "__main__":
    main()
