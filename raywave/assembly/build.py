"""Hybrid lenses from lens files: the refractive lens + the file's DOE, or a default blank DOE.

:mod:`raywave.io` reads a lens file's ``"doe"`` section into a :class:`~raywave.io.DOEData` (plain numbers and
a numpy phase map); this module builds the torch side, a :class:`~raywave.hybrid.HybridLens`. It sits in the
assembly layer, above :mod:`raywave.hybrid` (docs/architecture.md); ``raywave.hybrid.build`` re-exports it.

Grid rules (``load_hybrid`` / ``hybrid_from_spec``; explicit arguments override the file):

* **distance**: ``doe_distance``, else the file's ``doe.distance``, else (a lens file without a DOE) half
  way between the last vertex and the sensor (:data:`DEFAULT_DISTANCE_FRACTION` of the last thickness), moved
  towards the sensor until every beam spans at most :data:`MAX_DEFAULT_BEAM_PIXELS` pixels, never beyond the first
  caustic (:func:`fit_doe_distance`), and back from the rays' focus where the geometric-optics field would be off
  (:func:`go_field_distance`); ``hl.doe_info["distance_rule"]`` says which rule placed it.
* **pitch**: ``doe_pitch``, else the file's (``doe.pitch`` or the .npz's ``pitch``); a lens file without a
  DOE gets the pitch that samples its wavefront (:func:`nyquist_doe_pitch`: :data:`NYQUIST_FILL` of the
  Nyquist pitch of the steepest phase slope, relative to the chief ray, that any traced ray reaches on the DOE
  plane, for the given fields and wavelengths, rounded down to 2 significant digits and at most
  :data:`MAX_DEFAULT_PITCH`): finer than 1 µm for a fast lens, coarser for a slow one (a 100 mm F/10 singlet
  gets ~4 µm instead of 16 600² pixels at 1 µm). ``hl.doe_info["pitch_rule"]`` says which rule chose it.
  A DOE in the file without a pitch (e.g. from a .zmx) is an error.
* **grid**: a phase map fixes it (``(ny, nx)`` of the map; a ``doe_size`` that disagrees is an error). Otherwise
  ``doe_size`` (mm, width and height), else the file's ``shape`` or ``size``, else (no DOE in the file) a
  square that holds the beam: :data:`BEAM_MARGIN` × twice the largest ``|x|`` or ``|y|`` any traced ray
  reaches on the DOE plane (pupil rim and a hexapolar grid, for the given fields — default: the lens's
  fields and (0, 0) — and wavelengths), and with the exit-pupil stop edge (the default) at least the beam's extent
  plus the edge's diffraction band (:func:`edge_band_reach`), so that the blank DOE's clear aperture does not cut
  it. Sizes are rounded up to whole pixels. A DOE in the file without a
  size or shape (a .zmx diffractive surface without CLAP / SQAP) is an error unless ``doe_size`` is given.
* **phase**: the file's phase map (``PixelDOE``), else its ``phase_model`` (``raywave.doe.doe_from_phase_model``:
  BINARY_2, radial, Zernike, Fresnel, grating, cubic, sums), else blank; ``material`` / ``levels`` make it a
  fabricated, dispersive height map (``DOE.fabricate``); ``wrap`` wraps it to [0, 2π) without quantising.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from raywave.doe import BlankDOE, PixelDOE, doe_from_phase_model
from raywave.doe.spec import check_phase_finite
from raywave.hybrid.coherent.exit_pupil import (GO_FALLBACK_FRACTION, GO_PHASE_TOL, MAX_XP_SAMPLES, blank_edge_steps,
                                               go_phase_errors)
from raywave.hybrid.coherent.geometry import check_window_memory
from raywave.hybrid.coherent.stop_edge import RIPPLE_ZONES
from raywave.hybrid.hybrid_lens import BEAM_MARGIN, DEFAULT_EDGE_STEP, DEFAULT_STOP_EDGE, HybridLens
from raywave.io.errors import LensFileError, with_location
from raywave.lens.analysis import beam_field_points, beam_folds, beam_half_extent, beam_rays_at
from raywave.lens.build import clip_at_semi_diameters, lens_from_spec, resolve_lens_path
from raywave.lens.frames import image_space
from raywave.lens.paraxial import ParaxialUndefinedError, paraxial_data
from raywave.lens.prescription import rays_beyond_semi_diameters
from raywave.utils.checks import pitch_mm
from raywave.utils.errors import MemoryLimitError, NonFiniteError, check_allocation

__all__ = ["BEAM_MARGIN", "DEFAULT_DISTANCE_FRACTION", "DEFAULT_DOE_PITCH", "MAX_DEFAULT_PITCH", "NYQUIST_FILL",
           "CAUSTIC_MARGIN", "MAX_DEFAULT_BEAM_PIXELS", "beam_half_extent", "caustic_free_distance", "default_doe_size",
           "edge_band_reach", "fit_doe_distance", "go_field_distance", "hybrid_from_spec", "load_hybrid",
           "nyquist_doe_pitch"]

#: Pixel pitch (mm) of the blank DOE given to a lens file without a DOE when no ray can size it (before issue 19
#: every lens file without a DOE got it; now :func:`nyquist_doe_pitch` chooses).
DEFAULT_DOE_PITCH = 1e-3
#: the default pitch is this fraction of the Nyquist pitch of the steepest wavefront slope (a 25 % margin)
NYQUIST_FILL = 0.8
#: the largest default pitch (mm): the simulation grid also samples the DOE's own phase
MAX_DEFAULT_PITCH = 1e-2
#: Default DOE plane of a lens file without a DOE: this fraction of the way from the last vertex to the sensor.
DEFAULT_DISTANCE_FRACTION = 0.5
#: a lens file without a DOE: the default DOE plane moves towards the sensor until every source's beam spans at most
#: this many DOE pixels a side on it (:func:`fit_doe_distance`; a 25 mm beam at 0.6 µm would need 40 000²)
MAX_DEFAULT_BEAM_PIXELS = 2048
#: ... but it stays where every beam is at least this many times as wide as on the plane where its rays first cross
#: (a caustic between the lens and the plane makes the ray map, from which the field is built, many to one: the
#: field there is wrong, e.g. an f/3 double Gauss at 14°, 2 mm before focus: 0.17 rel L1 from the Huygens PSF)
CAUSTIC_MARGIN = 1.5
_MIN_PIXELS = 16
_PIXEL_TOL = 1e-6


#: more DOE pixels on a side than this is no grid at all (the memory check refuses far smaller ones)
_MAX_PIXELS_PER_SIDE = 2**31


def _pixels(length: float, pitch: float, source: str = "the lens") -> int:
    """Whole pixels covering ``length`` mm (rounded up, tolerating float noise); a ValueError naming ``source``
    when the count is not finite or beyond any grid (e.g. a beam sized by a 1e308 mm semi-diameter)."""
    n = length / pitch
    if not (math.isfinite(n) and n <= _MAX_PIXELS_PER_SIDE):
        raise ValueError(f"{source}: the DOE would span {length:g} mm = {n:g} pixels of {pitch:g} mm, not a usable "
                         "grid: check the lens's apertures and semi-diameters, or give the DOE a size "
                         "(doe_size; raywave psf: --doe-size MM [MM])")
    return max(1, math.ceil(n - _PIXEL_TOL))


def _slopes(lens, z: float, fields, wavelengths, depth):
    """Per (field, wavelength): the largest ``n·|d⊥ − d⊥_chief|`` of the traced rays on the plane z (a tensor
    (F, W), 0 where nothing reaches it) and the wavelengths (W,) µm."""
    at, n, wls = beam_rays_at(lens, z, fields, wavelengths, depth, chief=True)
    d = at.d[..., :2]
    rel = n * torch.linalg.vector_norm(d - d[..., :1, :], dim=-1)  # pupil sample 0 is the chief ray
    ok = at.valid & at.valid[..., :1] & torch.isfinite(rel)
    return torch.where(ok, rel, torch.zeros_like(rel)).amax(-1), torch.tensor(wls, dtype=torch.float64,
                                                                                device="cpu")


def nyquist_doe_pitch(lens, distance: float, fields=None, wavelengths=None, depth=None,
                      fill: float = NYQUIST_FILL) -> float | None:
    """The DOE pitch (mm) that samples the wavefront arriving ``distance`` mm after the last vertex: ``fill`` ×
    the Nyquist pitch ``λ / (2 n |d⊥ − d⊥_chief|)`` of the steepest slope (relative to the chief ray, whose
    carrier the field construction removes) over every traced ray (pupil rim and a hexapolar grid), field
    and wavelength (defaults as :func:`beam_half_extent`), rounded down to 2 significant digits and at most
    :data:`MAX_DEFAULT_PITCH`. None when no ray reaches the plane."""
    z = float(lens.vertex_z()[-1].detach()) + distance
    slope, wls = _slopes(lens, z, fields, wavelengths, depth)
    ok = slope > 0
    if not bool(ok.any()):
        return None
    pitch = float((fill * wls[None, :] * 1e-3 / (2 * slope)).masked_fill(~ok, math.inf).min())
    if not math.isfinite(pitch):
        return None
    digits = 10 ** (math.floor(math.log10(pitch)) - 1)
    return min(float(f"{math.floor(pitch / digits * (1 + 1e-9)) * digits:.2g}"), MAX_DEFAULT_PITCH)


def fit_doe_distance(lens, distance: float, pitch: float, fields=None, wavelengths=None, depth=None,
                     max_pixels: int = MAX_DEFAULT_BEAM_PIXELS, report: dict | None = None) -> float:
    """The default DOE distance (mm after the last vertex) for a lens file without a DOE (``lens``: the lens, or for a
    folded or mirrored one its image-space view, :func:`raywave.lens.frames.image_space`): ``distance`` when every
    source's beam spans at most ``max_pixels`` pixels of ``pitch`` mm a side on that plane, else the nearest plane
    towards the sensor where it does (the beam narrows towards focus while the Nyquist pitch, set by the rays'
    directions, stays the same: a fast lens with a large beam, e.g. an F/1.3 lens with a 21 mm pupil, needs
    20 000² pixels half way to the sensor and 2 000² a few mm before it). When no plane fits: the plane where the
    widest beam is narrowest. Never beyond the first caustic (:func:`caustic_free_distance`): an aberrated beam's
    rays cross before focus, and the field is built from a one-to-one ray map, so the plane stays before the
    crossing even where the beam then spans more than ``max_pixels``. With a blank DOE and
    ``stop_edge="exit_pupil"`` the PSF does not depend on the plane otherwise (docs/ray-wave.md). Rays: pupil rim
    and a hexapolar grid per field and wavelength (defaults as :func:`beam_half_extent`), traced once and carried
    along straight lines; a 1.1 margin for the window's edge band. ``report``: a dict that receives
    ``distance_rule`` ("half_way", "beam_fit" or "before_caustic") and ``caustic_distance`` (mm after the last
    vertex where the first rays cross, or None)."""
    last, z_last = _last_gap(lens), float(lens.vertex_z()[-1].detach())
    report = {} if report is None else report
    at, n, _ = beam_rays_at(lens, z_last + distance, fields, wavelengths, depth)
    ok = at.valid & torch.isfinite(at.o).all(-1)
    report.update(distance_rule="half_way", caustic_distance=None)
    if not bool(ok.any()):
        return distance
    xy0 = at.o[..., :2]
    tan = at.d[..., :2] / at.d[..., 2:]
    safe = caustic_free_distance(lens, fields, wavelengths, depth, report=report, beam=(xy0, tan, ok, distance))
    # offsets from the default plane
    dz = torch.linspace(0.0, 0.995 * last - distance, 400, dtype=torch.float64, device=xy0.device)
    w = _widest(xy0[None] + tan[None] * dz[:, None, None, None, None], ok) / pitch
    if float(w[0]) <= max_pixels or dz.numel() < 2 or float(dz[-1]) <= 0:
        fitted = distance
    else:
        fits = torch.nonzero(w <= max_pixels).squeeze(1)
        if fits.numel():
            i = int(fits[0])
            lo_, hi_ = float(dz[i - 1]), float(dz[i])  # refine the crossing by bisection
            for _ in range(30):
                mid = 0.5 * (lo_ + hi_)
                if float(_widest(xy0[None] + tan[None] * mid, ok)[0]) / pitch <= max_pixels:
                    hi_ = mid
                else:
                    lo_ = mid
            fitted = distance + hi_
        else:
            fitted = distance + float(dz[int(torch.argmin(w))])
        report["distance_rule"] = "beam_fit"
    if safe is not None and fitted > safe:
        fitted = safe
        report["distance_rule"] = "before_caustic"
    return fitted


def go_field_distance(lens, distance: float, pitch: float, sources: tuple = (None, None, None),
                      report: dict | None = None, sphere_cut: bool = True) -> float:
    """The default DOE distance (mm after the last vertex) of a blank DOE moved back from the rays' focus where the
    exit-pupil edge's Fresnel step would take its caustic fallback on the plane ``distance``: where a source's
    :func:`~raywave.hybrid.coherent.exit_pupil.go_phase_error` there exceeds
    :data:`~raywave.hybrid.coherent.exit_pupil.GO_PHASE_TOL`, the plane nearest it towards the lens where every such
    source's error is at most ``GO_FALLBACK_FRACTION`` × the tolerance: the plane on which the fallback would build
    the field before carrying it to the DOE plane by the angular spectrum. Placed there, the DOE takes the field as
    it is built, with no carrying step and no warning (a blank DOE's PSF with the exit-pupil edge does not depend on
    the plane, docs/ray-wave.md). Kept where no plane helps, that plane lies before the last vertex (the fallback
    builds there on a virtual plane; a DOE cannot sit there), an exit pupil lies after the plane, or a beam there
    would span more than ``MAX_XP_SAMPLES`` pixels of ``pitch`` mm or its window not fit in the memory available
    now (the fallback's own rules, with a 1.25× window: the engine then warns as before). ``sources`` = ``(fields, wavelengths, depth)`` as :func:`fit_doe_distance`;
    ``sphere_cut``: the edge step is "adaptive", so sources whose edge is cut on the DOE plane (a sphere focused on
    the sensor, :func:`~raywave.hybrid.coherent.exit_pupil.blank_edge_steps`) take no fallback and do not count.
    ``report`` receives ``distance_rule`` "go_field" and ``go_phase_error`` (rad, the largest that asked for the
    move) when it moves."""
    fields, wavelengths, depth = sources
    z_last = float(lens.vertex_z()[-1].detach())
    z_doe = z_last + distance
    wls = list(lens.wavelengths) if wavelengths is None else [
        float(w) for w in torch.as_tensor(wavelengths, device="cpu").reshape(-1)]
    z_xps = [_exit_pupil_z(lens, wl) for wl in wls]
    if any(z is None or not z < z_doe for z in z_xps):
        return distance
    points = beam_field_points(lens, fields)
    zs, err = go_phase_errors(lens, points, wls, depth, None, (z_xps, z_doe))
    need = err[..., -1] > GO_PHASE_TOL  # (F, W)
    if bool(need.any()) and sphere_cut:
        steps = blank_edge_steps(lens, points, wls, depth, (z_doe, z_last + _last_gap(lens)))
        need = need & torch.tensor([[s == "fresnel" for s in row] for row in steps], device=need.device)
    if not bool(need.any()):
        return distance
    worst = float(err[..., -1][need].max())
    plane = math.inf
    for fi, wi in torch.nonzero(need).tolist():
        fine = torch.nonzero(err[fi, wi] <= GO_FALLBACK_FRACTION * GO_PHASE_TOL).reshape(-1)
        if not fine.numel() or int(fine[-1]) == 0:  # no plane between the exit pupil and this one helps
            return distance
        plane = min(plane, float(zs[wi, int(fine[-1])]))
    if not plane > z_last:  # the fallback's plane lies inside the lens (a virtual plane): no DOE plane there
        return distance
    wx, wy = _footprint_sides(lens, plane, (fields, wavelengths, depth))
    if max(wx, wy) / pitch > MAX_XP_SAMPLES:
        return distance
    try:  # the window (beam and edge band) as the engine's fallback checks it (1.2×), with a margin: at the time
        # of the call, like the fallback (where it does not fit, the engine keeps the plane as before)
        # (the Fresnel step's, without a graph: the plane is chosen for the PSF whatever the mode of the load; a PSF
        # with gradients that does not fit there is refused by the engine's own check)
        check_window_memory(math.ceil(1.25 * wy / pitch), math.ceil(1.25 * wx / pitch), pitch, lens.device,
                            step="fresnel", graph=False)
    except MemoryLimitError:
        return distance
    if report is not None:
        report.update(distance_rule="go_field", go_phase_error=worst)
    return plane - z_last


def _footprint_sides(lens, z: float, sources: tuple) -> tuple[float, float]:
    """The largest x and y extents (mm) of any one source's beam on the plane ``z`` (mm from the first vertex;
    ``sources`` = ``(fields, wavelengths, depth)`` as :func:`beam_rays_at`), 0 where no ray reaches it."""
    at, _, _ = beam_rays_at(lens, z, *sources)
    ok = at.valid & torch.isfinite(at.o).all(-1)  # (F, W, N)
    big = torch.tensor(math.inf, dtype=at.o.dtype, device=at.o.device)
    xy = at.o[..., :2]
    span = torch.where(ok[..., None], xy, -big).amax(-2) - torch.where(ok[..., None], xy, big).amin(-2)
    span = torch.where(ok.any(-1)[..., None], span, torch.zeros_like(span)).reshape(-1, 2)
    return float(span[:, 0].max()), float(span[:, 1].max())


def _last_gap(lens) -> float:
    """The distance (mm) from the last vertex to the sensor along the light: the last thickness, or for a folded or
    mirrored lens's image-space view (:func:`raywave.lens.frames.image_space`) its signed last thickness, positive
    in that frame."""
    t = lens.last_thickness() if getattr(lens, "image_space_view", False) else lens.surfaces[-1].thickness
    return float(t.detach())


def _widest(xy: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """The largest side (mm) of any source's footprint, times 1.1 (the window's edge band): ``xy`` (Z, F, W, N, 2)
    ray positions on Z planes, ``ok`` (F, W, N) the rays that count → (Z,)."""
    big = torch.tensor(math.inf, dtype=xy.dtype, device=xy.device)
    hi = torch.where(ok[..., None], xy, -big).amax(-2)
    lo = torch.where(ok[..., None], xy, big).amin(-2)
    side = (hi - lo).amax(-1)
    side = torch.where(ok.any(-1), side, torch.zeros_like(side))
    return side.flatten(1).amax(1) * 1.1


def caustic_free_distance(lens, fields=None, wavelengths=None, depth=None, margin: float = CAUSTIC_MARGIN,
                          report: dict | None = None, beam: tuple | None = None) -> float | None:
    """The largest DOE distance (mm after the last vertex) before the sources' first caustic: the plane where the
    widest beam is still ``margin`` × as wide as on the first plane where any source's rays cross
    (:func:`raywave.lens.analysis.beam_folds`, 400 planes up to 0.995 of the last thickness); None when no rays
    cross there (or right after the lens, where no plane helps). Sources as :func:`fit_doe_distance`. ``report``
    receives ``caustic_distance`` (mm or None). ``beam``: the sources' rays already traced by
    :func:`raywave.lens.analysis.beam_rays_at` as ``(xy (F, W, N, 2) mm, tan (F, W, N, 2), ok (F, W, N), d)`` on the
    plane ``d`` mm after the last vertex (:func:`fit_doe_distance` passes its own; None: traced here)."""
    last, z_last = _last_gap(lens), float(lens.vertex_z()[-1].detach())
    dz = torch.linspace(0.0, 0.995 * last, 400, dtype=torch.float64, device=lens.device)
    folded = beam_folds(lens, z_last + dz, fields, wavelengths, depth).flatten(1).amax(1) > 0
    if not bool(folded.any()):
        return None
    i = int(torch.nonzero(folded)[0])
    if report is not None:
        report["caustic_distance"] = float(dz[i])
    if beam is None:
        at, _, _ = beam_rays_at(lens, z_last, fields, wavelengths, depth)
        beam = (at.o[..., :2], at.d[..., :2] / at.d[..., 2:], at.valid & torch.isfinite(at.o).all(-1), 0.0)
    xy, tan, ok, d0 = beam  # straight lines after the last surface
    w = _widest(xy[None] + tan[None] * (dz[:i + 1] - d0)[:, None, None, None, None], ok)
    wide = torch.nonzero(w[:i] >= margin * w[i]).squeeze(1)
    return float(dz[int(wide[-1])]) if wide.numel() else None  # crossing right after the lens: no plane helps


def default_doe_size(lens, distance: float, fields=None, wavelengths=None, depth=None,
                     margin: float = BEAM_MARGIN, edge_band: bool = False) -> tuple[float, float]:
    """(w, h) mm of a square DOE centred on the axis that holds the beam ``distance`` mm after the last vertex:
    ``margin`` × twice the largest |x| or |y| of :func:`beam_half_extent`; with ``edge_band``, at least twice
    that extent plus :func:`edge_band_reach` (a blank DOE of a lens file: its clear aperture must not cut the stop
    edge's diffraction band that the default edge builds beyond the beam's geometric edge)."""
    z = float(lens.vertex_z()[-1].detach()) + distance
    ext = beam_half_extent(lens, z, fields, wavelengths, depth)
    if ext is None:
        raise ValueError("no ray reaches the DOE plane (every ray is vignetted), so the beam cannot size the DOE; "
                         "give the DOE size")
    half = margin * max(ext)
    if edge_band:
        half = max(half, max(ext) + edge_band_reach(lens, z, fields, wavelengths, depth))
    return 2.0 * half, 2.0 * half


#: :func:`edge_band_reach`: the upper estimate's widening of the edge's Fresnel zone for the marginal rays' tilt
#: (as the engine's own estimate, ``raywave.hybrid.coherent.stop_edge._zone_estimate``)
EDGE_ZONE_WIDENING = 1.3


def edge_band_reach(lens, z: float, fields=None, wavelengths=None, depth=None) -> float:
    """Upper estimate (mm) of how far beyond the beam's geometric edge the default stop edge's field reaches on the
    plane ``z`` (mm from the first vertex; sources as :func:`beam_half_extent`): its ripple band ends at the Fresnel
    parameter ``ν_max = √2 · RIPPLE_ZONES`` (``raywave.hybrid.coherent.stop_edge``), ``s = ν_max / g =
    RIPPLE_ZONES · sqrt(λ_m L)``, with the edge's Fresnel length ``L = |z − z_xp| · |z_s − z| / |z_s − z_xp| /
    cos³θ`` (a sphere from the paraxial exit pupil ``z_xp`` converging on the sensor ``z_s``: the Fresnel scaling
    theorem; θ the steepest ray of the beam on the plane), widened by :data:`EDGE_ZONE_WIDENING`; the largest over
    the wavelengths. Where a DOE's clear aperture cuts into this band, it cuts the edge's diffraction: the
    Fraunhofer objective at 0.7 field with a DOE of 1.2× its beam (0.51 mm spare, band 0.77 mm) was 6.1e-4 rel L1
    from the converged Huygens PSF, 3.3e-4 with the band inside."""
    at, n, wls = beam_rays_at(lens, z, fields, wavelengths, depth)
    ok = at.valid & torch.isfinite(at.d).all(-1)
    if not bool(ok.any()):
        return 0.0
    d = at.d / torch.linalg.vector_norm(at.d, dim=-1, keepdim=True)
    cos2 = float((d[..., 2][ok] ** 2).min())
    z_s = float(lens.vertex_z()[-1].detach()) + float(lens.surfaces[-1].thickness.detach()) * lens.direction_signs()[-1]
    reach = 0.0
    for i, wl in enumerate(wls):
        to_sensor = abs(z_s - z)
        z_xp = _exit_pupil_z(lens, wl)
        length = to_sensor if z_xp is None or z_s == z_xp else abs(z - z_xp) * to_sensor / abs(z_s - z_xp)
        n_img = float(n[..., i, :].reshape(-1)[0])
        lam_m = wl * 1e-3 / n_img
        reach = max(reach, RIPPLE_ZONES * math.sqrt(lam_m * length / max(cos2, 1e-3) ** 1.5))
    return EDGE_ZONE_WIDENING * reach


def _exit_pupil_edge(lens, stop_edge: str | None) -> bool:
    """Whether the hybrid lens's stop edge will be formed at the exit pupil (``stop_edge``, None: the default), so
    that its default DOE is sized and placed for that edge: not where the paraxial exit pupil is undefined (NaN; the
    default edge falls back to the DOE plane there, and its DOE is then the DOE-plane edge's, the same PSF). A pupil
    at or near infinity (image-space telecentric) takes the exit-pupil edge like any other since 2026-12-01
    (:data:`~raywave.hybrid.hybrid_lens.EXIT_PUPIL_FAR`)."""
    if (DEFAULT_STOP_EDGE if stop_edge is None else stop_edge) != "exit_pupil":
        return False
    try:
        z_xp = float(paraxial_data(lens, lens.primary_wavelength).xp_z)
    except ParaxialUndefinedError:  # a decentred or tilted powered surface: the engine's real chief ray decides
        return True
    return not math.isnan(z_xp)


def _exit_pupil_z(lens, wavelength: float) -> float | None:
    """The paraxial exit pupil's z (mm) at ``wavelength`` µm, or None where it is at infinity or undefined (a
    decentred or tilted powered surface: :func:`edge_band_reach` then takes the plane-to-sensor distance, the
    Fresnel length of an exit pupil at infinity and an upper bound of it for one before the plane)."""
    try:
        z_xp = float(paraxial_data(lens, wavelength).xp_z)
    except ParaxialUndefinedError:
        return None
    return z_xp if math.isfinite(z_xp) else None


def _spec_lens(spec: dict, field_type: str | None, source: str):
    """The refractive :class:`~raywave.lens.Lens` of ``spec``, checked for the wave engine and read with
    ``field_type`` ("angle" / "object_height", None: the file's). ValueErrors name ``source``."""
    try:
        lens = lens_from_spec(spec)
    except ValueError as err:  # a spec that validates but builds no lens: name the file
        raise with_location(err, source)
    problem = lens.wave_support_problem()
    if problem is not None:
        raise ValueError(f"{source}: {problem}")
    if field_type is not None:
        if field_type not in ("angle", "object_height"):
            raise ValueError(f"field_type must be 'angle' or 'object_height', got {field_type!r}")
        lens.field_type = field_type
    return lens


def _first_distance(data, doe_distance: float | None, last: float, source: str) -> float:
    """The DOE plane's distance (mm after the last vertex) before any beam fit: ``doe_distance``, else the file's
    (``data``: its DOEData, None: no DOE in the file), else :data:`DEFAULT_DISTANCE_FRACTION` × ``last`` (the
    last thickness, mm, along the light). A ValueError unless 0 <= distance < last."""
    if doe_distance is not None:
        distance = float(doe_distance)
    elif data is not None and data.distance is not None:
        distance = data.distance
    else:
        distance = DEFAULT_DISTANCE_FRACTION * last
    if not (math.isfinite(distance) and 0 <= distance < last):
        raise ValueError(f"{source}: the DOE distance must lie between the last surface and the sensor "
                         f"(0 <= d < {last:g} mm, the last thickness), got {distance!r}")
    return distance


def _doe_pitch(optics, data, doe_pitch: float | None, distance: float, fields, wavelengths, depth,
               source: str) -> tuple[float, dict]:
    """The DOE pixel pitch (mm) and the rule that chose it (``{"pitch_rule": ...}`` for ``doe_info``):
    ``doe_pitch``, else the file's (``data``; a file DOE without one is an error), else
    :func:`nyquist_doe_pitch` of ``optics`` (the image-space lens) at ``distance`` mm, else
    :data:`DEFAULT_DOE_PITCH`. A ValueError unless finite and > 0."""
    if doe_pitch is not None:
        pitch = float(doe_pitch)
        rule = {"pitch_rule": "given"}
    elif data is not None and data.pitch is not None:
        pitch = data.pitch
        rule = {"pitch_rule": "file"}
    elif data is not None:
        raise ValueError(f"{source}: the DOE has no pixel pitch (the file does not give one): pass doe_pitch "
                         "(raywave psf: --doe-pitch MM)")
    else:
        pitch = nyquist_doe_pitch(optics, distance, fields, wavelengths, depth)
        rule = {"pitch_rule": "nyquist" if pitch is not None else "default", "nyquist_fill": NYQUIST_FILL}
        pitch = DEFAULT_DOE_PITCH if pitch is None else pitch
    if not (math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"the DOE pitch must be > 0 mm, got {pitch!r}")
    pitch_mm(pitch, "the DOE pitch (doe_pitch; raywave: --doe-pitch MM)")
    return pitch, rule


def _size_arg(doe_size) -> tuple[float, float] | None:
    """``doe_size`` (one length or one / two lengths, mm) as (width, height) mm; None when not given. A ValueError
    unless every length is finite and > 0."""
    if doe_size is None:
        return None
    size = tuple(float(s) for s in (doe_size if isinstance(doe_size, (list, tuple)) else (doe_size,)))
    if len(size) == 1:
        size = (size[0], size[0])
    if len(size) != 2 or not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"the DOE size must be one or two lengths > 0 mm (width, height), got {doe_size!r}")
    return size


def _doe_shape(optics, data, pitch: float, doe_pitch: float | None, size, distance: float, beam: tuple,
               source: str) -> tuple[int, int]:
    """The DOE grid ``(ny, nx)`` pixels of ``pitch`` mm: the file's phase map (``data``; a ``size`` (w, h) mm that
    disagrees is an error), else ``size``, else the file's shape (unless a given ``doe_pitch`` rescales its size),
    else its size, else (no DOE in the file) :func:`default_doe_size` of ``optics`` at ``distance`` mm for the
    sources ``beam`` = ``(fields, wavelengths, depth, edge_band)``, at least :data:`_MIN_PIXELS` a side. A file DOE
    with neither is an error, as is an unloaded phase map."""
    from_file = data is not None
    phase = data.phase if from_file else None
    if from_file and data.phase_path is not None and phase is None:
        raise ValueError(f"{source}: the DOE phase map {data.phase_path!r} was not loaded (resolve_doe(load=True))")
    if phase is not None:
        shape = tuple(phase.shape)
        if size is not None:
            want = (shape[1] * pitch, shape[0] * pitch)
            if any(abs(s - w) > 0.5 * pitch for s, w in zip(size, want)):
                raise ValueError(f"{source}: the DOE phase map ({shape[1]} × {shape[0]} pixels of {pitch:g} mm = "
                                 f"{want[0]:g} × {want[1]:g} mm) fixes the DOE size; a size of {size[0]:g} × "
                                 f"{size[1]:g} mm does not apply")
    elif size is not None:
        shape = (_pixels(size[1], pitch, source), _pixels(size[0], pitch, source))
    elif from_file and data.shape is not None and (data.size is None or doe_pitch is None):
        shape = data.shape
    elif from_file and data.size is not None:
        shape = (_pixels(data.size[1], pitch, source), _pixels(data.size[0], pitch, source))
    elif from_file:
        raise ValueError(f"{source}: the DOE has no size (the file gives neither 'size' nor 'shape', nor a .zmx "
                         "CLAP / SQAP): pass doe_size (raywave psf: --doe-size MM [MM])")
    else:
        fields, wavelengths, depth, band = beam
        w, h = default_doe_size(optics, distance, fields, wavelengths, depth, edge_band=band)
        shape = (max(_pixels(h, pitch, source), _MIN_PIXELS), max(_pixels(w, pitch, source), _MIN_PIXELS))
    return shape


#: bytes per DOE pixel held by the element itself when it stores a map (a float64 phase map and, fabricated, its
#: float64 height map); a blank DOE or a phase model stores nothing per pixel
DOE_BYTES_PER_PIXEL = 16


def widest_beam(optics, distance: float, fields=None, wavelengths=None, depth=None) -> float | None:
    """The widest single source's footprint (mm, the larger side, with the 1.1 edge-band margin) on the plane
    ``distance`` mm after the last vertex (sources as :func:`beam_half_extent`); None when no ray reaches it."""
    z = float(optics.vertex_z()[-1].detach()) + distance
    at, _, _ = beam_rays_at(optics, z, fields, wavelengths, depth)
    ok = at.valid & torch.isfinite(at.o).all(-1)
    if not bool(ok.any()):
        return None
    return float(_widest(at.o[..., :2][None], ok)[0])


def check_doe_memory(shape: tuple[int, int], pitch: float, oversample: int, stores_map: bool, source: str,
                     beam: float | None = None, device=None) -> None:
    """The memory estimate of a hybrid lens's DOE and of the field window of one PSF, before anything of their size
    is allocated or traced: the element's own arrays (:data:`DOE_BYTES_PER_PIXEL` per pixel when ``stores_map``)
    plus the largest field window, ``oversample``² simulation samples per pixel over the DOE grid or, when
    ``beam`` (mm, :func:`widest_beam`) is known, over the widest beam, at
    :func:`raywave.hybrid.coherent.geometry.window_bytes_per_sample` (the field built on the DOE plane, without a
    graph: a PSF with gradients is checked again by the engine). Refused
    (:class:`~raywave.utils.errors.MemoryLimitError`) over the limit of
    :func:`~raywave.utils.errors.check_allocation`, naming the options that shrink it and, for a pitch below
    0.1 µm, the likely unit slip."""
    from raywave.hybrid.coherent.geometry import window_bytes_per_sample

    ny, nx = (int(v) for v in shape)
    q = max(int(oversample), 1)
    wy, wx = ny, nx
    if beam is not None:
        side = math.ceil(beam / pitch) + 2
        wy, wx = min(ny, side), min(nx, side)
    per_sample = window_bytes_per_sample("cut", graph=False)
    need = float(ny) * nx * (DOE_BYTES_PER_PIXEL if stores_map else 0) + float(wy) * wx * q * q * per_sample
    slip = ""
    if pitch < 1e-4:
        slip = (f" (the pitch is {pitch:g} mm = {pitch * 1e3:g} µm, finer than any DOE pixel: pitches are in mm, "
                "1 µm = 0.001 mm)")
    check_allocation(need, f"{source}: the {nx}×{ny}-pixel DOE ({pitch * 1e3:.3g} µm pixels, oversample {q}) with "
                           f"a PSF's {wx * q}×{wy * q}-sample field window{slip}",
                     "use a coarser DOE pitch (doe_pitch; raywave: --doe-pitch, in mm), a lower oversample "
                     "(--oversample) or a smaller DOE (doe_size; --doe-size, in mm)", device)


def _make_doe(data, shape: tuple[int, int], pitch: float, source: str):
    """The DOE on the ``(ny, nx)`` grid of ``pitch`` mm: the file's phase map (``data``: its DOEData) as a
    :class:`PixelDOE`, else its phase model, else blank; fabricated as the file says (material, levels, wrap).
    ``data`` None: a blank square DOE. Non-finite phases are a :class:`LensFileError` naming ``source``."""
    from_file = data is not None
    phase = data.phase if from_file else None
    aperture = data.aperture if from_file else "square"
    model = data.phase_model if from_file else None
    material = data.material if from_file else None
    levels = data.levels if from_file else None
    wrap = bool(data.wrap) if from_file else False
    if phase is not None:
        doe = PixelDOE(phase, pitch, design_wavelength=data.design_wavelength, aperture=aperture, material=material)
        try:
            check_phase_finite(doe, f"the phase map {data.phase_path!r}", "its values are radians")
        except NonFiniteError as e:
            raise LensFileError(f"doe.phase: {e}", source) from None
        if levels is not None:
            doe.fabricate(levels=levels)
        elif wrap:
            doe.fabricate(levels=None)
    elif model is not None:
        try:
            doe = doe_from_phase_model(model, shape, pitch, aperture, design_wavelength=data.design_wavelength,
                                       material=material, levels=levels, wrap=wrap)
        except NonFiniteError as e:
            raise LensFileError(f"doe.phase_model: {e}", source) from None
    elif material is not None or levels is not None:
        doe = BlankDOE(shape, pitch, aperture=aperture, design_wavelength=data.design_wavelength, material=material)
    else:
        doe = BlankDOE(shape, pitch, aperture=aperture)
    return doe


def _doe_summary(data, doe, distance: float, pitch: float, oversample: int) -> dict:
    """The DOE's entries of ``hl.doe_info``: distance and pitch (mm), grid, aperture, phase file or model,
    oversampling and the fabrication settings (``data``: the file's DOEData, None: a default DOE)."""
    from_file = data is not None
    model = data.phase_model if from_file else None
    return dict(distance=distance, pitch=pitch, shape=list(doe.shape), size=list(doe.size),
                aperture=data.aperture if from_file else "square", phase=data.phase_path if from_file else None,
                oversample=oversample, phase_model=None if model is None else model["type"],
                material=doe.material_name, levels=doe.quant_levels, design_wavelength=doe.design_wavelength,
                dispersion=doe.dispersion)


def _clip_apertures_hint(lens) -> str:
    """A sentence for a memory refusal where the lens's rays pass outside surfaces' semi-diameters (which do not
    clip): those rays, steep behind the lens, set the DOE's Nyquist pitch; '' where none does."""
    beyond = rays_beyond_semi_diameters(lens)
    if not beyond:
        return ""
    where = ", ".join(f"{i} ({h:.3g} mm rays, semi-diameter {sd:.3g} mm)" for i, h, sd in beyond[:4])
    more = f" and {len(beyond) - 4} more" if len(beyond) > 4 else ""
    return (f". The lens's rays pass outside the semi-diameters of surface{'s' if len(beyond) > 1 else ''} {where}"
            f"{more}, which do not clip them: to vignette at the clear apertures as the lens's mounts do, load it "
            "with clip_apertures=True (raywave: --clip-apertures)")


def hybrid_from_spec(spec: dict, doe_data=None, doe_pitch: float | None = None, doe_size=None,
                     doe_distance: float | None = None, sensor_pitch: float | None = None,
                     oversample: int | None = None, fields=None, wavelengths=None, depth=None,
                     field_type: str | None = None, source: str = "<spec>", stop_edge: str | None = None,
                     edge_step: str | None = None) -> HybridLens:
    """A :class:`HybridLens` from a lens spec and its resolved DOE (:func:`raywave.io.resolve_doe`, None: the
    spec has no DOE, a blank one is made). See the module docstring for how the grid is chosen.

    Args:
        doe_pitch: DOE pixel pitch (mm), overriding the file's.
        doe_size: (width, height) mm or one number (square), overriding the file's size / shape (blank DOEs).
        doe_distance: mm from the last vertex to the DOE plane, overriding the file's.
        sensor_pitch: PSF pixel pitch (mm); default the lens's sensor pixel pitch, else the DOE pitch.
        oversample: simulation samples per DOE pixel per axis (default: the file's, else 1).
        fields, wavelengths, depth: the sources the default DOE size must hold (see :func:`beam_half_extent`).
        field_type: "angle" or "object_height": overrides the lens file's field type (how ``fields`` given to
            the hybrid lens are read).
    """
    if any(s.get("doe") is not None for s in spec.get("surfaces", []) if isinstance(s, dict)):
        raise ValueError(f"{source}: a surface carries a 'doe' (a DOE inside the lens): build it with "
                         "raywave.assembly.midsystem.load_midsystem / midsystem_from_spec (issue 46)")
    if sensor_pitch is not None:
        sensor_pitch = pitch_mm(sensor_pitch, "the sensor pitch (sensor_pitch; raywave: --sensor-pitch MM)")
    lens = _spec_lens(spec, field_type, source)
    # a folded, decentred or mirrored lens is sized in its image-space frame (z along the light, like the engine)
    optics = image_space(lens)
    last = float(lens.surfaces[-1].thickness.detach()) * lens.direction_signs()[-1]
    data = doe_data
    info: dict = {"source": "file" if data is not None else "default"}
    distance = _first_distance(data, doe_distance, last, source)
    band = _exit_pupil_edge(optics, stop_edge)  # the edge builds its ripple band (a paraxial trace: once)
    pitch, rule = _doe_pitch(optics, data, doe_pitch, distance, fields, wavelengths, depth, source)
    info.update(rule)
    if doe_distance is None and data is None:  # a beam too wide for the grid: move the default plane to focus
        fit: dict = {}
        distance = fit_doe_distance(optics, distance, pitch, fields, wavelengths, depth, report=fit)
        step = DEFAULT_EDGE_STEP if edge_step is None else edge_step
        if band and step in ("adaptive", "fresnel"):
            # ... but not so near it that the edge's Fresnel step would build the field elsewhere and carry it here
            distance = go_field_distance(optics, distance, pitch, (fields, wavelengths, depth), fit,
                                         sphere_cut=step == "adaptive")
        info.update(fit)
    size = _size_arg(doe_size)
    shape = _doe_shape(optics, data, pitch, doe_pitch, size, distance, (fields, wavelengths, depth, band), source)
    q = int(oversample) if oversample is not None else (data.oversample if data is not None else 1)
    stores_map = data is not None and (data.phase is not None or data.material is not None
                                       or data.levels is not None)
    beam = widest_beam(optics, distance, fields, wavelengths, depth)
    try:
        check_doe_memory(shape, pitch, q, stores_map, source, beam, lens.device)
    except MemoryLimitError as err:  # rays outside the elements: name the option that vignettes them
        raise MemoryLimitError(f"{err}{_clip_apertures_hint(lens)}") from None
    doe = _make_doe(data, shape, pitch, source)
    step = {} if edge_step is None else {"edge_step": edge_step}
    hl = HybridLens(lens, doe, distance, sensor_pitch=sensor_pitch, oversample=q, stop_edge=stop_edge, **step)
    info.update(_doe_summary(data, doe, distance, pitch, q))
    hl.doe_info = info
    return hl


def load_hybrid(path: str | Path, doe_pitch: float | None = None, doe_size=None, doe_distance: float | None = None,
                *, sensor_pitch: float | None = None, oversample: int | None = None, fields=None, wavelengths=None,
                depth=None, field_type: str | None = None, stop_edge: str | None = None,
                edge_step: str | None = None, clip_apertures: bool = False) -> HybridLens:
    """Read a lens file (raywave .json with its ``"doe"``, .zmx with a diffractive last surface, or any lens
    file, which gets a default blank DOE), or a bundled lens by name (``"hybrid_asphere"``, see
    :func:`raywave.lens.build.bundled_lens_path`), into a :class:`HybridLens`. ``clip_apertures``: vignette at
    every surface's semi-diameter (:func:`raywave.lens.build.clip_at_semi_diameters`; default off).

    ``hl.doe_info`` records the DOE used (distance, pitch, shape, size, aperture, phase file, and whether it
    came from the file or the defaults). ``stop_edge``, ``edge_step``: where the accurate field's sharp edge
    sits ("exit_pupil" or "doe"; None: the default, see :class:`HybridLens`) and how the exit-pupil edge reaches
    the DOE plane (None: the default step). See :func:`hybrid_from_spec` and the module docstring for the rules.
    """
    from raywave.io import read_hybrid_spec

    path = resolve_lens_path(path)
    spec, data = read_hybrid_spec(path)
    try:
        if clip_apertures:
            spec = clip_at_semi_diameters(spec)
        return hybrid_from_spec(spec, data, doe_pitch=doe_pitch, doe_size=doe_size, doe_distance=doe_distance,
                                sensor_pitch=sensor_pitch, oversample=oversample, fields=fields,
                                wavelengths=wavelengths, depth=depth, field_type=field_type, source=str(path),
                                stop_edge=stop_edge, edge_step=edge_step)
    except ValueError as err:  # every refusal names the file
        raise with_location(err, path)
