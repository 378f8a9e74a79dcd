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
    if type(v) is tuple and len(v) == 2 and type(v[0]) is kind and type(v[1]) is kind:
        return v  # already normalised (the common case: a Grid built from another's values)
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
        shape = self.shape
        if not (type(shape) is tuple and len(shape) == 2 and type(shape[0]) is int and type(shape[1]) is int):
            if isinstance(shape, (int, float)) or len(tuple(shape)) != 2:
                raise ValueError(f"Grid: shape must be (ny, nx), got {shape!r}")
            if any(float(s) != int(s) for s in shape):
                raise ValueError(f"Grid: shape must be integers, got {shape!r}")
            shape = tuple(int(s) for s in shape)
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


def _nested(v, name: str):
    """A number or nested sequences of numbers as ``(flat list of floats, shape)`` (plain Python: no tensor is
    made, so host metadata never lands on a device)."""
    if isinstance(v, torch.Tensor):
        return [float(x) for x in v.detach().reshape(-1).tolist()], tuple(v.shape)
    if isinstance(v, (str, bytes)):
        raise ValueError(f"Field: {name} must be numbers, got {v!r}")
    if type(v) in (list, tuple) and v:  # the common flat forms, without recursion: floats, or pairs of floats
        if all(type(x) is float for x in v):
            return list(v), (len(v),)
        if all(type(x) is tuple and len(x) == 2 and type(x[0]) is float and type(x[1]) is float for x in v):
            return [c for x in v for c in x], (len(v), 2)
    try:
        items = list(v)
    except TypeError:
        try:
            return [float(v)], ()
        except (TypeError, ValueError):
            raise ValueError(f"Field: {name} must be numbers, got {v!r}") from None
    parts = [_nested(x, name) for x in items]
    shapes = {shape for _, shape in parts}
    if len(shapes) > 1:
        raise ValueError(f"Field: {name} is ragged (elements of shapes {sorted(shapes)})")
    inner = shapes.pop() if shapes else ()
    return [x for flat, _ in parts for x in flat], (len(items), *inner)


def _host_values(v, name: str, width: int = 0):
    """``v`` as a flat list of host floats (a tensor read once) and its shape (``width`` > 0: a trailing axis of
    that length, e.g. 2 for a carrier, not part of the shape)."""
    flat, shape = _nested(v, name)
    if width:
        if not shape or shape[-1] != width:
            raise ValueError(f"Field: {name} must be a pair (α, β) or pairs per batch element, got shape {shape}")
        return [tuple(flat[i:i + width]) for i in range(0, len(flat), width)], shape[:-1]
    return flat, shape


def _per_element(v, name: str, batch: tuple, width: int = 0):
    """A per-element Field attribute normalised: one host value (a float, or a ``width``-tuple) when the batch
    shares it, else a flat tuple of ``prod(batch)`` values (row-major over the batch axes). ``v``: a value, or
    values with the batch shape (nested sequences or a tensor), or a flat sequence of ``prod(batch)``."""
    vals, shape = _host_values(v, name, width)
    count = math.prod(batch)
    if shape == ():
        return vals[0]
    if shape != batch and shape != (count,):
        raise ValueError(f"Field: {name} has shape {shape}; expected one value or one per batch element "
                         f"(batch shape {batch})")
    if all(x == vals[0] for x in vals):
        return vals[0]
    return tuple(vals)


@dataclass(frozen=True, eq=False)
class Field:
    """A sampled scalar field: the true field is ``U(x, y) = envelope · exp(i 2π n (α x + β y)/λ)``.

    A Field may carry **leading batch axes** (sources × wavelengths × depths, any shape; chromatix / hcipy style):
    ``envelope`` ``(..., ny, nx)`` on one :class:`Grid` shared by the batch (its pitch and array shape). Where the
    elements differ, the wavelength, the index, the carrier and the window each element lies on are given per
    element (host floats, read once: every discrete choice downstream is made from them without a device read);
    where they agree, one value is kept. Per-element values are stored flat (row-major over the batch axes,
    ``B = prod(batch_shape)`` of them): :meth:`wavelengths`, :meth:`indices`, :meth:`carriers`,
    :meth:`element_grids` give them for every element, :meth:`element` one element as a Field of its own.

    Args:
        envelope: complex tensor ``(..., ny, nx)`` on ``grid`` (real input is promoted to complex128; complex64
            is kept); any leading batch dimensions.
        grid: the :class:`Grid` of the last two dimensions (shared by the batch).
        wavelength: vacuum wavelength in µm: a number, or one per batch element (a tensor or nested sequence with
            the batch shape, or a flat sequence of B).
        n: (real) refractive index of the medium: a number or one per element.
        carrier: ``(α, β)`` direction cosines of the carrier in the medium, ``α² + β² < 1``: a pair, or one pair
            per element (shape ``(*batch, 2)`` or ``(B, 2)``).
        windows: None (every element lies on ``grid``), or one :class:`Grid` per element (flat, B): element ``b``'s
            samples ``[..., :ny_b, :nx_b]`` lie on ``windows[b]`` (the grid's pitch, a shape within the grid's,
            any origin) and the rest of its array is zero padding (a batch of windows of different sizes and
            places, zero-padded at the end to one array: what :func:`raywave.wave.propagation.propagate_batch`
            propagates, each element between its own windows).
    """

    envelope: torch.Tensor
    grid: Grid
    wavelength: float | tuple
    n: float | tuple = 1.0
    carrier: tuple = dc_field(default=(0.0, 0.0))
    windows: tuple | None = None

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
        batch = tuple(u.shape[:-2])
        lam = _per_element(self.wavelength, "wavelength", batch)
        n = _per_element(self.n, "n", batch)
        carrier = _per_element(self.carrier, "carrier", batch, width=2)
        for v in (lam if isinstance(lam, tuple) else (lam,)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Field: wavelength must be a positive number of µm, got {v!r}")
        for v in (n if isinstance(n, tuple) else (n,)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Field: n must be positive, got {v!r}")
        for a, b in (carrier if isinstance(carrier[0], tuple) else (carrier,)):
            if not (math.isfinite(a) and math.isfinite(b) and a * a + b * b < 1.0):
                raise ValueError(f"Field: carrier must be direction cosines with α² + β² < 1, got {(a, b)}")
        object.__setattr__(self, "wavelength", lam)
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "carrier", carrier)
        object.__setattr__(self, "windows", self._checked_windows(batch))

    def _checked_windows(self, batch: tuple):
        """:attr:`windows` checked (one Grid per element, the grid's pitch, a shape within the grid's); None when
        every element lies on the grid."""
        if self.windows is None:
            return None
        wins = tuple(self.windows)
        if len(wins) != math.prod(batch) or not batch:
            raise ValueError(f"Field: windows must be one Grid per batch element ({math.prod(batch)} for the batch "
                             f"shape {batch}), got {len(wins)}")
        ny, nx = self.grid.shape
        for i, w in enumerate(wins):
            if not isinstance(w, Grid):
                raise TypeError(f"Field: windows[{i}] must be a Grid, got {type(w).__name__}")
            if w.pitch != self.grid.pitch or w.shape[0] > ny or w.shape[1] > nx:
                raise ValueError(f"Field: windows[{i}] (pitch {w.pitch}, shape {w.shape}) must have the grid's pitch "
                                 f"{self.grid.pitch} and a shape within its {self.grid.shape}")
        return None if all(w == self.grid for w in wins) else wins

    # ---------------------------------------------------------------- the batch
    @property
    def batch_shape(self) -> tuple[int, ...]:
        """The leading batch axes of the envelope (``()`` for a single field)."""
        return tuple(self.envelope.shape[:-2])

    @property
    def count(self) -> int:
        """B, the number of fields in the batch (1 for a single field)."""
        return math.prod(self.batch_shape)

    @property
    def shared(self) -> bool:
        """Whether every element has the same wavelength, index, carrier and window (one geometry for all)."""
        return (not isinstance(self.wavelength, tuple) and not isinstance(self.n, tuple)
                and not isinstance(self.carrier[0], tuple) and self.windows is None)

    def wavelengths(self) -> tuple[float, ...]:
        """Every element's wavelength (µm), flat (B)."""
        return self.wavelength if isinstance(self.wavelength, tuple) else (self.wavelength,) * self.count

    def indices(self) -> tuple[float, ...]:
        """Every element's medium index, flat (B)."""
        return self.n if isinstance(self.n, tuple) else (self.n,) * self.count

    def carriers(self) -> tuple[tuple[float, float], ...]:
        """Every element's carrier ``(α, β)``, flat (B)."""
        return self.carrier if isinstance(self.carrier[0], tuple) else (self.carrier,) * self.count

    def element_grids(self) -> tuple[Grid, ...]:
        """The Grid every element's own samples lie on, flat (B): :attr:`windows`, or the grid for each."""
        return self.windows if self.windows is not None else (self.grid,) * self.count

    def element(self, index: int) -> Field:
        """Element ``index`` (flat, row-major over the batch axes) as a single Field on its own window."""
        if not 0 <= index < self.count:
            raise IndexError(f"Field.element: index {index} outside a batch of {self.count}")
        g = self.element_grids()[index]
        u = self.envelope.reshape(-1, *self.grid.shape)[index, :g.shape[0], :g.shape[1]]
        return Field(u, g, self.wavelengths()[index], self.indices()[index], self.carriers()[index])

    def flat(self) -> Field:
        """The same batch with one batch axis: envelope ``(B, ny, nx)`` (a view where possible)."""
        return replace(self, envelope=self.envelope.reshape(self.count, *self.grid.shape))

    @classmethod
    def stack(cls, fields) -> Field:
        """A batch ``(B, ny, nx)`` of the single fields ``fields`` (each ``(ny_b, nx_b)``, one pitch). On one grid
        they share it; on different windows each is zero-padded at its end to the largest shape and keeps its own
        window (:attr:`windows`; the batch's grid is the first field's origin with the padded shape)."""
        fields = list(fields)
        if not fields:
            raise ValueError("Field.stack: no fields")
        for i, f in enumerate(fields):
            if not isinstance(f, Field) or f.batch_shape or not f.shared:
                raise ValueError(f"Field.stack: fields[{i}] must be a single Field (no batch axes), got "
                                 f"{type(f).__name__} of batch shape {getattr(f, 'batch_shape', None)}")
            if f.grid.pitch != fields[0].grid.pitch:
                raise ValueError(f"Field.stack: fields[{i}] has the pitch {f.grid.pitch}, fields[0] "
                                 f"{fields[0].grid.pitch}: a batch shares its pitch")
        wave = dict(wavelength=[f.wavelength for f in fields], n=[f.n for f in fields],
                    carrier=[f.carrier for f in fields])
        if all(f.grid == fields[0].grid for f in fields):
            return cls(torch.stack([f.envelope for f in fields]), fields[0].grid, **wave)
        ny, nx = max(f.grid.shape[0] for f in fields), max(f.grid.shape[1] for f in fields)
        env = torch.stack([torch.nn.functional.pad(f.envelope, (0, nx - f.grid.shape[1], 0, ny - f.grid.shape[0]))
                           for f in fields])
        grid = Grid(fields[0].grid.origin, fields[0].grid.pitch, (ny, nx))
        return cls(env, grid, windows=tuple(f.grid for f in fields), **wave)

    # ---------------------------------------------------------------- copies and views
    def with_envelope(self, envelope: torch.Tensor, grid: Grid | None = None) -> Field:
        """The same wavelength, index and carrier with another envelope (on ``grid``, default this one; a new grid
        drops per-element :attr:`windows`)."""
        if grid is None:
            return Field(envelope, self.grid, self.wavelength, self.n, self.carrier, self.windows)
        return Field(envelope, grid, self.wavelength, self.n, self.carrier)

    def crop(self, iy0: int, iy1: int, ix0: int, ix1: int) -> Field:
        """The field on the half-open window ``(iy0, iy1, ix0, ix1)`` of its grid (a view of the envelope)."""
        if self.windows is not None:
            raise ValueError("Field.crop: the elements lie on windows of their own (a padded batch): crop an "
                             "element (Field.element) instead")
        return self.with_envelope(self.envelope[..., iy0:iy1, ix0:ix1], self.grid.window(iy0, iy1, ix0, ix1))

    def _element_values(self, values, dtype, device) -> torch.Tensor:
        """Flat per-element host ``values`` (B) as a float tensor with the batch shape and two unit axes."""
        return torch.tensor(values, dtype=dtype, device=device).reshape(*self.batch_shape, 1, 1)

    def total(self) -> torch.Tensor:
        """The true field ``U`` on the grid (envelope times the carrier), complex ``(..., ny, nx)`` (each element
        on its own window)."""
        if self.shared:
            if self.carrier == (0.0, 0.0):
                return self.envelope
            x, y = self.grid.coordinates(device=self.envelope.device)
            k = 2.0 * math.pi * self.n / (self.wavelength * 1e-3)  # rad/mm
            phase = k * (self.carrier[0] * x[None, :] + self.carrier[1] * y[:, None])
            return self.envelope * polar(torch.ones_like(phase), phase).to(self.envelope.dtype)
        dev, f64 = self.envelope.device, torch.float64
        k = 2.0 * math.pi * self._element_values(self.indices(), f64, dev) / (
            self._element_values(self.wavelengths(), f64, dev) * 1e-3)
        (a, b), grids = zip(*self.carriers()), self.element_grids()
        x0 = self._element_values([g.origin[0] for g in grids], f64, dev)
        y0 = self._element_values([g.origin[1] for g in grids], f64, dev)
        dx, dy = self.grid.coordinates(device=dev)
        dx, dy = dx - self.grid.origin[0], dy - self.grid.origin[1]
        phase = k * (self._element_values(a, f64, dev) * (x0 + dx) + self._element_values(b, f64, dev) * (y0 + dy[:, None]))
        return self.envelope * polar(torch.ones_like(phase), phase).to(self.envelope.dtype)

    def power(self) -> torch.Tensor:
        """``Σ |u|² · px · py`` over the last two dimensions (the carrier does not change it)."""
        px, py = self.grid.pitch
        return torch.view_as_real(self.envelope).square().sum(dim=(-3, -2, -1)) * (px * py)
