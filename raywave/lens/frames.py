"""The image space of a folded, decentred, tilted or mirrored lens, seen from its own local frame.

A lens with coordinate breaks traces in global coordinates, and after an odd number of mirrors its light travels
toward −z (:class:`~raywave.lens.lens.Lens`). The ray-wave engine (:class:`~raywave.hybrid.hybrid_lens.HybridLens`)
places its DOE plane and its sensor perpendicular to one straight +z axis. Both meet in the **image-space frame**:
the local frame after the last coordinate break (the frame of the image plane), with its z axis turned to the
light's direction of travel. A rigid change of coordinates of the rays leaving the last surface (position and
direction; optical path unchanged) puts them there, and the engine then works unchanged:

* positions ``(x, y, z) = (q_x, q_y, s·q_z + z_last)``, directions ``(e_x, e_y, s·e_z)``, where ``q = Rᵀ(p − o)``
  and ``e = Rᵀ d`` are the point and the direction in the image plane's local frame (rotation ``R``, origin ``o``
  at the last vertex, OpticStudio's frame), ``s`` = ±1 the direction of travel there (−1 after an odd number of
  mirrors) and ``z_last = lens.vertex_z()[-1]``, so the last vertex stays at the z the engine expects;
* x and y are the image plane's own (OpticStudio's image-surface coordinates; a 45° fold mirror therefore gives the
  unfolded lens's x and y, and the z flip ``s`` keeps light travelling toward +z);
* the image plane lies at ``z_last + s·t_last`` (``t_last`` the last thickness, negative after an odd number of
  mirrors): :meth:`ImageSpaceLens.image_z`.

:func:`image_space` returns the lens itself for a lens without coordinate breaks and mirrors (nothing changes),
else an :class:`ImageSpaceLens`, a light view that forwards everything else to the lens.
"""

from __future__ import annotations

import torch

from raywave.rays.bundle import RayBundle


def image_space_frame(lens) -> tuple[torch.Tensor, torch.Tensor, int]:
    """(R (3, 3), origin (3,), s): the image plane's local frame in global coordinates (``R`` turns local into
    global directions) with its origin moved back to the last vertex (mm; differentiable in the thicknesses), and
    the direction of travel ``s`` (+1 / −1) along its local z."""
    _, (rot, t) = lens.surface_frames()
    origin = t - rot[:, 2] * lens.surfaces[-1].thickness.to(t.dtype)
    return rot, origin, int(lens.direction_signs()[-1])


def to_image_space(lens, rays: RayBundle, frame=None) -> RayBundle:
    """``rays`` (global coordinates, in the image space) in the image-space frame of the module docstring.

    Args:
        rays: any batch shape S; o and d (S, 3); OPL, validity and wavelength unchanged.
        frame: :func:`image_space_frame` when the caller has it."""
    rot, origin, sign = image_space_frame(lens) if frame is None else frame
    rot, origin = rot.to(rays.dtype), origin.to(rays.dtype)
    flip = torch.tensor([1.0, 1.0, float(sign)], dtype=rays.dtype, device=rays.o.device)
    z0 = lens.vertex_z()[-1].to(rays.dtype)
    q = ((rays.o - origin) @ rot) * flip
    o = torch.cat([q[..., :2], (q[..., 2] + z0).unsqueeze(-1)], -1)
    return rays.replace(o=o, d=(rays.d @ rot) * flip)


class ImageSpaceLens:
    """A lens as the ray-wave engine sees it: every full trace ends in the image-space frame (module docstring).

    Only what differs from the lens is defined here; every other attribute is the lens's own (surfaces,
    materials, paraxial data, pupils, ray aiming helpers). A trace of all surfaces (``stop=None``) returns its
    rays in the image-space frame; a partial trace (``stop`` given, e.g. ray aiming up to the stop) stays in
    global coordinates, as the lens gives it. A record (``record=True``) holds every surface's points in that
    surface's local frame (where its aperture is defined).
    """

    image_space_view = True

    def __init__(self, lens):
        object.__setattr__(self, "lens", lens)

    def __getattr__(self, name):
        return getattr(self.lens, name)

    def __setattr__(self, name, value):
        raise AttributeError(f"the image-space view of a lens is read-only (set {name!r} on the lens itself)")

    def last_thickness(self) -> torch.Tensor:
        """Distance (mm, > 0 for a real image) from the last vertex to the image plane along the light."""
        return self.lens.direction_signs()[-1] * self.lens.surfaces[-1].thickness

    def image_z(self) -> torch.Tensor:
        """z (mm) of the image plane in the image-space frame (differentiable in the thicknesses)."""
        return self.lens.vertex_z()[-1] + self.last_thickness()

    def total_track(self) -> float:
        return float(self.image_z().detach())

    def to_image_space(self, rays: RayBundle) -> RayBundle:
        """:func:`to_image_space` of ``rays`` (global coordinates)."""
        return to_image_space(self.lens, rays)

    def trace(self, rays: RayBundle, start: int = 0, stop: int | None = None, record: bool = False,
              apertures: bool = True, n_all: list | None = None):
        """:meth:`Lens.trace <raywave.lens.lens.Lens.trace>`; with ``stop=None`` the result is in the image-space
        frame (and a record's points are in their surfaces' local frames)."""
        res = self.lens.trace(rays, start=start, stop=stop, record=record, apertures=apertures, n_all=n_all)
        if stop is not None:
            return res
        out, rec = res if record else (res, None)
        out = to_image_space(self.lens, out)
        if not record:
            return out
        frames, _ = self.lens.surface_frames()
        points = list(rec.points)
        for i in range(start, len(self.lens.surfaces)):
            k = i - start + 1
            rot, t = (v.to(out.dtype) for v in frames[i])
            p = torch.stack(points[k], -1)
            q = (p - t) @ rot
            points[k] = tuple(q.unbind(-1))
        return out, type(rec)(points, rec.valid)

    def trace_to_image(self, rays: RayBundle, z=None, record: bool = False):
        """Trace all surfaces and on to the image plane (or the plane ``z`` of the image-space frame)."""
        res = self.trace(rays, record=record)
        out, rec = res if record else (res, None)
        n_img = self.lens.surfaces[-1].material.n(rays.wavelength).to(rays.dtype)
        out = out.propagate_to_z(self.image_z().to(rays.dtype) if z is None else z, n_img)
        if record:
            rec.points.append(tuple(out.o.unbind(-1)))
            rec.valid.append(out.valid)
            return out, rec
        return out

    def image_coordinates(self, rays: RayBundle) -> RayBundle:
        """The identity: this view's rays are already in the image plane's frame."""
        return rays

    def __repr__(self) -> str:
        return f"ImageSpaceLens({self.lens!r})"


def image_space(lens):
    """The lens as the ray-wave engine sees it: the lens itself without coordinate breaks (that decentre or tilt)
    and mirrors, else its :class:`ImageSpaceLens` (module docstring)."""
    if getattr(lens, "image_space_view", False):
        return lens
    if lens.is_folded or lens.has_mirrors:
        return ImageSpaceLens(lens)
    return lens
