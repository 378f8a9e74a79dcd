"""The band convolution of the window-to-window angular spectrum (:mod:`raywave.wave.propagation.window`,
:mod:`raywave.wave.propagation.batch`): ``ifft2(fft2(u, s=(My, Mx))·h)[..., :noy, :nox]`` for a transfer function
``h`` that is zero outside the rectangle ``rows × cols`` of the FFT grid (given on it, ``(..., R, C)``).

Every 1-D transform runs along the contiguous last axis (issue 43): the band's columns are transposed once, in
blocks, so that the transforms along y, the product and the inverse along y run on rows of memory. A transform
along a strided axis costs ~1.7–2× the same transform along the last one on a CPU (pocketfft copies each line),
and gathering the band with ``index_select`` along the last axis ~7× a copy of its contiguous runs; the band is
one or two runs of the ``fftfreq`` grid (it wraps at the Nyquist frequency), so it is taken and put back by
slices. The same transforms on the same values as the plain product, to rounding.

Memory: the band runs in blocks of columns (:func:`band_chunks`): the full-height ``My × C`` arrays never exist.
"""

from __future__ import annotations

import itertools
import math

import torch

from raywave.utils import devices

#: a band convolution whose full-height band (My × C samples of the field's dtype) takes more bytes than this per
#: field of the batch runs in column blocks of about this size per field: the same FFTs on the same values, a lower
#: peak (a batch of B fields: B times this, the blocks as many as for one field)
BAND_CHUNK_BYTES = 8 * 2**20
#: :data:`BAND_CHUNK_BYTES` on an accelerator (CUDA: every op a kernel launch, memory aplenty): a map's bands run
#: in one block
BAND_CHUNK_BYTES_ACCELERATOR = 256 * 2**20


def band_chunks(u: torch.Tensor, my: int, n_cols: int) -> int:
    """How many column blocks :func:`convolve_band` splits a band of ``n_cols`` columns into (1: one block), for a
    field ``u`` ``(..., Ny, Nx)`` and the FFT height ``my`` (per field of the batch: see :data:`BAND_CHUNK_BYTES`, on
    an accelerator :data:`BAND_CHUNK_BYTES_ACCELERATOR`)."""
    per_col = my * u.element_size()
    limit = BAND_CHUNK_BYTES_ACCELERATOR if devices.accelerator(u) else BAND_CHUNK_BYTES
    return max(1, min(n_cols, math.ceil(per_col * n_cols / limit)))


def index_runs(idx: torch.Tensor) -> tuple[tuple[int, int], ...]:
    """The sorted indices ``idx`` (K,) as half-open runs ``((a, b), …)`` of consecutive values (one host read)."""
    v = idx.tolist()
    if not v:
        return ()
    runs, a = [], v[0]
    for prev, cur in zip(v, v[1:]):
        if cur != prev + 1:
            runs.append((a, prev + 1))
            a = cur
    runs.append((a, v[-1] + 1))
    return tuple(runs)


def take(x: torch.Tensor, runs) -> torch.Tensor:
    """The last-axis entries of ``x`` at the indices ``runs`` (:func:`index_runs`) in order: ``x[..., idx]`` by
    slices (a view for one run)."""
    parts = [x[..., a:b] for a, b in runs]
    if not parts:
        return x[..., :0]
    return parts[0] if len(parts) == 1 else torch.cat(parts, -1)


def put(out: torch.Tensor, runs, x: torch.Tensor, start: int = 0) -> torch.Tensor:
    """``out[..., idx[start:start + K]] = x`` (``x`` ``(..., K)``) by slices, in place (autograd keeps the copies);
    returns ``out``."""
    stop, pos, done = start + x.shape[-1], 0, 0
    for a, b in runs:
        lo, hi = max(start, pos), min(stop, pos + b - a)
        if lo < hi:
            out[..., a + lo - pos:a + hi - pos].copy_(x[..., done:done + hi - lo])
            done += hi - lo
        pos += b - a
    return out


def _scattered(x: torch.Tensor, runs, n: int) -> torch.Tensor:
    """``x`` ``(..., K)`` placed at the indices ``runs`` of a zero array ``(..., n)``."""
    return put(torch.zeros((*x.shape[:-1], n), dtype=x.dtype, device=x.device), runs, x)


def _blocks(n_cols: int, chunks: int):
    """The column blocks ``(c0, c1)`` of a band of ``n_cols`` columns in ``chunks`` pieces."""
    step = max(1, math.ceil(n_cols / chunks))
    return [(c0, min(c0 + step, n_cols)) for c0 in range(0, n_cols, step)]


def per_field(u: torch.Tensor, lead) -> bool:
    """Whether a band convolution of the batch ``lead`` (its leading shape) runs field by field: on a CPU with more
    than one field. Each field's column blocks then stay within :data:`BAND_CHUNK_BYTES` (cache-sized); the whole
    batch's blocks (B times larger) ran 1.6–2.9× slower per field on 2 threads (the 10×10×3 map's groups of 4–8
    fields: 58 vs 20 ms per field at 1440², bit for bit the same values). An accelerator keeps the batch."""
    return not devices.accelerator(u) and math.prod(lead) > 1


def _fields(fn, tensors: tuple, lead) -> list:
    """``fn`` of each field of the batch ``lead`` (its leading shape), in order: each of ``tensors`` ``(..., Y, X)``
    (or None) broadcast over ``lead`` (views: a shared tensor is not copied per field) and given by its field's
    slice."""
    views = [None if t is None else t.expand(*lead, *t.shape[-2:]) for t in tensors]
    return [fn(*(None if v is None else v[idx] for v in views)) for idx in itertools.product(*map(range, lead))]


def _field_by_field(fn, tensors: tuple, lead, tail) -> torch.Tensor:
    """:func:`_fields` of ``fn`` (returning ``(*tail)`` each), stacked to ``(*lead, *tail)``."""
    return torch.stack(_fields(fn, tensors, lead)).reshape(*lead, *tail)


#: :func:`_x_band` transforms at least this many blocks of rows (its full-width transient a fraction of the band)
X_ROW_BLOCKS = 4


def _x_band(u: torch.Tensor, mx: int, col_runs, chunks: int) -> torch.Tensor:
    """``fft(u, n=mx)`` along x on the band's columns: ``(..., Ny, C)``, transformed in ``chunks`` blocks of rows
    (the full-width spectrum exists a block at a time)."""
    ny = u.shape[-2]
    n_cols = sum(b - a for a, b in col_runs)
    out = torch.empty((*u.shape[:-2], ny, n_cols), dtype=u.dtype, device=u.device)
    step = max(1, math.ceil(ny / max(chunks, X_ROW_BLOCKS)))
    for r0 in range(0, ny, step):
        full = torch.fft.fft(u[..., r0:r0 + step, :], n=mx, dim=-1)
        pos = 0
        for a, b in col_runs:  # take(full, col_runs) written straight into its rows of out
            out[..., r0:r0 + step, pos:pos + b - a].copy_(full[..., a:b])
            pos += b - a
        del full
    return out


#: :func:`_x_inverse`'s blocks of rows are a multiple of this many rows (pocketfft's SIMD groups: 2–8 lines)
INVERSE_ROW_ALIGN = 16


def _x_inverse(band: torch.Tensor, mx: int, col_runs, n_keep: int, scale: float | None = None) -> torch.Tensor:
    """``ifft(full, dim=-1)[..., :n_keep]`` (times ``scale`` where given) of the full-width array ``full`` ``(..., R,
    mx)`` that holds ``band`` ``(..., R, C)`` at the columns ``col_runs`` and 0 elsewhere, without ``full``: in blocks
    of rows (as :func:`_x_band`'s) through one full-width buffer whose other columns are zeroed once. The same
    transforms of the same values as the whole array's, without its zero fill and with a cache-sized working set
    (a 1141 × 1875 inverse: ~2× faster in blocks)."""
    rows = band.shape[-2]
    out = torch.empty((*band.shape[:-1], n_keep), dtype=band.dtype, device=band.device)
    # a multiple of INVERSE_ROW_ALIGN rows a block: pocketfft transforms the lines in SIMD groups from the first, the
    # last few alone, so every line falls in the group it has in the whole array's transform (bit for bit)
    step = math.ceil(rows / max(band_chunks(band, mx, rows), X_ROW_BLOCKS))
    step = max(1, -(-step // INVERSE_ROW_ALIGN) * INVERSE_ROW_ALIGN)
    buf = torch.zeros((*band.shape[:-2], min(step, rows), mx), dtype=band.dtype, device=band.device)
    for r0 in range(0, rows, step):
        k = min(step, rows - r0)
        blk = put(buf[..., :k, :], col_runs, band[..., r0:r0 + k, :])  # the band's columns; the others stay 0
        res = torch.fft.ifft(blk, dim=-1)[..., :n_keep]
        if scale is None:
            out[..., r0:r0 + k, :].copy_(res)
        else:
            torch.mul(res, scale, out=out[..., r0:r0 + k, :])
        del res
    return out


def _padded_columns(ux: torch.Tensor, c0: int, c1: int, my: int) -> torch.Tensor:
    """The columns ``c0:c1`` of ``ux`` ``(..., Ny, C)`` transposed into rows of memory and zero-padded to ``my``:
    ``(..., c, My)``, in one copy (``fft(x.transpose().contiguous(), n=my)`` copies twice: the transpose, then
    the padding; the same values)."""
    ny = ux.shape[-2]
    buf = torch.empty((*ux.shape[:-2], c1 - c0, my), dtype=ux.dtype, device=ux.device)
    buf[..., ny:].zero_()
    buf[..., :ny].copy_(ux[..., c0:c1].transpose(-1, -2))
    return buf


def _y_spectrum(ux: torch.Tensor, c0: int, c1: int, my: int) -> torch.Tensor:
    """The transform along y (length ``my``) of the columns ``c0:c1`` of ``ux`` (:func:`_x_band`, ``(..., Ny, C)``),
    transposed into rows of memory: ``(..., c, My)``."""
    return torch.fft.fft(_padded_columns(ux, c0, c1, my), dim=-1)


def _y_band(ux: torch.Tensor, c0: int, c1: int, my: int, row_runs) -> torch.Tensor:
    """The band's spectrum on its columns ``c0:c1``, transposed ``(..., c, R)`` (:func:`_y_spectrum` on the band's
    rows)."""
    return take(_y_spectrum(ux, c0, c1, my), row_runs)


def _band_product_(spec: torch.Tensor, row_runs, h_block: torch.Tensor) -> torch.Tensor:
    """In place on a full-length spectrum ``spec`` ``(..., c, My)``: its band rows times ``h_block`` ``(..., c,
    R)``, every other entry 0 (the product scattered onto the FFT grid without a second array); returns ``spec``."""
    pos = prev = 0
    for a, b in row_runs:
        spec[..., prev:a].zero_()
        spec[..., a:b].mul_(h_block[..., pos:pos + b - a])
        pos, prev = pos + b - a, b
    spec[..., prev:].zero_()
    return spec


class _Columns:
    """The transposed column blocks ``(..., c, R)`` of a transfer function on its band: ``h`` a tensor ``(..., R, C)``
    (views), or a lazily evaluated band (:class:`~raywave.wave.propagation.kernels.TransferBand`: each block
    evaluated where it is used, in ``dtype``; no band-sized array)."""

    def __init__(self, h, dtype):
        self.lazy = not isinstance(h, torch.Tensor)
        self.h, self.dtype = h, dtype
        self.h_t = None if self.lazy else h.transpose(-1, -2)

    def block(self, c0: int, c1: int) -> torch.Tensor:
        return self.h.block(c0, c1, self.dtype) if self.lazy else self.h_t[..., c0:c1, :]


def _band_put_(spec: torch.Tensor, row_runs, values: torch.Tensor) -> torch.Tensor:
    """In place on a full-length spectrum ``spec`` ``(..., c, My)``: its band rows set to ``values`` ``(..., c, R)``,
    every other entry 0 (:func:`_band_product_` with the product already formed); returns ``spec``."""
    pos = prev = 0
    for a, b in row_runs:
        spec[..., prev:a].zero_()
        spec[..., a:b].copy_(values[..., pos:pos + b - a])
        pos, prev = pos + b - a, b
    spec[..., prev:].zero_()
    return spec


def convolve_band(u: torch.Tensor, h, size, rows: torch.Tensor, cols: torch.Tensor, noy: int,
                  nox: int, keep: list | None = None) -> torch.Tensor:
    """``ifft2(fft2(u, s=size)·H)[..., :noy, :nox]`` for ``H`` zero outside ``rows × cols`` (``h`` on it,
    ``(..., R, C)``, or one source's :class:`~raywave.wave.propagation.kernels.TransferBand`, evaluated a column
    block at a time where the product needs it; ``rows`` ``(R,)``, ``cols`` ``(C,)`` sorted int64 indices into the
    FFT grid ``size`` = ``(My, Mx)``), for ``u`` ``(..., Ny, Nx)``: the output window ``(..., noy, nox)``. Autograd
    records it where its inputs require grad (the plain operations; :class:`BandConvolve` keeps less for the
    backward). ``keep``: a list to which, without autograd on one field on a CPU, the input's band spectrum is
    appended a column block at a time (``(c, R)`` each, :func:`_blocks`' blocks: what :class:`BandConvolve`'s
    backward would recompute); left empty otherwise."""
    my, mx = size
    lazy = not isinstance(h, torch.Tensor)
    lead = u.shape[:-2] if lazy else torch.broadcast_shapes(u.shape[:-2], h.shape[:-2])
    if rows.numel() == 0 or cols.numel() == 0:
        return torch.zeros((*lead, noy, nox), dtype=u.dtype, device=u.device) + 0 * u.sum()
    grad = torch.is_grad_enabled() and (u.requires_grad or (not lazy and h.requires_grad))
    if devices.accelerator(u):
        return _convolve_indexed(u, h.full(u.dtype) if lazy else h, size, (rows, cols), (noy, nox), grad)
    if not grad and per_field(u, lead):
        return _field_by_field(lambda ui, hi: convolve_band(ui, h if lazy else hi, size, rows, cols, noy, nox),
                               (u, None if lazy else h), lead, (noy, nox))
    row_runs, col_runs = index_runs(rows), index_runs(cols)
    chunks = band_chunks(u, my, cols.numel())
    ux = _x_band(u, mx, col_runs, chunks)  # (..., Ny, C)
    h_t = _Columns(h, u.dtype)  # (..., C, R) a block at a time
    out = torch.zeros((*lead, noy, mx), dtype=u.dtype, device=u.device)
    blocks = _blocks(cols.numel(), chunks)
    for c0, c1 in blocks:
        blk = _padded_columns(ux, c0, c1, my)  # (..., c, My)
        if c1 == blocks[-1][1]:
            ux = None  # the last block: the x band is no longer needed (a lower peak for a one-block band)
        spec = torch.fft.fft(blk, dim=-1)
        del blk
        if grad:
            full = _scattered(take(spec, row_runs) * h_t.block(c0, c1), row_runs, my)
        else:  # the product in place on the block's spectrum (no band copy, no second full-length array)
            if keep is not None:  # the input's band spectrum, for a backward (:class:`BandConvolve`)
                kept = take(spec, row_runs)  # (a copy where the band's rows are two runs, else a view)
                keep.append(kept if len(row_runs) > 1 else kept.clone())
            full = _band_product_(spec, row_runs, h_t.block(c0, c1))
        del spec
        part = torch.fft.ifft(full, dim=-1)[..., :noy]  # (..., c, noy)
        del full
        put(out, col_runs, part.transpose(-1, -2), c0)
        del part
    return torch.fft.ifft(out, dim=-1)[..., :nox]


def _convolve_indexed(u: torch.Tensor, h: torch.Tensor, size, band: tuple, out_shape: tuple, grad: bool):
    """:func:`convolve_band` on an accelerator (every op a kernel launch): the band's rows and columns taken and put
    back by one indexed gather / copy each (``band`` = ``(rows, cols)``) instead of a slice copy per run of them, the
    transform along x in one pass (its full-width spectrum at once: at most the batch's FFT-grid arrays), the
    columns in the blocks of :func:`band_chunks`: the same transforms of the same values, ~20 ops a block instead
    of ~60. ``out_shape`` = ``(noy, nox)``; ``grad``: out-of-place products (autograd records them)."""
    (my, mx), (rows, cols), (noy, nox) = size, band, out_shape
    lead = torch.broadcast_shapes(u.shape[:-2], h.shape[:-2])
    ux = torch.fft.fft(u, n=mx, dim=-1).index_select(-1, cols)  # (..., Ny, C)
    h_t = h.transpose(-1, -2)  # (..., C, R)
    out = torch.zeros((*lead, noy, mx), dtype=u.dtype, device=u.device)
    for c0, c1 in _blocks(cols.numel(), band_chunks(u, my, cols.numel())):
        spec = torch.fft.fft(ux[..., c0:c1].transpose(-1, -2), n=my, dim=-1)  # (..., c, My)
        prod, hb = spec.index_select(-1, rows), h_t[..., c0:c1, :]
        prod = prod.mul_(hb) if not grad and prod.shape[:-2] == lead else prod * hb  # (in place unless broadcast)
        del spec
        full = torch.zeros((*prod.shape[:-1], my), dtype=prod.dtype, device=prod.device)
        full = full.index_copy(-1, rows, prod) if grad else full.index_copy_(-1, rows, prod)
        del prod
        part = torch.fft.ifft(full, dim=-1)[..., :noy].transpose(-1, -2)  # (..., noy, c)
        del full
        out = out.index_copy(-1, cols[c0:c1], part) if grad else out.index_copy_(-1, cols[c0:c1], part)
    return torch.fft.ifft(out, dim=-1)[..., :nox]


class BandConvolve(torch.autograd.Function):
    """:func:`convolve_band` with a hand-written backward (the adjoint transforms, in the same column blocks):
    autograd would keep the band spectrum, the product and both zero-filled grids; this keeps the inputs it needs
    and recomputes the input's band spectrum for the transfer function's gradient. Linear in ``u`` for fixed ``h``
    and in ``h`` for fixed ``u``: ``∂/∂u`` is the adjoint convolution with ``conj(h)``, ``∂/∂h`` the product of the
    output gradient's band spectrum with the input's conjugate band spectrum."""

    @staticmethod
    def forward(ctx, u, h, size, rows, cols, noy: int, nox: int):
        ctx.size, ctx.noy, ctx.nox, ctx.u_shape, ctx.h_shape = size, noy, nox, u.shape, h.shape
        # ∂/∂h needs the input's band spectrum: kept from the forward where it is small (one field on a CPU),
        # else the input kept and its spectrum recomputed in the backward
        keep = [] if ctx.needs_input_grad[1] and _keeps_spectrum(u, h, rows, cols) else None
        out = convolve_band(u, h, size, rows, cols, noy, nox, keep)
        ctx.spectrum = keep or None
        ctx.save_for_backward(u if ctx.needs_input_grad[1] and not keep else None,
                              h if ctx.needs_input_grad[0] else None, rows, cols)
        return out

    @staticmethod
    def backward(ctx, g):
        u, h, rows, cols = ctx.saved_tensors
        need = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        runs = index_runs(rows), index_runs(cols)
        ny, nx = ctx.u_shape[-2:]
        lead = g.shape[:-2]
        spectrum = ctx.spectrum
        if spectrum is not None:  # one field, its band spectrum kept
            grad_u, grad_h = _adjoint(g, spectrum, h, ctx.size, runs, (ny, nx), need)
        elif per_field(g, lead):  # field by field on a CPU, as the forward (:func:`per_field`)
            parts = _fields(lambda gi, ui, hi: _adjoint(gi, ui, hi, ctx.size, runs, (ny, nx), need),
                            (g, u if need[1] else None, h if need[0] else None), lead)
            grad_u = torch.stack([q[0] for q in parts]).reshape(*lead, ny, nx) if need[0] else None
            grad_h = torch.stack([q[1] for q in parts]).reshape(*lead, *parts[0][1].shape) if need[1] else None
        else:
            grad_u, grad_h = _adjoint(g, u, h, ctx.size, runs, (ny, nx), need)
        grad_h = grad_h.sum_to_size(ctx.h_shape) if need[1] else None
        grad_u = grad_u.sum_to_size(ctx.u_shape) if need[0] else None
        return grad_u, grad_h, None, None, None, None, None


#: :class:`BandConvolve` keeps the input's band spectrum from the forward for ``∂/∂h`` (instead of the input, its
#: spectrum recomputed in the backward: two of the backward's five passes of transforms) up to this many bytes (a
#: mid-system DOE's PSF window: 1015 × 1135 complex128, 18 MB)
KEEP_SPECTRUM_BYTES = 64 * 2**20


def _keeps_spectrum(u: torch.Tensor, h, rows: torch.Tensor, cols: torch.Tensor) -> bool:
    """Whether :class:`BandConvolve` keeps the input's band spectrum (:data:`KEEP_SPECTRUM_BYTES`): one field (no
    batch axes) on a CPU, the band within the bytes."""
    return (u.ndim == 2 and isinstance(h, torch.Tensor) and h.ndim == 2 and not devices.accelerator(u)
            and rows.numel() * cols.numel() * u.element_size() <= KEEP_SPECTRUM_BYTES)


def _adjoint(g: torch.Tensor, u, h: torch.Tensor, size, runs, in_shape, need) -> tuple:
    """:class:`BandConvolve`'s backward: ``(∂L/∂u (..., Ny, Nx) or None, ∂L/∂h (..., R, C) or None)`` (before any
    broadcast is summed) from the output's gradient ``g`` ``(..., noy, nox)``; ``runs`` = the band's ``(row runs,
    column runs)``, ``in_shape`` = ``(Ny, Nx)``, ``need`` = (∂u wanted, ∂h wanted). ``u``: the input (its band
    spectrum recomputed for ∂h), or that spectrum kept by the forward (a list of :func:`_blocks`' column blocks ``(...,
    c, R)``: :func:`convolve_band` ``keep``)."""
    (my, mx), (ny, nx), (need_u, need_h) = size, in_shape, need
    row_runs, col_runs = runs
    n_cols = sum(b - a for a, b in col_runs)
    # the output's adjoint chain: ifft along x (its adjoint fft / mx) and the columns' copy, then per block the
    # kept rows' ifft along y (fft / my) and the rows' copy: ∂L/∂(product) on the band
    chunks = band_chunks(g, my, n_cols)
    gx = _x_band(g, mx, col_runs, chunks)  # (..., noy, C), not yet / mx
    kept = isinstance(u, list)
    ux = _x_band(u, mx, col_runs, chunks) if need_h and not kept else None
    # ∂L/∂u's band columns before the inverse transform along x (:func:`_x_inverse`)
    full = torch.empty((*g.shape[:-2], ny, n_cols), dtype=g.dtype, device=g.device) if need_u else None
    h_t = _Columns(h, g.dtype) if need_u else None
    grad_h = []
    for i, (c0, c1) in enumerate(_blocks(n_cols, chunks)):
        gs = _y_spectrum(gx, c0, c1, my).div_(my * mx)  # (..., c, My); on the band rows ∂L/∂(product)
        if need_h:
            spec = u[i] if kept else _y_band(ux, c0, c1, my, row_runs)
            grad_h.append((take(gs, row_runs) * torch.conj_physical(spec)).transpose(-1, -2))
            del spec
        if need_u:  # in place: the band rows times conj(h), the others 0, as conj(conj(gs)·h) (the same values:
            # a product with a lazily conjugated strided block of h took ~8× the plain product's time)
            q = torch.conj_physical_(_band_product_(torch.conj_physical_(gs), row_runs, h_t.block(c0, c1)))
            part = torch.fft.ifft(q, dim=-1)[..., :ny].mul_(my)  # fft(n=my)'s adjoint: (..., c, ny)
            del q
            full[..., c0:c1].copy_(part.transpose(-1, -2))
            del part
        del gs
    del gx, ux
    grad_h = torch.cat(grad_h, dim=-1) if need_h else None
    grad_u = _x_inverse(full, mx, col_runs, nx, mx) if need_u else None
    return grad_u, grad_h
