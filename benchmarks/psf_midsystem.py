"""Cost of a DOE inside the lens (issue 46) against the same DOE before the sensor, A/B in one run.

System (as tests/wave_truth_doe.py): ideal lens A (f 10 mm, F/12.5, the stop), 6 mm, lens B (a thin phase surface
perfect for the beam it receives), the sensor 2.4–2.9 mm behind it; λ 0.55 µm, ks 32, 2 µm sensor pixels; every
field on a 1 µm grid (the mid-system method's blank plane 0.01 mm after B; the last-surface DOE on a plane there
too). Cases:

* ``mid``: the DOE (1 mm, 1 µm pixels) 3 mm after lens A, :class:`raywave.hybrid.midsystem.MidSystemLens`:
  a Fresnel-lens DOE (f 50 mm, continuous: one order), the same fabricated with 16 levels (the orders with ≥ 1 %:
  one), and a binary grating of 50 µm period (orders ±1, ±3, ±5);
* ``last``: the same DOE class before the sensor, :class:`raywave.hybrid.HybridLens` (the engine's one path).

The three cases above compare the defaults of both (the DOE-plane edge). ``fresnel16_1e-3``: the 16-level DOE
within the issue's 1e-3 of the reference (its weak orders −15, +17 kept, ``min_efficiency=1e-3``, the exact edge
``stop_edge="exit_pupil", edge_step="asm"``: 5.0e-4 / 5.6e-4 at 0° / 1.5°; order −31 is listed in ``orders`` but
left out as under-sampled), and ``fresnel16_1e-3_weak_doe`` the same with ``weak_edge="doe"`` (6.7e-4 / 7.7e-4),
each against the last-surface 16-level DOE at the engine's defaults (within 1e-3 of its own reference): the
comparison at equal accuracy (benchmarks/midsystem_orders_accuracy.py). ``grating_cull0.1``: the grating with the
orders far outside the crop left out (``Orders(cull_tol=0.1)``: +5, −5, +3; NOT at equal accuracy, 1.0e-3 from the
six orders; benchmarks/midsystem_cull.py). ``--cases`` runs some of them; a case whose
options an older tree does not have is reported as skipped there.

Times: median wall time of ``--repeat`` PSFs (forward; and forward + backward w.r.t. the DOE's parameters), one
thread. Prints one JSON object (and writes it with ``-o``).

For a DOE with several orders, ``last_forward_nsrc``: the last-surface DOE's PSF call with as many ordinary
sources as the mid-system DOE has orders (fields 0.01° apart), the floor of the orders' batched engine call.

Wall and CPU (``process_time``: on a shared machine, the work itself) seconds. A/B of two source trees (issue
46's cost, measured in one run): ``--a /old/tree --b . [--rounds 2]`` runs this script on each tree's ``raywave``
in its own process (``OMP_NUM_THREADS=1``), interleaved A, B, A, B, …, and reports every time's median over the
rounds per tree (and each round's), the mid/last ratios, and the B/A speed-up of the mid-system PSF::

    git worktree add --detach /tmp/m46_base 4b765c7
    python benchmarks/psf_midsystem.py --a /tmp/m46_base --b . --rounds 2 -o out.json"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
import warnings

import torch

from raywave.doe.params import FresnelDOE, GratingDOE
from raywave.hybrid import HybridLens
from raywave.hybrid.midsystem import MidSystemLens
from raywave.lens.lens import Lens
from raywave.materials import get_material
from raywave.surfaces.aperture import CircularAperture
from raywave.surfaces.geometry import Plane
from raywave.surfaces.interaction import Diffraction, IdealLens
from raywave.surfaces.surface import Surface

WL, KS, PS = 0.55, 32, 2e-3


def _pair_phase(p, q):
    sp = math.copysign(1.0, p[2])

    def phase(x, y, wavelength):
        k = 2 * math.pi / (wavelength * 1e-3)
        rp = torch.sqrt((x - p[0]) ** 2 + (y - p[1]) ** 2 + p[2] ** 2)
        rq = torch.sqrt((x - q[0]) ** 2 + (y - q[1]) ** 2 + q[2] ** 2)
        return k * (sp * rp - rq), k * (sp * (x - p[0]) / rp - (x - q[0]) / rq), k * (sp * (y - p[1]) / rp - (y - q[1]) / rq)

    return phase


def two_lens(f_doe: float, field_deg: float) -> Lens:
    """A (f 10, radius 0.4, stop) — 6 mm — B (perfect for the beam after a DOE of paraxial focal length f_doe
    3 mm after A) — the sensor."""
    t = math.tan(math.radians(field_deg))
    s = 7.0
    s2 = s if math.isinf(f_doe) else 1 / (1 / s + 1 / f_doe)
    p = (0.0, 10 * t * s2 / s, s2 - 3.0)
    z2 = 1 / (1 / p[2] + 1 / 10.0)
    q = (0.0, p[1] * z2 / p[2], z2)
    air = get_material("AIR")
    a = Surface(Plane(), air, 6.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0), is_stop=True)
    b = Surface(Plane(), air, z2, interaction=Diffraction(_pair_phase(p, q)))
    return Lens([a, b], wavelengths=(WL,), primary=0)


def _doe(kind):
    if kind == "grating":
        d = GratingDOE(0.05, 1000, 1e-3)
        return d.fabricate(2), math.inf
    d = FresnelDOE(50.0, 1000, 1e-3, wavelength=WL)
    return (d.fabricate(16) if kind == "fresnel16" else d), 50.0


def _time(fn, repeat, cpu: dict | None = None, key: str = ""):
    """Median wall seconds of ``repeat`` calls of ``fn``; the median CPU seconds (``process_time``: on a shared
    machine, the work itself, whatever the waiting) into ``cpu[key]``."""
    ts, cs = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    if cpu is not None:
        cpu[key] = statistics.median(cs)
    return statistics.median(ts)


#: the cases: (name, DOE kind, MidSystemLens options, HybridLens options of the last-surface DOE)
CASES = (
    ("fresnel", "fresnel", {}, {"stop_edge": "doe"}),
    ("fresnel16", "fresnel16", {}, {"stop_edge": "doe"}),
    ("grating", "grating", {}, {"stop_edge": "doe"}),
    # the 16-level DOE within the 1e-3 (benchmarks/midsystem_orders_accuracy.py) against the last-surface
    # 16-level DOE at the engine's defaults (within 1e-3 of its own reference): the equal-accuracy comparison
    ("fresnel16_1e-3", "fresnel16", {"min_efficiency": 1e-3, "stop_edge": "exit_pupil", "edge_step": "asm"}, {}),
    ("fresnel16_1e-3_weak_doe", "fresnel16", {"min_efficiency": 1e-3, "stop_edge": "exit_pupil", "edge_step": "asm",
                                              "weak_edge": "doe"}, {}),
    # the grating with the orders far outside the crop left out (Orders.cull_tol: +5, −5, +3 here, their bound 0.086):
    # NOT at equal accuracy against the six orders (1.0e-3 relative L1 from them; benchmarks/midsystem_cull.py)
    ("grating_cull0.1", "grating", {"cull_tol": 0.1}, {"stop_edge": "doe"}),
)


def run(repeat: int, field: float, only=None) -> dict:
    out = {"system": "ideal A (f 10, F/12.5) + 1 mm DOE at 1 µm 3 mm after it + lens B; ks 32, 2 µm pixels",
           "field_deg": field, "repeat": repeat, "threads": torch.get_num_threads(), "cases": {}}
    for name, kind, mid_kw, last_kw in CASES:
        if only and name not in only:
            continue
        doe, f_doe = _doe(kind)
        lens = two_lens(f_doe, field)
        try:
            mid = MidSystemLens(lens, doe, 0, 3.0, final_distance=0.01, final_size=1.0, final_pitch=1e-3,
                                sensor_pitch=PS, **mid_kw)
        except TypeError as e:  # an option this tree's MidSystemLens does not have (an A/B against an older tree)
            out["cases"][name] = {"skipped": str(e)}
            continue
        d2, _ = _doe(kind)
        last = HybridLens(two_lens(math.inf, field), d2, 0.01, sensor_pitch=PS, **last_kw)
        params = [p for p in doe.parameters() if p.requires_grad]
        params2 = [p for p in d2.parameters() if p.requires_grad]

        def fwd_mid():
            return mid.psf([(0.0, field)], WL, ks=KS)

        def fwd_last():
            return last.psf([(0.0, field)], WL, ks=KS)

        def bwd(f, ps):
            def go():
                y = f()
                if ps and y.requires_grad:
                    torch.autograd.grad(y[0, 0, KS // 2, KS // 2], ps, allow_unused=True)
            return go

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fwd_mid(), fwd_last()  # warm-up (imports, caches)
            cpu: dict = {}
            res = mid.psf_result([(0.0, field)], WL, ks=KS)
            culled = [list(s for s, _ in r["orders"]) for r in getattr(res, "culled", None) or []]
            row = {"orders": len(mid.orders(WL)), "mid_options": mid_kw, "last_options": last_kw,
                   "culled": culled[0] if culled else [],
                   "mid_forward_s": _time(fwd_mid, repeat, cpu, "mid_forward_cpu_s"),
                   "last_forward_s": _time(fwd_last, repeat, cpu, "last_forward_cpu_s"),
                   "mid_backward_s": _time(bwd(fwd_mid, params), repeat, cpu, "mid_backward_cpu_s"),
                   "last_backward_s": _time(bwd(fwd_last, params2), repeat, cpu, "last_backward_cpu_s")}
            n = row["orders"]
            if n > 1 and mid_kw.get("stop_edge", "doe") == "doe":  # the engine's floor: the last-surface DOE with
                many = [(0.0, field - 0.01 * i) for i in range(n)]  # as many ordinary sources (fields 0.01° apart)
                last.psf(many, WL, ks=KS)
                row["last_forward_nsrc_s"] = _time(lambda: last.psf(many, WL, ks=KS), repeat, cpu,
                                                   "last_forward_nsrc_cpu_s")
            row.update(cpu)
        row["forward_ratio"] = row["mid_forward_s"] / row["last_forward_s"]
        row["backward_ratio"] = row["mid_backward_s"] / row["last_backward_s"]
        row["forward_ratio_cpu"] = row["mid_forward_cpu_s"] / row["last_forward_cpu_s"]
        row["backward_ratio_cpu"] = row["mid_backward_cpu_s"] / row["last_backward_cpu_s"]
        out["cases"][name] = row
    return out


def _child(tree: str, repeat: int, field: float, only=None) -> dict:
    """One run of this script (the same harness for both trees) on the ``raywave`` of source tree ``tree``, one
    thread, in its own process."""
    env = dict(os.environ, PYTHONPATH=os.path.abspath(tree), OMP_NUM_THREADS="1")
    cmd = [sys.executable, os.path.abspath(__file__), "--repeat", str(repeat), "--field", str(field)]
    if only:
        cmd += ["--cases", *only]
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def run_ab(tree_a: str, tree_b: str, rounds: int, repeat: int, field: float, only=None) -> dict:
    """:func:`run` in two trees, interleaved A, B, A, B, … (``rounds`` each); medians per tree and case, the
    mid/last ratios of each tree and the B/A speed-up of the mid-system PSF."""
    runs = {"a": [], "b": []}
    for _ in range(rounds):
        for key, tree in (("a", tree_a), ("b", tree_b)):
            runs[key].append(_child(tree, repeat, field, only))
    first = runs["a"][0]
    out = {"system": first["system"], "field_deg": field, "repeat": repeat, "rounds": rounds, "threads": 1,
           "a": os.path.abspath(tree_a), "b": os.path.abspath(tree_b), "cases": {}}
    times = [f"{w}_{d}_{u}" for u in ("s", "cpu_s") for d in ("forward", "backward") for w in ("mid", "last")]
    for case in runs["b"][0]["cases"]:
        done = [k for k in ("a", "b") if "skipped" not in runs[k][0]["cases"].get(case, {"skipped": ""})]
        if not done:
            continue
        ref = runs[done[0]][0]["cases"][case]
        row = {"orders": ref["orders"], "mid_options": ref.get("mid_options"), "last_options": ref.get("last_options"),
               "culled": runs["b"][0]["cases"][case].get("culled")}
        extra = [t for t in ("last_forward_nsrc_s", "last_forward_nsrc_cpu_s") if t in ref]
        for key in done:
            med = {t: statistics.median(r["cases"][case][t] for r in runs[key]) for t in times + extra}
            if extra:  # the engine alone with as many sources as orders, over one source
                med["nsrc_over_one_cpu"] = med["last_forward_nsrc_cpu_s"] / med["last_forward_cpu_s"]
            for d in ("forward", "backward"):
                med[f"{d}_ratio"] = med[f"mid_{d}_s"] / med[f"last_{d}_s"]
                med[f"{d}_ratio_cpu"] = med[f"mid_{d}_cpu_s"] / med[f"last_{d}_cpu_s"]
            med["rounds"] = [{t: r["cases"][case][t] for t in times} for r in runs[key]]
            row[key] = med
        for d in ("forward", "backward"):
            if len(done) < 2:  # a case the old tree cannot run
                break
            row[f"mid_{d}_speedup_b_over_a"] = row["a"][f"mid_{d}_s"] / row["b"][f"mid_{d}_s"]
            row[f"mid_{d}_speedup_b_over_a_cpu"] = row["a"][f"mid_{d}_cpu_s"] / row["b"][f"mid_{d}_cpu_s"]
        out["cases"][case] = row
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--field", type=float, default=1.5, help="field angle (deg, along y)")
    ap.add_argument("--a", help="A/B: the first (old) source tree")
    ap.add_argument("--b", help="A/B: the second (new) source tree")
    ap.add_argument("--rounds", type=int, default=2, help="A/B: runs of each tree, interleaved")
    ap.add_argument("--cases", nargs="*", help=f"only these cases (of {', '.join(c[0] for c in CASES)})")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    if (a.a is None) != (a.b is None):
        ap.error("give both --a and --b for an A/B")
    res = run_ab(a.a, a.b, a.rounds, a.repeat, a.field, a.cases) if a.a else run(a.repeat, a.field, a.cases)
    text = json.dumps(res, indent=1)
    print(text)
    if a.output:
        with open(a.output, "w") as f:
            f.write(text)


if __name__ == "__main__":
    main()
