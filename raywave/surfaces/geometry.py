"""Surface shapes: sag, normal and ray intersection in the surface's local frame.

The local frame has its origin at the surface vertex and its z axis along the optical axis. All methods
take and return component tensors (``x, y, z`` separately) because elementwise kernels on contiguous
components are several times faster than on ``(..., 3)`` stacks; shapes broadcast freely.

Sag convention (as Zemax): positive curvature ``c = 1/R`` means the centre of curvature lies at +z, so the
surface bulges toward -z (a biconvex lens has c1 > 0, c2 < 0).
"""

from __future__ import annotations

import torch
from torch import nn

from raywave.utils.safe import safe_sqrt

#: Newton iterations for aspheric intersections (each converges quadratically from the conic start).
NEWTON_MAX_ITER = 30
#: Convergence tolerance of the Newton iteration on the ray parameter (mm).
NEWTON_TOL = 1e-12


def _param(value, requires_grad: bool = True) -> nn.Parameter:
    return nn.Parameter(torch.as_tensor(value, dtype=torch.float64).clone(), requires_grad=requires_grad)


class Geometry(nn.Module):
    """Base class: a rotationally symmetric surface z = sag(x, y) about the local z axis."""

    def sag(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Surface height z (mm) at (x, y) (mm)."""
        raise NotImplementedError

    def sag_gradient(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(dz/dx, dz/dy) at (x, y)."""
        raise NotImplementedError

    def in_domain(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Where the sag is defined (bool)."""
        return torch.ones_like(x, dtype=torch.bool)

    def normal(self, x, y, z):
        """Unit normal (nx, ny, nz) with nz > 0 at a point on the surface."""
        zx, zy = self.sag_gradient(x, y)
        inv = torch.rsqrt(1.0 + zx * zx + zy * zy)
        return -zx * inv, -zy * inv, inv

    def intersect(self, ox, oy, oz, dx, dy, dz):
        """Ray parameter ``t`` (mm, signed) where o + t·d meets the surface, and a validity mask."""
        raise NotImplementedError

    def paraxial_curvature(self) -> torch.Tensor:
        """Curvature of the osculating sphere at the vertex (1/mm), for the paraxial model."""
        raise NotImplementedError


class Plane(Geometry):
    """The plane z = 0 (stops, windows, ideal-lens and DOE planes)."""

    def sag(self, x, y):
        return torch.zeros_like(x)

    def sag_gradient(self, x, y):
        z = torch.zeros_like(x)
        return z, z

    def normal(self, x, y, z):
        zero = torch.zeros_like(x)
        return zero, zero, torch.ones_like(x)

    def intersect(self, ox, oy, oz, dx, dy, dz):
        ok = dz != 0
        t = -oz / torch.where(ok, dz, torch.ones_like(dz))
        return t, ok

    def __init__(self):
        super().__init__()
        self.register_buffer("_zero", torch.zeros((), dtype=torch.float64), persistent=False)

    def paraxial_curvature(self):
        return self._zero


class Standard(Geometry):
    """Sphere or conic: z = c r² / (1 + sqrt(1 - (1+k) c² r²)), closed-form intersection.

    Parameters: ``curvature`` c (1/mm, 0 for a plane) and ``conic`` k (0 sphere, -1 paraboloid).
    """

    def __init__(self, curvature: float = 0.0, conic: float = 0.0):
        super().__init__()
        self.curvature = _param(curvature)
        self.conic = _param(conic)

    def paraxial_curvature(self):
        return self.curvature

    def in_domain(self, x, y):
        c, k = self.curvature, self.conic
        return 1.0 - (1.0 + k) * c * c * (x * x + y * y) >= 0

    def sag(self, x, y):
        c, k = self.curvature, self.conic
        r2 = x * x + y * y
        arg = 1.0 - (1.0 + k) * c * c * r2
        return c * r2 / (1.0 + safe_sqrt(arg, arg >= 0, fill=1.0))

    def sag_gradient(self, x, y):
        c, k = self.curvature, self.conic
        arg = 1.0 - (1.0 + k) * c * c * (x * x + y * y)
        s = c / safe_sqrt(arg, arg > 0, fill=1.0)
        return s * x, s * y

    def normal(self, x, y, z):
        # Gradient of the implicit form c(x²+y²) + c(1+k) z² - 2z = 0: no square root needed.
        c, k = self.curvature, self.conic
        nx, ny, nz = -c * x, -c * y, 1.0 - c * (1.0 + k) * z
        inv = torch.rsqrt(nx * nx + ny * ny + nz * nz)
        return nx * inv, ny * inv, nz * inv

    def intersect(self, ox, oy, oz, dx, dy, dz):
        c, k = self.curvature, self.conic
        kp1 = 1.0 + k
        a = c * (dx * dx + dy * dy + kp1 * dz * dz)
        b = c * (ox * dx + oy * dy + kp1 * oz * dz) - dz
        cc = c * (ox * ox + oy * oy + kp1 * oz * oz) - 2.0 * oz
        disc = b * b - a * cc
        ok = disc > 0  # a tangent ray (disc = 0) has an infinite derivative: it is vignetted
        den = safe_sqrt(disc, ok, fill=1.0) - b  # stable root, continuous with the plane as c -> 0
        ok = ok & (den != 0)
        t = cc / torch.where(ok, den, torch.ones_like(den))
        # Keep the branch through the vertex (excludes the far half of a sphere / other hyperbola sheet).
        ok = ok & (kp1 * c * (oz + t * dz) <= 1.0)
        return t, ok


class EvenAsphere(Standard):
    """Even asphere: conic sag + a2 r² + a4 r⁴ + … (Zemax EVENASPH; a2 is included everywhere, paraxial too).

    ``coefficients[i]`` multiplies r^(2i+2) (i.e. a2, a4, a6, ...), in mm^(1-2i-2).
    Intersection: Newton's method from the conic solution; the gradient is taken from one differentiable
    Newton step at the converged point, which equals the implicit-function gradient exactly.
    """

    def __init__(self, curvature: float = 0.0, conic: float = 0.0, coefficients=(0.0,)):
        super().__init__(curvature, conic)
        coefficients = list(coefficients) or [0.0]
        self.coefficients = _param(coefficients)

    def paraxial_curvature(self):
        return self.curvature + 2.0 * self.coefficients[0]

    def _poly(self, r2):
        """(Σ a_{2i} r^{2i}, d/d(r²) of it) by Horner's rule."""
        a = self.coefficients
        n = a.shape[0]
        val = torch.zeros_like(r2) + a[n - 1]
        der = torch.zeros_like(r2) + (n * a[n - 1])
        for i in range(n - 2, -1, -1):
            val = val * r2 + a[i]
            der = der * r2 + (i + 1) * a[i]
        # val = Σ a[i] r2^i: one more factor r2 gives Σ a[i] r^(2i+2).
        return val * r2, der

    def sag(self, x, y):
        r2 = x * x + y * y
        poly, _ = self._poly(r2)
        return super().sag(x, y) + poly

    def sag_gradient(self, x, y):
        gx, gy = super().sag_gradient(x, y)
        r2 = x * x + y * y
        _, der = self._poly(r2)
        return gx + 2.0 * der * x, gy + 2.0 * der * y

    def normal(self, x, y, z):
        return Geometry.normal(self, x, y, z)

    def _newton_step(self, t, ox, oy, oz, dx, dy, dz):
        x, y = ox + t * dx, oy + t * dy
        f = oz + t * dz - self.sag(x, y)
        zx, zy = self.sag_gradient(x, y)
        fp = dz - zx * dx - zy * dy
        okp = fp.abs() > 1e-12
        return t - f / torch.where(okp, fp, torch.ones_like(fp)), f, okp

    def intersect(self, ox, oy, oz, dx, dy, dz):
        t0, ok0 = super().intersect(ox, oy, oz, dx, dy, dz)
        plane_t = -oz / torch.where(dz != 0, dz, torch.ones_like(dz))
        with torch.no_grad():
            t = torch.where(ok0, t0, plane_t).detach()
            args = [a.detach() for a in (ox, oy, oz, dx, dy, dz)]
            for _ in range(NEWTON_MAX_ITER):
                t_new, _, _ = self._newton_step(t, *args)
                t_new = torch.where(torch.isfinite(t_new), t_new, t)
                step = (t_new - t).abs()
                t = t_new
                if not bool((step > NEWTON_TOL).any()):
                    break
            # rays whose iterate is unusable (diverged, outside the sag's domain, not on the surface) restart
            # the differentiable step from t = 0 (their own, finite origin): a huge or non-finite t there would
            # overflow the polynomial and put 0·inf = NaN into the gradients of the valid rays' parameters
            x, y = args[0] + t * args[3], args[1] + t * args[4]
            f_d = args[2] + t * args[5] - self.sag(x, y)
            pre = torch.isfinite(t) & self.in_domain(x, y) & (f_d.abs() < 1e-9)
            t = torch.where(pre, t, torch.zeros_like(t))
        # One differentiable step at the converged point: gives the implicit-function gradient.
        t_final, f, okp = self._newton_step(t, ox, oy, oz, dx, dy, dz)
        ok = pre & okp & torch.isfinite(t_final)
        t_final = torch.where(ok, t_final, torch.zeros_like(t_final))
        return t_final, ok
