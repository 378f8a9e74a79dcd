"""The sequential lens: surfaces + media + stop + sensor plane, and the float64 ray tracer."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import nn

from raywave.materials.base import Air, Material
from raywave.rays.bundle import RayBundle
from raywave.surfaces.surface import Surface
from raywave.utils import devices
from raywave.utils.checks import wavelength_um, wavelengths_um


#: Rays per chunk when tracing large bundles on the CPU (see Lens._trace_chunked): small temporaries stay in the
#: caches and the allocator's pool (measured: a 1.7M-ray trace of the bundled asphere 1.7 s at 65536, 2.0 s at 4×,
#: 3.3 s unchunked, one thread).
TRACE_CHUNK = 65536
#: Rays per chunk on an accelerator (CUDA): there every op is a kernel launch and the host's loop over chunks is
#: what costs (issue 43: the Newton rounds of a 10×10×3 map trace ~10⁶ rays); this bounds the temporaries (~40
#: float64 arrays of the chunk: ~1.3 GB).
TRACE_CHUNK_ACCELERATOR = 2**22


def trace_chunk(device) -> int:
    """Rays per chunk of :meth:`Lens.trace` on ``device`` (a bundle of more than twice this many is traced in
    chunks; the values do not depend on it): :data:`TRACE_CHUNK` on the CPU, :data:`TRACE_CHUNK_ACCELERATOR`
    elsewhere."""
    return TRACE_CHUNK_ACCELERATOR if devices.accelerator(device) else TRACE_CHUNK


class LensGeometryWarning(UserWarning):
    """Surfaces that overlap at their edges (beyond any hard aperture): a lens file's drawing sizes, not an error."""


@dataclass
class TraceRecord:
    """Positions of the rays at every surface, for layout plots: lists of (x, y, z) tensors and masks."""

    points: list
    valid: list



def _interact(surface, point: tuple, d: tuple, media: tuple, wavelength, flip: bool) -> tuple:
    """Surface ``surface``'s interaction with rays at their local ``point`` (x, y, z) mm travelling along ``d``
    (dx, dy, dz), between the media of indices ``media`` (n1, n2) at ``wavelength`` µm: ``(dx', dy', dz', extra
    optical path or None, ok)``. ``flip``: rays may travel toward −z (after a mirror), and meet the normal from
    behind: it is turned to the ray's side."""
    x, y, z = point
    dx, dy, dz = d
    nx, ny, nz = surface.geometry.normal(x, y, z)
    if flip:
        sign = torch.where(dx * nx + dy * ny + dz * nz < 0, -1.0, 1.0)
        nx, ny, nz = nx * sign, ny * sign, nz * sign
    return surface.interaction(x, y, dx, dy, dz, nx, ny, nz, *media, wavelength)

class Lens(nn.Module):
    """A sequential lens (rotationally symmetric unless a surface is a toroid, a coordinate break or a mirror
    makes it otherwise).

    Geometry: surface ``i`` has its vertex at ``z_i`` = sum of the thicknesses before it (the first vertex
    at z = 0); the image (sensor) plane is at ``z_image`` = sum of all thicknesses. Light travels toward +z,
    and toward −z after a mirror (an odd number of mirrors), where thicknesses are negative (OpticStudio's
    convention). Coordinate breaks (:class:`~raywave.surfaces.interaction.CoordinateBreak` surfaces) decentre
    and tilt the local frames of the surfaces after them (:meth:`surface_frames`); the tracer then works in
    global coordinates, transforming the rays into each surface's local frame. ``vertex_z`` and ``image_z``
    are then positions along the *unfolded* thickness axis, not global z.

    Args:
        surfaces: the surfaces in order; each carries the medium after it and its thickness.
        object_distance: mm from the object plane to the first vertex (``math.inf`` for a distant object).
        object_material: medium in front of the first surface (air).
        fields: field values for analysis (degrees if ``field_type == "angle"``, mm if "object_height").
        wavelengths: analysis wavelengths (µm); ``primary`` indexes the design wavelength.
        sensor_size: (w, h) of the sensor (mm); ``sensor_resolution``: (nx, ny) pixels.
        epd: entrance pupil diameter (mm). If given, the stop's aperture radius is set from it.
        system_aperture: instead of ``epd``, any OpticStudio system aperture type as a one-key dict
            (``{"f_number": 4}``, ``{"object_na": 0.1}``, ...; see :meth:`set_system_aperture`).
    """

    def __init__(
        self,
        surfaces: list[Surface],
        object_distance: float = math.inf,
        object_material: Material | None = None,
        fields=(0.0,),
        field_type: str = "angle",
        wavelengths=(0.4861327, 0.5875618, 0.6562725),
        primary: int = 1,
        sensor_size=None,
        sensor_resolution=None,
        epd: float | None = None,
        name: str = "",
        catalogs=None,
        system_aperture: dict | None = None,
    ):
        super().__init__()
        if len(surfaces) == 0:
            raise ValueError("a lens needs at least one surface")
        stops = [i for i, s in enumerate(surfaces) if s.is_stop]
        if len(stops) > 1:
            raise ValueError(f"a lens has one aperture stop; surfaces {stops} are all marked as stop")
        breaks = [i for i in stops if surfaces[i].interaction.kind == "coordinate_break"]
        if breaks:
            raise ValueError(f"surface {breaks[0]}: a coordinate break cannot be the aperture stop")
        if not stops:
            first = next((s for s in surfaces if s.interaction.kind != "coordinate_break"), None)
            if first is None:
                raise ValueError("a lens needs at least one surface that is not a coordinate break")
            first.is_stop = True
        self.surfaces = nn.ModuleList(surfaces)
        if not (object_distance > 0):
            raise ValueError(f"object distance must be > 0 mm (or inf), got {object_distance!r}")
        self.object_distance = float(object_distance)
        self.object_material = object_material if object_material is not None else Air()
        if field_type not in ("angle", "object_height"):
            raise ValueError(f"field_type must be 'angle' or 'object_height', got {field_type!r}")
        self.field_type = field_type
        self.fields = [float(f) for f in fields]
        if field_type == "angle":
            from raywave.lens.sources import check_field_angles

            check_field_angles(self.fields, distant=math.isinf(self.object_distance))
        self.wavelengths = wavelengths_um(wavelengths, "the lens's wavelengths")
        if not 0 <= primary < len(self.wavelengths):
            raise ValueError(f"primary wavelength index {primary} out of range for {len(self.wavelengths)} wavelengths")
        self.primary = int(primary)
        self.sensor_size = None if sensor_size is None else (float(sensor_size[0]), float(sensor_size[1]))
        self.sensor_resolution = None if sensor_resolution is None else (int(sensor_resolution[0]), int(sensor_resolution[1]))
        self.name = name
        self.catalogs = list(catalogs) if catalogs else None
        self.epd = None if epd is None else float(epd)
        self.system_aperture = None
        #: the stop radius (mm) the system aperture gives where the stop's own fixed clear aperture (a .zmx stop's
        #: CLAP) is smaller and stays its hard edge (:meth:`_size_stop`): it sizes the paraxial pupil
        #: (:meth:`pupil_stop_radius`); None otherwise
        self.paraxial_stop_radius: float | None = None
        #: curvature (1/mm) of a lens file's curved object surface (finite object): object points lie on it
        self.object_curvature = 0.0
        #: curvature (1/mm) of a curved image surface (a lens file's): trace_to_image ends on it; 0: a plane
        self.image_curvature = 0.0
        #: the fields as a lens file defines them when not as angles or object heights ({"type":
        #: "real_image_height" or "paraxial_image_height", "values": heights in mm}); ``fields`` then holds the
        #: angles / object heights solved for them (raywave.lens.fields)
        self.field_definition: dict | None = None
        self.check_geometry()
        if system_aperture and self.epd is not None:
            raise ValueError("give either epd or system_aperture, not both")
        if self.epd is not None:
            self.set_entrance_pupil_diameter(self.epd)
        elif system_aperture:
            self.set_system_aperture(system_aperture)

    # ------------------------------------------------------------------ geometry
    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.is_stop)

    @property
    def primary_wavelength(self) -> float:
        return self.wavelengths[self.primary]

    @property
    def dtype(self) -> torch.dtype:
        return self.surfaces[0].thickness.dtype

    @property
    def device(self) -> torch.device:
        return self.surfaces[0].thickness.device

    @property
    def has_mirrors(self) -> bool:
        """Whether a surface reflects (``GLAS MIRROR``)."""
        return any(s.interaction.kind == "reflection" for s in self.surfaces)

    @property
    def is_folded(self) -> bool:
        """Whether a coordinate break decentres or tilts a frame (the tracer then uses :meth:`surface_frames`)."""
        return any(s.interaction.kind == "coordinate_break" and not s.interaction.is_identity for s in self.surfaces)

    def direction_signs(self) -> list[int]:
        """+1 / −1 for the object space and the medium after each surface: −1 after an odd number of mirrors
        (light travels toward −z of the local frames, thicknesses are negative)."""
        out, sign = [1], 1
        for s in self.surfaces:
            if s.interaction.kind == "reflection":
                sign = -sign
            out.append(sign)
        return out

    def wave_support_problem(self) -> str | None:
        """Why the ray-wave engine (:class:`~raywave.hybrid.hybrid_lens.HybridLens`, ``raywave psf``) cannot model
        this lens, or None.

        Folded, decentred, tilted and mirrored lenses are modelled in the image-space frame (the local frame after
        the last coordinate break, :mod:`raywave.lens.frames`): the DOE plane and the sensor lie perpendicular to
        its axis. The engine aims its chief rays with the paraxial entrance pupil and places the DOE by the
        paraxial image space, so a lens whose paraxial model is undefined (a decentred or tilted powered surface,
        :class:`~raywave.lens.paraxial.ParaxialUndefinedError`, which names the surface) is refused, as is a lens
        whose light leaves the last surface away from the image plane."""
        if self.image_curvature != 0.0:
            return (f"the image surface is curved (radius {1.0 / self.image_curvature:g} mm): the ray-wave engine "
                    "(HybridLens, raywave psf) needs a planar sensor; geometric analysis (trace_to_image, spot, "
                    "info) traces to the curved surface")
        if not (self.is_folded or self.has_mirrors):
            return None
        from raywave.lens.paraxial import ParaxialUndefinedError

        try:
            self.paraxial()
        except ParaxialUndefinedError as err:
            return (f"the ray-wave engine (HybridLens, raywave psf) needs the paraxial entrance pupil and image "
                    f"space to aim its chief rays, and {err}")
        last = self.direction_signs()[-1] * float(self.surfaces[-1].thickness.detach())
        if not last > 0:
            return (f"surface {len(self.surfaces) - 1} (the last): the image plane lies {last:g} mm from it against "
                    "the light's direction of travel (after an odd number of mirrors the last thickness must be "
                    "negative): no DOE plane fits between them")
        return None

    def surface_frames(self) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], tuple[torch.Tensor, torch.Tensor]]:
        """Global frames of the surfaces and of the image plane: ([(R_i, t_i)], (R_img, t_img)).

        ``R`` (3, 3) turns local into global directions, ``t`` (3,) is the vertex in global coordinates (mm); a
        point ``p_local`` of surface ``i`` is at ``R_i @ p_local + t_i``. The first vertex is the origin. A
        coordinate break's own frame is the one it starts from; it then applies its decentre and tilts
        (:meth:`~raywave.surfaces.interaction.CoordinateBreak.transform`), and every surface's thickness moves the
        origin along its local z. Differentiable in the thicknesses."""
        dev = self.device
        rot = torch.eye(3, dtype=torch.float64, device=dev)
        t = torch.zeros(3, dtype=torch.float64, device=dev)
        frames = []
        for s in self.surfaces:
            frames.append((rot, t))
            if s.interaction.kind == "coordinate_break":
                rc, tc = (v.to(dev) for v in s.interaction.transform())
                t = t + rot @ tc
                rot = rot @ rc
            t = t + rot[:, 2] * s.thickness
        return frames, (rot, t)

    def thicknesses(self) -> torch.Tensor:
        """(n_surfaces,) thicknesses (mm)."""
        return torch.stack([s.thickness for s in self.surfaces])

    def vertex_z(self) -> torch.Tensor:
        """(n_surfaces,) z of every vertex (mm); the first is 0."""
        t = self.thicknesses()
        return torch.cat([t.new_zeros(1), torch.cumsum(t[:-1], 0)])

    def image_z(self) -> torch.Tensor:
        """z of the image (sensor) plane (mm)."""
        return self.thicknesses().sum()

    def total_track(self) -> float:
        """First vertex to image plane (mm)."""
        return float(self.image_z().detach())

    def check_geometry(self) -> None:
        """Raise on thicknesses that make surfaces cross inside their clear apertures."""
        z = self.vertex_z().detach()
        for i, s in enumerate(self.surfaces):
            if not torch.isfinite(s.thickness).all():
                raise ValueError(f"surface {i}: thickness {float(s.thickness.detach())!r} is not finite")
        signs = self.direction_signs()
        for i, s in enumerate(self.surfaces):
            if s.interaction.kind == "ideal_lens" and signs[i] < 0:
                raise ValueError(f"surface {i}: an ideal (paraxial) lens after an odd number of mirrors is not "
                                 "supported (it is defined for light travelling toward +z)")
        for i in range(len(self.surfaces) - 1):
            a, b = self.surfaces[i], self.surfaces[i + 1]
            sign = signs[i + 1]
            if "coordinate_break" in (a.interaction.kind, b.interaction.kind):
                if a.interaction.kind == "coordinate_break" and not a.interaction.is_identity:
                    continue  # the next surface lies in another frame: no overlap test
                if b.interaction.kind == "coordinate_break":
                    continue
            if sign < 0:  # light travels toward -z: surface i+1 must lie at smaller z
                if float(a.thickness.detach()) > 0 and not a.material.is_air:
                    raise ValueError(f"surface {i}: positive thickness {float(a.thickness.detach())} mm inside glass "
                                     f"{a.material.name!r} after a mirror (light travels toward -z there: thicknesses "
                                     "after an odd number of mirrors are negative)")
                continue
            r = min(x for x in (a.clear_radius(), b.clear_radius(), 1e30) if x is not None)
            if r >= 1e30:
                r = 0.0
            # a radius set by semi-diameters (drawing sizes, or a lens file's floating aperture at its semi-diameter)
            # may lie beyond the beam: an overlap there is a warning (OpticStudio opens such files); on the axis or
            # inside a hard aperture of its own size, an error
            hard = [x.aperture.extent for x in (a, b) if x.aperture is not None and x.aperture.extent is not None
                    and not (x.semi_diameter is not None
                             and abs(x.aperture.extent - x.semi_diameter) <= 1e-12 * max(1.0, x.semi_diameter))]
            r_hard = min(hard) if hard else 0.0
            rs = torch.linspace(0, r, 65, dtype=torch.float64, device=self.device)
            zero = torch.zeros_like(rs)
            xs, ys = torch.cat([rs, zero]), torch.cat([zero, rs])  # along x and along y (toroids differ)
            rs = torch.cat([rs, rs])
            with torch.no_grad():
                za = z[i] + a.geometry.sag(xs, ys)
                zb = z[i + 1] + b.geometry.sag(xs, ys)
                ok = a.geometry.in_domain(xs, ys) & b.geometry.in_domain(xs, ys)
            gap = (zb - za)[ok]
            if float(a.thickness.detach()) < 0 and not a.material.is_air:
                raise ValueError(f"surface {i}: negative thickness {float(a.thickness.detach())} mm inside glass {a.material.name!r}")
            if gap.numel() and float(gap.min()) < -1e-9:
                where = float(rs[ok][int(torch.argmin(gap))])
                inside = (gap < -1e-9) & (rs[ok] <= max(r_hard, 0.0))
                if not bool(inside.any()):
                    warnings.warn(LensGeometryWarning(
                        f"surfaces {i} and {i + 1} overlap at their edges: at radius {where:.4g} mm (their "
                        f"semi-diameters) surface {i + 1} lies {-float(gap.min()):.4g} mm before surface {i}; rays "
                        "that reach there are traced as the surfaces are (OpticStudio opens such files)"),
                        stacklevel=3)
                    continue
                raise ValueError(
                    f"surfaces {i} and {i + 1} overlap: at radius {where:.4g} mm surface {i + 1} lies "
                    f"{-float(gap.min()):.4g} mm before surface {i} (thickness {float(a.thickness.detach()):.6g} mm too small)"
                )

    def set_system_aperture(self, aperture: dict | None) -> None:
        """Size the stop from a system aperture, as OpticStudio does: ``{"epd": mm}``, ``{"f_number": F}``
        (image space), ``{"working_f_number": F}`` (paraxial working F/#), ``{"object_na": NA}``,
        ``{"object_cone_angle": degrees}`` or ``{"float_by_stop_size": True}`` / None (the stop's aperture stays).

        The conversion to an entrance pupil diameter (:func:`raywave.lens.paraxial.epd_from_system_aperture`) is
        done now, with the current prescription, at the primary wavelength; ``self.epd`` is the result and
        ``self.system_aperture`` remembers the request (it is what :func:`raywave.lens.build.lens_to_spec`
        writes)."""
        from raywave.lens import paraxial

        if not aperture or aperture.get("float_by_stop_size"):
            self.system_aperture = None
            self.epd = None
            self.paraxial_stop_radius = None
            return
        if len(aperture) != 1:
            raise ValueError(f"a system aperture has one type, got {aperture!r}")
        (kind, value), = aperture.items()
        epd = paraxial.epd_from_system_aperture(self, kind, value)
        self._size_stop(epd)
        self.system_aperture = {kind: float(value)}

    def set_entrance_pupil_diameter(self, epd: float) -> None:
        """Size the stop so that the paraxial entrance pupil diameter is ``epd`` (mm)."""
        if not epd > 0:
            raise ValueError(f"entrance pupil diameter must be > 0 mm, got {epd!r}")
        self._size_stop(epd)
        self.system_aperture = {"epd": float(epd)}

    def _size_stop(self, epd: float) -> None:
        """Give the stop the circular radius that makes the paraxial entrance pupil ``epd`` mm wide."""
        from raywave.lens import paraxial
        from raywave.surfaces.aperture import CircularAperture

        if not epd > 0:
            raise ValueError(f"entrance pupil diameter must be > 0 mm, got {epd!r}")
        stop = self.surfaces[self.stop_index]
        m = float(paraxial.stop_to_entrance_pupil(self, self.primary_wavelength)[1].detach())
        radius = 0.5 * epd * abs(m)
        own = getattr(stop.aperture, "fixed_radius", None)
        self.paraxial_stop_radius = None
        if stop.aperture is None:
            stop.aperture = CircularAperture(radius).to(self.device)
        elif own is not None and own < radius * (1.0 - 1e-12):
            # the stop's own clear aperture (a .zmx stop's CLAP) is the beam's hard edge; the system aperture's
            # radius sizes only the paraxial pupil (paraxial_data: EPD, F/#), as in OpticStudio
            stop.aperture.set_radius(own)
            self.paraxial_stop_radius = radius
        else:
            stop.aperture.set_radius(radius)
        self.epd = float(epd)

    def set_sensor(self, size, resolution=None) -> None:
        """Set the sensor: ``size`` (w, h) in mm and ``resolution`` (nx, ny) pixels (pixel pitch = w / nx)."""
        w, h = (float(v) for v in size)
        if not (w > 0 and h > 0):
            raise ValueError(f"sensor size must be positive (mm), got {size!r}")
        if resolution is not None:
            nx, ny = (int(v) for v in resolution)
            if nx <= 0 or ny <= 0:
                raise ValueError(f"sensor resolution must be positive, got {resolution!r}")
            self.sensor_resolution = (nx, ny)
        self.sensor_size = (w, h)

    @property
    def pixel_pitch(self) -> float | None:
        """Sensor pixel pitch (mm), or None without a sensor resolution."""
        if self.sensor_size is None or self.sensor_resolution is None:
            return None
        return self.sensor_size[0] / self.sensor_resolution[0]

    def pupil_stop_radius(self) -> float:
        """The stop radius (mm) that sizes the paraxial pupil (:func:`raywave.lens.paraxial.paraxial_data`: EPD,
        exit pupil, F/#): the system aperture's, also where the stop's own fixed clear aperture (a .zmx stop's
        ``CLAP``) is smaller and cuts the beam (:meth:`stop_radius`, which the rays fill); else :meth:`stop_radius`."""
        return self.paraxial_stop_radius if self.paraxial_stop_radius is not None else self.stop_radius()

    def stop_radius(self) -> float:
        stop = self.surfaces[self.stop_index]
        r = stop.clear_radius()
        if r is None:
            raise ValueError(f"the stop (surface {self.stop_index}) has no aperture: give it one or set an entrance pupil diameter")
        if stop.aperture is not None and stop.aperture.shape == "square":
            return float(stop.aperture.half_width)
        if stop.aperture is not None and stop.aperture.shape == "circle":
            return float(stop.aperture.radius)  # its extent adds a decentre (OBDC), which sizes no pupil
        if stop.aperture is not None and stop.aperture.shape == "rectangle":
            # a fixed rectangle on the stop: the system aperture's circle (pupil_radius), else the inscribed one
            pr = stop.aperture.pupil_radius
            return float(pr) if pr is not None else float(stop.aperture.half_widths.min())
        return r

    # ------------------------------------------------------------------ media
    def indices(self, wavelength: torch.Tensor, surfaces: tuple | None = None) -> list:
        """Refractive indices [n_object, n_after_surface_0, ..., n_after_last] at ``wavelength`` (µm);
        ``surfaces`` = ``(start, stop)``: only the media that a trace through surfaces ``start .. stop-1`` meets
        (entries ``start .. stop``), the others None (a trace to the stop evaluates no glass behind it)."""
        media = [self.object_material] + [s.material for s in self.surfaces]
        lo, hi = (0, len(media) - 1) if surfaces is None else surfaces
        return [m.n(wavelength) if lo <= k <= hi else None for k, m in enumerate(media)]

    # ------------------------------------------------------------------ tracing
    def trace(self, rays: RayBundle, start: int = 0, stop: int | None = None, record: bool = False,
              apertures: bool = True, n_all: list | None = None):
        """Trace ``rays`` through surfaces ``start .. stop-1`` (default: all).

        Rays must be in the medium in front of surface ``start``. Returns the bundle at the last surface
        traced (after its interaction); with ``record=True`` also a :class:`TraceRecord`.
        Rays that miss a surface, leave an aperture or meet TIR get ``valid = False`` and stay finite.
        ``apertures=False`` ignores clear apertures (used by ray aiming). ``n_all``: the media's indices at the rays'
        wavelengths (:meth:`indices`, each broadcastable to the rays' shape) when the caller has them; a bundle
        traced in chunks takes its own.
        """
        stop = len(self.surfaces) if stop is None else stop
        n_rays = rays.valid.numel()
        if not record and n_rays > 2 * trace_chunk(rays.valid.device):
            return self._trace_chunked(rays, start, stop, apertures)
        return self._trace_kernel(rays, start, stop, record, apertures, n_all)

    def _trace_chunked(self, rays: RayBundle, start: int, stop: int, apertures: bool) -> RayBundle:
        """Trace a large bundle in chunks of :func:`trace_chunk` rays: small temporaries stay in the allocator's
        cache instead of being mapped afresh for every elementwise op (≈2× faster on CPU)."""
        shape = rays.shape
        flat = RayBundle(rays.o.reshape(-1, 3), rays.d.reshape(-1, 3),
                         torch.broadcast_to(rays.wavelength, shape).reshape(-1), rays.valid.reshape(-1),
                         rays.opl.reshape(-1))
        step = trace_chunk(flat.valid.device)
        # the media's indices once for the bundle (elementwise in the wavelength: each chunk's slice is what its own
        # evaluation gives), not once per chunk (issue 43)
        n_rays = flat.valid.numel()
        n_all = self.indices(flat.wavelength, (start, stop))
        outs = [self._trace_kernel(flat[i:i + step], start, stop, False, apertures,
                                   [n[i:i + step] if n is not None and n.ndim == 1 and n.shape[0] == n_rays else n
                                    for n in n_all])
                for i in range(0, n_rays, step)]
        return RayBundle(torch.cat([o.o for o in outs]).reshape(shape + (3,)),
                         torch.cat([o.d for o in outs]).reshape(shape + (3,)),
                         rays.wavelength,
                         torch.cat([o.valid for o in outs]).reshape(shape),
                         torch.cat([o.opl for o in outs]).reshape(shape))

    def _trace_kernel(self, rays: RayBundle, start: int, stop: int, record: bool, apertures: bool,
                      n_all: list | None = None):
        """Trace ``rays`` through surfaces ``start .. stop-1`` (:meth:`trace`); ``n_all``: the media's indices at
        the rays' wavelengths (:meth:`indices`) when the caller has them."""
        if self.is_folded:
            return self._trace_kernel_frames(rays, start, stop, record, apertures, n_all)
        wl = rays.wavelength
        mirrors = self.has_mirrors
        n_all = self.indices(wl, (start, stop)) if n_all is None else n_all
        zs = self.vertex_z().to(rays.dtype).unbind()  # each vertex's z as a 0-d view, from one op (not a select a use)
        signs = self.direction_signs() if mirrors else None
        x, y, z = rays.o.unbind(-1)
        dx, dy, dz = rays.d.unbind(-1)
        valid, opl = rays.valid, rays.opl
        rec = TraceRecord([(x, y, rays.o[..., 2])], [valid]) if record else None
        zero = one = None
        identity = self._identity_refractions()
        for i in range(start, stop):
            s = self.surfaces[i]
            if s.interaction.kind == "coordinate_break":  # an identity break: nothing happens
                if record:
                    rec.points.append((x, y, z))
                    rec.valid.append(valid)
                continue
            n1, n2 = n_all[i].to(rays.dtype), n_all[i + 1].to(rays.dtype)
            zl = z - zs[i]
            # light travelling toward +z here (no mirror before, or an even number): rays meet the surface's front
            t, ok = s.geometry.intersect(x, y, zl, dx, dy, dz, front=signs is None or signs[i] > 0)
            x, y, zl = x + t * dx, y + t * dy, zl + t * dz
            opl = opl + n1 * t
            if apertures and s.aperture is not None:
                ok = ok & s.aperture.contains(x, y)
            if identity[i]:  # refraction from air into air: the direction is kept exactly (no normal, no Snell)
                valid = valid & ok
            else:
                dx, dy, dz, extra, ok_i = _interact(s, (x, y, zl), (dx, dy, dz), (n1, n2), wl, mirrors)
                if extra is not None:
                    opl = opl + extra
                valid = valid & ok & ok_i
            z = zl + zs[i]
            # Park dead rays on the axis, at this vertex, so that later surfaces see harmless numbers (no NaN, no
            # inf, no huge z whose quadratic cancels to an exactly zero discriminant: an infinite sqrt derivative)
            if zero is None:  # 0-d constants once per trace (a Python number costs a scalar tensor per use)
                zero, one = x.new_zeros(()), x.new_ones(())
            x, y = torch.where(valid, x, zero), torch.where(valid, y, zero)
            z = torch.where(valid, z, zs[i])  # (the 0-d z broadcasts)
            opl = torch.where(valid, opl, zero)
            dx, dy, dz = torch.where(valid, dx, zero), torch.where(valid, dy, zero), torch.where(valid, dz, one)
            if record:
                rec.points.append((x, y, z))
                rec.valid.append(valid)
        out = RayBundle(torch.stack([x, y, z], -1), torch.stack([dx, dy, dz], -1), wl, valid, opl)
        return (out, rec) if record else out

    def _identity_refractions(self) -> list:
        """Per surface: True where it refracts from air into air (a stop, a dummy or a window-free aperture
        surface): Snell's law with n1 = n2 keeps every direction, so :meth:`_trace_kernel` skips it (issue 43: the
        normal and the refraction are ~30 ops a trace; only rounding differs, ~1e-16 in the directions)."""
        media = [self.object_material] + [s.material for s in self.surfaces]
        return [s.interaction.kind == "refraction" and isinstance(media[i], Air) and isinstance(media[i + 1], Air)
                for i, s in enumerate(self.surfaces)]

    def _trace_kernel_frames(self, rays: RayBundle, start: int, stop: int, record: bool, apertures: bool,
                             n_all: list | None = None):
        """The tracer for a lens with coordinate breaks: rays in global coordinates, each surface met in its local
        frame (:meth:`surface_frames`)."""
        wl = rays.wavelength
        n_all = self.indices(wl, (start, stop)) if n_all is None else n_all
        frames, _ = self.surface_frames()
        signs = self.direction_signs()
        x, y, z = rays.o.unbind(-1)
        dx, dy, dz = rays.d.unbind(-1)
        valid, opl = rays.valid, rays.opl
        rec = TraceRecord([(x, y, z)], [valid]) if record else None
        for i in range(start, stop):
            s = self.surfaces[i]
            if s.interaction.kind == "coordinate_break":
                if record:
                    rec.points.append((x, y, z))
                    rec.valid.append(valid)
                continue
            rot, tv = (v.to(rays.dtype) for v in frames[i])
            r = rot.unbind(0)
            (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = (row.unbind(0) for row in r)
            px, py, pz = x - tv[0], y - tv[1], z - tv[2]
            # into the local frame: R^T (p - t), R^T d
            xl, yl, zl = r00 * px + r10 * py + r20 * pz, r01 * px + r11 * py + r21 * pz, r02 * px + r12 * py + r22 * pz
            ex, ey, ez = r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz, r02 * dx + r12 * dy + r22 * dz
            n1, n2 = n_all[i].to(rays.dtype), n_all[i + 1].to(rays.dtype)
            t, ok = s.geometry.intersect(xl, yl, zl, ex, ey, ez, front=signs[i] > 0)
            xl, yl, zl = xl + t * ex, yl + t * ey, zl + t * ez
            opl = opl + n1 * t
            if apertures and s.aperture is not None:
                ok = ok & s.aperture.contains(xl, yl)
            ex, ey, ez, extra, ok_i = _interact(s, (xl, yl, zl), (ex, ey, ez), (n1, n2), wl, True)
            if extra is not None:
                opl = opl + extra
            valid = valid & ok & ok_i
            # dead rays: parked at the vertex, along the local axis (finite, harmless numbers)
            xl, yl, zl = torch.where(valid, xl, 0.0), torch.where(valid, yl, 0.0), torch.where(valid, zl, 0.0)
            ex, ey, ez = torch.where(valid, ex, 0.0), torch.where(valid, ey, 0.0), torch.where(valid, ez, 1.0)
            opl = torch.where(valid, opl, 0.0)
            # back to global coordinates
            x = r00 * xl + r01 * yl + r02 * zl + tv[0]
            y = r10 * xl + r11 * yl + r12 * zl + tv[1]
            z = r20 * xl + r21 * yl + r22 * zl + tv[2]
            dx, dy, dz = r00 * ex + r01 * ey + r02 * ez, r10 * ex + r11 * ey + r12 * ez, r20 * ex + r21 * ey + r22 * ez
            if record:
                rec.points.append((x, y, z))
                rec.valid.append(valid)
        out = RayBundle(torch.stack([x, y, z], -1), torch.stack([dx, dy, dz], -1), wl, valid, opl)
        return (out, rec) if record else out

    def image_frame(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(R (3, 3), t (3,)): the image plane's global frame (its vertex ``t``, its normal ``R[:, 2]``)."""
        return self.surface_frames()[1]

    def image_coordinates(self, rays: RayBundle) -> RayBundle:
        """``rays`` (global coordinates, e.g. from :meth:`trace_to_image`) in the image plane's local frame: x, y
        on the sensor, z along its normal. The identity for a lens without coordinate breaks."""
        if not self.is_folded:
            return rays
        rot, tv = (v.to(rays.dtype) for v in self.image_frame())
        return rays.replace(o=(rays.o - tv) @ rot, d=rays.d @ rot)

    def surface_coordinates(self, rays: RayBundle, index: int) -> RayBundle:
        """``rays`` (global coordinates) in the local frame of surface ``index`` (where its geometry and aperture
        are defined). The identity for a lens without coordinate breaks."""
        if not self.is_folded:
            return rays
        rot, tv = (v.to(rays.dtype) for v in self.surface_frames()[0][index])
        return rays.replace(o=(rays.o - tv) @ rot, d=rays.d @ rot)

    def require_unfolded(self, what: str, toward_plus_z: bool = False) -> None:
        """Raise a ValueError naming ``what`` if the lens has a coordinate break that decentres or tilts (for
        analyses written for one straight axis); with ``toward_plus_z`` also if the light leaves toward −z (an odd
        number of mirrors; for analyses that measure along +z), naming the last mirror."""
        if self.is_folded:
            i = next(i for i, s in enumerate(self.surfaces)
                     if s.interaction.kind == "coordinate_break" and not s.interaction.is_identity)
            raise ValueError(f"{what} is not supported for a lens with coordinate breaks (surface {i} decentres or "
                             "tilts the axis): it assumes one straight optical axis; trace real rays with "
                             "Lens.trace_to_image (and Lens.image_coordinates) instead")
        if toward_plus_z and self.direction_signs()[-1] < 0:
            i = max(i for i, s in enumerate(self.surfaces) if s.interaction.kind == "reflection")
            raise ValueError(f"{what} is not supported for a lens whose light leaves toward -z (surface {i} is the "
                             "last of an odd number of mirrors): it measures along +z; trace real rays with "
                             "Lens.trace_to_image instead")

    def trace_to_image(self, rays: RayBundle, z: float | torch.Tensor | None = None, record: bool = False):
        """Trace through all surfaces and on to the image plane (or to the plane ``z``).

        For a lens with coordinate breaks the result is in global coordinates, on the (possibly tilted) image
        plane of :meth:`image_frame`; ``z`` is then refused."""
        res = self.trace(rays, record=record)
        out, rec = res if record else (res, None)
        n_img = self.surfaces[-1].material.n(rays.wavelength).to(rays.dtype)
        if self.is_folded:
            if z is not None:
                raise ValueError("trace_to_image(z=...): a lens with coordinate breaks has no global image z; "
                                 "the rays stop on the image plane of lens.image_frame()")
            rot, tv = (v.to(rays.dtype) for v in self.image_frame())
            normal = rot[:, 2]
            s = ((tv - out.o) @ normal) / (out.d @ normal)
            out = out.replace(o=out.o + s.unsqueeze(-1) * out.d, opl=out.opl + n_img * s)
        else:
            out = out.propagate_to_z(self.image_z().to(rays.dtype) if z is None else z, n_img)
            if z is None and self.image_curvature != 0.0:
                out = self._to_curved_image(out, n_img)
        if record:
            x, y, zz = out.o.unbind(-1)
            rec.points.append((x, y, zz))
            rec.valid.append(out.valid)
            return out, rec
        return out

    def _to_curved_image(self, out: RayBundle, n_img) -> RayBundle:
        """``out`` (on the image vertex plane) carried on to the curved image surface (a sphere of curvature
        ``image_curvature``); rays that miss it become invalid."""
        from raywave.surfaces.geometry import Standard

        sphere = Standard(self.image_curvature).to(device=out.o.device, dtype=out.o.dtype).requires_grad_(False)
        x, y, zz = out.o.unbind(-1)
        dx, dy, dz = out.d.unbind(-1)
        t, ok = sphere.intersect(x, y, torch.zeros_like(zz), dx, dy, dz)
        t = torch.where(ok, t, torch.zeros_like(t))
        return out.replace(o=out.o + t.unsqueeze(-1) * out.d, opl=out.opl + n_img * t, valid=out.valid & ok)

    # ------------------------------------------------------------------ conveniences
    def paraxial(self, wavelength: float | None = None):
        """Paraxial data (EFL, BFL, pupils, ...) at ``wavelength`` (µm, default primary)."""
        from raywave.lens.paraxial import paraxial_data

        return paraxial_data(self, self.primary_wavelength if wavelength is None else wavelength_um(wavelength))

    def table(self, wavelength: float | None = None) -> str:
        """The prescription as text: one line per surface (radius, thickness, glass, semi-diameter, conic; the stop
        marked; aspheric terms below), semi-diameters traced at ``wavelength`` µm (default all the lens's);
        :mod:`raywave.lens.prescription`."""
        from raywave.lens.prescription import table  # lazy: prescription traces rays (raywave.lens.sources)

        return table(self, wavelength)

    def __str__(self) -> str:
        """The prescription (:meth:`table`; ``print(lens)``), without the traced semi-diameters if tracing fails.
        ``repr(lens)`` stays the module tree (``HybridLens.field_signature`` keys on it)."""
        try:
            return self.table()
        except Exception:  # noqa: BLE001 - a repr must not raise
            from raywave.lens.prescription import format_table, surface_table

            return format_table(self, surface_table(self, semi_diameters=False))

    def extra_repr(self) -> str:
        od = "inf" if math.isinf(self.object_distance) else f"{self.object_distance:g}"
        return f"name={self.name!r}, object_distance={od}, stop={self.stop_index}"
