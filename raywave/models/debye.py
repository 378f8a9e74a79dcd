"""Reference PSF of an aberration-free focus: the non-paraxial scalar Debye integral.

A converging spherical wave of numerical aperture NA = n·sin α (α: marginal ray angle in the image
medium of index n) with amplitude a(θ) on its reference sphere gives, near the focus (ρ, z),

    U(ρ, z) = k ∫₀^α a(θ) J₀(k ρ sin θ) exp(i k z cos θ) sin θ dθ,        k = 2π n / λ

(the φ integral of the Debye integral (k/2π) ∫∫ a exp(i k s·r) dΩ done analytically). With this
normalisation Parseval gives the integral of |U|² over any plane z = const exactly:

    ∫∫ |U|² dx dy = ∫ |a|² / cos θ dΩ = 2π ∫₀^α |a(θ)|² tan θ dθ,

which is what :func:`debye_total_power` returns and what ``energy_fraction`` is measured against.
(The scalar |U|² integrated over a plane is not the Poynting flux: a plane-wave component at angle θ
contributes |a|²/cos θ, not |a|², which is why the 1/cos θ appears.) The θ integral is done by
Gauss–Legendre quadrature with enough nodes for ~1e-10 accuracy.

Apodisations (amplitude on the reference sphere, up to a constant):

* ``"ideal_lens"``: a ∝ cos^(-3/2) θ — a perfect thin lens (Zemax paraxial surface, r = f tan θ) fed by a
  uniform collimated beam: uniform power per unit pupil area and dA/dΩ = f²/cos³θ.
* ``"aplanatic"``: a ∝ cos^(1/2) θ (Abbe sine condition, r = f sin θ).
* ``"uniform"``: a = 1.

Units: lengths in mm, wavelengths in µm (vacuum). Arrays are indexed [iy, ix], both increasing with the
coordinate; pixel [ks//2, ks//2] is centred on the focus.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

try:  # scipy (a listed dependency) is faster than the fallbacks: torch's J0, numpy's O(n³) Gauss nodes
    from scipy.special import j0 as _scipy_j0
    from scipy.special import roots_legendre as _roots_legendre
except ImportError:  # pragma: no cover
    _scipy_j0 = None
    _roots_legendre = np.polynomial.legendre.leggauss

APODIZATIONS = ("ideal_lens", "aplanatic", "uniform")

#: Largest (points × quadrature nodes) block evaluated at once (memory ~ 16 bytes each).
_BLOCK = 1 << 22


def _j0(x: np.ndarray) -> np.ndarray:
    if _scipy_j0 is not None:
        return _scipy_j0(x)
    return torch.special.bessel_j0(torch.from_numpy(x)).numpy()  # pragma: no cover


@lru_cache(maxsize=32)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [-1, 1]."""
    x, w = _roots_legendre(int(n))
    x.flags.writeable = w.flags.writeable = False
    return x, w


def pupil_amplitude(theta: np.ndarray, apodization: str = "ideal_lens") -> np.ndarray:
    """Amplitude a(θ) on the reference sphere (relative), for ray angles θ (rad) to the axis."""
    c = np.cos(theta)
    if apodization == "ideal_lens":
        return c**-1.5
    if apodization == "aplanatic":
        return np.sqrt(c)
    if apodization == "uniform":
        return np.ones_like(c)
    raise ValueError(f"apodization must be one of {APODIZATIONS}, got {apodization!r}")


def _aperture_angle(na: float, n: float) -> float:
    if not 0 < na < n:
        raise ValueError(f"numerical aperture must satisfy 0 < NA < n = {n}, got {na!r}")
    return math.asin(na / n)


def auto_n_theta(na: float, wavelength: float, rho_max: float, z: float = 0.0, n: float = 1.0) -> int:
    """Gauss–Legendre nodes that resolve J₀(kρ sin θ)·exp(ikz cos θ) over [0, α] up to ρ = ``rho_max`` (mm)
    and defocus ``z`` (mm): ~0.7 nodes per radian of phase excursion plus a margin (converges to ~1e-12)."""
    alpha = _aperture_angle(na, n)
    k = 2 * math.pi * n / (wavelength * 1e-3)
    excursion = k * (rho_max * math.sin(alpha) + abs(z) * (1 - math.cos(alpha)))
    return 40 + math.ceil(0.7 * excursion)


def _quadrature(na: float, n: float, n_theta: int, apodization: str):
    """Gauss–Legendre nodes θ (rad) on [0, α] and weights × a(θ) sin θ."""
    alpha = _aperture_angle(na, n)
    x, w = _gauss_legendre(int(n_theta))
    theta = 0.5 * alpha * (x + 1)
    return theta, 0.5 * alpha * w * pupil_amplitude(theta, apodization) * np.sin(theta)


def debye_field(rho, na: float, wavelength: float, z: float = 0.0, n: float = 1.0,
                apodization: str = "ideal_lens", n_theta: int | None = None) -> torch.Tensor:
    """Complex field U(ρ, z) of the Debye focus (normalisation in the module docstring).

    Args:
        rho: distances (mm) from the axis through the focus, any shape (array or tensor).
        na: numerical aperture n·sin α; ``wavelength``: vacuum wavelength (µm); ``z``: defocus (mm, + is
            past the focus, along the propagation); ``n``: index of the image medium.
        n_theta: quadrature nodes (default :func:`auto_n_theta` for the largest ρ).
    Returns: complex128 tensor of ``rho``'s shape; ∫∫|U|² dx dy over a whole plane is :func:`debye_total_power`.
    """
    rho = np.asarray(torch.as_tensor(rho, dtype=torch.float64, device="cpu"), dtype=np.float64)
    shape, rho = rho.shape, rho.reshape(-1)
    if n_theta is None:
        n_theta = auto_n_theta(na, wavelength, float(rho.max(initial=0.0)), z, n)
    k = 2 * math.pi * n / (wavelength * 1e-3)
    theta, wgt = _quadrature(na, n, n_theta, apodization)
    coef = k * wgt * np.exp(1j * k * z * np.cos(theta))
    s = k * np.sin(theta)
    out = np.empty(rho.shape, dtype=np.complex128)
    step = max(1, _BLOCK // len(theta))
    for i in range(0, len(rho), step):
        j0 = _j0(rho[i:i + step, None] * s[None, :])
        out[i:i + step] = j0 @ coef.real + 1j * (j0 @ coef.imag)
    return torch.from_numpy(out.reshape(shape))


def debye_total_power(na: float, n: float = 1.0, apodization: str = "ideal_lens") -> float:
    """∫∫ |U|² dx dy over any whole plane z = const for :func:`debye_field`: 2π ∫₀^α |a|² tan θ dθ."""
    alpha = _aperture_angle(na, n)
    x, w = _gauss_legendre(200)  # smooth integrand: exact to rounding
    theta = 0.5 * alpha * (x + 1)
    a = pupil_amplitude(theta, apodization)
    return float(2 * math.pi * 0.5 * alpha * np.sum(w * a * a * np.tan(theta)))


def sensor_offsets(ks: int, pitch: float, oversample: int) -> np.ndarray:
    """(ks·oversample,) sub-sample offsets (mm) from the crop centre along one axis: pixel i is centred at
    (i − ks//2)·pitch and holds ``oversample`` midpoint-rule samples."""
    if ks < 1 or oversample < 1 or not pitch > 0:
        raise ValueError(f"need ks >= 1, oversample >= 1 and pitch > 0, got {ks}, {oversample}, {pitch}")
    pix = (np.arange(ks) - ks // 2) * pitch
    sub = ((np.arange(oversample) + 0.5) / oversample - 0.5) * pitch
    return (pix[:, None] + sub[None, :]).reshape(-1)


def pixel_integrate(irradiance: torch.Tensor, ks: int, oversample: int, pitch: float) -> torch.Tensor:
    """(ks·os, ks·os) point samples → (ks, ks) power per pixel (mean × pitch²)."""
    return irradiance.reshape(ks, oversample, ks, oversample).mean((1, 3)) * pitch * pitch


@dataclass
class DebyePSF:
    """Result of :func:`debye_psf`.

    psf: (ks, ks) float64, pixel-integrated irradiance normalised to sum 1 over the crop, [iy, ix].
    energy_fraction: power in the crop / power through the whole focal plane (Parseval total).
    center: (x, y) mm of pixel [ks//2, ks//2] (the focus); pitch: mm; defocus: z (mm).
    """

    psf: torch.Tensor
    energy_fraction: float
    center: tuple[float, float]
    pitch: float
    defocus: float


def debye_psf(na: float, wavelength: float, ks: int, pitch: float, n: float = 1.0, center=(0.0, 0.0),
              defocus: float = 0.0, apodization: str = "ideal_lens", oversample: int = 5,
              n_theta: int | None = None) -> DebyePSF:
    """Aberration-free, non-paraxial scalar PSF of a focus of numerical aperture ``na``.

    Args:
        na: n·sin(marginal ray angle) in the image medium; ``wavelength``: vacuum µm; ``n``: image index.
        ks: crop size (pixels); ``pitch``: pixel size (mm). Pixel [iy, ix] is centred at
            center + ((ix − ks//2)·pitch, (iy − ks//2)·pitch); ``center``: focus on the sensor (mm). The
            pattern is centred on the focus, so ``center`` only labels the result.
        defocus: sensor plane z relative to the focus (mm).
        apodization: "ideal_lens" (a ∝ cos^-3/2 θ), "aplanatic" (a ∝ cos^1/2 θ) or "uniform".
        oversample: midpoint-rule samples per pixel and axis (1: point samples at the pixel centres).
        n_theta: Gauss–Legendre nodes in θ (default :func:`auto_n_theta`, converged to ~1e-10).
    Returns: :class:`DebyePSF` (psf (ks, ks) float64 summing to 1, energy fraction in the crop, ...).
    """
    off = sensor_offsets(ks, pitch, oversample)
    rho = np.hypot(off[None, :], off[:, None])
    u = debye_field(rho, na, wavelength, defocus, n, apodization, n_theta)
    power = pixel_integrate(u.abs() ** 2, ks, oversample, pitch)
    total = float(power.sum())
    return DebyePSF(power / total, total / debye_total_power(na, n, apodization),
                    (float(center[0]), float(center[1])), float(pitch), float(defocus))
