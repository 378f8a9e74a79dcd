"""Energy-conserving resampling of intensity maps to sensor pixels (exact area overlaps or a cubic kernel)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from raywave.wave.propagation._common import _pair, _positive, _xy


def _overlap_matrix(n_in, p_in, o_in, n_out, p_out, o_out, dtype, device) -> torch.Tensor:
    """(n_out, n_in) overlap lengths (mm) of 1-D pixel intervals; rows telescope (column sums = p_in)."""
    e_in = o_in + p_in * (torch.arange(n_in + 1, dtype=torch.float64, device=device) - 0.5)
    e_out = o_out + p_out * (torch.arange(n_out + 1, dtype=torch.float64, device=device) - 0.5)
    lo, hi = e_in[:-1][None, :], e_in[1:][None, :]
    c = torch.minimum(torch.maximum(e_out[:, None], lo), hi)  # (n_out+1, n_in) clipped output edges
    return (c[1:] - c[:-1]).to(dtype)


def _keys_antiderivative(t: torch.Tensor) -> torch.Tensor:
    """∫₀ᵗ of the Keys (a = −½) cubic kernel: odd, → ±½ beyond |t| = 2."""
    a = t.abs().clamp(max=2.0)
    inner = a * (1.0 + a * a * (-2.5 / 3.0 + 0.375 * a))
    b = a.clamp(min=1.0)
    k1 = 0.375 - 2.5 / 3.0 + 1.0
    outer = k1 + (b * (2.0 + b * (-2.0 + b * (2.5 / 3.0 - 0.125 * b)))) - (2.0 - 2.0 + 2.5 / 3.0 - 0.125)
    return torch.sign(t) * torch.where(a <= 1.0, inner, outer)


def _cubic_overlap_matrix(n_in, p_in, o_in, n_out, p_out, o_out, dtype, device) -> torch.Tensor:
    """(n_out, n_in) integrals over the output pixels of the input samples' cubic cardinal functions."""
    x_in = o_in + p_in * torch.arange(n_in, dtype=torch.float64, device=device)
    e_out = o_out + p_out * (torch.arange(n_out + 1, dtype=torch.float64, device=device) - 0.5)
    k = _keys_antiderivative((e_out[:, None] - x_in[None, :]) / p_in) * p_in  # (n_out+1, n_in)
    return (k[1:] - k[:-1]).to(dtype)


def _pitches(in_pitch, out_pitch) -> tuple[tuple[float, float], tuple[float, float]]:
    """The checked ``((px, py), (px, py))`` (mm, all > 0) of the input and output pixels."""
    ipx, ipy = _pair(in_pitch, "in_pitch")
    opx, opy = _pair(out_pitch, "out_pitch")
    for v in (ipx, ipy, opx, opy):
        _positive(v, "pitch")
    return (ipx, ipy), (opx, opy)


def _out_origin(out_origin):
    """``(x0, y0)`` mm of the output pixel (0, 0): floats, or 0-d float64 tensors of an ``out_origin`` ``(2,)``
    tensor that requires grad."""
    if isinstance(out_origin, torch.Tensor) and out_origin.requires_grad:
        # keep the output origin in the graph: d(out)/d(origin) is the exact derivative of the overlaps
        # (the intensity at the moving pixel edges), so a PSF crop that follows a chief ray differentiates
        return out_origin.reshape(2).to(torch.float64).unbind()
    return _xy(out_origin, "out_origin")


def _weights(kernel: str, x_axis, y_axis, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The float64 weights ``(W_x, W_y)``, ``(Nx_out, Nx_in)`` and ``(Ny_out, Ny_in)`` (overlaps in mm) of
    ``kernel``; each axis is ``(n_in, p_in, o_in, n_out, p_out, o_out)`` (pitches and origins in mm)."""
    if kernel == "box":
        wx = _overlap_matrix(*x_axis, torch.float64, device)
        wy = _overlap_matrix(*y_axis, torch.float64, device)
    elif kernel == "cubic":
        wx = _cubic_overlap_matrix(*x_axis, torch.float64, device)
        wy = _cubic_overlap_matrix(*y_axis, torch.float64, device)
    else:
        raise ValueError(f"kernel must be 'box' or 'cubic', got {kernel!r}")
    return wx, wy


def _scaled(mode: str, wx, wy, in_pitch, out_pitch) -> tuple[torch.Tensor, torch.Tensor]:
    """The weights ``(W_x, W_y)`` of :func:`_weights` (mm) for ``mode``: unchanged for ``"integral"``, divided by
    the input pitch for ``"sum"``, by the output pitch for ``"mean"`` (``in_pitch``, ``out_pitch``: ``(px, py)``
    mm)."""
    if mode == "integral":
        pass
    elif mode == "sum":
        wx, wy = wx / in_pitch[0], wy / in_pitch[1]
    elif mode == "mean":
        wx, wy = wx / out_pitch[0], wy / out_pitch[1]
    else:
        raise ValueError(f"mode must be 'integral', 'sum' or 'mean', got {mode!r}")
    return wx, wy


def pixel_integrate(
    intensity: torch.Tensor,
    in_pitch,
    out_pitch,
    in_origin,
    out_origin,
    out_shape: Sequence[int],
    mode: str = "integral",
    kernel: str = "box",
) -> torch.Tensor:
    """Resample an intensity map onto (larger or smaller) sensor pixels by exact area overlap.

    The input is taken as piecewise constant over its pixels (pixel ``[iy, ix]`` covers
    ``x0 + (ix ± ½)·px``, same in y); each output pixel ``[jy, jx]`` (centred at
    ``out_origin + (jx, jy)·out_pitch``) receives the overlap-weighted input. The weights are separable:
    ``out = W_y · I · W_xᵀ`` with two small dense matrices, so the cost is O(N_out·N_in) per axis.

    Args:
        intensity: real ``(..., Ny, Nx)``.
        in_pitch, out_pitch: mm (float or ``(px, py)``); any ratio (non-integer allowed).
        in_origin, out_origin: ``(x0, y0)`` mm of the centres of the respective pixels (0, 0); a
            ``out_origin`` tensor that requires grad stays differentiable.
        out_shape: ``(Ny_out, Nx_out)``.
        kernel: how the input varies between its samples: ``"box"`` (default) piecewise constant over its
            pixels (exact overlaps, never negative); ``"cubic"``: the samples are point values of a smooth
            irradiance, integrated through their cubic-convolution interpolant (exact for quadratics, so a
            sampled PSF integrates correctly whatever the alignment of the two grids; may dip below 0 by
            round-off-size amounts where the irradiance is ~0).
        mode: ``"integral"`` (default): input is irradiance, output is the irradiance integrated over each
            output pixel (energy per pixel, ``Σ out = Σ I·p_in²`` over the common area); ``"sum"``: input is
            energy per input pixel, output energy per output pixel (``Σ out = Σ in``; block sums for integer
            ratios); ``"mean"``: output is the mean irradiance over each output pixel.

    Returns:
        ``(..., Ny_out, Nx_out)`` in the dtype of ``intensity``; differentiable w.r.t. it.
    """
    if intensity.is_complex():
        raise TypeError("pixel_integrate expects a real intensity map")
    if intensity.ndim < 2:
        raise ValueError("expected shape (..., Ny, Nx)")
    (ipx, ipy), (opx, opy) = _pitches(in_pitch, out_pitch)
    xi0, yi0 = _xy(in_origin, "in_origin")
    xo0, yo0 = _out_origin(out_origin)
    noy, nox = (int(s) for s in out_shape)
    niy, nix = intensity.shape[-2:]
    if not intensity.is_floating_point():
        intensity = intensity.to(torch.float64)
    dt, dev = intensity.dtype, intensity.device
    wx, wy = _weights(kernel, (nix, ipx, xi0, nox, opx, xo0), (niy, ipy, yi0, noy, opy, yo0), dev)
    wx, wy = _scaled(mode, wx, wy, (ipx, ipy), (opx, opy))
    return wy.to(dt) @ (intensity @ wx.to(dt).transpose(0, 1))


def _through_double_grid(w: torch.Tensor, n: int, q: int) -> torch.Tensor:
    """Weights ``(K, 2n)`` on the intensity's samples at ``p/2`` that give what ``w`` ``(K, q·n)`` gives on its
    samples at ``p/q`` (the same origin; sample ``[q·i]`` resp. ``[2·i]`` on the field's ``[i]``), for the intensity
    of a field of ``n`` samples a period: a trigonometric polynomial with the frequencies ``|m| ≤ n − 1`` (cycles
    a period), which its ``2n`` samples hold exactly. ``A[a, i] = Σ_j w[a, j]·D(j/(q n) − i/(2n))`` with the
    Dirichlet kernel ``D(t) = (1/2n)·Σ_{|m|<n} e^{2πimt}``: the sum over ``j`` is a DFT of ``w``'s rows at the
    frequencies ``m``, the sum over ``m`` a DFT of length ``2n``. ``w`` is real, so both are real-input/output
    transforms: ``F = rfft(w)`` holds the ``m ≥ 0`` half (the ``m < 0`` half is its conjugate) and ``A =
    irfft(F[:n], 2n)`` (half the work of the complex pair; the same values to rounding). Differentiable in ``w``."""
    spec = torch.fft.rfft(w.to(torch.float64), dim=-1)[..., :n]  # Σ_j w[a, j]·e^{−2πi m j/(q n)}, 0 ≤ m < n
    nyquist = torch.zeros((*w.shape[:-1], 1), dtype=spec.dtype, device=w.device)  # |m| = n: not in the intensity
    return torch.fft.irfft(torch.cat([spec, nyquist], dim=-1), n=2 * n, dim=-1)


#: ``integrated_upsampled_intensity(refine=True)``: the change (sum |P_2q − P_q|, each normalised to sum 1) of a
#: pixel integral when ``q`` is doubled above which the doubled one is used (measured: the F/1.3 asphere at its 0.56 µm
#: Nyquist pixels, 4 → 8 changes it by 1.5e-3, and takes it from 1.6e-3 to 1.2e-4 of the converged Huygens PSF; the
#: bundled asphere at 3 µm pixels by ~1e-5)
REFINE_TOL = 2e-4


def upsampled_pixel_weights(shape, q: int, in_pitch, in_origin, out_pitch, out_origin, out_shape: Sequence[int],
                            device=None, refine: bool = False) -> tuple:
    """The weights of :func:`integrated_upsampled_intensity` for fields of ``shape`` ``(Ny, Nx)`` (the other
    arguments as there): one ``(W_y0, W_y1, W_x0, W_x1)`` float64 quadruple for ``q`` (and one for ``2q`` with
    ``refine``), each ``W`` on one of the ``2N`` grid's interleaved sample sets. They depend on the geometry alone
    (host numbers; ``out_origin`` a tensor that requires grad keeps them differentiable), so a caller that
    integrates many batches of one geometry builds them once (issue 43: the pixel integration's weights once per
    geometry, not once per batch) and passes them as ``weights``."""
    q = int(q)
    if q < 2:
        raise ValueError(f"q must be >= 2 (|u|² has twice the field's bandwidth), got {q}")
    ny, nx = (int(v) for v in shape)
    (ipx, ipy), (opx, opy) = _pitches(in_pitch, out_pitch)
    xi0, yi0 = _xy(in_origin, "in_origin")
    xo0, yo0 = _out_origin(out_origin)
    noy, nox = (int(s) for s in out_shape)

    def one(qq: int) -> tuple:
        wx, wy = _weights("cubic", (qq * nx, ipx / qq, xi0, nox, opx, xo0), (qq * ny, ipy / qq, yi0, noy, opy, yo0),
                          device)
        if qq != 2:
            wx, wy = _through_double_grid(wx, nx, qq), _through_double_grid(wy, ny, qq)
        return wy[:, 0::2], wy[:, 1::2], wx[:, 0::2], wx[:, 1::2]

    return (one(q), one(2 * q)) if refine else (one(q),)


def integrated_upsampled_intensity(u: torch.Tensor, q: int, in_pitch: float, in_origin, out_pitch: float, out_origin,
                                   out_shape: Sequence[int], window: torch.Tensor | None = None,
                                   refine: bool = False, weights: tuple | None = None) -> torch.Tensor:
    """The irradiance ``|u|²`` of a band-limited field, Fourier-interpolated ``q``-fold and integrated over
    sensor pixels through the cubic interpolant of those samples: ``pixel_integrate(upsampled_intensity(u, q,
    window), in_pitch/q, out_pitch, in_origin, out_origin, out_shape, kernel="cubic")`` up to round-off, at the
    cost of the ``q = 2`` grid.

    ``|u|²`` of a field of ``N`` samples a period holds the frequencies ``|m| ≤ N − 1``, so its ``2N`` samples
    determine its ``q·N`` ones exactly (trigonometric interpolation, linear): the cubic pixel weights on the
    ``q`` grid fold into weights on the ``2`` grid (:func:`_through_double_grid`), and the ``2N`` grid's samples
    come as its four interleaved sets (:func:`~raywave.wave.field.double_grid_intensity`): FFTs of ``N`` samples
    an axis instead of ``q·N``.

    Args:
        u: complex field ``(..., Ny, Nx)`` (pitch ``in_pitch`` mm, pixel ``(0, 0)`` at ``in_origin``); the window is
            periodic: taper it to ~0 at its edges (``window``, real ``(Ny, Nx)``, multiplies it).
        q: the upsampling whose cubic pixel integral this is (≥ 2).
        out_pitch, out_origin, out_shape: the sensor pixels as in :func:`pixel_integrate` (an ``out_origin``
            tensor that requires grad stays differentiable).

        refine: also the pixel integral at ``2q`` (from the same ``2N`` grid: the cost of two small matrix
            products), and for each image whose ``2q`` integral differs from the ``q`` one by more than
            :data:`REFINE_TOL` (relative L1 of the two normalised to sum 1) that one instead: the cubic pixel
            quadrature where ``q`` leaves more than that (a PSF as sharp as the field's grid allows on pixels of
            about its pitch); elsewhere the ``q`` result as it was. The choice is not differentiated (both are differentiable).
        weights: :func:`upsampled_pixel_weights` of this geometry (the same ``q`` and ``refine``), built once by a
            caller that integrates many batches of it; None: built here (the same values).

    Returns:
        float64 ``(..., Ny_out, Nx_out)``, differentiable with respect to ``u`` and ``out_origin``.
    """
    from raywave.wave.field import double_grid_intensity  # same package, a sibling module (no cycle at import)

    if weights is None:
        weights = upsampled_pixel_weights(u.shape[-2:], q, in_pitch, in_origin, out_pitch, out_origin, out_shape,
                                          u.device, refine)
    elif len(weights) != (2 if refine else 1):
        raise ValueError(f"integrated_upsampled_intensity: weights for refine={refine} hold {2 if refine else 1} "
                         f"sets, got {len(weights)} (build them with upsampled_pixel_weights(..., refine={refine}))")
    blocks = double_grid_intensity(u, window).to(torch.float64)  # (..., 2, 2, Ny, Nx): samples [2i + a, 2j + b]
    b = blocks.unbind(-4)

    def integral(w: tuple) -> torch.Tensor:
        wy0, wy1, wx0, wx1 = w
        return ((wy0 @ b[0][..., 0, :, :] + wy1 @ b[1][..., 0, :, :]) @ wx0.transpose(0, 1)
                + (wy0 @ b[0][..., 1, :, :] + wy1 @ b[1][..., 1, :, :]) @ wx1.transpose(0, 1))

    out = integral(weights[0])
    if not refine:
        return out
    fine = integral(weights[1])
    with torch.no_grad():
        a, b = (t / t.sum((-2, -1), keepdim=True).abs().clamp_min(1e-300) for t in (out, fine))
        change = (b - a).abs().sum((-2, -1))  # of the normalised integrals (the PSF's relative L1)
        need = change > REFINE_TOL
    if not bool(need.any()):
        return out
    return torch.where(need[..., None, None], fine, out)


@dataclass(frozen=True)
class PixelPlan:
    """The constants of :func:`integrated_upsampled_intensity` for one geometry, laid out for an accelerator
    (:func:`pixel_plan`; every op a kernel launch): ``modulation`` complex ``(Ny, Nx)`` the field's spectrum roll
    times the window, ``ramps`` the half-sample shifts' phase ramps ``(x (Nx,), y (Ny, 1))`` complex (those of
    :func:`~raywave.wave.field.double_grid_intensity`), ``wy`` float64 ``(S·K_y, 2Ny)`` and ``wxt`` ``(2Nx, S·K_x)``
    the pixel weights on the ``2N`` grid's samples in their order (the ``S`` weight sets stacked; ``wxt``
    transposed); ``out_shape`` ``(K_y, K_x)`` one set's output."""

    modulation: torch.Tensor
    ramps: tuple
    wy: torch.Tensor
    wxt: torch.Tensor
    out_shape: tuple

    @property
    def sets(self) -> int:
        """The number of weight sets S (2 with ``refine``: ``q`` and ``2q``)."""
        return self.wy.shape[0] // self.out_shape[0]


def pixel_plan(weights: tuple, window: torch.Tensor | None, dtype) -> PixelPlan:
    """The :class:`PixelPlan` of :func:`upsampled_pixel_weights`' ``weights`` (one set, or two with ``refine``)
    and the field's ``window`` (real ``(Ny, Nx)`` or None) for fields of the complex ``dtype``: built once per
    geometry by a caller on an accelerator (:func:`integrated_intensity_planned`)."""
    from raywave.wave.field import _half_sample_ramp, _roll_modulation  # a sibling module (no import cycle)

    wy0 = weights[0][0]
    ny, nx = wy0.shape[1], weights[0][2].shape[1]
    dev = wy0.device
    mod = _roll_modulation(ny, dev)[:, None] * _roll_modulation(nx, dev)[None, :]
    if window is not None:
        mod = mod * window

    def interleaved(even, odd):  # (K, N) pairs → (K, 2N): column 2i + a the sample set a's column i
        return torch.stack([even, odd], -1).flatten(-2)

    wy = torch.cat([interleaved(w[0], w[1]) for w in weights])
    wxt = torch.cat([interleaved(w[2], w[3]) for w in weights]).transpose(0, 1)
    ramps = (_half_sample_ramp(nx, dev).to(dtype), _half_sample_ramp(ny, dev).to(dtype)[:, None])
    return PixelPlan(mod.to(dtype), ramps, wy, wxt, (wy0.shape[0], weights[0][2].shape[0]))


def integrated_intensity_planned(u: torch.Tensor, plan: PixelPlan) -> torch.Tensor:
    """:func:`integrated_upsampled_intensity` of ``u`` ``(B, Ny, Nx)`` with its :class:`PixelPlan` (its weights
    and window; with two sets, ``refine``): the same sums to rounding in fewer ops (an accelerator's plan): the
    ``2N`` grid's samples (:func:`~raywave.wave.field.double_grid_intensity`'s, from the plan's constants) written
    in their order, every set's pixel integral from two batched products, the refined one chosen without a host
    read. float64 ``(B, K_y, K_x)``; differentiable in ``u``."""
    v = u * plan.modulation
    rx, ry = plan.ramps
    xb = torch.stack([v, torch.fft.ifft(torch.fft.fft(v, dim=-1) * rx, dim=-1)], -1).flatten(-2)  # [i, 2j + b]
    grid = torch.stack([xb, torch.fft.ifft(torch.fft.fft(xb, dim=-2) * ry, dim=-2)], -2).flatten(-3, -2)
    r = torch.view_as_real(grid)  # (B, 2Ny, 2Nx, 2): sample [2i + a, 2j + b]
    if torch.is_grad_enabled() and grid.requires_grad:
        inten = r[..., 0].square() + r[..., 1].square()
    else:
        inten = r[..., 0].square().add_(r[..., 1].square())
    inten = inten.to(torch.float64)
    b = inten.shape[0]
    full = torch.bmm(plan.wy.expand(b, -1, -1), torch.bmm(inten, plan.wxt.expand(b, -1, -1)))  # (B, S·Ky, S·Kx)
    ky, kx = plan.out_shape
    out = full[..., :ky, :kx]
    if plan.sets == 1:
        return out
    fine = full[..., ky:, kx:]
    with torch.no_grad():
        a, b = (t_ / t_.sum((-2, -1), keepdim=True).abs().clamp_min(1e-300) for t_ in (out, fine))
        need = (b - a).abs().sum((-2, -1)) > REFINE_TOL
    return torch.where(need[..., None, None], fine, out)
