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
    """Base class: a surface z = sag(x, y) in the local frame (rotationally symmetric about the local z axis
    unless ``rotationally_symmetric`` is False)."""

    #: False for shapes whose paraxial data depend on the section (toroids): the paraxial model sees y–z only.
    rotationally_symmetric = True
    #: the sag is even in x and in y (``sag(−x, y) = sag(x, −y) = sag(x, y)``): true of every rotationally symmetric
    #: shape and of the toroid; a mirror-symmetric lens sends the source (−x, y) the mirror image of the field of
    #: (x, y) (:mod:`raywave.hybrid.mirror`). A shape with odd terms in x or y must set it False.
    mirror_symmetric = True

    def sag(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Surface height z (mm) at (x, y) (mm)."""
        raise NotImplementedError

    def sag_gradient(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(dz/dx, dz/dy) at (x, y)."""
        raise NotImplementedError

    def sag_and_gradient(self, x: torch.Tensor, y: torch.Tensor):
        """``(sag, (dz/dx, dz/dy))`` at (x, y): the values of :meth:`sag` and :meth:`sag_gradient` (a shape whose
        two share work computes it once: a Newton step of the ray intersection needs both)."""
        return self.sag(x, y), self.sag_gradient(x, y)

    def in_domain(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Where the sag is defined (bool)."""
        return torch.ones_like(x, dtype=torch.bool)

    def normal(self, x, y, z):
        """Unit normal (nx, ny, nz) with nz > 0 at a point on the surface."""
        zx, zy = self.sag_gradient(x, y)
        inv = torch.rsqrt(1.0 + zx * zx + zy * zy)
        return -zx * inv, -zy * inv, inv

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        """Ray parameter ``t`` (mm, signed) where o + t·d meets the surface, and a validity mask.

        ``front``: every ray comes from the surface's front (−z) side, whatever its direction (the tracer says so
        where the light travels toward +z: before any mirror, or after an even number). Else the side is taken from
        the ray's direction (toward −z: from behind, as after a mirror). The two agree for rays travelling toward +z;
        they differ for a ray that meets a front surface travelling backward (a fisheye's field beyond 90°)."""
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

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        ok = dz != 0
        t = -oz / torch.where(ok, dz, self._one)
        return t, ok

    def __init__(self):
        super().__init__()
        self.register_buffer("_zero", torch.zeros((), dtype=torch.float64), persistent=False)
        self.register_buffer("_one", torch.ones((), dtype=torch.float64), persistent=False)  # intersect's fill

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
        # a 0-d 1 for the intersection's fills (a fill from a Python number or ones_like costs an op a use; issue 43)
        self.register_buffer("_one", torch.ones((), dtype=torch.float64), persistent=False)
        self._flat_key, self._flat = None, False  # :meth:`_is_flat`'s answer and the curvature it was read from

    def paraxial_curvature(self):
        return self.curvature

    def _is_flat(self) -> bool:
        """Whether the curvature is exactly 0 (a flat surface: a stop, a window), read from the host once per value
        of the parameter (its storage and version: an optimiser's step or a load changes them), not per trace."""
        c = self.curvature
        key = (c.data_ptr(), c._version, c.device)
        if key != self._flat_key:
            self._flat_key, self._flat = key, bool(c.detach() == 0)
        return self._flat

    def extra_repr(self) -> str:
        c = float(self.curvature.detach())
        return f"radius={'inf' if c == 0 else f'{1.0 / c:.8g}'}, conic={float(self.conic.detach()):.8g}"

    def in_domain(self, x, y):
        c, k = self.curvature, self.conic
        return 1.0 - (1.0 + k) * c * c * (x * x + y * y) >= 0

    def sag(self, x, y):
        return self._conic_sag(x * x + y * y)

    def sag_gradient(self, x, y):
        s = self._conic_slope(x * x + y * y)
        return s * x, s * y

    def _conic_sag(self, r2):
        """The conic's sag at ``r2 = x² + y²`` (mm²)."""
        c, k = self.curvature, self.conic
        arg = 1.0 - (1.0 + k) * c * c * r2
        return c * r2 / (1.0 + torch.sqrt(torch.where(arg >= 0, arg, self._one)))  # safe_sqrt, a 0-d fill

    def _conic_slope(self, r2):
        """``s`` with the conic's sag gradient ``(s·x, s·y)`` at ``r2 = x² + y²`` (1/mm)."""
        c, k = self.curvature, self.conic
        arg = 1.0 - (1.0 + k) * c * c * r2
        return c / torch.sqrt(torch.where(arg > 0, arg, self._one))  # safe_sqrt, a 0-d fill

    def normal(self, x, y, z):
        # Gradient of the implicit form c(x²+y²) + c(1+k) z² - 2z = 0: no square root needed.
        c, k = self.curvature, self.conic
        nx, ny, nz = -c * x, -c * y, 1.0 - c * (1.0 + k) * z
        inv = torch.rsqrt(nx * nx + ny * ny + nz * nz)
        return nx * inv, ny * inv, nz * inv

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        if not torch.is_grad_enabled() and self._is_flat():
            return self._flat_intersect(oz, dz, front)
        c, k = self.curvature, self.conic
        kp1 = 1.0 + k
        a = c * (dx * dx + dy * dy + kp1 * dz * dz)
        b = c * (ox * dx + oy * dy + kp1 * oz * dz) - dz
        cc = c * (ox * ox + oy * oy + kp1 * oz * oz) - 2.0 * oz
        disc = b * b - a * cc
        ok = disc > 0  # a tangent ray (disc = 0) has an infinite derivative: it is vignetted
        # The root continuous with the plane as c -> 0: t = (-b - s·root) / a with s = +1 for a ray travelling toward
        # +z, -1 toward -z (after a mirror). Written as cc / (-b + s·root) it has no cancellation where -b and s·root
        # share a sign (the usual case, and the plane limit a -> 0); where they do not (an origin far from the
        # vertex, e.g. on the other sheet of a hyperboloid) the quotient by a is the stable form. ``front``: s = +1 for
        # every ray (the crossing from the front side, a ray travelling backward onto a front surface included).
        one = self._one
        root = torch.sqrt(torch.where(ok, disc, one))  # safe_sqrt(disc, ok, fill=1.0)
        sroot = root if front else torch.where(dz < 0, -root, root)
        den = sroot - b
        by_a = (b * sroot > 0) & (a != 0)  # -b and s·root of opposite signs: den cancels
        ok = ok & ((den != 0) | by_a)
        by_a = by_a & ok
        t = cc / torch.where(ok & ~by_a, den, one)
        t = torch.where(by_a, (-b - sroot) / torch.where(by_a, a, one), t)
        # Keep the branch through the vertex (excludes the far half of a sphere / other hyperbola sheet).
        ok = ok & (kp1 * c * (oz + t * dz) <= 1.0)
        return t, ok

    def _flat_intersect(self, oz, dz, front: bool):
        """:meth:`intersect` where c = 0, without autograd (issue 43: 5 ops instead of ~40, a stop's in every
        trace): the general form's own values, bit for bit. With c = 0 it has a = 0, b = −dz, cc = −2·oz,
        disc = dz² and root = |dz| (a correctly rounded square root of a square), so den = s·|dz| + dz is 2·dz where
        the ray crosses the way it is taken (``front``: dz > 0; else any dz ≠ 0) and 0 elsewhere (not ok), and
        t = cc / den (by_a never holds: a = 0)."""
        ok = dz > 0 if front else dz != 0
        return (-2.0 * oz) / torch.where(ok, 2.0 * dz, self._one), ok


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

    def _poly_terms(self) -> tuple:
        """The coefficients a_i and (i + 1)·a_i as 0-d tensors (two tuples), taken once (not two indexings and a
        product per term)."""
        a = self.coefficients
        n = a.shape[0]
        return a.unbind(), (a * torch.arange(1, n + 1, dtype=a.dtype, device=a.device)).unbind()

    def _poly(self, r2, terms: tuple | None = None):
        """(Σ a_{2i} r^{2i}, d/d(r²) of it) by Horner's rule; ``terms``: :meth:`_poly_terms` when the caller has
        them (a Newton iteration's constants)."""
        terms, slopes = self._poly_terms() if terms is None else terms
        n = len(terms)
        if n == 1:
            val = torch.zeros_like(r2) + terms[0]
            der = torch.zeros_like(r2) + slopes[0]
        else:  # the first Horner step from a_{n-1} itself (the same values as 0 + a_{n-1}, two ops fewer)
            val = r2 * terms[n - 1] + terms[n - 2]
            der = r2 * slopes[n - 1] + slopes[n - 2]
        for i in range(n - 3, -1, -1):
            val = val * r2 + terms[i]
            der = der * r2 + slopes[i]
        # val = Σ a[i] r2^i: one more factor r2 gives Σ a[i] r^(2i+2).
        return val * r2, der

    def sag(self, x, y):
        r2 = x * x + y * y
        poly, _ = self._poly(r2)
        return self._conic_sag(r2) + poly

    def sag_gradient(self, x, y):
        # the gradient alone (a surface normal): the same values as sag_and_gradient's, without the sag's ops
        r2 = x * x + y * y
        _, slopes = self._poly_terms()
        n = len(slopes)
        der = torch.zeros_like(r2) + slopes[0] if n == 1 else r2 * slopes[n - 1] + slopes[n - 2]
        for i in range(n - 3, -1, -1):
            der = der * r2 + slopes[i]
        s = self._conic_slope(r2)
        return s * x + 2.0 * der * x, s * y + 2.0 * der * y

    def sag_and_gradient(self, x, y, terms: tuple | None = None):
        r2 = x * x + y * y
        poly, der = self._poly(r2, terms)
        s = self._conic_slope(r2)
        return self._conic_sag(r2) + poly, (s * x + 2.0 * der * x, s * y + 2.0 * der * y)

    def normal(self, x, y, z):
        return Geometry.normal(self, x, y, z)

    def frozen(self, like: torch.Tensor) -> "_FrozenPoly":
        """This asphere with its polynomial's terms taken once, for an iteration without autograd (call it under
        ``torch.no_grad``; :func:`newton_intersect`): the same values as the surface's own methods, fewer ops per
        step; ``like``: a tensor of the rays' shape and dtype."""
        return _FrozenPoly(self, like)

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        return newton_intersect(self, Standard.intersect(self, ox, oy, oz, dx, dy, dz, front), ox, oy, oz, dx, dy, dz)


class _FrozenPoly:
    """An :class:`EvenAsphere` whose constants are taken once (:meth:`EvenAsphere.frozen`), for a Newton iteration
    without autograd: ``sag``, ``sag_and_gradient`` and ``in_domain`` with the surface's own values, in fewer ops
    (issue 43): the polynomial and its slope by one Horner's rule on (2, ...) pairs, the point and the gradient's x
    and y as pairs too (every element the same op on the same numbers: the same values). (Not ``addcmul``: its
    vectorised CPU kernel fuses the product and the sum, other values.) ``like``: a tensor of the rays' shape and
    dtype (the pairs take its dtype: as 0-d terms would, they must not promote a float32 trace to float64)."""

    def __init__(self, geom, like: torch.Tensor):
        self.geom = geom
        a = geom.coefficients
        n = a.shape[0]
        # (a_i, 2·(i + 1)·a_i) pairs: the slope terms (i + 1)·a_i doubled (exact: a power of two), so that the
        # gradient's 2·Σ (i + 1) a_i r^(2i) comes out of Horner's rule directly; shaped to broadcast with the rays
        pairs = torch.stack([a, a * torch.arange(2, 2 * n + 1, 2, dtype=a.dtype, device=a.device)])
        self.pairs = pairs.to(like.dtype).reshape((2, n) + (1,) * like.ndim).unbind(1)
        c, k = geom.curvature, geom.conic
        self.q = (1.0 + k) * c * c  # the conic's (1 + k)·c², as its sag and slope form it (the same rounding)
        self.one = geom._one  # a 0-d fill (a Python number or ones_like costs an op a use)
        self.rays = None  # the rays' (x, y) origins and directions as (2, ...) pairs, once per intersection

    def _arg(self, r2):
        return 1.0 - self.q * r2

    def _poly(self, r2):
        """(Σ a_{2i} r^{2i}, 2·d/d(r²) of it): :meth:`EvenAsphere._poly`'s values (the second doubled)."""
        p = self.pairs
        n = len(p)
        v = torch.zeros_like(r2) + p[0] if n == 1 else r2 * p[n - 1] + p[n - 2]
        for i in range(n - 3, -1, -1):
            v = v * r2 + p[i]
        val, der2 = v.unbind(0)
        return val * r2, der2

    def sag(self, x, y):
        r2 = x * x + y * y
        c, arg = self.geom.curvature, self._arg(r2)
        return c * r2 / (1.0 + torch.sqrt(torch.where(arg >= 0, arg, self.one))) + self._poly(r2)[0]

    def sag_and_gradient(self, x, y):
        sag, g, _ = self._at(torch.stack(torch.broadcast_tensors(x, y)))
        return sag, g.unbind(0)

    def _at(self, xy):
        """``(sag, (dz/dx, dz/dy) as a (2, ...) pair, in_domain)`` at the points ``xy`` (2, ...):
        :meth:`EvenAsphere.sag_and_gradient`'s values and :meth:`Standard.in_domain`'s mask (the conic's
        ``(1 + k)·c²·r²`` is the same product), the conic's square root taken once for the sag and the slope (the
        slope's ``arg > 0`` takes the root where the sag's ``arg >= 0`` does, 1 where ``arg = 0``: the same
        values)."""
        x, y = xy.unbind(0)
        r2 = x * x + y * y
        poly, der2 = self._poly(r2)
        c, arg = self.geom.curvature, self._arg(r2)
        dom = arg >= 0
        root = torch.sqrt(torch.where(dom, arg, self.one))
        s = c / torch.where(arg > 0, root, self.one)
        sag = c * r2 / (1.0 + root)
        return sag + poly, s * xy + der2 * xy, dom

    def in_domain(self, x, y):
        return self.geom.in_domain(x, y)

    def step(self, t, args: list):
        """``(t − f/f', f, f' usable, in_domain)`` at ``t``: :func:`_newton_step`'s values (``t − f/f'`` as one
        ``addcdiv``: the quotient rounded, then the difference, as two ops round them), and the domain mask at the
        ray's point (``args``: the ray's ``(ox, oy, oz, dx, dy, dz)``)."""
        ox, oy, oz, dx, dy, dz = args
        if not all(v.shape == t.shape for v in (ox, oy, dx, dy)):  # broadcast rays: the components one by one
            x, y = ox + t * dx, oy + t * dy
            sag, (zx, zy) = self.sag_and_gradient(x, y)
            dom = self.in_domain(x, y)
            fp = dz - zx * dx - zy * dy
        else:
            if self.rays is None:
                self.rays = torch.stack([ox, oy]), torch.stack([dx, dy])
            o2, d2 = self.rays
            sag, g, dom = self._at(o2 + t * d2)
            gx, gy = (g * d2).unbind(0)
            fp = dz - gx - gy
        f = oz + t * dz - sag
        okp = fp.abs() > 1e-12
        return torch.addcdiv(t, f, torch.where(okp, fp, self.one), value=-1.0), f, okp, dom  # t − f/f'


def _newton_step(geom, t, ox, oy, oz, dx, dy, dz):
    x, y = ox + t * dx, oy + t * dy
    sag, (zx, zy) = geom.sag_and_gradient(x, y)
    f = oz + t * dz - sag
    fp = dz - zx * dx - zy * dy
    okp = fp.abs() > 1e-12
    return t - f / torch.where(okp, fp, torch.ones_like(fp)), f, okp


class _Plain:
    """A shape without a frozen form seen as one (:meth:`_FrozenPoly.step`): its own methods, fills and mask."""

    def __init__(self, geom, like):
        self.geom, self.one = geom, like.new_ones(())

    def sag(self, x, y):
        return self.geom.sag(x, y)

    def in_domain(self, x, y):
        return self.geom.in_domain(x, y)

    def step(self, t, args: list):
        return (*_newton_step(self.geom, t, *args), None)


def newton_intersect(geom: Geometry, start, ox, oy, oz, dx, dy, dz):
    """Ray parameter ``t`` and validity where o + t·d meets ``geom`` (any sag with a gradient), by Newton's method.

    ``start``: (t0, ok0), a first guess (e.g. the base conic's intersection; the vertex plane where ok0 is
    False). The iteration runs without autograd; one differentiable Newton step from the converged point then
    gives the implicit-function gradient exactly. Rays whose residual stays above 1e-9 mm, or that land outside
    the sag's domain, are invalid (t = 0). Without autograd (a ray aiming's traces) that last step is the
    iteration's own and its residual the one checked (:func:`_final_step_no_grad`: the same values, fewer ops).
    """
    grad = torch.is_grad_enabled()
    t0, ok0 = start
    with torch.no_grad():
        one = getattr(geom, "_one", None)  # a 0-d fill where the shape has one (a conic's)
        plane_t = -oz / torch.where(dz != 0, dz, torch.ones_like(dz) if one is None else one)
        t = torch.where(ok0, t0, plane_t).detach()
        args = [a.detach() for a in (ox, oy, oz, dx, dy, dz)]
        # the iteration's constants taken once (an even asphere's frozen form), else the shape's own methods
        frozen = geom.frozen(t) if hasattr(geom, "frozen") else _Plain(geom, t)
        prev = None
        for _ in range(NEWTON_MAX_ITER):
            t_new = frozen.step(t, args)[0]
            t_new = torch.where(torch.isfinite(t_new), t_new, t)
            step = (t_new - t).abs()
            t = t_new
            # converged when the next step is within the tolerance: Newton's next step, step³/prev² (quadratic
            # convergence, its constant from the last two steps), so that no iteration only confirms a step of
            # ~1e-16 mm (issue 43: an iteration is ~50 ops of every trace of an asphere); the first by the step
            # itself. A ray whose steps are 0 (converged, or unusable: kept) gives 0/0 = NaN, not above.
            nxt = step if prev is None else step * step * step / (prev * prev)
            if not bool((nxt > NEWTON_TOL).any()):
                break
            prev = step
        if not grad:
            return _final_step_no_grad(frozen, t, args)
        # rays whose iterate is unusable (diverged, outside the sag's domain, not on the surface) restart the
        # differentiable step from t = 0 (their own, finite origin): a huge or non-finite t there would overflow
        # the polynomial and put 0·inf = NaN into the gradients of the valid rays' parameters
        x, y = args[0] + t * args[3], args[1] + t * args[4]
        f_d = args[2] + t * args[5] - frozen.sag(x, y)
        pre = torch.isfinite(t) & frozen.in_domain(x, y) & (f_d.abs() < 1e-9)
        t = torch.where(pre, t, torch.zeros_like(t))
    # One differentiable step at the converged point: gives the implicit-function gradient.
    t_final, f, okp = _newton_step(geom, t, ox, oy, oz, dx, dy, dz)
    ok = pre & okp & torch.isfinite(t_final)
    t_final = torch.where(ok, t_final, torch.zeros_like(t_final))
    return t_final, ok


def _final_step_no_grad(frozen, t, args: list):
    """:func:`newton_intersect`'s last step without autograd (issue 43: the sag evaluated once at the converged
    ``t``, not twice): the Newton step at ``t`` and the residual ``f`` there, the residual that the differentiable
    path checks (the same sag at the same point). A ray whose ``t`` is unusable gets ``(0, False)`` either way, and
    a usable one the step from its own ``t``: the differentiable path's values."""
    t_final, f, okp, dom = frozen.step(t, args)
    if dom is None:
        dom = frozen.in_domain(args[0] + t * args[3], args[1] + t * args[4])
    ok = torch.isfinite(t) & dom & (f.abs() < 1e-9) & okp & torch.isfinite(t_final)
    return torch.where(ok, t_final, torch.zeros_like(frozen.one)), ok


class OddAsphere(Standard):
    """Odd asphere (Zemax ODDASPHE): conic sag + b1 r + b2 r² + b3 r³ + … + b8 r⁸.

    ``coefficients[i]`` multiplies r^(i+1) (b1, b2, b3, ...), in mm^(-i). b1 ≠ 0 makes the vertex a cone point
    (its normal is taken along the axis there). Paraxial curvature: c + 2·b2 (b1 is a cone, not a power; as
    raywave's even asphere, the r² term counts). Intersection: Newton from the conic solution, as
    :class:`EvenAsphere`.
    """

    rotationally_symmetric = True

    def __init__(self, curvature: float = 0.0, conic: float = 0.0, coefficients=(0.0,)):
        super().__init__(curvature, conic)
        coefficients = list(coefficients) or [0.0]
        self.coefficients = _param(coefficients)

    def paraxial_curvature(self):
        b = self.coefficients
        return self.curvature + (2.0 * b[1] if b.shape[0] > 1 else 0.0 * b[0])

    def _r(self, x, y):
        return self._r_of(x * x + y * y)

    @staticmethod
    def _r_of(r2):
        """``(r, r > 0)`` from ``r2 = x² + y²`` (r = 0 on the axis, with a finite gradient)."""
        pos = r2 > 0
        return safe_sqrt(r2, pos, fill=0.0), pos

    def _poly(self, r):
        """(Σ b_i r^i, Σ_{i>=2} i b_i r^(i-2)) by Horner's rule."""
        b = self.coefficients
        n = b.shape[0]
        val = torch.zeros_like(r) + b[n - 1]
        for i in range(n - 2, -1, -1):
            val = val * r + b[i]
        if n >= 2:
            der = torch.zeros_like(r) + n * b[n - 1]
            for i in range(n - 2, 0, -1):
                der = der * r + (i + 1) * b[i]
        else:
            der = torch.zeros_like(r)
        return val * r, der

    def sag(self, x, y):
        r, _ = self._r(x, y)
        poly, _ = self._poly(r)
        return super().sag(x, y) + poly

    def sag_gradient(self, x, y):
        return self.sag_and_gradient(x, y)[1]

    def sag_and_gradient(self, x, y):
        r2 = x * x + y * y
        r, pos = self._r_of(r2)
        poly, der = self._poly(r)
        # d/dr (b1 r) = b1, times x/r; 0 on the axis (the cone point)
        cone = self.coefficients[0] / torch.where(pos, r, torch.ones_like(r))
        cone = torch.where(pos, cone, torch.zeros_like(cone))
        s = der + cone
        s0 = self._conic_slope(r2)
        return self._conic_sag(r2) + poly, (s0 * x + s * x, s0 * y + s * y)

    def normal(self, x, y, z):
        return Geometry.normal(self, x, y, z)

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        return newton_intersect(self, Standard.intersect(self, ox, oy, oz, dx, dy, dz, front), ox, oy, oz, dx, dy, dz)


class Toroidal(Standard):
    """Toroid (Zemax TOROIDAL): a curve in the y–z plane rotated about an axis parallel to y at distance R.

    The y–z curve z_y(y) = c y² / (1 + sqrt(1 − (1+k) c² y²)) + a2 y² + a4 y⁴ + … + a14 y¹⁴ (``curvature`` c,
    ``conic`` k, ``coefficients`` [a2, a4, ...]) turns about the axis (x = 0, z = R), R = 1/``rotation_curvature``
    (0: R infinite, a cylinder with power in y only):

        z(x, y) = z_y + (q − sqrt(q² − c_r² x²)) / c_r,   q = 1 − c_r z_y,   c_r = 1/R

    (= R − sqrt((R − z_y)² − x²), written to stay exact as c_r → 0). Vertex curvatures: c + 2 a2 in y–z,
    c_r in x–z. Not rotationally symmetric: paraxial data describe the y–z section (as OpticStudio).
    Intersection: Newton from the y–z conic's intersection, as :class:`EvenAsphere`.
    """

    rotationally_symmetric = False

    def __init__(self, curvature: float = 0.0, conic: float = 0.0, rotation_curvature: float = 0.0,
                 coefficients=(0.0,)):
        super().__init__(curvature, conic)
        self.rotation_curvature = _param(rotation_curvature)
        coefficients = list(coefficients) or [0.0]
        self.coefficients = _param(coefficients)

    def paraxial_curvature(self):
        return self.curvature + 2.0 * self.coefficients[0]

    def _profile(self, y):
        """(z_y, dz_y/dy) of the y–z curve."""
        c, k = self.curvature, self.conic
        y2 = y * y
        arg = 1.0 - (1.0 + k) * c * c * y2
        ok = arg >= 0
        root = safe_sqrt(arg, ok, fill=1.0)
        z = c * y2 / (1.0 + root)
        dz = c * y / torch.where(arg > 0, root, torch.ones_like(root))
        a = self.coefficients
        n = a.shape[0]
        val = torch.zeros_like(y2) + a[n - 1]
        der = torch.zeros_like(y2) + (n * a[n - 1])
        for i in range(n - 2, -1, -1):
            val = val * y2 + a[i]
            der = der * y2 + (i + 1) * a[i]
        return z + val * y2, dz + 2.0 * der * y

    def _rotation(self, x, y):
        zy, dzy = self._profile(y)
        cr = self.rotation_curvature
        q = 1.0 - cr * zy
        arg = q * q - cr * cr * x * x
        return zy, dzy, cr, q, arg

    def in_domain(self, x, y):
        c, k = self.curvature, self.conic
        _, _, _, q, arg = self._rotation(x, y)
        return (1.0 - (1.0 + k) * c * c * y * y >= 0) & (arg >= 0) & (q > 0)

    def sag(self, x, y):
        zy, _, cr, q, arg = self._rotation(x, y)
        s = safe_sqrt(arg, arg >= 0, fill=0.0)
        # (q - s) / c_r = c_r x² / (q + s): the second form is exact at c_r = 0
        den = q + s
        return zy + cr * x * x / torch.where(den != 0, den, torch.ones_like(den))

    def sag_gradient(self, x, y):
        zy, dzy, cr, q, arg = self._rotation(x, y)
        ok = arg > 0
        s = torch.where(ok, safe_sqrt(arg, ok, fill=1.0), torch.ones_like(arg))
        return cr * x / s, q / s * dzy

    def normal(self, x, y, z):
        return Geometry.normal(self, x, y, z)

    def intersect(self, ox, oy, oz, dx, dy, dz, front: bool = False):
        return newton_intersect(self, Standard.intersect(self, ox, oy, oz, dx, dy, dz, front), ox, oy, oz, dx, dy, dz)
