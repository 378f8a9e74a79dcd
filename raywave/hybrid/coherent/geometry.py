"""Geometry shared by the field constructions: chief rays, beam footprints on the DOE plane, DOE clipping,
the simulation grid and its windows."""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens.analysis import fold_fraction, pupil_grid
from raywave.lens.sources import (VignettingWarning, chief_pupil, entrance_plane_z, point_source_rays,
                                  source_weight)
from raywave.rays.pupil import RIM_INSET  # the footprint's rim a hair inside the stop: the engine's one rim rule
from raywave.utils.errors import check_allocation
from raywave.wave.grid import Grid
from raywave.wave.propagation.transfer import WindowSource, window_fft_shape
from raywave.hybrid.coherent.record import DOEField, FieldInfo, SamplingWarning
from raywave.hybrid.coherent.vignetting import NEAR_ZONES, aperture_zones, rim_clearance, vignetting_edges


def _medium_index(lens, wavelength) -> float:
    """The image medium's refractive index (host float) at ``wavelength`` µm (a number, or a one-element float64
    tensor on the lens's device: no tensor made for it)."""
    wl = wavelength if isinstance(wavelength, torch.Tensor) else torch.tensor(wavelength, dtype=torch.float64,
                                                                              device=lens.device)
    return float(lens.surfaces[-1].material.n(wl))


def _check_beyond_last_surface(out, z_doe: float) -> None:
    z = out.o[..., 2].detach()
    z = z[out.valid] if bool(out.valid.any()) else z.new_zeros(1) - math.inf
    if z.numel() and float(z.max()) > z_doe + 1e-12:
        raise ValueError(f"the DOE plane (z = {z_doe:.6g} mm) cuts the last lens surface: a ray leaves it at "
                         f"z = {float(z.max()):.6g} mm; move the DOE further from the lens")


def chief_rays(lens, fields, wavelengths, depth, z_doe: float, z_sensor: float):
    """Chief rays (aimed at the stop centre, through the refractive lens only) at the DOE and the sensor.

    Returns ``(at_doe, at_sensor, uv)``: bundles of shape (F, W) and the chief rays' entrance-plane points
    (F, W, 2) mm (detached)."""
    cr = point_source_rays(lens, fields, wavelengths, pupil=chief_pupil(lens), aim="full", depth=depth)
    o, d = cr.o[:, :, 0].detach(), cr.d[:, :, 0].detach()
    uv = o[..., :2] + d[..., :2] * ((entrance_plane_z(lens) - o[..., 2:]) / d[..., 2:])
    out = lens.trace(cr, apertures=False)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at_doe = out.propagate_to_z(z_doe, n)
    at_sensor = out.propagate_to_z(z_sensor, n)
    return at_doe[:, :, 0], at_sensor[:, :, 0], uv


def _footprint(lens, field, wavelength, depth, z_doe: float, n_grid: int = 15, n_rim: int = 72, virtual: bool = False):
    """Lit bounding box ``(xmin, xmax, ymin, ymax)`` on the DOE plane (None if every ray is vignetted) of one
    field (2,) at one wavelength (1,) µm (:func:`footprints` of a 1×1 batch).

    ``virtual``: the plane may lie inside the lens (a virtual plane reached by extending the rays that leave
    the last surface backwards along straight lines, e.g. the exit pupil)."""
    return footprints(lens, torch.as_tensor(field).reshape(1, 2), wavelength, depth, z_doe, n_grid, n_rim,
                      virtual)[0][0]




def footprints(lens, fields, wavelengths, depth, z_doe: float, n_grid: int = 15, n_rim: int = 72,
               virtual: bool = False) -> list:
    """Lit bounding boxes ``(xmin, xmax, ymin, ymax)`` (mm) on the plane ``z_doe`` of fields (F, 2) at wavelengths
    (W,) µm, a nested list ``[F][W]`` (None where every ray is vignetted), from one trace of all F×W beams (~250
    rays each: the rim of the pupil and a grid inside, every ray aimed at its stop point). See :func:`_footprint`."""
    px, py = _footprint_pupil(n_grid, n_rim, lens.device)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # the caller reports vignetting once
        rays = point_source_rays(lens, fields, wavelengths, pupil=(px, py), aim="full", depth=depth)
        out = lens.trace(rays)
        return _boxes(lens, out, z_doe, virtual)


def _footprint_pupil(n_grid: int, n_rim: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The normalised stop points ``(px, py)`` of :func:`footprints`' rays: ``n_rim`` on the rim, a hair inside it,
    and the ``n_grid``² grid's points inside the circle."""
    t = torch.linspace(0, 2 * math.pi, n_rim + 1, dtype=torch.float64, device=device)[:-1]
    g = torch.linspace(-1, 1, n_grid, dtype=torch.float64, device=device)
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    inside = gx**2 + gy**2 <= 1
    # the rim a hair inside the stop's edge: a ray aimed exactly at it passes or is stopped by the rounding of its
    # aim (a mirror-image source could lose a rim ray its twin keeps, and its footprint, node spacing and field
    # would differ by the construction's sampling: ~1e-7 of the PSF)
    return torch.cat([torch.cos(t), gx[inside]]) * RIM_INSET, torch.cat([torch.sin(t), gy[inside]]) * RIM_INSET


def _boxes(lens, out, z_doe: float, virtual: bool) -> list:
    """:func:`footprints`' nested list ``[F][W]`` of lit boxes from the traced rays ``out`` (F, W, N) (after the last
    surface, apertures applied; no autograd)."""
    if not virtual:
        _check_beyond_last_surface(out, z_doe)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, n)
    valid, x, y = at.valid, at.o[..., 0], at.o[..., 1]
    inf = torch.full_like(x, math.inf)
    box = torch.stack([torch.where(valid, x, inf).amin(-1), torch.where(valid, x, -inf).amax(-1),
                       torch.where(valid, y, inf).amin(-1), torch.where(valid, y, -inf).amax(-1)], -1).cpu()
    box, lit = box.tolist(), valid.any(-1).cpu().tolist()  # host values: no read per element
    return [[tuple(b) if on else None for b, on in zip(box_row, lit_row)] for box_row, lit_row in zip(box, lit)]


#: :func:`footprints_and_clippings`' rim ring (rays) and stop grid (cells a side)
_RIM_RAYS, _STOP_GRID = 72, 48


def footprints_and_clippings(lens, doe, fields, wavelengths, depth, z_doe: float, folds: bool = False,
                             chief: tuple | None = None, vignetting: bool = False) -> tuple:
    """``(footprints(...), doe_clippings(..., folds=folds))`` of the same F×W beams (default samplings) from one
    aimed trace of both ray sets (issue 43: one aiming, one paraxial set-up and one trace for the call instead of
    two); ``chief``: these sources' :func:`~raywave.lens.sources.chief_aim` when the caller shares it.

    ``vignetting``: also ``{(f, w): VignettingEdge}`` (a third item) of the sources whose stop grid or rim ring loses
    rays before the DOE plane to a surface other than the stop, or whose rim passes within
    :data:`~raywave.hybrid.coherent.vignetting.NEAR_ZONES` Fresnel zones of such a surface's aperture
    (:func:`~raywave.hybrid.coherent.vignetting.vignetting_edges`): which of them do is read with the clipping (no host
    read of its own; the rim's clearance from one recorded trace of the rim ring, only on a lens with apertures besides
    the stop); only those are traced again."""
    fx, fy = _footprint_pupil(15, _RIM_RAYS, lens.device)
    cx, cy, index = pupil_grid(_STOP_GRID, lens.device)
    k = fx.numel()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # the caller reports vignetting once
        rays = point_source_rays(lens, fields, wavelengths, pupil=(torch.cat([fx, cx]), torch.cat([fy, cy])),
                                 aim="full", depth=depth, chief=chief)
        out = lens.trace(rays)
        boxes = _boxes(lens, out[..., :k], z_doe, False)
        extra = zones = None
        if vignetting:  # any rim-ring or stop-grid ray lost before the DOE plane, and (where the lens has apertures
            # besides the stop) the rim's clearance inside them: read with the clipping
            v = out.valid
            extra = ((~v[..., :_RIM_RAYS]).any(-1) | (~v[..., k:]).any(-1)).to(torch.float64)[None]
            zones = aperture_zones(lens, wavelengths)
            if zones is not None:
                clear, surf = rim_clearance(lens, rays[..., :_RIM_RAYS], zones)
                extra = torch.cat([extra, clear[None], surf.to(torch.float64)[None]])
        clips = _clippings(lens, doe, rays[..., k:], out[..., k:], z_doe, (index, _STOP_GRID) if folds else None,
                           depth, extra)
    if not vignetting:
        return boxes, clips
    clips, extra = clips
    near = {}
    if zones is not None:
        near = {(i, j): (extra[1][i][j], int(extra[2][i][j])) for i in range(len(extra[0]))
                for j in range(len(extra[0][i]))}
    suspect = [(i, j) for i, row in enumerate(extra[0]) for j, on in enumerate(row)
               if on or near.get((i, j), (math.inf,))[0] < NEAR_ZONES]
    keep = torch.cat([torch.arange(_RIM_RAYS, device=lens.device), torch.arange(k, k + cx.numel(), device=lens.device)])
    return boxes, clips, vignetting_edges(lens, rays[..., keep] if suspect else rays, suspect, (index, _STOP_GRID),
                                          _RIM_RAYS, near)


def inside_doe(doe, xy: torch.Tensor) -> torch.Tensor:
    """Whether points ``xy`` (..., 2) mm on the DOE plane fall inside the DOE aperture (square grid or the
    inscribed circle), bool (...)."""
    w, h = doe.size
    if doe.aperture == "circle":
        return xy[..., 0] ** 2 + xy[..., 1] ** 2 <= (0.5 * min(w, h)) ** 2
    return (xy[..., 0].abs() <= 0.5 * w) & (xy[..., 1].abs() <= 0.5 * h)


def doe_clipping(lens, doe, field, wavelength, depth, z_doe: float, n_grid: int = 48) -> tuple[float, float]:
    """Fraction of the beam's power blocked by the DOE aperture, and the beam's half extent on the DOE plane.

    Rays on a regular ``n_grid``² grid over the stop (every ray aimed at its stop point, so each carries
    about the same power) are traced through the lens with its apertures (vignetted rays leave the beam
    before the DOE) to the plane ``z_doe``; each ray is weighted by :func:`source_weight`. Returns
    ``(blocked, half)``: the blocked power fraction (0..1) of the rays that leave the lens, and the largest
    |x| or |y| (mm) of their landing points (the half side of a centred square DOE that holds them all);
    ``(0, 0)`` if every ray is vignetted. Cheap (one batched trace of ~0.8·n_grid² rays); a diagnostic,
    not differentiable.

    Args: field (2,) in the lens's field type, wavelength (1,) µm tensor, depth (mm or None). Many fields and
    wavelengths at once: :func:`doe_clippings`."""
    return doe_clippings(lens, doe, torch.as_tensor(field).reshape(1, 2), wavelength, depth, z_doe, n_grid)[0][0]


def doe_clippings(lens, doe, fields, wavelengths, depth, z_doe: float, n_grid: int = 48, folds: bool = False) -> list:
    """:func:`doe_clipping` of fields (F, 2) at wavelengths (W,) µm from one trace of all F×W beams: a nested list
    ``[F][W]`` of ``(blocked, half)``, with ``folds`` ``(blocked, half, folded)``: ``folded`` the fraction of the
    stop grid's cells whose rays have crossed before the DOE plane (:func:`raywave.lens.analysis.fold_fraction`; 0:
    none, the ray map is one to one). (The rays' aiming iterates over the whole batch, so the values can differ
    from single calls' in the last digits of the aim: ~1e-12 mm on the stop.)"""
    px, py, index = pupil_grid(n_grid, lens.device)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # the caller reports vignetting once
        rays = point_source_rays(lens, fields, wavelengths, pupil=(px, py), aim="full", depth=depth)
        out = lens.trace(rays)
        return _clippings(lens, doe, rays, out, z_doe, (index, n_grid) if folds else None, depth)


def _clippings(lens, doe, rays, out, z_doe: float, folds, depth, extra: torch.Tensor | None = None):
    """:func:`doe_clippings`' nested list from the aimed rays ``rays`` (F, W, N) of the :func:`pupil_grid` and
    their trace ``out`` (apertures applied; no autograd); ``folds``: ``(index, n_grid)`` of that grid, or None;
    ``depth`` the object distance (:func:`source_weight`). ``extra``: a (K, F, W) tensor read with the blocked
    fractions (no host read of its own), returned as ``(list, extra as K nested lists [F][W])``."""
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, n)
    v = at.valid
    xy = at.o[..., :2]
    w = torch.where(v, source_weight(lens, rays, depth).expand_as(v), torch.zeros((), dtype=xy.dtype,
                                                                                  device=xy.device))
    blocked = (w * ~inside_doe(doe, xy)).sum(-1) / w.sum(-1).clamp_min(1e-300)
    half = torch.where(v[..., None], xy.abs(), torch.zeros((), dtype=xy.dtype, device=xy.device)).amax((-1, -2))
    lit = v.any(-1)
    folded = fold_fraction(xy, v, folds[0], folds[1]).cpu().tolist() if folds is not None else None
    if extra is not None:  # read with the blocked fractions
        blocked, *extra = torch.cat([blocked[None], extra.to(blocked.dtype)]).cpu().tolist()
    else:
        blocked = blocked.cpu().tolist()
    half, lit = half.cpu().tolist(), lit.cpu().tolist()  # host values
    result = []
    for i in range(v.shape[0]):
        row = []
        for j in range(v.shape[1]):
            entry = (blocked[i][j], half[i][j]) if lit[i][j] else (0.0, 0.0)
            row.append(entry if folded is None else entry + (folded[i][j],))
        result.append(row)
    return result if extra is None else (result, extra)


def _sim_grid(doe, oversample: int):
    p = doe.pitch / oversample
    x0, y0 = doe.sim_origin(oversample)
    sy, sx = doe.sim_shape(oversample)
    return p, x0, y0, sy, sx


def _warn_nyquist(slope_ratio: torch.Tensor, lit: torch.Tensor, xy: torch.Tensor, field, wavelength, pitch) -> None:
    """Warn when the envelope's local phase slope exceeds Nyquist on lit samples."""
    if slope_ratio.numel() == 0:
        return
    r = torch.where(lit, slope_ratio.detach(), torch.zeros_like(slope_ratio))
    at = torch.argmax(r)
    any_lit, worst, ratio = torch.stack([lit.any().to(r.dtype), at.to(r.dtype), r.reshape(-1)[at]]).tolist()
    if not any_lit:  # (one host read for the three)
        return
    worst = int(worst)
    if ratio > 1.0:
        x, y = (float(v) for v in xy.reshape(-1, 2)[worst])
        _nyquist_warning(ratio, (x, y), field, wavelength, pitch, stacklevel=5)


def _nyquist_warning(ratio: float, at: tuple, field, wavelength: float, pitch: float, stacklevel: int) -> None:
    """The :class:`SamplingWarning` of :func:`_warn_nyquist`: the phase slope ``ratio`` × Nyquist at the point ``at``
    = (x, y) mm of the DOE plane (host floats), for ``field`` at ``wavelength`` µm, simulation pitch ``pitch`` mm."""
    x, y = at
    warnings.warn(
        f"DOE grid too coarse for field {list(map(float, field))} at {wavelength:g} µm: the wavefront's phase "
        f"slope reaches {ratio:.2f}× the Nyquist limit of the {pitch * 1e3:g} µm simulation pitch at "
        f"(x, y) = ({x:.4g}, {y:.4g}) mm on the DOE plane; the field aliases. Use a finer DOE pitch or "
        f"oversample ≥ {math.ceil(ratio * 1.05)}.", SamplingWarning, stacklevel=stacklevel)


#: peak bytes per simulation sample of a DOE-plane field window, by ``(step, graph)``: ``step`` "fresnel" (the field
#: built on its plane with the stop's knife edge, the Fresnel edge step, and the PSF's propagation to the sensor),
#: "cut" (the same with the edges cut sharply: the DOE-plane edge, a blank DOE's cut edge; the faithful splat, not
#: measured, is held to it too), "asm" (the exact construction: built on a plane near the exit pupil and carried to
#: the DOE plane by the windowed angular spectrum; per sample of the larger of its two windows) or "fallback" (the
#: caustic fallback: the Fresnel step on an earlier plane, carried to the DOE plane near the focus; per sample of the
#: earlier plane's window; since h47m the carry itself is estimated by :data:`CARRY_BYTES` from its FFT grid, and
#: "fallback" counts only the Fourier upsampling of a coarsened carry, per sample of the DOE-plane window, not
#: measured); ``graph``: whether autograd keeps the construction's graph (gradients enabled). Measured
#: (benchmarks/window_memory.py, the Zeiss Pro-Tessar on axis, DOE pitches 9.6 – 2.8 µm, 1.2·10⁶ – 2.8·10⁷ samples,
#: and 1.2 µm, 1.1 – 1.3·10⁸ samples, without a graph; benchmarks/results/window_memory_2026-12-01_xxv_h47a.json):
#: 1.28 – 1.44× the least-squares slope of the peak resident memory against the samples, at least 1.14× its steepest
#: rise between neighbouring sizes from 4·10⁶ samples on (compiled and eager kernels) and above the whole extra peak
#: per sample of the largest window (the Fresnel step without a graph: 74 B against a slope of 51.9 B, a rise of up
#: to 65.2 B and 53.7 B a sample on 1.25·10⁸ samples)
#: ``("fresnel", True)`` 175 since 2026-12-01 (h47c; was 160): with the short-reach ripple band (4 zones on axis) the
#: bundled asphere's 5.41·10⁶-sample window with a graph peaked at 1.046 GB, above 160 B a sample + the tests' fixed
#: 128 MiB (1.000 GB): the peak's parts that follow the band shrink less than the window
WINDOW_BYTES = {("fresnel", False): 74, ("fresnel", True): 175, ("cut", False): 92, ("cut", True): 215,
                ("asm", False): 215, ("asm", True): 260, ("fallback", False): 120, ("fallback", True): 200}


def window_bytes_per_sample(step: str = "cut", graph: bool | None = None) -> int:
    """:data:`WINDOW_BYTES` of ``step`` ("fresnel", "cut", "asm" or "fallback"); ``graph`` None: whether gradients
    are enabled now (:func:`torch.is_grad_enabled`: a graph may be kept)."""
    if graph is None:
        graph = torch.is_grad_enabled()
    try:
        return WINDOW_BYTES[(step, bool(graph))]
    except KeyError:
        raise ValueError(f"the window's step is 'fresnel', 'cut', 'asm' or 'fallback', got {step!r}") from None


def check_window_memory(ny: int, nx: int, p: float, device=None, step: str = "cut",
                        graph: bool | None = None) -> None:
    """Refuse (:class:`~raywave.utils.errors.MemoryLimitError`) a field window of ny×nx simulation samples of
    pitch ``p`` mm that would not fit in memory, before anything of that size is allocated: at
    :func:`window_bytes_per_sample` of ``step`` and ``graph`` (None: gradients enabled now) a sample."""
    check_allocation(float(ny) * float(nx) * window_bytes_per_sample(step, graph),
                     f"the {ny}×{nx}-sample DOE-plane field (simulation pitch {p * 1e3:.3g} µm)",
                     "use a coarser DOE pitch (doe pitch / --doe-pitch), a lower oversample (--oversample), a "
                     "smaller DOE or, for a blank DOE, a plane nearer focus (--doe-distance; the beam is narrower "
                     "there, but the plane must stay before the rays' first crossing: CausticWarning)", device)


#: peak bytes of the caustic fallback's carry (issue 47, h47m: the plain carry from the fallback's plane or the
#: farthest plane before the fold that fits, and the scaled carry), by ``graph``: ``(fft, field, sphere)`` bytes per
#: sample of the windowed angular spectrum's FFT grid (:func:`carry_fft_shape`: the transfer function is built on all
#: of it, ~57 B a band sample while it is built and 16 B held: the carry's peak), of the field carried (the
#: construction on the earlier plane, held throughout) and, for the scaled carry, of the DOE-plane window (the sphere's
#: factor and its float64 temporaries, after the propagation: the larger of the two counts). Measured
#: (benchmarks/fallback_memory.py, no graph, peak RSS above the process's before the PSF; the Leica Elmarit-R 28 mm,
#: Pentax-DA 50 mm and Planar 80 mm at 0.7 field at two DOE pitches and under 6 GiB, the Planar's 16 GiB plane and the
#: Olympus 24 mm's scaled carry, 11 points, 0.32 – 1.82·10⁸ FFT samples;
#: benchmarks/results/window_memory_fallback_2026-12-01_xxvii_h47m.json): 49.2 B an FFT sample plus 16.6 B a carried
#: sample (least squares; residuals within 2 % from 9·10⁷ FFT samples on, −8 % on the two smallest, where a fixed
#: ~0.1 GiB counts); the estimate is 1.07 – 1.24× every point's peak (1.2× from 9·10⁷ FFT samples on). The sphere's
#: 96 B are counted, not measured (its phase was not the peak of the scaled points). With a graph ×2 (one point, the
#: Leica at a 2.2 µm pitch: 1.62× the no-graph fit, the estimate 1.54× its peak). The old single "fallback" estimate
#: (120 B a sample of the larger window) admitted 0.71 – 0.97× the peaks (6.3 – 8.1 GiB under a 6 GiB limit)
CARRY_BYTES = {False: (56, 32, 96), True: (112, 64, 192)}


def carry_fft_shape(n_from, n_doe, pitch: float, dz: float, medium: tuple, carrier=(0.0, 0.0)) -> tuple:
    """``(My, Mx)``: the FFT grid of :func:`~raywave.wave.propagate_window` carrying a field of ``n_from`` = (ny, nx)
    samples of ``pitch`` mm by ``dz`` mm onto a window of ``n_doe`` = (ny, nx) samples (its default band limit;
    ``medium`` = (wavelength µm, n), ``carrier`` (α, β) the envelope's): host numbers, nothing allocated."""
    src = WindowSource((int(n_from[0]), int(n_from[1])), (0.0, 0.0), (0.0, 0.0), float(medium[0]), float(dz),
                       float(medium[1]), (float(carrier[0]), float(carrier[1])))
    return window_fft_shape(src, (int(n_doe[0]), int(n_doe[1])), pitch)


def carry_bytes(n_from, fft, n_doe=None, graph: bool | None = None) -> float:
    """The caustic fallback's carry's peak memory estimate (bytes, :data:`CARRY_BYTES`): the carried field of
    ``n_from`` = (ny, nx) samples, the FFT grid ``fft`` = (My, Mx) (:func:`carry_fft_shape`) and, for the scaled
    carry, its DOE-plane window ``n_doe`` = (ny, nx) (None: the plain carry); ``graph`` None: whether gradients are
    enabled now."""
    if graph is None:
        graph = torch.is_grad_enabled()
    b_fft, b_field, b_sphere = CARRY_BYTES[bool(graph)]
    field = b_field * float(n_from[0]) * float(n_from[1])
    total = b_fft * float(fft[0]) * float(fft[1]) + field
    if n_doe is not None:  # the sphere's factor comes after the propagation has let its transfer function go
        total = max(total, field + b_sphere * float(n_doe[0]) * float(n_doe[1]))
    return total


def check_carry_memory(n_from, n_doe, fft, p: float, device=None, scaled: bool = False,
                       graph: bool | None = None, extra: float = 0.0) -> None:
    """Refuse (:class:`~raywave.utils.errors.MemoryLimitError`) the caustic fallback's carry of a field of ``n_from``
    = (ny, nx) samples of pitch ``p`` mm onto the DOE-plane window of ``n_doe`` samples through the FFT grid ``fft``
    (:func:`carry_fft_shape`), at :func:`carry_bytes` (``scaled``: the scaled carry; ``extra`` bytes more), before
    anything of its size is allocated."""
    need = carry_bytes(n_from, fft, n_doe if scaled else None, graph) + float(extra)
    what = ("the caustic fallback's " + ("scaled " if scaled else "") +
            f"carry of the {int(n_from[0])}×{int(n_from[1])}-sample field (simulation pitch {p * 1e3:.3g} µm) to "
            f"the {int(n_doe[0])}×{int(n_doe[1])}-sample DOE-plane window (a {int(fft[0])}×{int(fft[1])} FFT grid)")
    check_allocation(need, what, "use a coarser DOE pitch (doe pitch / --doe-pitch), a smaller PSF crop (ks), or a "
                     "DOE plane further from the rays' focus (--doe-distance: nearer the lens); or raise the limit "
                     "(RAYWAVE_MEMORY_LIMIT / --memory-limit)", device)


def lit_box(grid: Grid, bbox, margin: float) -> tuple[int, int, int, int] | None:
    """The half-open window ``(iy0, iy1, ix0, ix1)`` of ``grid`` (:class:`~raywave.wave.Grid`, e.g. a DOE's
    :meth:`~raywave.doe.DOE.sim_grid`) whose samples cover ``bbox = (xmin, xmax, ymin, ymax)`` ± ``margin`` (mm),
    clamped to the grid (``grid.window(*box)`` is its sub-grid); None when it misses the grid."""
    xmin, xmax, ymin, ymax = bbox
    (x0, y0), (px, py), (sy, sx) = grid.origin, grid.pitch, grid.shape
    ix0 = max(math.floor((xmin - margin - x0) / px), 0)
    ix1 = min(math.ceil((xmax + margin - x0) / px) + 1, sx)
    iy0 = max(math.floor((ymin - margin - y0) / py), 0)
    iy1 = min(math.ceil((ymax + margin - y0) / py) + 1, sy)
    if ix1 <= ix0 or iy1 <= iy0:
        return None
    return iy0, iy1, ix0, ix1


def _empty_field(doe, oversample, carrier, n, wavelength, z, center, rays, mode) -> DOEField:
    env = torch.zeros((1, 1), dtype=torch.complex128, device=doe.device)
    return DOEField.on_box(env, (0, 1, 0, 1), doe.sim_grid(oversample), (wavelength, n, carrier), z, center,
                           FieldInfo(int(rays), mode))


def _first_last(mask: torch.Tensor) -> list:
    """``[any, first, last + 1]`` of the 1-D bool ``mask`` as 0-d int64 tensors on its device (where nothing is set:
    0, 0 and the mask's length): the indices that ``nonzero`` would give, without reading them on the host."""
    n = mask.numel()
    if n == 0:
        return [torch.zeros((), dtype=torch.int64, device=mask.device)] * 3
    m = mask.to(torch.int64)
    return [m.amax(), torch.argmax(m), n - torch.argmax(m.flip(0))]


def _crop_to_lit(weight: torch.Tensor, *tensors):
    """Row/column bounds of the non-zero part of ``weight`` (ny, nx) (one host read)."""
    w = weight.detach()
    rows, cols = _first_last(w.amax(1) > 0), _first_last(w.amax(0) > 0)
    lit, r0, r1, _, c0, c1 = torch.stack(rows + cols).tolist()
    if not lit:
        return None
    return r0, r1, c0, c1


def _near_nodes(keep: torch.Tensor, pos_y: torch.Tensor, pos_x: torch.Tensor, margin: int = 3):
    """Half-open ranges ``((ya, yb), (xa, xb))`` of the fine samples (positions ``pos_y`` (Ny,), ``pos_x`` (Nx,) in
    node units) within ``margin`` node spacings of the rows / columns of ``keep`` (ky, kx) that hold a kept node,
    or None when no node is kept: the only samples whose interpolated values can be lit (cubic interpolation
    reaches 2 nodes), so the rest of the node span is never interpolated. One host read."""
    rows, cols = _first_last(keep.any(1)), _first_last(keep.any(0))

    def span(pos, lo, hi):  # lo, hi: the kept nodes' first and last index (0-d int64)
        return _first_last((pos >= lo - margin) & (pos <= hi + margin))

    ys, xs = span(pos_y, rows[1], rows[2] - 1), span(pos_x, cols[1], cols[2] - 1)
    kept, y_any, ya, yb, x_any, xa, xb = torch.stack([rows[0], *ys, *xs]).tolist()
    if not kept or not y_any or not x_any:
        return None
    return (ya, yb), (xa, xb)


def _common_setup(lens, doe, source, planes: tuple, chief, oversample: int, medium: float | None = None):
    """What both field constructions start from, for the :class:`~raywave.hybrid.coherent.settings.Source` ``source``,
    the planes ``(z_doe, z_sensor)`` mm and the :class:`~raywave.hybrid.coherent.settings.ChiefRays` ``chief`` (its
    ``doe`` and ``sensor`` rays): field type, field (2,), wavelength (1,), medium index (``medium``: the caller's,
    else read here), simulation grid (p, x0, y0, sy, sx), carrier (α, β), chief-ray centre on the sensor, DOE →
    sensor distance."""
    field, wavelength, field_type = source.field, source.wavelength, source.field_type
    (z_doe, z_sensor), chief_doe, chief_sensor = planes, chief.doe, chief.sensor
    field = torch.as_tensor(field, dtype=torch.float64, device=lens.device)
    field = field if field.shape == (2,) else field.reshape(2)  # (issue 43: each op counts, a reshape too)
    wl = torch.tensor([float(wavelength)], dtype=torch.float64, device=lens.device)
    carrier = tuple(chief_doe.d.tolist()[:2])  # (one host read)
    n = _medium_index(lens, wl) if medium is None else float(medium)
    return (field_type or lens.field_type, field, wl, n, _sim_grid(doe, oversample),
            carrier, tuple(chief_sensor.o.unbind()[:2]), z_sensor - z_doe)
