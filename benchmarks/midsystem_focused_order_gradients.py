"""Issue 46 (diagnostic): the gradient of a mid-system DOE's order that focuses before the next surface, against
central differences. The 16-level Fresnel DOE (f 50 mm, 800 × 1 µm pixels) 3 mm after lens A of the two-lens system
of tests/wave_truth_doe.py, at 1°: order +17 focuses 2.1 mm after it, before lens B. ``d(Σ w·PSF)`` (ks 16, the
weights of tests/test_midsystem_weak_edge.py) with respect to the DOE's focal length and lens A's, analytic against
central differences at several relative steps, for: order +17 alone with the DOE-plane cut (``"17 doe"``) and with
the exact edge (``"17 exact"``), orders 1 and +17 with ``weak_edge="doe"`` and with the exact edge for both.
``--freeze-edge-plane``: the exact edge's step plane (``exit_pupil._rim_step_plane``, chosen from the rim images'
detached z) held at the unperturbed lens's in the finite differences; ``--freeze-nodes``: the accurate construction's
node grid (``accurate._node_layout``: its spacing from the footprint, centred on the chief ray's point) likewise
(this process only).

What it shows (2026-11-29, h46c; docs/ray-wave.md "A DOE inside the lens"): with the DOE-plane cut the analytic
gradient agrees at the step 1e-7 (2.5e-5 for order +17 alone), and steps ≥ 1e-6 straddle the cut's coverage kinks
(1.4 %); with the exact edge order +17's gradient is off (analytic −8.3e-5 against +2.27e-4): for the DOE's focal
length that is the step plane and the node grid, which the differences move and the gradient holds (both frozen:
−8.331e-5, 2.6e-4); for lens A's (3.11e-4 against 2.99e-4) 25 % with both frozen, not explained.

Usage: ``python benchmarks/midsystem_focused_order_gradients.py [--configs "17 doe" ...] [--steps 1e-7,1e-6]
[--freeze-edge-plane] [--freeze-nodes] [--out FILE]`` (prints JSON rows as it goes; ~1 min per exact-edge row on
one CPU thread).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.coherent.accurate as acc  # noqa: E402
import raywave.hybrid.coherent.exit_pupil as xp  # noqa: E402
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


class FrozenStepPlane:
    """While active, ``_rim_step_plane`` returns its first result for each (DOE plane, pitch)."""

    def __init__(self):
        self.memo, self.orig = {}, xp._rim_step_plane

    def __enter__(self):
        def frozen(rim, z_xp, z_doe, wavelength, n, p):
            out = self.orig(rim, z_xp, z_doe, wavelength, n, p)
            return self.memo.setdefault((round(float(z_doe), 9), p), out)
        xp._rim_step_plane = frozen
        return self

    def __exit__(self, *exc):
        xp._rim_step_plane = self.orig


class FrozenNodes:
    """While active, ``accurate._node_layout`` returns its first node grid for each plane (z rounded to 1 nm)."""

    def __init__(self):
        self.memo, self.orig = {}, acc._node_layout

    def __enter__(self):
        def frozen(b, bbox):
            nd = self.memo.setdefault(round(float(b.z_doe), 6), self.orig(b, bbox))
            return acc._Nodes(nd.gx.clone(), nd.gy.clone(), nd.h)
        acc._node_layout = frozen
        return self

    def __exit__(self, *exc):
        acc._node_layout = self.orig


def measure(name: str, steps, freeze: bool, freeze_nodes: bool = False) -> list:
    orders, kw = CONFIGS[name]
    doe, lens, ml = system(orders, **kw)
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # order +17's pixel loss (named by the sampling report)
            return (ml.psf([FIELD], 0.55, ks=16)[0, 0] * w).sum()

    params = {"doe focal length": doe.focal_length, "lens A focal length": lens.surfaces[0].interaction.focal_length}
    rows = []
    with FrozenStepPlane() if freeze else _Null(), FrozenNodes() if freeze_nodes else _Null():
        t0 = time.perf_counter()
        diffs = M.central_differences(loss, params, steps)
        t_all = time.perf_counter() - t0
    for pname, st, g, fd in diffs:
        rows.append({"config": name, "param": pname, "step": st, "analytic": g, "fd": fd, "rel": (g - fd) / abs(fd),
                     "freeze_edge_plane": freeze, "freeze_nodes": freeze_nodes, "seconds": t_all})
    return rows


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument("--steps", default="1e-7,1e-6")
    ap.add_argument("--freeze-edge-plane", action="store_true")
    ap.add_argument("--freeze-nodes", action="store_true")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    steps = [float(s) for s in a.steps.split(",")]
    rows = []
    for name in a.configs:
        for row in measure(name, steps, a.freeze_edge_plane, a.freeze_nodes):
            emit_row(rows, row, a.out)


if __name__ == "__main__":
    main()
