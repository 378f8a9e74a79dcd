"""The vignetting guard's figures (issue 47 class G) on lens files: per case the vignetting edge's length, the lost
ray fractions, the surface and the estimate (raywave.hybrid.coherent.vignetting), from the engine's own diagnostic
trace (no PSF). Cases as benchmarks/stop_edge_references.py's (``file:PATH:FRAC``, ``real:NAME:FRAC``,
``asphere:DEG``), or ``bundled:FRAC`` (the bundled hybrid_asphere at a fraction of its largest field).

    python benchmarks/vignetting_edges.py CASE [CASE ...] [--json OUT]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

from _report import emit_row  # benchmarks/ is on sys.path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def figures(hl, fld, wl, depth=None) -> dict:
    """The vignetting guard's figures of one source (field (2,), wavelength µm) of the HybridLens ``hl``."""
    from raywave.hybrid.coherent.geometry import footprints_and_clippings

    f = torch.tensor([list(fld)], dtype=torch.float64)
    wls = torch.tensor([wl], dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, clips, edges = footprints_and_clippings(hl.optics, hl.doe, f, wls, depth, hl.doe_z(), folds=True,
                                                   vignetting=True)
    e = edges.get((0, 0))
    out = {"field": list(fld), "wavelength_um": wl, "doe_clipped": clips[0][0][0]}
    if e is None:
        out.update(vignetted=False, estimate=0.0)
    else:
        out.update(vignetted=True, surface=e.surface, lost=e.lost, rim_lost=e.rim_lost, length=e.length,
                   clearance_zones=e.clearance, estimate=e.estimate)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    import stop_edge_references as ser

    rows = []
    for case in a.cases:
        if case.startswith("bundled:"):
            import raywave
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                hl = raywave.load_hybrid("hybrid_asphere") if hasattr(raywave, "load_hybrid") else None
            frac = float(case.split(":")[1])
            top = max(abs(float(v)) for v in hl.lens.fields)
            fld, wl, depth = (0.0, frac * top), hl.lens.primary_wavelength, None
        else:
            hl, fld, wl, depth = ser._hybrid(case, {})
        row = {"case": case, **figures(hl, fld, wl, depth)}
        emit_row(rows, row, a.json)  # streamed: an interrupted run keeps its rows


if __name__ == "__main__":
    main()
