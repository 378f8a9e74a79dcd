"""Many windows propagated as one batch (issue 43): the windowed angular spectrum of :func:`propagate_window` for B
sources at once, on one FFT grid.

The B sources of a batch share the pitch, the output window's shape and (in practice) the wavelength; each keeps its
own input window (shape and origin), output origin, carrier, distance and medium index (:class:`WindowSource`). The
batch runs

* one FFT size ``(My, Mx)`` for all: the largest that any source needs (:func:`~raywave.wave.propagation.transfer.
  window_transfer`'s size of each, a fast size), so every source's circular convolution stays the linear one. A
  source's result on a larger FFT grid differs from its own-size result only by the rolled-off kernel's tails,
  which wrap around at the own size (PSFs of resolved fields: ≤ 6.4e-9 relative L1 on the real lenses and the
  bundled asphere at ×1.25 … ×4, ≤ 1.5e-7 where the DOE's edge clips the beam; benchmarks/fft_size_convergence.py);
* one transfer tensor ``(B, R, C)`` on the union of the sources' bands (:func:`batch_transfer`), each source's band
  limit that of its own input window (exactly 0 outside it, so the union adds only zeros);
* one band convolution of the zero-padded input windows ``(B, Ny, Nx)`` (:func:`propagate_batch`).

The vocabulary is that of :mod:`raywave.wave.grid`: a batched :class:`~raywave.wave.grid.Field` in (its elements
on their own windows of one padded array), a batched Field out on the output Grids; :class:`WindowBatch` is the
host-side plan (:meth:`WindowBatch.of` the field, the output windows and the distances) by which a caller memoises
:func:`batch_transfer`.

Lengths mm, wavelengths µm; float64 transfer functions, complex128 (or complex64) fields. Host-side choices (FFT
size, the band's rows and columns) are made once per batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from raywave.utils import devices
from raywave.utils.phasor import polar
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation._common import _TWO_PI, _pair
from raywave.wave.propagation.band import (KEEP_SPECTRUM_BYTES, _adjoint, _band_put_, _blocks, _x_band, _y_band,
                                           _y_spectrum, band_chunks, convolve_band, index_runs, put, take)
from raywave.wave.propagation.kernels import (TransferBand, adjoint_terms, band_values, roll_off_terms,
                                             transfer_params)
from raywave.wave.propagation.transfer import WindowSource, _geometry
from raywave.wave.propagation.window import _convolve

__all__ = ["BatchTransfer", "WindowBatch", "WindowSource", "batch_transfer", "propagate_batch"]


@dataclass(frozen=True)
class WindowBatch:
    """B :class:`WindowSource` propagated to output windows of one ``out_shape`` ``(ny, nx)`` on one ``pitch`` (mm, a
    float (square pixels; a pair of equal values is stored as one) or ``(px, py)``), with the band limit's ``margin`` (pixels) and ``guard`` (Fresnel zones) of
    :func:`window_transfer`. The host-side plan of :func:`propagate_batch` (:meth:`of` a batched Field), hashable:
    a caller may memoise :func:`batch_transfer` by it."""

    sources: tuple[WindowSource, ...]
    out_shape: tuple[int, int]
    pitch: float | tuple[float, float]
    margin: float = 0.5
    guard: float = 2.0

    def __post_init__(self):
        object.__setattr__(self, "sources", tuple(self.sources))
        object.__setattr__(self, "out_shape", tuple(int(v) for v in self.out_shape))
        px, py = _pair(self.pitch, "pitch")
        object.__setattr__(self, "pitch", px if px == py else (px, py))  # square pixels: one float
        object.__setattr__(self, "margin", float(self.margin))
        object.__setattr__(self, "guard", float(self.guard))
        if not self.sources:
            raise ValueError("WindowBatch: no sources")

    @classmethod
    def of(cls, field: Field, out, z, margin: float = 0.5, guard: float = 2.0) -> WindowBatch:
        """The plan of propagating the batched :class:`~raywave.wave.grid.Field` ``field`` by ``z`` (mm, one
        distance or one per element, flat B) onto ``out`` (one :class:`~raywave.wave.grid.Grid` for every element,
        or one per element, flat B, all of one shape): each element between its own window
        (:meth:`~raywave.wave.grid.Field.element_grids`) and its output window, with its own wavelength, index and
        carrier. Clear errors for mismatched counts, shapes and pitches."""
        if not isinstance(field, Field):
            raise TypeError(f"WindowBatch.of: expected a raywave.wave.Field, got {type(field).__name__}")
        b = field.count
        outs = _per_source(out, b, "out")
        for i, g in enumerate(outs):
            if not isinstance(g, Grid):
                raise TypeError(f"propagate_batch: out[{i}] must be a raywave.wave.Grid, got {type(g).__name__}")
            if g.pitch != field.grid.pitch or g.shape != outs[0].shape:
                raise ValueError(f"propagate_batch: out[{i}] (pitch {g.pitch}, shape {g.shape}) must have the field's "
                                 f"pitch {field.grid.pitch} and the shape of out[0] {outs[0].shape}")
        zs = _per_source(z, b, "z")
        sources = tuple(WindowSource(g.shape, g.origin, o.origin, lam, zz, n, c) for g, o, lam, zz, n, c in
                        zip(field.element_grids(), outs, field.wavelengths(), zs, field.indices(), field.carriers()))
        return cls(sources, outs[0].shape, field.grid.pitch, margin, guard)

    def in_shape(self) -> tuple[int, int]:
        """The common (padded) input shape ``(Ny, Nx)``: the largest of the sources'."""
        return (max(s.in_shape[0] for s in self.sources), max(s.in_shape[1] for s in self.sources))

    def field(self, envelope: torch.Tensor) -> Field:
        """The batched :class:`~raywave.wave.grid.Field` of these sources whose (zero-padded) envelopes are
        ``envelope`` ``(B, Ny, Nx)`` (:meth:`in_shape`; each source's own window at the start of its array):
        ``WindowBatch.of(self.field(u), self.out_grids(), self.distances()) == self`` (the same margin and guard)."""
        src = self.sources
        windows = tuple(Grid(s.in_origin, self.pitch, s.in_shape) for s in src)
        grid = Grid(src[0].in_origin, self.pitch, tuple(envelope.shape[-2:]))
        return Field(envelope, grid, [s.wavelength for s in src], [s.n for s in src], [s.carrier for s in src],
                     windows)

    def out_grids(self) -> tuple[Grid, ...]:
        """Each source's output window (B)."""
        return tuple(Grid(s.out_origin, self.pitch, self.out_shape) for s in self.sources)

    def distances(self) -> tuple:
        """Each source's distance ``z`` (mm, B)."""
        return tuple(s.z for s in self.sources)

    def fft_size(self) -> tuple[int, int]:
        """The common FFT size ``(My, Mx)``: the largest any source needs (each a fast size)."""
        sizes = [g.size for g in self.geometries()]
        return max(s[0] for s in sizes), max(s[1] for s in sizes)

    def geometries(self) -> list:
        """Each source's checked geometry (:func:`raywave.wave.propagation.transfer._geometry`, host floats)."""
        return [_geometry(s, self.out_shape, self.pitch, self.margin, self.guard) for s in self.sources]


def _per_source(v, b: int, name: str) -> tuple:
    """``v`` (one value, or a sequence of ``b``) as a tuple of ``b`` values (a Grid or a number is one value)."""
    if isinstance(v, Grid) or isinstance(v, (int, float)) or (isinstance(v, torch.Tensor) and v.ndim == 0):
        return (v,) * b
    if isinstance(v, torch.Tensor):
        v = v.detach().cpu().reshape(-1).tolist()
    v = tuple(v)
    if len(v) != b:
        raise ValueError(f"propagate_batch: {name} must be one value or one per field of the batch ({b}), got {len(v)}")
    return v


@dataclass
class BatchTransfer:
    """The transfer functions of a :class:`WindowBatch` on the union of their bands: ``band`` complex128
    ``(B, R, C)`` on the rows ``rows`` (R,) × columns ``cols`` (C,) (int64 indices into the ``fftfreq`` grids of
    ``size`` ``(My, Mx)``); ``rel`` a :class:`RollOffRel` (or, :meth:`placed`, a dense float64 ``(B, 3, R, C)``) or
    None: the roll-off weights' relative first-order changes ``(∂W/∂z, ∂W/∂s_x, ∂W/∂s_y)/W``
    (``weight_derivative``); ``wave`` float64 ``(3, B, 1, 1)``: each
    source's ``(n/λ, n α/λ, n β/λ)`` (1/mm), for the axial frequency of the distance perturbation; ``pitch``
    ``(px, py)`` mm; ``batch`` the :class:`WindowBatch` it was built for."""

    size: tuple[int, int]
    rows: torch.Tensor
    cols: torch.Tensor
    band: torch.Tensor | None
    rel: "torch.Tensor | RollOffRel | None"
    wave: torch.Tensor
    pitch: tuple[float, float]
    batch: WindowBatch | None = None
    #: on a CPU: each source's own band (:class:`OwnBand`), which :func:`propagate_batch` convolves field by field;
    #: ``band`` / ``rel`` are then None until :meth:`placed` puts them on the union
    parts: tuple | None = None

    @property
    def count(self) -> int:
        """The number of sources B."""
        return len(self.parts) if self.parts is not None else int(self.band.shape[0])

    def placed(self) -> "BatchTransfer":
        """This transfer with ``band`` (and ``rel``) on the union of the bands (zeros outside each source's own):
        itself when they are there, else :attr:`parts` placed by block copies."""
        if self.band is not None:
            return self
        wd = any(p.rel is not None for p in self.parts)
        band, rel = _place_parts(self.parts, (self.rows, self.cols), wd)
        return BatchTransfer(self.size, self.rows, self.cols, band, rel, self.wave, self.pitch, self.batch)


class OwnBand:
    """One source's transfer function on its own band, on the rows ``rows`` (R_i,) × columns ``cols`` (C_i,) of the
    FFT grid: ``values`` a :class:`~raywave.wave.propagation.kernels.TransferBand` (evaluated where the band
    convolution uses it) or None (the band is empty); ``rel`` a :class:`RollOffRel` of one source or None
    (:class:`BatchTransfer`'s, for this source). :attr:`band` evaluates the whole band, complex128 ``(R_i, C_i)``
    (None where it is empty)."""

    __slots__ = ("rows", "cols", "values", "_rel", "_rel_params")

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, values: TransferBand | None,
                 rel: "RollOffRel | None" = None, rel_params: tuple | None = None):
        self.rows, self.cols, self.values, self._rel = rows, cols, values, rel
        self._rel_params = rel_params  # (the source's parameters for a rel built on first use)

    @property
    def rel(self) -> "RollOffRel | None":
        """The roll-off derivatives (built on first use: the engine's backward evaluates them in its compiled loop,
        :func:`~raywave.wave.propagation.kernels.adjoint_terms`, and never asks for them)."""
        if self._rel is None and self._rel_params is not None:
            self._rel = _rel(self._rel_params, self.values.fx, self.values.fy)
        return self._rel

    @property
    def band(self) -> torch.Tensor | None:
        return None if self.values is None else self.values.full()



@dataclass
class RollOffRel:
    """The roll-off weights' relative first-order changes ``(∂W/∂z, ∂W/∂s_x, ∂W/∂s_y)/W`` of a band ``(B, R, C)``,
    kept on the lines where they can be non-zero (the roll-off lines of :func:`_ramp_lines`; elsewhere the factor is
    1 and its derivatives 0): ``x`` the column runs ``((a, b, ∂z (B, R, b − a), ∂s_x (B, R, b − a)), …)``, ``y`` the
    row runs ``((a, b, ∂z (B, b − a, C), ∂s_y (B, b − a, C)), …)``. A dense ``(B, 3, R, C)`` array is ~36 MB per
    source of a map and was saved for every backward; its uses are sums over the band (:meth:`sums`) and, for a
    non-zero perturbation, the amplitude (:meth:`amplitude`). Entries where the weight is 0 (evanescent, rolled
    off) may be non-zero here: they multiply a transfer function that is 0 there."""

    shape: tuple
    x: tuple
    y: tuple
    device: torch.device | None = None

    def dense(self, live: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, 3, R, C)`` float64 (0 off the roll-off lines, and where ``live`` (B, R, C) bool is False)."""
        b, r, c = self.shape
        out = torch.zeros((b, 3, r, c), dtype=torch.float64, device=self.device)
        for a, e, fz, fs in self.x:
            out[:, 0, :, a:e] += fz
            out[:, 1, :, a:e] = fs
        for a, e, fz, fs in self.y:
            out[:, 0, a:e, :] += fz
            out[:, 2, a:e, :] = fs
        return out if live is None else torch.where(live[:, None], out, torch.zeros((), dtype=out.dtype,
                                                                                     device=out.device))

    def sums(self, q: torch.Tensor, chan: int) -> torch.Tensor:
        """``Σ q·rel[:, chan]`` over the band, ``(B, 1, 1)``, for ``q`` ``(B, R, C)`` (``chan`` 0: ∂z, 1: ∂s_x,
        2: ∂s_y), over the roll-off lines alone."""
        out = torch.zeros_like(q[..., :1, :1])
        if chan in (0, 1):
            for a, e, fz, fs in self.x:
                out = out + (q[..., :, a:e] * (fz if chan == 0 else fs)).sum((-2, -1), keepdim=True)
        if chan in (0, 2):
            for a, e, fz, fs in self.y:
                out = out + (q[..., a:e, :] * (fz if chan == 0 else fs)).sum((-2, -1), keepdim=True)
        return out

    def amplitude(self, sx, sy, dz) -> torch.Tensor:
        """``1 + s_x R_x + s_y R_y + dz R_z`` ``(B, R, C)`` (``sx``, ``sy`` ``(B, 1, 1)``, ``dz`` 0-d)."""
        d = self.dense()
        return 1.0 + (sx * d[:, 1] + sy * d[:, 2] + dz * d[:, 0])

    def source(self, i: int) -> "RollOffRel":
        """The source ``i``'s (a batch of one)."""
        def one(runs):
            return tuple((a, e, fz[i:i + 1], fs[i:i + 1]) for a, e, fz, fs in runs)

        return RollOffRel((1, *self.shape[1:]), one(self.x), one(self.y), self.device)

def _columns(values: list[list[float]], device) -> list[torch.Tensor]:
    """Per-source host values ``[B][K]`` as K float64 ``(B, 1, 1)`` tensors (one transfer to the device)."""
    t = torch.tensor(values, dtype=torch.float64, device=device)
    return list(t.T.reshape(t.shape[1], -1, 1, 1).unbind(0))


def _union_candidates(f: torch.Tensor, k, offset, zf, lo, hi, taper) -> torch.Tensor:
    """Indices of the frequencies ``f`` (1-D, cycles/mm) where some source's band can be non-zero (the batched
    :func:`~raywave.wave.propagation.transfer._candidates`; per-source ``(B, 1, 1)`` parameters, ``offset`` the
    carrier's frequency k·α)."""
    g = f[None, None, :] + offset  # (B, 1, M)
    q = k * k - g * g
    s1 = zf * g / torch.sqrt(q.clamp_min(1e-300))
    at_zero = (lo - taper <= 0.0) & (0.0 <= hi + taper)
    ok = torch.where(s1 > 0, s1 <= hi + taper, torch.where(s1 < 0, s1 >= lo - taper, at_zero))
    return torch.nonzero(((q > 0) & ok).any(0).reshape(-1)).squeeze(1)


def _host_candidates(geos: list, m: int, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_union_candidates` of the sources ``geos`` (their host geometries) on one axis (``axis`` 0: x, the
    columns; 1: y, the rows) of an ``m``-point FFT grid, in host arithmetic (numpy: the same IEEE operations in the
    same order, so the same lines): ``(indices (K,) int64, their frequencies (K,) float64 cycles/mm)``. An
    accelerator's plan (no kernels, no device→host read for the band's lines)."""
    pitch = geos[0].pitch[axis]
    f = np.fft.fftfreq(m, d=pitch)
    col = np.array([[g.k, g.zf, g.carrier[axis], *(g.bx if axis == 0 else g.by)] for g in geos],
                   dtype=np.float64)[:, :, None]
    k, zf, a, lo, hi, taper = col.transpose(1, 0, 2)  # each (B, 1)
    g = f[None, :] + k * a
    q = k * k - g * g
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = zf * g / np.sqrt(np.maximum(q, 1e-300))
    at_zero = (lo - taper <= 0.0) & (0.0 <= hi + taper)
    ok = np.where(s1 > 0, s1 <= hi + taper, np.where(s1 < 0, s1 >= lo - taper, at_zero))
    idx = np.nonzero(((q > 0) & ok).any(0))[0].astype(np.int64)
    return idx, f[idx]


def _ramp_lines(g, g_other, k, zf, band) -> torch.Tensor:
    """Indices of the band's lines (``g`` (B, 1, C) or (B, R, 1): one axis's physical frequencies; ``g_other`` the
    other's) where some source's lateral shift may leave its ``[lo, hi]`` (the batched
    :func:`~raywave.wave.propagation.transfer._ramp_lines`): elsewhere every source's roll-off factor is exactly 1."""
    lo, hi, _ = band
    o2 = g_other * g_other
    dims = (-2, -1)
    a, b = o2.amin(dims, keepdim=True), o2.amax(dims, keepdim=True)
    q_near, q_far = k * k - g * g - a, k * k - g * g - b
    ok = q_far > 0
    s_near = zf * g / torch.sqrt(torch.where(ok, q_near, 1.0))
    s_far = zf * g / torch.sqrt(torch.where(ok, q_far, 1.0))
    tol = 1e-9 * torch.maximum(torch.maximum(lo.abs(), hi.abs()), torch.full_like(lo, 1e-9))
    inside = ok & (torch.minimum(s_near, s_far) >= lo + tol) & (torch.maximum(s_near, s_far) <= hi - tol)
    return torch.nonzero(~inside.all(0).reshape(-1)).squeeze(1)


def _rel_lines(g, g_other, kz, band, dim: int) -> tuple:
    """The roll-off weights' relative derivatives of one axis (``dim`` −1: x, the band's columns; −2: y, its rows;
    ``g`` that axis's physical frequencies, ``g_other`` the other's, ``kz`` = ``(k, zf)``) on the lines that can roll
    off alone (:func:`_ramp_lines`; elsewhere the factor is 1 and its derivatives 0), a contiguous run of lines at a
    time, each in one compiled loop (:func:`~raywave.wave.propagation.kernels.roll_off_terms`): the runs of
    :class:`RollOffRel`, ``((a, b, ∂ log W/∂z, ∂ log W/∂s), …)`` on the lines ``a:b`` of ``dim``."""
    k, zf = kz
    stacked = torch.stack(band, -1)  # (B, 1, 1, 3)
    facs = []
    for a, b in index_runs(_ramp_lines(g, g_other, k, zf, band)):
        fac = roll_off_terms(g.narrow(dim, a, b - a), g_other, k, zf, stacked)
        facs.append((a, b, fac[..., 0], fac[..., 1]))
    return tuple(facs)


def batch_transfer(batch: WindowBatch, device=None, weight_derivative: bool = False) -> BatchTransfer:
    """The transfer functions of every source of ``batch`` on the common FFT grid (:meth:`WindowBatch.fft_size`),
    as one ``(B, R, C)`` tensor on the union of their bands: for each source the ``G`` of :func:`window_transfer`
    (its own band limit, carrier, window shift and distance) sampled on that grid; ``weight_derivative``: also the
    roll-off weights' first-order changes (for a differentiable distance and window shift, :func:`propagate_batch`).
    """
    geos = batch.geometries()
    if any(g.bx[2] <= 0 or g.by[2] <= 0 for g in geos):
        raise ValueError("batch_transfer: every source needs a roll-off (guard > 0 and z != 0); use "
                         "window_transfer for the sharp band limit")
    my, mx = batch.fft_size()
    (px, py) = geos[0].pitch
    k, zf, ax, ay, dx, dy, bxl, bxh, bxt, byl, byh, byt = _columns(
        [[g.k, g.zf, g.carrier[0], g.carrier[1], g.shift[0], g.shift[1], *g.bx, *g.by] for g in geos], device)
    kax, kay = k * ax, k * ay
    wave = torch.stack([k, kax, kay])
    # each source's parameters of the compiled transfer function (kernels.PARAMS), one transfer
    pvec = torch.tensor([transfer_params(g) for g in geos], dtype=torch.float64, device=device)
    params = (k, zf, kax, kay, dx, dy, (bxl, bxh, bxt), (byl, byh, byt))
    if devices.accelerator(device):
        # an accelerator: the band's lines from host arithmetic (the same lines), one transfer each
        (cols, fxc), (rows, fyr) = _host_candidates(geos, mx, 0), _host_candidates(geos, my, 1)
        # (fresh host arrays: shared, not copied, then sent; one op each, not two)
        cols, rows, fxc, fyr = (torch.from_numpy(np.ascontiguousarray(v)).to(device) for v in (cols, rows, fxc, fyr))
        if cols.numel() == 0 or rows.numel() == 0:
            return _empty_transfer(batch, (rows, cols), wave, weight_derivative, device)
        band, rel = _band_values(params, pvec, (fxc, fyr), weight_derivative)
        return BatchTransfer((my, mx), rows, cols, band, rel, wave, (px, py), batch)
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=device)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=device)
    cols = _union_candidates(fx, k, kax, zf, bxl, bxh, bxt)
    rows = _union_candidates(fy, k, kay, zf, byl, byh, byt)
    if cols.numel() == 0 or rows.numel() == 0:
        return _empty_transfer(batch, (rows, cols), wave, weight_derivative, device)
    if _by_source(device, len(geos)):
        parts = _own_band_values(params, pvec, (fx, fy), weight_derivative)
        return BatchTransfer((my, mx), rows, cols, None, None, wave, (px, py), batch, parts)
    band, rel = _band_values(params, pvec, (fx[cols], fy[rows]), weight_derivative)
    return BatchTransfer((my, mx), rows, cols, band, rel, wave, (px, py), batch)


def _empty_transfer(batch: WindowBatch, lines: tuple, wave: torch.Tensor, weight_derivative: bool,
                    device) -> BatchTransfer:
    """:func:`batch_transfer` where no line of the band passes (``lines`` = ``(rows, cols)``, one of them empty)."""
    geos = batch.geometries()
    rows, cols = lines
    empty = torch.zeros((len(geos), rows.numel(), cols.numel()), dtype=torch.complex128, device=device)
    rel = RollOffRel(tuple(empty.shape), (), (), empty.device) if weight_derivative else None
    return BatchTransfer(batch.fft_size(), rows, cols, empty, rel, wave, geos[0].pitch, batch)


def _by_source(device, b: int) -> bool:
    """Whether :func:`batch_transfer` describes each source on its own band (a CPU: a lazily evaluated
    :class:`~raywave.wave.propagation.kernels.TransferBand` per source, which the band convolution evaluates a column
    block at a time where it multiplies the spectrum; the work follows each source's own band, ~3× less than the
    union's for a map's batches) rather than the batch at once on the union (an accelerator: one set of kernels)."""
    return not devices.accelerator(device)


def _band_values(params: tuple, pvec: torch.Tensor, freqs: tuple, weight_derivative: bool):
    """``(band (B, R, C) complex128, rel (:class:`RollOffRel`) or None)``: the transfer functions of the sources
    ``pvec`` ``(B, 12)`` (:data:`~raywave.wave.propagation.kernels.PARAMS`) on the frequencies ``freqs`` = ``(fxc,
    fyr)`` (1/mm; the band ``fyr[:, None], fxc``), in one compiled loop; ``params`` (:func:`batch_transfer`'s ``(k,
    zf, kα, kβ, dx, dy, x band, y band)``, each ``(B, 1, 1)``) for the roll-off derivatives."""
    fxc, fyr = freqs
    band = band_values(fxc, fyr, pvec)
    return band, (_rel(params, fxc, fyr) if weight_derivative else None)


def _rel(params: tuple, fxc: torch.Tensor, fyr: torch.Tensor) -> "RollOffRel":
    """The roll-off weights' relative derivatives (:class:`RollOffRel`) of the sources ``params`` (as
    :func:`_band_values`) on the band ``fyr[:, None], fxc``, evaluated on the roll-off lines alone."""
    k, zf, kax, kay, _, _, bx, by = params
    gxs, gys = fxc + kax, fyr[:, None] + kay  # (B, 1, C), (B, R, 1): physical frequencies (cycles/mm)
    fac_x = _rel_lines(gxs, gys, (k, zf), bx, -1)
    fac_y = _rel_lines(gys, gxs, (k, zf), by, -2)
    return RollOffRel((k.shape[0], fyr.numel(), fxc.numel()), fac_x, fac_y, fxc.device)


def _own_band_values(params: tuple, pvec: torch.Tensor, freqs: tuple, weight_derivative: bool) -> tuple:
    """Each source on its own band (its own candidate rows and columns, the lines where it alone can roll off): a
    tuple of :class:`OwnBand`, their values lazily evaluated (:class:`~raywave.wave.propagation.kernels.
    TransferBand`; ``pvec`` ``(B, 12)`` their parameters). The same values as :func:`_band_values` on the union,
    where the union holds exact zeros outside each source's band (:meth:`BatchTransfer.placed`)."""
    fx, fy = freqs
    parts = []
    for i in range(pvec.shape[0]):
        one = tuple(p[i:i + 1] if isinstance(p, torch.Tensor) else tuple(q[i:i + 1] for q in p) for p in params)
        k, zf, kax, kay, _, _, bx, by = one
        c_own = _union_candidates(fx, k, kax, zf, *bx)
        r_own = _union_candidates(fy, k, kay, zf, *by)
        if c_own.numel() == 0 or r_own.numel() == 0:
            parts.append(OwnBand(r_own, c_own, None, None))
            continue
        fxc, fyr = fx[c_own], fy[r_own]
        # (the parameters a tensor of their own: a compiled loop guards on a view's offset into its base)
        parts.append(OwnBand(r_own, c_own, TransferBand(fxc, fyr, pvec[i].clone()), None,
                             one if weight_derivative else None))
    return tuple(parts)


def _place_parts(parts: tuple, band_index: tuple, weight_derivative: bool):
    """The sources' own bands ``parts`` (:class:`OwnBand`) placed into the union ``band_index`` = ``(rows, cols)``:
    ``(band (B, R, C), rel (B, 3, R, C) or None)``, zeros outside each source's band (there its weight is exactly
    0, as the union's evaluation gives)."""
    rows, cols = band_index
    b, dev = len(parts), rows.device
    # not zero-filled: each source's entries are written once, its own band's or (outside it) zeros
    band = torch.empty((b, rows.numel(), cols.numel()), dtype=torch.complex128, device=dev)
    rel = torch.empty((b, 3, rows.numel(), cols.numel()), dtype=torch.float64, device=dev) \
        if weight_derivative else None
    for i, part in enumerate(parts):
        if part.band is None:
            band[i].zero_()
            if weight_derivative:
                rel[i].zero_()
            continue
        rp = index_runs(torch.searchsorted(rows, part.rows))
        cp = index_runs(torch.searchsorted(cols, part.cols))
        values = part.band
        _place(band[i], values, rp, cp)
        _zero_outside(band[i], rp, cp)
        if weight_derivative:
            _place(rel[i], part.rel.dense(values[None] != 0)[0], rp, cp)
            _zero_outside(rel[i], rp, cp)
    return band, rel


def _complement(runs, n: int) -> list[tuple[int, int]]:
    """The half-open runs of ``0 … n − 1`` outside the sorted runs ``runs``."""
    out, prev = [], 0
    for a, b in runs:
        if a > prev:
            out.append((prev, a))
        prev = b
    if prev < n:
        out.append((prev, n))
    return out


def _zero_outside(dst: torch.Tensor, row_runs, col_runs) -> None:
    """Zero ``dst`` ``(..., R, C)`` outside the rows ``row_runs`` × columns ``col_runs`` (what :func:`_place` wrote), in
    place: the rows outside whole, the columns outside on the rows inside."""
    for a, b in _complement(row_runs, dst.shape[-2]):
        dst[..., a:b, :].zero_()
    cols_out = _complement(col_runs, dst.shape[-1])
    for ra, rb in row_runs:
        for ca, cb in cols_out:
            dst[..., ra:rb, ca:cb].zero_()


def _place(dst: torch.Tensor, src: torch.Tensor, row_runs, col_runs) -> None:
    """``dst[..., rpos, cpos] = src`` for the positions given as runs
    (:func:`~raywave.wave.propagation.band.index_runs`), by block copies."""
    r0 = 0
    for ra, rb in row_runs:
        c0 = 0
        for ca, cb in col_runs:
            dst[..., ra:rb, ca:cb].copy_(src[..., r0:r0 + rb - ra, c0:c0 + cb - ca])
            c0 += cb - ca
        r0 += rb - ra


def _axial(fx: torch.Tensor, fy: torch.Tensor, wave: torch.Tensor) -> torch.Tensor:
    """``w = sqrt((n/λ)² − |f + f_c|²)`` (cycles/mm, 0 where evanescent) on the band ``fy[:, None], fx[None, :]``
    for every source (``wave`` ``(3, B, 1, 1)``: n/λ, k·α, k·β): ``(B, R, C)``."""
    k, kax, kay = wave.unbind(0)
    arg = k * k - (fx + kax) ** 2 - (fy[:, None] + kay) ** 2
    ok = arg > 0
    return torch.where(ok, torch.sqrt(torch.where(ok, arg, 1.0)), torch.zeros((), dtype=arg.dtype, device=arg.device))



def _amplitude(rel, sx, sy, dz):
    """``1 + s_x R_x + s_y R_y + dz R_z`` (B, R, C) of the roll-off derivatives ``rel`` (a :class:`RollOffRel` or a
    dense ``(B, 3, R, C)`` tensor), or None without them."""
    if rel is None:
        return None
    if isinstance(rel, RollOffRel):
        return rel.amplitude(sx, sy, dz)
    return 1.0 + (sx * rel[:, 1] + sy * rel[:, 2] + dz * rel[:, 0])

class _Perturbed(torch.autograd.Function):
    """The batched :class:`~raywave.wave.propagation.window._Perturbed`: ``h·a·exp(iφ)`` with ``φ = 2π(f_x s_x +
    f_y s_y + w·dz)``, ``a = 1 + s_x R_x + s_y R_y + dz R_z``, per source (``sx``, ``sy`` ``(B, 1, 1)`` mm; ``dz``
    0-d mm, shared), with a hand-written backward (the scalars' gradients as reductions over each source's band).
    ``h`` does not require grad (a transfer function). Zero-valued ``sx, sy, dz`` give ``h`` itself (bit for bit)."""

    @staticmethod
    def _factors(sx, sy, dz, fx, fy, wave, rel, dtype):
        phase = _TWO_PI * (fy[:, None] * sy + fx * sx)
        if wave is not None:
            phase = phase + _TWO_PI * dz * _axial(fx, fy, wave)
        e = polar(torch.ones((), dtype=phase.dtype, device=phase.device), phase).to(dtype)
        return e, _amplitude(rel, sx, sy, dz)

    @staticmethod
    def forward(ctx, h, sx, sy, dz, fx, fy, wave, rel):
        # the engine's perturbations are zero-valued (they carry derivatives only): then e^{iφ} = 1 and a = 1, and
        # the value is h itself, bit for bit, without the band-sized phase and weight factors (one host read)
        ctx.zero = not bool(torch.cat([sx.reshape(-1), sy.reshape(-1), dz.reshape(-1)]).any())
        if ctx.zero:
            y = h.view_as(h)
        else:
            e, amp = _Perturbed._factors(sx, sy, dz, fx, fy, wave, rel, h.dtype)
            y = h * e if amp is None else h * e * amp.to(h.real.dtype)
        ctx.rel = rel  # a RollOffRel (its tensors are the transfer's, which no one modifies) or a dense tensor
        ctx.save_for_backward(y, sx, sy, dz, fx, fy, wave)
        return y

    @staticmethod
    def backward(ctx, g):
        y, sx, sy, dz, fx, fy, wave = ctx.saved_tensors
        grads = [None] * 8
        grads[1:4] = _scalar_grads(g, y, (sx, sy, dz), (fx, fy, wave, ctx.rel), ctx.zero, ctx.needs_input_grad[1:4])
        return tuple(grads)


def _scalar_grads(g: torch.Tensor, y: torch.Tensor, scalars: tuple, band: tuple, zero: bool, needs) -> list:
    """The gradients of :class:`_Perturbed`'s ``(sx, sy, dz)`` (``scalars``; None where ``needs`` says not wanted)
    from the gradient ``g`` of its output ``y`` ``(B, R, C)``; ``band`` = ``(fx, fy, wave, rel)`` (the band's
    frequencies, the axial frequency's ``wave`` or None, the roll-off derivatives or None), ``zero``: the
    perturbation is zero-valued (the amplitude is 1)."""
    sx, sy, dz = scalars
    fx, fy, wave, rel = band
    qa_c = (g.conj() * y).to(torch.complex128)  # conj(g)·h·e^{iφ}·a
    qa = qa_c.imag
    amp = None if rel is None or zero else _amplitude(rel, sx, sy, dz)
    q_re = qa_c.real if amp is None else qa_c.real / amp
    del qa_c
    w = None if wave is None or not needs[2] else _axial(fx, fy, wave)
    grads = [None] * 3
    for i, (freq, chan, target) in enumerate(((fx, 1, sx), (fy, 2, sy), (w, 0, dz))):
        if not needs[i]:
            continue
        part = torch.zeros_like(qa[..., :1, :1])
        if freq is not None and i < 2:  # a frequency of one axis: the band summed across the other axis first
            line = qa.sum(-2 if i == 0 else -1)  # (B, C) or (B, R)
            part = part - _TWO_PI * (line * freq).sum(-1)[:, None, None]
        elif freq is not None:
            part = part - _TWO_PI * (qa * freq).sum((-2, -1), keepdim=True)
        if isinstance(rel, RollOffRel):
            part = part + rel.sums(q_re, chan)
        elif rel is not None:
            part = part + (q_re * rel[:, chan]).sum((-2, -1), keepdim=True)
        grads[i] = part.sum_to_size(target.shape)
    return grads


class _BandJob(NamedTuple):
    """One source's band convolution with a lazily evaluated transfer function (:class:`_TransferConvolve`): its
    :class:`OwnBand` ``part``, the FFT grid ``size`` ``(My, Mx)`` and the output window ``out_shape`` ``(noy,
    nox)``."""

    part: OwnBand
    size: tuple
    out_shape: tuple


class _TransferConvolve(torch.autograd.Function):
    """The band convolution of one field ``u`` ``(Ny, Nx)`` with its source's transfer function perturbed to first
    order by zero-valued ``sx``, ``sy`` (``(1, 1, 1)`` mm) and ``dz`` (0-d mm) (each None or a tensor that carries a
    derivative; :class:`_Perturbed`), the transfer function evaluated where it is used (``job`` a :class:`_BandJob`:
    :class:`~raywave.wave.propagation.kernels.TransferBand`): the forward is the convolution without autograd, bit
    for bit (the perturbation is zero), and keeps ``u`` alone besides the scalars; the backward
    (:func:`_transfer_adjoint`) is :class:`~raywave.wave.propagation.band.BandConvolve`'s adjoint and
    :class:`_Perturbed`'s reductions with the band's products in one compiled loop per column block
    (:func:`~raywave.wave.propagation.kernels.adjoint_terms`): no band-sized array."""

    @staticmethod
    def forward(ctx, u, sx, sy, dz, job: _BandJob):
        ctx.job, ctx.in_shape = job, tuple(u.shape[-2:])
        part = job.part
        scalars = any(ctx.needs_input_grad[1:4])
        # the scalars' gradients need the input's band spectrum: kept from the forward where it is small (the
        # column blocks the backward walks; two of its six passes of transforms not redone), else u kept
        # (saved as tensors: autograd frees them after the backward, while the graph's outputs may live on)
        keep = [] if scalars and _keeps_band(u, part) else None
        out = convolve_band(u, part.values, job.size, part.rows, part.cols, *job.out_shape, keep)
        ctx.save_for_backward(u if scalars and not keep else None, sx, sy, dz, *(keep or ()))
        return out

    @staticmethod
    def backward(ctx, g):
        u, sx, sy, dz, *kept = ctx.saved_tensors
        job = ctx.job
        part, need_u, needs = job.part, ctx.needs_input_grad[0], ctx.needs_input_grad[1:4]
        if not any(needs):
            runs = index_runs(part.rows), index_runs(part.cols)
            grad_u, _ = _adjoint(g, None, part.values, job.size, runs, ctx.in_shape, (need_u, False))
            return grad_u, None, None, None, None
        grad_u, terms = _transfer_adjoint(g, kept or u, job, ctx.in_shape, need_u)
        grads = [grad_u, None, None, None, None]
        for i, target in enumerate((sx, sy, dz)):
            if needs[i]:
                grads[i + 1] = terms[i].reshape((1,) * target.ndim)
        return tuple(grads)


def _keeps_band(u: torch.Tensor, part) -> bool:
    """Whether :class:`_TransferConvolve` keeps the input ``u``'s band spectrum from its forward (one field on a CPU,
    the band of ``part`` (:class:`OwnBand`) within :data:`~raywave.wave.propagation.band.KEEP_SPECTRUM_BYTES`)."""
    return (u.ndim == 2 and not devices.accelerator(u)
            and part.rows.numel() * part.cols.numel() * u.element_size() <= KEEP_SPECTRUM_BYTES)


def _transfer_adjoint(g: torch.Tensor, u, job: _BandJob, in_shape: tuple, need_u: bool):
    """:class:`_TransferConvolve`'s backward from the output's gradient ``g`` ``(noy, nox)``: ``(∂L/∂u (Ny, Nx) or
    None, the gradients of (s_x, s_y, dz) (three 0-d))``; ``u`` the input ``(Ny, Nx)`` or its band spectrum kept by
    the forward (:func:`~raywave.wave.propagation.band.convolve_band`'s ``keep``: a list of the column blocks'
    ``(c, R)``, the blocks this walks), from one compiled loop per column block
    (:func:`~raywave.wave.propagation.kernels.adjoint_terms`: the band's products, the transfer function and its
    roll-off derivatives evaluated in it) between the transforms of
    :func:`~raywave.wave.propagation.band._adjoint`, in its column blocks."""
    part = job.part
    tb = part.values
    (my, mx), (ny, nx) = job.size, in_shape
    row_runs, col_runs = index_runs(part.rows), index_runs(part.cols)
    chunks = band_chunks(g, my, part.cols.numel())
    gx = _x_band(g, mx, col_runs, chunks)  # (noy, C), not yet / mx
    kept = u if isinstance(u, list) else None
    ux = None if kept is not None else _x_band(u, mx, col_runs, chunks)
    full = torch.zeros((ny, mx), dtype=g.dtype, device=g.device) if need_u else None
    terms = torch.zeros(3, dtype=torch.float64, device=g.device)
    for i, (c0, c1) in enumerate(_blocks(part.cols.numel(), chunks)):
        gs = _y_spectrum(gx, c0, c1, my).div_(my * mx)  # (c, My); on the band rows ∂L/∂(product)
        su = _y_band(ux, c0, c1, my, row_runs) if kept is None else kept[i]  # (c, R)
        re, im, *per_col = adjoint_terms(torch.view_as_real(take(gs, row_runs)), torch.view_as_real(su),
                                         tb.fx[c0:c1, None].clone(), tb.fy, tb.p)  # (a view: guards on its base)
        del su
        terms += torch.stack(per_col).sum(-1)
        if need_u:  # the band rows: gs·conj(G), the others 0; fft(n=my)'s adjoint
            q = _band_put_(gs, row_runs, torch.complex(re, im))
            put(full, col_runs, torch.fft.ifft(q, dim=-1)[..., :ny].mul_(my).transpose(-1, -2), c0)
            del q
        del gs, re, im
    del gx, ux
    grad_u = torch.fft.ifft(full, dim=-1)[..., :nx] * mx if need_u else None
    return grad_u, terms.unbind(0)


def propagate_batch(field: Field, out, z=None, *legacy, transfer: BatchTransfer | None = None,
                    shift: torch.Tensor | None = None, dz: torch.Tensor | None = None, margin: float = 0.5,
                    guard: float = 2.0) -> Field:
    """Propagate the batched :class:`~raywave.wave.grid.Field` ``field`` (envelope ``(..., Ny, Nx)``, any batch
    axes, B elements; each with its own wavelength, index, carrier and window where they differ, zero-padded at
    its end: :meth:`~raywave.wave.grid.Field.stack`) by ``z`` mm (one distance, or one per element) onto ``out``
    (one :class:`~raywave.wave.grid.Grid` of the field's pitch for every element, or one per element, all of one
    shape ``(ny, nx)``) as one batch: one FFT size, one transfer tensor, one band convolution (the module
    docstring). Each element equals :func:`~raywave.wave.propagation.propagate_window` of it alone where the batch
    needs no larger FFT grid than it does (otherwise to the sampling of its rolled-off kernel's spectrum).

    Args:
        transfer: :func:`batch_transfer` of ``WindowBatch.of(field, out, z, margin, guard)`` (a caller that
            propagates many batches of one geometry builds it once; checked against that plan); None: built here
            (with ``weight_derivative`` when ``shift`` or ``dz`` is given).
        shift: ``(..., 2)`` mm (the batch shape, or ``(B, 2)``) and ``dz`` (0-d, mm): zero-valued tensors that carry
            the derivatives of each output window's position and of the distance (the first-order perturbation of
            :func:`~raywave.wave.propagation.propagate_window`; the transfer built with ``weight_derivative``).
        margin, guard: the band limit's, as :func:`~raywave.wave.propagation.propagate_window` (``guard`` > 0).

    Returns:
        The propagated Field, envelope ``(..., ny, nx)``, each element on its output window (one grid of the output
        shape; :attr:`~raywave.wave.grid.Field.windows` where the output windows differ), with the input's
        wavelengths, indices and carriers. The form of before issue 43 (``propagate_batch(u, transfer, out_shape,
        ...)``) raises a TypeError naming this one.
    """
    if legacy or not isinstance(field, Field):
        raise TypeError("propagate_batch takes a batched raywave.wave.Field since issue 43: propagate_batch(field, "
                        "out, z, *, transfer=None, shift=None, dz=None, margin=0.5, guard=2.0) -> Field; a padded "
                        "(B, Ny, Nx) tensor u of a WindowBatch wb is wb.field(u), with out=wb.out_grids(), "
                        "z=wb.distances()")
    wb = WindowBatch.of(field, out, z, margin, guard)
    b = field.count
    if transfer is None:
        transfer = batch_transfer(wb, field.envelope.device, shift is not None or dz is not None)
    elif transfer.count != b or (transfer.batch is not None and transfer.batch != wb):
        raise ValueError(f"propagate_batch: the transfer was built for another batch (its {transfer.count} "
                         f"sources vs the field's {b}, or another geometry): build it with "
                         "batch_transfer(WindowBatch.of(field, out, z, margin, guard))")
    if shift is not None:
        if tuple(shift.shape) not in ((*field.batch_shape, 2), (b, 2)):
            raise ValueError(f"propagate_batch: shift must have the shape {(*field.batch_shape, 2)} (or {(b, 2)}), "
                             f"got {tuple(shift.shape)}")
        shift = shift.reshape(b, 2)
    u = field.envelope.reshape(b, *field.grid.shape)
    env = _propagate_flat(u, transfer, wb.out_shape, shift, dz)
    outs = wb.out_grids()
    return Field(env.reshape(*field.batch_shape, *wb.out_shape), outs[0], field.wavelength, field.n, field.carrier,
                 outs)


def _propagate_flat(u: torch.Tensor, transfer: BatchTransfer, out_shape, shift: torch.Tensor | None,
                    dz: torch.Tensor | None) -> torch.Tensor:
    """The envelopes ``u`` ``(B, Ny, Nx)`` (each source's window zero-padded at its end to the batch's input shape)
    propagated by the transfer functions of :func:`batch_transfer` onto their output windows ``(B, ny, nx)``
    (``out_shape``); ``shift`` ``(B, 2)`` mm and ``dz`` (0-d mm) as :func:`propagate_batch`. A transfer with each
    source's own band (:attr:`BatchTransfer.parts`, a CPU's) runs field by field on those bands (the union's
    columns outside a source's band hold zeros: the same values without their transforms)."""
    noy, nox = (int(s) for s in out_shape)
    b, dev = u.shape[0], u.device
    perturbed = shift is not None or dz is not None
    if perturbed:  # (the perturbation's tensors: none without one)
        zero = torch.zeros((b, 1, 1), dtype=torch.float64, device=dev)
        sx, sy = (zero, zero) if shift is None else (s.reshape(b, 1, 1) for s in shift.to(torch.float64).unbind(-1))
        dzt = torch.zeros((), dtype=torch.float64, device=dev) if dz is None else dz.reshape(()).to(torch.float64)
        my, mx = transfer.size
        px, py = transfer.pitch
        fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=dev)
        fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=dev)
    if transfer.parts is not None and not devices.accelerator(u):
        # zero-valued perturbations (the engine's: they carry derivatives only) leave each source's transfer function
        # as it is: it is evaluated where the band convolution multiplies it (one host read for the batch)
        zero = not perturbed or not bool(torch.cat([sx.reshape(-1), sy.reshape(-1), dzt.reshape(-1)]).any())
        grad = torch.is_grad_enabled() and (u.requires_grad or (perturbed and (
            sx.requires_grad or sy.requires_grad or dzt.requires_grad)))
        outs = []
        # the fields as views of one unbind: its backward stacks their gradients once, where each indexed read's
        # backward would allocate (and add) a zero array of the whole batch (B² window-sized arrays)
        us = u.unbind(0)
        for i, part in enumerate(transfer.parts):
            if part.values is None:  # nothing passes: zeros (that keep u in the graph)
                outs.append(torch.zeros((noy, nox), dtype=u.dtype, device=dev) + 0 * us[i].sum())
            elif not zero:  # a non-zero perturbation: the band's values times its factors
                wave = None if dz is None else transfer.wave[:, i:i + 1]
                h = _Perturbed.apply(part.band[None], sx[i:i + 1], sy[i:i + 1], dzt, fx[part.cols], fy[part.rows],
                                     wave, part.rel)[0]
                outs.append(_convolve(us[i], h.to(u.dtype), transfer.size, part.rows, part.cols, noy, nox))
            elif grad:
                job = _BandJob(part, transfer.size, (noy, nox))
                scalars = (sx[i:i + 1], sy[i:i + 1], dzt) if perturbed else (None, None, None)
                outs.append(_TransferConvolve.apply(us[i], *scalars, job))
            else:
                outs.append(convolve_band(us[i], part.values, transfer.size, part.rows, part.cols, noy, nox))
        return torch.stack(outs)
    transfer = transfer.placed()
    h = transfer.band
    if perturbed:
        h = _Perturbed.apply(h, sx, sy, dzt, fx[transfer.cols], fy[transfer.rows],
                             None if dz is None else transfer.wave, transfer.rel)
    return _convolve(u, h.to(u.dtype), transfer.size, transfer.rows, transfer.cols, noy, nox)
