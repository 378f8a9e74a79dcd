"""Issue 47's cost: how the exit-pupil stop edge's accuracy and window size depend on the width of its Fresnel ripple
band on the DOE plane (``RIPPLE_ZONES``, 5 zones; the band's outer end only, the edge wave's inner tail kept at its
5-zone value unless ``--coupled``). A study: it sets the module constants ``RIPPLE_ZONES`` of
raywave.hybrid.coherent.accurate / exit_pupil (and ``_nu_inner``) for the run, as a user cannot.

``cases``: the default edge's rel L1 against the converged references of benchmarks/stop_edge_references.py (its
cases, ks 32, ``--cache`` the folder of its references), with the DOE-plane field's window (samples) per case.
``map``: the bundled ``hybrid_asphere`` PSF map (``--grid`` × ``--grid`` fields × 3 wavelengths, ks 64): CPU seconds
(``time.process_time``, one thread: a shared machine's wall time says nothing) and the windows' mean sample count, per
band width, and the DOE-plane edge (``stop_edge="doe"``) for the ratio. One JSON line per run.

    PYTHONPATH=. python benchmarks/ripple_margin.py cases --zones 5 3 2 --cache DIR asphere:0 real:cooke_triplet:0
    PYTHONPATH=. python benchmarks/ripple_margin.py map --zones 5 4 3 2 --doe
"""

import argparse
import json
import math
import sys
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


@contextmanager
def ripple_zones(zones: float, coupled: bool, windows: list):
    """The exit-pupil edge with ``zones`` Fresnel zones of ripple band (the inner tail at 5 zones unless
    ``coupled``), the DOE-plane windows' shapes appended to ``windows``."""
    import raywave.hybrid.coherent.accurate as ac
    import raywave.hybrid.coherent.stop_edge as se

    saved = (se.RIPPLE_ZONES, se.MAX_RIPPLE_ZONES, ac._nu_inner, se._nu_inner, ac._window_field)
    full = se.RIPPLE_ZONES
    window_field = ac._window_field

    def recorded(b, env, box, sim, rays):
        windows.append(tuple(env.shape))
        return window_field(b, env, box, sim, rays)

    se.RIPPLE_ZONES = se.MAX_RIPPLE_ZONES = float(zones)  # fixed (no reach rule)
    if not coupled:
        ac._nu_inner = se._nu_inner = lambda _zones: se.INNER_TAIL * math.sqrt(2.0) * full
    ac._window_field = recorded
    try:
        yield
    finally:
        se.RIPPLE_ZONES, se.MAX_RIPPLE_ZONES, ac._nu_inner, se._nu_inner, ac._window_field = saved


def run_cases(a):
    import stop_edge_references as refs

    for zones in a.zones:
        for case in a.cases:
            windows = []
            t = time.process_time()
            with ripple_zones(zones, a.coupled, windows):
                r = refs.run(case, 32, ["default"], a.max_n, a.cache)
            d = r.get("default", r.get("error"))
            print(json.dumps(dict(case=case, zones=zones, coupled=a.coupled, l1=d["l1"] if isinstance(d, dict) else d,
                                  window=list(windows[0]) if windows else None, cpu_s=time.process_time() - t,
                                  ref_error=r.get("ref_error"))), flush=True)


def run_map(a):
    from raywave.assembly.build import load_hybrid
    from raywave.imaging import psf_map

    runs = [("exit_pupil", z) for z in a.zones] + ([("doe", None)] if a.doe else [])
    for edge, zones in runs:
        windows = []
        hl = load_hybrid("hybrid_asphere", stop_edge=None if edge == "exit_pupil" else "doe")
        with ripple_zones(zones if zones is not None else 5.0, a.coupled, windows), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            psf_map(hl, (a.grid, a.grid), wavelengths=[0.66, 0.53, 0.47], ks=a.ks, progress=False)  # warm
            windows.clear()
            t = time.process_time()
            psf_map(hl, (a.grid, a.grid), wavelengths=[0.66, 0.53, 0.47], ks=a.ks, progress=False)
            cpu = time.process_time() - t
        n = 3 * a.grid * a.grid
        print(json.dumps(dict(edge=edge, zones=zones, coupled=a.coupled, grid=a.grid, ks=a.ks, psfs=n, cpu_s=cpu,
                              cpu_s_per_psf=cpu / n, windows_built=len(windows),
                              mean_window_samples=sum(h * w for h, w in windows) / max(len(windows), 1))), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["cases", "map"])
    ap.add_argument("cases", nargs="*")
    ap.add_argument("--zones", type=float, nargs="+", default=[5.0, 3.0, 2.0])
    ap.add_argument("--coupled", action="store_true",
                    help="the inner tail follows the band (as FieldSettings.ripple_zones)")
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--max-n", type=int, default=1024)
    ap.add_argument("--grid", type=int, default=6)
    ap.add_argument("--ks", type=int, default=64)
    ap.add_argument("--doe", action="store_true", help="map: also the DOE-plane edge")
    a = ap.parse_intermixed_args(argv)
    torch.set_num_threads(1)
    torch.set_grad_enabled(False)
    (run_cases if a.what == "cases" else run_map)(a)


if __name__ == "__main__":
    main()
