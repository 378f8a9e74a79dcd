"""Propagation between two windows (the efficient path): :func:`propagate_window` and the first-order
perturbation of its transfer function by a window shift and an extra distance (:class:`_Perturbed`).

Method (Matsushima 2010, Opt. Express 18, 18453): linear convolution by FFTs of size ≥ N_in + N_out − 1 (+ the
guard) per axis with the transfer function ``H(f + f_c)·exp(i2π f·(out_origin − in_origin))`` restricted to the
frequencies whose geometric shift ``z·tanθ`` (per axis) can carry light from the input window into the output
window, then rolled off smoothly over ``guard`` Fresnel zones (see :func:`window_transfer`). This removes
wrap-around and kernel aliasing, and the cost scales with ``(N_in + N_out + 4·guard·F/p)²`` instead of the full
DOE grid. ``guard=0`` is the sharp band limit of the paper, whose truncation error decays only like 1/distance:
for a hard-edged aperture whose edge lies within a Fresnel zone of the window extremes it reaches ~6e-3 of the
peak amplitude, against ~1e-4 with ``guard=2`` (see tests/test_propagation.py).
"""

from __future__ import annotations

import math
import torch

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation._common import (_TWO_PI, _UM_TO_MM, _positive, _sqrt_kz, _xy, check_single_field,
                                              legacy_call)
from raywave.wave.propagation.transfer import WindowSource, WindowTransfer, _window_transfer


def propagate_window(field: Field, out: Grid, z=None, *legacy, margin: float = 0.5, guard: float = 2.0,
                     shift: torch.Tensor | None = None, transfer: tuple | None = None, dz: torch.Tensor | None = None,
                     **legacy_kw) -> Field:
    """Propagate a field from its window to the output window ``out`` (shifted band-limited ASM).

    The true field is ``U(x, y) = u(x, y) · exp(i k n (α x + β y))`` with ``k = 2π/λ`` and
    ``carrier = (α, β)`` direction cosines (typically the chief ray's); removing the carrier keeps the sampled
    envelope far below Nyquist for off-axis light. An FFT convolution on the band of frequencies that can carry
    light between the windows (method, cost, accuracy: the module docstring): crop the field to the lit footprint.

    Args:
        field: the :class:`~raywave.wave.grid.Field` to propagate: envelope ``u`` ``(..., Ny_in, Nx_in)`` on its
            grid (pixel (0, 0) centred at the grid's origin), its vacuum wavelength (µm), medium index ``n`` and
            carrier ``(α, β)`` (removed at the input and the output), shared by any leading batch axes (a batch
            whose elements differ: :func:`~raywave.wave.propagation.propagate_batch`).
        out: the output window, a :class:`~raywave.wave.grid.Grid` of the field's pitch (any origin, not only on
            the input's lattice, and any shape).
        z: propagation distance in mm (negative allowed; float or 0-d tensor).
        margin: tolerance of the band limit in pixels beyond the pixel-centre extremes (default ½ pixel).
        guard: width of the smooth roll-off of the band limit beyond that range, in Fresnel zones
            ``sqrt(λ|z|/(n cos³θ_c))`` (default 2; the FFT grows by the same amount). ``guard=0`` is the sharp
            band limit of the paper (an error up to ~6e-3 of the peak amplitude instead of ~1e-4: module docstring).
        shift: optional ``(2,)`` tensor (mm), an extra translation of the output window added to
            ``out.origin`` through a phase ramp on the spectrum; pass a zero-valued tensor that carries a
            derivative to make the result differentiable with respect to where the window sits (a PSF crop
            that follows a chief ray). Keep it well below the margin (sub-sample). With a ``transfer`` built by
            ``weight_derivative=True`` (the default when ``transfer`` is None) the derivative includes the band
            limit's roll-off following the window.
        transfer: a precomputed ``window_transfer(field, out, z, ...)`` result for exactly this geometry (a caller
            that propagates many fields between the same windows builds it once).
        dz: optional 0-d tensor (mm), an extra propagation distance added to ``z``: the transfer function
            becomes ``(G + dz·D)·exp(i2π·dz·w)``, ``w = sqrt((n/λ)² − |f + f_c|²)`` the axial frequency at the
            true spatial frequency (0 where evanescent) and ``D`` the first-order change of the roll-off weights
            (:func:`window_transfer` ``weight_derivative=True``; the FFT size and the band's rows/columns stay
            those of ``z``). Pass a zero-valued tensor that carries a derivative (``d − d.detach()``): the result
            is unchanged and differentiable with respect to the distance, exactly to first order, while reusing
            a cached ``transfer`` (a sensor plane that moves with the lens). ``transfer`` must then be the
            3-tuple of ``weight_derivative=True`` (a 2-tuple is rebuilt).

    Returns:
        The output :class:`~raywave.wave.grid.Field` on ``out`` with the input's wavelength, index and carrier:
        envelope ``(..., Ny_out, Nx_out)`` (the true field divided by ``exp(i k n (α x + β y))`` at the output
        coordinates), the input's dtype.

    The form of before issue 43 (``propagate_window(u, pitch, wavelength, z, in_origin, out_origin, out_shape,
    n=, carrier=, ...)``) raises a TypeError that says how to build the Field and the Grid.
    """
    if legacy or legacy_kw or not isinstance(field, Field):
        legacy_call("propagate_window", "propagate_window(field, out, z, *, margin=0.5, guard=2.0, shift=None, "
                    "transfer=None, dz=None) -> Field")
    check_single_field(field, out, z, "propagate_window")
    u = field.envelope
    if transfer is None or (dz is not None and len(transfer) < 3):
        transfer = _window_transfer(WindowSource.between(field, out, z), out.shape, field.grid.pitch, (margin, guard),
                                    u.device, dz is not None or shift is not None)
    h, size, rows, cols = _applied_transfer(transfer, field, shift, dz)
    return field.with_envelope(_convolve(u, h, size, rows, cols, *out.shape), out)


def _applied_transfer(transfer, field: Field, shift, dz):
    """``(h, (My, Mx), rows, cols)``: the transfer function in the envelope's dtype on the band ``rows × cols``
    (int64 indices ``(R,)``, ``(C,)``; ``h`` ``(R, C)``) of the FFT grid ``(My, Mx)`` of a :class:`WindowTransfer`,
    or on the whole grid (``h`` ``(My, Mx)``, ``rows``/``cols`` None) of a plain tuple; times the window shift
    ``shift`` ``(2,)`` (mm) and the extra distance ``dz`` (0-d, mm) where given (``field``'s pitch, wavelength, index
    and carrier)."""
    u = field.envelope
    if isinstance(transfer, WindowTransfer):
        h, rows, cols = transfer.band, transfer.rows.to(u.device), transfer.cols.to(u.device)
        rel = transfer.band_rel
    else:  # a plain (G, (My, Mx)[, R]) tuple: the full FFT grid
        h, rel, rows, cols = transfer[0], transfer[2] if len(transfer) > 2 else None, None, None
    my, mx = transfer[1]
    if shift is not None or dz is not None:
        h = _perturbed(h.to(u.dtype), rel, ((my, mx), rows, cols), field, shift, dz)
    return h.to(u.dtype), (my, mx), rows, cols


def _convolve(u, h, size, rows, cols, noy: int, nox: int):
    """The output window ``(..., noy, nox)`` of ``u`` ``(..., Ny_in, Nx_in)`` convolved with the transfer function
    ``h`` on the FFT grid ``size`` (see :func:`_applied_transfer`): over the whole grid where ``rows`` is None,
    else over the band alone, with the hand-written backward where autograd records the product."""
    if rows is None:
        return _convolve_full(u, h, size, noy, nox)
    if torch.is_grad_enabled() and (u.requires_grad or h.requires_grad) and rows.numel() and cols.numel():
        return _BandConvolve.apply(u, h, size, rows, cols, noy, nox)
    return _convolve_band(u, h, size, rows, cols, noy, nox)


def _perturbed(h, rel, band, field: Field, shift, dz):
    """``h`` times the first-order window shift and extra distance (:class:`_Perturbed`), on the band ``band`` =
    ``(size, rows, cols)``: the rows × cols of the FFT grid ``size`` (or the whole grid where ``rows`` is None);
    ``field``: the pitch, wavelength, index, carrier and device."""
    (my, mx), rows, cols = band
    device = field.envelope.device
    px, py = field.grid.pitch
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=device)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=device)
    if rows is not None:
        fx, fy = fx[cols], fy[rows]
    zero = torch.zeros((), dtype=torch.float64, device=device)
    sx, sy = (zero, zero) if shift is None else shift.to(device=device, dtype=torch.float64).reshape(2).unbind()
    dz = _dz_tensor(dz, device) if dz is not None else zero
    axial = (field.wavelength, field.n, field.carrier) if dz.requires_grad or float(dz) != 0 else None
    return _Perturbed.apply(h, sx, sy, dz, fx, fy, axial, rel)


def _convolve_full(u, h, size, noy, nox):
    """``ifft2(fft2(u, s=size)·h)[..., :noy, :nox]``, one axis at a time: the first pass transforms only the rows
    of ``u`` that hold data, the last only the ``noy`` rows kept."""
    my, mx = size
    spec = torch.fft.fft(torch.fft.fft(u, n=mx, dim=-1), n=my, dim=-2)
    out = torch.fft.ifft(torch.fft.ifft(spec * h, dim=-2)[..., :noy, :], dim=-1)
    return out[..., :nox]


def _convolve_band(u, h, size, rows, cols, noy, nox):
    """:func:`_convolve_full` for an ``h`` that is zero outside the rectangle ``rows × cols`` (given as ``h`` on it,
    ``(R, C)``): the transforms along y run only over the ``C`` columns of the band (the others are zero after the
    product), and the product and the inverse transform along y only over the band's rows resp. columns. The
    same FFTs on the same values as the full product, without the columns that are zero."""
    my, mx = size
    lead = u.shape[:-2]
    if rows.numel() == 0 or cols.numel() == 0:
        return torch.zeros((*lead, noy, nox), dtype=u.dtype, device=u.device) + 0 * u.sum()
    chunks = _band_chunks(u, my, cols.numel())
    if chunks > 1 and not (torch.is_grad_enabled() and (u.requires_grad or h.requires_grad)):
        return _convolve_band_chunked(u, h, size, rows, cols, noy, nox, chunks)
    # peak memory: every full-size intermediate is released before the next one is made
    prod = _band_spectrum(u, size, rows, cols)
    # in place unless autograd needs the factors (the product's backward keeps both)
    prod = prod.mul_(h) if not (torch.is_grad_enabled() and (prod.requires_grad or h.requires_grad)) else prod * h
    full_y = _scatter(prod, -2, rows, my)
    del prod  # before the inverse transform: the band and both full-height grids would be alive at once
    part = torch.fft.ifft(full_y, dim=-2)
    del full_y
    full_x = _scatter(part[..., :noy, :], -1, cols, mx)
    del part
    return torch.fft.ifft(full_x, dim=-1)[..., :nox]


#: a band convolution whose full-height band (My × C samples of the field's dtype) takes more bytes than this per
#: field of the batch runs in column chunks of about this size per field (without autograd): the same FFTs on the
#: same values, a lower peak (a batch of B fields: B times this, the chunks as many as for one field)
BAND_CHUNK_BYTES = 8 * 2**20
#: :data:`BAND_CHUNK_BYTES` on an accelerator (CUDA: every op a kernel launch, memory aplenty): a map's bands run
#: in one block
BAND_CHUNK_BYTES_ACCELERATOR = 256 * 2**20


def _band_chunks(u, my: int, n_cols: int) -> int:
    """How many column chunks :func:`_convolve_band` splits a band of ``n_cols`` columns into (1: none), for a
    field ``u`` ``(..., Ny, Nx)`` and the FFT height ``my`` (per field of the batch: see :data:`BAND_CHUNK_BYTES`, on
    an accelerator :data:`BAND_CHUNK_BYTES_ACCELERATOR`)."""
    per_col = my * u.element_size()
    limit = BAND_CHUNK_BYTES if u.device.type == "cpu" else BAND_CHUNK_BYTES_ACCELERATOR
    return max(1, min(n_cols, math.ceil(per_col * n_cols / limit)))


def _convolve_band_chunked(u, h, size, rows, cols, noy: int, nox: int, chunks: int):
    """:func:`_convolve_band` (no autograd) in ``chunks`` blocks of the band's columns: the transform along x runs
    over blocks of rows and keeps only the band's columns, then each column block goes through the transform along
    y, the product, the inverse along y and into the output's columns. The same 1-D FFTs on the same values; the
    full-height (My × C) arrays never exist."""
    my, mx = size
    ny = u.shape[-2]
    n_cols = cols.numel()
    step_r = max(1, math.ceil(ny / chunks))
    ux = torch.cat([torch.fft.fft(u[..., r0:r0 + step_r, :], n=mx, dim=-1).index_select(-1, cols)
                    for r0 in range(0, ny, step_r)], dim=-2)  # (..., ny, C)
    out = torch.zeros((*u.shape[:-2], noy, mx), dtype=u.dtype, device=u.device)
    step = math.ceil(n_cols / chunks)
    for c0 in range(0, n_cols, step):
        spec = torch.fft.fft(ux[..., c0:c0 + step], n=my, dim=-2).index_select(-2, rows)
        spec.mul_(h[..., c0:c0 + step])
        part = torch.fft.ifft(_scatter(spec, -2, rows, my), dim=-2)[..., :noy, :]
        del spec
        out.index_copy_(-1, cols[c0:c0 + step], part)
        del part
    del ux
    return torch.fft.ifft(out, dim=-1)[..., :nox]


def _band_spectrum(u, size, rows, cols):
    """The band ``rows × cols`` of ``fft2(u, s=size)``: the first pass along one axis, then only the band's lines
    along the other (the cheaper order of the two)."""
    my, mx = size
    ny, nx = u.shape[-2:]
    # the two orders give the same DFT (to rounding); the cheaper one transforms fewer / shorter lines: x first
    # costs ny transforms of mx and C of my, y first nx of my and R of mx
    if ny * _fft_cost(mx) + cols.numel() * _fft_cost(my) <= nx * _fft_cost(my) + rows.numel() * _fft_cost(mx):
        spec = torch.fft.fft(torch.fft.fft(u, n=mx, dim=-1).index_select(-1, cols), n=my, dim=-2)
        return spec.index_select(-2, rows)
    spec = torch.fft.fft(torch.fft.fft(u, n=my, dim=-2).index_select(-2, rows), n=mx, dim=-1)
    return spec.index_select(-1, cols)


def _fft_cost(n: int) -> float:
    """Relative cost of one FFT of length ``n`` (n·log2 n)."""
    return n * math.log2(max(n, 2))


def _scatter(x, dim: int, index, n: int):
    """``x`` placed at ``index`` along ``dim`` of a zero array ``n`` long there, filled in place (the zeros carry no
    graph, so autograd keeps the copy's gradient)."""
    shape = list(x.shape)
    shape[dim] = n
    return torch.zeros(shape, dtype=x.dtype, device=x.device).index_copy_(dim, index, x)


class _BandConvolve(torch.autograd.Function):
    """:func:`_convolve_band` with a hand-written backward (the adjoint transforms): autograd would keep the band
    spectrum, the product and both zero-filled grids (~4 band-sized complex arrays per PSF, the largest share of a
    trained lens's propagation memory); this keeps the inputs it needs and recomputes the input's band spectrum
    for the transfer function's gradient. Linear in ``u`` for fixed ``h`` and in ``h`` for fixed ``u``:
    ``∂/∂u`` is the adjoint convolution with ``conj(h)``, ``∂/∂h`` the product of the output gradient's band
    spectrum with the input's conjugate band spectrum."""

    @staticmethod
    def forward(ctx, u, h, size, rows, cols, noy: int, nox: int):
        ctx.size, ctx.noy, ctx.nox, ctx.u_shape, ctx.h_shape = size, noy, nox, u.shape, h.shape
        ctx.save_for_backward(u if ctx.needs_input_grad[1] else None, h if ctx.needs_input_grad[0] else None,
                              rows, cols)
        return _convolve_band(u, h, size, rows, cols, noy, nox)

    @staticmethod
    def backward(ctx, g):
        u, h, rows, cols = ctx.saved_tensors
        chunks = _band_chunks(g, ctx.size[0], cols.numel())
        if chunks > 1:
            return _BandConvolve._backward_chunked(ctx, g, u, h, rows, cols, chunks)
        (my, mx), noy, nox, (ny, nx) = ctx.size, ctx.noy, ctx.nox, ctx.u_shape[-2:]
        # the output's adjoint chain: ifft along x (fft / mx), the columns' copy, ifft along y over the kept rows
        g = torch.fft.fft(g, n=mx, dim=-1).index_select(-1, cols) / mx  # (..., noy, C)
        g = torch.fft.fft(g, n=my, dim=-2).index_select(-2, rows) / my  # (..., R, C): ∂L/∂(product)
        grad_u = grad_h = None
        if ctx.needs_input_grad[1]:
            grad_h = (g * _band_spectrum(u, (my, mx), rows, cols).conj()).sum_to_size(ctx.h_shape)
        if ctx.needs_input_grad[0]:
            part = torch.fft.ifft(_scatter(g * h.conj(), -2, rows, my), dim=-2)[..., :ny, :] * my  # fft(n=my)'s adjoint
            del g
            full = _scatter(part, -1, cols, mx)
            del part
            grad_u = (torch.fft.ifft(full, dim=-1)[..., :nx] * mx).sum_to_size(ctx.u_shape)
        return grad_u, grad_h, None, None, None, None, None

    @staticmethod
    def _backward_chunked(ctx, g, u, h, rows, cols, chunks: int):
        """:meth:`backward` in ``chunks`` blocks of the band's columns (a large band: the same 1-D transforms on the
        same values, without the full-height My × C arrays; see :func:`_convolve_band_chunked`)."""
        (my, mx), (ny, nx) = ctx.size, ctx.u_shape[-2:]
        need_u, need_h = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        n_cols = cols.numel()
        step = math.ceil(n_cols / chunks)
        g = torch.fft.fft(g, n=mx, dim=-1).index_select(-1, cols) / mx  # (..., noy, C)
        ux = torch.fft.fft(u, n=mx, dim=-1).index_select(-1, cols) if need_h else None  # (..., ny, C)
        full = torch.zeros((*g.shape[:-2], ny, mx), dtype=g.dtype, device=g.device) if need_u else None
        grad_h = []
        for c0 in range(0, n_cols, step):
            gc = torch.fft.fft(g[..., c0:c0 + step], n=my, dim=-2).index_select(-2, rows) / my  # (..., R, c)
            if need_h:
                spec = torch.fft.fft(ux[..., c0:c0 + step], n=my, dim=-2).index_select(-2, rows)
                width = spec.shape[-1]
                grad_h.append((gc * spec.conj()).sum_to_size(*ctx.h_shape[:-1], width))
                del spec
            if need_u:
                part = torch.fft.ifft(_scatter(gc * h[..., c0:c0 + step].conj(), -2, rows, my), dim=-2)[..., :ny, :]
                full.index_copy_(-1, cols[c0:c0 + step], part * my)
                del part
            del gc
        del g, ux
        grad_h = torch.cat(grad_h, dim=-1) if need_h else None
        grad_u = (torch.fft.ifft(full, dim=-1)[..., :nx] * mx).sum_to_size(ctx.u_shape) if need_u else None
        return grad_u, grad_h, None, None, None, None, None


class _Perturbed(torch.autograd.Function):
    """``h·a·exp(iφ)`` with ``φ = 2π(f_x s_x + f_y s_y + w·dz)`` and ``a = 1 + s_x R_x + s_y R_y + dz R_z`` (the
    window shift, the extra distance and the roll-off weights' first-order change), with a hand-written
    backward: the scalars' gradients are a few reductions instead of autograd's chain of full-size complex
    temporaries. ``axial``: ``(λ µm, n, carrier)`` of the axial frequency ``w`` (:func:`_axial_frequency`), None:
    no distance term; ``rel`` None: no weight terms (a = 1).

    Memory: the backward keeps the output ``y = h·a·e^{iφ}`` (which the band convolution that follows keeps
    anyway: one array for both) instead of ``h``, and recomputes ``w`` and ``e^{iφ}``: ``conj(g)·h·e^{iφ} =
    conj(g)·y / a``."""

    @staticmethod
    def _factors(sx, sy, dz, fx, fy, axial, rel, dtype):
        """``(exp(iφ), a)`` on the band (``a`` None without weight terms)."""
        phase = _TWO_PI * (fy[:, None] * sy + fx[None, :] * sx)
        if axial is not None:
            phase = phase + _TWO_PI * dz * _axial_frequency(fx, fy, *axial)
        e = torch.polar(torch.ones_like(phase), phase).to(dtype)  # exp(iφ)
        amp = None if rel is None else 1.0 + (sx * rel[1] + sy * rel[2] + dz * rel[0])
        return e, amp

    @staticmethod
    def forward(ctx, h, sx, sy, dz, fx, fy, axial, rel):
        e, amp = _Perturbed._factors(sx, sy, dz, fx, fy, axial, rel, h.dtype)
        y = h * e if amp is None else h * e * amp.to(h.real.dtype)
        # the band-sized factors are recomputed in backward (the same values): only the output and the inputs
        # other than h are kept
        ctx.axial = axial
        ctx.save_for_backward(y, sx, sy, dz, fx, fy, rel)
        return y

    @staticmethod
    def backward(ctx, g):
        y, sx, sy, dz, fx, fy, rel = ctx.saved_tensors
        grads = [None] * 8
        if ctx.needs_input_grad[0]:
            e, amp = _Perturbed._factors(sx, sy, dz, fx, fy, ctx.axial, rel, y.dtype)
            grads[0] = g * e.conj() if amp is None else g * e.conj() * amp.to(g.real.dtype)
        if any(ctx.needs_input_grad[1:4]):
            sums = _Perturbed._scalar_sums(g, y, sx, sy, dz, fx, fy, ctx.axial, rel)
            for i in (1, 2, 3):
                if ctx.needs_input_grad[i]:
                    grads[i] = sums[i - 1]
        return tuple(grads)

    @staticmethod
    def _scalar_sums(g, y, sx, sy, dz, fx, fy, axial, rel):
        """The real gradients of ``(s_x, s_y, dz)``: ``Re Σ conj(g)·∂y/∂s = Re Σ conj(g)·h·e^{iφ}·(∂a/∂s + i a
        ∂φ/∂s)``, with ``conj(g)·h·e^{iφ}·a = conj(g)·y`` (``a`` real), summed over blocks of
        :data:`PERTURBED_BLOCK_ROWS` rows of the band: its band-sized temporaries (~8 arrays, the peak of a
        lens-trained backward) exist a block at a time."""
        sums = [y.real.new_zeros(()).to(torch.float64) for _ in range(3)]
        for r0 in range(0, y.shape[-2], PERTURBED_BLOCK_ROWS):
            rows = slice(r0, r0 + PERTURBED_BLOCK_ROWS)
            qa_c = (g[..., rows, :].conj() * y[..., rows, :]).to(torch.complex128)  # q·a
            qa = qa_c.imag
            rel_b = None if rel is None else rel[:, rows]
            if rel_b is None:
                q_re = qa_c.real
            else:
                q_re = qa_c.real / (1.0 + (sx * rel_b[1] + sy * rel_b[2] + dz * rel_b[0]))
            w = None if axial is None else _axial_frequency(fx, fy[rows], *axial)
            for k, (freq, chan) in enumerate(((fx[None, :], 1), (fy[rows, None], 2), (w, 0))):
                part = -_TWO_PI * (qa * freq).sum() if freq is not None else sums[k].new_zeros(())
                if rel_b is not None:
                    part = part + (q_re * rel_b[chan]).sum()
                sums[k] = sums[k] + part
        return sums


#: rows of the band per block of :meth:`_Perturbed._scalar_sums`
PERTURBED_BLOCK_ROWS = 64


def _dz_tensor(dz, device) -> torch.Tensor:
    """A scalar ``dz`` (mm) as a 0-d float64 tensor on ``device`` (keeps its graph)."""
    if not isinstance(dz, torch.Tensor):
        raise TypeError("dz must be a 0-d torch.Tensor (a zero-valued tensor that carries a derivative)")
    if dz.numel() != 1:
        raise ValueError(f"dz must be a scalar, got shape {tuple(dz.shape)}")
    if not math.isfinite(float(dz.detach())):
        raise ValueError(f"dz must be finite, got {float(dz.detach())}")
    return dz.to(device=device, dtype=torch.float64).reshape(())


def _axial_frequency(fx: torch.Tensor, fy: torch.Tensor, wavelength: float, n: float, carrier) -> torch.Tensor:
    """``w = sqrt((n/λ)² − |f + f_c|²)`` (cycles/mm) on the ``fftfreq`` grid ``fy[:, None], fx[None, :]`` of an
    envelope whose carrier ``f_c = n·carrier/λ`` was removed; 0 on evanescent components. λ in µm, f in 1/mm."""
    k = _positive(n, "n") / (_positive(wavelength, "wavelength") * _UM_TO_MM)
    ax, ay = _xy(carrier, "carrier")
    arg = k * k - (fx[None, :] + k * ax) ** 2 - (fy[:, None] + k * ay) ** 2
    ok = arg > 0
    return torch.where(ok, _sqrt_kz(arg, ok), torch.zeros((), dtype=arg.dtype, device=arg.device))
