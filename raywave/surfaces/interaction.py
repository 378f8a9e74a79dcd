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


def refract(dx, dy, dz, nx, ny, nz, n1, n2):
    """Vector Snell's law.

    Args: unit direction (dx, dy, dz), unit normal (nx, ny, nz) on the same side as the ray's travel
    (d·N > 0), indices n1 (before) and n2 (after), all broadcastable tensors.
    Returns: (dx', dy', dz', ok) with ok False for total internal reflection (direction then finite).
    """
    cos_i = dx * nx + dy * ny + dz * nz
    mu = n1 / n2
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    ok = k >= 0
    g = safe_sqrt(k, ok) - mu * cos_i
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

    def forward(self, x, y, dx, dy, dz, nx, ny, nz, n1, n2, wavelength):
        dx, dy, dz, ok = refract(dx, dy, dz, nx, ny, nz, n1, n2)
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
