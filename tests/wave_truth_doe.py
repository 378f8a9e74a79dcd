"""An independent scalar wave-optics reference for a DOE inside a lens (issue 46): no rays, no raywave engine.

The system: a distant point source at field angle (θx, θy); ideal thin lens A (focal length ``f_a``, the stop: a
sharp circle of radius ``radius_a``), a gap ``gap1``, the DOE (a thin phase screen: its pixel map, as fabricated),
a gap ``gap2``, ideal thin lens B, and the sensor at B's image of the beam's focus. Variants (issue 46): a second
DOE ``gap12`` behind the first; the first DOE conformal on a sphere in air (its phase applied on the sag by
multi-slice angular spectrum, :func:`through_curved_screen`: no rays, no local-grating model).

* Lens A turns the plane wave at (θx, θy) into the sphere converging exactly on ``f_a·(tan θx, tan θy, 1)``
  (raywave's ``IdealLens`` is that lens for collimated light).
* Lens B is perfect for the beam it actually receives (Zemax PARAXIAL, OPD mode 0): the beam leaving the DOE
  converges (paraxially) on a point P (A's focus imaged by the DOE's paraxial power ``1/f_doe``, on axis); B turns
  the sphere on P into the sphere on P', P's image by a thin lens of focal length ``f_b``, with the exact phase
  ``φ_B = k (±|X − P| − |X − P'|)``; the sensor lies in P''s plane.

Propagation: the exact angular spectrum (evanescent waves dropped, Matsushima's band limit on the sampled transfer
function) on the DOE's own grid (one sample per DOE pixel, or ``oversample``), the aperture's edge anti-aliased by
its pixel coverage (sub-sampled 16×16 on the edge pixels). The sensor plane's irradiance is integrated over the
sensor pixels exactly for the band-limited samples (a box filter applied in Fourier space), on pixels centred on a
given point. :func:`airy_reference` checks the machinery: lens A alone against the Rayleigh–Sommerfeld integral
done by quadrature (the non-paraxial Airy pattern).

numpy / scipy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from scipy.interpolate import CubicSpline
from scipy.special import roots_legendre


@dataclass
class TwoLensSystem:
    """Lengths mm, wavelength µm, angles degrees. ``f_doe``: the DOE's paraxial focal length for the beam's order
    (``inf``: none); ``doe_phase``: the DOE's phase (rad) on the grid ``(n, n)`` (None: a blank DOE)."""

    wavelength: float = 0.55
    f_a: float = 10.0
    radius_a: float = 0.4
    gap1: float = 3.0
    gap2: float = 3.0
    f_b: float = 10.0
    f_doe: float = math.inf
    field: tuple = (0.0, 0.0)
    #: a second DOE ``gap12`` mm behind the first (``gap2`` then runs from it to B), paraxial focal length ``f_doe2``
    f_doe2: float = math.inf
    gap12: float = 0.0
    #: the first DOE on a sphere of this radius (mm, vertex on its plane; ``inf``: a plane), in air on both sides
    doe_radius: float = math.inf

    @property
    def k(self) -> float:
        return 2 * math.pi / (self.wavelength * 1e-3)

    def focus_a(self) -> np.ndarray:
        """A's focus (x, y, z) mm, z from A."""
        tx, ty = (math.tan(math.radians(v)) for v in self.field)
        return np.array([self.f_a * tx, self.f_a * ty, self.f_a])

    def beam_focus(self) -> np.ndarray:
        """P: where the beam leaving the DOE converges (paraxial image of A's focus by the DOE), (x, y, z from B)."""
        pa = self.focus_a()
        s = pa[2] - self.gap1  # from the DOE
        s2, mag = _thin_image(s, self.f_doe)
        s3, mag2 = _thin_image(s2 - self.gap12, self.f_doe2)
        return np.array([pa[0] * mag * mag2, pa[1] * mag * mag2, s3 - self.gap2])

    def image(self) -> np.ndarray:
        """P': B's image of P, (x, y, z from B); z is the sensor distance."""
        p = self.beam_focus()
        z2 = 1.0 / (1.0 / p[2] + 1.0 / self.f_b)
        return np.array([p[0] * z2 / p[2], p[1] * z2 / p[2], z2])


def _thin_image(s: float, f: float):
    """``(s', m)``: the paraxial image distance (mm, after the element) of a point ``s`` mm after a thin element of
    focal length ``f`` (a converging beam's focus: s > 0), and the lateral magnification."""
    if math.isinf(f):
        return s, 1.0
    s2 = 1.0 / (1.0 / s + 1.0 / f)
    return s2, s2 / s


def coords(n: int, pitch: float):
    """Sample-centre coordinates (mm) of a centred n-sample axis (as a DOE's simulation grid)."""
    return (np.arange(n) - (n - 1) / 2) * pitch


def circle_coverage(x: np.ndarray, y: np.ndarray, radius: float, pitch: float, sub: int = 16) -> np.ndarray:
    """Fraction of each pixel (centres x (nx,), y (ny,), pitch mm) inside the circle of ``radius`` (sub×sub
    sub-samples on the pixels the edge crosses)."""
    r = np.hypot(x[None, :], y[:, None])
    cov = (r < radius).astype(np.float64)
    edge = np.abs(r - radius) < pitch
    iy, ix = np.nonzero(edge)
    o = (np.arange(sub) + 0.5) / sub - 0.5
    for a, b in zip(iy, ix):
        xs = x[b] + o[None, :] * pitch
        ys = y[a] + o[:, None] * pitch
        cov[a, b] = np.mean(xs * xs + ys * ys < radius * radius)
    return cov


def asm(u: np.ndarray, pitch: float, z: float, wavelength: float, shift=(0.0, 0.0)) -> np.ndarray:
    """Angular-spectrum propagation of ``u`` (ny, nx) over ``z`` mm in air (λ µm); the output is sampled at the
    input's sample positions plus ``shift`` (mm, a lateral offset of the output grid)."""
    h = asm_transfer(u.shape, pitch, z, wavelength, shift)
    return sfft.ifft2(sfft.fft2(u, workers=1) * h, workers=1)


def asm_transfer(shape, pitch: float, z: float, wavelength: float, shift=(0.0, 0.0)) -> np.ndarray:
    """The band-limited angular-spectrum transfer function of :func:`asm` on a grid of ``shape``."""
    ny, nx = shape
    lam = wavelength * 1e-3
    fx = sfft.fftfreq(nx, pitch)
    fy = sfft.fftfreq(ny, pitch)
    f2 = fx[None, :] ** 2 + fy[:, None] ** 2
    w2 = 1.0 / lam**2 - f2
    prop = w2 > 0
    w = np.sqrt(np.where(prop, w2, 0.0))
    # Matsushima & Shimobaba's band limit: the transfer function's chirp stays sampled
    lim_x = 1.0 / (lam * math.sqrt((2 * z / (nx * pitch)) ** 2 + 1))
    lim_y = 1.0 / (lam * math.sqrt((2 * z / (ny * pitch)) ** 2 + 1))
    band = prop & (np.abs(fx)[None, :] < lim_x) & (np.abs(fy)[:, None] < lim_y)
    return np.where(band, np.exp(2j * math.pi * (z * w + fx[None, :] * shift[0] + fy[:, None] * shift[1])), 0)


def _sphere(x, y, p, sign: float, k: float):
    """Phase (rad) of a sphere on p = (x, y, z): −sign·k·|X − p| (sign +1 converging toward p)."""
    return -sign * k * np.sqrt((x[None, :] - p[0]) ** 2 + (y[:, None] - p[1]) ** 2 + p[2] ** 2)


def pixel_integrate(intensity: np.ndarray, pitch: float, sensor_pitch: float) -> np.ndarray:
    """Irradiance integrated over sensor pixels of ``sensor_pitch`` centred on every sample (box filter in
    Fourier space: exact for band-limited samples)."""
    ny, nx = intensity.shape
    fx = sfft.fftfreq(nx, pitch)
    fy = sfft.fftfreq(ny, pitch)
    box = np.sinc(fx * sensor_pitch)[None, :] * np.sinc(fy * sensor_pitch)[:, None]
    return np.real(sfft.ifft2(sfft.fft2(intensity, workers=1) * box, workers=1))


def _transmission(n: int, pad: int, phase) -> np.ndarray:
    """The DOE grid's transmission on the padded grid: ``exp(i phase)`` inside (phase (n, n) rad, or None: 1; a
    complex array is the transmission itself, e.g. a chosen sum of diffraction orders), 0 outside."""
    t = np.zeros((n + 2 * pad, n + 2 * pad), dtype=np.complex128)
    if phase is None:
        t[pad:pad + n, pad:pad + n] = 1.0
    elif np.iscomplexobj(phase):
        t[pad:pad + n, pad:pad + n] = phase
    else:
        t[pad:pad + n, pad:pad + n] = np.exp(1j * np.asarray(phase))
    return t


def sag_sphere(x: np.ndarray, y: np.ndarray, radius: float) -> np.ndarray:
    """Sag (mm, along +z) of a sphere of ``radius`` mm with its vertex at the origin, on the grid (y, x); points
    beyond the hemisphere get the rim's sag."""
    r2 = np.minimum(x[None, :] ** 2 + y[:, None] ** 2, radius * radius)
    return r2 / (radius + math.copysign(1.0, radius) * np.sqrt(radius * radius - r2))


def through_curved_screen(u: np.ndarray, t: np.ndarray, sag: np.ndarray, pitch: float, wavelength: float,
                          dz: float, lit: float = 1e-3):
    """The field ``u`` (on the vertex plane) through a thin screen ``t`` lying on the surface ``z = sag(x, y)``:
    multi-slice, the angular spectrum (exact) between planes ``dz`` apart, and every point's transmission applied
    on the plane nearest its sag (an error below ``dz/2`` in its position). The screen's lit part (``|u|² >
    lit·max`` where ``t ≠ 0``) sets the sag range; points beyond it (the faint edge-diffraction tails) take the
    range's end planes. Returns ``(field, z)``: the field on the plane ``z`` mm after the vertex."""
    inten = np.abs(u) ** 2 * (np.abs(t) > 0)
    lit_mask = inten > lit * inten.max()
    lo, hi = float(sag[lit_mask].min()), float(sag[lit_mask].max())
    m = max(1, int(math.ceil((hi - lo) / dz)))
    step = (hi - lo) / m if hi > lo else dz
    idx = np.clip(np.floor((sag - lo) / step), 0, m - 1).astype(int)  # slab of every point
    z = lo + 0.5 * step  # the slabs' mid-planes
    u = asm(u, pitch, z, wavelength) if z != 0 else u
    h = asm_transfer(u.shape, pitch, step, wavelength)
    for j in range(m):
        u = np.where(idx == j, u * t, u)
        if j < m - 1:
            u = sfft.ifft2(sfft.fft2(u, workers=1) * h, workers=1)
            z += step
    return u, z


def sensor_psf(sys: TwoLensSystem, n: int, pitch: float, doe_phase, center, sensor_pitch: float, ks: int,
               pad: int = 400, doe2_phase=None, sag_step: float = 2.5e-4):
    """The reference PSF ``(ks, ks)`` (sum 1), pixel ``[ks//2, ks//2]`` centred on ``center`` (x, y) mm.

    Args: the system; the DOE's grid (``n`` samples of ``pitch`` mm, centred: its simulation grid), which blocks
    the light outside it; the DOE's phase on it (rad, (n, n); None: a blank DOE of that size; complex: its
    transmission); sensor pixels of
    ``sensor_pitch`` (an integer multiple of ``pitch``); ``pad`` samples of grid on every side of the DOE's;
    ``doe2_phase``: the second DOE's (same grid; with ``sys.gap12``); ``sag_step``: the multi-slice step (mm) of a
    DOE on a sphere (``sys.doe_radius``), :func:`through_curved_screen`."""
    doe_n = n
    n = doe_n + 2 * pad
    t = _transmission(doe_n, pad, doe_phase)
    s = int(round(sensor_pitch / pitch))
    if abs(s * pitch - sensor_pitch) > 1e-9 * sensor_pitch:
        raise ValueError("the sensor pitch must be an integer multiple of the grid pitch")
    k = sys.k
    x = coords(n, pitch)
    u = circle_coverage(x, x, sys.radius_a, pitch) * np.exp(1j * (_sphere(x, x, sys.focus_a(), 1.0, k) + k * sys.f_a))
    u = asm(u, pitch, sys.gap1, sys.wavelength)
    z = 0.0
    if math.isinf(sys.doe_radius):
        u = u * t
    else:
        u, z = through_curved_screen(u, t, sag_sphere(x, x, sys.doe_radius), pitch, sys.wavelength, sag_step)
    if sys.gap12 > 0 or doe2_phase is not None:
        u = asm(u, pitch, sys.gap12 - z, sys.wavelength) * _transmission(doe_n, pad, doe2_phase)
        z = 0.0
    u = asm(u, pitch, sys.gap2 - z, sys.wavelength)
    p, q = sys.beam_focus(), sys.image()
    phi_b = _sphere(x, x, q, 1.0, k) - _sphere(x, x, p, math.copysign(1.0, p[2]), k)
    u = u * np.exp(1j * (phi_b - phi_b[n // 2, n // 2]))
    # output grid: the samples shifted so that ``center`` is a sample
    x0 = x[0]
    dx = (center[0] - x0) / pitch
    dy = (center[1] - x0) / pitch
    sx, sy = (dx - math.floor(dx)) * pitch, (dy - math.floor(dy)) * pitch
    u = asm(u, pitch, q[2], sys.wavelength, shift=(sx, sy))
    irr = pixel_integrate(np.abs(u) ** 2, pitch, sensor_pitch)
    jx, jy = int(math.floor(dx)), int(math.floor(dy))
    idx = (np.arange(ks) - ks // 2) * s
    crop = irr[np.ix_(jy + idx, jx + idx)]
    if jy + idx.min() < 0 or jx + idx.min() < 0 or jy + idx.max() >= n or jx + idx.max() >= n:
        raise ValueError("the sensor crop leaves the reference grid")
    crop = np.clip(crop, 0, None)
    return crop / crop.sum()


def airy_reference(sys: TwoLensSystem, sensor_pitch: float, ks: int, sub: int = 6, n_rho: int = 200,
                   n_phi: int = 256, n_radii: int | None = None) -> np.ndarray:
    """Lens A alone, on axis: the Rayleigh–Sommerfeld (first kind) integral over its pupil by Gauss–Legendre
    quadrature (radius) and the trapezoidal rule (azimuth), at the focal plane, integrated over sensor pixels
    (``sub``² Gauss–Legendre points each); (ks, ks), sum 1. The radial profile is computed on ``n_radii`` radii up to
    the crop's corner (default: 24 a micrometre) and interpolated by a cubic spline. Converged: with 24 radii a µm the
    spline is within 1e-8 (ring relative L1) of 48 a µm, and 8 → 12 pixel points change it by 5e-11; with n_rho 300,
    n_phi 512 the quadrature is converged for radii ≤ 0.2 mm (600 → 1024 changes nothing). Issue 46: the earlier
    form (600 radii over twice the crop's width, linear interpolation, midpoint pixel points) was 2.6e-3 – 7e-3 off
    ring by ring on a 128-pixel crop, which read as an engine error."""
    k, a, f = sys.k, sys.radius_a, sys.f_a
    t, wt = roots_legendre(n_rho)
    rho = 0.5 * a * (t + 1)
    w_rho = 0.5 * a * wt * rho
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    r_max = sensor_pitch * (ks // 2 + 1) * math.sqrt(2.0)
    n_r = n_radii if n_radii is not None else max(64, int(math.ceil(r_max * 1e3 * 24)))
    radii = np.linspace(0, r_max, n_r)
    prof = np.empty(radii.size)
    cp, sp = np.cos(phi), np.sin(phi)
    r0 = np.sqrt(rho * rho + f * f)[:, None]
    for i, r in enumerate(radii):
        dx = r - rho[:, None] * cp[None, :]
        dy = -rho[:, None] * sp[None, :]
        big_r = np.sqrt(dx * dx + dy * dy + f * f)
        h = (f / big_r**2) * (1 / big_r - 1j * k) * np.exp(1j * k * (big_r - r0))
        prof[i] = abs(np.sum(h * w_rho[:, None]) * (2 * math.pi / n_phi)) ** 2
    g, wg = roots_legendre(sub)
    o = 0.5 * g * sensor_pitch
    c = (np.arange(ks) - ks // 2) * sensor_pitch
    xx = (c[:, None] + o[None, :]).reshape(-1)
    ww = np.tile(0.5 * wg, ks)
    rr = np.hypot(xx[None, :], xx[:, None])
    img = (CubicSpline(radii, prof)(rr) * ww[None, :] * ww[:, None]).reshape(ks, sub, ks, sub).sum((1, 3))
    return img / img.sum()


def rel_l1(a, b) -> float:
    """Σ|a − b| / Σ|b|."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.abs(a - b).sum() / np.abs(b).sum())
