"""Point sources: rays from a field point into the entrance pupil, aimed at the aperture stop.

Field conventions (as OpticStudio):

* ``field_type="angle"``: (θx, θy) in degrees; the chief ray in object space travels along
  (tan θx, tan θy, 1), so a positive θy images at +y (the object point is at -y: the image is inverted).
* ``field_type="object_height"``: (hx, hy) in mm on the object plane (finite objects only).

Pupil coordinates (px, py) are normalised to the stop: a ray with pupil coordinates (px, py) passes the
stop surface at (px, py)·R_stop, found by Newton iteration on the ray's crossing point with the paraxial
entrance-pupil plane ("ray aiming"). ``aim="paraxial"`` skips the iteration and samples the paraxial
entrance pupil uniformly instead (as OpticStudio with ray aiming off).

Batch shape of every bundle made here: (F, W, N) = (fields, wavelengths, pupil samples).
For a distant object the starting OPL is measured from the plane wavefront through the first vertex
(global origin); for a finite object from the object point.
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens import paraxial
from raywave.rays import pupil as pupil_patterns
from raywave.rays.bundle import RayBundle
from raywave.utils.checks import MAX_FIELD_ANGLE, MAX_WIDE_FIELD_ANGLE, wavelengths_um

AIM_MAX_ITER = 30


class VignettingWarning(UserWarning):
    """Every ray of a point source is vignetted or misses the lens."""


AIM_TOL = 1e-12  # mm, on the stop


def _as_fields(field, dtype, device) -> torch.Tensor:
    f = torch.as_tensor(field, dtype=dtype, device=device)
    if f.ndim == 0:
        f = torch.stack([torch.zeros_like(f), f])
    if f.ndim == 1:
        if f.shape[0] != 2:
            raise ValueError(f"a field point is (x, y); got {tuple(f.shape)} values")
        f = f[None]
    return f  # (F, 2)


def object_distance(lens, depth=None) -> float:
    """The object distance (mm from the first vertex, ``inf`` for a distant object): ``depth`` when given,
    else the lens's own."""
    if depth is None:
        return lens.object_distance
    depth = float(depth)
    if not depth > 0:
        raise ValueError(f"object depth must be > 0 mm (or inf), got {depth!r}")
    return depth




def check_field_angles(fields, distant: bool = False) -> None:
    """Raise ValueError for a field angle (degrees, any shape) that is not finite or out of range: below 90° in
    magnitude for a finite object (the object point is placed with tan θ: 90° is a point at infinity on the object
    plane), below 180° for an object at infinity (``distant``: a fisheye's field beyond 90°, light from behind the
    first vertex; 180° would be the axis seen backward)."""
    f = torch.as_tensor(fields, dtype=torch.float64, device="cpu").detach().reshape(-1)
    limit = MAX_WIDE_FIELD_ANGLE if distant else MAX_FIELD_ANGLE
    bad = ~torch.isfinite(f) | (f.abs() >= limit)
    if bool(bad.any()):
        why = ("" if distant else f"; beyond {MAX_FIELD_ANGLE:g}° only for an object at infinity (a fisheye's field "
               "seen from behind the first vertex)")
        raise ValueError(f"field angle {float(f[bad][0])!r}° is not a field angle: angles must be finite and "
                         f"between -{limit:g}° and {limit:g}° (exclusive){why}")


def wide_fields(fields) -> torch.Tensor:
    """(F,) bool: angle fields (F, 2) in degrees at or beyond 90° (either component): their collimated beam travels
    sideways or backward (d_z <= 0), so their rays are parametrised on the plane through the paraxial entrance-pupil
    centre perpendicular to the beam (:func:`beam_basis`) instead of the entrance-pupil plane z = ep_z."""
    return (fields.abs() >= MAX_FIELD_ANGLE).any(-1)


def beam_direction(fields: torch.Tensor) -> torch.Tensor:
    """Unit directions (F, 3) of collimated beams at angle fields (F, 2) (degrees), as OpticStudio defines them:
    tan θx = l/n, tan θy = m/n, with n < 0 where either angle is beyond 90° (θ in (-180°, 180°)). Below 90° this is
    (tan θx, tan θy, 1) normalised; a single-axis field at or beyond 90° is (sin θ, cos θ) in its plane."""
    t = torch.tan(torch.deg2rad(fields))
    d = torch.stack([t[:, 0], t[:, 1], torch.ones_like(t[:, 0])], -1)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    wide = wide_fields(fields)
    if bool(wide.any()):
        rad = torch.deg2rad(fields)
        s, c = torch.sin(rad), torch.cos(rad)
        zero = torch.zeros_like(s[:, 0])
        along_y = torch.stack([zero, s[:, 1], c[:, 1]], -1)  # θx = 0
        along_x = torch.stack([s[:, 0], zero, c[:, 0]], -1)  # θy = 0
        both = -d  # both angles set: the same l/n, m/n with n < 0
        d_wide = torch.where((fields[:, 0] == 0)[:, None], along_y,
                             torch.where((fields[:, 1] == 0)[:, None], along_x, both))
        d = torch.where(wide[:, None], d_wide, d)
    return d


def beam_basis(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(e1, e2), each (F, 3): an orthonormal basis of the plane perpendicular to the beam directions ``d`` (F, 3),
    the images of x̂ and ŷ under the rotation about ẑ × d that takes ẑ to d (continuous in the field angle; a
    meridional y field has e1 = x̂, e2 = (0, cos θ, -sin θ)). Defined for d ≠ ±ẑ."""
    dx, dy, dz = d.unbind(-1)
    s2 = dx * dx + dy * dy
    s2 = torch.where(s2 > 0, s2, torch.ones_like(s2))
    # Rodrigues: R v = v cos α + (a × v) sin α + a (a·v)(1 - cos α), a = (-dy, dx, 0)/sin α, cos α = dz
    k = (1.0 - dz) / s2  # (1 - cos α) / sin² α
    e1 = torch.stack([dz + k * dy * dy, -k * dx * dy, -dx], -1)
    e2 = torch.stack([-k * dx * dy, dz + k * dx * dx, -dy], -1)
    return e1, e2


def _directions_and_points(lens, fields, field_type, ep_z, dtype, depth=None):
    """Per field: chief-ray direction (F,3) for distant objects, or object point (F,3) for finite ones."""
    dist = object_distance(lens, depth)
    if field_type == "angle":
        check_field_angles(fields, distant=math.isinf(dist))
    if math.isinf(dist):
        if field_type != "angle":
            raise ValueError("a distant object (object distance inf) needs angle fields, not object heights")
        return beam_direction(fields), None
    z_obj = -dist
    if field_type == "angle":
        t = torch.tan(torch.deg2rad(fields))
        xy = t * (z_obj - ep_z)
    else:
        xy = fields
    z_pts = torch.full_like(xy[:, :1], z_obj)
    c = getattr(lens, "object_curvature", 0.0) if depth is None else 0.0
    if c:  # a lens file's curved object surface: the object point lies on it (sphere of curvature c)
        r2 = (xy * xy).sum(-1, keepdim=True)
        z_pts = z_pts + c * r2 / (1.0 + torch.sqrt(torch.clamp(1.0 - c * c * r2, min=0.0)))
    pts = torch.cat([xy, z_pts], -1)
    return None, pts


def _wide_start_distance(lens, ep_z: float) -> float:
    """How far (mm) before the plane across the beam a wide field's ray starts: beyond the first surface (a sphere
    around the origin of radius |ep_z| + four times the first surface's size). Where it starts matters little: the
    ray meets the first surface's front (its entry crossing, found from any point of its line) and its optical path
    is counted from the plane wavefront through the origin."""
    first = lens.surfaces[0]
    size = max(x for x in (first.clear_radius(), first.semi_diameter, 1.0) if x is not None)
    return abs(ep_z) + 4.0 * size + 1.0


def to_beam_coordinates(uv: torch.Tensor, fields: torch.Tensor, ep_z: float) -> torch.Tensor:
    """The coordinates (F, W, N, 2) mm on the plane across the beam (:func:`beam_basis`, through (0, 0, ep_z)) of the
    rays of angle ``fields`` (F, 2) given by ``uv`` (F, W, N, 2) in their own parametrisation (the entrance-pupil
    plane below 90°, the plane across the beam at or beyond): a ray's place in a continuation in field angle."""
    wide = wide_fields(fields)
    d = beam_direction(fields)
    e1, e2 = (e[:, None, None, :] for e in beam_basis(d))
    p = torch.cat([uv, torch.zeros_like(uv[..., :1])], -1)  # crossing of z = ep_z, relative to (0, 0, ep_z)
    across = torch.stack([(p * e1).sum(-1), (p * e2).sum(-1)], -1)
    return torch.where(wide[:, None, None, None], uv, across)


def from_beam_coordinates(s: torch.Tensor, fields: torch.Tensor, ep_z: float) -> torch.Tensor:
    """Inverse of :func:`to_beam_coordinates`: the ``uv`` (F, W, N, 2) of the rays of ``fields`` (F, 2) whose
    coordinates on the plane across their beam are ``s`` (F, W, N, 2)."""
    wide = wide_fields(fields)
    d = beam_direction(fields)
    e1, e2 = (e[:, None, None, :] for e in beam_basis(d))
    q = s[..., :1] * e1 + s[..., 1:2] * e2  # relative to (0, 0, ep_z)
    dz = d[:, None, None, 2:3]
    uv = (q - d[:, None, None, :] * (q[..., 2:3] / torch.where(dz > 0, dz, torch.ones_like(dz))))[..., :2]
    return torch.where(wide[:, None, None, None], s, uv)


def entrance_plane_z(lens) -> float:
    """z (mm) of the paraxial entrance-pupil plane, where ``uv`` coordinates of :func:`rays_through` live."""
    return float(paraxial.stop_to_entrance_pupil(lens, lens.primary_wavelength)[0].detach())


def source_weight(lens, rays: RayBundle, depth=None) -> torch.Tensor:
    """Power per unit area of the entrance-pupil plane carried by each ray of :func:`rays_through` (relative).

    A distant object is a plane wave: uniform, ∝ the direction cosine d_z. A point source radiating
    isotropically gives ∝ cos θ / r² on a plane at distance r along the ray, i.e. d_z³ / Δz². Shape S."""
    dz = rays.d[..., 2]
    dist = object_distance(lens, depth)
    if math.isinf(dist):  # per unit area of the entrance-pupil plane; of the plane across the beam beyond 90°
        return torch.where(dz > 0, dz, torch.ones_like(dz))
    gap = entrance_plane_z(lens) + dist
    return dz**3 / gap**2


def _source_part(lens, fields, field_type, wavelength, dtype=torch.float64, depth=None, ep_z: float | None = None):
    """What :func:`rays_through` computes from the sources alone (not from their rays' ``uv``): ``(wavelengths
    (F or 1, W, 1) µm, ep_z mm, beam directions (F, 3) or None, object points (F, 3) or None, wide fields (F,) bool
    or None where none is wide, the object medium's index)``; an iteration over ``uv`` (ray aiming) takes it once."""
    device = lens.device
    wl = torch.as_tensor(wavelength, dtype=dtype, device=device)
    wl = wl if wl.ndim == 3 else wl.reshape(1, -1, 1)  # (F, 1, 1): a wavelength per field row
    ep_z = entrance_plane_z(lens) if ep_z is None else float(ep_z)
    d_inf, pts = _directions_and_points(lens, fields, field_type, ep_z, dtype, depth)
    wide = None
    if d_inf is not None:
        w = wide_fields(torch.as_tensor(fields, dtype=dtype, device=device).reshape(-1, 2))
        wide = w if bool(w.any()) else None
    n0 = lens.object_material.n(wl).to(dtype)
    return wl, ep_z, d_inf, pts, wide, n0


def rays_through(lens, uv: torch.Tensor, fields, field_type, wavelength, dtype=torch.float64, depth=None,
                 ep_z: float | None = None, source: tuple | None = None) -> RayBundle:
    """Rays from each field point crossing the entrance-pupil plane at ``uv`` (F, W, N, 2) (mm).

    ``ep_z``: the entrance-plane z (:func:`entrance_plane_z`) when the caller already has it (it costs a
    paraxial trace). ``source``: :func:`_source_part` of these arguments when the caller has it (an iteration
    over ``uv``: the sources' directions, checks and index once, not once per step)."""
    device = lens.device
    wl, ep_z, d_inf, pts, wide, n0 = (_source_part(lens, fields, field_type, wavelength, dtype, depth, ep_z)
                                      if source is None else source)
    F, W, N = uv.shape[:3]
    target = torch.cat([uv, torch.full_like(uv[..., :1], ep_z)], -1)
    if d_inf is not None:
        d = d_inf[:, None, None, :].expand(F, W, N, 3)
        z_start = min(ep_z, 0.0) - 1.0
        o = target + d * ((z_start - ep_z) / d[..., 2:3])
        if wide is not None:  # uv on the plane across the beam through (0, 0, ep_z); start well before the lens
            e1, e2 = (e[:, None, None, :] for e in beam_basis(d_inf))
            across = target.new_tensor([0.0, 0.0, ep_z]) + uv[..., :1] * e1 + uv[..., 1:2] * e2
            o = torch.where(wide[:, None, None, None], across - d * _wide_start_distance(lens, ep_z), o)
        opl = n0 * (o * d).sum(-1)  # distance from the plane wavefront through the origin
    else:
        o = pts[:, None, None, :].expand(F, W, N, 3)
        d = target - o
        d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
        opl = torch.zeros((F, W, N), dtype=dtype, device=device)
    return RayBundle.create(o, d, wl, opl=opl, dtype=dtype, device=device)


def _stop_hit(lens, uv, fields, field_type, wavelength, depth=None, ep_z=None, source=None):
    rays = rays_through(lens, uv, fields, field_type, wavelength, depth=depth, ep_z=ep_z, source=source)
    out = lens.trace(rays, stop=lens.stop_index + 1, apertures=False)
    if lens.is_folded:  # the stop's own frame: its centre is the origin of its local x, y
        out = lens.surface_coordinates(out, lens.stop_index)
    return out.o[..., :2], out.valid


def _newton_aim(lens, uv, target, fields, field_type, wavelength, h, depth=None, ep_z=None, source=None):
    """Solve stop_hit(uv) = target for uv (F, W, N, 2) by Newton with a finite-difference Jacobian. ``source``:
    :func:`_source_part` of these sources when the caller has it."""
    dx, dy = torch.tensor([[h, 0.0], [0.0, h]], dtype=uv.dtype, device=uv.device)  # the finite-difference steps
    n = uv.shape[-2]
    # what the sources alone decide (directions, checks, index) and the target's scale: once, not every step
    if source is None:
        source = _source_part(lens, fields, field_type, wavelength, depth=depth, ep_z=ep_z)
    scale = max(1.0, float(target.abs().max()))
    for _ in range(AIM_MAX_ITER):
        # the rays and their two finite-difference neighbours in one trace (each ray is traced on its own)
        p3, v3 = _stop_hit(lens, torch.cat([uv, uv + dx, uv + dy], dim=-2), fields, field_type, wavelength, depth,
                           ep_z, source)
        p, v, px, py = p3[..., :n, :], v3[..., :n], p3[..., n:2 * n, :], p3[..., 2 * n:, :]
        err = p - target
        conv = err.abs().amax(-1) <= AIM_TOL * scale
        if bool((conv | ~v).all()):
            break  # p, v are those of the final uv
        j = torch.stack([(px - p) / h, (py - p) / h], -1)  # (..., 2 out, 2 in)
        det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
        good = v & (det.abs() > 1e-300)
        det = torch.where(good, det, torch.ones_like(det))
        du = (j[..., 1, 1] * err[..., 0] - j[..., 0, 1] * err[..., 1]) / det
        dv = (-j[..., 1, 0] * err[..., 0] + j[..., 0, 0] * err[..., 1]) / det
        step = torch.stack([du, dv], -1)
        uv = torch.where(good[..., None], uv - step, uv)
    else:  # the last step moved uv: its stop hits
        p, v = _stop_hit(lens, uv, fields, field_type, wavelength, depth, ep_z, source)
    ok = v & ((p - target).abs().amax(-1) <= 1e-9 * scale)
    return uv, ok


def aim_chief_rays(lens, fields, field_type, wavelength, depth=None, ep_z=None,
                   source: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Entrance-plane crossing (F, W, 1, 2) of each chief ray, aimed at the stop centre; with continuation
    in field (0 → full) for wide-angle lenses where the paraxial guess misses. ``source``: :func:`_source_part`
    of these sources when the caller has it."""
    F = fields.shape[0]
    W = torch.as_tensor(wavelength).numel()
    r_ep = 0.5 * paraxial.entrance_pupil_diameter(lens)
    h = 1e-7 * max(r_ep, 1e-3)
    uv = torch.zeros((F, W, 1, 2), dtype=torch.float64, device=lens.device)
    target = torch.zeros_like(uv)
    uv1, ok = _newton_aim(lens, uv, target, fields, field_type, wavelength, h, depth, ep_z, source)
    if bool(ok.all()):
        return uv1, ok
    uv_c = uv.clone()
    wide = field_type == "angle" and bool(wide_fields(fields).any())
    if wide:
        return _aim_adaptive(lens, uv, target, fields, field_type, wavelength, h, depth, ep_z)
    for frac in (0.1, 0.2, 0.35, 0.5, 0.65, 0.8, 0.9, 1.0):
        uv_c, ok = _newton_aim(lens, uv_c, target, fields * frac, field_type, wavelength, h, depth, ep_z)
    rows = ~ok.reshape(F, -1).all(-1)
    if field_type == "angle" and bool(rows.any()):  # those fields again, by adaptive steps (a fisheye's below 90°)
        wl_rows = wavelength[rows] if torch.is_tensor(wavelength) and wavelength.ndim == 3 else wavelength
        uv_a, ok_a = _aim_adaptive(lens, uv[rows], target[rows], fields[rows], field_type, wl_rows, h, depth, ep_z)
        uv_c, ok = uv_c.clone(), ok.clone()
        uv_c[rows], ok[rows] = uv_a, ok_a
    return uv_c, ok


def _aim_adaptive(lens, uv, target, fields, field_type, wavelength, h, depth, ep_z):
    """(uv (F, W, 1, 2), ok (F, W, 1)) of the chief rays of angle ``fields`` (F, 2) aimed by adaptive steps in field
    from the axis, each start carried over on the plane across the beam (the parametrisation changes at 90°, see
    rays_through); a step whose aiming fails is halved, down to :data:`WIDE_MIN_STEP`. For a field at or beyond 90°,
    or one whose fixed steps fail (a fisheye's pupil moves far from its paraxial place)."""
    ep = entrance_plane_z(lens) if ep_z is None else float(ep_z)
    done, step = 0.0, 0.1
    good = uv.clone()
    ok = torch.zeros(uv.shape[:3], dtype=torch.bool, device=uv.device)
    while done < 1.0 and step >= WIDE_MIN_STEP:
        frac = min(1.0, done + step)
        trial = from_beam_coordinates(to_beam_coordinates(good, fields * done, ep), fields * frac, ep)
        trial, ok = _newton_aim(lens, trial, target, fields * frac, field_type, wavelength, h, depth, ep_z)
        if bool(ok.all()):
            good, done, step = trial, frac, min(0.25, 1.5 * step)
        else:
            step *= 0.5
    if done < 1.0:
        return from_beam_coordinates(to_beam_coordinates(good, fields * done, ep), fields, ep), ok & False
    return good, ok


#: The smallest continuation step (fraction of the field) when aiming a field at or beyond 90°.
WIDE_MIN_STEP = 1e-3


def _pupil_samples(lens, pupil, generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised pupil coordinates (px, py), each (N,) float64 (1 = the stop's rim), from ``(pattern, n)``
    (:func:`raywave.rays.pupil.sample`, rim samples inset by the rim rule) or explicit ``(px, py)`` tensors (traced
    as given: a caller that needs the exact rim, e.g. the stop edge's image, passes it; one that wants the rim rule
    applies :func:`raywave.rays.pupil.inset_rim`)."""
    if isinstance(pupil[0], str):  # a named pattern: its rim samples inset by the rim rule (raywave.rays.pupil)
        return pupil_patterns.sample(pupil[0], pupil[1], generator=generator, device=lens.device)
    return tuple(torch.as_tensor(p, dtype=torch.float64, device=lens.device).reshape(-1) for p in pupil)


def _chief_jacobian_inverse(lens, uv_c, ok_c, fields, field_type, wl, h, depth, ep_z, source=None):
    """Inverse Jacobian (F, W, 1, 2, 2) of the stop crossing (mm) with respect to the entrance-plane crossing (mm)
    at the chief rays ``uv_c`` (F, W, 1, 2) mm, by forward differences of step ``h`` mm; and ``bad`` (F, W, 1):
    fields without a usable Jacobian (chief ray not aimed, ``ok_c`` False, or singular), where the identity
    stands in. ``source``: :func:`_source_part` of these sources when the caller has it."""
    dx, dy = torch.tensor([[h, 0.0], [0.0, h]], dtype=torch.float64, device=uv_c.device)
    # the chief rays and their two neighbours in one trace (each ray is traced on its own; issue 43: one trace's
    # ops instead of three)
    p3, _ = _stop_hit(lens, torch.cat([uv_c, uv_c + dx, uv_c + dy], dim=-2), fields, field_type, wl, depth, ep_z,
                      source)
    p0, p1, p2 = p3.split(uv_c.shape[-2], dim=-2)
    j = torch.stack([(p1 - p0) / h, (p2 - p0) / h], -1)  # (F, W, 1, 2, 2)
    # A field whose chief ray cannot be aimed (e.g. beyond the lens's field) has no usable Jacobian.
    det = torch.linalg.det(j)
    bad = ~torch.isfinite(det) | (det.abs() < 1e-12) | ~ok_c.reshape(det.shape)
    eye = torch.eye(2, dtype=j.dtype, device=j.device).expand_as(j)
    j = torch.where(bad[..., None, None], eye, torch.nan_to_num(j))
    return torch.linalg.inv(j), bad


def _aimed_uv(lens, pn, fields, field_type, wl, aim, radii: tuple, depth, source: tuple, chief: tuple | None = None):
    """Entrance-plane crossings uv (F, W, N, 2) mm of the rays with normalised pupil coordinates ``pn``
    (F, W, N, 2), aimed as ``aim`` says (see :func:`point_source_rays`), and their validity (F, W, N): False
    where aiming failed. ``wl`` (W,) µm; ``radii`` = (entrance-pupil radius, stop radius) (mm); ``source``:
    :func:`_source_part` of these sources (its ``ep_z``, the entrance plane, included; issue 43: taken once for
    every aiming step, not once per step's function); ``chief``: these sources' :func:`chief_aim` when the caller
    has it. No autograd."""
    ep_z = source[1]
    r_ep, r_stop = radii
    valid = torch.ones(pn.shape[:3], dtype=torch.bool, device=lens.device)
    if aim == "paraxial":
        return pn * r_ep, valid
    if aim not in ("full", "chief"):
        raise ValueError(f"aim must be 'full', 'chief' or 'paraxial', got {aim!r}")
    h = 1e-6 * max(r_ep, 1e-3)
    if chief is None:
        chief = _chief_aim(lens, fields, field_type, wl, (r_ep, h), depth, ep_z, source)
    uv_c, ok_c, jinv, bad = chief
    # Linear map pupil -> entrance plane from the chief ray's Jacobian.
    valid = valid & ~bad
    uv = uv_c + torch.einsum("fwnij,fwmj->fwmi", jinv, pn * r_stop)
    if aim == "full":
        uv, ok = _newton_aim(lens, uv, pn * r_stop, fields, field_type, wl, h, depth, ep_z, source)
        valid = valid & ok
    return uv, valid & ok_c


def _chief_aim(lens, fields, field_type, wl, steps: tuple, depth, ep_z, source: tuple | None = None) -> tuple:
    """``(uv_c (F, W, 1, 2), ok_c (F, W, 1), J⁻¹ (F, W, 1, 2, 2), bad (F, W, 1))``: the chief rays aimed at the stop
    centre and the inverse Jacobian of the stop crossing around them (:func:`aim_chief_rays`,
    :func:`_chief_jacobian_inverse`); ``steps`` = (entrance-pupil radius mm, finite-difference step mm);
    ``source``: :func:`_source_part` of these sources when the caller has it."""
    uv_c, ok_c = aim_chief_rays(lens, fields, field_type, wl, depth, ep_z, source)
    jinv, bad = _chief_jacobian_inverse(lens, uv_c, ok_c, fields, field_type, wl, steps[1], depth, ep_z, source)
    return uv_c, ok_c, jinv, bad


def chief_aim(lens, field=(0.0, 0.0), wavelength=None, field_type: str | None = None, depth=None) -> tuple:
    """The chief rays' aim that :func:`point_source_rays` computes for these sources (``aim`` "full" or "chief"):
    pass it as its ``chief`` to several ray sets of the same sources (the same ``field``, ``wavelength``,
    ``field_type`` and ``depth``), which then share one aiming (issue 43: a map's footprints, edge rays and stop
    grids), each with the values its own call gives. No autograd."""
    field_type = field_type or lens.field_type
    fields = _as_fields(field, torch.float64, lens.device)
    wl = torch.as_tensor(lens.primary_wavelength if wavelength is None else wavelength, dtype=torch.float64,
                         device=lens.device).reshape(-1)
    r_ep = 0.5 * paraxial.entrance_pupil_diameter(lens)
    with torch.no_grad():
        return _chief_aim(lens, fields, field_type, wl, (r_ep, 1e-6 * max(r_ep, 1e-3)), depth, entrance_plane_z(lens))


def _warn_dead_fields(rays: RayBundle, fields: torch.Tensor, wl: torch.Tensor) -> None:
    """One :class:`VignettingWarning` (attributed to :func:`point_source_rays`'s caller) for the first
    (field (F, 2), wavelength (W,) µm) pair of which no ray of ``rays`` (F, W, N) is valid."""
    F, W = fields.shape[0], wl.numel()
    dead = ~rays.valid.reshape(F, W, -1).any(-1)
    if bool(dead.any()):
        fi, wi = (int(v) for v in dead.nonzero()[0])
        wide = ("; a field at or beyond 90° reaches the stop only through a first surface curved enough to take light "
                "from behind its vertex (a fisheye's front element)" if bool(wide_fields(fields[fi:fi + 1]).any())
                else "")
        warnings.warn(f"field {fields[fi].tolist()} at {float(wl[wi]):g} µm: every ray is vignetted or misses the "
                      f"lens (none reaches the stop){wide}; results for it are empty", VignettingWarning, stacklevel=3)


def point_source_rays(
    lens,
    field=(0.0, 0.0),
    wavelength=None,
    pupil=("grid", 21),
    field_type: str | None = None,
    aim: str = "full",
    generator: torch.Generator | None = None,
    dtype=torch.float64,
    depth: float | None = None,
    chief: tuple | None = None,
) -> RayBundle:
    """Rays from field point(s) through the pupil, shape (F, W, N).

    Args:
        field: (x, y) or (F, 2): degrees (angle fields) or mm (object heights), see the module docstring.
        wavelength: µm, scalar or (W,) (default: the lens's primary wavelength).
        pupil: ``(pattern, n)`` (see :func:`raywave.rays.pupil.sample`) or explicit ``(px, py)`` tensors.
        depth: object distance (mm from the first vertex; ``inf``: distant) overriding the lens's own.
        aim: "full" (every ray aimed at its stop point), "chief" (chief ray aimed, pupil mapped linearly
            around it), or "paraxial" (paraxial entrance pupil).
        chief: :func:`chief_aim` of these sources (the same ``field``, ``wavelength``, ``field_type``, ``depth``),
            when several ray sets share it.
    Rays whose aiming fails (vignetted in front of the stop) are returned invalid.
    """
    field_type = field_type or lens.field_type
    fields = _as_fields(field, torch.float64, lens.device)
    if wavelength is not None and not isinstance(wavelength, torch.Tensor):
        wavelengths_um(wavelength)  # the one wavelength check (a tensor comes from raywave's own code)
    wl = torch.as_tensor(lens.primary_wavelength if wavelength is None else wavelength, dtype=torch.float64,
                         device=lens.device).reshape(-1)
    px, py = _pupil_samples(lens, pupil, generator)
    F, W, N = fields.shape[0], wl.numel(), px.numel()
    r_ep = 0.5 * paraxial.entrance_pupil_diameter(lens)
    ep_z = entrance_plane_z(lens)  # once: every aiming iteration needs it
    r_stop = lens.stop_radius()
    pn = torch.stack([px, py], -1)[None, None].expand(F, W, N, 2)
    # what the sources alone decide (their checks, directions, the object medium's index): once for the aiming
    # and the rays (issue 43)
    source = _source_part(lens, fields, field_type, wl, depth=depth, ep_z=ep_z)
    with torch.no_grad():
        uv, valid = _aimed_uv(lens, pn, fields, field_type, wl, aim, (r_ep, r_stop), depth, source, chief)
    uv = torch.nan_to_num(uv.detach())
    rays = rays_through(lens, uv, fields, field_type, wl, dtype=dtype, depth=depth, ep_z=ep_z,
                        source=source if dtype == torch.float64 else None)
    if not bool(valid.all()):
        rays = rays.replace(valid=rays.valid & valid)
    _warn_dead_fields(rays, fields, wl)
    return rays


def chief_pupil(lens) -> tuple[torch.Tensor, torch.Tensor]:
    """The pupil sample ``(px, py)`` of the chief ray: the stop centre, (1,) float64 each on the lens's device."""
    zero = torch.zeros(1, dtype=torch.float64, device=lens.device)
    return zero, zero


def chief_ray(lens, field=(0.0, 0.0), wavelength=None, field_type: str | None = None, depth=None) -> RayBundle:
    """The chief ray(s) (F, W, 1): aimed at the centre of the stop."""
    return point_source_rays(lens, field, wavelength, pupil=chief_pupil(lens), field_type=field_type, aim="full",
                             depth=depth)


def marginal_rays(lens, field=(0.0, 0.0), wavelength=None, field_type: str | None = None) -> RayBundle:
    """The four marginal rays (F, W, 4) at pupil (0, 1), (0, -1), (1, 0), (-1, 0) (edge of the stop)."""
    px = torch.tensor([0.0, 0.0, 1.0, -1.0], dtype=torch.float64, device=lens.device)
    py = torch.tensor([1.0, -1.0, 0.0, 0.0], dtype=torch.float64, device=lens.device)
    return point_source_rays(lens, field, wavelength, pupil=(px, py), field_type=field_type, aim="full")
