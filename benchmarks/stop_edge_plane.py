"""How well is the exit-pupil stop edge defined off axis? (issue 19: the 1e-3 goal at 17.5°)

Both exit-pupil models put the stop's sharp edge on one surface: the ray-wave engine's exact construction
(``stop_edge="exit_pupil", edge_step="asm"``) on the paraxial exit-pupil *plane*, the Huygens model
(:func:`raywave.models.huygens_psf`) on the reference *sphere* through the chief ray's exit-pupil point. Off axis
the stop's rim is not imaged onto either: pupil aberrations put the image of each rim point at its own z
(:func:`raywave.hybrid.coherent.stop_rim_images`). This script measures, on the bundled asphere at one field
(default 1.0 of the full field, 17.5°; benchmarks/psf.py's edge case: 6 mm blank DOE at 1 µm, 0.7 mm after the
lens, 3 µm pixels, λ 0.53 µm, ks 32), L1 distances ``Σ|p − q|`` (PSFs summing to 1) of:

* the ray-wave PSF with 64 and 128 nodes (its own convergence), with its edge at the stop's rim images (the exact
  construction since 2026-11-28) and cut sharply on the paraxial exit-pupil plane (before);
* the Huygens PSF at ``n_pupil`` and 3/4 of it (the reference's own convergence), and with the obliquity factor;
* the ray-wave PSF with the sharp edge's plane moved to the mean, nearest and farthest rim image (the spread
  that the choice of one plane leaves open), each against the paraxial-plane PSF and against Huygens.

Prints one JSON object (and writes it with ``-o``). ~3 min on 2 cores at the defaults (the Huygens PSFs).

    python benchmarks/stop_edge_plane.py [--field 1.0] [--n-pupil 384] [--threads 2] [-o out.json]
"""

from __future__ import annotations

import argparse
import sys
import time

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

KS, PITCH, WL = 32, 3e-3, 0.53


def _l1(a, b) -> float:
    return float((a / a.sum() - b / b.sum()).abs().sum())


def run(field_fraction: float, n_pupil: int) -> dict:
    import torch

    from psf import DOE_DIST, DOE_PITCH, _edge_lens
    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens
    from raywave.hybrid.coherent import stop_rim_images
    from raywave.models import huygens_psf

    _, lens = _edge_lens("doe", "auto")
    fld = (0.0, field_fraction * max(lens.fields))
    out = {"benchmark": "stop edge plane", "lens": "hybrid_asphere", "field_deg": fld[1], "wavelength_um": WL,
           "ks": KS, "pixel_mm": PITCH, "metric": "L1 = sum|p - q| (0..2)"}

    import raywave.hybrid.coherent.exit_pupil as xp

    def engine(nodes=64, plane=None, rim=True):
        hl = HybridLens(lens, BlankDOE(6000, DOE_PITCH), DOE_DIST, sensor_pitch=PITCH, stop_edge="exit_pupil",
                        edge_step="asm")
        if plane is not None:  # the sharp edge on another plane (a probe of the model, not an option)
            hl._exit_pupil_planes = lambda wls: [plane for _ in wls]
        real = xp._rim_step_plane
        if not rim:  # the edge cut sharply on the (exit-pupil) plane, as before 2026-11-28
            xp._rim_step_plane = lambda rim_, z_xp, *a: (None, z_xp)
        try:
            return hl, hl.psf(fld, WL, ks=KS, rays=nodes)[0, 0].detach()
        finally:
            xp._rim_step_plane = real

    t0 = time.perf_counter()
    hl, p64 = engine(64)
    _, p128 = engine(128)
    out["engine_64_vs_128_nodes"] = _l1(p64, p128)
    ref = huygens_psf(lens, fld, WL, ks=KS, pitch=PITCH, n_pupil=n_pupil).psf.to(torch.float64)
    coarse = huygens_psf(lens, fld, WL, ks=KS, pitch=PITCH, n_pupil=3 * n_pupil // 4).psf.to(torch.float64)
    obl = huygens_psf(lens, fld, WL, ks=KS, pitch=PITCH, n_pupil=n_pupil, obliquity=True).psf.to(torch.float64)
    out["n_pupil"] = n_pupil
    out["huygens_3/4_vs_n_pupil"] = _l1(coarse, ref)
    out["huygens_obliquity_vs_without"] = _l1(obl, ref)
    out["engine_vs_huygens"] = _l1(p64, ref)  # the edge at the rim images (the exact construction's default)
    _, p_plane = engine(64, rim=False)
    out["engine_plane_edge_vs_huygens"] = _l1(p_plane, ref)
    z0 = hl.exit_pupil_z(WL)
    _, zr = stop_rim_images(lens, torch.tensor(fld, dtype=torch.float64), WL, None)
    zr = zr.detach()
    out["exit_pupil_z_paraxial_mm"] = z0
    out["rim_image_z_mm"] = {"min": float(zr.min()), "mean": float(zr.mean()), "max": float(zr.max())}
    rows = []
    for name, z in (("mean", float(zr.mean())), ("min", float(zr.min())), ("max", float(zr.max()))):
        _, p = engine(64, z, rim=False)
        rows.append({"edge_plane": name, "z_mm": z, "dz_mm": z - z0, "vs_paraxial_plane": _l1(p, p_plane),
                     "vs_huygens": _l1(p, ref)})
        print(rows[-1], file=sys.stderr, flush=True)
    out["moved_edge_plane"] = rows
    out["seconds"] = time.perf_counter() - t0
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--field", type=float, default=1.0, help="fraction of the full field (default 1.0: 17.5°)")
    ap.add_argument("--n-pupil", type=int, default=384, help="Huygens pupil cells per side (default 384)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("-o", "--output", default=None)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    out = run(a.field, a.n_pupil)
    out["threads"] = a.threads
    emit_json(out, a.output)
    return out


if __name__ == "__main__":
    main()
