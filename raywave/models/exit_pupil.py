"""Exit-pupil (Huygens) diffraction PSF from traced rays: an independent reference for the ray-wave engine.

The model (Zemax "Huygens PSF"; Chen et al. 2021):

1. A regular n_pupil × n_pupil grid of cells over the normalised stop [-1, 1]² is traced from the field
   point (rays aimed at the cell centres on the stop, ``aim="full"``), with the stop's aperture switched
   off: instead, each cell is weighted by the fraction of it that lies inside the stop (a circular stop
   gets an anti-aliased edge; cells fully outside carry nothing). Every other aperture clips hard: a
   vignetted ray carries nothing.
2. Each ray is carried (straight, in the image medium, keeping its float64 OPL) to the **reference
   sphere**: centred on the chief ray's intersection C with the sensor plane, through the point E where
   the chief ray crosses the paraxial exit-pupil plane (radius R = |E − C|, as in
   :func:`raywave.lens.analysis.wavefront_opd`; the sphere may be virtual, i.e. reached backwards).
3. Power: a ray's cell carries dP ∝ (power per unit entrance-pupil-plane area,
   :func:`raywave.lens.sources.source_weight`: uniform for a distant object, cos³/r² for a near one) ×
   (the cell's entrance-plane area) × (its stop coverage). Its area dS on the sphere comes from central
   finite differences of the ray positions over the pupil grid (one-sided next to a failed ray), times the
   stop coverage as well: a partly covered cell keeps the irradiance of a full one over part of its area.
   The field amplitude on the sphere is A = sqrt(dP/dS), so each sample contributes A·dS = sqrt(dP·dS).
4. Huygens–Fresnel sum over the sphere samples Q_j to every sensor sample P:

       U(P) = (n/λ) Σ_j sqrt(dP_j dS_j) · K_j · exp(i k₀ (OPL_j + n |P − Q_j|)) / |P − Q_j|

   with K = 1 by default, or (``obliquity=True``) the Fresnel–Kirchhoff K = (1 + cos χ)/2, χ the angle
   between P − Q and the inward sphere normal: near the focus χ ≲ |P − C|/R, so K − 1 ~ 1e-6 and the PSF
   changes by ~1e-7 (L1, F/4 ideal lens over ±15 µm).

Pixel integration: by default (``oversample=None``) the pixel-integrated |U|² uses q×q Gauss–Legendre nodes
per pixel, q = :func:`auto_oversample` chosen from the PSF's bandwidth: |U|² holds spatial frequencies up to
2·NA/λ (NA = n·max |d⊥ − d⊥,chief| over the traced rays), and q = ceil(2 + 4·NA·pitch/λ) nodes integrate a
pixel of that band to ~1e-4 in L1 (measured on the Debye focus: F/4 at 3 µm pixels, q = 5, L1 3e-5, where
the former default of 3 midpoint samples per axis left 0.07 and even 15 left 2.7e-3). An explicit integer
``oversample`` keeps the midpoint rule with that many samples per pixel and axis. The PSF is normalised to
sum 1. ``energy_fraction`` = crop power / Σ_j dP_j / cos γ_j (γ_j: ray angle to the
axis), the Parseval total of |U|² over the whole plane in the Debye approximation — the same convention
as :mod:`raywave.models.debye`.

Quadrature: ``quadrature="grid"`` (the cells of a square grid, as above) or ``"polar"`` (:func:`polar_nodes`: Gauss–
Legendre rings × the trapezoid rule in azimuth, spectrally convergent for a circular stop; the default of
``n_pupil="auto"``). The sum over the sphere runs as matrix products on tiles of the sensor's tensor grid of nodes
(:mod:`raywave.models.huygens_sum`, ~1e-6 of the point-by-point sum, ~10× faster), the point-by-point sum only with
``obliquity``.

Sampling limits: the discrete sum replicates the PSF with period λ/(n Δ(sinθ)) ≈ λ·n_pupil/(2·NA) on the
sensor, so n_pupil must exceed 2·NA·(crop width + PSF extent)/λ; and the wavefront must change by less than
about half a wave per pupil cell; :func:`huygens_psf` warns (RuntimeWarning) when either fails.
Cost ∝ (ks·q)² × n_pupil²; the sum is chunked (< 100 MB of temporaries).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from raywave.lens import paraxial
from raywave.lens.sources import chief_ray, entrance_plane_z, point_source_rays, source_weight
from raywave.models.base import ModelPSFResult, PSFModel
from raywave.models.huygens_sum import huygens_sum_grid

#: Largest (sensor points × sphere points) block of the Huygens sum (~50 bytes each in temporaries).
_BLOCK = 1 << 20
#: Sub-samples per axis used to measure how much of an edge cell lies inside a circular stop.
_COVER_SUB = 16
#: Most Gauss–Legendre nodes per pixel and axis that :func:`auto_oversample` returns.
_MAX_NODES = 32
#: ``n_pupil="auto"``: the estimated rel L1 error of the reference that ends the refinement (default)
AUTO_TOL = 2e-4
#: ``n_pupil="auto"``: the finest pupil grid (cells per side) tried (cost ∝ n²: ~2–3 min at ks 32, 768 cells)
AUTO_MAX_N = 768
#: ``n_pupil="auto"``: the smallest first grid, and the wavefront's largest change (waves) between neighbouring cells
AUTO_MIN_N = 128
AUTO_WAVES_PER_CELL = 0.25
#: ``n_pupil="auto"``: the refinement ratio between levels
AUTO_RATIO = 1.5
#: ``n_pupil="auto"`` with ``quadrature="polar"``: the first level as a fraction of :func:`auto_n_pupil`'s grid, and
#: the ratio between levels (its error falls faster than any power of n once the wavefront is resolved)
POLAR_FIRST = 0.4
POLAR_RATIO = 1.25


def auto_oversample(na: float, wavelength: float, pitch: float) -> int:
    """Gauss–Legendre nodes per pixel and axis that integrate |U|² over a pixel to ~1e-4 (L1 of the PSF).

    |U|² on the sensor is band-limited to 2·NA/λ; with ``r = pitch / (λ/(2 NA))`` (pixel over the PSF's
    finest period) the measured need on the Debye focus is q ≈ 2 + 2r (F/4, 0.53 µm: 1 µm pixels q = 3,
    L1 2.4e-5; 3 µm pixels q = 5, 3.4e-5; NA 0.25 at 3 µm: q = 8, 2.1e-5). na: n·sin of the cone's
    half-angle about the chief ray; wavelength: µm; pitch: mm."""
    r = pitch * 2.0 * na / (wavelength * 1e-3)
    return int(min(max(math.ceil(2.0 + 2.0 * r - 1e-9), 1), _MAX_NODES))


def _pixel_nodes(ks: int, pitch: float, q: int, gauss: bool):
    """Sample offsets (ks·q,) mm from the crop centre along one axis (pixel i centred at (i − ks//2)·pitch) and
    their weights (q,) summing to 1 within a pixel: Gauss–Legendre nodes, or the midpoint rule."""
    if gauss:
        x, w = np.polynomial.legendre.leggauss(q)
        sub, w = 0.5 * pitch * x, w / 2.0
    else:
        sub, w = ((np.arange(q) + 0.5) / q - 0.5) * pitch, np.full(q, 1.0 / q)
    pix = (np.arange(ks) - ks // 2) * pitch
    return (pix[:, None] + sub[None, :]).reshape(-1), torch.from_numpy(w)


@dataclass
class HuygensPSF:
    """Result of :func:`huygens_psf`.

    psf: (ks, ks) float64, pixel-integrated irradiance normalised to sum 1, [iy, ix] increasing with y, x.
    center: (x, y) mm of the centre of pixel [ks//2, ks//2] on the sensor.
    sensor_z: z of the sensor plane (mm); pitch: pixel size (mm).
    energy_fraction: power in the crop / power through the whole plane (see the module docstring).
    sphere_center: (x, y, z) mm, the chief ray's sensor intercept; sphere_radius: R (mm).
    n_rays: rays that contributed.
    n_pupil: pupil cells per side of the (finest) grid used.
    error_estimate: with ``n_pupil="auto"``, the estimated rel L1 error of ``psf`` from the pupil sampling (see
        :func:`huygens_psf`); None for a fixed ``n_pupil``.
    levels: with ``n_pupil="auto"``, ``((n, rel L1 change from the previous level), ...)`` of every grid tried.
    """

    psf: torch.Tensor
    center: tuple[float, float]
    sensor_z: float
    pitch: float
    energy_fraction: float
    sphere_center: tuple[float, float, float]
    sphere_radius: float
    n_rays: int
    n_pupil: int = 0
    error_estimate: float | None = None
    levels: tuple = ()


def _chief_past_obscurations(lens, rays, z_s: float, n_img: float):
    """The chief ray on the sensor plane z_s, vignetted by the clear apertures only: an obscuration may block it
    (an obscured pupil on axis), and the reference sphere needs only its path."""
    out, rec = lens.trace(rays, record=True, apertures=False)
    ok = out.valid
    for i, s in enumerate(lens.surfaces):
        if s.aperture is not None:
            ok = ok & s.aperture.clear_contains(rec.points[i + 1][0], rec.points[i + 1][1])
    return out.replace(valid=ok).propagate_to_z(z_s, n_img)


def _stop_coverage(lens, n: int, dtype, device):
    """Pupil cell centres (n, n) px, py over [-1, 1]² and the fraction (n, n) of each cell inside the stop."""
    h = 2.0 / n
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) * h - 1
    py, px = torch.meshgrid(c, c, indexing="ij")
    aperture = lens.surfaces[lens.stop_index].aperture
    if aperture is not None and aperture.shape == "square":
        return px, py, torch.ones_like(px)  # the cells tile the square exactly
    r = torch.hypot(px, py)
    cover = (r <= 1).to(dtype)
    edge = (r - 1).abs() <= h / math.sqrt(2)
    s = ((torch.arange(_COVER_SUB, dtype=dtype, device=device) + 0.5) / _COVER_SUB - 0.5) * h
    sx = px[edge][:, None, None] + s[None, None, :]
    sy = py[edge][:, None, None] + s[None, :, None]
    cover[edge] = (sx * sx + sy * sy <= 1).to(dtype).mean((1, 2))
    return px, py, cover


def _grid_derivative(p: torch.Tensor, ok: torch.Tensor, dim: int):
    """Derivative per grid step of p (n, n, C) along ``dim`` (0: rows, 1: columns), central where both
    neighbours are ``ok``, one-sided where one is. Returns (derivative, defined mask)."""
    n = p.shape[dim]
    idx = torch.arange(n, device=p.device)
    nxt, prv = idx.clamp(max=n - 2) + 1, (idx - 1).clamp(min=0)
    p_n, p_p = p.index_select(dim, nxt), p.index_select(dim, prv)
    ok_n = ok.index_select(dim, nxt) & ok & (idx < n - 1).reshape((-1, 1) if dim == 0 else (1, -1))
    ok_p = ok.index_select(dim, prv) & ok & (idx > 0).reshape((-1, 1) if dim == 0 else (1, -1))
    d = torch.where((ok_n & ok_p)[..., None], 0.5 * (p_n - p_p),
                    torch.where(ok_n[..., None], p_n - p, torch.where(ok_p[..., None], p - p_p, 0.0)))
    return d, ok_n | ok_p


def _cell_area(p: torch.Tensor, ok: torch.Tensor):
    """Area (n, n) of each grid cell mapped to the points p (n, n, 3): |∂p/∂i × ∂p/∂j| (per unit cell)."""
    du, ok_u = _grid_derivative(p, ok, 1)
    dv, ok_v = _grid_derivative(p, ok, 0)
    return torch.linalg.vector_norm(torch.linalg.cross(du, dv, dim=-1), dim=-1), ok & ok_u & ok_v


def _check_sampling(opl, d, use, wl_mm: float, n: float, crop: float) -> None:
    """Warn when the pupil grid under-samples the wavefront: more than half a wave of ``opl`` (n, n) between
    neighbouring cells, or PSF replicas (period λ/(n·Δs), Δs the largest direction step between neighbouring
    rays ``d`` (n, n, 3)) closer than the crop width ``crop`` (mm)."""
    phase_step, dir_step = 0.0, 0.0
    along_x = ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))
    along_y = ((slice(1, None),), (slice(None, -1),))
    for a, b in (along_x, along_y):
        both = use[a] & use[b]
        if bool(both.any()):
            phase_step = max(phase_step, float((opl[a] - opl[b]).abs()[both].max()) / wl_mm)
            dir_step = max(dir_step, float(torch.linalg.vector_norm(d[a] - d[b], dim=-1)[both].max()))
    period = wl_mm / (n * dir_step) if dir_step > 0 else math.inf
    if phase_step > 0.5 or crop > period:
        warnings.warn(f"huygens_psf: the pupil grid under-samples the wavefront ({phase_step:.2f} waves between "
                      f"neighbouring rays; PSF replicas every {period * 1e3:.1f} µm for a {crop * 1e3:.1f} µm crop): "
                      "raise n_pupil", RuntimeWarning, stacklevel=3)


class _Sphere(NamedTuple):
    """The reference sphere: ``center`` (3,) mm, the chief ray's sensor intercept C; ``chief_dir`` (3,) the chief
    ray's direction cosines; ``radius`` R (mm); ``side`` ±1, the side of the sensor it lies on (the exit
    pupil's); ``opl_ref`` the chief ray's OPL (mm) at the sphere."""

    center: torch.Tensor
    chief_dir: torch.Tensor
    radius: float
    side: float
    opl_ref: float


def _reference_sphere(lens, field, wl: float, depth, z_s: float, n_img: float, sphere: str = "paraxial") -> _Sphere:
    """The reference sphere of ``field`` at ``wl`` µm: centred on the chief ray's intercept C with the sensor plane
    z_s (mm), through the point E where it crosses the paraxial exit-pupil plane (image index ``n_img``).
    A ValueError when the chief ray is vignetted or the exit pupil gives no sphere."""
    ch = lens.trace_to_image(chief_ray(lens, field, wl, depth=depth), z=z_s)
    if not bool(ch.valid.all()) and any(s.aperture is not None and s.aperture.obscuration is not None
                                        for s in lens.surfaces):
        ch = _chief_past_obscurations(lens, chief_ray(lens, field, wl, depth=depth), z_s, n_img)
    if not bool(ch.valid.all()):
        raise ValueError(f"the chief ray of field {field} is vignetted; no reference sphere")
    cen, d_ch, opl_ch = ch.o.reshape(3), ch.d.reshape(3), float(ch.opl.reshape(()))
    xp_z = float(paraxial.exit_pupil(lens, wl)[0])
    if not math.isfinite(xp_z) or xp_z == z_s:
        raise ValueError(f"the paraxial exit pupil (z = {xp_z}) gives no reference sphere")
    radius = abs((xp_z - z_s) / float(d_ch[2]))
    side = math.copysign(1.0, xp_z - z_s)  # the sphere lies on the exit-pupil side of the sensor
    if sphere == "rim":
        radius = _rim_radius(lens, field, wl, depth, cen, radius)
    elif sphere not in ("paraxial", "rim_images"):  # rim_images: the paraxial sphere inside, the rim images at the rim
        raise ValueError(f"sphere must be 'paraxial', 'rim' or 'rim_images', got {sphere!r}")
    return _Sphere(cen, d_ch, radius, side, opl_ch + n_img * side * radius)


def _rim_radius(lens, field, wl: float, depth, cen: torch.Tensor, fallback: float) -> float:
    """The reference sphere's radius (mm) that puts the stop's rim where it is sharp: the mean distance from the
    sphere's centre ``cen`` (3,) to the images of the stop's rim points
    (:func:`raywave.hybrid.coherent.stop_rim_images`: where the rays through each rim point from neighbouring sources
    cross; on axis they lie on one circle, which the sphere then contains exactly). ``fallback`` where they cannot be
    traced."""
    from raywave.hybrid.coherent.stop_edge import stop_rim_images

    rim = stop_rim_images(lens, field, wl, depth)
    if rim is None or rim.points is None:
        return fallback
    return float(torch.linalg.vector_norm(rim.points.detach() - cen, dim=-1).mean())


def _vignetting(lens, rec, valid: torch.Tensor) -> torch.Tensor:
    """Which traced rays (mask shaped like ``valid``) pass every aperture except the stop's clear edge (the
    pupil cells' coverage holds that one), ``rec`` the trace's record of surface points."""
    vig = torch.ones_like(valid)
    for i, s in enumerate(lens.surfaces):
        if s.aperture is not None and i != lens.stop_index:
            vig = vig & s.aperture.contains(rec.points[i + 1][0], rec.points[i + 1][1])
        elif s.aperture is not None and s.aperture.obscuration is not None:  # `cover` has the stop's clear edge
            vig = vig & ~s.aperture.obscuration.blocks(rec.points[i + 1][0], rec.points[i + 1][1])
    return vig


def _trace_pupil(lens, field, wl: float, depth, n_pupil: int, z_s: float, n_img: float):
    """Trace the pupil grid: every cell that touches the stop plus one ring for the finite differences.

    Returns (rays at the source, the traced rays on the sensor plane z_s mm, their vignetting mask, the stop
    coverage (n_pupil, n_pupil) of each cell, the (n_pupil, n_pupil) mask of the traced cells)."""
    px, py, cover = _stop_coverage(lens, n_pupil, torch.float64, lens.device)
    h = 2.0 / n_pupil
    traced = torch.hypot(px, py) <= 1 + 1.5 * math.sqrt(2) * h
    if float(cover.min()) == 1.0:
        traced = torch.ones_like(traced)
    rays = point_source_rays(lens, field, wl, pupil=(px[traced], py[traced]), aim="full", depth=depth)
    out, rec = lens.trace(rays, record=True, apertures=False)
    vig = _vignetting(lens, rec, out.valid)
    return rays, out.propagate_to_z(z_s, n_img), vig, cover, traced


#: ``quadrature="polar"``: the step (normalised stop coordinates) of the extra rays whose finite differences give
#: each node's Jacobians (central differences: error ~ step² relative)
POLAR_FD_STEP = 1e-4
#: ``quadrature="polar"``: the wavefront's largest change (waves, the crop's tilt at its edge included) between
#: neighbouring nodes above which a fixed ``n_pupil`` warns. Measured with the levels of ``n_pupil="auto"``: the
#: bundled asphere at 14° 1.53 (1.0e-3 from the next level), 1.09 (1.4e-9); at 7° / 17.5° 1.11 / 1.42 (6e-6 / 5e-6)
POLAR_WAVES_PER_NODE = 1.25
#: ``quadrature="polar"``: pupil nodes traced at once (each with its four neighbours for the Jacobians)
_POLAR_CHUNK = 1 << 16


def polar_nodes(n_pupil: int, square: bool = False, dtype=torch.float64, device=None):
    """The pupil nodes ``(px, py, w)`` (N,) of ``quadrature="polar"`` over the normalised stop, ``w`` the area
    weights (summing to π, the unit disc's area): ``n_pupil // 2`` Gauss–Legendre rings in ρ ∈ [0, 1] (weight ρ),
    each with the trapezoid rule in azimuth on ``max(8, ⌈π ρ n_pupil⌉)`` nodes (rounded up to a multiple of 4: the
    node density along a ring that of an ``n_pupil``² grid). Both rules converge faster than any power of the node
    count for a smooth integrand, and a circular stop's edge is exactly the outer ring's circle: the Huygens sum
    over a circular stop converges spectrally (the square grid's cells at the edge: as 1/n²). ``square``: a square
    stop, the tensor Gauss–Legendre rule over [-1, 1]² (weights summing to 4)."""
    x, w = np.polynomial.legendre.leggauss(max(2, n_pupil // (1 if square else 2)))
    if square:
        gx, gy = np.meshgrid(x, x)
        return (torch.as_tensor(gx.reshape(-1), dtype=dtype, device=device),
                torch.as_tensor(gy.reshape(-1), dtype=dtype, device=device),
                torch.as_tensor(np.outer(w, w).reshape(-1), dtype=dtype, device=device))
    rho, wr = 0.5 * (x + 1.0), 0.5 * w
    px, py, ww = [], [], []
    for i, (r, v) in enumerate(zip(rho, wr)):
        m = 4 * math.ceil(max(8, math.ceil(math.pi * r * n_pupil)) / 4)
        th = (np.arange(m) + 0.5 * (i % 2)) * (2 * math.pi / m)
        px.append(r * np.cos(th)), py.append(r * np.sin(th)), ww.append(np.full(m, v * r * 2 * math.pi / m))
    return tuple(torch.as_tensor(np.concatenate(a), dtype=dtype, device=device) for a in (px, py, ww))


def _polar_samples(lens, field, wl: float, depth, n_pupil: int, z_s: float, n_img: float, sph: _Sphere,
                   crop: float, check: bool = True):
    """The sphere samples of ``quadrature="polar"``: the nodes of :func:`polar_nodes`, each traced with four
    neighbours ±:data:`POLAR_FD_STEP` in px and py (apertures off) whose central differences give the Jacobians of
    the maps from the normalised stop to the entrance plane (power) and to the sphere (area). Returns, for the
    nodes that pass every aperture except the stop's clear edge (the nodes lie inside it), their sphere points
    ``q`` (N, 3) mm, OPL (N,) mm relative to the chief ray's, powers dP (N,), sphere areas dS (N,) mm² and ray
    directions (N, 3). ``check``: warn (RuntimeWarning) when the wavefront, plus the tilt that the crop's width
    ``crop`` mm adds at its edge, changes by more than :data:`POLAR_WAVES_PER_NODE` waves between neighbouring
    nodes."""
    dev = lens.device
    aperture = lens.surfaces[lens.stop_index].aperture
    px, py, w = polar_nodes(n_pupil, aperture is not None and aperture.shape == "square", device=dev)
    e = POLAR_FD_STEP
    ep_z = entrance_plane_z(lens)
    res = {k: [] for k in ("q", "opl", "dp", "ds", "d", "ok", "grad")}
    for c0 in range(0, px.numel(), _POLAR_CHUNK):
        x, y = px[c0:c0 + _POLAR_CHUNK], py[c0:c0 + _POLAR_CHUNK]
        m = x.numel()
        allx = torch.cat([x, x + e, x - e, x, x])
        ally = torch.cat([y, y, y, y + e, y - e])
        rays = point_source_rays(lens, field, wl, pupil=(allx, ally), aim="full", depth=depth)
        out, rec = lens.trace(rays, record=True, apertures=False)
        vig = _vignetting(lens, rec, out.valid).reshape(-1)[:m]
        out = out.propagate_to_z(z_s, n_img)
        q, opl, geom = _onto_sphere(out, sph, n_img)
        q, opl, geom = q.reshape(5, m, 3), opl.reshape(5, m), geom.reshape(5, m)
        ep = rays.o + rays.d * ((ep_z - rays.o[..., 2]) / rays.d[..., 2])[..., None]
        ep = ep.reshape(5, m, 3)[..., :2]
        dqx, dqy = (q[1] - q[2]) / (2 * e), (q[3] - q[4]) / (2 * e)
        dex, dey = (ep[1] - ep[2]) / (2 * e), (ep[3] - ep[4]) / (2 * e)
        js = torch.linalg.vector_norm(torch.linalg.cross(dqx, dqy, dim=-1), dim=-1)
        jep = (dex[:, 0] * dey[:, 1] - dex[:, 1] * dey[:, 0]).abs()
        wt = w[c0:c0 + _POLAR_CHUNK]
        res["q"].append(q[0]), res["opl"].append(opl[0])
        res["dp"].append(source_weight(lens, rays, depth).reshape(5, m)[0] * jep * wt), res["ds"].append(js * wt)
        res["d"].append(out.d.reshape(5, m, 3)[0]), res["ok"].append(vig & geom.all(0) & out.valid.reshape(5, m).all(0))
        d = out.d.reshape(5, m, 3)
        res["grad"].append(torch.hypot((opl[1] - opl[2]) / (2 * e), (opl[3] - opl[4]) / (2 * e))
                           + 0.5 * crop * n_img * torch.hypot(torch.linalg.vector_norm(d[1] - d[2], dim=-1),
                                                              torch.linalg.vector_norm(d[3] - d[4], dim=-1)) / (2 * e))
    q, opl, dp, ds, d, ok, grad = (torch.cat(res[k]) for k in ("q", "opl", "dp", "ds", "d", "ok", "grad"))
    ok = ok & torch.isfinite(dp) & torch.isfinite(ds) & (dp > 0) & torch.isfinite(grad)
    if not bool(ok.any()):
        raise ValueError(f"field {field} at {wl} µm: every ray is vignetted")
    waves = float(grad[ok].max()) * (math.pi / n_pupil) / (wl * 1e-3)  # per node spacing (GL rings: ≤ π/n_pupil)
    if check and waves > POLAR_WAVES_PER_NODE:
        warnings.warn(f"huygens_psf: the polar pupil nodes under-sample the wavefront and the crop's tilt "
                      f"({waves:.2f} waves between neighbouring nodes): raise n_pupil", RuntimeWarning, stacklevel=4)
    return q[ok], opl[ok], dp[ok], ds[ok], d[ok]


def _rim_surface(rim, sph: _Sphere):
    """``radius(px, py)``: the distance (mm) from the reference sphere's centre ``sph.center`` of the surface through
    the stop rim's images ``rim`` (:func:`raywave.hybrid.coherent.stop_rim_images`) at the stop's normalised
    coordinates (px, py): the rim images' distances ``rho(theta)`` at r = 1 (their trigonometric interpolation), the
    sphere's radius at the centre, each azimuthal harmonic m of ``rho − R`` weighted by ``r^|m|`` (the mean by r²): a
    polynomial in px, py, smooth everywhere (issue 47, h47/h47b)."""
    rho = torch.linalg.vector_norm(rim.points.detach() - sph.center, dim=-1)
    k = rho.numel()
    coef = torch.fft.rfft(rho) / k
    r0 = float(sph.radius)

    def radius(x, y):
        r, th = torch.sqrt(x * x + y * y), torch.atan2(y, x)
        out = r0 + (float(coef[0].real) - r0) * r * r
        for m in range(1, coef.shape[0]):
            w = 1.0 if (k % 2 == 0 and m == coef.shape[0] - 1) else 2.0
            out = out + w * (float(coef[m].real) * torch.cos(m * th) - float(coef[m].imag) * torch.sin(m * th)) * r**m
        return out
    return radius


def _rim_image_samples(lens, field, wl: float, depth, n_pupil: int, z_s: float, n_img: float, sph: _Sphere,
                       crop: float, check: bool = True):
    """:func:`_polar_samples` (the same returns) with the nodes on the surface of :func:`_rim_surface` instead of
    the sphere (``sphere="rim_images"``: each ray carried to its own radius about the sphere's centre, so that the
    stop's edge, the outer ring, sits at each rim point's own image, where the edge is sharp) and each node's area its
    ray tube's cross-section normal to the ray (``|(∂q/∂px × ∂q/∂py)·d|``; on the sphere the same to ~1e-7, the rays
    being nearly normal to it). No sampling warning (``crop``, ``check`` unused: the levels' agreement of
    ``n_pupil="auto"`` is the check). A ValueError where the rim images cannot be traced."""
    from raywave.hybrid.coherent import stop_rim_images  # (the package's name: a study may move the images)

    rim = stop_rim_images(lens, field, wl, depth)
    if rim is None:
        raise ValueError(f"field {field}: no stop-rim images (sphere='rim_images')")
    radius = _rim_surface(rim, sph)
    px, py, w = polar_nodes(n_pupil, False, device=lens.device)
    e, ep_z = POLAR_FD_STEP, entrance_plane_z(lens)
    res = {k: [] for k in ("q", "opl", "dp", "ds", "d", "ok")}
    for c0 in range(0, px.numel(), _POLAR_CHUNK):
        x, y = px[c0:c0 + _POLAR_CHUNK], py[c0:c0 + _POLAR_CHUNK]
        m = x.numel()
        allx, ally = torch.cat([x, x + e, x - e, x, x]), torch.cat([y, y, y, y + e, y - e])
        rays = point_source_rays(lens, field, wl, pupil=(allx, ally), aim="full", depth=depth)
        out, rec = lens.trace(rays, record=True, apertures=False)
        vig = _vignetting(lens, rec, out.valid).reshape(-1)[:m]
        out = out.propagate_to_z(z_s, n_img)
        rad = radius(allx, ally).reshape(out.o.shape[:-1])
        wv = out.o - sph.center
        b = (wv * out.d).sum(-1)
        disc = b * b - ((wv * wv).sum(-1) - rad * rad)
        t = -b + sph.side * torch.sqrt(disc.clamp_min(0))
        q = (out.o + t[..., None] * out.d).reshape(5, m, 3)
        opl = (out.opl + n_img * t - sph.opl_ref).reshape(5, m)
        ep = rays.o + rays.d * ((ep_z - rays.o[..., 2]) / rays.d[..., 2])[..., None]
        ep = ep.reshape(5, m, 3)[..., :2]
        dqx, dqy = (q[1] - q[2]) / (2 * e), (q[3] - q[4]) / (2 * e)
        dex, dey = (ep[1] - ep[2]) / (2 * e), (ep[3] - ep[4]) / (2 * e)
        d0 = out.d.reshape(5, m, 3)[0]
        d0 = d0 / torch.linalg.vector_norm(d0, dim=-1, keepdim=True)
        js = (torch.linalg.cross(dqx, dqy, dim=-1) * d0).sum(-1).abs()
        jep = (dex[:, 0] * dey[:, 1] - dex[:, 1] * dey[:, 0]).abs()
        wt = w[c0:c0 + _POLAR_CHUNK]
        res["q"].append(q[0]), res["opl"].append(opl[0]), res["d"].append(d0), res["ds"].append(js * wt)
        res["dp"].append(source_weight(lens, rays, depth).reshape(5, m)[0] * jep * wt)
        res["ok"].append(vig & (disc >= 0).reshape(5, m).all(0) & out.valid.reshape(5, m).all(0))
    q, opl, dp, ds, d, ok = (torch.cat(res[k]) for k in ("q", "opl", "dp", "ds", "d", "ok"))
    ok = ok & torch.isfinite(dp) & torch.isfinite(ds) & (dp > 0)
    if not bool(ok.any()):
        raise ValueError(f"field {field} at {wl} µm: every ray is vignetted")
    return q[ok], opl[ok], dp[ok], ds[ok], d[ok]


def _onto_sphere(out, sph: _Sphere, n_img: float):
    """Carry the rays ``out`` (on the sensor plane) straight to the reference sphere (forwards or backwards).
    Returns their points (…, 3) mm, OPL (…) mm relative to the chief ray's and the mask of those that meet it."""
    w = out.o - sph.center
    b = (w * out.d).sum(-1)
    disc = b * b - ((w * w).sum(-1) - sph.radius * sph.radius)
    t = -b + sph.side * torch.sqrt(disc.clamp_min(0))
    q = out.o + t[..., None] * out.d
    opl = out.opl + n_img * t - sph.opl_ref
    return q, opl, out.valid & (disc >= 0)


def _to_grid(v: torch.Tensor, traced: torch.Tensor, fill=0.0) -> torch.Tensor:
    """Per-ray values ``v`` (1, 1, N, …) of the traced cells back onto the pupil grid (n, n, …), ``fill``
    elsewhere (``traced``: the (n, n) mask of the N traced cells)."""
    g = torch.full(traced.shape + v.shape[3:], fill, dtype=v.dtype, device=traced.device)
    g[traced] = v.reshape((-1,) + v.shape[3:])
    return g


def _cell_powers(lens, rays, depth, q: torch.Tensor, geom: torch.Tensor, vig: torch.Tensor, cover: torch.Tensor,
                 traced: torch.Tensor):
    """Power dP (n, n) of each pupil cell (source weight × entrance-plane area × stop coverage, arbitrary units),
    its area dS (n, n) mm² on the sphere (× coverage) and the mask (n, n) of the cells that carry light.
    ``q``, ``geom``: the rays' sphere points and sphere mask (:func:`_onto_sphere`); ``vig``: their vignetting."""
    # Entrance-plane crossings (power per cell) and everything else back onto the (n, n) grid.
    ep = rays.o + rays.d * ((entrance_plane_z(lens) - rays.o[..., 2]) / rays.d[..., 2])[..., None]
    ep = torch.cat([ep[..., :2], torch.zeros_like(ep[..., :1])], -1)
    ok = _to_grid(geom, traced, False)
    ds, ok_s = _cell_area(_to_grid(q, traced), ok)
    da, ok_a = _cell_area(_to_grid(ep, traced), ok)
    # A partly covered cell keeps the irradiance of a full one on a fraction `cover` of its area.
    dp = _to_grid(source_weight(lens, rays, depth), traced) * da * cover
    ds = ds * cover
    use = ok_s & ok_a & _to_grid(vig, traced, False) & (cover > 0) & (dp > 0)
    return dp, ds, use


def _nodes_per_pixel(oversample: int | None, d: torch.Tensor | None, d_chief: torch.Tensor, n_img: float, wl: float,
                     pitch: float) -> int:
    """Samples per pixel and axis: ``oversample``, or (None) :func:`auto_oversample` from the NA of the ray
    directions ``d`` (N, 3) (needed only then) about the chief ray's ``d_chief`` (3,) (``wl`` µm, ``pitch`` mm).
    A ValueError below 1."""
    if oversample is None:
        na = n_img * float(torch.linalg.vector_norm(d[:, :2] - d_chief[:2], dim=-1).max())
        oversample = auto_oversample(na, wl, pitch)
    oversample = int(oversample)
    if oversample < 1:
        raise ValueError(f"oversample must be >= 1 (or None: automatic), got {oversample}")
    return oversample


def _sensor_power(q, opl, amp, sph: _Sphere, center, ks: int, pitch: float, nodes: int, gauss: bool, wl: float,
                  n_img: float, obliquity: bool) -> torch.Tensor:
    """Power (ks, ks) float64 of each sensor pixel (``pitch`` mm, pixel [ks//2, ks//2] centred at ``center``
    (x, y) mm): the Huygens sum of the sphere samples (``q`` (N, 3) mm relative to C, ``opl`` (N,) mm, ``amp``
    (N,) = sqrt(dP dS)) at ``nodes`` points per pixel and axis (Gauss–Legendre or midpoint), integrated."""
    dtype, device = torch.float64, amp.device
    cen = sph.center
    off, wq = _pixel_nodes(ks, pitch, nodes, gauss)
    off = torch.as_tensor(off, dtype=dtype, device=device)
    gy, gx = torch.meshgrid(off + (center[1] - float(cen[1])), off + (center[0] - float(cen[0])), indexing="ij")
    if obliquity:
        pxy = torch.stack([gx.reshape(-1), gy.reshape(-1)], -1)
        u = _huygens_sum(pxy, q, opl, amp, sph.radius, 2 * math.pi / (wl * 1e-3), n_img, obliquity)
    else:  # the sensor nodes form a tensor grid: the sum as matrix products (raywave.models.huygens_sum)
        u = huygens_sum_grid(gx[0], gy[:, 0], q, opl, amp, sph.radius, 2 * math.pi / (wl * 1e-3), n_img)
    u = u.reshape(-1) * (n_img / (wl * 1e-3))
    wq = wq.to(dtype=dtype, device=device)
    irr = u.abs().square().reshape(ks, nodes, ks, nodes)
    return (irr * wq[None, :, None, None] * wq[None, None, None, :]).sum((1, 3)) * pitch * pitch


def huygens_psf(lens, field=(0.0, 0.0), wavelength=None, ks: int = 64, pitch: float | None = None, center=None,
                n_pupil: int | str = 256, depth: float | None = None, sensor_z: float | None = None,
                oversample: int | None = None, obliquity: bool = False, tol: float = AUTO_TOL,
                max_n_pupil: int = AUTO_MAX_N, sphere: str = "paraxial", quadrature: str | None = None) -> HuygensPSF:
    """Huygens PSF of ``lens`` for one field point and wavelength (model in the module docstring).

    Args:
        field: (x, y) field point (degrees or mm, the lens's field type); ``wavelength``: µm (default primary).
        ks: crop size (pixels); ``pitch``: pixel size (mm, default the sensor's pixel pitch, else 1 µm).
        center: (x, y) mm of pixel [ks//2, ks//2] (default: the chief ray's sensor intercept).
        n_pupil: pupil grid cells per side over the stop diameter (the polar quadrature: nodes as dense), or
            ``"auto"``: chosen and refined until converged. With ``quadrature="polar"`` (the default for "auto"):
            the first level :data:`POLAR_FIRST` × :func:`auto_n_pupil`'s grid, then ×:data:`POLAR_RATIO` per level
            up to ``max_n_pupil`` until two levels differ by at most ``tol``; that change is ``error_estimate`` (an
            upper bound: the error falls faster than any power of n once the wavefront is resolved, and resolved
            levels agree to ~1e-10: the double Gauss at full field 384 vs 512 nodes 5.5e-11, where the grid needs
            ~1200 cells for 1e-3), and the finer level is returned. With ``quadrature="grid"``: :func:`auto_n_pupil`
            for the first grid, then ×1.5 per level, until the estimated error is at most ``tol``. The grid sum's
            error from the pupil
            sampling falls as 1/n² (measured on the bundled asphere on axis, ks 32 at 3 µm: 128 / 192 / 256 /
            384 cells are 1.43e-3 / 6.1e-4 / 3.0e-4 / 7.9e-5 from 512, i.e. ≈ 25/n²), so two levels n₀ < n₁ = 1.5 n₀ give the estimate
            ``|P₁ − P₀| / (1.5² − 1)`` of P₁'s error and the Richardson extrapolation ``(2.25 P₁ − P₀) / 1.25``
            (clamped at 0, renormalised), which is what is returned; ``error_estimate`` is the estimate for P₁
            (an upper bound for the extrapolation while the 1/n² law holds), ``levels`` every grid's change.
        depth: object distance (mm) overriding the lens's own; ``sensor_z``: sensor plane z (mm, default
            ``lens.image_z()``).
        oversample: None (default): Gauss–Legendre nodes per pixel and axis, as many as the PSF's bandwidth
            needs (:func:`auto_oversample`); an integer: that many midpoint-rule samples per pixel and axis.
        obliquity: apply the Fresnel–Kirchhoff factor (1 + cos χ)/2 (off by default: near the focus it
            changes the PSF by ~1e-7 in L1).
        sphere: where the reference sphere (centred on the chief ray's sensor intercept C) passes: "paraxial"
            (the default) through the chief ray's crossing with the paraxial exit-pupil plane; "rim" at the mean
            distance from C of the stop rim's images, where the GO field's edge is physically sharp (on axis they
            lie on one circle, which the sphere then holds exactly; the paraxial sphere misses it by the pupil's
            spherical aberration and its own sag: 52 µm on the bundled asphere, 0.35 mm on the f/3 double Gauss,
            1 mm on the F/1.3 asphere, where the Kirchhoff cut on it is not where the edge is sharp);
            "rim_images" (polar quadrature only): the sum over a surface through each rim point's own image (off
            axis the pupil's aberrations spread them along the rays: 129–154 mm from C on the double Gauss at full
            field, whose paraxial sphere has 121.8), blending into the paraxial sphere inside (:func:`_rim_surface`),
            so that the sharp cut sits where the stop's edge is imaged: the reference issue 47's slow test uses
            (2.2e-3 from the paraxial one on the double Gauss at full field, 5e-6 – 6e-4 elsewhere).
        quadrature: the pupil sum's nodes. "grid" (the default for an integer ``n_pupil``): the cells of a square
            grid, the stop's edge anti-aliased by each cell's coverage (error ∝ 1/n²). "polar" (the default for
            "auto"): :func:`polar_nodes`, Gauss–Legendre rings × the trapezoid rule in azimuth, the circular stop's
            edge exactly the outer ring, each node's Jacobians from four neighbouring rays (error falling faster
            than any power of n for a smooth wavefront: 1.6e-6 from the Debye focus at 64 nodes, where the grid is
            1.07e-3). A vignetting aperture other than the stop (a hard cut inside the pupil) takes that
            convergence back to the grid's.
    Returns: :class:`HuygensPSF` (float64 psf (ks, ks) summing to 1, centre, sensor z, energy fraction).
    """
    if quadrature is None:
        quadrature = "polar" if n_pupil == "auto" else "grid"
    if quadrature not in ("grid", "polar"):
        raise ValueError(f"quadrature must be 'grid' or 'polar', got {quadrature!r}")
    kw = dict(ks=ks, pitch=pitch, center=center, depth=depth, sensor_z=sensor_z, oversample=oversample,
              obliquity=obliquity, sphere=sphere, quadrature=quadrature)
    if isinstance(n_pupil, str):
        if n_pupil != "auto":
            raise ValueError(f"n_pupil must be an integer or 'auto', got {n_pupil!r}")
        return _huygens_auto(lens, field, wavelength, kw, float(tol), int(max_n_pupil))
    return _huygens_fixed(lens, field, wavelength, n_pupil=int(n_pupil), **kw)


def auto_n_pupil(lens, field, wavelength, ks: int, pitch: float | None = None, depth: float | None = None,
                 sensor_z: float | None = None, probe: int = 64, sphere: str = "paraxial") -> int:
    """The first pupil grid (cells per side) of ``huygens_psf(n_pupil="auto")`` for ``field`` at ``wavelength`` µm:
    the wavefront (its OPL on the reference sphere, traced on a ``probe``² grid) changes by at most
    :data:`AUTO_WAVES_PER_CELL` waves between neighbouring cells, the PSF's replicas lie at least 1.5 crop widths
    (``ks`` pixels of ``pitch`` mm) apart, and at least :data:`AUTO_MIN_N` cells; a multiple of 16."""
    dtype = torch.float64
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    pitch = float(pitch if pitch is not None else (lens.pixel_pitch or 1e-3))
    with torch.no_grad():
        z_s = float(lens.image_z() if sensor_z is None else sensor_z)
        n_img = float(lens.surfaces[-1].material.n(torch.tensor(wl, dtype=dtype, device="cpu")))
        sph = _reference_sphere(lens, field, wl, depth, z_s, n_img, sphere)
        rays, out, vig, cover, traced = _trace_pupil(lens, field, wl, depth, probe, z_s, n_img)
        q, opl, geom = _onto_sphere(out, sph, n_img)
        use = _to_grid(geom & vig, traced, False) & (cover > 0)
        opl_g, d_g = _to_grid(opl, traced), _to_grid(out.d, traced)
    waves, dstep = 0.0, 0.0
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None),), (slice(None, -1),))):
        both = use[a] & use[b]
        if bool(both.any()):
            waves = max(waves, float((opl_g[a] - opl_g[b]).abs()[both].max()) / (wl * 1e-3))
            dstep = max(dstep, float(torch.linalg.vector_norm(d_g[a] - d_g[b], dim=-1)[both].max()))
    n_wave = probe * waves / AUTO_WAVES_PER_CELL
    n_rep = probe * 1.5 * ks * pitch * n_img * dstep / (wl * 1e-3)  # replica period λ/(n Δs) ≥ 1.5 crops
    n = max(AUTO_MIN_N, n_wave, n_rep)
    return int(16 * math.ceil(n / 16))


def _huygens_auto(lens, field, wavelength, kw: dict, tol: float, max_n: int) -> HuygensPSF:
    """``huygens_psf(n_pupil="auto")``: levels n₀ (:func:`auto_n_pupil`), 1.5 n₀, … until the estimated error of the
    finest level is at most ``tol`` or the next level would exceed ``max_n``; the Richardson extrapolation of the
    last two (the 1/n² law)."""
    polar = kw["quadrature"] == "polar"
    if polar:
        kw = dict(kw, check=False)
    n = auto_n_pupil(lens, field, wavelength, kw["ks"], kw["pitch"], kw["depth"], kw["sensor_z"], sphere=kw["sphere"])
    n = min(int(16 * math.ceil(POLAR_FIRST * n / 16)) if polar else n, max_n)
    prev = _huygens_fixed(lens, field, wavelength, n_pupil=n, **kw)
    levels, est = [(n, None)], None
    while True:
        n_next = int(16 * math.ceil((POLAR_RATIO if polar else AUTO_RATIO) * n / 16))
        if n_next > max_n:
            break
        cur = _huygens_fixed(lens, field, wavelength, n_pupil=n_next, **kw)
        change = float((cur.psf - prev.psf).abs().sum())
        levels.append((n_next, change))
        if polar:  # spectral convergence: the change bounds the coarser level's error, far above the finer's
            est = change
            result = replace(cur, n_pupil=n_next, error_estimate=est)
        else:
            r2 = (n_next / n) ** 2
            est = change / (r2 - 1.0)
            ext = ((r2 * cur.psf - prev.psf) / (r2 - 1.0)).clamp_min(0.0)
            result = replace(cur, psf=ext / ext.sum(), n_pupil=n_next, error_estimate=est)
        prev, n = cur, n_next
        if est <= tol:
            break
    if est is None:  # a single level (max_n reached at once): no estimate
        result = replace(prev, n_pupil=n)
    if est is None or est > tol:
        warnings.warn(f"huygens_psf: the pupil sampling did not converge to {tol:g} within {max_n} cells "
                      f"(levels {levels}); the reference is uncertain by about "
                      f"{'?' if est is None else format(est, '.2g')} rel L1", RuntimeWarning, stacklevel=3)
    return replace(result, levels=tuple(levels))


def _huygens_fixed(lens, field=(0.0, 0.0), wavelength=None, ks: int = 64, pitch: float | None = None, center=None,
                   n_pupil: int = 256, depth: float | None = None, sensor_z: float | None = None,
                   oversample: int | None = None, obliquity: bool = False, sphere: str = "paraxial",
                   quadrature: str = "grid", check: bool = True) -> HuygensPSF:
    """:func:`huygens_psf` on a fixed pupil sampling of ``n_pupil`` (arguments as there; ``check``: the polar
    nodes' sampling warning, off within ``n_pupil="auto"``, whose levels' agreement is the check)."""
    dtype = torch.float64
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    if pitch is None:
        pitch = lens.pixel_pitch or 1e-3
    with torch.no_grad():
        z_s = float(lens.image_z() if sensor_z is None else sensor_z)
        n_img = float(lens.surfaces[-1].material.n(torch.tensor(wl, dtype=dtype, device="cpu")))
        sph = _reference_sphere(lens, field, wl, depth, z_s, n_img, sphere)
        if sphere == "rim_images" and quadrature != "polar":
            raise ValueError("sphere='rim_images' needs quadrature='polar' (or n_pupil='auto')")
        if quadrature == "polar":
            samples = _rim_image_samples if sphere == "rim_images" else _polar_samples
            q, opl, dp, ds, d_all = samples(lens, field, wl, depth, n_pupil, z_s, n_img, sph, ks * pitch, check)
            amp = torch.sqrt(dp * ds)
            q = q - sph.center
            dz = d_all[:, 2]
            ds_use = ds
        elif quadrature == "grid":
            rays, out, vig, cover, traced = _trace_pupil(lens, field, wl, depth, n_pupil, z_s, n_img)
            q, opl, geom = _onto_sphere(out, sph, n_img)
            dp, ds, use = _cell_powers(lens, rays, depth, q, geom, vig, cover, traced)
            amp = torch.sqrt(dp * ds)[use]
            if amp.numel() == 0:
                raise ValueError(f"field {field} at {wl} µm: every ray is vignetted")
            _check_sampling(_to_grid(opl, traced), _to_grid(out.d, traced), use, wl * 1e-3, n_img, ks * pitch)
            q, opl = (_to_grid(q, traced) - sph.center)[use], _to_grid(opl, traced)[use]
            dz = _to_grid(out.d[..., 2], traced)[use]
            d_all, ds_use = _to_grid(out.d, traced)[use], ds[use]
        else:
            raise ValueError(f"quadrature must be 'grid' or 'polar', got {quadrature!r}")
        # Sensor samples relative to C (the sensor plane contains C, so their z offset is 0).
        cen = sph.center
        if center is None:
            center = (float(cen[0]), float(cen[1]))
        nodes = _nodes_per_pixel(oversample, d_all, sph.chief_dir, n_img, wl, pitch)
        power = _sensor_power(q, opl, amp, sph, center, ks, pitch, nodes, oversample is None, wl, n_img, obliquity)
        total = float(power.sum())
        plane_total = float((amp.square() / ds_use / dz.abs()).sum())  # Σ dP / cos γ
    return HuygensPSF(power / total, (float(center[0]), float(center[1])), z_s, float(pitch), total / plane_total,
                      tuple(float(v) for v in cen), sph.radius, int(amp.numel()), int(n_pupil))


def _huygens_sum(p: torch.Tensor, q: torch.Tensor, opl: torch.Tensor, amp: torch.Tensor, radius: float,
                 k0: float, n: float, obliquity: bool) -> torch.Tensor:
    """Σ_j amp_j K_j exp(i k0 (opl_j + n (r − R))) / r for sensor points p (M, 2) (relative to the sphere
    centre, z offset 0) and sphere points q (N, 3) (relative to the centre), r = |p − q|. Returns (M,)
    complex128. ``num`` = r² − R² = |p|² − 2 p·q + (|q|² − R²) comes from one matmul of augmented vectors
    and r − R = num / (r + R), so the phase keeps full float64 precision."""
    qq = (q * q).sum(-1)
    qa = torch.cat([-2 * q[:, :2], torch.ones_like(qq)[:, None], (qq - radius * radius)[:, None]], -1)
    pp = (p * p).sum(-1, keepdim=True)
    pa = torch.cat([p, pp, torch.ones_like(pp)], -1)
    ko, c = k0 * opl, k0 * n
    out = torch.empty(p.shape[0], dtype=torch.complex128, device=p.device)
    step = max(1, _BLOCK // q.shape[0])
    for i in range(0, p.shape[0], step):
        num = pa[i:i + step] @ qa.T
        r = torch.sqrt(num + radius * radius)
        phase = torch.addcdiv(ko, num, r + radius, value=c)
        w = amp / r
        if obliquity:  # cos χ = (q − p)·q / (r R) = (|q|² + R² − |p|² + num) / (2 r R)
            w = w * (0.5 + (num - pp[i:i + step] + (qq + radius * radius)) / (4 * radius * r))
        out[i:i + step] = torch.complex(torch.einsum("ij,ij->i", w, torch.cos(phase)),
                                        torch.einsum("ij,ij->i", w, phase.sin_()))
    return out


class ExitPupilModel(PSFModel):
    """Chen et al. (2021)'s exit-pupil diffraction model behind the common comparison interface
    (:mod:`raywave.models.interface`): :func:`huygens_psf` for every field point and wavelength, on the hybrid
    lens's sensor plane and pixel pitch, crop centred on the chief ray (the engine's convention).

    It traces to the exit pupil's reference sphere and cannot carry a DOE (the DOE changes the light path
    after its plane): a DOE whose phase is not zero everywhere is an error. The DOE's aperture is ignored
    (a clear aperture: the model only diffracts at the lens's stop and apertures), so give the hybrid lens a
    DOE large enough for the beam: a DOE that clips it is warned about (RuntimeWarning).

    Args: ``hybrid`` (:class:`~raywave.hybrid.HybridLens`), ``n_pupil`` (pupil grid cells per side, or "auto", the
    default: refined until the estimated error is at most ``tol``, see :func:`huygens_psf`; the result's
    ``info["n_pupil"]`` and ``info["error_estimate"]`` (F, W) say what each PSF used and how far it may be off),
    ``sphere`` (the reference sphere: "paraxial" or "rim", see :func:`huygens_psf`),
    ``oversample`` (None, default: Gauss–Legendre nodes per pixel chosen from the PSF's bandwidth, see
    :func:`auto_oversample`; an integer q ≥ 2: point samples at pitch/q integrated through their cubic
    interpolant, the former method, which needs pitch/q well below λ/(2·NA): F/4 at 3 µm pixels, q = 3 is
    0.015 from the Debye focus in L1, q = 6 2.0e-3, the default 6.7e-4).
    """

    name = "exit_pupil"

    def __init__(self, hybrid, n_pupil: int | str = "auto", oversample: int | None = None, tol: float = AUTO_TOL,
                 sphere: str = "paraxial"):
        super().__init__(hybrid)
        for name, v, low in (("n_pupil", n_pupil, 8), ("oversample", oversample, 2)):
            if (v is None and name == "oversample") or (v == "auto" and name == "n_pupil"):
                continue
            if isinstance(v, (bool, str)) or int(v) != v or int(v) < low:
                alt = " or None" if name == "oversample" else " or 'auto'"
                raise ValueError(f"{name} must be an integer >= {low}{alt}, got {v!r}")
        if not tol > 0:
            raise ValueError(f"tol must be > 0, got {tol!r}")
        self.n_pupil = n_pupil if n_pupil == "auto" else int(n_pupil)
        self.oversample = None if oversample is None else int(oversample)
        self.tol = float(tol)
        if sphere not in ("paraxial", "rim"):
            raise ValueError(f"sphere must be 'paraxial' or 'rim', got {sphere!r}")
        self.sphere = sphere

    def _check_blank(self, wavelengths) -> None:
        from raywave.doe import BlankDOE

        doe = self.hybrid.doe
        if type(doe) is BlankDOE and doe.quant_levels is None:
            return  # zero phase by construction (its full grid need not be allocated: a default DOE can be large)
        with torch.no_grad():
            for wl in wavelengths:
                ph = doe.phase_pixels(wl, slice(None), slice(None))
                if bool((ph != 0).any()):
                    iy, ix = (int(v) for v in torch.nonzero(ph != 0)[0])
                    raise ValueError(
                        f"the exit-pupil model (Chen et al. 2021) cannot simulate a DOE: this DOE's phase is not zero "
                        f"(e.g. {float(ph[iy, ix]):.4g} rad at pixel [{iy}, {ix}] at {wl:g} µm). It traces to the "
                        "exit pupil, which a DOE's phase modulation makes meaningless; use a blank DOE (clear "
                        "aperture) or the ray-wave model")

    def _check_clear(self, fields, wavelengths, depth) -> None:
        from raywave.lens.analysis import beam_half_extent

        hl = self.hybrid
        ext = beam_half_extent(hl.lens, hl.doe_z(), fields, wavelengths, depth)
        if ext is None:
            return
        w, h = hl.doe.size
        if hl.doe.aperture == "circle":
            clipped = math.hypot(*ext) > 0.5 * min(w, h)
        else:
            clipped = ext[0] > 0.5 * w or ext[1] > 0.5 * h
        if clipped:
            warnings.warn(f"exit-pupil model: the beam reaches |x|, |y| = {ext[0]:.4g}, {ext[1]:.4g} mm on the DOE "
                          "plane, "
                          f"beyond the {w:.4g}×{h:.4g} mm DOE ({hl.doe.aperture}) that the ray-wave model clips it "
                          "with; this model ignores the DOE aperture, so the two differ", RuntimeWarning, stacklevel=3)

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None):
        """PSFs ``(F, W, ks, ks)`` as :class:`raywave.models.interface.ModelPSFResult`."""
        from raywave.lens.sources import _as_fields

        ks = self._check_ks(ks)
        hl = self.hybrid
        wls = hl.wavelength_list(wavelengths)
        self._check_blank(wls)
        f = _as_fields(fields, torch.float64, hl.lens.device)
        self._check_clear(f, wls, depth)
        psfs, centers, outs, nr, nps, ests = [], [], [], [], [], []
        for i in range(f.shape[0]):
            pr, cr, orow, rr, npr, er = [], [], [], [], [], []
            for wl in wls:
                h, inside = self._one(tuple(float(v) for v in f[i]), wl, ks, depth)
                pr.append(h.psf), cr.append(torch.tensor(h.center, dtype=torch.float64, device=h.psf.device))
                orow.append(torch.tensor(1.0 - inside, dtype=torch.float64, device=h.psf.device))
                rr.append(h.n_rays), npr.append(h.n_pupil)
                er.append(math.nan if h.error_estimate is None else h.error_estimate)
            psfs.append(torch.stack(pr)), centers.append(torch.stack(cr)), outs.append(torch.stack(orow))
            nr.append(rr), nps.append(npr), ests.append(er)
        info = {"n_pupil": torch.tensor(nps, device="cpu"),
                "error_estimate": torch.tensor(ests, dtype=torch.float64, device="cpu")}
        return ModelPSFResult(torch.stack(psfs), torch.stack(centers), torch.stack(outs), hl.sensor_pitch,
                              torch.tensor(nr, device="cpu"), model=self.name, info=info)

    def _one(self, field, wl: float, ks: int, depth):
        """One PSF: ``(HuygensPSF, energy fraction in the crop)``. ``oversample`` None: :func:`huygens_psf`'s
        Gauss–Legendre pixel integration. Otherwise the Huygens irradiance at ``oversample`` point samples per pixel
        and axis (plus a margin), integrated over the sensor pixels through its cubic interpolant (exact for
        quadratics: with 3 samples per 1 µm pixel at F/4 it is 1e-3 from the Debye focus in L1, where the midpoint
        rule leaves 9e-3)."""
        from raywave.wave.propagation import pixel_integrate

        hl, q, p = self.hybrid, self.oversample, self.hybrid.sensor_pitch
        if q is None:  # Gauss–Legendre pixel integration (auto_oversample)
            h = huygens_psf(hl.lens, field, wl, ks=ks, pitch=p, n_pupil=self.n_pupil, depth=depth,
                            sensor_z=hl.sensor_z(), tol=self.tol, sphere=self.sphere)
            return h, h.energy_fraction
        nf = ks * q + 5
        h = huygens_psf(hl.lens, field, wl, ks=nf, pitch=p / q, n_pupil=self.n_pupil, depth=depth,
                        sensor_z=hl.sensor_z(), oversample=1, tol=self.tol, sphere=self.sphere)
        cx, cy = h.center
        irr = h.psf * (h.energy_fraction / (p / q) ** 2)
        psf = pixel_integrate(irr, p / q, p, (cx - (nf // 2) * p / q, cy - (nf // 2) * p / q),
                              (cx - (ks // 2) * p, cy - (ks // 2) * p), (ks, ks), kernel="cubic").clamp_min(0.0)
        inside = float(psf.sum())
        return replace(h, psf=psf / inside), inside
