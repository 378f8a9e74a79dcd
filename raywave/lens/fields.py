"""Fields given as image heights (OpticStudio's FTYP 2 and 3) -> the angles or object heights raywave traces.

A lens file may define its fields by where they land on the image surface:

* **paraxial image height** (FTYP 2): the paraxial chief ray (through the centre of the paraxial entrance pupil)
  lands at height h on the image plane. Linear: h = k · tan θ (object at infinity) or h = k · y (finite object,
  object height y), with k from the paraxial system matrix (:func:`paraxial_image_height_per_field`).
* **real image height** (FTYP 3): the real chief ray (aimed at the centre of the stop, at the primary
  wavelength) lands at height h, as OpticStudio solves it. Found by a safeguarded secant iteration on real
  traces, all fields at once, from the paraxial estimate (:func:`solve_real_image_heights`), to 1e-12 mm.

The solved fields are angles in degrees (object at infinity) or object heights in mm (finite object), in
raywave's sign convention (raywave.lens.sources: a positive angle images at +y, so a positive image height gives a
positive angle; a finite object with an inverted image gives a negative object height). Heights are radial: a
rotationally symmetric lens images -h at minus the field of +h.
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens import paraxial
from raywave.lens.sources import _wide_start_distance, chief_ray
from raywave.rays.bundle import RayBundle
from raywave.utils.checks import MAX_FIELD_ANGLE, MAX_WIDE_FIELD_ANGLE

#: Image-height tolerance of the real chief-ray solve (mm).
HEIGHT_TOL = 1e-12
#: Newton / secant iterations at most (each converges in a handful; a height beyond reach stops early).
MAX_ITER = 60
#: The largest angle the solve tries (degrees): rays are aimed with tan θ.
ANGLE_LIMIT = MAX_FIELD_ANGLE - 1e-6
IMAGE_HEIGHT_TYPES = ("paraxial_image_height", "real_image_height")
#: The largest angle (degrees) the continuation in the beam's direction tries: just under 180° (the axis seen
#: backward).
WIDE_ANGLE_LIMIT = MAX_WIDE_FIELD_ANGLE - 1e-6
#: The smallest continuation step in image height (fraction of the height sought) before a height is given up.
MIN_HEIGHT_STEP = 1e-5
#: Newton iterations at most per continuation step.
BEAM_NEWTON_ITER = 25
#: The largest change of the field angle (radians) one Newton step of the continuation may make.
BEAM_MAX_ANGLE_STEP = math.radians(5.0)


class FieldSolveWarning(UserWarning):
    """An image-height field that no chief ray reaches (left out of the lens's fields)."""


def paraxial_image_height_per_field(lens, wavelength: float | None = None) -> float:
    """k (mm per unit of tan θ, or mm per mm of object height): the paraxial chief ray's height on the image
    plane (the last thickness after the last surface) per unit field, from the paraxial system matrix."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    m = paraxial.system_matrix(lens, wl).detach()
    a, b, c, d = (float(v) for v in (m[0, 0], m[0, 1], m[1, 0], m[1, 1]))
    n = [float(v.detach()) for v in paraxial.surface_powers(lens, wl)[1]]
    ep_z = float(paraxial.stop_to_entrance_pupil(lens, wl)[0].detach())
    t_last = float(lens.surfaces[-1].thickness.detach())  # signed as n[-1] after mirrors: t / n > 0
    if math.isinf(lens.object_distance):
        y0, nu0 = -ep_z, n[0]  # u0 = tan θ = 1: through the entrance-pupil centre
    else:
        s = lens.object_distance
        u = -1.0 / (s + ep_z)  # from the object point at height 1 through the entrance-pupil centre
        y0, nu0 = 1.0 + s * u, n[0] * u
    y1, nu1 = a * y0 + b * nu0, c * y0 + d * nu0
    return y1 + t_last * nu1 / n[-1]


def _chief_heights(lens, values: torch.Tensor, wl: float):
    """(image heights (F,) mm, valid (F,)) of the real chief rays of the fields ``values`` (F,) (the lens's field
    type), on the image surface in its own frame."""
    f = torch.stack([torch.zeros_like(values), values], -1)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a vignetted trial field is handled here
        out = lens.image_coordinates(lens.trace_to_image(chief_ray(lens, f, [wl])))
    y = out.o[:, 0, 0, 1]
    ok = out.valid[:, 0, 0] & torch.isfinite(y)
    return y, ok


def _field_limit(lens) -> float:
    """The largest field value the solve may try: just under 90° for angles; for object heights a large bound."""
    return ANGLE_LIMIT if lens.field_type == "angle" else math.inf


def _to_field(lens, t: torch.Tensor) -> torch.Tensor:
    """The lens's field value for the solve variable ``t`` (tan θ for angles, the object height otherwise)."""
    return torch.rad2deg(torch.atan(t)) if lens.field_type == "angle" else t


def _meridional_rays(lens, t: torch.Tensor, ye: torch.Tensor, ep_z: float, wl: float) -> RayBundle:
    """Rays in the y–z plane: field variable ``t`` (M,) (tan θ, or the object height in mm) crossing the paraxial
    entrance-pupil plane z = ``ep_z`` at height ``ye`` (M,) mm."""
    zero = torch.zeros_like(t)
    if math.isinf(lens.object_distance):
        d = torch.stack([zero, t, torch.ones_like(t)], -1)
        d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        z0 = min(ep_z, 0.0) - 1.0
        o = torch.stack([zero, ye + (z0 - ep_z) * t, torch.full_like(t, z0)], -1)
    else:
        c = getattr(lens, "object_curvature", 0.0)  # a curved object surface: the point lies on it
        z_obj = -lens.object_distance + c * t * t / (1.0 + torch.sqrt(torch.clamp(1.0 - c * c * t * t, min=0.0)))
        o = torch.stack([zero, t, z_obj], -1)
        d = torch.stack([zero, ye - t, ep_z - z_obj], -1)
        d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return RayBundle.create(o, d, wl, dtype=torch.float64, device=lens.device)


def _stop_and_image_heights(lens, t, ye, ep_z, wl):
    """(height at the stop (M,), height on the image surface (M,), valid (M,)) of :func:`_meridional_rays`."""
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # trial rays of the solve: a vignetted one is dropped by `ok` below
        out, rec = lens.trace_to_image(_meridional_rays(lens, t, ye, ep_z, wl), record=True)
    y_stop = rec.points[lens.stop_index + 1][1]
    y_img = out.o[..., 1]
    ok = out.valid & torch.isfinite(y_img) & torch.isfinite(y_stop)
    return y_stop, y_img, ok


def _solve_newton(lens, h: torch.Tensor, k: float, wl: float):
    """(t (F,), converged (F,)): for an unfolded lens without mirrors, Newton's method on (t, y_e) for the
    meridional ray through the centre of the stop (y = 0 there) that lands at ``h`` (F,) on the image surface, a
    finite-difference Jacobian from rays traced with the trial ones (one trace per iteration)."""
    ep_z = float(paraxial.stop_to_entrance_pupil(lens, wl)[0].detach())
    limit = math.tan(math.radians(ANGLE_LIMIT)) if lens.field_type == "angle" else math.inf
    t = (h / k).clamp(-limit, limit)
    ye = torch.zeros_like(t)
    done = h == 0
    t = torch.where(done, torch.zeros_like(t), t)
    tol = HEIGHT_TOL * max(1.0, float(h.abs().max()))
    good = (t.clone(), ye.clone())
    for _ in range(MAX_ITER):
        dt = 1e-7 * torch.clamp(t.abs(), min=1e-3)
        dy = torch.full_like(ye, 1e-7 * max(1.0, lens.stop_radius()))
        ys, yi, ok = _stop_and_image_heights(lens, torch.cat([t, t + dt, t]), torch.cat([ye, ye, ye + dy]), ep_z, wl)
        F = t.shape[0]
        ys, yi, ok = ys.reshape(3, F), yi.reshape(3, F), ok.reshape(3, F)
        base_ok = ok[0] | done
        if not bool(base_ok.all()):  # a vignetted trial: halve back toward the last good one
            t = torch.where(base_ok, t, 0.5 * (t + good[0]))
            ye = torch.where(base_ok, ye, 0.5 * (ye + good[1]))
            continue
        r1, r2 = ys[0], yi[0] - h
        done = done | ((r1.abs() <= tol) & (r2.abs() <= tol))
        good = (torch.where(done, good[0], t), torch.where(done, good[1], ye))
        good = (torch.where(ok[0], t, good[0]), torch.where(ok[0], ye, good[1]))
        if bool(done.all()):
            break
        a11, a21 = (ys[1] - ys[0]) / dt, (yi[1] - yi[0]) / dt
        a12, a22 = (ys[2] - ys[0]) / dy, (yi[2] - yi[0]) / dy
        det = a11 * a22 - a12 * a21
        det = torch.where(det != 0, det, torch.ones_like(det))
        step_t = (a22 * r1 - a12 * r2) / det
        step_y = (-a21 * r1 + a11 * r2) / det
        t_new = torch.where(done, t, (t - step_t).clamp(-limit, limit))
        if bool(((t_new == t) | done).all()):  # stuck at the angle limit: the height is beyond reach
            break
        t = t_new
        ye = torch.where(done, ye, ye - step_y)
    return t, done


def solve_real_image_heights(lens, heights, wavelength: float | None = None) -> tuple[list[float], list[int]]:
    """The fields (the lens's field type: degrees or mm) whose real chief rays land at ``heights`` (mm) on the
    image surface at ``wavelength`` (µm, default primary), and the indices of the heights no chief ray reaches
    (:func:`real_image_height_fields` gives the reason for each)."""
    fields, why = real_image_height_fields(lens, heights, wavelength)
    return fields, sorted(why)


def real_image_height_fields(lens, heights, wavelength: float | None = None) -> tuple[list[float], dict[int, str]]:
    """The fields (the lens's field type: degrees or mm) whose real chief rays land at ``heights`` (mm) on the
    image surface at ``wavelength`` (µm, default primary), and {index: reason} for the heights no chief ray reaches.

    An unfolded lens without mirrors: Newton's method on the meridional ray through the stop centre
    (:func:`_solve_newton`). Where that fails, for angle fields of an object at infinity (a fisheye's beyond 90°,
    or a pupil too aberrated for the paraxial start): a continuation in image height from the axis over beam
    directions up to 180° (:func:`solve_wide_real_image_heights`), which names why a height is beyond reach.
    Otherwise (mirrors, coordinate breaks, a finite object) a secant iteration in tan θ (or object height) on
    raywave's aimed chief rays, all heights at once, from the paraxial estimate; a step to a vignetted or non-finite
    field is halved back toward the last good one."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    h = torch.as_tensor([abs(float(v)) for v in heights], dtype=torch.float64, device=lens.device)
    sign = [(-1.0 if float(v) < 0 else 1.0) for v in heights]
    try:
        k = paraxial_image_height_per_field(lens, wl)
    except (paraxial.ParaxialUndefinedError, ZeroDivisionError, ValueError):
        k = math.nan
    if not (math.isfinite(k) and k != 0.0):  # no paraxial model: a real trace at a small field
        t_small = 1e-4
        y, ok = _chief_heights(lens, _to_field(lens, torch.tensor([t_small], dtype=torch.float64)), wl)
        k = float(y[0]) / t_small if bool(ok[0]) and float(y[0]) != 0.0 else 1.0
    plain = not (lens.is_folded or lens.has_mirrors)
    fields = [0.0] * len(heights)
    missed = list(range(len(heights)))
    if plain:
        t, done = _solve_newton(lens, h, k, wl)
        for i, f in enumerate(_to_field(lens, t)):
            fields[i] = sign[i] * float(f)
        missed = [i for i in range(len(heights)) if not bool(done[i])]
    wide_ok = plain and lens.field_type == "angle" and math.isinf(lens.object_distance)
    if missed and not wide_ok:  # a strongly aberrated pupil can defeat the meridional Newton start: the aimed secant
        again, still = _solve_secant(lens, h[missed], k, wl)
        for j, i in enumerate(missed):
            fields[i] = sign[i] * again[j]
        missed = [missed[j] for j in still]
    unit = "angles below 90°" if lens.field_type == "angle" else "object heights"
    why = {i: f"no chief ray at {unit} reaches it" for i in missed}
    # an object at infinity (a fisheye's pupil defeats the Newton start, or the height lies beyond 90°): the
    # continuation over beam directions below
    if not missed:
        return fields, why
    if lens.field_type != "angle" or not math.isinf(lens.object_distance):
        for i in missed:
            why[i] += " (a field beyond 90° needs an object at infinity, seen from behind the first vertex)"
        return fields, why
    if not plain:
        for i in missed:
            why[i] += " (fields beyond 90° are solved for a lens without mirrors or coordinate breaks only)"
        return fields, why
    solved, beyond = solve_wide_real_image_heights(lens, [float(h[i]) for i in missed], wl)
    for j, i in enumerate(missed):
        if j in solved:
            fields[i] = sign[i] * solved[j]
            del why[i]
        else:
            b = beyond[j]
            why[i] = (f"{b.why}: the real chief ray reaches {b.reached:.6g} mm at most, at field {b.angle:.6g}° "
                      "(a continuation in image height from the axis over beam directions up to 180°)")
    return fields, why


def _solve_secant(lens, h: torch.Tensor, k: float, wl: float) -> tuple[list[float], list[int]]:
    """(fields (the lens's field type), indices not reached) for the heights ``h`` (F,) >= 0: a secant iteration
    in tan θ (or object height) on raywave's aimed chief rays from the paraxial estimate ``h / k``; a step to a
    vignetted or non-finite field is halved back toward the last good one."""
    limit = math.tan(math.radians(ANGLE_LIMIT)) if lens.field_type == "angle" else math.inf
    t_prev = torch.zeros_like(h)
    y_prev = torch.zeros_like(h)
    t = (h / k).clamp(-limit, limit)
    done = h == 0
    t = torch.where(done, torch.zeros_like(t), t)
    good_t, good_y = t_prev.clone(), y_prev.clone()
    gave_up = torch.zeros_like(done)
    for _ in range(MAX_ITER):
        if bool((done | gave_up).all()):
            break
        y, ok = _chief_heights(lens, _to_field(lens, t), wl)
        bad = ~ok & ~done & ~gave_up
        # a vignetted trial: halve back toward the last good field
        t = torch.where(bad, 0.5 * (t + good_t), t)
        if bool(bad.any()):
            continue
        err = y - h
        conv = (err.abs() <= HEIGHT_TOL * max(1.0, float(h.max()))) | done
        good_t = torch.where(~done, t, good_t)
        good_y = torch.where(~done, y, good_y)
        done = conv
        slope = (y - y_prev) / (t - t_prev)
        slope = torch.where(torch.isfinite(slope) & (slope != 0), slope, torch.full_like(slope, k))
        t_new = t - err / slope
        t_new = t_new.clamp(-limit, limit)
        # at the angle limit and still short of the height: beyond reach (stop iterating that field)
        beyond = (t.abs() >= limit) & (y < h) & ~done
        gave_up = gave_up | beyond
        t_prev, y_prev = t, y
        t = torch.where(done | gave_up, t, t_new)
        if bool((done | gave_up).all()):
            break
    missed = [i for i in range(h.shape[0]) if not bool(done[i])]
    return [float(f) for f in _to_field(lens, good_t)], missed


def solve_paraxial_image_heights(lens, heights, wavelength: float | None = None) -> list[float]:
    """The fields (degrees or mm) whose paraxial chief rays land at ``heights`` (mm) on the image plane."""
    k = paraxial_image_height_per_field(lens, wavelength)
    if k == 0.0 or not math.isfinite(k):
        raise ValueError(f"paraxial image height fields: the paraxial chief ray's image height per unit field is {k} "
                         "(an afocal lens or an image plane at the exit pupil): no field gives a non-zero height")
    t = [float(v) / k for v in heights]
    if lens.field_type == "angle":
        return [math.degrees(math.atan(v)) for v in t]
    return t


def apply_image_height_fields(lens, kind: str, heights, where: str = "lens") -> None:
    """Set ``lens.fields`` to the angles / object heights whose chief rays land at ``heights`` (mm; ``kind``:
    "paraxial_image_height" or "real_image_height") and keep the definition in ``lens.field_definition``. A height
    that no chief ray reaches (beyond a fisheye's 90°, or vignetted) is left out with a :class:`FieldSolveWarning`
    naming it."""
    if kind not in IMAGE_HEIGHT_TYPES:
        raise ValueError(f"{where}: field type {kind!r} is not an image height ({', '.join(IMAGE_HEIGHT_TYPES)})")
    heights = [float(v) for v in heights]
    if kind == "paraxial_image_height":
        fields, missed = solve_paraxial_image_heights(lens, heights), []
        if lens.field_type == "angle":
            missed = [i for i, f in enumerate(fields) if not abs(f) < MAX_FIELD_ANGLE]
        why = {i: "its angle is not below 90°" for i in missed}
    else:
        fields, why = real_image_height_fields(lens, heights)
        missed = sorted(why)
    for i in missed:
        warnings.warn(FieldSolveWarning(
            f"{where}: no chief ray reaches the image height {heights[i]:g} mm (field {i + 1}, "
            f"{kind.replace('_', ' ')}): {why[i]}; left out of the lens's fields"), stacklevel=2)
    keep = [i for i in range(len(heights)) if i not in missed] or [0]
    lens.fields = [fields[i] if i not in missed else 0.0 for i in keep]
    lens.field_definition = {"type": kind, "values": [heights[i] if i not in missed else 0.0 for i in keep]}


# --- real image heights reached by a chief ray from any direction (a fisheye's field beyond 90°) -------------------

class _BeamStop:
    """Why the continuation in image height stopped short of a height: ``reached`` (mm) the largest height solved,
    ``angle`` (degrees) its field, ``why`` the reason in words."""

    def __init__(self, reached: float, angle: float, why: str):
        self.reached, self.angle, self.why = reached, angle, why


def _beam_rays(lens, theta: torch.Tensor, s: torch.Tensor, ep_z: float, wl: float) -> RayBundle:
    """Meridional rays of an object at infinity in any direction: the beam (0, sin θ, cos θ) (θ (M,) radians, in
    (-π, π): beyond π/2 it travels backward, from behind the first vertex, as OpticStudio's field angle), crossing the
    plane across the beam through the paraxial entrance-pupil centre (0, 0, ``ep_z``) at ``s`` (M,) mm along
    e2 = (0, cos θ, -sin θ) (raywave.lens.sources.beam_basis: the parametrisation of raywave's rays beyond 90°, the
    entrance-pupil height times cos θ below). Each starts well before the lens on its line."""
    zero = torch.zeros_like(theta)
    sn, cs = torch.sin(theta), torch.cos(theta)
    d = torch.stack([zero, sn, cs], -1)
    p = torch.stack([zero, s * cs, ep_z - s * sn], -1)
    o = p - d * _wide_start_distance(lens, ep_z)
    return RayBundle.create(o, d, wl, dtype=torch.float64, device=lens.device)


def _beam_trace(lens, theta: torch.Tensor, s: torch.Tensor, ep_z: float, wl: float):
    """(height at the stop (M,), height on the image surface (M,), valid (M,), index (M,) of the first surface
    that stops the ray (-1: none; len(surfaces): the image surface)) of :func:`_beam_rays`."""
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # trial rays of the solve: blocked ones come back in `first_dead`, named by its warning
        out, rec = lens.trace_to_image(_beam_rays(lens, theta, s, ep_z, wl), record=True)
    y_stop = rec.points[lens.stop_index + 1][1]
    y_img = out.o[..., 1]
    ok = out.valid & torch.isfinite(y_img) & torch.isfinite(y_stop)
    alive = torch.stack([v.expand_as(ok) for v in rec.valid[1:]], 0)  # (surfaces + image, M)
    first_dead = torch.where(alive.all(0), torch.full_like(theta, -1, dtype=torch.long),
                             (~alive).to(torch.long).argmax(0))
    return y_stop, y_img, ok, first_dead


def _beam_newton(lens, h: float, theta: float, s: float, ep_z: float, wl: float, tol: float):
    """Newton's method on (θ, s) for the meridional ray of a distant object that passes the stop centre and lands
    at ``h`` mm on the image surface, from (``theta`` rad, ``s`` mm), a finite-difference Jacobian from rays traced
    with the trial one. Returns (θ, s, converged, why): ``why`` names the failure (a dead trial's surface, the height
    no longer growing with the angle, or the 180° limit)."""
    limit = math.radians(WIDE_ANGLE_LIMIT)
    ds = 1e-7 * max(1.0, lens.stop_radius())
    why = "Newton's method did not converge"
    for _ in range(BEAM_NEWTON_ITER):
        dth = 1e-7 * max(abs(theta), 1e-3)
        th = torch.tensor([theta, theta + dth, theta], dtype=torch.float64, device=lens.device)
        ss = torch.tensor([s, s, s + ds], dtype=torch.float64, device=lens.device)
        ys, yi, ok, dead = _beam_trace(lens, th, ss, ep_z, wl)
        if not bool(ok[0]):
            return theta, s, False, _dead_reason(lens, int(dead[0]))
        r1, r2 = float(ys[0]), float(yi[0]) - h
        if abs(r1) <= tol and abs(r2) <= tol:
            return theta, s, True, ""
        if not bool(ok.all()):
            return theta, s, False, "a neighbouring ray is blocked (the edge of the lens's reach)"
        a11, a21 = float(ys[1] - ys[0]) / dth, float(yi[1] - yi[0]) / dth
        a12, a22 = float(ys[2] - ys[0]) / ds, float(yi[2] - yi[0]) / ds
        det = a11 * a22 - a12 * a21
        if det == 0.0 or not math.isfinite(det):
            return theta, s, False, "the image height stops changing with the field angle"
        step_t = (a22 * r1 - a12 * r2) / det
        step_s = (-a21 * r1 + a11 * r2) / det
        scale = min(1.0, BEAM_MAX_ANGLE_STEP / max(abs(step_t), 1e-300))
        theta_new = theta - scale * step_t
        if abs(theta_new) >= limit:
            return theta, s, False, f"the field angle reaches {WIDE_ANGLE_LIMIT:.4g}° (the axis seen backward)"
        theta, s = theta_new, s - scale * step_s
    return theta, s, False, why


def _dead_reason(lens, k: int) -> str:
    """Why a chief ray stopped at lens surface index ``k`` (``len(surfaces)``: the image surface), in words; the
    surfaces numbered as in the lens file (the object surface 0)."""
    if k >= len(lens.surfaces):
        return "the chief ray misses the curved image surface"
    if lens.surfaces[k].aperture is not None:
        return f"the chief ray is blocked by the aperture of surface {k + 1} (or misses it)"
    return f"the chief ray misses surface {k + 1} or is totally internally reflected there"


def _height_slope(lens, theta: float, s: float, ep_z: float, wl: float) -> float:
    """d(image height)/dθ (mm per radian) along the chief rays (the stop-centre constraint held) at (θ, s)."""
    dth, ds = 1e-6 * max(abs(theta), 1e-3), 1e-6 * max(1.0, lens.stop_radius())
    th = torch.tensor([theta, theta + dth, theta], dtype=torch.float64, device=lens.device)
    ss = torch.tensor([s, s, s + ds], dtype=torch.float64, device=lens.device)
    ys, yi, ok, _ = _beam_trace(lens, th, ss, ep_z, wl)
    if not bool(ok.all()):
        return math.nan
    a11, a21 = float(ys[1] - ys[0]) / dth, float(yi[1] - yi[0]) / dth
    a12, a22 = float(ys[2] - ys[0]) / ds, float(yi[2] - yi[0]) / ds
    return (a21 * a12 - a22 * a11) / a12 if a12 != 0.0 else math.nan


def solve_wide_real_image_heights(lens, heights, wavelength: float | None = None):
    """The field angles (degrees, in (-180°, 180°)) whose real chief rays land at ``heights`` (mm, >= 0) on the image
    surface, for an object at infinity: a continuation in image height from the axis, each step Newton's method on
    the beam direction θ and the ray's place across the beam (:func:`_beam_rays`), so a chief ray from beyond 90° (a
    fisheye's, seen from behind the first vertex) is found as one below. Returns ({index: angle}, {index:
    :class:`_BeamStop`}) for the heights reached and those beyond reach, with the reason.

    Only for an unfolded lens without mirrors whose fields are angles of an object at infinity."""
    wl = lens.primary_wavelength if wavelength is None else wavelength
    ep_z = float(paraxial.stop_to_entrance_pupil(lens, wl)[0].detach())
    tol = HEIGHT_TOL * max(1.0, max((abs(float(v)) for v in heights), default=1.0))
    order = sorted(range(len(heights)), key=lambda i: abs(float(heights[i])))
    solved: dict[int, float] = {}
    beyond: dict[int, _BeamStop] = {}
    h_cur, th_cur, s_cur = 0.0, 0.0, 0.0
    slope = None  # dθ/dh of the last two solved points: the predictor of the next start
    stop = None
    for i in order:
        target = abs(float(heights[i]))
        if stop is not None:  # a smaller height was already beyond reach
            beyond[i] = stop
            continue
        step = max(target - h_cur, 0.0) / 8.0 if target > h_cur else 0.0
        why = ""
        while h_cur < target - tol:
            h_next = min(target, h_cur + step)
            th0 = th_cur + (slope * (h_next - h_cur) if slope is not None else 0.0)
            th, s, ok, why_k = _beam_newton(lens, h_next, th0, s_cur, ep_z, wl, tol)
            if not ok and slope is not None:  # the predictor overshot: from the last solved ray
                th, s, ok, why_k = _beam_newton(lens, h_next, th_cur, s_cur, ep_z, wl, tol)
            if ok:
                if h_next > h_cur:
                    slope = (th - th_cur) / (h_next - h_cur)
                h_cur, th_cur, s_cur = h_next, th, s
                step = min(1.5 * step, target - h_cur) if h_cur < target else step
            else:
                why = why_k
                step *= 0.5
                if step < MIN_HEIGHT_STEP * target:
                    break
        if h_cur >= target - tol:
            solved[i] = math.degrees(th_cur)
            continue
        rate = _height_slope(lens, th_cur, s_cur, ep_z, wl)
        if math.isfinite(rate) and rate <= 1e-6 * max(1.0, h_cur):
            why = "the image height stops growing with the field angle (its largest)"
        stop = _BeamStop(h_cur, math.degrees(th_cur), why)
        beyond[i] = stop
    return solved, beyond
