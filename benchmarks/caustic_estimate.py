"""Issue 47: the a-priori estimate of the DOE plane's nearness to a caustic (:func:`raywave.hybrid.coherent.exit_pupil.
go_phase_error`, the geometric-optics field's second-order phase error, rad) beside the default's error from the
converged references, for the cases of benchmarks/stop_edge_references.py; with the other candidates measured for
the issue (the beam's width ratio to its first crossing plane, the ray map's smallest Jacobian over its median, the
distance to the nearest local focus in depths of focus λ/NA², and the edge rays' aberration over their Fresnel
number). Tracing only (seconds per case). One JSON line per case (and the list with ``-o``).

    PYTHONPATH=. python benchmarks/caustic_estimate.py [CASES] [--errors F.json] [-o F]
"""

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stop_edge_references as ser  # noqa: E402

from raywave.hybrid.coherent.exit_pupil import (GO_FALLBACK_FRACTION, GO_PHASE_TOL, edge_focus_many,  # noqa: E402
                                                go_phase_error)
from raywave.hybrid.coherent.settings import Source  # noqa: E402
from raywave.lens.analysis import fold_fraction, pupil_grid  # noqa: E402
from raywave.lens.sources import point_source_rays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
K47 = ROOT / "benchmarks/results/stop_edge_references_2026-11-29_k47.json"


def candidates(lens, fld, wl, depth, z_doe, z_s) -> dict:
    """The other estimates of one source (see the module's docstring)."""
    px, py, idx = pupil_grid(32, lens.device)
    rays = point_source_rays(lens, torch.tensor([fld], dtype=torch.float64), [wl], pupil=(px, py), aim="full",
                             depth=depth)
    out = lens.trace(rays)
    n = float(lens.surfaces[-1].material.n(torch.tensor([wl], dtype=torch.float64)))
    t = out.d[0, 0, :, :2] / out.d[0, 0, :, 2:]
    x = out.o[0, 0, :, :2] + t * (z_doe - out.o[0, 0, :, 2:])
    v = out.valid[0, 0]
    sgn = 1.0 if z_s > z_doe else -1.0
    zs = z_doe + sgn * torch.linspace(0, abs(z_s - z_doe) * 0.999, 400, dtype=torch.float64)
    xyz = x[None] + t[None] * (zs - z_doe)[:, None, None]
    folded = torch.nonzero(fold_fraction(xyz, v.expand(xyz.shape[:-1]), idx, 32) > 0)

    def width(z):
        p = (x + t * (z - z_doe))[v]
        return float((p.amax(0) - p.amin(0)).max())

    zc = float(zs[int(folded[0])]) if folded.numel() else None
    # the ray map's Jacobian on the plane (cells of the 32² grid) and its roots along z: the rays' local foci
    full = torch.full((32 * 32, 2), math.nan, dtype=torch.float64)
    full[idx] = torch.where(v[:, None], x, torch.full_like(x, math.nan))
    ft = torch.full((32 * 32, 2), math.nan, dtype=torch.float64)
    ft[idx] = torch.where(v[:, None], t, torch.full_like(t, math.nan))
    g, gt = full.reshape(32, 32, 2), ft.reshape(32, 32, 2)
    a1, b1 = g[:-1, 1:] - g[:-1, :-1], g[1:, :-1] - g[:-1, :-1]
    a2, b2 = gt[:-1, 1:] - gt[:-1, :-1], gt[1:, :-1] - gt[:-1, :-1]
    cc = a1[..., 0] * b1[..., 1] - a1[..., 1] * b1[..., 0]
    qa = a2[..., 0] * b2[..., 1] - a2[..., 1] * b2[..., 0]
    qb = a1[..., 0] * b2[..., 1] + a2[..., 0] * b1[..., 1] - a1[..., 1] * b2[..., 0] - a2[..., 1] * b1[..., 0]
    ok = torch.isfinite(cc)
    disc = (qb * qb - 4 * qa * cc).clamp_min(0).sqrt()
    roots = torch.stack([(-qb - disc) / (2 * qa), (-qb + disc) / (2 * qa)])
    ahead = torch.where(roots * sgn > 0, roots.abs(), torch.full_like(roots, math.inf)).amin(0)
    ahead = float(ahead[ok].min())
    tv = t[v]
    na = n * math.sin(math.atan(float((tv - tv[0]).norm(dim=-1).max()) / 2))  # half the cone's full angle
    dof = wl * 1e-3 / n / (na / n) ** 2
    waves, zf, na_e, n_e = edge_focus_many(lens, [list(fld)], [wl], depth)[0][0]
    nf = abs(zf - z_doe) / ((wl * 1e-3 / n_e) / (na_e / n_e) ** 2)
    return dict(z_first_crossing=zc, width_ratio=width(z_doe) / width(zc) if zc is not None else None,
                jacobian_min_over_median=float(cc[ok].abs().min() / cc[ok].abs().median()),
                focus_distance_dof=ahead / dof, edge_waves=waves, edge_fresnel_number=nf, edge_waves_over_nf=waves / nf)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*")
    ap.add_argument("--errors", default=str(K47), help="the default's errors (stop_edge_references.py's JSON)")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    known = {r["case"]: r for r in json.loads(Path(a.errors).read_text())["rows"]}
    rows = []
    for case in a.cases or list(known):
        hl, fld, wl, depth = ser._hybrid(case, {})
        lens = hl.optics
        z_doe, z_s, z_xp = float(hl.doe_z()), float(hl.sensor_z()), float(hl.exit_pupil_z(wl))
        src = Source(fld, wl, depth, lens.field_type)
        zs, err = go_phase_error(lens, src, z_xp, z_doe)
        fine = torch.nonzero(err <= GO_FALLBACK_FRACTION * GO_PHASE_TOL).squeeze(1)
        r = known.get(case, {})
        row = dict(case=case, default_l1=(r.get("default") or {}).get("l1"), doe_l1=(r.get("doe") or {}).get("l1"),
                   z_doe=z_doe, z_xp=z_xp, z_sensor=z_s, go_phase_error_rad=float(err[-1]),
                   triggers=bool(float(err[-1]) > GO_PHASE_TOL),
                   fallback_mm_before=(z_doe - float(zs[int(fine[-1])])) if fine.numel() else None,
                   **candidates(lens, list(fld), wl, depth, z_doe, z_s))
        print(json.dumps(row), flush=True)
        rows.append(row)
    if a.output:
        Path(a.output).write_text(json.dumps(dict(
            command="PYTHONPATH=. python benchmarks/caustic_estimate.py -o F", tolerance_rad=GO_PHASE_TOL,
            rows=rows), indent=1))
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    warnings.simplefilter("ignore")
    main()
