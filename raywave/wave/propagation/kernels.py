"""The transfer function of a window pair as one compiled loop (:func:`raywave.utils.fused.fused`, issue 43), and
:class:`TransferBand`: a source's transfer function on its band, evaluated block by block where the band
convolution multiplies it (:func:`~raywave.wave.propagation.band.convolve_band`) instead of as a band-sized array.

The function is that of :func:`~raywave.wave.propagation.transfer.window_transfer` (its docstring): on the
frequencies ``f`` (cycles/mm, the envelope's, carrier removed) ``G = W · exp(2πi (z·w + f_x d_x + f_y d_y))`` with
``w = sqrt(k² − |f + f_c|²)``, ``W`` 0 where evanescent and otherwise the product of the quintic roll-offs of the
lateral shifts ``Δ = z (f + f_c)/w`` per axis beyond their bands. One loop evaluates ``w``, both roll-offs, the
phase and its ``cos``/``sin`` per sample (the eager chain: ~20 passes over band-sized arrays, the roll-off restricted
to the lines where it can act; here every sample runs the roll-off, whose factor is exactly 1 inside the band).
Values to rounding of the eager chain's (a few ulp of the phase, ~1e4 rad: ~1e-12 of |G|; the phase is reduced to
one cycle before its ``cos``/``sin``, which makes them 1.5× faster).

Lengths mm, frequencies cycles/mm, float64.
"""

from __future__ import annotations

import math

import torch

from raywave.utils.fused import fused

__all__ = ["BandView", "SharedBand", "TransferBand", "adjoint_terms", "band_values", "roll_off_terms", "transfer_params",
           "transfer_values"]

_TWO_PI = 2.0 * math.pi
#: the layout of a source's parameter vector (:func:`transfer_params`): n/λ, z, the carrier's frequency (k·α, k·β),
#: the output-to-input window shift (dx, dy), and per axis the band of Δ as (middle, half width, roll-off width)
PARAMS = ("k", "z", "kax", "kay", "dx", "dy", "x_mid", "x_half", "x_taper", "y_mid", "y_half", "y_taper")


def transfer_params(geo) -> list[float]:
    """The parameter vector (:data:`PARAMS`, host floats) of a checked geometry ``geo``
    (:func:`~raywave.wave.propagation.transfer._geometry`). Every roll-off width must be > 0 (the sharp band limit
    has no loop here)."""
    k, (ax, ay), (dx, dy) = geo.k, geo.carrier, geo.shift
    (xl, xh, xt), (yl, yh, yt) = geo.bx, geo.by
    return [k, geo.zf, k * ax, k * ay, dx, dy, 0.5 * (xl + xh), 0.5 * (xh - xl), xt, 0.5 * (yl + yh),
            0.5 * (yh - yl), yt]


def _parts(fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor):
    """``(Re G, Im G)`` on ``fx``, ``fy`` (broadcast against each other and against ``p``'s leading axes; ``p``
    ``(..., 12)`` the :data:`PARAMS`), float64. The operations of the eager
    :func:`~raywave.wave.propagation.batch._band_values`, in its order."""
    k, z, kax, kay, dx, dy, xm, xh, xt, ym, yh, yt = p.unbind(-1)
    gx, gy = fx + kax, fy + kay  # physical frequencies
    arg = (k * k - gy * gy) - gx * gx
    prop = arg > 0
    w = torch.where(prop, arg, 1.0).sqrt()  # (n/λ)·cosθ; 1 on evanescent samples
    weight = prop.to(arg.dtype)  # evanescent: exactly 0
    inv_w = 1.0 / w
    for g, mid, half, taper in ((gx, xm, xh, xt), (gy, ym, yh, yt)):
        # how far Δ lies outside its band (0 inside), over the roll-off width, and the smoothstep S(t): W ← W − W·S
        t = (((z * g) * inv_w - mid).abs() - half).clamp_min(0.0).div(taper).clamp_max(1.0)
        s = t * t * t * (10.0 + t * (6.0 * t - 15.0))
        weight = weight - s * weight
    # the phase in cycles, reduced to [−½, ½] before the 2π: the vector cos/sin then skip their slow argument
    # reduction (phases of ~1e4 rad: 1.5× less time for the loop; the same rounding, ~1e-12 cycles)
    cycles = w * z + (fx * dx + fy * dy)
    phase = (cycles - torch.round(cycles)) * _TWO_PI
    return torch.cos(phase) * weight, torch.sin(phase) * weight


def _values(fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    re, im = _parts(fx, fy, p)
    return torch.stack([re, im], -1)


#: ``G`` on ``fx``, ``fy`` for the parameters ``p`` (:func:`_parts`'s broadcasting) as a stacked ``(..., 2)`` float64
#: tensor (:func:`torch.view_as_complex` gives complex128): one compiled loop
transfer_values = fused(_values)


def _adjoint_terms(gs: torch.Tensor, su: torch.Tensor, fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor):
    """The band convolution's backward on a block of one source's band, with ``G`` and the roll-off weights'
    derivatives evaluated in the loop: ``gs`` the output gradient's band spectrum and ``su`` the input's (stacked
    ``(c, R, 2)``, transposed columns), ``fx`` ``(c, 1)``, ``fy`` ``(R,)``, ``p`` ``(12,)``. Returns ``gs·conj(G)``
    (the input gradient's band spectrum) as its real and imaginary planes ``(c, R)`` and, per column ``(c,)``, the
    window shift's and the distance's gradient terms ``Σ_rows (−2π Im q·∂φ/∂s + Re q·∂ log W/∂s)`` for ``s`` =
    ``(s_x, s_y, z)`` with ``q = conj(gs·conj(su))·G`` (``∂φ/∂s`` = ``f_x``, ``f_y``, ``w``; the gradients of
    :class:`~raywave.wave.propagation.batch._Perturbed` at a zero perturbation, whose roll-off derivatives are those
    of :func:`_roll_off_terms`), float64."""
    k, z, kax, kay, dx, dy, xm, xh, xt, ym, yh, yt = p.unbind(-1)
    gx, gy = fx + kax, fy + kay
    arg = (k * k - gy * gy) - gx * gx
    prop = arg > 0
    w = torch.where(prop, arg, 1.0).sqrt()
    weight = prop.to(arg.dtype)
    inv_w = 1.0 / w
    dlogs = []
    for g, mid, half, taper in ((gx, xm, xh, xt), (gy, ym, yh, yt)):
        shift = (z * g) * inv_w
        sgn = torch.sign(shift - mid)
        dist = ((shift - mid).abs() - half).clamp_min(0.0)
        t = (dist / taper).clamp_max(1.0)
        s = t * t * t * (10.0 + t * (6.0 * t - 15.0))
        weight = weight - s * weight
        ramp = (dist > 0) & (dist < taper)
        dlog = torch.where(t < 1, -30.0 * t * t / ((1.0 - t) * (1.0 + t * (3.0 + 6.0 * t))).clamp_min(1e-300), 0.0)
        dlogs.append((torch.where(ramp, dlog * ((sgn * shift / z - dist / (2.0 * z)) / taper), 0.0),
                      torch.where(ramp, dlog * (-sgn / taper), 0.0)))
    cycles = w * z + (fx * dx + fy * dy)
    phase = (cycles - torch.round(cycles)) * _TWO_PI
    hr, hi = torch.cos(phase) * weight, torch.sin(phase) * weight
    a, b = gs[..., 0].to(hr.dtype), gs[..., 1].to(hr.dtype)
    c, d = su[..., 0].to(hr.dtype), su[..., 1].to(hr.dtype)
    ghr, ghi = a * c + b * d, b * c - a * d  # gs·conj(su): the transfer function's gradient
    qa, q_re = ghr * hi - ghi * hr, ghr * hr + ghi * hi
    (fz_x, fs_x), (fz_y, fs_y) = dlogs
    g_sx = (q_re * fs_x - _TWO_PI * (qa * fx)).sum(-1)
    g_sy = (q_re * fs_y - _TWO_PI * (qa * fy)).sum(-1)
    g_dz = (q_re * (fz_x + fz_y) - _TWO_PI * (qa * w)).sum(-1)
    return (a * hr + b * hi).to(gs.dtype), (b * hr - a * hi).to(gs.dtype), g_sx, g_sy, g_dz


#: :func:`_adjoint_terms` as one compiled loop
adjoint_terms = fused(_adjoint_terms)


def _roll_off_terms(g: torch.Tensor, g_other: torch.Tensor, k: torch.Tensor, z: torch.Tensor, band: torch.Tensor):
    """The roll-off weight's relative derivatives ``(∂ log W/∂z, ∂ log W/∂s)`` of one axis on lines of the band:
    ``g`` that axis's physical frequencies and ``g_other`` the other's (cycles/mm, broadcast to the lines' shape),
    ``k`` = n/λ, ``z`` (mm, non-zero) and ``band`` ``(..., 3)`` = ``(lo, hi, roll-off width)`` of the lateral shift
    (mm), each broadcast per source. Stacked ``(..., 2)`` float64: the operations of the eager
    :func:`~raywave.wave.propagation.transfer._roll_off`, in its order."""
    lo, hi, taper = band.unbind(-1)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    arg = (k * k - g_other * g_other) - g * g
    shift = (z * g) * (1.0 / torch.where(arg > 0, arg, 1.0).sqrt())
    sgn = torch.sign(shift - mid)
    dshift = sgn * shift / z  # Δ ∝ z
    dist = ((shift - mid).abs() - half).clamp_min(0.0)
    ramp = (dist > 0) & (dist < taper)
    dt_z = torch.where(ramp, (dshift - dist / (2.0 * z)) / taper, 0.0)  # T ∝ sqrt|z|
    dt_s = torch.where(ramp, -sgn / taper, 0.0)  # the band moves with the window
    t = (dist / taper).clamp_max(1.0)
    # d(log(1 − S))/dt, S' = 30 t²(1 − t)², 1 − S = (1 − t)³(1 + 3t + 6t²): finite up to t = 1
    dlog = torch.where(t < 1, -30.0 * t * t / ((1.0 - t) * (1.0 + t * (3.0 + 6.0 * t))).clamp_min(1e-300), 0.0)
    return torch.stack([dlog * dt_z, dlog * dt_s], -1)


_roll_off_flat = fused(_roll_off_terms)


def roll_off_terms(g: torch.Tensor, g_other: torch.Tensor, k: torch.Tensor, z: torch.Tensor,
                   band: torch.Tensor) -> torch.Tensor:
    """:func:`_roll_off_terms` in one compiled loop, ``(*shape, 2)`` for the broadcast ``shape`` of its arguments
    (``band`` broadcast with its last axis dropped). The arguments are expanded into flat arrays of one length (a
    run of roll-off lines is a sliver of the band: a few copies), so that one compiled graph serves every source
    count, run width and axis (a size-1 axis that broadcasts would otherwise compile a graph of its own)."""
    shape = torch.broadcast_shapes(g.shape, g_other.shape, k.shape, z.shape, band.shape[:-1])
    n = math.prod(shape)
    flat = [t.expand(shape).reshape(-1) for t in (g, g_other, k, z)]
    lo_hi = band.expand(*shape, 3).reshape(-1, 3)
    if n == 1:  # (a length-1 array compiles a graph of its own: one sample twice, the same values)
        flat, lo_hi = [t.repeat(2) for t in flat], lo_hi.repeat(2, 1)
    return _roll_off_flat(*flat, lo_hi)[:n].reshape(*shape, 2)


class TransferBand:
    """One source's transfer function on its band ``fy × fx`` (its rows' ``fy`` ``(R,)`` and columns' ``fx`` ``(C,)``
    frequencies, cycles/mm; ``p`` ``(12,)`` float64 its :data:`PARAMS`), evaluated on demand: :meth:`block` the
    transposed columns ``c0:c1`` (what the band convolution multiplies a block of its spectrum by), :meth:`full` the
    whole ``(R, C)`` band. The band-sized complex array exists only where :meth:`full` is asked for."""

    __slots__ = ("fx", "fy", "p")

    def __init__(self, fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor):
        self.fx, self.fy, self.p = fx, fy, p

    @property
    def shape(self) -> tuple[int, int]:
        """``(R, C)``."""
        return (self.fy.numel(), self.fx.numel())

    @property
    def device(self) -> torch.device:
        return self.p.device

    def block(self, c0: int, c1: int, dtype=torch.complex128) -> torch.Tensor:
        """``G`` on the columns ``c0:c1``, transposed: ``(c1 − c0, R)`` of ``dtype``."""
        fx, fy = _two(self.fx[c0:c1].clone()), _two(self.fy)  # (a view: a compiled loop guards on its base)
        g = torch.view_as_complex(transfer_values(fx[:, None], fy, self.p))[:c1 - c0, :self.fy.numel()]
        return g if g.dtype == dtype else g.to(dtype)

    def full(self, dtype=torch.complex128) -> torch.Tensor:
        """``G`` on the band: ``(R, C)`` of ``dtype``."""
        return band_values(self.fx, self.fy, self.p, dtype)


class SharedBand:
    """A transfer function evaluated once on a set of frequency lines, ``fx`` ``(C,)`` × ``fy`` ``(R,)`` (cycles/mm;
    ``p`` ``(12,)`` its :data:`PARAMS`), for several sources whose bands are among those lines (:class:`BandView`:
    the mirror images of one source propagated in its frame, :mod:`raywave.hybrid.mirror`). Evaluated on first use
    as one ``(C, R)`` complex128 array (the transposed columns :class:`TransferBand` gives), then read by slices."""

    __slots__ = ("fx", "fy", "p", "_t")

    def __init__(self, fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor):
        self.fx, self.fy, self.p, self._t = fx, fy, p, None

    def columns(self) -> torch.Tensor:
        """``G`` on every line, transposed: ``(C, R)`` complex128 (evaluated once)."""
        if self._t is None:
            self._t = TransferBand(self.fx, self.fy, self.p).block(0, self.fx.numel())
        return self._t


def _run(pos: list, a: int, b: int):
    """``(start, stop)`` where the positions ``pos[a:b]`` are consecutive ascending integers, else None."""
    return (pos[a], pos[b - 1] + 1) if b > a and pos[b - 1] - pos[a] == b - a - 1 else None


class BandView:
    """One source's band read from a :class:`SharedBand`: its columns and rows at the positions ``cols`` ``(C_i,)``
    and ``rows`` ``(R_i,)`` (host lists of ints, ascending where they are runs) among the shared lines; the
    interface of :class:`TransferBand` that the band convolution uses (:meth:`block`, :meth:`full`, :attr:`shape`).
    A block is a view of the shared array where its positions are runs, else a gathered copy."""

    __slots__ = ("shared", "cols", "rows", "_row_run")

    def __init__(self, shared: SharedBand, cols: list, rows: list):
        self.shared, self.cols, self.rows = shared, list(cols), list(rows)
        self._row_run = _run(self.rows, 0, len(self.rows))

    @property
    def shape(self) -> tuple[int, int]:
        """``(R_i, C_i)``."""
        return (len(self.rows), len(self.cols))

    @property
    def device(self) -> torch.device:
        return self.shared.p.device

    def block(self, c0: int, c1: int, dtype=torch.complex128) -> torch.Tensor:
        """``G`` on the columns ``c0:c1``, transposed: ``(c1 − c0, R_i)`` of ``dtype``."""
        t = self.shared.columns()
        run = _run(self.cols, c0, c1)
        g = t[run[0]:run[1]] if run else t.index_select(0, torch.tensor(self.cols[c0:c1], device=t.device))
        if self._row_run:
            g = g[:, self._row_run[0]:self._row_run[1]]
        else:
            g = g.index_select(1, torch.tensor(self.rows, device=t.device))
        return g if g.dtype == dtype else g.to(dtype)

    def full(self, dtype=torch.complex128) -> torch.Tensor:
        """``G`` on the band: ``(R_i, C_i)`` of ``dtype``."""
        return self.block(0, len(self.cols), dtype).transpose(0, 1).contiguous()


def band_values(fx: torch.Tensor, fy: torch.Tensor, p: torch.Tensor, dtype=torch.complex128) -> torch.Tensor:
    """``G`` on the band ``fy[:, None], fx`` (``(R,)``, ``(C,)`` cycles/mm) of the sources ``p`` (``(12,)``: ``(R,
    C)``; ``(B, 12)``: ``(B, R, C)``), in one compiled loop, as ``dtype``."""
    r, c = fy.numel(), fx.numel()
    pp = p if p.ndim == 1 else _two(p)[:, None, None, :]
    g = torch.view_as_complex(transfer_values(_two(fx), _two(fy)[:, None], pp))[..., :r, :c]
    if p.ndim > 1:
        g = g[:p.shape[0]]
    return g if g.dtype == dtype else g.to(dtype)


def _two(v: torch.Tensor) -> torch.Tensor:
    """``v`` with its first axis at least 2 long (a single entry repeated): a compiled loop's size-1 axis would
    compile a graph of its own (the values do not depend on the position)."""
    return v if v.shape[0] != 1 else v.repeat(2, *([1] * (v.ndim - 1)))
