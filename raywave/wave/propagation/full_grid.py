"""Classic band-limited angular spectrum on the full grid (the reference path; Matsushima & Shimobaba 2009)."""

from __future__ import annotations

import math

import torch

from raywave.wave.propagation._common import (_TWO_PI, _UM_TO_MM, _as_field, _pair, _positive, _sqrt_kz,
                                              _transfer, _z_value)


def angular_spectrum(
    u: torch.Tensor,
    pitch,
    wavelength: float,
    z,
    n: float = 1.0,
    pad: float = 2,
    band_limit: bool = True,
) -> torch.Tensor:
    """Band-limited angular-spectrum propagation on the full grid (Matsushima & Shimobaba 2009).

    Args:
        u: complex field ``(..., Ny, Nx)`` sampled at ``pitch`` (any origin; the output shares it).
        pitch: sample spacing in mm, a float or ``(px, py)``.
        wavelength: vacuum wavelength in µm.
        z: propagation distance in mm (may be negative: back-propagation; may be a 0-d tensor).
        n: refractive index of the homogeneous medium (default air = 1).
        pad: zero-padding factor; the FFT grid is ``ceil(pad·N)`` per axis (``pad=2`` is the classic
            doubling that turns the circular convolution into a linear one). The result is cropped back to
            ``(Ny, Nx)`` (the input's own sample positions).
        band_limit: apply the band limit ``|f_x| < 1 / ((λ/n)·sqrt((2 z/(M_x p_x))² + 1))`` (same in y)
            that suppresses aliasing of the sampled transfer function; ``False`` gives the plain ASM.

    Returns:
        The propagated field ``(..., Ny, Nx)``, same dtype as ``u`` (complex). Evanescent components are 0.
    """
    u = _as_field(u)
    px, py = _pair(pitch, "pitch")
    _positive(px, "pitch"), _positive(py, "pitch")
    lam = _positive(wavelength, "wavelength") * _UM_TO_MM
    n = _positive(n, "n")
    if float(pad) < 1:
        raise ValueError(f"pad must be >= 1, got {pad}")
    zf, zt = _z_value(z)
    ny, nx = u.shape[-2:]
    my, mx = int(math.ceil(float(pad) * ny - 1e-9)), int(math.ceil(float(pad) * nx - 1e-9))

    dev = u.device
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=dev)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=dev)
    k = n / lam  # cycles / mm in the medium
    arg = k * k - fx[None, :] ** 2 - fy[:, None] ** 2
    mask = arg > 0
    if band_limit:
        lim_x = k / math.sqrt((2.0 * zf / (mx * px)) ** 2 + 1.0)
        lim_y = k / math.sqrt((2.0 * zf / (my * py)) ** 2 + 1.0)
        mask = mask & (fx.abs()[None, :] < lim_x) & (fy.abs()[:, None] < lim_y)
    phase = _TWO_PI * zt * _sqrt_kz(arg, mask)
    h = _transfer(phase, mask, u.dtype)

    spec = torch.fft.fft2(u, s=(my, mx))
    out = torch.fft.ifft2(spec * h)
    return out[..., :ny, :nx]
