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
from raywave.wave.propagation.band import BandConvolve, convolve_band
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
        return BandConvolve.apply(u, h, size, rows, cols, noy, nox)
    return convolve_band(u, h, size, rows, cols, noy, nox)


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
        # zero-valued perturbations (they carry derivatives only): the value is h itself, bit for bit, without the
        # band-sized factors (one host read)
        ctx.zero = not bool(torch.stack([sx, sy, dz]).any())
        if ctx.zero:
            y = h.view_as(h)
        else:
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
        if ctx.needs_input_grad[0] and ctx.zero:
            grads[0] = g
        elif ctx.needs_input_grad[0]:
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
        :data:`PERTURBED_BLOCK_ROWS` rows of the band: its band-sized temporaries (~4 arrays, the peak of a
        lens-trained backward) exist a block at a time. Per block: ``q·a = conj(g)·y`` once; the shifts' terms
        ``Σ Im(q·a)·f`` as the block summed down its rows (f_x) or across its columns (f_y) first, then one short
        product; the roll-off terms ``Σ Re(q)·R`` of the three channels as one matrix-vector product; ``a`` is
        not formed for zero-valued perturbations (it is 1 exactly: ``Re(q) = Re(q·a)``)."""
        sums = torch.zeros(3, dtype=torch.float64, device=y.device)
        zero = rel is None or not bool(torch.stack([sx, sy, dz]).detach().any())  # (one host read)
        for r0 in range(0, y.shape[-2], PERTURBED_BLOCK_ROWS):
            rows = slice(r0, r0 + PERTURBED_BLOCK_ROWS)
            qa_c = torch.view_as_real((g[..., rows, :].conj() * y[..., rows, :]).to(torch.complex128))  # q·a
            qa = qa_c[..., 1]
            terms = [-_TWO_PI * (qa.sum(-2) * fx).sum(), -_TWO_PI * (qa.sum(-1) * fy[rows]).sum(),
                     -_TWO_PI * (qa * _axial_frequency(fx, fy[rows], *axial)).sum() if axial is not None
                     else sums.new_zeros(())]
            if rel is not None:
                rel_b = rel[:, rows]
                q_re = qa_c[..., 0] if zero else qa_c[..., 0] / (1.0 + (sx * rel_b[1] + sy * rel_b[2] +
                                                                         dz * rel_b[0]))
                if q_re.ndim == 2:  # the channels (dz, s_x, s_y) in one pass over the block
                    r_d, r_x, r_y = torch.mv(rel_b.reshape(3, -1), q_re.reshape(-1)).unbind()
                else:
                    r_d, r_x, r_y = ((q_re * rel_b[c]).sum() for c in range(3))
                terms = [terms[0] + r_x, terms[1] + r_y, terms[2] + r_d]
            sums = sums + torch.stack(terms)
        return list(sums.unbind())


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
