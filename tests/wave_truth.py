"""Independent scalar wave-optics truths for the ray-wave engine: no rays, no exit pupil, no engine code.

A field is sampled on a regular grid (pitch ``p`` mm, ``origin`` the (x, y) mm of sample [0, 0]) as an *envelope*
``env`` times a plane-wave carrier ``exp(i k (cx x + cy y))`` (``carrier`` = (cx, cy), direction sines); every
propagation is the plain full-grid angular spectrum (:func:`asm`: zero-padded, no band limit, no windowing of the
transfer function) and every thin element multiplies the field by its exact phase. The PSF on the sensor is the
intensity of the sampled field, integrated over the sensor's pixels exactly for a band-limited intensity
(:func:`pixel_power`: the box filter applied in the Fourier domain, sampled at the pixel centres).

The systems:

- :func:`two_ideal_lenses_psf`: a plane wave at angle θ through a sharp circular stop on ideal lens A (the exact
  phase that turns that plane wave into a sphere converging on ``f_A·(tan θ_x, tan θ_y, 1)``), the angular spectrum
  to ideal lens B (the exact phase that turns a sphere converging on that point into a sphere converging on its
  paraxial image by B: "perfect for the beam it actually receives"), an optional thin phase element (a DOE: any
  callable phase) between them or after B, and the angular spectrum to the sensor. The stop's edge diffracts all the
  way from A: the truth knows nothing of exit pupils.

Shared by tests/test_ideal_lens_truth.py (issue 47) and, for a DOE between the lenses, issue 46.
Units: mm, wavelengths in µm, +z the optical axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

C128 = torch.complex128
F64 = torch.float64


def fft_size(n: int) -> int:
    """The smallest 2^a·3^b·5^c ≥ n (a fast FFT length)."""
    best = 1 << max(int(n - 1).bit_length(), 0)
    p2 = 1
    while p2 < 2 * n:
        p3 = p2
        while p3 < 2 * n:
            p5 = p3
            while p5 < 2 * n:
                if n <= p5 < best:
                    best = p5
                p5 *= 5
            p3 *= 3
        p2 *= 2
    return best


def grid_xy(origin, shape, pitch: float):
    """Sample coordinates (x, y), each (ny, nx) mm, of the grid ``shape`` = (ny, nx) starting at ``origin`` (x, y)."""
    ny, nx = shape
    gx = origin[0] + torch.arange(nx, dtype=F64) * pitch
    gy = origin[1] + torch.arange(ny, dtype=F64) * pitch
    y, x = torch.meshgrid(gy, gx, indexing="ij")
    return x, y


def asm(env: torch.Tensor, origin, pitch: float, wavelength: float, z: float, carrier, out_origin, out_shape,
        margin: float = 0.3, n: float = 1.0) -> torch.Tensor:
    """The plain angular spectrum over ``z`` mm of the field ``env·exp(i k n (cx x + cy y))`` (``env`` (ny, nx)
    complex128 on the grid at ``origin``, pitch mm, ``wavelength`` µm in vacuum, medium index ``n``): the envelope
    (same carrier) on the output grid ``out_shape`` at ``out_origin`` (any (x, y): a sub-sample offset is a phase ramp
    of the spectrum). One zero-padded FFT grid holds both windows and ``margin`` mm around them; evanescent waves are
    dropped. Exact for a field that fits the grid (no aliasing of what leaves it beyond the margin)."""
    p = pitch
    (ny, nx), (oy, ox) = env.shape, tuple(out_shape)
    lo_x = min(origin[0], out_origin[0]) - margin
    hi_x = max(origin[0] + (nx - 1) * p, out_origin[0] + (ox - 1) * p) + margin
    lo_y = min(origin[1], out_origin[1]) - margin
    hi_y = max(origin[1] + (ny - 1) * p, out_origin[1] + (oy - 1) * p) + margin
    jx, jy = int(math.ceil((origin[0] - lo_x) / p)), int(math.ceil((origin[1] - lo_y) / p))
    bx, by = origin[0] - jx * p, origin[1] - jy * p  # the big grid's origin: on the input's lattice
    nx_ = fft_size(int(math.ceil((hi_x - bx) / p)) + 2)
    ny_ = fft_size(int(math.ceil((hi_y - by) / p)) + 2)
    big = torch.zeros((ny_, nx_), dtype=C128)
    big[jy:jy + ny, jx:jx + nx] = env
    kx = int(math.floor((out_origin[0] - bx) / p + 1e-9))
    ky = int(math.floor((out_origin[1] - by) / p + 1e-9))
    dx, dy = out_origin[0] - bx - kx * p, out_origin[1] - by - ky * p
    k = n / (wavelength * 1e-3)  # cycles / mm
    fx = torch.fft.fftfreq(nx_, d=p, dtype=F64)
    fy = torch.fft.fftfreq(ny_, d=p, dtype=F64)
    gx, gy = fx + k * carrier[0], fy + k * carrier[1]
    arg = k * k - gx[None, :] ** 2 - gy[:, None] ** 2
    ph = 2 * math.pi * (z * torch.sqrt(arg.clamp_min(0.0)) + fx[None, :] * dx + fy[:, None] * dy)
    h = torch.polar((arg > 0).to(F64), ph)
    return torch.fft.ifft2(torch.fft.fft2(big) * h)[ky:ky + oy, kx:kx + ox]


def circle_cover(x: torch.Tensor, y: torch.Tensor, radius: float, pitch: float, sub: int = 16) -> torch.Tensor:
    """Area fraction of each ``pitch`` sample cell (centred at x, y) inside the circle of ``radius`` about the origin
    (``sub``² samples on the edge's cells)."""
    rr = torch.sqrt(x * x + y * y)
    c = (rr <= radius).to(F64)
    edge = (rr - radius).abs() < pitch
    s = ((torch.arange(sub, dtype=F64) + 0.5) / sub - 0.5) * pitch
    xs, ys = x[edge][:, None, None] + s[None, None, :], y[edge][:, None, None] + s[None, :, None]
    c[edge] = ((xs * xs + ys * ys) <= radius * radius).to(F64).mean((1, 2))
    return c


def taper(shape, width: int) -> torch.Tensor:
    """A (ny, nx) C¹ raised-cosine taper falling from 1 to 0 over ``width`` samples at every edge."""
    def one(n):
        w = torch.ones(n, dtype=F64)
        t = 0.5 - 0.5 * torch.cos(math.pi * (torch.arange(width, dtype=F64) + 0.5) / width)
        w[:width], w[n - width:] = t, t.flip(0)
        return w
    return one(shape[0])[:, None] * one(shape[1])[None, :]


def pixel_power(inten: torch.Tensor, origin, pitch: float, center, ks: int, pixel: float) -> torch.Tensor:
    """Power (ks, ks) in the sensor pixels of size ``pixel`` mm, pixel [ks//2, ks//2] centred at ``center`` (x, y),
    of the intensity ``inten`` (ny, nx) sampled at ``pitch`` on the grid at ``origin``: the box filter of a pixel
    applied to the band-limited intensity in the Fourier domain (exact for an intensity band-limited below the
    grid's Nyquist frequency and ~0 at the grid's edges), then sampled at the pixel centres by the same spectrum."""
    ny, nx = inten.shape
    spec = torch.fft.fft2(inten.to(F64))
    fx = torch.fft.fftfreq(nx, d=pitch, dtype=F64)
    fy = torch.fft.fftfreq(ny, d=pitch, dtype=F64)
    spec = spec * (torch.sinc(fy * pixel)[:, None] * torch.sinc(fx * pixel)[None, :]) * pixel * pixel
    off = (torch.arange(ks, dtype=F64) - ks // 2) * pixel
    px, py = center[0] + off - origin[0], center[1] + off - origin[1]
    ex = torch.exp(2j * math.pi * fx[None, :] * px[:, None])  # (ks, nx)
    ey = torch.exp(2j * math.pi * fy[None, :] * py[:, None])  # (ks, ny)
    return (ey @ spec.to(C128) @ ex.T).real / (nx * ny)


def sphere_phase(x: torch.Tensor, y: torch.Tensor, z: float, point, wavelength: float) -> torch.Tensor:
    """Phase (rad) −k·|r − point| of a sphere converging on ``point`` (x, y, z) mm, at the plane z (k = 2π/λ, air)."""
    k = 2 * math.pi / (wavelength * 1e-3)
    return -k * torch.sqrt((x - point[0]) ** 2 + (y - point[1]) ** 2 + (z - point[2]) ** 2)


@dataclass
class TwoLenses:
    """Ideal lens A (focal length ``f_a`` mm, the stop: a sharp circle of ``radius`` mm, at z = 0) and ideal lens B
    (``f_b`` mm) ``gap`` mm behind it, in air; the sensor at B's paraxial image of A's focal plane."""

    f_a: float = 80.0
    f_b: float = 12.0
    gap: float = 10.0
    radius: float = 0.6

    def image_distance(self) -> float:
        """z (mm) of the sensor behind B: the paraxial image of A's focal plane by B."""
        u = self.f_a - self.gap
        return 1.0 / (1.0 / self.f_b + 1.0 / u)

    def focus_a(self, theta) -> tuple[float, float, float]:
        """Where lens A sends a plane wave at the angles ``theta`` = (θx, θy) degrees: f_A·(tan θx, tan θy, 1)."""
        return (self.f_a * math.tan(math.radians(theta[0])), self.f_a * math.tan(math.radians(theta[1])), self.f_a)

    def focus_b(self, theta) -> tuple[float, float, float]:
        """B's image of :meth:`focus_a` (through B's centre, undeviated): the system's focus (x, y, z) mm."""
        pa = self.focus_a(theta)
        v = self.image_distance()
        m = v / (self.f_a - self.gap)
        return (pa[0] * m, pa[1] * m, self.gap + v)

    def effective_focal_length(self) -> float:
        return 1.0 / (1.0 / self.f_a + 1.0 / self.f_b - self.gap / (self.f_a * self.f_b))

    def na(self) -> float:
        """Image-space NA on axis (the marginal ray's sine at the focus)."""
        h = self.radius * (self.f_a - self.gap) / self.f_a
        return math.sin(math.atan(h / self.image_distance()))


def _direction(p_from, p_to):
    d = [b - a for a, b in zip(p_from, p_to)]
    s = math.sqrt(sum(v * v for v in d))
    return d[0] / s, d[1] / s


def two_ideal_lenses_psf(system: TwoLenses, theta, wavelength: float, center, ks: int, pixel: float,
                         pitch: float = 1e-3, doe=None, doe_z: float | None = None, sensor_z: float | None = None,
                         margin: float = 0.4, doe_lattice=None) -> torch.Tensor:
    """The PSF (ks, ks) float64 summing to 1 of :class:`TwoLenses` for a plane wave at ``theta`` (θx, θy) degrees,
    ``wavelength`` µm, on the sensor (default at :meth:`TwoLenses.image_distance` behind B; ``sensor_z`` mm from A
    otherwise), pixels of ``pixel`` mm, pixel [ks//2, ks//2] centred at ``center`` (x, y) mm. ``doe``: an optional
    thin phase element ``doe(x, y, wavelength) -> phase (rad)`` at ``doe_z`` mm from A (between the lenses, or after
    B). Field sampled at ``pitch`` mm (the stop's edge area-weighted), ``margin`` mm of ripples kept around the beam
    and tapered off (their light lands ≥ ~margin mm from the focus). ``doe_lattice``: (x, y) mm of a pixel centre of a
    pixelated DOE (:func:`pixel_phase`) of pitch ``pitch``: the DOE plane's samples then sit on its pixel centres, one
    sample a pixel, instead of straddling the pixels' phase steps."""
    s = system
    th = [math.radians(t) for t in theta]
    pa = s.focus_a(theta)
    pb = s.focus_b(theta)
    z_s = s.gap + s.image_distance() if sensor_z is None else float(sensor_z)
    # A: the stop's envelope with the carrier of the chief ray towards focus_a (the plane wave's own carrier
    # (sin θx, sin θy) plus A's exact phase make the sphere)
    n0 = int(math.ceil(2 * s.radius / pitch)) + 6
    org = (-(n0 - 1) / 2 * pitch,) * 2
    x, y = grid_xy(org, (n0, n0), pitch)
    c_a = _direction((0.0, 0.0, 0.0), pa)
    phi = sphere_phase(x, y, 0.0, pa, wavelength) - 2 * math.pi / (wavelength * 1e-3) * (c_a[0] * x + c_a[1] * y)
    env = circle_cover(x, y, s.radius, pitch).to(C128) * torch.polar(torch.ones_like(phi), phi)
    planes = [(s.gap, "B")]
    if doe is not None:
        planes.append((float(doe_z), "DOE"))
    planes.sort()
    z, carrier = 0.0, c_a
    beam_r = s.radius  # the geometric beam's half-width on the current plane
    k = 2 * math.pi / (wavelength * 1e-3)
    for zp, what in planes:
        target = pa if zp <= s.gap else pb  # the beam converges on A's focus before B, on B's image after it
        cx0 = org[0] + (env.shape[1] - 1) / 2 * pitch
        cy0 = org[1] + (env.shape[0] - 1) / 2 * pitch
        t = (zp - z) / (target[2] - z)
        cx1, cy1 = cx0 + (target[0] - cx0) * t, cy0 + (target[1] - cy0) * t
        beam_r = beam_r * abs(target[2] - zp) / abs(target[2] - z)
        m = int(math.ceil((beam_r + margin) / pitch))
        out_org = (cx1 - m * pitch, cy1 - m * pitch)
        if what == "DOE" and doe_lattice is not None:
            out_org = tuple(c + round((o - c) / pitch) * pitch for o, c in zip(out_org, doe_lattice))
        env = asm(env, org, pitch, wavelength, zp - z, carrier, out_org, (2 * m + 1, 2 * m + 1), margin=margin)
        env = env * taper(env.shape, max(int(0.25 * margin / pitch), 4))
        org, z = out_org, zp
        x, y = grid_xy(org, env.shape, pitch)
        if what == "B":
            new = _direction((0.0, 0.0, s.gap), pb)
            phi = (sphere_phase(x, y, zp, pb, wavelength) - sphere_phase(x, y, zp, pa, wavelength)
                   + k * ((carrier[0] - new[0]) * x + (carrier[1] - new[1]) * y))
            carrier = new
        else:
            phi = doe(x, y, wavelength)
        env = env * torch.polar(torch.ones_like(phi), phi)
    # to the sensor: the crop plus a margin of samples, on the grid's lattice shifted to the crop's corner
    half = (ks // 2 + 8) * pixel
    nout = int(math.ceil(2 * half / pitch)) + 1
    out_org = (center[0] - half, center[1] - half)
    u = asm(env, org, pitch, wavelength, z_s - z, carrier, out_org, (nout, nout), margin=margin)
    inten = u.abs().square()
    p = pixel_power(inten * taper(inten.shape, int(4 * pixel / pitch)), out_org, pitch, center, ks, pixel)
    return p / p.sum()


def doe_phase_on(doe, wavelength: float):
    """A raywave DOE as the truth's thin element: ``(origin (x, y) mm, pitch mm, phase (ny, nx) rad)`` of its whole
    pixel grid at ``wavelength`` µm (its definition: the fabricated, quantised phase of each pixel; nothing of the
    engine's propagation). The grid's extent is the DOE's (square) aperture."""
    with torch.no_grad():
        x, y = doe.pixel_xy()
        ph = doe.phase_pixels(wavelength, slice(None), slice(None)).detach().to(F64)
    return (float(x[0]), float(y[0])), float(doe.pitch), ph


def pixel_phase(doe, wavelength: float):
    """A raywave DOE as :func:`two_ideal_lenses_psf`'s thin element: ``(phase(x, y, wavelength) -> rad, lattice)``,
    ``phase`` the phase of the pixel (of :func:`doe_phase_on`) holding each point (the nearest pixel centre; the edge
    pixels' beyond the grid), ``lattice`` (x, y) mm of pixel [0, 0]'s centre (pass it as ``doe_lattice``)."""
    origin, p, ph = doe_phase_on(doe, wavelength)

    def phase(x, y, _wavelength):
        ix = torch.clamp(torch.round((x - origin[0]) / p).long(), 0, ph.shape[1] - 1)
        iy = torch.clamp(torch.round((y - origin[1]) / p).long(), 0, ph.shape[0] - 1)
        return ph[iy, ix]
    return phase, origin


def ideal_lens_doe_psf(f: float, radius: float, wavelength: float, center, ks: int, pixel: float, sensor_dist: float,
                       doe=None, doe_dist: float | None = None, depth: float | None = None,
                       margin: float = 0.3) -> torch.Tensor:
    """The on-axis PSF (ks, ks) float64 summing to 1 of an ideal thin lens (focal length ``f`` mm, a sharp circular
    stop of ``radius`` mm on it) with an optional DOE (a raywave DOE: :func:`doe_phase_on`, its grid and square
    aperture; sampled at its pitch) ``doe_dist`` mm behind it, on the sensor ``sensor_dist`` mm behind the lens.
    The source: a plane wave (``depth`` None) or a point ``depth`` mm in front of the lens (a spherical wave, amplitude
    ∝ 1/distance); the lens is exact for it (the phase that turns it into a sphere converging on its image,
    1/v = 1/f − 1/depth). Plain angular spectrum lens → DOE → sensor (:func:`asm`); pixels of ``pixel`` mm,
    pixel [ks//2, ks//2] centred at ``center``."""
    pitch = float(doe.pitch) if doe is not None else 1e-3
    v = f if depth is None else 1.0 / (1.0 / f - 1.0 / depth)
    n0 = int(math.ceil(2 * radius / pitch)) + 6
    org = (-(n0 - 1) / 2 * pitch,) * 2
    x, y = grid_xy(org, (n0, n0), pitch)
    amp = circle_cover(x, y, radius, pitch)
    if depth is not None:
        amp = amp * depth / torch.sqrt(x * x + y * y + depth * depth)
    env = amp.to(C128) * torch.polar(torch.ones_like(x), sphere_phase(x, y, 0.0, (0.0, 0.0, v), wavelength))
    z = 0.0
    if doe is not None:
        d_org, _, ph = doe_phase_on(doe, wavelength)
        env = asm(env, org, pitch, wavelength, doe_dist, (0.0, 0.0), d_org, ph.shape, margin=margin)
        env = env * torch.polar(torch.ones_like(ph), ph)
        org, z = d_org, doe_dist
    half = (ks // 2 + 8) * pixel
    nout = int(math.ceil(2 * half / pitch)) + 1
    out_org = (center[0] - half, center[1] - half)
    u = asm(env, org, pitch, wavelength, sensor_dist - z, (0.0, 0.0), out_org, (nout, nout), margin=margin)
    inten = u.abs().square()
    p = pixel_power(inten * taper(inten.shape, int(4 * pixel / pitch)), out_org, pitch, center, ks, pixel)
    return p / p.sum()
