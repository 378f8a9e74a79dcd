"""What a surface does to a ray that reaches it: refraction, an ideal thin lens, (later) diffraction.

A surface is geometry × material × interaction (as in Optiland): a new kind of surface physics is a new
interaction, not a new surface class. Every interaction maps the incoming direction (unit, components) at
the hit point to the outgoing direction, adds any optical path it introduces, and reports rays it kills.
"""

from __future__ import annotations

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
