"""Parametrised DOEs: radially symmetric profile, Zemax BINARY_2 even polynomial, Zernike (Noll), Fresnel lens,
linear grating, cubic phase, and the sum of DOEs on one grid.

Each is a :class:`~raywave.doe.DOE` (an ``nn.Module``) whose parameters are float64 ``nn.Parameter``; its
:meth:`design_phase_pixels` is the phase (rad) at the design wavelength, turned into the phase at any
wavelength, the height map and the fabricated (wrapped, quantised) profile by the base class. Coordinates are
the DOE pixel centres (mm, on the optical axis), ``r = sqrt(x² + y²)``, ``θ = atan2(y, x)``; a phase
increasing toward +x tilts the light toward +x (docs/conventions.md). ``model_spec()`` / ``from_model_spec``
give the small dict stored in a lens file's ``doe.phase_model``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from raywave.doe.base import DOE, SumDOE  # SumDOE lives in base (DOE.__add__ builds it); re-exported here
from raywave.utils.checks import positive_float

__all__ = ["Binary2DOE", "CubicDOE", "FresnelDOE", "GratingDOE", "RadialDOE", "SumDOE", "ZernikeDOE", "noll_to_nm",
           "zernike_noll"]


def _param(values, name: str, ndim: int) -> nn.Parameter:
    t = torch.as_tensor(values, dtype=torch.float64).detach().clone()
    if t.ndim != ndim:
        want = "one number" if ndim == 0 else "a 1-D list of numbers"
        raise ValueError(f"{name} must be {want}, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return nn.Parameter(t)


def _positive(x, name: str, unit: str = "mm") -> float:
    return positive_float(x, name, unit)


def _list(t: torch.Tensor) -> list[float]:
    return [float(v) for v in t.detach().cpu().reshape(-1)]


class _Analytic(DOE):
    """Shared plumbing: the grid and optics keywords, pixel coordinates, radius defaults."""

    def _r2(self, rows, cols) -> torch.Tensor:
        x, y = self.pixel_xy(rows, cols)
        return x[None, :] ** 2 + y[:, None] ** 2

    def _half_size(self) -> float:
        return 0.5 * min(self.size)

    @classmethod
    def from_model_spec(cls, model: dict, shape, pitch, aperture="square", **optics):
        kw = {k: v for k, v in model.items() if k != "type"}
        return cls(**kw, shape=shape, pitch=pitch, aperture=aperture, **optics)


class RadialDOE(_Analytic):
    """A radially symmetric profile: ``N`` phase samples (rad) at ``r_k = k·radius/(N−1)``, k = 0..N−1,
    linearly interpolated in r (held at the last sample beyond ``radius``, default half the smaller grid side).
    Suited to rotationally symmetric aberration correction."""

    spec_type = "radial"

    def __init__(self, profile, shape, pitch: float, radius: float | None = None, aperture: str = "square", **optics):
        super().__init__(shape, pitch, aperture, **optics)
        self.profile = _param(profile, "the radial profile", 1)
        if self.profile.numel() < 2:
            raise ValueError("a radial profile needs at least 2 samples")
        self.radius = self._half_size() if radius is None else _positive(radius, "radius")

    def design_phase_pixels(self, rows, cols):
        n = self.profile.numel()
        t = torch.sqrt(self._r2(rows, cols)) * ((n - 1) / self.radius)
        i0 = torch.clamp(torch.floor(t), 0, n - 2).to(torch.long)
        w = torch.clamp(t - i0, 0.0, 1.0)
        return self.profile[i0] * (1 - w) + self.profile[i0 + 1] * w

    def model_spec(self):
        return {"type": "radial", "radius": self.radius, "profile": _list(self.profile)}


class Binary2DOE(_Analytic):
    """Zemax OpticStudio's BINARY_2 phase: ``φ = M · Σ_{i=1..N} A_i ρ^{2i}``, ``ρ = r / norm_radius``, with
    the coefficients ``A_i`` in radians and ``M`` the diffraction order (OpticStudio's PARM 0; XDAT 1 = N, XDAT 2
    = normalisation radius, XDAT 3.. = A_i). Same sign: a positive phase gradient deflects rays toward it, so a
    negative ``A_1`` focuses (OpticStudio's ray-bending law ``n'l' = n l + (M λ / 2π) ∂φ/∂x`` and raywave's
    ``exp(+iφ)`` agree). OpticStudio's phase in radians does not depend on the wavelength: that is this DOE's
    default ``dispersion="none"``; give a material to make it a dispersive height map designed at λ0."""

    spec_type = "binary_2"

    def __init__(self, coefficients, norm_radius: float, shape, pitch: float, order: float = 1.0,
                 aperture: str = "square", **optics):
        super().__init__(shape, pitch, aperture, **optics)
        self.coefficients = _param(coefficients, "the BINARY_2 coefficients", 1)
        self.norm_radius = _positive(norm_radius, "the BINARY_2 normalisation radius")
        o = float(order)
        if not math.isfinite(o):
            raise ValueError(f"the diffraction order must be a finite number, got {order!r}")
        self.order = o

    def design_phase_pixels(self, rows, cols):
        rho2 = self._r2(rows, cols) / self.norm_radius ** 2
        acc = torch.zeros_like(rho2)
        for a in reversed(list(self.coefficients.unbind(0))):  # Horner in ρ²: ρ²(A1 + ρ²(A2 + ...))
            acc = (acc + a) * rho2
        return acc * self.order

    def model_spec(self):
        return {"type": "binary_2", "order": self.order, "norm_radius": self.norm_radius,
                "coefficients": _list(self.coefficients)}


def noll_to_nm(j: int) -> tuple[int, int]:
    """Noll index j >= 1 -> (n, m): m > 0 a cosine term (even j), m < 0 a sine term (odd j), m = 0 radial."""
    if isinstance(j, bool) or not isinstance(j, int) or j < 1:
        raise ValueError(f"a Noll index is an integer >= 1, got {j!r}")
    n = int((-1 + math.isqrt(8 * (j - 1) + 1)) // 2)
    p = j - n * (n + 1) // 2
    k = n % 2
    m = ((p + k) // 2) * 2 - k
    return n, (m if j % 2 == 0 else -m) if m else 0


def zernike_noll(j: int, rho: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Noll's normalised Zernike polynomial Z_j (RMS 1 on the unit disk): ``sqrt(n+1) R_n^0`` (m = 0),
    ``sqrt(2(n+1)) R_n^|m| cos(mθ)`` (even j), ``... sin(|m|θ)`` (odd j); θ from +x toward +y."""
    n, m = noll_to_nm(j)
    ma = abs(m)
    rad = torch.zeros_like(rho)
    for k in range((n - ma) // 2 + 1):
        c = (-1) ** k * math.factorial(n - k) / (math.factorial(k) * math.factorial((n + ma) // 2 - k)
                                                 * math.factorial((n - ma) // 2 - k))
        rad = rad + c * rho ** (n - 2 * k)
    if m == 0:
        return math.sqrt(n + 1) * rad
    ang = torch.cos(ma * theta) if m > 0 else torch.sin(ma * theta)
    return math.sqrt(2 * (n + 1)) * rad * ang


class ZernikeDOE(_Analytic):
    """``φ = Σ_j c_j Z_j(r / radius, θ)``: Noll-ordered, Noll-normalised Zernike polynomials (``coefficients[0]``
    is j = 1, piston; any number of terms, rad) on the disk of ``radius`` mm (default half the smaller grid
    side; the polynomials are extended beyond it, the aperture decides where light passes)."""

    spec_type = "zernike"

    def __init__(self, coefficients, shape, pitch: float, radius: float | None = None, aperture: str = "square",
                 **optics):
        super().__init__(shape, pitch, aperture, **optics)
        self.coefficients = _param(coefficients, "the Zernike coefficients", 1)
        self.radius = self._half_size() if radius is None else _positive(radius, "radius")

    def design_phase_pixels(self, rows, cols):
        x, y = self.pixel_xy(rows, cols)
        xx, yy = x[None, :] / self.radius, y[:, None] / self.radius
        rho = torch.sqrt(xx ** 2 + yy ** 2)
        theta = torch.atan2(yy.expand_as(rho), xx.expand_as(rho))
        out = torch.zeros_like(rho)
        for j, c in enumerate(self.coefficients.unbind(0), start=1):
            out = out + c * zernike_noll(j, rho, theta)
        return out

    def model_spec(self):
        return {"type": "zernike", "radius": self.radius, "coefficients": _list(self.coefficients)}


class FresnelDOE(_Analytic):
    """A diffractive lens of focal length ``focal_length`` (mm; < 0 diverging) at ``wavelength`` (µm, default
    the design wavelength): the exact hyperbolic phase that turns a normally incident plane wave into a spherical
    wave converging to (0, 0, f): ``φ = −sign(f)·(2π/λ)·(sqrt(r² + f²) − |f|)``
    (≈ ``−π r²/(λ f)`` paraxially),
    unwrapped; :meth:`fabricate` wraps / quantises it into the kinoform. ``focal_length`` is a parameter."""

    spec_type = "fresnel"

    def __init__(self, focal_length: float, shape, pitch: float, wavelength: float | None = None,
                 aperture: str = "square", **optics):
        super().__init__(shape, pitch, aperture, **optics)
        f = float(focal_length)
        if not (math.isfinite(f) and f != 0.0):
            raise ValueError(f"the Fresnel lens's focal length must be a finite non-zero length (mm), got "
                             f"{focal_length!r}")
        self.focal_length = _param(f, "focal_length", 0)
        self.wavelength = self.design_wavelength if wavelength is None else _positive(wavelength, "wavelength", "µm")

    def design_phase_pixels(self, rows, cols):
        r2 = self._r2(rows, cols)
        f = self.focal_length
        sag = r2 / (torch.sqrt(r2 + f * f) + f.abs())  # sqrt(r²+f²) − |f| without cancellation
        return -torch.sign(f).detach() * (2 * math.pi / (self.wavelength * 1e-3)) * sag

    def model_spec(self):
        return {"type": "fresnel", "focal_length": float(self.focal_length.detach()), "wavelength": self.wavelength}


class GratingDOE(_Analytic):
    """A linear phase ramp (a blazed grating once wrapped): ``φ = 2π (x cos θ + y sin θ) / period``, ``period``
    in mm, orientation ``angle`` θ in degrees from +x toward +y; the first order is deflected toward
    (cos θ, sin θ) with ``sin α = λ/period``. Fabricated with L = 2 levels it is a 0/π binary grating.
    ``period`` and ``angle`` are parameters."""

    spec_type = "grating"

    def __init__(self, period: float, shape, pitch: float, angle: float = 0.0, aperture: str = "square", **optics):
        super().__init__(shape, pitch, aperture, **optics)
        self.period = _param(_positive(period, "the grating period"), "period", 0)
        self.angle = _param(float(angle), "angle", 0)

    def design_phase_pixels(self, rows, cols):
        x, y = self.pixel_xy(rows, cols)
        t = torch.deg2rad(self.angle)
        return (2 * math.pi / self.period) * (x[None, :] * torch.cos(t) + y[:, None] * torch.sin(t))

    def model_spec(self):
        return {"type": "grating", "period": float(self.period.detach()), "angle": float(self.angle.detach())}


class CubicDOE(_Analytic):
    """The cubic phase mask of wavefront coding (extended depth of field): ``φ = α ((x/R)³ + (y/R)³)``, ``α`` in
    radians (a parameter), ``R`` = ``radius`` mm (default half the smaller grid side)."""

    spec_type = "cubic"

    def __init__(self, alpha: float, shape, pitch: float, radius: float | None = None, aperture: str = "square",
                 **optics):
        super().__init__(shape, pitch, aperture, **optics)
        self.alpha = _param(float(alpha), "alpha", 0)
        self.radius = self._half_size() if radius is None else _positive(radius, "radius")

    def design_phase_pixels(self, rows, cols):
        x, y = self.pixel_xy(rows, cols)
        u, v = x / self.radius, y / self.radius
        return self.alpha * (u[None, :] ** 3 + v[:, None] ** 3)

    def model_spec(self):
        return {"type": "cubic", "alpha": float(self.alpha.detach()), "radius": self.radius}
