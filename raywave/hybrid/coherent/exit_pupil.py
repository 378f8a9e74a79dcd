"""The stop's sharp edge at the exit pupil (:func:`exit_pupil_field`): the exact angular-spectrum step or the
Fresnel step to the DOE plane, and the per-source choice of ``method="adaptive"`` (:func:`adaptive_edge_step`)."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from typing import NamedTuple

import torch

from raywave.doe.base import DOE, BlankDOE
from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.utils import devices
from raywave.utils.errors import MemoryLimitError
from raywave.utils.memo import recent
from raywave.wave.field import fourier_upsample
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import propagate_window, window_transfer
from raywave.hybrid.coherent.accurate import accurate_field_steps
from raywave.hybrid.coherent.geometry import (WINDOW_BYTES, _common_setup, _empty_field, _footprint, _medium_index,
                                             carry_fft_shape, check_carry_memory, check_window_memory, lit_box)
from raywave.hybrid.coherent.record import DOEField, FieldInfo, StopEdgeWarning
from raywave.hybrid.coherent.sphere_chart import SphereChart, sample_bicubic
from raywave.hybrid.coherent.settings import ChiefRays, FieldSettings, Known, Planes, Source, check_types
from raywave.hybrid.coherent.stop_edge import (EXIT_PUPIL_FAR, MAX_RIPPLE_ZONES, RIPPLE_ZONES, _nu_inner,
                                               _zone_estimate, ripple_band, stop_rim_images)
from raywave.hybrid.coherent.tracing import run_serial


#: largest beam extent (simulation samples a side) on the exit-pupil plane that :func:`exit_pupil_field` accepts
MAX_XP_SAMPLES = 8192
#: ``method="auto"`` of :func:`exit_pupil_field`: the exact angular-spectrum construction up to this beam extent
#: (simulation samples a side on the exit-pupil plane), the Fresnel step beyond
AUTO_ASM_SAMPLES = 3072
#: ``method="adaptive"``: where the Fresnel step's error estimate rejects it and the beam on the exit-pupil plane
#: spans more than "auto"'s :data:`AUTO_ASM_SAMPLES`, the exact construction still runs where its window on its own
#: plane (the beam there and the widest ripple band, samples of its lattice a side: :func:`_exact_step_fits`) spans at
#: most this many samples and fits in memory (~8 GB at its 215 B a sample without a graph): the estimate says the
#: Fresnel step cannot hold 1e-3 there (class J of docs/ray-wave.md: the doublet's sensor 5.5 mm past its focus, a
#: 4 425-sample beam, a 5 053² window with the band: the Fresnel step 1.44e-3 from the converged reference, the exact
#: construction 1.9e-4 in ~12 s and 2.8 GB peak)
FALLBACK_ASM_SAMPLES = 6144
#: the exact construction with the rim's images: the shortest Fresnel step from a rim image to the plane where the
#: angular spectrum takes over, in pixels of that step's Fresnel zone ``sqrt(λ d / n)`` (a step whose zone spans a
#: pixel or two is not resolved by the grid; 16 pixels: 0.48 mm at 1 µm and 0.53 µm)
RIM_STEP_ZONE_PIXELS = 16.0


def exit_pupil_field(lens, doe, source: Source, planes: Planes, chief: ChiefRays,
                     settings: FieldSettings = FieldSettings()) -> DOEField:
    """The accurate DOE-plane field with the stop's sharp edge formed where it belongs: at the exit pupil.

    ``method="fresnel"``: the analytic step. The geometric-optics field is built on the DOE plane
    itself (:func:`accurate_field`, rays traced past the stop's edge without apertures), and the stop's edge,
    instead of being cut sharply there, is multiplied by the knife-edge Fresnel factor of the edge sharp on the
    exit-pupil plane (:func:`stop_edge_factor`, with the local Fresnel length of :func:`_fresnel_scale`: the
    distance from the exit pupil along the ray, the ray's tilt and the wave's local convergence). Costs about
    what the DOE-plane edge costs (a few times), on the DOE's grid, for a beam of any size. Other apertures'
    edges stay on the DOE plane. ``chief_xp`` is not used.

    ``method="asm"``: the exact construction (the reference the Fresnel step is measured against). The
    geometric-optics field is built by :func:`accurate_field` on a plane near the exit pupil (usually a
    virtual plane inside the lens: the rays leaving the last surface travel on straight lines in the image
    medium, so extending them backwards is exact), with the stop's edge formed where it is sharp; it is then
    propagated to the DOE plane by the windowed angular spectrum (:func:`raywave.wave.propagate_window`,
    chief-ray carrier removed), which adds the Fresnel diffraction of the edge between the two planes (that
    the DOE-plane construction, with its hard edge at the DOE, leaves out). Off axis the stop's rim is not
    imaged onto one plane (pupil aberrations: on the bundled asphere at 17.5° its images lie 0.17 mm before to
    0.34 mm after the paraxial exit pupil). With ``rim_images`` (the default) the field is therefore built on a
    plane just beyond every rim image (towards the DOE, at least :data:`RIM_STEP_ZONE_PIXELS` pixels of Fresnel
    zone away), each node's edge diffracting over the short step from its own rim point's image (the Fresnel
    step of ``method="fresnel"``, accurate over such a step), and the angular spectrum carries it the rest of the
    way; without (or where the DOE plane leaves no room for the step): sharp on the paraxial exit-pupil plane
    ``z_xp``. The output window is the DOE-plane footprint plus ``ripple_zones`` Fresnel zones of the farthest
    edge's distance for the edge's ripples, clamped to the DOE grid; the DOE aperture is applied there.
    Differentiable like :func:`accurate_field`.

    Args: ``source`` (:class:`~raywave.hybrid.coherent.settings.Source`: field point, wavelength, depth, field
    type), ``planes`` (the DOE, sensor and exit-pupil planes ``z_xp``, mm), ``chief`` (the chief ray on the DOE
    plane, the sensor and, for "asm", the exit-pupil plane; its entrance-plane point ``uv`` if known),
    ``settings`` (``nodes``, ``oversample``, ``check`` as :func:`accurate_field`; ``ripple_zones``, ``method``,
    ``rim_images``). ``method="asm"`` raises ValueError when the beam on the exit-pupil plane spans more than
    :data:`MAX_XP_SAMPLES` simulation samples (a large beam: the field there would not fit in memory).
    ``method="auto"``: "asm" up to :data:`AUTO_ASM_SAMPLES` samples, else "fresnel". ``method="adaptive"``
    (:class:`~raywave.hybrid.HybridLens`'s default): :func:`adaptive_edge_step` per source, the Fresnel step or, with
    a blank DOE on a spherical wave, the edge cut on the DOE plane (``method="doe"``, exact there: the construction of
    :func:`accurate_field` with the stop's sharp edge on the DOE plane); where the Fresnel step's error estimate for
    a crop reaching ``settings.crop_reach`` mm rejects it (:func:`fresnel_step_estimates`), "asm" where the beam fits
    (:data:`FALLBACK_ASM_SAMPLES` and the memory: :func:`_adaptive_fallback`). The field's ``info.edge_step``
    records the step. ``rim_images``: each node's edge is sharp at its stop-rim point's own image
    (:func:`stop_rim_images`); False: on the exit-pupil plane for every node (both steps as they were before the rim
    images)."""
    return run_serial(exit_pupil_field_steps(lens, doe, source, planes, chief, settings))


def exit_pupil_field_steps(lens, doe, source: Source, planes: Planes, chief: ChiefRays,
                           settings: FieldSettings = FieldSettings(), known: Known = Known()) -> DOEField:
    """:func:`exit_pupil_field` as a generator of trace requests (see :func:`accurate_field_steps`). ``known``
    (:class:`~raywave.hybrid.coherent.settings.Known`): ``bbox``, ``entrance`` as :func:`accurate_field_steps`
    (the DOE-plane footprint and the entrance pupil, when the caller has them for many fields); ``stop_rim``: the
    rim images (:func:`stop_rim_images`) when the caller traced them (None: traced here)."""
    check_types("exit_pupil_field_steps", source, planes, chief, settings)
    field, wavelength, depth, field_type = source.field, source.wavelength, source.depth, source.field_type
    z_xp, z_doe, z_sensor = planes.z_xp, planes.z_doe, planes.z_sensor
    chief_xp, chief_doe, chief_sensor, chief_uv = chief.xp, chief.doe, chief.sensor, chief.uv
    nodes, oversample, check = settings.nodes, settings.oversample, settings.check
    ripple_zones, method, rim_images = settings.ripple_zones, settings.method, settings.rim_images
    bbox, entrance, stop_rim = known.bbox, known.entrance, known.stop_rim
    if z_xp is None:
        raise ValueError("exit_pupil_field: planes.z_xp (the exit-pupil plane, mm) is required")
    # None: each construction widens RIPPLE_ZONES by its edge waves' reach (stop_edge.ripple_band)
    ripple_zones = None if ripple_zones is None else float(ripple_zones)
    p_sim = doe.pitch / oversample
    on_doe = ChiefRays(chief_doe, chief_sensor, uv=chief_uv)  # the chief ray on the DOE plane
    xb = ...
    if method == "adaptive":  # the caller's choice (decided for all its sources at once), else this source's own
        estimate = known.edge_estimate
        method = known.edge_step
        if method is None:
            method = adaptive_edge_step(lens, doe, field, wavelength, depth, z_doe, z_sensor, field_type)
            if method == "fresnel":
                if stop_rim is None:
                    stop_rim = stop_rim_images(lens, field, wavelength, depth, field_type,
                                               bound=(z_doe, EXIT_PUPIL_FAR))
                estimate = fresnel_step_estimates([stop_rim], (wavelength, _medium_index(lens, float(wavelength))),
                                                  (z_doe, z_sensor), settings.crop_reach, p_sim,
                                                  obscuration_fraction(lens))[0]
                method = "fresnel" if fresnel_step_holds(estimate) else "asm"
        if method == "asm":  # the estimate says the Fresnel step cannot hold: the exact construction where it fits
            method, xb = _adaptive_fallback(lens, source, (planes, chief_doe, p_sim),
                                            (estimate, stop_rim, settings.crop_reach))
    if method == "doe":  # exact for this source (see adaptive_edge_step): the edge cut on the DOE plane
        fd = yield from accurate_field_steps(lens, doe, source, Planes(z_doe, z_sensor), on_doe,
                                             replace(settings, virtual=False, stop_plane=None),
                                             Known(bbox, entrance, medium=known.medium))
        return fd.with_info(stop_edge="exit_pupil", edge_step="doe")
    if xb is ...:
        method, xb = _edge_method(lens, field, wavelength, depth, z_xp, p_sim, method)
    z_from, sphere, fallback_rim = None, None, None
    if method == "fresnel" and settings.check:  # the plane too near a caustic: built before it, carried by the ASM
        z_from, est, others = _fallback_planes(lens, source, z_xp, z_doe, known.go_error)
        if z_from is not None:  # the carry's DOE-plane window (its memory: issue 47, h47m)
            fallback_rim = stop_rim if stop_rim is not None else stop_rim_images(
                lens, field, wavelength, depth, field_type, bound=(z_doe, EXIT_PUPIL_FAR))
            plan = _carry_plan(lens, doe, source, (z_xp, z_doe, z_sensor), chief,
                               (settings, fallback_rim, known.medium))
            z0, z_from = z_from, _fallback_fits(lens, source, z_from, z_doe, p_sim, est, others, final=False,
                                                carry=plan)
            if z_from is None:  # no plane fits the plain carry: the scaled one on the fallback's own plane
                z_from, sphere = _scaled_fallback_fits(lens, source, (z0, z_doe, z_sensor), p_sim, est,
                                                       chief_sensor, plan)
        if z_from is not None:
            method = "asm"
    if method == "fresnel":
        rim = None
        if rim_images:
            rim = stop_rim if stop_rim is not None else fallback_rim if fallback_rim is not None else \
                stop_rim_images(lens, field, wavelength, depth, field_type, bound=(z_doe, EXIT_PUPIL_FAR))
        fd = yield from accurate_field_steps(lens, doe, source, Planes(z_doe, z_sensor), on_doe,
                                             replace(settings, virtual=False, stop_plane=z_xp,
                                                     ripple_zones=ripple_zones),
                                             Known(bbox, entrance, rim, reach=known.reach if rim is stop_rim else ...,
                                                   medium=known.medium))
        return fd.with_info(stop_edge="exit_pupil", edge_step="fresnel")
    if method != "asm":
        raise ValueError(f"method must be 'adaptive', 'auto', 'fresnel' or 'asm', got {method!r}")
    _check_xp_beam(xb, p_sim, z_xp)
    _, fld, wl, n, (p, x0, y0, sy, sx), carrier_doe, center, zprop = _common_setup(
        lens, doe, source, (z_doe, z_sensor), chief, oversample, known.medium)
    rim = None
    if rim_images or z_from is not None:
        rim = stop_rim if stop_rim is not None else fallback_rim if fallback_rim is not None else \
            stop_rim_images(lens, field, wavelength, depth, field_type, bound=(z_doe, EXIT_PUPIL_FAR))
    # the construction and its angular spectrum on a lattice m× coarser than the DOE's where the wave's own
    # bandwidth allows (the envelope upsampled to the DOE pitch at the end): its cost falls ~m²
    # the edge waves that land in the crop turn by up to its reach over the distance from the exit pupil
    m = 1 if sphere is not None else _exact_coarsening(rim, chief_doe, (z_xp, z_doe, z_sensor), (wavelength, n), p,
                                                       (settings.crop_reach, z_from is None))
    lattice = doe if m == 1 else CoarseLattice.of(doe.sim_grid(oversample), m, doe.device)
    coarse = settings if m == 1 else replace(settings, oversample=1)
    if sphere is not None:  # the scaled carry: the envelope relative to the sphere on the magnified lattice
        lattice = _scaled_lattice(doe.sim_grid(oversample), sphere, (z_from, z_doe), doe.device)
        coarse = replace(settings, oversample=1, sphere=sphere)
    if z_from is not None:  # the caustic fallback: the Fresnel step to z_from, the angular spectrum beyond
        z_edge, z_far = z_from, _rim_step_plane(rim, z_xp, z_doe, wavelength, n, 0.0)[1]
        chief_xp = chief_doe
    else:
        z_edge, z_far = _rim_step_plane(rim, z_xp, z_doe, wavelength, n, m * p)
    if z_edge is None:  # the edge sharp on the exit-pupil plane
        fx = yield from accurate_field_steps(lens, lattice, source, Planes(z_xp, z_sensor),
                                             ChiefRays(chief_xp, chief_sensor, uv=chief_uv),
                                             replace(coarse, virtual=True, stop_plane=None), Known(medium=known.medium))
    else:  # sharp at every rim point's image, stepped to z_edge (chief ray: a straight line in the image medium)
        fx = yield from accurate_field_steps(lens, lattice, source, Planes(z_edge, z_sensor),
                                             ChiefRays(chief_xp.propagate_to_z(z_edge, n), chief_sensor, uv=chief_uv),
                                             replace(coarse, virtual=True, stop_plane=z_xp,
                                                     ripple_zones=ripple_zones),
                                             Known(stop_rim=rim, medium=known.medium))
    carrier = fx.carrier if sphere is None else carrier_doe  # the chief ray's direction: the same on both planes
    bbox = _footprint(lens, fld, wl, depth, z_doe)  # also checks that the DOE plane lies behind the lens
    step = "fresnel" if z_from is not None else "asm"  # (the caustic fallback: the Fresnel step, carried)
    if bbox is None or _dark(fx):
        return _empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays,
                            "accurate").with_info(stop_edge="exit_pupil", edge_step=step)
    dz = z_doe - (z_xp if z_edge is None else z_edge)
    margin = _window_margin(ripple_zones, rim, (z_doe, z_sensor, z_far), chief_sensor,
                            (wavelength, n, carrier), settings.crop_reach) + 4 * m * p
    sim = doe.sim_grid(oversample)
    box = lit_box(sim, bbox, margin)
    if box is None:
        return _empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays,
                            "accurate").with_info(stop_edge="exit_pupil", edge_step=step)
    grid = sim.window(*box)
    if z_from is not None:  # the caustic fallback's carry: its FFT grid, exactly (issue 47, h47m)
        _check_fallback_carry(fx, grid, (sim, box, m, lens.device), (dz, wavelength, n), sphere, (z_from, z_doe))
    else:  # the exact construction's carry: per sample of the larger window
        (cy, cx), (wy, wx) = fx.grid.shape, grid.shape
        (ny, nx) = (cy, cx) if cy * cx > wy * wx else (wy, wx)
        check_window_memory(ny, nx, p, lens.device, step="asm")
    fin = Field(fx.envelope, fx.grid, float(wavelength), n, carrier)
    if sphere is not None:
        carrier = carrier_doe
        u = scaled_carry(fin, grid, sphere, (z_from, z_doe), carrier_doe)
    elif m == 1:
        u = propagate_window(fin, grid, dz, transfer=edge_transfer(known.transfers, fin, grid, dz)).envelope
    else:
        u = _coarse_propagate(fin, sim, box, dz, m, known.transfers)
    if not _square_coverage(doe):  # (a square DOE's coverage is 1 on its grid: u itself, without two passes)
        u = u * doe.coverage(grid, oversample, device=u.device).to(u.dtype)
    lost, half = _window_loss(fin, u, (sim, bbox, margin))
    return DOEField(Field(u, grid, float(wavelength), n, carrier), box, zprop, center,
                    FieldInfo(fx.rays, "accurate", stop_edge="exit_pupil", edge_step=step, band_clipped=lost,
                              band_half=half, band_total=True))


def _window_loss(carried: Field, u: torch.Tensor, wanted: tuple):
    """``(lost, half)``: the fraction of the carried field's power (``carried``, on its own plane) that the DOE-plane
    window ``u`` (on the DOE's lattice) does not hold, a 0-dim tensor (not read here), and the half width (mm) of the
    square DOE that holds the window asked for; ``(0.0, 0.0)`` where that window, ``wanted`` = ``(sim, bbox,
    margin)`` (:func:`~raywave.hybrid.coherent.geometry.lit_box`'s arguments), lies inside the DOE grid (host numbers:
    nothing computed). The loss counts the geometric beam's clipping too (the caller subtracts
    :func:`~raywave.hybrid.coherent.geometry.doe_clipping`'s): the angular spectrum keeps the power of what it
    carries into the window."""
    sim, (xmin, xmax, ymin, ymax), margin = wanted
    (x0, y0), (sy, sx), p = sim.origin, sim.shape, sim.pitch[0]
    if xmin - margin >= x0 and ymin - margin >= y0 and xmax + margin <= x0 + (sx - 1) * p \
            and ymax + margin <= y0 + (sy - 1) * p:
        return 0.0, 0.0
    half = max(abs(xmin - margin), abs(xmax + margin), abs(ymin - margin), abs(ymax + margin))
    before = torch.view_as_real(carried.envelope.detach()).square().sum() * (carried.grid.pitch[0] ** 2)
    after = torch.view_as_real(u.detach()).square().sum() * (p * p)
    return (1.0 - after / before.clamp_min(1e-300)).clamp_min(0.0), half


#: :func:`_dark`: a field whose largest real or imaginary part is below this has its power summed (its squares may
#: underflow to 0); above it the power is positive
DARK_CHECK_TINY = 1e-150


def _dark(fd) -> bool:
    """Whether the field ``fd``'s power (:attr:`~raywave.hybrid.coherent.record.DOEField.power`) is 0, without its
    window-sized ``|U|`` (a complex modulus: ~10 ms on the 16-level mid-system DOE's 1141 × 1139 construction) and
    without a graph: no sample nonzero, or every sample so small that the power sums to 0 (as it is computed)."""
    with torch.no_grad():
        parts = torch.view_as_real(fd.envelope.detach())
        top = float(parts.abs().max()) if parts.numel() else 0.0
        return top == 0.0 or (top < DARK_CHECK_TINY and float(fd.power) == 0.0)


def _square_coverage(doe) -> bool:
    """Whether ``doe``'s :meth:`~raywave.doe.DOE.coverage` is 1 on every window of its grid: a square aperture and
    the base class's coverage."""
    return type(doe).coverage is DOE.coverage and getattr(doe, "aperture", None) == "square"


#: the exact construction's lattice is coarsened (:func:`asm_coarsening`) while its pitch stays within this fraction
#: of the Nyquist pitch of the wave's envelope (the rim rays' largest direction-cosine difference from the chief
#: ray's, whose carrier the envelope has removed): ½ keeps the envelope's spectrum in the inner half of the coarse
#: band, which the Fourier upsampling to the DOE pitch then interpolates exactly
ASM_NYQUIST_FRACTION = 0.5
#: the most the exact construction's lattice is coarsened
MAX_ASM_COARSENING = 8
#: coarse samples added on each side of the DOE-plane window before the Fourier upsampling, the outer ones tapered
#: to 0 (a raised cosine): the upsampling's periodic window then has no jump at its edges
ASM_UPSAMPLE_PAD = 8


def asm_coarsening(rim, chief_doe, wavelength: float, n: float, p: float, tail: float = 0.0) -> int:
    """``m`` ≥ 1: how many DOE-lattice samples (pitch ``p`` mm) one sample of the exact construction's lattice spans
    (:func:`exit_pupil_field`, ``method="asm"`` and the caustic fallback; issue 46: a mid-system DOE's strongest order
    at 1 µm spent ≥ 90 % of its PSF's time on a 2307² field its phase needs only a quarter of): the largest integer
    with ``m·p ≤`` :data:`ASM_NYQUIST_FRACTION` · ``λ/(2 n Δ)``, ``Δ`` the largest difference of a rim ray's
    direction cosine (:class:`~raywave.hybrid.coherent.stop_edge.RimImages` ``directions``, the image medium) from
    the chief ray's on the DOE plane (``chief_doe``: the envelope's carrier), plus ``tail``, at most
    :data:`MAX_ASM_COARSENING`; 1 without rim rays (the DOE's own lattice, as before). ``wavelength`` µm, ``n`` the
    image medium's index. ``tail``: the largest further turn (direction cosine) of the stop edge's waves that land in
    the PSF crop (its reach on the sensor over the distance from the exit pupil, :class:`~raywave.hybrid.coherent.
    settings.FieldSettings` ``crop_reach``): the rim rays' spread alone is the geometric spot's, and the lattice it
    allows drops the edge waves of the far tail (issue 46: lens A alone, F/12.5, a 128-pixel crop of 2 µm, the DOE
    plane 3 mm before the focus: 1.1e-2 off the Rayleigh–Sommerfeld integral at 90–126 µm on the 3× lattice, 2.2e-3
    on the 2× one that the crop's reach asks for; tests/test_far_tails.py)."""
    dirs = getattr(rim, "directions", None) if rim is not None else None
    if dirs is None or MAX_ASM_COARSENING <= 1:
        return 1
    c = chief_doe.d.detach()[:2].to(dirs.dtype)
    spread = float((dirs.detach()[:, :2] - c).abs().max()) + float(tail)  # (one host read)
    if not math.isfinite(spread) or spread <= 0.0:
        return 1
    p_max = ASM_NYQUIST_FRACTION * wavelength * 1e-3 / (2.0 * n * spread)
    return max(1, min(MAX_ASM_COARSENING, int(math.floor(p_max / p + 1e-9))))


class CoarseLattice:
    """A virtual plane's simulation lattice every ``m``-th sample of a DOE's (``fine``: its simulation
    :class:`~raywave.wave.Grid`), the same origin, ``m`` times its pitch, extended without bound: what the exact
    construction reads of a DOE (``pitch``, ``sim_origin``, ``sim_shape``, ``sim_grid`` at ``oversample`` 1,
    ``device``) when :func:`asm_coarsening` allows a coarser grid."""

    def __init__(self, origin, pitch: float, shape, device):
        self.origin, self.pitch, self.shape, self.device = tuple(origin), float(pitch), tuple(shape), device

    @classmethod
    def of(cls, fine: Grid, m: int, device=None) -> "CoarseLattice":
        sy, sx = fine.shape
        return cls(fine.origin, fine.pitch[0] * m, (-(-sy // m), -(-sx // m)), device)

    def sim_origin(self, oversample: int = 1):
        return self.origin

    def sim_shape(self, oversample: int = 1):
        return self.shape

    def sim_grid(self, oversample: int = 1) -> Grid:
        return Grid(self.origin, self.pitch, self.shape)


def _check_fallback_carry(fx, grid: Grid, lattice: tuple, step: tuple, sphere, planes: tuple) -> None:
    """Refuse (:class:`~raywave.utils.errors.MemoryLimitError`) the caustic fallback's carry of the construction
    ``fx`` (:class:`~raywave.hybrid.coherent.record.DOEField` on the earlier plane) onto the DOE-plane window
    ``grid`` before anything of its size is allocated, from its exact FFT grid (:func:`~raywave.hybrid.coherent.
    geometry.carry_fft_shape`) and :func:`~raywave.hybrid.coherent.geometry.carry_bytes`. ``lattice`` = ``(sim, box,
    m)``: the DOE's simulation grid, the window's box on it and the coarsening (m > 1: the carry onto the coarse
    window of :func:`_coarse_window`, plus the Fourier upsampling to the DOE pitch at :data:`~raywave.hybrid.coherent.
    geometry.WINDOW_BYTES` "fallback" a fine sample, not measured) and the device; ``step`` = ``(dz mm, wavelength
    µm, n)``; ``sphere`` the scaled carry's point (None: the plain carry), ``planes`` = ``(z_from, z_doe)`` mm."""
    sim, box, m, device = lattice
    dz, wavelength, n = step
    n_from, pitch = tuple(fx.grid.shape), fx.grid.pitch[0]
    if sphere is not None:  # scaled_carry's propagation: the envelope relative to the sphere, the scaled distance
        r1, r2 = sphere[2] - planes[0], sphere[2] - planes[1]
        fft = carry_fft_shape(n_from, grid.shape, pitch, dz * r1 / r2, (wavelength, n))
        check_carry_memory(n_from, grid.shape, fft, pitch, device, scaled=True)
        return
    out, extra = grid, 0.0
    if m > 1:
        out = _coarse_window(sim, box, m)
        extra = WINDOW_BYTES[("fallback", torch.is_grad_enabled())] * float(grid.shape[0]) * float(grid.shape[1])
    fft = carry_fft_shape(n_from, out.shape, pitch, dz, (wavelength, n), fx.carrier)
    check_carry_memory(n_from, out.shape, fft, pitch, device, extra=extra)


def _coarse_window(sim: Grid, box, m: int) -> Grid:
    """The coarse window (``sim``'s origin, ``m`` times its pitch) of :func:`_coarse_propagate`: the coarse samples
    that cover the box ``(iy0, iy1, ix0, ix1)`` of the DOE's simulation lattice ``sim`` plus
    :data:`ASM_UPSAMPLE_PAD` a side, an odd count a side."""
    iy0, iy1, ix0, ix1 = box
    pad = ASM_UPSAMPLE_PAD

    def span(i0, i1):  # coarse indices covering fine [i0, i1) plus the pad, an odd count
        j0, j1 = i0 // m - pad, -(-(i1 - 1) // m) + 1 + pad
        return j0, j1 + (1 - (j1 - j0) % 2)

    (jy0, jy1), (jx0, jx1) = span(iy0, iy1), span(ix0, ix1)
    return Grid(sim.position(jy0 * m, jx0 * m), m * sim.pitch[0], (jy1 - jy0, jx1 - jx0))


def _coarse_propagate(field: Field, sim: Grid, box, dz: float, m: int, transfers=None) -> torch.Tensor:
    """The envelope (complex128 on the window ``box`` ``(iy0, iy1, ix0, ix1)`` of the DOE's simulation lattice
    ``sim``) of ``field`` (on the coarse lattice: ``sim``'s origin, ``m`` times its pitch) propagated ``dz`` mm:
    :func:`~raywave.wave.propagation.propagate_window` onto the coarse window that covers ``box`` plus
    :data:`ASM_UPSAMPLE_PAD` samples a side (an odd number a side: no Nyquist term), those tapered to 0, then
    :func:`~raywave.wave.field.fourier_upsample` by ``m`` and the crop to ``box``. ``transfers``: the engine's memo
    of the step's transfer functions (:func:`edge_transfer`), or None."""
    iy0, iy1, ix0, ix1 = box
    pad = ASM_UPSAMPLE_PAD
    out = _coarse_window(sim, box, m)
    (jy0, jx0), (ny_c, nx_c) = (iy0 // m - pad, ix0 // m - pad), out.shape  # (its first coarse sample, its size)
    uc = propagate_window(field, out, dz, transfer=edge_transfer(transfers, field, out, dz)).envelope
    taper = [_edge_taper(n_, pad, uc.device) for n_ in (ny_c, nx_c)]
    up = fourier_upsample(uc * (taper[0][:, None] * taper[1][None, :]).to(uc.dtype), m)
    oy, ox = iy0 - jy0 * m, ix0 - jx0 * m
    return up[oy:oy + iy1 - iy0, ox:ox + ix1 - ix0]


#: how many of the exact exit-pupil step's window transfer functions an engine keeps (:func:`edge_transfer`): each
#: is the band of a wide FFT (the 16-level mid-system DOE of benchmarks/psf_midsystem.py: 1752×1767, 50 MB)
EDGE_TRANSFER_MEMO = 2


def edge_transfer(memo, field: Field, out: Grid, dz: float):
    """The window transfer function (:func:`~raywave.wave.propagation.window_transfer`) of the exact exit-pupil
    step, ``field`` (its grid, wavelength, index and carrier) propagated ``dz`` mm onto ``out``, from ``memo`` (an
    ``OrderedDict``: the engine's, its :data:`EDGE_TRANSFER_MEMO` most recent geometries) when this geometry's is
    there, else built and kept; None without a memo (:func:`~raywave.wave.propagation.propagate_window` builds it).
    The key is the geometry's exact numbers, so a hit is the function that would be built (the same values, bit for
    bit): a lens evaluated again unchanged (a benchmark, a PSF map's second pass) skips the band's ~3·10⁶
    square roots and phasors (issue 46: a third of the 16-level mid-system DOE's PSF); a lens that moved misses."""
    if memo is None:
        return None
    g = field.grid
    key = (tuple(g.shape), tuple(float(v) for v in g.origin), tuple(float(v) for v in g.pitch),
           tuple(float(v) for v in out.origin), tuple(out.shape), float(field.wavelength), float(dz),
           float(field.n), tuple(float(v) for v in field.carrier), str(field.envelope.device))
    return recent(memo, key, lambda: window_transfer(field, out, dz), EDGE_TRANSFER_MEMO)


def _edge_taper(n: int, pad: int, device) -> torch.Tensor:
    """(n,) float64: 1 except the outer ``pad`` samples at either end, a raised cosine from 1 down to 0 (the
    outermost sample 0)."""
    w = torch.ones(n, dtype=torch.float64, device=device)
    if pad > 0:
        ramp = 0.5 - 0.5 * torch.cos(math.pi * torch.arange(pad, dtype=torch.float64, device=device) / pad)
        w[:pad] = ramp
        w[n - pad:] = ramp.flip(0)
    return w


def _window_margin(ripple_zones, rim, zs, chief_sensor, medium, crop_reach: float = 0.0) -> float:
    """The DOE-plane window's margin (mm) beyond the footprint for the exact construction and the caustic fallback:
    ``ripple_zones`` Fresnel zones of the plain distance ``z_doe − z_far`` (``zs = (z_doe, z_sensor, z_far)``; the
    farthest rim image), or with the default band (None) :data:`RIPPLE_ZONES` of them, or the reach rule's wider band
    (:func:`ripple_band`) in the converging beam's zones (:func:`_zone_estimate`: near a caustic the plain distance's
    zone overstates it ~3×, and a 12-zone band of it would ask for a 17 GiB window on the double Gauss at full field),
    whichever is wider. ``medium`` ``(wavelength µm, n, carrier (α, β))``; ``crop_reach`` (mm) the PSF crop's
    half-diagonal (0: unknown), for the band of a crop inside the rim rays' ring (:func:`ripple_band`)."""
    z_doe, z_sensor, z_far = zs
    wavelength, n, carrier = medium
    plain = math.sqrt(wavelength * 1e-3 * abs(z_doe - z_far) / n)
    if ripple_zones is not None:
        return ripple_zones * plain
    zones = ripple_band(rim, z_doe, z_sensor, chief_sensor.o[:2].detach(), wavelength * 1e-3 / n,
                        crop_reach=crop_reach)
    margin = RIPPLE_ZONES * plain
    if zones > RIPPLE_ZONES:
        margin = max(margin, zones * _zone_estimate(wavelength, n, z_doe - z_far, z_sensor - z_far, *carrier))
    return margin


def _rim_step_plane(rim, z_xp: float, z_doe: float, wavelength: float, n: float, p: float):
    """``(z_edge, z_far)`` mm for the exact construction: ``z_edge`` the plane beyond every rim image of ``rim``
    (:func:`stop_rim_images`; towards the DOE plane ``z_doe``) by the step whose Fresnel zone spans
    :data:`RIM_STEP_ZONE_PIXELS` pixels of ``p`` mm, or None (no rim images, a rim image at or beyond the DOE
    plane, or no room for the step before it: the edge stays on the exit-pupil plane ``z_xp``); ``z_far`` the edge
    farthest from the DOE plane (its ripples spread the most)."""
    if rim is None:
        return None, z_xp
    zr = rim[1].detach()
    s = 1.0 if z_doe >= z_xp else -1.0
    near = float(zr.max()) if s > 0 else float(zr.min())
    far = float(zr.min()) if s > 0 else float(zr.max())
    step = (RIM_STEP_ZONE_PIXELS * p) ** 2 * n / (wavelength * 1e-3)
    z_edge = max(near, z_xp) + step if s > 0 else min(near, z_xp) - step
    if not math.isfinite(z_edge) or s * (z_doe - z_edge) < step:
        return None, z_xp
    return z_edge, (min(far, z_xp) if s > 0 else max(far, z_xp))


def _exact_coarsening(rim, chief_doe, zs: tuple, medium: tuple, p: float, how: tuple) -> int:
    """The exact construction's coarsening ``m`` (:func:`asm_coarsening` with the edge waves that land in the crop:
    ``crop_reach`` mm over the exit pupil's distance from the sensor), lowered where its rim step needs room
    (:func:`_room_for_rim_step`, with ``room``; not for the caustic fallback, whose plane is its own). ``zs`` =
    ``(z_xp, z_doe, z_sensor)`` mm, ``medium`` = ``(wavelength µm, n)``, ``p`` the DOE's simulation pitch mm, ``how``
    = ``(crop_reach, room)``."""
    (z_xp, z_doe, z_sensor), (wavelength, n), (crop_reach, room) = zs, medium, how
    far = abs(z_sensor - z_xp)
    tail = crop_reach / far if crop_reach > 0 and far > 0 else 0.0
    m = asm_coarsening(rim, chief_doe, wavelength, n, p, tail)
    return _room_for_rim_step(m, rim, (z_xp, z_doe), medium, p) if room else m


def _room_for_rim_step(m: int, rim, zs: tuple, medium: tuple, p: float) -> int:
    """The exact construction's coarsening ``m`` (:func:`asm_coarsening`) lowered until its rim step fits between the
    rim images ``rim`` and the DOE plane (:func:`_rim_step_plane` at the pitch ``m·p`` mm; the step grows as
    ``(m p)²``), else 1: with no room for the step the edge is cut sharp on the exit-pupil plane, and a sharp edge on a
    coarse lattice aliases its edge waves (tests/test_ideal_lens_truth.py's lens with its sensor 8 mm past the focus:
    1.4e-3 from the wave truth with the 2 µm lattice's sharp edge, 5.0e-4 with the DOE's 1 µm lattice and its rim
    step). ``zs`` = ``(z_xp, z_doe)`` mm, ``medium`` = ``(wavelength µm, n)``."""
    while m > 1 and rim is not None and _rim_step_plane(rim, *zs, *medium, m * p)[0] is None:
        m -= 1
    return m


def _beam_fits(lens, xb, p_sim: float, limit: int) -> bool:
    """Whether the exact construction's beam ``xb`` ``(xmin, xmax, ymin, ymax)`` mm (None: none) spans at most
    ``limit`` simulation samples of ``p_sim`` mm a side and its window (the beam 1.2× wide) fits in memory
    (:func:`~raywave.hybrid.coherent.geometry.check_window_memory`, as the construction will check it)."""
    if xb is None or max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > limit:
        return False
    return _window_fits(lens, xb, p_sim, "asm")


def _window_fits(lens, xb, p_sim: float, step: str) -> bool:
    """Whether the window of the beam ``xb`` ``(xmin, xmax, ymin, ymax)`` mm (1.2× wide) at ``p_sim`` mm a sample
    fits in memory for ``step`` (:func:`~raywave.hybrid.coherent.geometry.check_window_memory`, as the construction
    will check it)."""
    try:
        check_window_memory(math.ceil(1.2 * (xb[3] - xb[2]) / p_sim), math.ceil(1.2 * (xb[1] - xb[0]) / p_sim),
                            p_sim, lens.device, step=step)
    except MemoryLimitError:
        return False
    return True


def _adaptive_fallback(lens, source: Source, where: tuple, edge: tuple):
    """``(method, xb)`` for a source of ``method="adaptive"`` whose Fresnel step the error estimate
    (:func:`fresnel_step_estimates`) rejects: "asm" where the beam on the exit-pupil plane fits the exact construction
    ("auto"'s :data:`AUTO_ASM_SAMPLES` simulation samples a side and its window in memory, or beyond that
    :func:`_exact_step_fits`), else "fresnel" with a :class:`StopEdgeWarning` naming the estimate, where it failed on
    the crop's reach (a failed curvature ratio is warned by the construction itself: :data:`~raywave.hybrid.coherent.
    accurate.EDGE_CURVATURE_LIMIT`, naming ``edge_step="asm"``). ``where`` = ``(planes, chief ray on the DOE plane,
    simulation pitch mm)``, ``edge`` = ``(estimate, rim images or None, crop_reach mm)``."""
    planes, chief_doe, p_sim = where
    estimate = edge[0]
    method, xb = _edge_method(lens, source.field, source.wavelength, source.depth, planes.z_xp, p_sim, "asm")
    if _beam_fits(lens, xb, p_sim, AUTO_ASM_SAMPLES) or (
            _beam_fits(lens, xb, p_sim, FALLBACK_ASM_SAMPLES) and _exact_step_fits(lens, source, where, edge[1:])):
        return "asm", xb
    if estimate is not None and estimate[0] > estimate[1]:
        fld = [round(float(v), 6) for v in torch.as_tensor(source.field).reshape(-1).tolist()]
        warnings.warn(f"field {fld} at {float(source.wavelength):g} µm: {describe_estimate(estimate)}: the PSF crop "
                      "reaches beyond the edge waves the Fresnel edge step holds, and the exact construction does not "
                      f"fit (its window spans over {FALLBACK_ASM_SAMPLES} samples on its plane, or over the "
                      "memory): kept the Fresnel step; take a smaller crop (ks) (on a sensor far from "
                      "the focus, where the crop lies inside the rim rays' ring, a DOE plane nearer the exit pupil "
                      "instead), or a coarser DOE pitch; where only memory stopped it, a higher limit "
                      "(RAYWAVE_MEMORY_LIMIT / raywave --memory-limit) lets the exact construction run",
                      StopEdgeWarning,
                      stacklevel=4)
    return "fresnel", None


def _exact_step_fits(lens, source: Source, where: tuple, edge: tuple) -> bool:
    """Whether the exact construction's window on its own plane (the rim step's plane, :func:`_rim_step_plane`, else
    the exit pupil's), on its lattice (:func:`_exact_coarsening`), spans at most :data:`FALLBACK_ASM_SAMPLES` a side
    and fits in memory: the beam there (one trace) plus, on the rim step's plane, the widest ripple band
    (:data:`~raywave.hybrid.coherent.stop_edge.MAX_RIPPLE_ZONES` zones of :data:`RIM_STEP_ZONE_PIXELS` samples) on
    both sides, at least 1.2× the beam. The beam on the exit-pupil plane understates it where the rim images lie far
    from it (a random lens of tests/test_random_lenses.py: 5 883 samples there, a 9 632² window on the step's plane).
    ``where`` = ``(planes, chief ray on the DOE plane, simulation pitch mm)``, ``edge`` = ``(rim images or None:
    traced here, crop_reach mm)``."""
    (planes, chief_doe, p_sim), (rim, crop_reach) = where, edge
    z_xp, z_doe, z_sensor = planes.z_xp, planes.z_doe, planes.z_sensor
    wl = float(source.wavelength)
    n = _medium_index(lens, wl)
    if rim is None:
        rim = stop_rim_images(lens, source.field, wl, source.depth, source.field_type, bound=(z_doe, EXIT_PUPIL_FAR))
    q = p_sim * _exact_coarsening(rim, chief_doe, (z_xp, z_doe, z_sensor), (wl, n), p_sim, (crop_reach, True))
    z_edge = _rim_step_plane(rim, z_xp, z_doe, wl, n, q)[0]
    _, xb = _edge_method(lens, source.field, wl, source.depth, z_xp if z_edge is None else z_edge, q, "asm")
    if xb is None:
        return True
    band = 0.0 if z_edge is None else MAX_RIPPLE_ZONES * RIM_STEP_ZONE_PIXELS * q
    ny, nx = (math.ceil(max(1.2 * w, w + 2 * band) / q) for w in (xb[3] - xb[2], xb[1] - xb[0]))
    if max(ny, nx) > FALLBACK_ASM_SAMPLES:
        return False
    try:
        check_window_memory(ny, nx, q, lens.device, step="asm")
    except MemoryLimitError:
        return False
    return True


def _edge_method(lens, field, wavelength: float, depth, z_xp: float, p_sim: float, method: str):
    """``(method, xb)``: the edge step ``method`` with "auto" resolved ("asm" up to :data:`AUTO_ASM_SAMPLES`
    simulation samples of ``p_sim`` mm across the beam on the exit-pupil plane ``z_xp`` mm, else "fresnel"), and
    the beam's footprint ``(xmin, xmax, ymin, ymax)`` mm there (traced for "auto" and "asm"; None otherwise or
    when every ray is vignetted) for the field (2,) at ``wavelength`` µm."""
    xb = None
    if method in ("auto", "asm"):
        xb = _footprint(lens, torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(2),
                        torch.tensor([float(wavelength)], dtype=torch.float64, device=lens.device), depth, z_xp,
                        virtual=True)
    if method == "auto":
        big = xb is not None and max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > AUTO_ASM_SAMPLES
        method = "fresnel" if big else "asm"
    return method, xb


#: :func:`go_fallback_plane`: the largest geometric-optics phase error (rad, :func:`go_phase_error`) accepted on the
#: DOE plane before the field is built on an earlier plane and carried there by the angular spectrum. Measured on 22
#: cases (benchmarks/results/caustic_estimate_2026-11-29_p47.json; rel L1 of the default from converged references):
#: the double Gauss on axis 3.2e-4 rad (1.07e-3 rel L1; with the fallback 2.9e-4) and at 0.7 field 2.0e-4 (2.46e-3;
#: 8.3e-4); every case within 1e-3 has at most 8.6e-5 (the F/1.3 asphere at full field, 3.7e-4); ideal lenses < 1e-14.
#: The double Gauss at full field, 1.06e-4 (2.73e-3), was left below it (1.25e-4 until 2026-11-29, h47b) while the
#: fallback did not mend it (1.83e-3 / 1.98e-3 built 4 / 8 mm before its plane); with the ripple band's reach rule
#: (:func:`~raywave.hybrid.coherent.stop_edge.ripple_band`) and against the reference whose edge sits at the rim
#: images it does (6.8e-4 against 1.40e-3 on the plane itself; benchmarks/results/stop_edge_references_xiv_h47b.json),
#: so the tolerance now sits between 8.6e-5 and 1.06e-4. The estimate ranks the cases; it does not predict the
#: error's size (error / estimate 3 to 30)
GO_PHASE_TOL = 1.0e-4
#: the fallback's plane: where :func:`go_phase_error` has fallen to this fraction of :data:`GO_PHASE_TOL`
GO_FALLBACK_FRACTION = 0.5
#: :func:`go_phase_error`'s pupil grid (a side, over 1.1 × the stop's radius) and planes from the exit pupil
GO_GRID = 32
GO_PLANES = 32


def go_phase_error(lens, source: Source, z_xp: float, z_doe: float):
    """How far the geometric-optics field on the planes between the exit pupil ``z_xp`` and ``z_doe`` (mm from the
    first vertex) is from the wave, for one source: ``(z (P,) mm, error (P,) rad)``, ``error`` the largest
    ``|δφ − mean δφ|`` over the stop of the second-order (diffraction) term of the eikonal that geometric optics
    drops,

        ``δφ(p, z) = (1/2k) ∫_{z_xp}^{z} ∇⊥²A / A dz'``,  ``A = |det ∂x/∂p|^(-1/2)``,  ``k = 2π n / λ``,

    along each ray p of a :data:`GO_GRID`² stop grid (traced once, apertures off, straight lines in the image
    medium; the paraxial wave equation's phase correction, the next term of the WKB series). A plane near a
    caustic, where the rays' density varies fast on the scale of a Fresnel zone, has a large ``δφ``: it grows as
    1/distance towards the rays' local foci. A sphere (an ideal lens) has ``δφ`` 0 (to rounding). Cost: one trace of
    1 024 rays (and one with apertures, for the lit ones) and :data:`GO_PLANES` planes of finite differences.
    ``error`` 0 where no ray is traced. Many sources at once: :func:`go_phase_errors`."""
    fld = torch.as_tensor(source.field, dtype=torch.float64, device=lens.device).reshape(1, 2)
    zs, err = go_phase_errors(lens, fld, [float(source.wavelength)], source.depth, source.field_type,
                              ([z_xp], z_doe))
    return zs[0], err[0, 0]


#: :func:`go_phase_errors` evaluates the finite differences of this many sources at a time (memory: ~15 arrays of
#: GO_PLANES × GO_GRID² samples per source)
GO_SOURCE_BLOCK = 16
#: :data:`GO_SOURCE_BLOCK` on an accelerator (every op a kernel launch, memory aplenty: ~4 MB a source): a call's
#: sources in one block (issue 43: a 10×10×3 map's 75 sources dispatched ~150 ops a block of 16)
GO_SOURCE_BLOCK_ACCELERATOR = 512


def go_phase_errors(lens, fields: torch.Tensor, wls: list[float], depth, field_type, planes,
                    chief: tuple | None = None, band_fold: bool = False):
    """:func:`go_phase_error` of the sources ``fields`` (F, 2) × ``wls`` (W wavelengths, µm) from one trace of all
    their stop grids (F·W·1 024 rays, apertures off, and one with apertures): ``planes`` = ``(z_xps, z_doe)``, the
    exit-pupil plane of each wavelength (W,) and the DOE plane (mm); ``chief``: these sources'
    :func:`~raywave.lens.sources.chief_aim` when the caller shares it. Returns ``(zs (W, P) mm, error (F, W, P)
    rad)``; with ``band_fold`` (the engine's caustic fallback) ``inf`` on the planes where the rays past the stop's
    rim fold (or are lost) within the edge's ripple band (:func:`_band_cut`; one more trace of F·W·992 rays)."""
    dev = lens.device
    z_xps, z_doe = [float(z) for z in planes[0]], float(planes[1])
    ext, ng = 1.1, GO_GRID
    g = ((torch.arange(ng, dtype=torch.float64, device=dev) + 0.5) / ng * 2 - 1) * ext
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    f = fields.reshape(-1, 2).to(device=dev, dtype=torch.float64)
    nf, nw = f.shape[0], len(wls)
    # with band_fold (and an unfolded lens) the band's rays (:func:`_band_cut`) are aimed and traced with the stop
    # grid's, after them (issue 47: one aiming and one trace instead of two; each ray is aimed and traced on its own)
    band = _band_pupil(dev) if band_fold and not lens.is_folded else None
    ngo = ng * ng
    pupil = (gx.flatten(), gy.flatten())
    if band is not None:
        pupil = (torch.cat([pupil[0], band[0]]), torch.cat([pupil[1], band[1]]))
    band_rays = None
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # a diagnostic trace, apertures off
        rays = point_source_rays(lens, f, list(wls), pupil=pupil, aim="full", depth=depth,
                                 field_type=field_type or lens.field_type, chief=chief)
        lit = None
        if lens.is_folded:
            out = lens.trace(rays, apertures=False)
        else:  # one trace: a ray passes every aperture where it passes each on its own path (issue 43: not two)
            out, rec = lens.trace(rays, apertures=False, record=True)
            lit = out.valid
            for i, srf in enumerate(lens.surfaces):
                if srf.aperture is not None and srf.interaction.kind != "coordinate_break":
                    lit = lit & srf.aperture.contains(*rec.points[i + 1][:2])
        if lit is None:
            lit = lens.trace(rays).valid
        o, d, valid = out.o, out.d, out.valid  # (F, W, N, 3), (F, W, N)
        if band is not None:  # the stop grid's rays first, then the band's
            band_rays = (o[:, :, ngo:], d[:, :, ngo:], valid[:, :, ngo:])
            o, d, valid, lit = o[:, :, :ngo], d[:, :, :ngo], valid[:, :, :ngo], lit[:, :, :ngo]
        lit = lit.reshape(nf, nw, ng, ng)  # the rays every aperture passes (inside the stop)
        n = lens.surfaces[-1].material.n(torch.tensor(list(wls), dtype=torch.float64, device=dev))  # (W,)
        tan = (d[..., :2] / d[..., 2:]).reshape(nf, nw, ng, ng, 2)
        x0 = (o[..., :2] + (d[..., :2] / d[..., 2:]) * (z_doe - o[..., 2:])).reshape(nf, nw, ng, ng, 2)
        bad = ~(valid.reshape(nf, nw, ng, ng) & torch.isfinite(x0).all(-1) & torch.isfinite(tan).all(-1))
        x0 = x0.masked_fill(bad[..., None], math.nan)
        u = torch.linspace(0.0, 1.0, GO_PLANES + 1, dtype=torch.float64, device=dev)
        zx = torch.tensor(z_xps, dtype=torch.float64, device=dev)[:, None]
        zs = zx + (z_doe - zx) * (1 - (1 - u) ** 2)  # (W, P), denser towards the DOE plane
        k = 2 * math.pi * n / (torch.tensor(list(wls), dtype=torch.float64, device=dev) * 1e-3)  # (W,)
        inside = (gx**2 + gy**2 <= 1.0)
        # every source's planes, a block of sources at a time (flattened F·W)
        src_x0, src_tan = x0.reshape(nf * nw, ng, ng, 2), tan.reshape(nf * nw, ng, ng, 2)
        src_ok = (lit & inside).reshape(nf * nw, ng, ng)
        wi = torch.arange(nw, device=dev).repeat(nf)  # each flattened source's wavelength
        blk = GO_SOURCE_BLOCK_ACCELERATOR if devices.accelerator(dev) else GO_SOURCE_BLOCK
        if nf * nw <= blk:  # one block: no slices, no concatenation
            err = _go_error_block(src_x0, src_tan, src_ok, zs[wi], k[wi], (z_doe, 2 * ext / ng))
        else:
            err = torch.cat([_go_error_block(src_x0[i:i + blk], src_tan[i:i + blk], src_ok[i:i + blk],
                                             zs[wi[i:i + blk]], k[wi[i:i + blk]], (z_doe, 2 * ext / ng))
                             for i in range(0, nf * nw, blk)])
        err = err.reshape(nf, nw, -1)
        if band_fold:
            cut = _band_cut(lens, f, list(wls), (depth, field_type or lens.field_type, chief), zs, z_xps, band_rays)
            err = err.masked_fill(cut, math.inf)
    return zs, err


#: :func:`_band_cut`'s rays: this many azimuths around the stop's rim, at these fractions of its radius
BAND_AZIMUTHS = 32
BAND_RADII = tuple(1.0 + 0.02 * i for i in range(31))


def _band_pupil(dev) -> tuple:
    """The stop coordinates ``(px, py)`` (:data:`BAND_AZIMUTHS` · len(:data:`BAND_RADII`),) in stop radii of
    :func:`_band_cut`'s rays, azimuth-major."""
    phi = torch.arange(BAND_AZIMUTHS, dtype=torch.float64, device=dev) * (2 * math.pi / BAND_AZIMUTHS)
    rad = torch.tensor(BAND_RADII, dtype=torch.float64, device=dev)
    return (rad[None, :] * torch.cos(phi)[:, None]).flatten(), (rad[None, :] * torch.sin(phi)[:, None]).flatten()


def _band_cut(lens, f: torch.Tensor, wls: list, how: tuple, zs: torch.Tensor, z_xps: list,
              traced: tuple | None = None) -> torch.Tensor:
    """Whether the ripple band of the stop's edge (:data:`~raywave.hybrid.coherent.stop_edge.RIPPLE_ZONES` Fresnel
    zones outside its shadow) meets a fold of the rays past the stop's rim, or rays that cannot be traced, on each
    plane ``zs`` (W, P) mm: ``(F, W, P)`` bool for the sources ``f`` (F, 2) × ``wls`` (µm; ``how`` = ``(depth,
    field type, chief aim)``, ``z_xps`` the exit-pupil planes (W,) mm). Per azimuth of :data:`BAND_AZIMUTHS` around
    the rim, the rays through :data:`BAND_RADII` of the stop's radius (apertures off, straight lines after the
    lens): their distance ``s`` outwards from the rim ray's landing (along the landing of the next ray out) grows
    until they fold (or a ray is lost); the band is cut where they do, at a reach below ``RIPPLE_ZONES · sqrt(λ_m L)``,
    ``L = d (z_f − z)/(z_f − z_xp)`` (``d = z − z_xp``; ``z_f`` where the rim ray and the next one out cross: the
    wave's local focus across the edge). The Fresnel step's factor multiplies the geometric field continued past
    the rim (its amplitude singular at the fold, none beyond it) over the band: the Olympus M.Zuiko 12 mm at 0.7
    field, rays folding 0.07 mm (~2 zones) outside the shadow 2.2 mm before the sensor: 1.84e-3 from the converged
    reference on that plane, 3.4e-4 – 5.5e-4 built 3.9 – 1.9 mm before it and carried by the angular spectrum.
    ``traced``: the band rays after the lens ``(o, d, valid)`` (F, W, A·K, …) when the caller traced them
    (:func:`go_phase_errors`, with its stop grid's), else aimed and traced here."""
    dev = f.device
    depth, field_type, chief = how
    nf, nw, na, nk = f.shape[0], len(wls), BAND_AZIMUTHS, len(BAND_RADII)
    if traced is None:
        rays = point_source_rays(lens, f, wls, pupil=_band_pupil(dev), aim="full", depth=depth,
                                 field_type=field_type, chief=chief)
        out = lens.trace(rays, apertures=False)
        traced = (out.o, out.d, out.valid)
    o, d = traced[0].reshape(nf * nw, na, nk, 3), traced[1].reshape(nf * nw, na, nk, 3)
    wi = torch.arange(nw, device=dev).repeat(nf)  # each flattened source's wavelength
    n = lens.surfaces[-1].material.n(torch.tensor(wls, dtype=torch.float64, device=dev))
    lam = torch.tensor(wls, dtype=torch.float64, device=dev) * 1e-3 / n  # (W,) mm in the image medium
    zx = torch.tensor(z_xps, dtype=torch.float64, device=dev)
    valid = traced[2].reshape(nf * nw, na, nk)
    blk = GO_SOURCE_BLOCK_ACCELERATOR if devices.accelerator(dev) else GO_SOURCE_BLOCK
    cut = [_band_cut_block(o[i:i + blk], d[i:i + blk], valid[i:i + blk],
                           (zs[wi[i:i + blk]], zx[wi[i:i + blk]], lam[wi[i:i + blk]]))
           for i in range(0, nf * nw, blk)]
    return (cut[0] if len(cut) == 1 else torch.cat(cut)).reshape(nf, nw, -1)


def _band_cut_block(o, d, valid, planes: tuple) -> torch.Tensor:
    """:func:`_band_cut` for a block of S sources: their band rays after the lens ``o``, ``d`` (S, A, K, 3) and
    ``valid`` (S, A, K); ``planes`` = ``(zs (S, P) mm, exit-pupil planes (S,) mm, λ_m (S,) mm)``. Returns (S, P)
    bool (memory: ~10 arrays of A·K·P samples a source)."""
    zs, zx, lam = planes
    tan = d[..., :2] / d[..., 2:]
    ok = valid & torch.isfinite(tan).all(-1)
    z = zs[:, None, None, :]  # (S, 1, 1, P)
    x = o[..., :2, None] + tan[..., None] * (z[..., None, :] - o[..., 2:, None])  # (S, A, K, 2, P)
    out_dir = x[:, :, 1] - x[:, :, 0]  # (S, A, 2, P): outwards, along the next ray's landing
    norm = out_dir.norm(dim=-2, keepdim=True).clamp_min(1e-300)
    s = ((x - x[:, :, :1]) * (out_dir / norm)[:, :, None]).sum(-2)  # (S, A, K, P)
    grows = torch.cat([torch.ones_like(s[:, :, :1], dtype=torch.bool), s[:, :, 1:] > s[:, :, :-1]], 2)
    held = torch.cumprod((grows & ok[..., None]).to(torch.int8), 2).bool()  # the rays out to the first fold/loss
    reach = torch.where(held, s, torch.zeros_like(s)).amax(2)  # (S, A, P)
    reach = torch.where(held[:, :, -1], math.inf, reach)  # no fold or loss out to the last ray: not cut
    # the local focus across the edge: where the rim ray and the next one out cross (their separation's zero)
    dt = ((tan[:, :, 1] - tan[:, :, 0])[..., None] * (out_dir / norm)).sum(-2)  # (S, A, P) per mm of z
    zp = z[:, :, 0]  # (S, 1, P)
    zf = zp - norm[..., 0, :] / torch.where(dt.abs() > 1e-300, dt, torch.full_like(dt, 1e-300))
    zx = zx[:, None, None]
    length = ((zp - zx).abs() * (zf - zp) / (zf - zx)).abs()
    band = RIPPLE_ZONES * torch.sqrt(lam[:, None, None] * length)
    return (ok[:, :, :1] & (reach < band)).any(1)  # (S, P): azimuths whose rim ray is traced


def _go_error_block(x0, tan, ok, zs, k, plane) -> torch.Tensor:
    """:func:`go_phase_errors` for a block of S sources: the ray map ``x0`` (S, ng, ng, 2) mm on the DOE plane and its
    slopes ``tan`` (S, ng, ng, 2), the lit rays inside the stop ``ok`` (S, ng, ng), each source's planes ``zs`` (S,
    P) mm and wave number ``k`` (S,) 1/mm; ``plane`` = ``(z_doe mm, grid spacing in stop units)``. Returns the error
    (S, P) rad."""
    z_doe, h = plane
    lap = _lap_over_amp(x0[:, None] + (zs - z_doe)[:, :, None, None, None] * tan[:, None], h)  # (S, P, ng, ng)
    dz = (zs[:, 1:] - zs[:, :-1]).abs()[:, :, None, None]
    dphi = torch.cat([torch.zeros_like(lap[:, :1]), torch.cumsum(0.5 * (lap[:, 1:] + lap[:, :-1]) * dz, 1)], 1)
    dphi = dphi / (2 * k[:, None, None, None])
    good = ok[:, None] & torch.isfinite(dphi)
    cnt = good.sum((2, 3)).clamp_min(1)
    v = torch.where(good, dphi, torch.zeros_like(dphi))
    mean = v.sum((2, 3)) / cnt
    return torch.where(good, (dphi - mean[..., None, None]).abs(), torch.zeros_like(dphi)).amax((2, 3))


def _lap_over_amp(x: torch.Tensor, h: float) -> torch.Tensor:
    """``∇⊥²A / A`` (1/mm²) on planes of the ray map ``x`` (..., ng, ng, 2) mm over a stop grid of spacing ``h``
    (normalised stop units), ``A = |det ∂x/∂p|^(-1/2)``: central differences with the chain rule
    ``∇_x = (∂x/∂p)^(-T) ∇_p``; NaN where a stencil lacks a ray (the grid's outer rows, vignetted rays)."""
    def dp(f):  # central differences along the grid's columns (p) and rows (q) of f (..., ng, ng), NaN at the border
        pad = torch.nn.functional.pad  # (the differences NaN-padded: one op, not a fill, a slice and a copy)
        fp = pad((f[..., :, 2:] - f[..., :, :-2]) / (2 * h), (1, 1), value=math.nan)
        fq = pad((f[..., 2:, :] - f[..., :-2, :]) / (2 * h), (0, 0, 1, 1), value=math.nan)
        return fp, fq

    (m00, m01), (m10, m11) = dp(x[..., 0]), dp(x[..., 1])  # dx/dp, dx/dq, dy/dp, dy/dq
    det = m00 * m11 - m01 * m10
    amp = det.abs() ** -0.5
    ap, aq = dp(amp)
    gx, gy = (m11 * ap - m10 * aq) / det, (-m01 * ap + m00 * aq) / det  # ∇_x A
    gxp, gxq = dp(gx)
    gyp, gyq = dp(gy)
    return (m11 * gxp - m10 * gxq - m01 * gyp + m00 * gyq) / det / amp


def go_fallback_plane(lens, source: Source, z_xp: float, z_doe: float, known: tuple | None = None):
    """``(z_from, error)``: where the exit-pupil edge's Fresnel step builds its geometric-optics field for one source
    when the DOE plane ``z_doe`` lies too near the rays' focus (:func:`go_phase_error` ``error`` rad >
    :data:`GO_PHASE_TOL` there): the plane nearest the DOE plane, between it and the exit pupil ``z_xp``, where the
    error is at most :data:`GO_FALLBACK_FRACTION` × the tolerance (the field is then carried to the DOE plane by the
    angular spectrum, exact over that step); ``(None, error)`` when the DOE plane is fine (or no plane is), and
    ``(None, 0.0)`` when it lies before the exit pupil. ``known``: this source's :func:`go_phase_error` ``(z,
    error)`` when the caller computed it for many sources (:func:`go_phase_errors`)."""
    return _fallback_planes(lens, source, z_xp, z_doe, known)[:2]


def _fallback_planes(lens, source: Source, z_xp: float, z_doe: float, known: tuple | None = None):
    """:func:`go_fallback_plane`'s ``(z_from, error)`` and the planes to try, in order, where ``z_from``'s beam does
    not fit (:func:`_fallback_fits`): every plane nearer the DOE plane than ``z_from`` whose error is finite (the rays
    past the rim do not fold within the edge's band there) and below the DOE plane's own, the farthest from the DOE
    plane first: the construction is exact on the rim images' plane (the exact construction's) and its Fresnel step
    and geometric optics grow with the distance from them, so the field is built as far back as the memory allows.
    Issue 47, class B (h47f): the Planar 80 mm F/2.8 off axis, whose DOE plane lies past such a fold and whose plane
    within the fraction of the tolerance needs 14 163 samples a side, has planes 2 – 6 times the tolerance before
    the fold that fit."""
    if not z_xp < z_doe:  # a DOE plane before the exit pupil (its edge stepped backwards): no earlier plane
        return None, 0.0, ()
    zs, err = go_phase_error(lens, source, z_xp, z_doe) if known is None else known
    err = err.tolist()  # (one host read; issue 43: no tensor op per source)
    e = err[-1]
    if not e > GO_PHASE_TOL:
        return None, e, ()
    fine = [k for k, v in enumerate(err) if v <= GO_FALLBACK_FRACTION * GO_PHASE_TOL]
    if (not fine or fine[-1] == 0) and math.isinf(e):  # the rays past the rim fold within the edge's band there
        # (go_phase_errors' band_fold) and no plane is within the tolerance: the nearest plane where they do not fold
        fine = [k for k, v in enumerate(err) if math.isfinite(v)]
    if not fine or fine[-1] == 0:
        return None, e, ()
    zl = zs.tolist()
    others = [k for k in range(fine[-1] + 1, len(err) - 1) if math.isfinite(err[k]) and err[k] < e]
    return float(zl[fine[-1]]), e, tuple((float(zl[k]), float(err[k])) for k in others)


def _plane_side(lens, source: Source, z: float, p_sim: float) -> tuple:
    """``(side, xb)``: the beam's footprint ``xb`` on the plane ``z`` mm (traced; None where every ray is
    vignetted) and its larger extent in simulation samples of ``p_sim`` mm (inf without a footprint)."""
    fld = torch.as_tensor(source.field, dtype=torch.float64, device=lens.device).reshape(2)
    xb = _footprint(lens, fld, torch.tensor([float(source.wavelength)], dtype=torch.float64, device=lens.device),
                    source.depth, z, virtual=True)
    return (math.inf if xb is None else max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim), xb


class CarryPlan(NamedTuple):
    """What the caustic fallback's fit tests know of its carry before the construction (issue 47, h47m): the
    DOE-plane window's ``window`` (ny, nx) samples (:func:`_carry_plan`), ``medium`` (wavelength µm, n), the
    envelope's ``carrier`` (α, β), the DOE plane ``z_doe`` and the sensor ``z_sensor`` mm, the device, and what the
    edge band's margin on an earlier plane needs (:func:`_window_margin`): ``edge`` = ``(ripple_zones, rim images,
    z_far mm, chief ray on the sensor, the PSF crop's reach mm)``, None: no margin (1.2× the beam)."""
    window: tuple
    medium: tuple
    carrier: tuple
    z_doe: float
    z_sensor: float
    device: object
    edge: tuple | None = None


def _carry_plan(lens, doe, source: Source, zs: tuple, chief: ChiefRays, how: tuple) -> CarryPlan:
    """The :class:`CarryPlan` of a source's caustic fallback: its DOE-plane window as the construction will make it
    (the footprint on the DOE plane ``zs[1]`` plus :func:`_window_margin` for the rim images ``rim`` and 4 samples,
    clamped to the DOE's simulation grid; (1, 1) where nothing is lit). ``zs`` = ``(z_xp, z_doe, z_sensor)`` mm,
    ``how`` = ``(settings, rim, medium index or None)``."""
    z_xp, z_doe, z_sensor = zs
    settings, rim, medium = how
    wavelength = float(source.wavelength)
    n = _medium_index(lens, wavelength) if medium is None else float(medium)
    carrier = tuple(float(v) for v in chief.doe.d.detach().tolist()[:2])
    fld = torch.as_tensor(source.field, dtype=torch.float64, device=lens.device).reshape(2)
    bbox = _footprint(lens, fld, torch.tensor([wavelength], dtype=torch.float64, device=lens.device), source.depth,
                      z_doe)
    sim = doe.sim_grid(settings.oversample)
    window = (1, 1)
    z_far = _rim_step_plane(rim, z_xp, z_doe, wavelength, n, 0.0)[1]
    rz = None if settings.ripple_zones is None else float(settings.ripple_zones)
    if bbox is not None:
        margin = _window_margin(rz, rim, (z_doe, z_sensor, z_far), chief.sensor, (wavelength, n, carrier),
                                settings.crop_reach)
        box = lit_box(sim, bbox, margin + 4 * sim.pitch[0])
        if box is not None:
            window = (box[1] - box[0], box[3] - box[2])
    return CarryPlan(window, (wavelength, n), carrier, float(z_doe), float(z_sensor), lens.device,
                     (rz, rim, z_far, chief.sensor, settings.crop_reach))


def _from_window(plan: CarryPlan, xb, z: float, p_sim: float) -> tuple:
    """The carried field's window (ny, nx) on the plane ``z`` mm for the fit test: the beam ``xb`` plus the edge band's
    margin there on both sides (:func:`_window_margin` of the plan's ``edge``, the construction's own band rule with
    the DOE plane's distances: ~1.1 – 1.2× the cropped construction on the Pentax-DA 50 mm at 0.7 field), at least
    1.2× the beam, in samples of ``p_sim`` mm."""
    wy, wx = xb[3] - xb[2], xb[1] - xb[0]
    margin = 0.0
    if plan.edge is not None:
        rz, rim, z_far, chief_sensor, crop_reach = plan.edge
        margin = _window_margin(rz, rim, (z, plan.z_sensor, z_far), chief_sensor, (*plan.medium, plan.carrier),
                                crop_reach)
    return (math.ceil(max(1.2 * wy, wy + 2 * margin) / p_sim), math.ceil(max(1.2 * wx, wx + 2 * margin) / p_sim))


def _plane_fits(lens, side: float, xb, p_sim: float, carry: tuple) -> bool:
    """Whether a beam of ``side`` samples (footprint ``xb``) fits the caustic fallback: at most
    :data:`MAX_XP_SAMPLES` a side and its carry in memory (issue 47, h47m: :func:`~raywave.hybrid.coherent.geometry.
    carry_bytes` of its window, beam and edge band 1.2× wide, and its FFT grid onto the DOE-plane window), as the
    carry will check it. ``carry`` = ``(plan, z, sphere)``: the :class:`CarryPlan`, the plane ``z`` mm of the beam and
    the scaled carry's point ``(x, y, z)`` mm (None: the plain carry; ``p_sim`` is then the scaled lattice's)."""
    if not side <= MAX_XP_SAMPLES:
        return False
    plan, z, sphere = carry
    n_from = _from_window(plan, xb, z, p_sim)
    dz, carrier = plan.z_doe - z, plan.carrier
    if sphere is not None:
        dz, carrier = dz * (sphere[2] - z) / (sphere[2] - plan.z_doe), (0.0, 0.0)
    try:
        fft = carry_fft_shape(n_from, plan.window, p_sim, dz, plan.medium, carrier)
        check_carry_memory(n_from, plan.window, fft, p_sim, plan.device, scaled=sphere is not None)
    except MemoryLimitError:
        return False
    return True


def _fallback_fits(lens, source: Source, z_from: float, z_doe: float, p_sim: float, est: float, others=(),
                   final: bool = True, carry: CarryPlan | None = None):
    """``z_from`` when the beam there spans at most :data:`MAX_XP_SAMPLES` simulation samples of ``p_sim`` mm a
    side (the exact construction's limit; the window's memory is checked as for any field), with a
    :class:`StopEdgeWarning` naming the fallback; else the first of ``others`` (:func:`_fallback_planes`: ``(z,
    error)`` pairs, the farthest from the DOE plane first) whose beam fits, with a warning naming its error; else
    None with a warning that the DOE plane ``z_doe`` is too near the rays' focus for the construction (``est``: the
    :func:`go_phase_error` there, rad); without ``final`` (the caller tries the scaled carry next,
    :func:`_scaled_fallback_fits`) None without a warning. ``carry``: the :class:`CarryPlan` whose memory each plane's
    carry must fit (None: a DOE-plane window as large as the beam on the plane, the FFT grid twice its side)."""
    side, xb = _plane_side(lens, source, z_from, p_sim)
    where = _fallback_where(source, z_doe, est)
    if not _plane_fits(lens, side, xb, p_sim, (_plan_for(carry, lens, xb, p_sim, z_doe), z_from, None)):
        for z, err in others:  # issue 47, class B: the farthest plane that fits
            s2, xb2 = _plane_side(lens, source, z, p_sim)
            if _plane_fits(lens, s2, xb2, p_sim, (_plan_for(carry, lens, xb2, p_sim, z_doe), z, None)):
                warnings.warn(f"{where}; building it {z_doe - z_from:.3g} mm before would take {side:.0f} samples a "
                              f"side (over {MAX_XP_SAMPLES}, or more than the memory holds): the field is built "
                              f"{z_doe - z:.3g} mm before it, where the geometric-optics field is off by ~{err:.2g} "
                              "rad, and carried to it by the angular spectrum (slower)", StopEdgeWarning,
                              stacklevel=4)
                return z
        if not final:
            return None
        warnings.warn(f"{where}, and building it {z_doe - z_from:.3g} mm before would take {side:.0f} samples a side "
                      f"(over {MAX_XP_SAMPLES}, or more than the memory holds): built on the plane itself; move the "
                      "DOE towards the lens or use a coarser DOE pitch", StopEdgeWarning, stacklevel=4)
        return None
    warnings.warn(f"{where}; the field is built {z_doe - z_from:.3g} mm before it and carried to it by the angular "
                  "spectrum (slower)", StopEdgeWarning, stacklevel=4)
    return z_from


def _plan_for(carry, lens, xb, p_sim: float, z_doe: float) -> CarryPlan:
    """``carry``, or where None (a caller without the DOE's grid) a :class:`CarryPlan` whose DOE-plane window is the
    beam ``xb``'s on its own plane (1.2× wide at ``p_sim`` mm), on axis at 0.55 µm in air: an upper bound of the
    window near the rays' focus."""
    if carry is not None or xb is None:
        return carry if carry is not None else CarryPlan((1, 1), (0.55, 1.0), (0.0, 0.0), z_doe, math.inf,
                                                         lens.device)
    win = (math.ceil(1.2 * (xb[3] - xb[2]) / p_sim), math.ceil(1.2 * (xb[1] - xb[0]) / p_sim))
    return CarryPlan(win, (0.55, 1.0), (0.0, 0.0), z_doe, math.inf, lens.device)


def _fallback_where(source: Source, z_doe: float, est: float) -> str:
    """The start of the caustic fallback's warnings: the DOE plane ``z_doe`` near the rays' focus, and why."""
    fld = [round(float(v), 6) for v in torch.as_tensor(source.field).reshape(-1).tolist()]
    return (f"the DOE plane z = {z_doe:.4g} mm lies near the rays' focus for field {fld} at "
            f"{float(source.wavelength):g} µm: " +
            ("the rays past the stop's rim fold within the edge's ripple band there" if math.isinf(est) else
             f"the geometric-optics field there is off by ~{est:.2g} rad (go_phase_error > {GO_PHASE_TOL:g} rad)"))


def _scaled_fallback_fits(lens, source: Source, zs: tuple, p_sim: float, est: float, chief_sensor,
                          carry: CarryPlan | None = None):
    """``(z_from, sphere)`` for the scaled carry (:func:`scaled_carry`) of the caustic fallback from its plane
    ``z_from`` (``zs = (z_from, z_doe, z_sensor)`` mm) where no plane fits the plain carry: ``sphere`` ``(x, y, z)``
    mm the chief ray's sensor point (``chief_sensor``), the beam there in samples of ``p_sim / M`` (``M`` the
    sphere's magnification from ``z_from`` to ``z_doe``) within :data:`MAX_XP_SAMPLES` and its carry in memory
    (``carry``: the :class:`CarryPlan`, as :func:`_fallback_fits`), with a :class:`StopEdgeWarning` naming it; else
    ``(None, None)`` with the warning that the field is built on the DOE plane itself."""
    z_from, z_doe, z_sensor = zs
    where = _fallback_where(source, z_doe, est)
    side, xb = _plane_side(lens, source, z_from, p_sim)
    sphere = tuple(float(v) for v in chief_sensor.o.detach()[:2].tolist()) + (float(z_sensor),)
    mag = (z_sensor - z_doe) / (z_sensor - z_from) if z_sensor != z_from else 0.0
    if 0.0 < mag < 1.0 and xb is not None and _plane_fits(lens, side * mag, xb, p_sim / mag,
                                                          (_plan_for(carry, lens, xb, p_sim, z_doe), z_from, sphere)):
        warnings.warn(f"{where}; the field is built {z_doe - z_from:.3g} mm before it, relative to the sphere "
                      f"converging on the chief ray's sensor point on a lattice {1 / mag:.3g}× the DOE pitch "
                      f"({side * mag:.0f} samples a side, {side:.0f} at the DOE pitch), and carried to it by the "
                      "scaled angular spectrum (slower)", StopEdgeWarning, stacklevel=4)
        return z_from, sphere
    warnings.warn(f"{where}, and building it {z_doe - z_from:.3g} mm before would take {side:.0f} samples a side "
                  f"(over {MAX_XP_SAMPLES}, or more than the memory holds): built on the plane itself; move the "
                  "DOE towards the lens or use a coarser DOE pitch", StopEdgeWarning, stacklevel=4)
    return None, None


def _scaled_lattice(sim: Grid, sphere: tuple, planes: tuple, device) -> CoarseLattice:
    """The lattice of the scaled carry's construction on the plane ``planes[0]`` (``planes = (z_from, z_doe)`` mm):
    the DOE's simulation lattice ``sim`` seen from the point ``sphere`` ``(x, y, z)`` mm, i.e. magnified about its
    foot ``(x, y)`` by ``1/M``, ``M = (z − z_doe)/(z − z_from)``."""
    fx, fy, fz = sphere
    z_from, z_doe = planes
    mag = (fz - z_doe) / (fz - z_from)
    ox, oy = sim.origin
    sy, sx = sim.shape
    return CoarseLattice((fx + (ox - fx) / mag, fy + (oy - fy) / mag), sim.pitch[0] / mag,
                         (math.ceil(sy / mag), math.ceil(sx / mag)), device)


#: :func:`scaled_carry` carries the envelope in the chart of :mod:`~raywave.hybrid.coherent.sphere_chart` (issue 47,
#: h47o) where True; False (the default): in the far plane's own coordinates (h47f; the metric's O(θ·Δθ) variation
#: left in). Measured (rel L1 from the converged Huygens PSF, docs/notes/ray-wave-research.md): the analytic disc at
#: 30° 0.111 → 0.006 (relative L2); the Olympus 24 mm at 0.7 field 1.46e-3 → 1.14e-3; the Leica 28 mm at 0.7 under
#: 6 GiB 2.46e-3 → 1.50e-3; the Nikon 300 mm at 0.7 3.09e-4 → 2.83e-4; the Planar 80 mm at 0.7 forced
#: from the plain carry's plane 2.30e-3 → 2.67e-3 on its lattice, 1.39e-3 → 1.32e-3 on one 2× finer (the bicubic
#: resampling loses on the lattice's near-Nyquist content); its extra arrays are not in the carry's memory estimate
#: (:func:`~raywave.hybrid.coherent.geometry.carry_bytes`): not the default until both are settled
SCALED_CARRY_CHART = False


def _charted_carry(field: Field, out: Grid, sphere: tuple, planes: tuple) -> torch.Tensor:
    """The envelope (complex, ``out``'s shape) of :func:`scaled_carry` before the sphere's phase: ``field``'s
    envelope (relative to the sphere, on the far plane ``planes[0]``) resampled into the
    :class:`~raywave.hybrid.coherent.sphere_chart.SphereChart` about its power centroid, carried ``dz·R₁/R₂`` there
    by the angular spectrum, and read (bicubic) at the chart point of each DOE-plane sample's sphere image
    ``F + (x' − F)/M`` on the far plane."""
    fx, fy, fz = sphere
    z_from, z_doe = planes
    r1, r2 = fz - z_from, fz - z_doe
    mag = r2 / r1
    env, g1 = field.envelope, field.grid
    dev, dt = env.device, torch.float64
    (ny, nx), (x0, y0), pc = g1.shape, g1.origin, g1.pitch[0]
    xs = x0 + torch.arange(nx, dtype=dt, device=dev) * pc
    ys = y0 + torch.arange(ny, dtype=dt, device=dev) * pc
    with torch.no_grad():
        w = torch.view_as_real(env.detach()).square().sum(-1)
        tot = w.sum().clamp_min(1e-300)
        cx = float((w.sum(0) * xs).sum() / tot)
        cy = float((w.sum(1) * ys).sum() / tot)
    chart = SphereChart((cx, cy), (fx, fy, fz), r1)
    pq = pc * chart.s_min
    # the chart grid over the input lattice's image (its border's chart points)
    bx = torch.cat([xs, xs, torch.full((ny,), xs[0], dtype=dt, device=dev), torch.full((ny,), xs[-1], dtype=dt,
                                                                                       device=dev)])
    by = torch.cat([torch.full((nx,), ys[0], dtype=dt, device=dev), torch.full((nx,), ys[-1], dtype=dt, device=dev),
                    ys, ys])
    q0, q1 = chart.forward(bx, by)
    qx0, qy0 = float(q0.min()), float(q1.min())
    mx, my = int(math.ceil((float(q0.max()) - qx0) / pq)) + 1, int(math.ceil((float(q1.max()) - qy0) / pq)) + 1
    gq = Grid((qx0, qy0), pq, (my, mx))
    qa = qx0 + torch.arange(mx, dtype=dt, device=dev) * pq
    qb = qy0 + torch.arange(my, dtype=dt, device=dev) * pq
    px, py = chart.inverse(qa[None, :].expand(my, mx), qb[:, None].expand(my, mx))
    aq = sample_bicubic(env, (x0, y0), pc, px, py)
    del px, py
    # the DOE-plane samples' sphere images on the far plane, in the chart
    (oy_n, ox_n), (ox, oy), po = out.shape, out.origin, out.pitch[0]
    xo = fx + (ox + torch.arange(ox_n, dtype=dt, device=dev) * po - fx) / mag
    yo = fy + (oy + torch.arange(oy_n, dtype=dt, device=dev) * out.pitch[1] - fy) / mag
    s0, s1 = chart.forward(xo[None, :].expand(oy_n, ox_n), yo[:, None].expand(oy_n, ox_n))
    pad = 3 * pq
    ax0, ay0 = float(s0.min()) - pad, float(s1.min()) - pad
    nox = int(math.ceil((float(s0.max()) + pad - ax0) / pq)) + 1
    noy = int(math.ceil((float(s1.max()) + pad - ay0) / pq)) + 1
    go = Grid((ax0, ay0), pq, (noy, nox))
    carried = propagate_window(Field(aq.to(env.dtype), gq, field.wavelength, field.n, (0.0, 0.0)), go,
                               (z_doe - z_from) * r1 / r2).envelope
    del aq
    return sample_bicubic(carried, (ax0, ay0), pq, s0, s1).to(env.dtype)


def scaled_carry(field: Field, out: Grid, sphere: tuple, planes: tuple, carrier: tuple) -> torch.Tensor:
    """The envelope (complex, ``out``'s shape; relative to ``carrier`` ``(α, β)``) on the DOE window ``out`` of the
    plane ``z_doe`` of a wave built on the plane ``z_from`` (``planes = (z_from, z_doe)`` mm) as ``field``: its
    envelope relative to the spherical wave converging on ``sphere`` ``(x, y, z_f)`` mm (carrier 0, on the lattice
    :func:`_scaled_lattice`). The Fresnel scaling of a converging wave (issue 47, class B, h47f): with ``R1``,
    ``R2`` the distances from the two planes to ``z_f`` and ``M = R2/R1``, the wave on ``z_doe`` at ``x'`` is the
    envelope propagated ``dz·R1/R2`` (angular spectrum, exact for the envelope's own spectrum) read at ``x_f + (x' −
    x_f)/M``, times ``1/M`` and the sphere there: its rays are the straight lines to the point, mapped exactly; the
    envelope's deviations from them are carried paraxially about the axis (their Fresnel length exact only to
    ``O(θ²)`` in the rays' tilt ``θ``). The lattice is the beam's own size over the DOE pitch's, ``1/M`` times
    coarser than the plane's Nyquist pitch would ask: the exact carry's window of the Nikon 300 mm F/2.8's plane 38
    mm before its DOE plane, 16 162 samples a side, is 3 870 here."""
    fx, fy, fz = sphere
    z_from, z_doe = planes
    r1, r2 = fz - z_from, fz - z_doe
    mag = r2 / r1
    ox, oy = out.origin
    if SCALED_CARRY_CHART:
        a = _charted_carry(field, out, sphere, planes)
    else:
        # (a lattice f× finer than out's pitch / M: every f-th sample of the carried window)
        f = max(1, int(round(out.pitch[0] / mag / field.grid.pitch[0])))
        src = Grid((fx + (ox - fx) / mag, fy + (oy - fy) / mag), field.grid.pitch[0],
                   (f * (out.shape[0] - 1) + 1, f * (out.shape[1] - 1) + 1))
        a = propagate_window(Field(field.envelope, field.grid, field.wavelength, field.n, (0.0, 0.0)), src,
                             (z_doe - z_from) * r1 / r2).envelope[::f, ::f]
    k = 2 * math.pi * field.n / (field.wavelength * 1e-3)
    dev, dt = a.device, torch.float64
    xs = ox + torch.arange(out.shape[1], dtype=dt, device=dev) * out.pitch[0]
    ys = oy + torch.arange(out.shape[0], dtype=dt, device=dev) * out.pitch[1]
    rr = torch.sqrt((xs[None, :] - fx) ** 2 + (ys[:, None] - fy) ** 2 + r2 * r2)
    phase = -k * ((rr - abs(r2)) + carrier[0] * xs[None, :] + carrier[1] * ys[:, None])
    return a * (torch.polar(torch.full_like(rr, 1.0 / mag), phase)).to(a.dtype)


def edge_fresnel_number(beam_half: float, wavelength: float, n: float, d: float, r: float) -> float:
    """The Fresnel number ``N_F = a² n / (λ L)`` of the stop edge's circle as the DOE plane sees it: ``a`` (mm) the
    beam's half width on the DOE plane, ``L = d (R − d)/R`` the edge's Fresnel length there (``d`` mm from the
    edge's image, the exit pupil, to the DOE plane; ``R`` mm from it to the focus, the sensor: the Fresnel scaling of
    a converging wave), ``wavelength`` µm, ``n`` the image medium's index. The number of Fresnel zones the edge's
    ripples are spread over across the beam's radius is ``sqrt(N_F)``: the knife-edge step is a local (straight,
    slowly varying edge) expansion in ``1/sqrt(N_F)`` that keeps its first order (the edge's curvature); near focus
    (``R − d → 0``) the ripples cover the beam and ``N_F`` falls. ``inf`` where ``d`` is 0 (the DOE at the pupil).
    A diagnostic: it does not predict the step's error (issue 47: the double Gauss on axis, N_F 177, 1.07e-2 from the
    converged Huygens PSF; the bundled asphere, N_F 105–130, and the two-lens truth system, N_F 27, ≤ 9e-4)."""
    length = abs(d * (r - d) / r) if r != 0 else abs(d)
    if length == 0.0:
        return math.inf
    return beam_half * beam_half * n / (wavelength * 1e-3 * length)


#: the rings (fractions of the stop's radius) and azimuths of the rays with which :func:`edge_aberration` tests the
#: wave near the stop's edge
SPHERE_RINGS = (0.9, 1.0, 1.1)
SPHERE_AZIMUTHS = 16


def edge_aberration(lens, field, wavelength: float, depth, field_type: str | None = None) -> float:
    """How far (waves, ≥ 0) the wave near the stop's edge is from a sphere, for one source (2,) at ``wavelength``
    µm: the rays through :data:`SPHERE_RINGS` × :data:`SPHERE_AZIMUTHS` points of the stop (apertures off, straight
    lines in the image medium after the last surface), the point X closest to all of them (least squares), and
    ``max_i dist(ray_i, X) · NA / λ_m`` (``NA = n·max_i |d_i × d̄|``, the rays' spread about their mean direction
    ``d̄``; ``λ_m = λ/n``): the transverse aberration of the edge's rays in units of the focus's diffraction scale,
    about the wave aberration (waves) that the edge's neighbourhood carries. 0 for a perfect sphere (whatever the
    sensor's defocus: :func:`adaptive_edge_step` checks that apart); ``inf`` when a ray cannot be traced.

    With a blank DOE this says where the stop's edge may be cut sharply on the DOE plane instead of at the exit
    pupil: for a spherical wave the focal field of a sharp aperture does not depend on where along the cone the
    aperture sits (the Fresnel scaling theorem), so the DOE-plane edge is then exact and cheaper than the edge step
    (the F/1.3 asphere on axis: 1.2e-4 rel L1 from the converged Huygens PSF, where the Fresnel step leaves 1.4e-3).
    """
    return _edge_focus(lens, field, wavelength, depth, field_type)[0]


def _edge_focus(lens, field, wavelength: float, depth, field_type: str | None = None):
    """``(waves, focus z mm, NA, n)`` of :func:`edge_aberration` (``waves`` inf, the rest None, where a ray cannot
    be traced): the aberration, the z of the point closest to the edge's rays, their spread ``n·sin`` and the image
    medium's index (:func:`edge_focus_many` of the one source)."""
    return edge_focus_many(lens, field, [float(wavelength)], depth, field_type)[0][0]


def edge_focus_many(lens, fields, wavelengths, depth, field_type: str | None = None,
                    chief: tuple | None = None) -> list:
    """:func:`_edge_focus` of every source of ``fields`` (F, 2) × ``wavelengths`` (W,) µm, from one trace of their
    F·W·48 edge rays (issue 43: a map's sources share it): ``[F][W]`` tuples ``(waves, focus z mm, NA, n)``. Each
    ray is aimed and traced on its own, so each source's values are its own call's (to the aiming's rounding).
    ``chief``: these sources' :func:`~raywave.lens.sources.chief_aim` when the caller shares it."""
    dev = lens.device
    f = torch.as_tensor(fields, dtype=torch.float64, device=dev).reshape(-1, 2)
    th = torch.arange(SPHERE_AZIMUTHS, dtype=torch.float64, device=dev) * (2 * math.pi / SPHERE_AZIMUTHS)
    r = torch.tensor(SPHERE_RINGS, dtype=torch.float64, device=dev)[:, None]
    px, py = (r * torch.cos(th)).reshape(-1), (r * torch.sin(th)).reshape(-1)
    wl = torch.tensor([float(w) for w in wavelengths], dtype=torch.float64, device=dev)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # a diagnostic trace, apertures off
        rays = point_source_rays(lens, f, wl, pupil=(px, py), aim="full", depth=depth,
                                 field_type=field_type or lens.field_type, chief=chief)
        out = lens.trace(rays, apertures=False)
        ok = out.valid.all(-1)  # (F, W)
        o, d = out.o, out.d  # (F, W, N, 3)
        d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        proj = torch.eye(3, dtype=torch.float64, device=dev) - d[..., :, None] * d[..., None, :]  # (F, W, N, 3, 3)
        a = torch.where(ok[..., None, None], proj.sum(-3), torch.eye(3, dtype=torch.float64, device=dev))
        # parallel edge rays (a lens without power, e.g. a fuzzed file) have no closest point: not a sphere (inf)
        x, info = torch.linalg.solve_ex(a, (proj @ o[..., None]).sum(-3))
        x = x[..., 0]  # (F, W, 3)
        ok = ok & (info == 0)
        dist = torch.linalg.vector_norm((proj @ (x[..., None, :] - o)[..., None])[..., 0], dim=-1).amax(-1)
        mean = d.mean(-2)
        mean = mean / torch.linalg.vector_norm(mean, dim=-1, keepdim=True)
        n = lens.surfaces[-1].material.n(wl).to(torch.float64)  # (W,)
        na = n * torch.linalg.vector_norm(torch.linalg.cross(d, mean[..., None, :].expand_as(d)), dim=-1).amax(-1)
        value = dist * na / (wl * 1e-3 / n)
        host = torch.stack([value, x[..., 2], na, n.expand_as(na), ok.to(torch.float64)], -1).cpu().tolist()
    out = []
    for row in host:
        out.append([])
        for v, z, na_, n_, good in row:
            fine = good == 1.0 and math.isfinite(v) and math.isfinite(z)
            out[-1].append((v, z, na_, n_) if fine else (math.inf, None, None, None))
    return out


#: ``method="adaptive"``: the wave near the stop's edge is taken for a sphere (:func:`edge_aberration`, waves) up to
#: this value. Measured (rel L1 of the DOE-plane edge from converged references): 2.6e-5 waves on the F/1.3 asphere
#: on axis, 1.2e-4; ideal lenses ~1e-12 waves, 2.8e-4 (the wave-optics truths of tests/test_ideal_lens_truth.py);
#: 0.56 waves (the Cooke triplet on axis) already 1.8e-2, 0.11 on the bundled asphere on axis
SPHERE_TOL = 0.01


def is_blank(doe) -> bool:
    """Whether ``doe`` has zero phase at every wavelength and nothing to train (:class:`raywave.doe.BlankDOE`):
    only its clear aperture acts on the field."""
    return isinstance(doe, BlankDOE)


def adaptive_edge_step(lens, doe, field, wavelength: float, depth, z_doe: float, z_sensor: float,
                       field_type: str | None = None) -> str:
    """The edge step of ``method="adaptive"`` (the default of :class:`raywave.hybrid.HybridLens`) for one source:
    "doe" where the DOE is blank (:func:`is_blank`), the wave near the stop's edge a sphere to within
    :data:`SPHERE_TOL` waves (:func:`edge_aberration`) and the sensor at its focus (:func:`defocus_mismatch` ≤
    :data:`SPHERE_TOL`; ``z_doe``, ``z_sensor`` mm the planes): the focal field of a sharp aperture on a spherical
    wave does not depend on the plane along the cone where it cuts (the Fresnel scaling theorem), so the edge cut on
    the DOE plane is the exit-pupil edge's exact result there, and the cheapest; else "fresnel" (the knife-edge
    step; the PSF calls then check it against its error estimate, :func:`fresnel_step_estimates`).
    A blank DOE's PSF and a phase DOE's PSF of the same lens may so come from different edge constructions: their
    difference then holds the Fresnel step's own error (1.3e-3 in a grating's first-order efficiency unmixed with
    the blank PSF at F/4, tests/test_doe_params.py); pass ``edge_step="fresnel"`` to compare them like for like."""
    return adaptive_edge_steps(lens, doe, field, [float(wavelength)], depth, (z_doe, z_sensor), field_type)[0][0]


def adaptive_edge_steps(lens, doe, fields, wavelengths, depth, planes: tuple, field_type: str | None = None,
                        chief: tuple | None = None) -> list:
    """:func:`adaptive_edge_step` of every source of ``fields`` (F, 2) × ``wavelengths`` (W,) µm (``planes`` =
    ``(z_doe, z_sensor)`` mm): ``[F][W]`` of "doe" or "fresnel", the edge rays of all sources traced once
    (:func:`edge_focus_many`; issue 43: a map's call decides them together in its shared geometry step);
    ``chief``: these sources' :func:`~raywave.lens.sources.chief_aim` when the caller shares it."""
    nf = torch.as_tensor(fields).reshape(-1, 2).shape[0]
    if not is_blank(doe):
        return [["fresnel"] * len(wavelengths) for _ in range(nf)]
    return blank_edge_steps(lens, fields, wavelengths, depth, planes, field_type, chief)


def blank_edge_steps(lens, fields, wavelengths, depth, planes: tuple, field_type: str | None = None,
                     chief: tuple | None = None) -> list:
    """:func:`adaptive_edge_steps` for a blank DOE: ``[F][W]`` of "doe" (the wave near the stop's edge a sphere
    focused on the sensor, :func:`_sphere_step`) or "fresnel", from one trace of the sources' edge rays (arguments as
    :func:`adaptive_edge_steps`)."""
    z_doe, z_sensor = planes
    return [[_sphere_step(foc, wl, z_doe, z_sensor) for foc, wl in zip(row, wavelengths)]
            for row in edge_focus_many(lens, fields, wavelengths, depth, field_type, chief)]


def _sphere_step(focus: tuple, wavelength: float, z_doe: float, z_sensor: float) -> str:
    """"doe" where the edge's wave ``focus`` (:func:`_edge_focus`) is a sphere focused on the sensor (both to
    :data:`SPHERE_TOL`), else "fresnel"."""
    waves, z_focus, na, n = focus
    if not waves <= SPHERE_TOL:
        return "fresnel"
    if defocus_mismatch(z_focus, na, n, wavelength, z_doe, z_sensor) > SPHERE_TOL:
        return "fresnel"
    return "doe"


def defocus_mismatch(z_focus: float, na: float, n: float, wavelength: float, z_doe: float, z_sensor: float) -> float:
    """Waves by which a spherical wave's PSF on a defocused sensor depends on the plane where its aperture cuts:
    the plane is free only at the focus (Fresnel scaling). With the defocus ``δ = z_sensor − z_focus`` (mm), the
    aperture's Fresnel number seen from the sensor, ≈ the defocus in waves ``|δ|·NA²/(2λ_m)``, changes between the
    exit pupil and the DOE plane by the relative amount ``|δ| / |z_focus − z_doe|`` (to first order): their product.
    An ideal f 2 mm F/8 lens with the object at 15 mm (δ = −0.31 mm, the DOE 1.8 mm before focus): 0.14 waves, and
    the DOE-plane cut 6.5e-2 rel L1 from the Huygens PSF; a sensor at the focus: 0."""
    delta = z_sensor - z_focus
    gap = abs(z_focus - z_doe)
    if gap == 0.0:
        return math.inf
    return abs(delta) * na * na / (2 * float(wavelength) * 1e-3 / n) * abs(delta) / gap


#: ``method="adaptive"`` (issue 47): the Fresnel step is kept while the PSF crop reaches at most this many of the
#: edge's Fresnel zones as the sensor sees them (:func:`fresnel_step_estimates`: the crop's reach over the zone
#: ``sqrt(λ_m L)`` on the DOE plane times its magnification ``R/d`` to the sensor, the smallest over the rim), scaled
#: down where the inner tail is cut by the grid's anti-aliasing limit (:func:`~raywave.hybrid.coherent.stop_edge.
#: _band_limits`: the step's inner tail holds the edge waves up to ``ν_b/√2`` zones inside the shadow, 4 with the
#: default band). Calibrated on lens A (ideal, F/12.5, a zero-phase DOE 1 to 7 mm before the focus, whole-crop
#: relative L1 against the Rayleigh–Sommerfeld integral, crops of 32 to 384 pixels of 2 µm;
#: benchmarks/edge_estimate.py, edge_estimate_2026-11-30_xxiii_h47a.json): with the curvature ratio ≤ 0.28 every crop
#: within 3.21 zones ≤ 4.8e-4 (3.3 zones 7.8e-4), 3.68 – 3.76 zones 6.8e-4 – 1.64e-3, 4.5 – 4.9 zones 1.5e-3 –
#: 2.4e-3, beyond up to 1.2e-2 (the exact construction 0.99e-4 – 2.3e-4 on all of them). The bundled asphere's
#: 64-pixel crops of 3 µm reach 2.6 – 3.12 zones (its default keeps the Fresnel step there)
FRESNEL_REACH_ZONES = 3.5
#: ``method="adaptive"``: the Fresnel step is kept while the edge's Fresnel zone on the DOE plane is at most this
#: fraction of the radius of curvature of the edge's shadow there (:func:`fresnel_step_estimates`; the rim's image
#: curve, divided by an obscuration's size over the stop's: :func:`obscuration_fraction`). Lens A on small crops
#: (within the reach above): 0.28 (N_F 12.5) 2.1e-4, 0.37 (N_F 7.3) 8.3e-4, 0.56 (N_F 3.2) 1.07e-2; a 0.4
#: obscuration 2 mm before the DOE (tests/test_obscuration.py) 0.34: 2 % of the power off
FRESNEL_CURVATURE_MAX = 0.3


def obscuration_fraction(lens) -> float:
    """The smallest radius of curvature of the stop's edges over its clear radius (1: no obscuration): a circular
    obscuration's radius (an annulus's inner radius, a rectangle's smaller half width) over the stop aperture's
    radius (a square's half width, a rectangle's smaller half width); 1 where either is unknown."""
    try:
        ap = lens.surfaces[lens.stop_index].aperture
    except (AttributeError, IndexError, TypeError):
        return 1.0
    obs = getattr(ap, "obscuration", None)
    if obs is None:
        return 1.0
    if hasattr(ap, "radius"):
        outer = float(ap.radius)
    elif hasattr(ap, "half_width"):
        outer = float(ap.half_width)
    elif hasattr(ap, "half_widths"):
        outer = float(ap.half_widths.min())
    else:
        return 1.0
    if obs.shape == "circle":
        inner = float(obs.radius)
    elif obs.shape == "annulus":
        inner = float(obs.inner_radius) if float(obs.inner_radius) > 0 else float(obs.radius)
    else:
        inner = float(obs.half_widths.min())
    return min(1.0, inner / outer) if outer > 0 and inner > 0 else 1.0


def fresnel_step_estimates(rims: list, medium: tuple, planes: tuple, crop_reach: float, p_sim: float,
                           obscured: float = 1.0) -> list:
    """Whether the exit-pupil edge's Fresnel step can hold 1e-3 (relative L1 of the PSF crop) for the sources
    ``rims`` (their :func:`~raywave.hybrid.coherent.stop_edge.stop_rim_images` at one wavelength, R), from their
    rim rays alone (one host read for all; no trace): per source None (no rim images) or ``(zones, zones_max,
    curvature)``. Per rim point ``j`` (its image ``E_j``, its ray's direction ``u_j``), ``d_j`` and ``R_j`` the
    distances along the ray from ``E_j`` to the DOE plane and the sensor (``planes = (z_doe, z_sensor)`` mm),
    ``L_j = d_j (R_j − d_j) / R_j`` (a converging wave's Fresnel length), the zone ``sqrt(λ_m L_j)`` (``medium =
    (wavelength µm, n)``, ``λ_m = λ/n``) and its image on the sensor ``R_j/d_j · sqrt(λ_m L_j)``:

    * ``zones``: the crop's reach ``crop_reach`` (mm, :meth:`~raywave.hybrid.HybridLens.crop_reach`; 0: the
      caller does not know its crop) over the smallest image of a zone; on a sensor so far from the rim rays' focus
      that they all land beyond that reach (the crop inside their ring), the reach from each landing (``crop_reach``
      plus the landing's distance from the ring's centre, :func:`_defocus_ring`) over its own zone image, the largest
      over the rim. The edge wave that lands ``ρ`` from the rim
      ray's focus leaves the DOE plane ``ρ d/R`` inside the shadow; the step's inner tail holds it up to ``ν_b/√2``
      zones (4 with the default band) and no single-edge knife edge holds the far edge's wave once it crosses the
      beam's centre (``sqrt(N_F)`` zones); ``zones_max`` = :data:`FRESNEL_REACH_ZONES` × ``min(1, ν_b/(4√2))``,
      ``ν_b`` the inner tail's limit at the simulation pitch ``p_sim`` mm (:func:`~raywave.hybrid.coherent.
      stop_edge._band_limits`).
    * ``curvature``: the largest zone over the local radius of curvature of the rim rays' curve on the DOE plane
      (three neighbouring rim points), divided by ``obscured`` (:func:`obscuration_fraction`): ``1/sqrt(N_F)``
      for a round beam, compared with :data:`FRESNEL_CURVATURE_MAX`.

    :func:`fresnel_step_holds` reads the verdict. Calibrated on measured cases (the constants' notes)."""
    out = [None] * len(rims)
    live = [k for k, r in enumerate(rims) if r is not None and getattr(r, "points", None) is not None
            and getattr(r, "directions", None) is not None]
    if not live:
        return out
    z_doe, z_sensor = planes
    lam = float(medium[0]) * 1e-3 / float(medium[1])
    with torch.no_grad():
        e = torch.stack([rims[k].points.detach() for k in live])  # (B, k, 3)
        u = torch.stack([rims[k].directions.detach() for k in live])
        t_d = (z_doe - e[..., 2]) / u[..., 2]  # along the ray from the rim image to the DOE plane (mm)
        t_s = (z_sensor - e[..., 2]) / u[..., 2]
        zone = torch.sqrt(lam * (t_d * (t_s - t_d) / t_s).abs())
        image = zone * (t_s / t_d).abs()
        reach = float(crop_reach) + _defocus_ring(e, u, t_s, float(crop_reach))  # (B, k) mm on the sensor
        p = e[..., :2] + t_d[..., None] * u[..., :2]  # the rim rays on the DOE plane (B, k, 2)
        a, c = p.roll(1, -2), p.roll(-1, -2)
        ab, bc, ac = ((x - y).norm(dim=-1) for x, y in ((p, a), (c, p), (c, a)))
        cross = ((p - a)[..., 0] * (c - a)[..., 1] - (p - a)[..., 1] * (c - a)[..., 0]).abs()
        rho = ab * bc * ac / (2 * cross).clamp_min(1e-300)  # circumradius of three neighbours (mm)
        host = torch.stack([(reach / image).amax(-1), zone.amin(-1), (zone / rho).amax(-1)], -1).cpu().tolist()
    for k, (zones, z_min, curv) in zip(live, host):
        if not (math.isfinite(zones) and math.isfinite(z_min) and math.isfinite(curv)) or zones < 0 or z_min <= 0:
            continue
        nu_b = max(min(0.6 * z_min / (math.sqrt(2.0) * p_sim), _nu_inner(RIPPLE_ZONES)), 2.0)
        out[k] = (zones, FRESNEL_REACH_ZONES * min(1.0, nu_b / _nu_inner(RIPPLE_ZONES)), curv / obscured)
    return out


def _defocus_ring(e: torch.Tensor, u: torch.Tensor, t_s: torch.Tensor, crop_reach: float) -> torch.Tensor:
    """How much farther (mm) the PSF crop's points lie from each rim ray's landing on the sensor than the crop's own
    reach ``crop_reach`` mm, ``(B, k)``, for rim images ``e`` and directions ``u`` ``(B, k, 3)`` reaching the sensor
    ``t_s`` ``(B, k)`` mm along them: each landing's distance from the rim rays' centre where the sensor lies so far
    from their focus that every one lands beyond the crop's reach (a defocused sensor: the crop inside the rim's
    ring, class J of docs/ray-wave.md), else 0 (some land within it: a focus, aberrated or not, the case the
    estimate was calibrated on; or the caller does not know its crop, ``crop_reach`` 0)."""
    if not crop_reach > 0:
        return torch.zeros_like(t_s)
    land = e[..., :2] + t_s[..., None] * u[..., :2]  # the rim rays on the sensor (B, k, 2)
    ring = (land - land.mean(-2, keepdim=True)).norm(dim=-1)
    inside = ring.amin(-1, keepdim=True) > crop_reach
    return torch.where(inside, ring, torch.zeros_like(ring))


def fresnel_step_holds(estimate) -> bool:
    """:func:`fresnel_step_estimates`' verdict for one source: True where the Fresnel step is expected to hold
    1e-3 (or no estimate could be made)."""
    if estimate is None:
        return True
    zones, zones_max, curvature = estimate
    return zones <= zones_max and curvature <= FRESNEL_CURVATURE_MAX


def describe_estimate(estimate) -> str:
    """The text of :func:`fresnel_step_estimates`' ``estimate`` for a warning."""
    zones, zones_max, curvature = estimate
    return (f"the Fresnel step's error estimate: the crop reaches {zones:.3g} of the edge's Fresnel zones (at most "
            f"{zones_max:.3g}), its zone is {curvature:.2g} × its radius of curvature (at most "
            f"{FRESNEL_CURVATURE_MAX:g})")


def _check_xp_beam(xb, p_sim: float, z_xp: float) -> None:
    """Refuse (ValueError) a beam whose footprint ``xb`` ``(xmin, xmax, ymin, ymax)`` mm on the exit-pupil plane
    ``z_xp`` mm spans more than :data:`MAX_XP_SAMPLES` simulation samples of ``p_sim`` mm (the exact construction's
    grid there would not fit in memory)."""
    if xb is not None and max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > MAX_XP_SAMPLES:
        raise ValueError(f"stop_edge='exit_pupil': the beam is {xb[1] - xb[0]:.3g}×{xb[3] - xb[2]:.3g} mm on the "
                         f"exit-pupil plane z = {z_xp:.4g} mm, over {MAX_XP_SAMPLES} samples of {p_sim * 1e3:g} µm "
                         "a side, too large for the exact angular-spectrum construction: use the Fresnel step "
                         "(HybridLens(edge_step='fresnel'), the default) or stop_edge='doe'")
