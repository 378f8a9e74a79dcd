"""What a surface does to a ray that reaches it: refraction, an ideal thin lens, diffraction (local grating).

A surface is geometry × material × interaction (as in Optiland): a new kind of surface physics is a new
interaction, not a new surface class. Every interaction maps the incoming direction (unit, components) at
the hit point to the outgoing direction, adds any optical path it introduces, and reports rays it kills.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from raywave.utils.safe import safe_sqrt


def refract(dx, dy, dz, nx, ny, nz, n1, n2, one=None):
    """Vector Snell's law.

    Args: unit direction (dx, dy, dz), unit normal (nx, ny, nz) on the same side as the ray's travel
    (d·N > 0), indices n1 (before) and n2 (after), all broadcastable tensors.
    Returns: (dx', dy', dz', ok) with ok False for total internal reflection (direction then finite).
    ``one``: a 0-d 1 (the square root's fill) when the caller has one (issue 43: ``ones_like`` costs an op a call).
    """
    cos_i = dx * nx + dy * ny + dz * nz
    mu = n1 / n2
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    ok = k >= 0
    g = (safe_sqrt(k, ok) if one is None else torch.sqrt(torch.where(ok, k, one))) - mu * cos_i
    return mu * dx + g * nx, mu * dy + g * ny, mu * dz + g * nz, ok


class Interaction(nn.Module):
    """Base class of surface interactions."""

    kind = "base"

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        """Returns (dx', dy', dz', extra_opl (mm) or None, ok)."""
        raise NotImplementedError

    def paraxial_power(self, curvature, n1, n2):
        """Optical power (1/mm) of the surface in the paraxial (y, n·u) model."""
        raise NotImplementedError


class Refraction(Interaction):
    """Ordinary refraction between the media before and after the surface."""

    kind = "refraction"

    def __init__(self):
        super().__init__()
        self.register_buffer("_one", torch.ones((), dtype=torch.float64), persistent=False)  # refract's 0-d fill

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        dx, dy, dz, ok = refract(dx, dy, dz, nx, ny, nz, n1, n2, self._one)
        return dx, dy, dz, None, ok

    def paraxial_power(self, curvature, n1, n2):
        return (n2 - n1) * curvature


class IdealLens(Interaction):
    """A perfect thin lens of focal length ``focal_length`` (mm), as Zemax's PARAXIAL surface.

    Ray directions obey n2·tan(θ2) = n1·tan(θ1) − n2·r/f in x and y, which images every object plane
    perfectly (stigmatic in tangent space). The added optical path makes the lens perfect in phase for
    collimated input at any field angle: every ray of a plane wave reaches the focal point with the same
    OPL. (For a point source at a finite distance the ray geometry is perfect but the phase is not.)
    The surface geometry must be a plane.
    """

    kind = "ideal_lens"

    def __init__(self, focal_length: float):
        super().__init__()
        if focal_length == 0:
            raise ValueError("ideal lens focal length must be non-zero")
        self.focal_length = nn.Parameter(torch.tensor(float(focal_length), dtype=torch.float64))

    def paraxial_power(self, curvature, n1, n2):
        return n2 / self.focal_length

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        f = self.focal_length
        ok = dz > 0
        inv_dz = 1.0 / torch.where(ok, dz, torch.ones_like(dz))
        mu = n1 / n2
        ux, uy = mu * dx * inv_dz, mu * dy * inv_dz  # tangents of the undeviated ray through the centre
        tx, ty = ux - x / f, uy - y / f
        inv = torch.rsqrt(1.0 + tx * tx + ty * ty)
        # Phase of a perfect lens for a plane wave of this direction: OPL equal at the focus (f·ux, f·uy, f).
        ix, iy = f * ux - x, f * uy - y
        dist = torch.sqrt(ix * ix + iy * iy + f * f)
        dist0 = f.abs() * torch.sqrt(1.0 + ux * ux + uy * uy)
        sign = torch.sign(f)
        extra = -n1 * (x * dx + y * dy) - sign * n2 * (dist - dist0)
        return tx * inv, ty * inv, inv, extra, ok

    def extra_repr(self):
        return f"focal_length={float(self.focal_length.detach())}"


class Diffraction(Interaction):
    """A thin diffractive phase φ(x, y) on the surface, traced with the local grating approximation (Zemax's
    diffractive surfaces, Zhu et al. 2023): the ray is bent by the local phase gradient,

        n2·d2_t = n1·d1_t + (m λ / 2π) ∇φ          (tangential components, vector form)

    i.e. n2 sin θ2 − n1 sin θ1 = m λ (∂φ/∂x) / 2π along the grating vector, which *includes* the refraction
    from n1 to n2 (φ = 0 is Snell's law); the normal component follows from |d2| = 1 (evanescent: ``ok`` False).
    The optical path gains ``m λ φ / 2π`` (mm): the DOE multiplies the field by ``exp(+i m φ)``, so OPL and ray
    direction agree (Malus–Dupin: the OPL's gradient along the surface is the tangential n·d after it).

    Args:
        phase: callable ``(x, y, wavelength) -> (φ, ∂φ/∂x, ∂φ/∂y)``: rad and rad/mm at the hit points
            (mm; the wavelength in µm, a tensor broadcastable with x). ∇φ = (∂φ/∂x, ∂φ/∂y, 0) is projected
            onto the tangent plane (exact for a plane surface).
        order: diffraction order m.

    ``paraxial_power`` is the refraction's only: the diffractive power depends on the wavelength and on φ's
    curvature, which the (y, nu) model does not see.
    """

    kind = "diffraction"

    def __init__(self, phase, order: float = 1.0):
        super().__init__()
        if not callable(phase):
            raise TypeError("Diffraction needs a callable phase(x, y, wavelength) -> (phi, dphi_dx, dphi_dy)")
        order = float(order)
        if not math.isfinite(order):
            raise ValueError(f"the diffraction order must be finite, got {order!r}")
        self.phase = phase
        self.order = order

    def paraxial_power(self, curvature, n1, n2):
        return (n2 - n1) * curvature

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        phi, gx, gy = self.phase(x, y, wavelength)
        s = self.order * wavelength * 1e-3 / (2 * math.pi)  # mm per radian
        ax, ay, az = n1 * dx + s * gx, n1 * dy + s * gy, n1 * dz  # n1·d + G (G with zero z component)
        c = ax * nx + ay * ny + az * nz
        tx, ty, tz = ax - c * nx, ay - c * ny, az - c * nz  # tangential part: conserved across the surface
        k = n2 * n2 - (tx * tx + ty * ty + tz * tz)
        ok = k >= 0
        g = safe_sqrt(k, ok)
        return (tx + g * nx) / n2, (ty + g * ny) / n2, (tz + g * nz) / n2, s * phi, ok

    def extra_repr(self):
        return f"order={self.order:g}"


def linear_grating_phase(period: float, angle: float = 0.0):
    """A linear phase ``φ = 2π (x cos a + y sin a) / period`` (period mm, ``angle`` a in degrees from +x) as a
    :class:`Diffraction` phase callable."""
    a = math.radians(angle)
    kx, ky = 2 * math.pi * math.cos(a) / period, 2 * math.pi * math.sin(a) / period

    def phase(x, y, wavelength):
        return kx * x + ky * y, torch.full_like(x, kx), torch.full_like(y, ky)

    return phase


class Reflection(Interaction):
    """A mirror (Zemax ``GLAS MIRROR``): the ray is reflected, ``d' = d − 2 (d·N) N``.

    The medium after a mirror is the medium before it (the surface's ``material`` is that medium); the light then
    travels back along the local axis, and the thickness after the mirror is negative (OpticStudio's convention).
    In the paraxial (y, n·u) model the index changes sign at every reflection (n' = −n), so that the power is the
    refraction formula's ``(n' − n) c = −2 n c`` and thickness / index stays positive (see
    :func:`raywave.lens.paraxial.signed_indices`). ``paraxial_power`` receives those signed indices.
    """

    kind = "reflection"

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        c = dx * nx + dy * ny + dz * nz
        ok = torch.ones_like(c, dtype=torch.bool)
        return dx - 2.0 * c * nx, dy - 2.0 * c * ny, dz - 2.0 * c * nz, None, ok

    def paraxial_power(self, curvature, n1, n2):
        return (n2 - n1) * curvature


def _rotation(axis: str, degrees: float) -> torch.Tensor:
    """Right-handed rotation matrix (3×3, float64) by ``degrees`` about the local ``axis`` ('x', 'y' or 'z')."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        m = [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    elif axis == "y":
        m = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    else:
        m = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    return torch.tensor(m, dtype=torch.float64)


class CoordinateBreak(Interaction):
    """A coordinate break (Zemax ``TYPE COORDBRK``): no optical effect on the rays; it moves and turns the local
    frame of every surface after it.

    OpticStudio's semantics: with ``order`` 0 the frame is first decentred by (``decenter_x``, ``decenter_y``)
    (mm, along the current local x and y), then tilted about the local x axis by ``tilt_x``, then about the *new*
    local y by ``tilt_y``, then about the new local z by ``tilt_z`` (degrees, right-handed). With ``order`` ≠ 0
    the same steps run in reverse: tilt about z, then the new y, then the new x, then decentre. The surface's
    thickness then moves the origin along the new local z. A coordinate break has no geometry, no aperture and
    no power; its medium is the medium before it.

    The frame step is ``x_parent = R · x_new + t`` (:meth:`transform`).
    """

    kind = "coordinate_break"

    def __init__(self, decenter_x: float = 0.0, decenter_y: float = 0.0, tilt_x: float = 0.0, tilt_y: float = 0.0,
                 tilt_z: float = 0.0, order: int = 0):
        super().__init__()
        vals = dict(decenter_x=decenter_x, decenter_y=decenter_y, tilt_x=tilt_x, tilt_y=tilt_y, tilt_z=tilt_z)
        for k, v in vals.items():
            if not math.isfinite(float(v)):
                raise ValueError(f"coordinate break {k} must be finite, got {v!r}")
        self.decenter_x, self.decenter_y = float(decenter_x), float(decenter_y)
        self.tilt_x, self.tilt_y, self.tilt_z = float(tilt_x), float(tilt_y), float(tilt_z)
        if not math.isfinite(float(order)):
            raise ValueError(f"coordinate break order flag must be a finite number, got {order!r}")
        self.order = 0 if float(order) == 0.0 else 1

    @property
    def is_identity(self) -> bool:
        return not any((self.decenter_x, self.decenter_y, self.tilt_x, self.tilt_y, self.tilt_z))

    def transform(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(R (3, 3), t (3,)), float64: a point with coordinates ``x_new`` in the frame after the break has
        coordinates ``R @ x_new + t`` in the frame before it (thickness not included)."""
        rx, ry, rz = _rotation("x", self.tilt_x), _rotation("y", self.tilt_y), _rotation("z", self.tilt_z)
        dec = torch.tensor([self.decenter_x, self.decenter_y, 0.0], dtype=torch.float64)
        if self.order == 0:
            return rx @ ry @ rz, dec  # decentre, then tilt x, new y, new z
        rot = rz @ ry @ rx  # tilt z, new y, new x, then decentre along the tilted axes
        return rot, rot @ dec

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        raise RuntimeError("a coordinate break does not interact with rays (the lens tracer skips it)")

    def paraxial_power(self, curvature, n1, n2):
        return torch.zeros_like(torch.as_tensor(n1, dtype=torch.float64))

    def to_spec(self) -> dict:
        return {"decenter": [self.decenter_x, self.decenter_y], "tilt": [self.tilt_x, self.tilt_y, self.tilt_z],
                "order": self.order}

    def extra_repr(self):
        return (f"decenter=({self.decenter_x:g}, {self.decenter_y:g}), tilt=({self.tilt_x:g}, {self.tilt_y:g}, "
                f"{self.tilt_z:g}), order={self.order}")
