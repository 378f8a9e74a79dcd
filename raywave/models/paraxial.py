"""Paraxial wave optics: the refractive lens as an ideal thin lens of its paraxial focal length, then the DOE,
then angular-spectrum propagation to the sensor (the model of most end-to-end "deep optics" work).

The model (per field point and wavelength λ):

1. **The thin lens.** The refractive lens is replaced by one perfect thin lens in the plane ``z_L`` with the
   lens's paraxial focal length at λ (:func:`raywave.lens.paraxial.paraxial_data`: EFL, so its chromatic
   focal shift is kept) and a circular stop of the entrance-pupil radius in that plane (a thin lens is its
   own stop and pupils). ``plane="principal"`` (default) puts it at the lens's rear principal plane H'
   (primary wavelength): the lens's exact paraxial equivalent, so the sensor's distance from the paraxial
   focus (and a DOE's focusing power) act as in the real system; ``plane="sensor"`` puts it where the lens's
   own object plane (``lens.object_distance``, usually infinity) images exactly onto the sensor
   (``z_L = z_sensor − s'``: the usual deep-optics set-up, the sensor in focus by construction).
2. **Object depth and field.** An object at ``depth`` (mm from the first vertex, i.e. ``s = depth + z_L``
   from the thin lens) images at ``s'`` from the Gaussian equation ``n'/s' = 1/EFL − n/s`` (``s' = n'·EFL``
   for a distant object), so a depth other than the lens's own defocuses the PSF. A field angle θ is the
   chief ray through the lens centre: the image point sits at ``(n/n') s' tan θ`` (``EFL·tan θ`` in air, no
   distortion); an object height h images at ``−(n s')/(n' s) h``.
3. **The field at the DOE plane.** A perfect thin lens turns the incoming wave into a perfect spherical
   wave converging to the image point (the exact sphere, not its quadratic approximation, so the model is
   exact for an ideal lens at any NA). It is carried geometrically to the DOE plane (as the ray-wave model
   carries the real wave): uniform irradiance over the stop's central projection (a disc), amplitude
   ``sqrt(1/d_z)`` (the engine's convention), an anti-aliased edge, and the DOE aperture.
4. **DOE and propagation**: exactly the engine's (:meth:`raywave.hybrid.HybridLens.propagate`): ``exp(iφ)``,
   band-limited angular spectrum to the sensor, pixel integration, crop centred on this model's own chief ray
   (the paraxial image point), sum 1. Differentiable with respect to the DOE's parameters.

What it misses by construction: every aberration of the refractive lens (and its distortion, vignetting,
pupil aberrations); so it is exact for an ideal lens and departs as the real lens's wavefront does.
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.hybrid.coherent import DOEField, FieldInfo, SamplingWarning
from raywave.lens.paraxial import entrance_pupil_diameter
from raywave.lens.sources import object_distance
from raywave.models.base import ModelPSFResult, PSFModel, lit_window, propagate_fields, window_field, window_xy
from raywave.utils.phasor import polar

__all__ = ["ParaxialModel", "thin_lens_plane"]

_PLANES = ("sensor", "principal")


def _image_index(lens, wavelength: float) -> float:
    return float(lens.surfaces[-1].material.n(torch.tensor(wavelength, dtype=torch.float64, device="cpu")).detach())


def _object_index(lens, wavelength: float) -> float:
    return float(lens.object_material.n(torch.tensor(wavelength, dtype=torch.float64, device="cpu")).detach())


def _image_distance(efl: float, n_obj: float, n_img: float, s: float) -> float:
    """Gaussian image distance s' (mm) of an object ``s`` mm in front of a thin lens (``inf``: distant)."""
    power = 1.0 / efl - (0.0 if math.isinf(s) else n_obj / s)
    if power == 0.0:
        raise ValueError(f"the object at {s:g} mm from the thin lens sits in its front focal plane: no image")
    return n_img / power


def thin_lens_plane(lens, sensor_z: float, plane: str = "principal") -> float:
    """z (mm) of the paraxial model's thin lens (see the module docstring), at the primary wavelength."""
    if plane not in _PLANES:
        raise ValueError(f"plane must be one of {_PLANES}, got {plane!r}")
    wl = lens.primary_wavelength
    pd = lens.paraxial(wl)
    if not math.isfinite(pd.efl):
        raise ValueError("the lens has no optical power (infinite EFL): the paraxial model needs a focusing lens")
    n_img, n_obj = _image_index(lens, wl), _object_index(lens, wl)
    z_last = float(lens.vertex_z()[-1].detach())
    if plane == "principal":
        return z_last + pd.bfl - n_img * pd.efl
    d0 = lens.object_distance
    z = sensor_z - n_img * pd.efl
    for _ in range(50):  # s' depends on z_L through s = d0 + z_L: a fast fixed point for d0 >> f
        z_new = sensor_z - _image_distance(pd.efl, n_obj, n_img, d0 + z)
        if abs(z_new - z) < 1e-12:
            break
        z = z_new
    return z


class ParaxialModel(PSFModel):
    """Paraxial wave optics on the hybrid lens's DOE and sensor (model in the module docstring).

    Args:
        hybrid: the :class:`~raywave.hybrid.HybridLens` (its refractive lens only gives EFL, pupil and fields).
        plane: "principal" (default) or "sensor": where the thin lens sits.
    """

    name = "paraxial"

    def __init__(self, hybrid, plane: str = "principal"):
        super().__init__(hybrid)
        if plane not in _PLANES:
            raise ValueError(f"plane must be one of {_PLANES}, got {plane!r}")
        self.plane = plane

    def thin_lens(self):
        """(z_L, stop radius) mm of the thin lens."""
        lens = self.lens
        with torch.no_grad():
            z_l = thin_lens_plane(lens, self.hybrid.sensor_z(), self.plane)
            # the beam's entrance pupil (the paraxial EPD, or its image of a stop's own smaller CLAP: class E)
            radius = 0.5 * entrance_pupil_diameter(lens, lens.primary_wavelength)
        z_doe = self.hybrid.doe_z()
        if not z_l < z_doe:
            raise ValueError(f"the paraxial model's thin lens (z = {z_l:.6g} mm) lies behind the DOE plane "
                             f"(z = {z_doe:.6g} mm): use plane='principal' or move the DOE further back")
        return z_l, radius

    def image_point(self, field, wavelength: float, depth, z_l: float):
        """Image point (x, y, z) mm of one field point (2,) at ``wavelength`` through the thin lens."""
        lens = self.lens
        with torch.no_grad():
            efl = lens.paraxial(wavelength).efl
        n_obj, n_img = _object_index(lens, wavelength), _image_index(lens, wavelength)
        dist = object_distance(lens, depth)
        s = dist + z_l
        sp = _image_distance(efl, n_obj, n_img, s)
        fx, fy = (float(v) for v in field)
        if lens.field_type == "angle":
            scale = (n_obj / n_img) * sp
            xy = (scale * math.tan(math.radians(fx)), scale * math.tan(math.radians(fy)))
        else:
            if math.isinf(s):
                raise ValueError("object-height fields need a finite object distance")
            m = -(n_obj * sp) / (n_img * s)
            xy = (m * fx, m * fy)
        return (xy[0], xy[1], z_l + sp), n_img

    def doe_field(self, field, wavelength: float, depth=None, check: bool = True) -> DOEField:
        """The :class:`~raywave.hybrid.DOEField` the thin lens delivers at the DOE plane (DOE phase not applied)."""
        hl, doe = self.hybrid, self.doe
        q = hl.oversample
        p = doe.pitch / q
        dev = doe.device
        z_l, radius = self.thin_lens()
        (px, py, pz), n = self.image_point(field, wavelength, depth, z_l)
        z_doe, z_sen = hl.doe_z(), hl.sensor_z()
        sp = pz - z_l
        t = (z_doe - z_l) / sp
        cx, cy = t * px, t * py  # the chief ray (through the lens centre) on the DOE plane
        r_doe = radius * abs(1.0 - t)
        norm = math.sqrt(px * px + py * py + sp * sp)
        alpha, beta = px / norm * math.copysign(1.0, sp), py / norm * math.copysign(1.0, sp)
        ts = (z_sen - z_l) / sp
        center = (torch.tensor(ts * px, dtype=torch.float64, device=dev),
                  torch.tensor(ts * py, dtype=torch.float64, device=dev))
        win, origin = lit_window(doe, q, (cx - r_doe, cx + r_doe, cy - r_doe, cy + r_doe), 2 * p)
        if win is None or r_doe == 0.0:
            env = torch.zeros((1, 1), dtype=torch.complex128, device=dev)
            return window_field(env, None, doe.sim_grid(q), (float(wavelength), n, (alpha, beta)), z_sen - z_doe,
                                center, FieldInfo(0, "paraxial"))
        x, y = window_xy(win, origin, p, dev)
        k = 2 * math.pi / (wavelength * 1e-3)
        dx, dy, dz = x - px, y - py, z_doe - pz
        r = torch.sqrt(dx * dx + dy * dy + dz * dz)
        r_c = math.sqrt((cx - px) ** 2 + (cy - py) ** 2 + dz * dz)
        conv = math.copysign(1.0, pz - z_doe)  # converging toward the image point (diverging past it)
        # phase of the sphere minus the carrier, both relative to the chief ray's landing point (float64)
        phase = -conv * k * n * (r - r_c) - k * n * (alpha * (x - cx) + beta * (y - cy))
        amp = torch.sqrt(r / abs(dz))  # sqrt(irradiance / d_z) with a uniform irradiance
        rho = torch.sqrt((x - cx) ** 2 + (y - cy) ** 2)
        cover = (0.5 + (r_doe - rho) / p).clamp(0.0, 1.0) * doe.coverage(win, q, device=dev)
        env = polar(amp * cover, phase)
        if check:
            # local slope of the envelope's phase at the rim against the Nyquist limit of the simulation pitch
            sx = (-conv * (x - px) / r - alpha).abs()
            sy = (-conv * (y - py) / r - beta).abs()
            ratio = float(torch.where(cover > 0, torch.maximum(sx, sy), torch.zeros_like(sx)).max()) * n * 2 * p / (
                wavelength * 1e-3)
            if ratio > 1.0:
                warnings.warn(f"paraxial model: the DOE simulation pitch {p * 1e3:g} µm under-samples the converging "
                              f"wave of field {list(map(float, field))} at {wavelength:g} µm ({ratio:.2f}× Nyquist)",
                              SamplingWarning, stacklevel=3)
        return window_field(env, win, doe.sim_grid(q), (float(wavelength), n, (alpha, beta)), z_sen - z_doe, center,
                            FieldInfo(0, "paraxial"))

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> ModelPSFResult:
        ks = self._check_ks(ks)
        f = self._fields(fields)
        wls = self._wavelengths(wavelengths)
        z_l, radius = self.thin_lens()
        fds = [[self.doe_field(f[i], wl, depth) for wl in wls] for i in range(f.shape[0])]
        with torch.no_grad():
            efl = [self.lens.paraxial(wl).efl for wl in wls]
        info = {"thin_lens_z": z_l, "stop_radius": radius, "efl": efl, "plane": self.plane}
        return propagate_fields(self.hybrid, fds, ks, self.name, info)
