"""Value types for sampled fields (issue 17): a :class:`Grid` (where the samples are) and a :class:`Field`
(a complex envelope on a Grid, with its wavelength, medium index and carrier).

One convention everywhere:

* **world space**: ``(x, y)`` in mm in a plane; sample ``[iy, ix]`` is the centre ``(x0 + ix·px, y0 + iy·py)`` of
  its pixel, ``origin = (x0, y0)`` the centre of sample ``[0, 0]`` (coordinates grow with the index);
* **index space**: the grid's own sample indices ``(iy, ix)``, arrays indexed ``[..., iy, ix]``;
* a sub-rectangle is **half-open** in index space: rows ``iy0 <= iy < iy1``, columns ``ix0 <= ix < ix1``, given
  as ``(iy0, iy1, ix0, ix1)`` (numpy/torch slicing; an empty range is not a window).

Both are frozen (immutable); a Field holds its tensor by reference (the tensor may carry a graph).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field, replace

import torch

from raywave.utils.phasor import polar

__all__ = ["Grid", "Field"]


def _pair_of(v, name: str, kind=float) -> tuple:
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().tolist()
    if isinstance(v, (int, float)) and kind is float:
        v = (v, v)
    try:
        a, b = v
    except (TypeError, ValueError):
        raise ValueError(f"Grid: {name} must be an (x, y) pair, got {v!r}") from None
    return kind(a), kind(b)


@dataclass(frozen=True)
class Grid:
    """A regular grid of samples in a plane (see the module docstring for the conventions).

    Args:
        origin: ``(x0, y0)`` mm, the centre of sample ``[0, 0]``.
        pitch: sample spacing in mm, a float (square pixels) or ``(px, py)``; positive.
        shape: ``(ny, nx)`` samples (index order, as the arrays); positive integers.
    """

    origin: tuple[float, float]
    pitch: tuple[float, float]
    shape: tuple[int, int]

    def __post_init__(self):
        origin = _pair_of(self.origin, "origin")
        pitch = _pair_of(self.pitch, "pitch")
        if isinstance(self.shape, (int, float)) or len(tuple(self.shape)) != 2:
            raise ValueError(f"Grid: shape must be (ny, nx), got {self.shape!r}")
        if any(float(s) != int(s) for s in self.shape):
            raise ValueError(f"Grid: shape must be integers, got {self.shape!r}")
        shape = tuple(int(s) for s in self.shape)
        if not all(math.isfinite(v) for v in origin):
            raise ValueError(f"Grid: origin must be finite, got {origin}")
        if not all(math.isfinite(p) and p > 0 for p in pitch):
            raise ValueError(f"Grid: pitch must be positive and finite, got {pitch}")
        if min(shape) < 1:
            raise ValueError(f"Grid: shape must be positive, got {shape}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "pitch", pitch)
        object.__setattr__(self, "shape", shape)

    # ---------------------------------------------------------------- index space <-> world space
    def position(self, iy, ix) -> tuple[float, float]:
        """World ``(x, y)`` mm of (possibly fractional) index ``(iy, ix)``."""
        return self.origin[0] + ix * self.pitch[0], self.origin[1] + iy * self.pitch[1]

    def index_of(self, x, y) -> tuple[float, float]:
        """Fractional index ``(iy, ix)`` of the world point ``(x, y)`` mm (inverse of :meth:`position`)."""
        return (y - self.origin[1]) / self.pitch[1], (x - self.origin[0]) / self.pitch[0]

    def coordinates(self, dtype=torch.float64, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Sample-centre coordinates ``(x (nx,), y (ny,))`` mm."""
        ny, nx = self.shape
        x = self.origin[0] + self.pitch[0] * torch.arange(nx, dtype=dtype, device=device)
        y = self.origin[1] + self.pitch[1] * torch.arange(ny, dtype=dtype, device=device)
        return x, y

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` mm of the pixel edges (half a pitch beyond the outer sample centres)."""
        (x0, y0), (px, py), (ny, nx) = self.origin, self.pitch, self.shape
        return x0 - 0.5 * px, x0 + (nx - 0.5) * px, y0 - 0.5 * py, y0 + (ny - 0.5) * py

    # ---------------------------------------------------------------- sub-windows (half-open, index space)
    def window(self, iy0: int, iy1: int, ix0: int, ix1: int) -> Grid:
        """The sub-grid of rows ``iy0 <= iy < iy1`` and columns ``ix0 <= ix < ix1`` (half-open, inside this grid)."""
        ny, nx = self.shape
        if not (0 <= iy0 < iy1 <= ny and 0 <= ix0 < ix1 <= nx):
            raise ValueError(f"Grid.window: ({iy0}, {iy1}, {ix0}, {ix1}) is not a non-empty half-open window of a "
                             f"grid of shape {self.shape}")
        return Grid(self.position(iy0, ix0), self.pitch, (iy1 - iy0, ix1 - ix0))

    def locate(self, sub: Grid, tol: float = 1e-9) -> tuple[int, int, int, int]:
        """The half-open window ``(iy0, iy1, ix0, ix1)`` of this grid that ``sub`` is (same pitch, its samples on
        this grid's samples to ``tol`` pixels, inside it); inverse of :meth:`window`."""
        if sub.pitch != self.pitch:
            raise ValueError(f"Grid.locate: pitch {sub.pitch} differs from this grid's {self.pitch}")
        fy, fx = self.index_of(*sub.origin)
        iy0, ix0 = round(fy), round(fx)
        if abs(fy - iy0) > tol or abs(fx - ix0) > tol:
            raise ValueError(f"Grid.locate: origin {sub.origin} is not on this grid's samples (index {fy}, {fx})")
        box = (iy0, iy0 + sub.shape[0], ix0, ix0 + sub.shape[1])
        self.window(*box)  # inside?
        return box

    def translated(self, dx: float, dy: float) -> Grid:
        """The same grid moved by ``(dx, dy)`` mm."""
        return replace(self, origin=(self.origin[0] + dx, self.origin[1] + dy))


@dataclass(frozen=True, eq=False)
class Field:
    """A sampled scalar field: the true field is ``U(x, y) = envelope · exp(i 2π n (α x + β y)/λ)``.

    Args:
        envelope: complex tensor ``(..., ny, nx)`` on ``grid`` (real input is promoted to complex128; complex64
            is kept); any leading batch dimensions.
        grid: the :class:`Grid` of the last two dimensions.
        wavelength: vacuum wavelength in µm.
        n: (real) refractive index of the medium.
        carrier: ``(α, β)`` direction cosines of the carrier in the medium, ``α² + β² < 1``.
    """

    envelope: torch.Tensor
    grid: Grid
    wavelength: float
    n: float = 1.0
    carrier: tuple[float, float] = dc_field(default=(0.0, 0.0))

    def __post_init__(self):
        u = self.envelope
        if not isinstance(u, torch.Tensor):
            raise TypeError(f"Field: envelope must be a torch.Tensor, got {type(u).__name__}")
        if not isinstance(self.grid, Grid):
            raise TypeError(f"Field: grid must be a Grid, got {type(self.grid).__name__}")
        if u.ndim < 2 or tuple(u.shape[-2:]) != self.grid.shape:
            raise ValueError(f"Field: envelope shape {tuple(u.shape)} does not end in the grid's shape {self.grid.shape}")
        if not u.is_complex():
            if not (u.is_floating_point() or u.dtype in (torch.int32, torch.int64, torch.bool)):
                raise TypeError(f"Field: unsupported envelope dtype {u.dtype}")
            object.__setattr__(self, "envelope", u.to(torch.complex64 if u.dtype == torch.float32 else torch.complex128))
        lam, n = float(self.wavelength), float(self.n)
        if not (math.isfinite(lam) and lam > 0):
            raise ValueError(f"Field: wavelength must be a positive number of µm, got {self.wavelength!r}")
        if not (math.isfinite(n) and n > 0):
            raise ValueError(f"Field: n must be positive, got {self.n!r}")
        a, b = _pair_of(self.carrier, "carrier")
        if not (math.isfinite(a) and math.isfinite(b) and a * a + b * b < 1.0):
            raise ValueError(f"Field: carrier must be direction cosines with α² + β² < 1, got {(a, b)}")
        object.__setattr__(self, "wavelength", lam)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "carrier", (a, b))

    def with_envelope(self, envelope: torch.Tensor, grid: Grid | None = None) -> Field:
        """The same wavelength, index and carrier with another envelope (on ``grid``, default this one)."""
        return Field(envelope, self.grid if grid is None else grid, self.wavelength, self.n, self.carrier)

    def crop(self, iy0: int, iy1: int, ix0: int, ix1: int) -> Field:
        """The field on the half-open window ``(iy0, iy1, ix0, ix1)`` of its grid (a view of the envelope)."""
        return self.with_envelope(self.envelope[..., iy0:iy1, ix0:ix1], self.grid.window(iy0, iy1, ix0, ix1))

    def total(self) -> torch.Tensor:
        """The true field ``U`` on the grid (envelope times the carrier), complex ``(..., ny, nx)``."""
        if self.carrier == (0.0, 0.0):
            return self.envelope
        x, y = self.grid.coordinates(device=self.envelope.device)
        k = 2.0 * math.pi * self.n / (self.wavelength * 1e-3)  # rad/mm
        phase = k * (self.carrier[0] * x[None, :] + self.carrier[1] * y[:, None])
        return self.envelope * polar(torch.ones_like(phase), phase).to(self.envelope.dtype)

    def power(self) -> torch.Tensor:
        """``Σ |u|² · px · py`` over the last two dimensions (the carrier does not change it)."""
        px, py = self.grid.pitch
        return torch.view_as_real(self.envelope).square().sum(dim=(-3, -2, -1)) * (px * py)
