"""Building sampled complex fields from ray data (pure functions, float64).

Two ways to turn rays into a field on a grid:

* :func:`splat_bilinear` spreads every ray's complex amplitude into its four neighbouring pixels (the
  method of the ray-wave paper). It averages *phasors*: where the phase changes across a pixel the
  amplitude drops, and with fewer rays than pixels the field is Monte-Carlo noise.
* :func:`upsample_nodes` interpolates *smooth real* quantities (optical path, amplitude, distance to a
  vignetting edge) from a coarse regular grid of exactly traced rays to the fine grid; the phase is formed
  only afterwards, so nothing aliases however coarse the ray grid is, as long as the quantities are smooth.

Arrays are indexed ``[iy, ix]``; lengths in mm.
"""

from __future__ import annotations

import torch

from raywave.utils import devices
from raywave.wave.propagation._common import fast_fft_size

__all__ = ["cubic_matrix", "cubic_matrices", "upsampled_intensity", "double_grid_intensity", "keys_matrix",
           "upsample_nodes", "upsample_nodes_window", "splat_bilinear", "edge_coverage", "fourier_upsample"]


def _keys(t: torch.Tensor) -> torch.Tensor:
    """Keys (1981) cubic convolution kernel with a = −1/2: reproduces quadratics exactly (3rd-order)."""
    t = t.abs()
    t2, t3 = t * t, t * t * t
    inner = 1.5 * t3 - 2.5 * t2 + 1.0
    outer = -0.5 * t3 + 2.5 * t2 - 4.0 * t + 2.0
    return torch.where(t <= 1, inner, torch.where(t < 2, outer, torch.zeros_like(t)))


def cubic_matrix(pos: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """Interpolation matrix ``(len(pos), n_nodes)`` from values at nodes 0..n_nodes−1 to the positions
    ``pos`` (in node units, within [0, n_nodes − 1]).

    Cubic convolution with a = −1/2; beyond the ends the node values are extrapolated quadratically
    (f₋₁ = 3f₀ − 3f₁ + f₂), which keeps the scheme exact for quadratics up to the boundary."""
    if n_nodes < 3:
        raise ValueError("need at least 3 nodes to interpolate")
    # one grid of :func:`cubic_matrices` (the same taps and ghost folding: one implementation for both)
    counts = torch.full((1, 1), float(n_nodes), dtype=pos.dtype, device=pos.device)
    return cubic_matrices(pos.reshape(1, -1), counts, n_nodes)[0]


def cubic_matrices(pos: torch.Tensor, n_nodes: torch.Tensor, k_max: int) -> torch.Tensor:
    """:func:`cubic_matrix` of B node grids at once, zero-padded to ``k_max`` columns: ``(B, N, k_max)`` from the
    positions ``pos`` (B, N) (node units, within [0, n_nodes − 1]) and the node counts ``n_nodes`` float64 (each ≥ 3,
    ≤ ``k_max``): (B, 1), one per grid, or (B, N), one per position (e.g. a grid's y and x positions in one call).
    Each row's first ``n_nodes`` columns equal :func:`cubic_matrix`'s bit for bit (the same taps, the same ghost
    folding in the same order); its columns beyond are 0."""
    b, n = pos.shape
    dev, dt = pos.device, pos.dtype
    base = torch.minimum(torch.floor(pos).clamp_min(0), n_nodes - 2)
    k = base[..., None] + torch.arange(-1, 3, dtype=dt, device=dev)  # (B, N, 4)
    m = torch.zeros((b, n, k_max + 2), dtype=dt, device=dev)  # columns: ghost, nodes..., ghost, padding
    m.scatter_add_(-1, (k + 1).long(), _keys(pos[..., None] - k))
    j = torch.arange(k_max, dtype=dt, device=dev)
    table = torch.tensor([0.0, 3.0, -3.0, 1.0, 0.0], dtype=dt, device=dev)

    def fold(d):  # 3, −3, 1 at d = 0, 1, 2, else 0 (d: whole numbers)
        return table[(d + 1).clamp(0, 4).long()]

    hi = m.gather(-1, (n_nodes + 1).long()[:, :, None].expand(b, n, 1))  # (B, N, 1): each row's high ghost
    out = m[..., 1:k_max + 1] + m[..., :1] * fold(j) + hi * fold(n_nodes[:, :, None] - 1 - j)
    return torch.where(j < n_nodes[:, :, None], out, torch.zeros_like(out))


def keys_matrix(n_nodes: int, stride: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """:func:`cubic_matrix` for nodes at every ``stride``-th fine sample: ``((n_nodes − 1)·stride + 1, n_nodes)``."""
    n_fine = (n_nodes - 1) * stride + 1
    return cubic_matrix(torch.arange(n_fine, dtype=dtype, device=device) / stride, n_nodes)


def upsample_nodes(values: torch.Tensor, stride: int | None = None, pos_y: torch.Tensor | None = None,
                   pos_x: torch.Tensor | None = None) -> torch.Tensor:
    """Interpolate ``(..., Ky, Kx)`` node values to a fine grid; differentiable.

    Either ``stride`` (nodes at every stride-th fine sample: output ``((Ky−1)·s+1, (Kx−1)·s+1)``) or the fine
    samples' positions ``pos_y`` (Ny,), ``pos_x`` (Nx,) in node units (any offset and spacing). Separable
    cubic convolution (:func:`cubic_matrix`), two small matrix products."""
    ky, kx = values.shape[-2:]
    if stride is not None:
        my = keys_matrix(ky, stride, values.dtype, values.device)
        mx = keys_matrix(kx, stride, values.dtype, values.device)
    else:
        my, mx = cubic_matrix(pos_y.to(values.dtype), ky), cubic_matrix(pos_x.to(values.dtype), kx)
    if devices.accelerator(values):  # an accelerator: two dense products (two kernels)
        return my @ values @ mx.T
    return _banded_upsample(values, my, mx)


#: fine samples per block of :func:`_banded_upsample` (a block's taps span about ``UPSAMPLE_BLOCK / stride + 3``
#: nodes)
UPSAMPLE_BLOCK = 64


def _row_spans(m: torch.Tensor, block: int) -> list[tuple[int, int, int, int]]:
    """The blocks ``(r0, r1, k0, k1)`` of ``block`` rows of the interpolation matrix ``m`` (n, K) with the half-open
    column span ``k0:k1`` holding every nonzero of their rows (one host read)."""
    nz = m.detach() != 0
    col = torch.arange(m.shape[1], device=m.device)
    lo = torch.where(nz, col, m.shape[1]).amin(1)
    hi = torch.where(nz, col, -1).amax(1) + 1
    starts = list(range(0, m.shape[0], block))
    bounds = torch.stack([torch.stack([lo[r:r + block].min(), hi[r:r + block].max()]) for r in starts]).tolist()
    return [(r, min(r + block, m.shape[0]), max(k0, 0), max(k1, k0, 0)) for r, (k0, k1) in zip(starts, bounds)]


def _banded_upsample(values: torch.Tensor, my: torch.Tensor, mx: torch.Tensor) -> torch.Tensor:
    """``my @ values @ mx.T`` for the cubic matrices ``my`` (Ny, Ky), ``mx`` (Nx, Kx) (four taps a row) on a CPU:
    block by block of :data:`UPSAMPLE_BLOCK` fine samples, each product over the nodes its rows touch only (the
    same sums of the same nonzero terms as the dense products, to rounding; ~3× faster for a 117² → 877 × 1106
    window: the dense products spend ~90 % of their work on zeros). First ``t = mx @ valuesᵀ`` (..., Nx, Ky) in
    blocks of x, then each block of y rows ``my[rows, span] @ t[..., span]ᵀ`` into its rows of the output. With
    autograd for the values (``my``, ``mx`` constants) :class:`_BandedUpsample`: the same forward
    operations (bit for bit: a replay compares the two), the backward the transposed banded products."""
    if torch.is_grad_enabled() and (my.requires_grad or mx.requires_grad):
        return my @ values @ mx.T  # differentiable positions (no caller in the engine): the dense products
    if torch.is_grad_enabled() and values.requires_grad:
        with torch.no_grad():
            out = _banded_values(values, my, mx)
        return _BandedUpsample.apply(values, my, mx, out)
    return _banded_values(values, my, mx)


def _banded_values(values: torch.Tensor, my: torch.Tensor, mx: torch.Tensor) -> torch.Tensor:
    """:func:`_banded_upsample`'s products without autograd: ``(..., Ny, Nx)``."""
    ky, kx = values.shape[-2:]
    lead = values.shape[:-2]
    v = values.reshape(-1, ky, kx)
    ny, nx = my.shape[0], mx.shape[0]
    xs, ys = _row_spans(mx, UPSAMPLE_BLOCK), _row_spans(my, UPSAMPLE_BLOCK)
    t = torch.empty((v.shape[0], nx, ky), dtype=v.dtype, device=v.device)
    for b in range(v.shape[0]):
        for x0, x1, k0, k1 in xs:
            torch.mm(mx[x0:x1, k0:k1], v[b, :, k0:k1].T, out=t[b, x0:x1])
    out = torch.empty((v.shape[0], ny, nx), dtype=v.dtype, device=v.device)
    for b in range(v.shape[0]):
        for y0, y1, k0, k1 in ys:
            torch.mm(my[y0:y1, k0:k1], t[b][:, k0:k1].T, out=out[b, y0:y1])
    return out.reshape(*lead, ny, nx)


def _banded_adjoint(g: torch.Tensor, my: torch.Tensor, mx: torch.Tensor, node_shape: tuple) -> torch.Tensor:
    """The adjoint of :func:`_banded_values`: ``myᵀ @ g @ mx`` (..., Ky, Kx) for ``g`` (..., Ny, Nx), block by block
    of fine samples (each block's products onto the node span its rows touch, added where spans overlap)."""
    lead = g.shape[:-2]
    return _banded_adjoints(list(g.reshape(-1, *g.shape[-2:]).unbind(0)), my, mx, node_shape).reshape(*lead,
                                                                                                      *node_shape)


def _banded_adjoints(gs: list, my: torch.Tensor, mx: torch.Tensor, node_shape: tuple) -> torch.Tensor:
    """:func:`_banded_adjoint` of the channels ``gs`` (each ``(Ny, Nx)``, or None: a zero gradient), without their
    stack: ``(len(gs), Ky, Kx)`` (the same products channel by channel)."""
    ky, kx = node_shape
    g0 = next(g for g in gs if g is not None)
    xs, ys = _row_spans(mx, UPSAMPLE_BLOCK), _row_spans(my, UPSAMPLE_BLOCK)
    out = torch.zeros((len(gs), ky, kx), dtype=g0.dtype, device=g0.device)
    s = torch.zeros((g0.shape[0], kx), dtype=g0.dtype, device=g0.device)
    for b, g in enumerate(gs):
        if g is None:
            continue
        if b:
            s.zero_()
        for x0, x1, k0, k1 in xs:  # s = g @ mx: (Ny, Kx)
            if k1 > k0:
                s[:, k0:k1].addmm_(g[:, x0:x1], mx[x0:x1, k0:k1])
        for y0, y1, k0, k1 in ys:  # out = myᵀ @ s: (Ky, Kx)
            if k1 > k0:
                out[b, k0:k1].addmm_(my[y0:y1, k0:k1].T, s[y0:y1])
    return out


class _BandedUpsample(torch.autograd.Function):
    """``my @ values @ mx.T`` (:func:`_banded_upsample`, or a window of it: ``my``, ``mx`` the window's rows) whose
    values ``out`` were computed without autograd (:func:`_banded_values`), differentiable in ``values`` (..., Ky,
    Kx) alone: the backward is :func:`_banded_adjoint` of the rows given (no per-block slices, products and
    concatenations in the graph, whose backward would add window-sized zero arrays per slice; no gradient array of
    a whole window for a crop of it)."""

    @staticmethod
    def forward(ctx, values, my, mx, out):
        ctx.save_for_backward(my, mx)
        ctx.kshape = values.shape
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        my, mx = ctx.saved_tensors
        return _banded_adjoint(g, my, mx, tuple(ctx.kshape[-2:])).reshape(ctx.kshape), None, None, None


class _BandedChannels(torch.autograd.Function):
    """:class:`_BandedUpsample` of channels ``values`` (C, Ky, Kx) returned as the C channel views of ``out`` (C, Ny,
    Nx) (one output each): the backward takes each channel's gradient where it is (:func:`_banded_adjoints`; a
    channel without one is skipped), where an unbind of one output would first stack the channels' gradients into a
    window-sized (C, Ny, Nx) array (issue 43). The same values and gradients bit for bit."""

    @staticmethod
    def forward(ctx, values, my, mx, out):
        ctx.save_for_backward(my, mx)
        ctx.kshape = values.shape
        ctx.set_materialize_grads(False)
        return out.unbind(0)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *gs):
        my, mx = ctx.saved_tensors
        if all(g is None for g in gs):
            return None, None, None, None
        return _banded_adjoints(list(gs), my, mx, tuple(ctx.kshape[-2:])), None, None, None


def upsample_nodes_window(values: torch.Tensor, pos_y: torch.Tensor, pos_x: torch.Tensor):
    """:func:`upsample_nodes` of ``values`` (..., Ky, Kx) at the positions ``pos_y`` (Ny,), ``pos_x`` (Nx,) for a
    caller that reads the values first and then keeps a window of them: ``(fine, window)``, ``fine`` (..., Ny, Nx)
    the values (detached) and ``window(box)`` the differentiable window ``box = (a0, a1, b0, b1)`` (half-open
    rows, columns) of them; ``window(box, split=True)`` (``values`` (C, Ky, Kx)) its C channels, as one unbind would
    give them. On a CPU with autograd the window's backward is the banded transpose of its own rows
    (:class:`_BandedUpsample`, :class:`_BandedChannels`; issue 46: the interpolation's backward through its blocks'
    slices and products, and the window's zero-padded gradient of the whole array, were a tenth of a mid-system DOE
    PSF's backward); the same values bit for bit (the products without autograd are those with it)."""
    grad = torch.is_grad_enabled() and values.requires_grad
    if not grad or devices.accelerator(values):
        fine = upsample_nodes(values, pos_y=pos_y, pos_x=pos_x)

        def plain(box, split=False):
            w = fine[..., box[0]:box[1], box[2]:box[3]]
            return w.unbind(0) if split else w

        return fine.detach(), plain
    ky, kx = values.shape[-2:]
    my, mx = cubic_matrix(pos_y.to(values.dtype), ky), cubic_matrix(pos_x.to(values.dtype), kx)
    with torch.no_grad():
        fine = _banded_upsample(values, my, mx)

    def window(box, split=False):
        a0, a1, b0, b1 = box
        fn = _BandedChannels if split else _BandedUpsample
        return fn.apply(values, my[a0:a1], mx[b0:b1], fine[..., a0:a1, b0:b1])

    return fine, window


def _roll_modulation(n: int, device) -> torch.Tensor:
    """``e^{2πi·(n//2)·k/n}`` (n,) complex128: multiplying a field by it rolls its spectrum by ``n//2``, so that
    the spectrum's indices ``0 … n−1`` hold the centred frequencies ``−n//2 … n − 1 − n//2`` in order."""
    k = torch.arange(n, dtype=torch.float64, device=device)
    return torch.polar(torch.ones(n, dtype=torch.float64, device=device), 2 * torch.pi * (n // 2) * k / n)


def _half_sample_ramp(n: int, device) -> torch.Tensor:
    """``e^{iπk/n}`` (n,) complex128: the spectrum's factor of a half-sample shift (:func:`_half_sample_shift`)."""
    k = torch.arange(n, dtype=torch.float64, device=device)
    return torch.polar(torch.ones(n, dtype=torch.float64, device=device), torch.pi * k / n)


#: :func:`_half_sample_shift` of ``n`` samples runs as a circular convolution through FFTs of a 5-smooth length
#: ``M ≥ 2n − 1`` when ``n`` has a prime factor above this: an FFT's pass for a prime factor ``p`` costs ~``n·p``
#: (issue 43: the PSF windows' 213 = 3·71 samples took 3.9× the time of 225 ones for an FFT pair, 12.9 against 7.1 ms
#: for the padded convolution on a batch's (4, 2, 213, 213) fields, 1 thread; the same shift to ~1e-15). CPU only
SHIFT_SMOOTH_PRIME = 7


def _largest_prime_factor(n: int) -> int:
    """The largest prime factor of ``n`` ≥ 1 (1 for 1)."""
    p, big = 2, 1
    while p * p <= n:
        while n % p == 0:
            n, big = n // p, p
        p += 1
    return max(big, n) if n > 1 else big


def _half_sample_shift(v: torch.Tensor, dim: int) -> torch.Tensor:
    """The band-limited interpolant of the rolled field ``v`` (see :func:`_roll_modulation`) half a sample along
    ``dim``: ``ifft(fft(v)·e^{iπk/n})`` — the odd samples of its 2× upsampling (the even ones are ``v``). For a length
    ``n`` with a large prime factor (:data:`SHIFT_SMOOTH_PRIME`) the same circular convolution with the kernel
    ``h = ifft(e^{iπk/n})`` through zero-padded FFTs of a smooth length ``M ≥ 2n − 1`` (the kernel's ``2n − 1`` taps
    ``h[(t) mod n]``, ``t = −(n−1) … n−1``: the linear convolution's samples ``n−1 … 2n−2`` are the circular one's,
    untouched by the wrap-around of length ``M``): the same values to rounding (~1e-15), a view of the padded result."""
    n = v.shape[dim]
    rows = dim in (-2, v.ndim - 2)
    ramp = _half_sample_ramp(n, v.device)
    if devices.accelerator(v) or _largest_prime_factor(n) <= SHIFT_SMOOTH_PRIME:  # (cuFFT: its own Bluestein)
        ramp = ramp.to(v.dtype)
        return torch.fft.ifft(torch.fft.fft(v, dim=dim) * (ramp[:, None] if rows else ramp), dim=dim)
    m = fast_fft_size(2 * n - 1)
    taps = torch.fft.ifft(ramp)[torch.arange(-(n - 1), n, device=v.device) % n]
    kernel = torch.fft.fft(taps, n=m).to(v.dtype)
    spec = torch.fft.fft(v, n=m, dim=dim)
    kernel = kernel[:, None] if rows else kernel
    if torch.is_grad_enabled() and spec.requires_grad:
        return torch.fft.ifft(spec * kernel, dim=dim).narrow(dim, n - 1, n)
    spec = spec.mul_(kernel)  # without autograd in place: one padded array (fewer fresh pages)
    return torch.fft.ifft(spec, dim=dim, out=spec).narrow(dim, n - 1, n)


def double_grid_intensity(u: torch.Tensor, window: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`upsampled_intensity` with ``factor`` 2, as its four interleaved sample sets: ``(..., 2, 2, Ny, Nx)``
    with ``[..., a, b, i, j]`` = output sample ``[2i + a, 2j + b]`` (the same values to rounding).

    The even samples of a 2× band-limited upsampling are the field itself, the odd ones a half-sample shift of
    it: four FFT passes of length ``N`` an axis instead of ``2N`` ones, arrays of the field's size (in cache)."""
    ny, nx = u.shape[-2:]
    mod = _roll_modulation(ny, u.device)[:, None] * _roll_modulation(nx, u.device)[None, :]
    if window is not None:
        mod = mod * window
    v = u * mod.to(u.dtype)
    xb = torch.stack([v, _half_sample_shift(v, -1)], dim=-3)  # (..., b, Ny, Nx): even, odd columns
    blocks = torch.stack([xb, _half_sample_shift(xb, -2)], dim=-4)  # (..., a, b, Ny, Nx)
    r = torch.view_as_real(blocks)
    if torch.is_grad_enabled() and blocks.requires_grad:
        return r[..., 0].square() + r[..., 1].square()
    out = r[..., 0].square()
    return out.add_(r[..., 1].square())


def splat_bilinear(x: torch.Tensor, y: torch.Tensor, values: torch.Tensor, origin, pitch: float, shape) -> torch.Tensor:
    """Sum ``values`` (N,) at points (x, y) (N,) mm into a grid ``shape = (ny, nx)`` with bilinear weights.

    Pixel ``[iy, ix]`` is centred at ``origin + (ix, iy)·pitch``. Points outside the grid are dropped.
    Differentiable with respect to ``values`` and the positions."""
    ny, nx = (int(s) for s in shape)
    fx = (x - origin[0]) / pitch
    fy = (y - origin[1]) / pitch
    ix0 = torch.floor(fx.detach())
    iy0 = torch.floor(fy.detach())
    wx1, wy1 = fx - ix0, fy - iy0
    wx0, wy0 = 1 - wx1, 1 - wy1
    out = torch.zeros(ny * nx, dtype=values.dtype, device=values.device)
    ix0, iy0 = ix0.long(), iy0.long()
    for dy, wy in ((0, wy0), (1, wy1)):
        for dx, wx in ((0, wx0), (1, wx1)):
            ix, iy = ix0 + dx, iy0 + dy
            ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
            idx = (iy * nx + ix)[ok]
            out = out.index_add(0, idx, (values * (wx * wy).to(values.dtype))[ok])
    return out.reshape(ny, nx)


def edge_coverage(distance: torch.Tensor, pitch: float) -> torch.Tensor:
    """Fraction of a pixel inside an edge from the signed distance (mm, > 0 inside) of its centre:
    ``clamp(0.5 + d/pitch, 0, 1)`` (exact for a straight edge along a pixel axis)."""
    return (0.5 + distance / pitch).clamp(0.0, 1.0)


def upsampled_intensity(u: torch.Tensor, factor: int, window: torch.Tensor | None = None) -> torch.Tensor:
    """The intensity of the band-limited (sinc) ``q``-times upsampled field ``u·window`` ``(..., Ny, Nx)`` →
    ``(..., q·Ny, q·Nx)`` (float; output sample ``[q·i, q·j]`` coincides with input ``[i, j]``; the window is
    treated as periodic: taper the field to ~0 at its edges). A field sampled at pitch p carries frequencies up
    to 1/(2p), so |u|² reaches 1/p: its intensity is only sampled correctly on the p/2 grid (q ≥ 2).
    Computed without building the centred padded spectrum.

    The spectrum is rolled by half its length through a modulation of the input (folded into ``window``)
    and zero-padded at its end by the inverse FFT itself; the output is then the upsampled field times a
    linear phase, which the modulus removes."""
    q = int(factor)
    ny, nx = u.shape[-2:]
    mod = _roll_modulation(ny, u.device)[:, None] * _roll_modulation(nx, u.device)[None, :] * float(q * q)
    if window is not None:
        mod = mod * window
    spec = torch.fft.fft2(u * mod.to(u.dtype))
    # ifft2(spec, s=(q·Ny, q·Nx)) one axis at a time: the first pass transforms only the Ny rows of the spectrum
    # (the zero padding's rows stay zero through it)
    up = torch.fft.ifft(torch.fft.ifft(spec, n=q * nx, dim=-1), n=q * ny, dim=-2)
    del spec
    r = torch.view_as_real(up)
    if torch.is_grad_enabled() and up.requires_grad:
        return r[..., 0].square() + r[..., 1].square()
    out = r[..., 0].square()  # without autograd: one array less at the peak (the same sums)
    return out.add_(r[..., 1].square())


def fourier_upsample(u: torch.Tensor, factor: int) -> torch.Tensor:
    """The band-limited (periodic sinc) interpolation of the complex field ``u`` ``(..., ny, nx)`` on a grid
    ``factor`` times finer: ``(..., factor·ny, factor·nx)``, output sample ``[f·i, f·j]`` = input ``[i, j]``
    (exact for a field whose spectrum lies within the input grid's band; the window is periodic: taper the field
    to ~0 at its edges): the inverse FFT of the spectrum zero-padded to ``factor`` times its length (an even length's
    Nyquist term split in halves), computed as ``factor`` shifted copies per axis. Differentiable."""
    f = int(factor)
    if f < 1:
        raise ValueError(f"fourier_upsample: factor must be a positive integer, got {factor}")
    if f == 1:
        return u
    # one axis at a time, as f interleaved sample sets of the input's size: set r is the input shifted by r/f of a
    # sample (its spectrum times a phase ramp, the FFTs of the input's length), set 0 the input itself (issue 46:
    # the padded spectrum's inverse FFT of f× the length, e.g. 1006 = 2·503 for a 503-sample window, took 2× as
    # long; the same interpolant to rounding)
    return _upsampled_axis(_upsampled_axis(u, f, -1), f, -2)


def _shift_ramps(n: int, f: int, dtype, device) -> torch.Tensor:
    """(f − 1, n): the spectrum's factors of the shifts by r/f of a sample (r = 1 … f − 1) of the band-limited
    interpolant of :func:`fourier_upsample` on ``n`` samples: ``exp(2πi k r/(f n))`` at the centred frequency k, and
    at the Nyquist frequency of an even ``n`` (split in halves at ±n/2 by the interpolant) ``cos(π r/f)``."""
    k = torch.fft.fftfreq(n, d=1.0 / n, dtype=torch.float64, device=device)  # centred frequencies (Nyquist: −n/2)
    r = torch.arange(1, f, dtype=torch.float64, device=device)[:, None]
    ramps = torch.polar(torch.ones((f - 1, n), dtype=torch.float64, device=device), 2 * torch.pi * k * r / (f * n))
    if n % 2 == 0:
        ramps[:, n // 2] = torch.cos(torch.pi * r[:, 0] / f).to(ramps.dtype)
    return ramps.to(dtype)


def _upsampled_axis(u: torch.Tensor, f: int, dim: int) -> torch.Tensor:
    """:func:`fourier_upsample` of ``u`` along ``dim`` (−1 or −2) alone: ``f·n`` samples, sample ``f·i + r`` the
    interpolant at ``i + r/f`` (``r = 0``: ``u`` itself)."""
    n = u.shape[dim]
    spec = torch.fft.fft(u, dim=dim)
    ramps = _shift_ramps(n, f, spec.dtype, u.device)
    if dim == -2:
        ramps = ramps[:, :, None]
    sets = [u] + [torch.fft.ifft(spec * ramps[r], dim=dim) for r in range(f - 1)]
    out = torch.stack(sets, dim=dim)  # (..., n, f, m) along the rows, (..., m, n, f) along the columns
    shape = list(u.shape)
    shape[dim] = f * n
    return out.reshape(shape)
