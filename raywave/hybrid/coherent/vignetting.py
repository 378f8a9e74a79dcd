"""A guard for the exit-pupil stop edge (issue 47, class G): an aperture other than the stop that vignettes a
source's stop-filling beam, or lies near its rim, and what leaving that aperture's own edge waves out may cost.

The exit-pupil edge (``stop_edge="exit_pupil"``, the default) diffracts the stop's rim from its images; an aperture
that vignettes the beam is cut sharply on the DOE plane, without its edge waves (docs/ray-wave.md, "An aperture that
vignettes the beam cuts it"), and one just outside the beam's rim clips the stop edge's own waves, which the engine
does not see. Against a wave truth (benchmarks/vignetting_truth.py) the cost does not follow the cut edge's length: a
sliver costs as much as a deep cut, and an aperture a fraction of a Fresnel zone outside the rim nearly as much.
:func:`vignetting_edges` reads which rays were lost from the rays :func:`~raywave.hybrid.coherent.geometry.
footprints_and_clippings` already traces (the stop grid and the rim ring, aimed and traced with the apertures once
for the call), and :func:`rim_clearance` the rim's clearance inside the other apertures in Fresnel zones; only the
sources that lost rays, or come near such an aperture, are traced again, with the per-surface record, to name the
surface. A guard, not a figure: :func:`estimate` of the clearance (:data:`CUT_COST` where the aperture cuts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from raywave.lens.paraxial import system_matrix

#: what an aperture that cuts the beam, or lies at its rim, costs the default's PSF (relative L1): half the upper end
#: of the DOE-plane (sharp) edge's cost for the stop's whole rim on the scan's real lenses (1e-2 – 1e-1,
#: docs/ray-wave.md's seed-scan table). Measured (benchmarks/vignetting_truth.py against the two-ideal-lens wave truth
#: with a clear aperture on lens B, whose DOE-plane edge is 4.5e-2; vignetting_warning_2026-12-01_xxvii_h47g.json):
#: 1.6e-2 – 2.0e-2 whether the aperture cuts a sliver (0.5 % of the rays) or a quarter of the beam, or passes 6 µm
#: outside its rim (the stop edge's waves clipped there): not the cut edge's length; the JP S48-25673 at full field
#: 7.0e-3, the Pro-Tessar with its semi-diameters clipping at 0.7 field 8.2e-3 (their DOE-plane edges 2.5e-2 / 5.4e-2)
CUT_COST = 0.05

#: how fast that cost falls with the aperture's clearance outside the beam's rim, per Fresnel zone of the stop edge's
#: waves there (``sqrt(λ |B|)``, B the stop → surface ray-transfer element): the truth's 1.65e-2, 9.5e-3, 2.2e-3,
#: 7.8e-4 at 0.08, 0.35, 1.03, 1.70 zones, ~exp(-1.8 c); 4.4 zones: the truth's own level (2e-4)
ZONE_DECAY = 1.8

#: the guard's estimate (relative L1 of the PSF) from which :class:`~raywave.hybrid.coherent.record.
#: VignettingEdgeWarning` warns
VIGNETTING_WARN = 1e-3

#: the clearance (Fresnel zones) below which an aperture is looked at: where the estimate reaches
#: :data:`VIGNETTING_WARN` (2.17 zones)
NEAR_ZONES = math.log(CUT_COST / VIGNETTING_WARN) / ZONE_DECAY

#: a ray outside a non-stop aperture by less than this fraction of the aperture's extent counts as passing it in the
#: lost-ray figures (an element's clear aperture printed at the beam's rim: the rim ring lies 1e-9 inside the stop's
#: edge); the clearance still sees it (0 zones)
RIM_TOLERANCE = 1e-3


def estimate(clearance: float) -> float:
    """The guard's estimate (relative L1) for an aperture ``clearance`` Fresnel zones outside the beam's rim (≤ 0: it
    cuts the beam): :data:`CUT_COST` · exp(-:data:`ZONE_DECAY` · max(clearance, 0))."""
    return CUT_COST * math.exp(-ZONE_DECAY * max(clearance, 0.0))


def aperture_zones(lens, wavelengths) -> tuple | None:
    """``(surfaces [J], zones (W, J) mm)``: the lens's apertures other than the stop's and the Fresnel zone there of
    the stop edge's waves at each wavelength (µm, (W,) tensor): ``sqrt(λ |B|)``, B the reduced ray-transfer element
    between the stop and the surface (paraxial, on axis; the same either way along the axis, the end surfaces'
    powers not entering it); None without such apertures or where the paraxial matrices are undefined (a decentred
    or folded lens)."""
    stop = lens.stop_index
    js = [j for j, s in enumerate(lens.surfaces) if s.aperture is not None and j != stop]
    if not js:
        return None
    try:
        rows = []
        for wl in wavelengths.reshape(-1).tolist():
            b = torch.stack([system_matrix(lens, wl, min(j, stop), max(j, stop) + 1)[0, 1] for j in js])
            rows.append(torch.sqrt(wl * 1e-3 * b.abs()).clamp_min(1e-9))
        return js, torch.stack(rows)
    except (ValueError, NotImplementedError, RuntimeError):
        return None


def rim_clearance(lens, rim, zones: tuple) -> tuple:
    """``(clearance (F, W), surface (F, W))``: the least clearance (Fresnel zones of :func:`aperture_zones`
    ``zones``) of the beam's rim ring ``rim`` (aimed rays (F, W, R)) inside the non-stop apertures, and the surface
    where it is least; -inf where a rim ray misses a surface (or meets total internal reflection). One recorded trace
    without the apertures; no host read."""
    js, z = zones
    _, rec = lens.trace(rim, record=True, apertures=False)
    ok = rec.valid[-1]
    per = []
    for k, j in enumerate(js):
        x, y = rec.points[j + 1][0], rec.points[j + 1][1]
        c = lens.surfaces[j].aperture.slack(x, y) / z[:, k][None, :, None]
        per.append(torch.where(ok, c, torch.full_like(c, -math.inf)).amin(-1))
    c = torch.stack(per, -1)  # (F, W, J)
    at = c.argmin(-1)
    surf = torch.tensor(js, dtype=torch.int64, device=c.device)[at]
    return c.amin(-1), surf


@dataclass(frozen=True)
class VignettingEdge:
    """One source's vignetting by apertures other than the stop (and the DOE's, :class:`DOEApertureWarning`).

    Attributes:
        surface: the index of the surface that loses the most of the source's rays (its clear aperture, or the
            rays miss it or meet total internal reflection there).
        lost: the fraction of the stop grid's rays lost before the DOE plane (by any surface but the stop).
        rim_lost: the fraction of the stop rim's ring of rays lost.
        length: the vignetting edge's length across the stop (in the stop's radius: the larger of the grid's
            boundary-crossing estimate and the lost rim's arc) over the stop rim's 2π.
        clearance: the least clearance of the beam's rim inside those apertures, in Fresnel zones of the stop edge's
            waves there (≤ 0: an aperture cuts the beam; -inf: a rim ray misses a surface).
        estimate: what the missing edge waves may cost the PSF (relative L1; a guard, not a figure):
            :func:`estimate` of the clearance.
    """

    surface: int
    lost: float
    rim_lost: float
    length: float
    clearance: float
    estimate: float


def edge_length(state: torch.Tensor, n_grid: int) -> torch.Tensor:
    """The length (in stop radii) of the boundary between passing (``state`` 1) and vignetted (2) cells of the
    ``n_grid``² stop grid ``state`` (..., n_grid, n_grid) (0: outside the stop or lost at the stop itself, ignored):
    the count of neighbouring passing/vignetted pairs along x and y times the cell size ``2 / n_grid`` times π/4
    (Cauchy–Crofton: a curve of random direction crosses (|cos| + |sin|) / h grid lines per unit length, 4/π on
    average). Returns (...,) float64."""
    a, b = state[..., :, :-1], state[..., :, 1:]
    c, d = state[..., :-1, :], state[..., 1:, :]
    cross_x = ((a * b) == 2).sum((-1, -2))  # {1, 2}: one passes, the other is vignetted
    cross_y = ((c * d) == 2).sum((-1, -2))
    return (cross_x + cross_y).to(torch.float64) * (2.0 / n_grid) * (math.pi / 4.0)


def _lost_where(lens, rays, tol: float) -> torch.Tensor:
    """(..., N) int64: the index of the surface where each ray of ``rays`` (aimed, in object space) is lost (-1: it
    passes every surface), from one recorded trace without the apertures (the rays' points on every surface, where
    a trace with them parks the lost rays on the axis): the first surface that the ray misses (or meets total
    internal reflection at) or whose aperture it passes outside; outside a non-stop aperture by less than ``tol`` ×
    its extent counts as passing it."""
    _, rec = lens.trace(rays, record=True, apertures=False)
    first = torch.full(rays.valid.shape, -1, dtype=torch.int64, device=rays.valid.device)
    for i, s in enumerate(lens.surfaces):
        gone = ~rec.valid[i + 1]
        if s.aperture is not None:
            x, y = rec.points[i + 1][0], rec.points[i + 1][1]
            ext = s.aperture.extent if i != lens.stop_index else 0.0
            ext = ext if ext is not None and math.isfinite(ext) else 1.0
            gone = gone | (s.aperture.slack(x, y) < -tol * ext)
        first = torch.where(gone & (first < 0), torch.full_like(first, i), first)
    return first


def vignetting_edges(lens, rays, suspect: list, grid: tuple, n_rim: int, near: dict | None = None) -> dict:
    """``{(f, w): VignettingEdge}`` for the sources ``suspect`` (``(f, w)`` indices into the aimed bundle ``rays``
    (F, W, N): the footprint's ``n_rim`` rim rays first, then the :func:`~raywave.lens.analysis.pupil_grid` cells
    ``grid`` = ``(index, n_grid)``) some of whose rays were lost before the DOE plane: one recorded trace of their
    rays, one host read. Sources whose rays are all lost at the stop itself (an obscuration on it), or by a hair at a
    rim aperture (:data:`RIM_TOLERANCE`), are left out."""
    if not suspect:
        return {}
    index, n_grid = grid
    dev = rays.o.device
    fi = torch.tensor([s[0] for s in suspect], dtype=torch.long, device=dev)
    wi = torch.tensor([s[1] for s in suspect], dtype=torch.long, device=dev)
    sub = rays[fi, wi][:, None]  # (S, 1, N)
    with torch.no_grad():
        first = _lost_where(lens, sub, RIM_TOLERANCE)
    first = first[:, 0]  # (S, N)
    stop = lens.stop_index
    lost = (first >= 0) & (first != stop)
    rim, cells = lost[:, :n_rim], lost[:, n_rim:]
    at_stop = (first[:, n_rim:] == stop)
    full = torch.zeros((len(suspect), n_grid * n_grid), dtype=torch.int64, device=dev)
    full[:, index] = torch.where(at_stop, 0, torch.where(cells, 2, 1))
    length = torch.maximum(edge_length(full.reshape(-1, n_grid, n_grid), n_grid),
                           2.0 * math.pi * rim.to(torch.float64).mean(-1)) / (2.0 * math.pi)
    n_surf = len(lens.surfaces)
    counts = torch.stack([(first == i).sum(-1) for i in range(n_surf)], -1)  # (S, surfaces)
    counts[:, stop] = 0
    worst = counts.argmax(-1)
    table = torch.stack([cells.to(torch.float64).mean(-1), rim.to(torch.float64).mean(-1), length,
                         worst.to(torch.float64)], -1).cpu().tolist()  # one host read
    near = near or {}
    out = {}
    for s, (c, r, ell, j) in zip(suspect, table):
        clear, j_near = near.get(s, (-math.inf, None))
        if ell > 0 or c > 0 or r > 0:  # rays lost: the aperture cuts the beam
            out[s] = VignettingEdge(int(j), c, r, ell, min(clear, 0.0), estimate(min(clear, 0.0)))
        elif j_near is not None and clear < NEAR_ZONES:  # none lost: an aperture near the rim clips the edge's waves
            out[s] = VignettingEdge(int(j_near), 0.0, 0.0, 0.0, clear, estimate(clear))
    return out
