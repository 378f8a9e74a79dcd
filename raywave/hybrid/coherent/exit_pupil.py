"""The stop's sharp edge at the exit pupil (:func:`exit_pupil_field`): the exact angular-spectrum step or the
Fresnel step to the DOE plane."""

from __future__ import annotations

import math

import torch

from raywave.wave.grid import Field
from raywave.wave.propagation import propagate_window
from raywave.hybrid.coherent.accurate import accurate_field_steps
from raywave.hybrid.coherent.geometry import _common_setup, _empty_field, _footprint, check_window_memory, lit_box
from raywave.hybrid.coherent.record import DOEField, FieldInfo, FieldSettings, Source, Traced
from raywave.hybrid.coherent.stop_edge import RIPPLE_ZONES, stop_rim_images
from raywave.hybrid.coherent.tracing import run_serial


#: largest beam extent (simulation samples a side) on the exit-pupil plane that :func:`exit_pupil_field` accepts
MAX_XP_SAMPLES = 8192
#: ``method="auto"`` of :func:`exit_pupil_field`: the exact angular-spectrum construction up to this beam extent
#: (simulation samples a side on the exit-pupil plane), the Fresnel step beyond
AUTO_ASM_SAMPLES = 3072
#: the exact construction with the rim's images: the shortest Fresnel step from a rim image to the plane where the
#: angular spectrum takes over, in pixels of that step's Fresnel zone ``sqrt(λ d / n)`` (a step whose zone spans a
#: pixel or two is not resolved by the grid; 16 pixels: 0.48 mm at 1 µm and 0.53 µm)
RIM_STEP_ZONE_PIXELS = 16.0


def exit_pupil_field(lens, doe, field, wavelength: float, depth, z_xp: float, z_doe: float, z_sensor: float,
                     chief_xp, chief_doe, chief_sensor, nodes: int = 64, oversample: int = 1,
                     field_type: str | None = None, check: bool = True, chief_uv=None,
                     ripple_zones: float | None = None, method: str = "auto", rim_images: bool = True) -> DOEField:
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

    Args: as :func:`accurate_field`, plus ``z_xp`` (mm) and ``chief_xp`` (the chief ray on that plane).
    ``method="asm"`` raises ValueError when the beam on the exit-pupil plane spans more than
    :data:`MAX_XP_SAMPLES` simulation samples (a large beam: the field there would not fit in memory).
    ``method="auto"``: "asm" up to :data:`AUTO_ASM_SAMPLES` samples, else "fresnel". ``rim_images``: each node's
    edge is sharp at its stop-rim point's own image (:func:`stop_rim_images`); False: on the exit-pupil plane for
    every node (both steps as they were before the rim images)."""
    return run_serial(exit_pupil_field_steps(lens, doe, field, wavelength, depth, z_xp, z_doe, z_sensor, chief_xp,
                                             chief_doe, chief_sensor, nodes=nodes, oversample=oversample,
                                             field_type=field_type, check=check, chief_uv=chief_uv,
                                             ripple_zones=ripple_zones, method=method, rim_images=rim_images))


def exit_pupil_field_steps(lens, doe, field, wavelength: float, depth, z_xp: float, z_doe: float, z_sensor: float,
                     chief_xp, chief_doe, chief_sensor, nodes: int = 64, oversample: int = 1,
                     field_type: str | None = None, check: bool = True, chief_uv=None,
                     ripple_zones: float | None = None, method: str = "auto", rim_images: bool = True,
                     bbox=None, entrance=None, stop_rim=None) -> DOEField:
    """:func:`exit_pupil_field` as a generator of trace requests (see :func:`accurate_field_steps`). ``bbox``,
    ``entrance``: as :func:`accurate_field_steps` (the DOE-plane footprint and the entrance pupil, when the caller
    has them for many fields); ``stop_rim``: the rim images (:func:`stop_rim_images`) when the caller
    traced them (None: traced here)."""
    ripple_zones = RIPPLE_ZONES if ripple_zones is None else float(ripple_zones)
    p_sim = doe.pitch / oversample
    method, xb = _edge_method(lens, field, wavelength, depth, z_xp, p_sim, method)
    if method == "fresnel":
        rim = None
        if rim_images:
            rim = stop_rim if stop_rim is not None else stop_rim_images(lens, field, wavelength, depth, field_type)
        fd = yield from accurate_field_steps(
            lens, doe, Source(field, wavelength, depth, chief_doe, chief_sensor, chief_uv), z_doe, z_sensor,
            FieldSettings(nodes, oversample, field_type, check, stop_plane=z_xp, ripple_zones=ripple_zones),
            Traced(bbox, rim, entrance))
        return fd.with_info(stop_edge="exit_pupil")
    if method != "asm":
        raise ValueError(f"method must be 'auto', 'fresnel' or 'asm', got {method!r}")
    _check_xp_beam(xb, p_sim, z_xp)
    _, fld, wl, n, (p, x0, y0, sy, sx), _, center, zprop = _common_setup(
        lens, doe, field, wavelength, z_doe, z_sensor, chief_doe, chief_sensor, oversample, field_type)
    rim = None
    if rim_images:
        rim = stop_rim if stop_rim is not None else stop_rim_images(lens, field, wavelength, depth, field_type)
    z_edge, z_far = _rim_step_plane(rim, z_xp, z_doe, wavelength, n, p)
    if z_edge is None:  # the edge sharp on the exit-pupil plane
        fx = yield from accurate_field_steps(
            lens, doe, Source(field, wavelength, depth, chief_xp, chief_sensor, chief_uv), z_xp, z_sensor,
            FieldSettings(nodes, oversample, field_type, check, virtual=True))
    else:  # sharp at every rim point's image, stepped to z_edge (chief ray: a straight line in the image medium)
        fx = yield from accurate_field_steps(
            lens, doe, Source(field, wavelength, depth, chief_xp.propagate_to_z(z_edge, n), chief_sensor, chief_uv),
            z_edge, z_sensor, FieldSettings(nodes, oversample, field_type, check, virtual=True, stop_plane=z_xp,
                                            ripple_zones=ripple_zones), Traced(stop_rim=rim))
    carrier = fx.carrier  # the chief ray's direction: the same on both planes
    bbox = _footprint(lens, fld, wl, depth, z_doe)  # also checks that the DOE plane lies behind the lens
    if bbox is None or float(fx.power.detach()) == 0.0:
        return _empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays,
                            "accurate").with_info(stop_edge="exit_pupil")
    dz = z_doe - (z_xp if z_edge is None else z_edge)
    margin = ripple_zones * math.sqrt(wavelength * 1e-3 * abs(z_doe - z_far) / n) + 4 * p
    sim = doe.sim_grid(oversample)
    box = lit_box(sim, bbox, margin)
    if box is None:
        return _empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays,
                            "accurate").with_info(stop_edge="exit_pupil")
    grid = sim.window(*box)
    check_window_memory(*grid.shape, p, lens.device)
    u = propagate_window(fx.envelope, p, wavelength, dz, fx.origin, grid.origin, grid.shape, n=n, carrier=carrier)
    u = u * doe.coverage(grid, oversample, device=u.device).to(u.dtype)
    return DOEField(Field(u, grid, float(wavelength), n, carrier), box, zprop, center,
                    FieldInfo(fx.rays, "accurate", stop_edge="exit_pupil"))


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


def _check_xp_beam(xb, p_sim: float, z_xp: float) -> None:
    """Refuse (ValueError) a beam whose footprint ``xb`` ``(xmin, xmax, ymin, ymax)`` mm on the exit-pupil plane
    ``z_xp`` mm spans more than :data:`MAX_XP_SAMPLES` simulation samples of ``p_sim`` mm (the exact construction's
    grid there would not fit in memory)."""
    if xb is not None and max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > MAX_XP_SAMPLES:
        raise ValueError(f"stop_edge='exit_pupil': the beam is {xb[1] - xb[0]:.3g}×{xb[3] - xb[2]:.3g} mm on the "
                         f"exit-pupil plane z = {z_xp:.4g} mm, over {MAX_XP_SAMPLES} samples of {p_sim * 1e3:g} µm "
                         "a side, too large for the exact angular-spectrum construction: use the Fresnel step "
                         "(HybridLens(edge_step='fresnel'), the default) or stop_edge='doe'")
