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
from raywave.lens.sources import chief_ray
from raywave.rays.bundle import RayBundle
from raywave.utils.checks import MAX_FIELD_ANGLE

#: Image-height tolerance of the real chief-ray solve (mm).
HEIGHT_TOL = 1e-12
#: Newton / secant iterations at most (each converges in a handful; a height beyond reach stops early).
MAX_ITER = 60
#: The largest angle the solve tries (degrees): rays are aimed with tan θ.
ANGLE_LIMIT = MAX_FIELD_ANGLE - 1e-6
IMAGE_HEIGHT_TYPES = ("paraxial_image_height", "real_image_height")


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
    image surface at ``wavelength`` (µm, default primary), and the indices of the heights no chief ray reaches.

    An unfolded lens without mirrors: Newton's method on the meridional ray through the stop centre
    (:func:`_solve_newton`). Otherwise a secant iteration in tan θ (or object height) on raywave's aimed chief rays,
    all heights at once, from the paraxial estimate; a step to a vignetted or non-finite field is halved back
    toward the last good one."""
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
    if not (lens.is_folded or lens.has_mirrors):
        t, done = _solve_newton(lens, h, k, wl)
        missed = [i for i in range(len(heights)) if not bool(done[i])]
        fields = [sg * float(f) for sg, f in zip(sign, _to_field(lens, t))]
        if not missed:
            return fields, []
        # a strongly aberrated pupil (a fisheye's) can defeat the meridional Newton start: the aimed secant
        again, still = _solve_secant(lens, h[missed], k, wl)
        for j, i in enumerate(missed):
            fields[i] = sign[i] * again[j]
        return fields, [missed[j] for j in still]
    again, still = _solve_secant(lens, h, k, wl)
    return [sg * f for sg, f in zip(sign, again)], still


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
    else:
        fields, missed = solve_real_image_heights(lens, heights)
    if missed:
        # the solve tries angles below 90° (each trial beyond would aim a fisheye's chief ray by continuation from the
        # axis, minutes per height); angle fields beyond 90° are read as given (raywave.lens.sources)
        unit = "angles below 90°" if lens.field_type == "angle" else "object heights"
        warnings.warn(FieldSolveWarning(
            f"{where}: no chief ray at {', '.join(unit.split()[:1])} reaches the image height"
            f"{'s' if len(missed) > 1 else ''} {', '.join(f'{heights[i]:g} mm' for i in missed)} "
            f"({kind.replace('_', ' ')}; the solve tries {unit}): left out of the lens's fields"), stacklevel=2)
    keep = [i for i in range(len(heights)) if i not in missed] or [0]
    lens.fields = [fields[i] if i not in missed else 0.0 for i in keep]
    lens.field_definition = {"type": kind, "values": [heights[i] if i not in missed else 0.0 for i in keep]}
