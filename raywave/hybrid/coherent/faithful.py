"""The faithful construction (the paper's splatting, :func:`faithful_field`)."""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.wave.field import splat_bilinear
from raywave.wave.grid import Field
from raywave.hybrid.coherent.geometry import (_check_beyond_last_surface, _common_setup, _empty_field,
                                              _warn_nyquist, check_window_memory, inside_doe, lit_box)
from raywave.hybrid.coherent.record import DOEField, FieldInfo
from raywave.hybrid.coherent.settings import ChiefRays, FieldSettings, Planes, Source, check_types


def faithful_field(lens, doe, source: Source, planes: Planes, chief: ChiefRays,
                   settings: FieldSettings = FieldSettings()) -> DOEField:
    """The paper's DOE-plane field: ``settings.n_rays`` rays sampled uniformly at random over the pupil (slightly
    overfilled so that the real apertures cut the beam), each ray's complex amplitude ``d_z · exp(i k OPL)``
    spread bilinearly into its four neighbouring pixels.

    ``source`` (:class:`~raywave.hybrid.coherent.settings.Source`): the field point, wavelength, depth;
    ``planes``: the DOE and sensor planes; ``chief``: the chief ray at both. ``settings.full_grid=True`` returns the
    whole DOE simulation grid with no carrier removed (as the paper's full angular-spectrum propagation needs);
    otherwise the lit window, demodulated by the chief-ray carrier. ``settings.generator`` (torch.Generator) makes
    the ray sample replayable. ``settings.trace_dtype`` is the tracing precision: float32 reproduces the precision
    failure of the paper's Fig. S2 (the optical paths of ~10⁴ waves lose a sizeable fraction of a wave); the field
    is always assembled in complex128 afterwards."""
    check_types("faithful_field", source, planes, chief, settings)
    wavelength, depth, z_doe = source.wavelength, source.depth, planes.z_doe
    n_rays, oversample, full_grid, check = settings.n_rays, settings.oversample, settings.full_grid, settings.check
    generator, dtype = settings.generator, settings.trace_dtype
    field_type, field, wl, n, (p, x0, y0, sy, sx), (alpha, beta), center, zprop = _common_setup(
        lens, doe, source, (z_doe, planes.z_sensor), chief, oversample)
    dev = lens.device
    # drawn where the generator lives (the CPU by default: the same sample on every device), then moved
    gdev = generator.device if generator is not None else "cpu"
    r = 1.05 * torch.sqrt(torch.rand(n_rays, generator=generator, dtype=torch.float64, device=gdev)).to(dev)
    t = 2 * math.pi * torch.rand(n_rays, generator=generator, dtype=torch.float64, device=gdev).to(dev)
    with warnings.catch_warnings():
        # the pupil is overfilled on purpose (r ≤ 1.05: the stop clips the rim), so vignetting is expected here;
        # HybridLens reports a field that no light reaches. Other warnings (wavelength range, ...) pass through.
        warnings.simplefilter("ignore", VignettingWarning)
        rays = point_source_rays(lens, field, wl, pupil=(r * torch.cos(t), r * torch.sin(t)), aim="chief", depth=depth,
                                 dtype=dtype)
    out = lens.trace(rays)
    _check_beyond_last_surface(out, z_doe)
    nn_ = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, nn_)
    xy, dvec, opl = at.o[0, 0, :, :2], at.d[0, 0], at.opl[0, 0]
    valid, clipped, beam_half = _doe_pass(doe, xy, at.valid[0, 0])
    if not bool(valid.any()):
        return _empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, n_rays,
                            "faithful").with_info(clipped=clipped, beam_half=beam_half)
    xy, dvec, opl = xy[valid], dvec[valid], opl[valid]
    k = 2 * math.pi / (wavelength * 1e-3)
    ref = opl.detach().min()
    phase = (k * (opl - ref)).to(torch.float64)  # formed in the tracing precision
    xy, dvec = xy.to(torch.float64), dvec.to(torch.float64)
    sim = doe.sim_grid(oversample)
    phase, box, carrier = _splat_window(sim, p, (sy, sx), full_grid, xy, phase, k, n, (alpha, beta))
    grid = sim.window(*box)
    check_window_memory(grid.shape[0] * (2 if full_grid else 1), grid.shape[1] * (2 if full_grid else 1), p, dev)
    u = splat_bilinear(xy[:, 0], xy[:, 1], torch.polar(dvec[:, 2], phase), grid.origin, p, grid.shape)
    if check:
        slope = n * torch.sqrt((dvec[:, 0] - carrier[0]) ** 2 + (dvec[:, 1] - carrier[1]) ** 2)
        ratio = slope * (2 * p) / (wavelength * 1e-3)
        _warn_nyquist(ratio, torch.ones_like(ratio, dtype=torch.bool), xy, field.tolist(), wavelength, p)
    u = u * doe.coverage(grid, oversample, device=dev).to(u.dtype)
    return DOEField(Field(u, grid, float(wavelength), n, carrier), box, zprop, center,
                    FieldInfo(n_rays, "faithful", full_grid=full_grid, clipped=clipped, beam_half=beam_half))


def _doe_pass(doe, xy: torch.Tensor, passed: torch.Tensor):
    """Which rays pass the DOE aperture, from their DOE-plane points ``xy`` (N, 2) mm and ``passed`` (N,) bool
    (through the lens): ``(valid (N,) bool, clipped, beam_half)``, the fraction of the passed rays that the
    aperture blocks and the beam's half-width (mm, largest |x| or |y| of the passed rays; 0 when none)."""
    inside = inside_doe(doe, xy)
    valid = passed & inside
    # the rays sample the pupil uniformly: the blocked power fraction is the blocked ray fraction
    clipped = float((passed & ~inside).sum()) / max(int(passed.sum()), 1)
    beam_half = float(xy.detach()[passed].abs().max()) if bool(passed.any()) else 0.0
    return valid, clipped, beam_half


def _splat_window(sim, p: float, shape, full_grid: bool, xy: torch.Tensor, phase: torch.Tensor, k: float, n: float,
                  carrier):
    """Where the rays are spread on the simulation grid ``sim`` (pitch ``p`` mm, ``shape`` (sy, sx)):
    ``(phase, box, carrier)``. ``full_grid``: the whole grid, ``phase`` (N,) rad as it is, no carrier; else the lit
    window around the rays' points ``xy`` (N, 2) mm (+ 2 samples), ``phase`` less the chief ray's carrier ``(α, β)``
    (direction cosines; ``k`` = 2π/λ in 1/mm, ``n`` the image medium's index). ``box``: half-open
    ``(iy0, iy1, ix0, ix1)`` on ``sim``."""
    if full_grid:
        return phase, (0, shape[0], 0, shape[1]), (0.0, 0.0)
    # the lit window: each ray's phasor is demodulated by the chief ray's carrier *before* it is spread,
    # so the spread envelope varies slowly even for off-axis light (the paper's full grid spreads the
    # carrier itself and aliases once the local fringe frequency passes Nyquist: see the warning)
    alpha, beta = carrier
    phase = phase - k * n * (alpha * xy[:, 0] + beta * xy[:, 1])
    xs = xy.detach()
    bbox = (float(xs[:, 0].min()), float(xs[:, 0].max()), float(xs[:, 1].min()), float(xs[:, 1].max()))
    box = lit_box(sim, bbox, 2 * p)  # valid rays lie inside the DOE: never None
    return phase, box, (alpha, beta)
