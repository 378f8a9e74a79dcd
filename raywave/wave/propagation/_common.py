"""Shared conventions and small helpers of the propagation package: argument checks, the FFT size, pixel
coordinates, the NaN-free square root of the axial frequency (see :mod:`raywave.wave.propagation`)."""

from __future__ import annotations

import math

import torch

from raywave.utils.phasor import polar
from raywave.wave.grid import Field, Grid

_TWO_PI = 2.0 * math.pi
_UM_TO_MM = 1e-3


# ----------------------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------------------
def _pair(v, name: str) -> tuple[float, float]:
    """A float or an (x, y) pair → (x, y) floats."""
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().tolist()
    if isinstance(v, (int, float)):
        return float(v), float(v)
    if len(v) != 2:
        raise ValueError(f"{name} must be a float or an (x, y) pair, got {v!r}")
    return float(v[0]), float(v[1])


def _xy(v, name: str) -> tuple[float, float]:
    """An (x, y) pair → floats (no scalar broadcast)."""
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().tolist()
    if isinstance(v, (int, float)) or len(v) != 2:
        raise ValueError(f"{name} must be an (x, y) pair, got {v!r}")
    return float(v[0]), float(v[1])


def _positive(v, name: str) -> float:
    v = float(v.detach()) if isinstance(v, torch.Tensor) else float(v)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    return v


def legacy_call(name: str, signature: str):
    """Raise the TypeError of a call in the form that issue 43 replaced (loose tensor, pitch, wavelength, origins,
    shape arguments): the new signature and how to build its arguments."""
    raise TypeError(f"{name} takes a Field and an output Grid since issue 43: {signature}. Build them from the old "
                    "arguments as field = raywave.wave.Field(u, raywave.wave.Grid(in_origin, pitch, u.shape[-2:]), "
                    "wavelength, n, carrier) and out = raywave.wave.Grid(out_origin, pitch, out_shape)")


def check_single_field(field: Field, out: Grid, z, where: str) -> None:
    """The checks of a one-geometry propagation of ``field`` by ``z`` onto ``out``: a Field whose elements share
    their wavelength, index, carrier and window (a batch whose elements differ goes through
    :func:`~raywave.wave.propagation.propagate_batch`), an output Grid of the field's pitch, a distance."""
    if not isinstance(out, Grid):
        raise TypeError(f"{where}: the output window must be a raywave.wave.Grid, got {type(out).__name__}")
    if out.pitch != field.grid.pitch:
        raise ValueError(f"{where}: the output grid's pitch {out.pitch} differs from the field's {field.grid.pitch}")
    if z is None:
        raise TypeError(f"{where}: missing the propagation distance z (mm)")
    if not field.shared:
        raise ValueError(f"{where}: the field's {field.count} elements differ in wavelength, index, carrier or "
                         "window; propagate them together with raywave.wave.propagation.propagate_batch")


def _as_field(u: torch.Tensor) -> torch.Tensor:
    if not isinstance(u, torch.Tensor):
        raise TypeError("the field must be a torch.Tensor")
    if u.ndim < 2:
        raise ValueError(f"the field must have shape (..., Ny, Nx), got {tuple(u.shape)}")
    if u.dtype in (torch.complex128, torch.complex64):
        return u
    if u.dtype == torch.float32:
        return u.to(torch.complex64)
    if u.is_floating_point() or u.dtype in (torch.int32, torch.int64, torch.bool):
        return u.to(torch.complex128)
    raise TypeError(f"unsupported field dtype {u.dtype}")


def _z_value(z) -> tuple[float, torch.Tensor | float]:
    """(float z for masks, z for the phase: a float64 tensor when a tensor was given, to keep its graph)."""
    if isinstance(z, torch.Tensor):
        if z.numel() != 1:
            raise ValueError("z must be a scalar")
        zf = float(z.detach())
        zt = z.reshape(()).to(torch.float64)
    else:
        zf = float(z)
        zt = zf
    if not math.isfinite(zf):
        raise ValueError(f"z must be finite, got {zf}")
    return zf, zt


def fast_fft_size(n: int) -> int:
    """Smallest integer ≥ n of the form 2^a·3^b·5^c (fast on pocketfft and cuFFT)."""
    n = int(n)
    if n <= 1:
        return 1
    best = 1 << (n - 1).bit_length()  # a power of two always works
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def grid_coordinates(
    n: int, pitch: float, origin: float, *, dtype=torch.float64, device=None
) -> torch.Tensor:
    """Pixel-centre coordinates ``origin + i·pitch``, i = 0..n-1 (mm), as a 1-D tensor."""
    return origin + pitch * torch.arange(int(n), dtype=dtype, device=device)


def _sqrt_kz(arg: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """sqrt(arg) where ok, 1 elsewhere (NaN-free forward and backward)."""
    return torch.sqrt(torch.where(ok, arg, 1.0))


def _transfer(phase: torch.Tensor, mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    h = polar(torch.ones_like(phase), phase)
    return torch.where(mask, h, torch.zeros((), dtype=h.dtype, device=h.device)).to(dtype)
