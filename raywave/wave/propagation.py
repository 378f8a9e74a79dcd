"""Free-space (homogeneous-medium) scalar propagation of sampled complex fields.

Pure functions on ``torch`` tensors; no state, no caching. Conventions shared by every function here:

* Lengths (pitch, origins, z) in **mm**, wavelengths in **µm** (vacuum), ``n`` is the (real) medium index.
* Fields have shape ``(..., Ny, Nx)`` (any leading batch dims) and are indexed ``[iy, ix]``; the sample
  ``[iy, ix]`` sits at ``(x0 + ix·px, y0 + iy·py)`` where ``origin = (x0, y0)`` is the centre of pixel (0, 0),
  so coordinates increase with the index.
* ``pitch`` is a float (square pixels) or a pair ``(px, py)``.
* Time dependence ``exp(-iωt)``: a plane wave travelling towards +z is ``exp(+i k n z)``, so the transfer
  function is ``H(f) = exp(+i 2π z sqrt((n/λ)² - |f|²))``; evanescent components are set to 0 (never
  exponentially amplified, never NaN).
* complex128 by default, complex64 accepted (real input is promoted). The transfer function is always
  evaluated in float64 (the absolute phase 2π z n/λ reaches ~1e5 rad) and cast to the field's dtype.
* Differentiable with respect to the input field; ``z`` may also be a (0-d) tensor, in which case the result
  is differentiable with respect to it too (the band-limit weights and FFT sizes use its detached value and
  are held fixed in the derivative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

__all__ = [
    "NyquistReport",
    "angular_spectrum",
    "fast_fft_size",
    "grid_coordinates",
    "nyquist_check",
    "pixel_integrate",
    "propagate_window",
    "window_transfer",
]

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
    return torch.sqrt(torch.where(ok, arg, torch.ones_like(arg)))


def _transfer(phase: torch.Tensor, mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    h = torch.polar(torch.ones_like(phase), phase)
    return torch.where(mask, h, torch.zeros((), dtype=h.dtype, device=h.device)).to(dtype)


# ----------------------------------------------------------------------------------------------------------
# 1. classic band-limited angular spectrum (reference path)
# ----------------------------------------------------------------------------------------------------------
def angular_spectrum(
    u: torch.Tensor,
    pitch,
    wavelength: float,
    z,
    n: float = 1.0,
    pad: float = 2,
    band_limit: bool = True,
) -> torch.Tensor:
    """Band-limited angular-spectrum propagation on the full grid (Matsushima & Shimobaba 2009).

    Args:
        u: complex field ``(..., Ny, Nx)`` sampled at ``pitch`` (any origin; the output shares it).
        pitch: sample spacing in mm, a float or ``(px, py)``.
        wavelength: vacuum wavelength in µm.
        z: propagation distance in mm (may be negative: back-propagation; may be a 0-d tensor).
        n: refractive index of the homogeneous medium (default air = 1).
        pad: zero-padding factor; the FFT grid is ``ceil(pad·N)`` per axis (``pad=2`` is the classic
            doubling that turns the circular convolution into a linear one). The result is cropped back to
            ``(Ny, Nx)`` (the input's own sample positions).
        band_limit: apply the band limit ``|f_x| < 1 / ((λ/n)·sqrt((2 z/(M_x p_x))² + 1))`` (same in y)
            that suppresses aliasing of the sampled transfer function; ``False`` gives the plain ASM.

    Returns:
        The propagated field ``(..., Ny, Nx)``, same dtype as ``u`` (complex). Evanescent components are 0.
    """
    u = _as_field(u)
    px, py = _pair(pitch, "pitch")
    _positive(px, "pitch"), _positive(py, "pitch")
    lam = _positive(wavelength, "wavelength") * _UM_TO_MM
    n = _positive(n, "n")
    if float(pad) < 1:
        raise ValueError(f"pad must be >= 1, got {pad}")
    zf, zt = _z_value(z)
    ny, nx = u.shape[-2:]
    my, mx = int(math.ceil(float(pad) * ny - 1e-9)), int(math.ceil(float(pad) * nx - 1e-9))

    dev = u.device
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=dev)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=dev)
    k = n / lam  # cycles / mm in the medium
    arg = k * k - fx[None, :] ** 2 - fy[:, None] ** 2
    mask = arg > 0
    if band_limit:
        lim_x = k / math.sqrt((2.0 * zf / (mx * px)) ** 2 + 1.0)
        lim_y = k / math.sqrt((2.0 * zf / (my * py)) ** 2 + 1.0)
        mask = mask & (fx.abs()[None, :] < lim_x) & (fy.abs()[:, None] < lim_y)
    phase = _TWO_PI * zt * _sqrt_kz(arg, mask)
    h = _transfer(phase, mask, u.dtype)

    spec = torch.fft.fft2(u, s=(my, mx))
    out = torch.fft.ifft2(spec * h)
    return out[..., :ny, :nx]


# ----------------------------------------------------------------------------------------------------------
# 2. shifted band-limited angular spectrum between two windows (efficient path)
# ----------------------------------------------------------------------------------------------------------
def window_transfer(
    in_shape: Sequence[int],
    out_shape: Sequence[int],
    pitch,
    wavelength: float,
    z,
    in_origin,
    out_origin,
    n: float = 1.0,
    carrier=(0.0, 0.0),
    margin: float = 0.5,
    guard: float = 2.0,
    device=None,
    weight_derivative: bool = False,
) -> tuple:
    """Transfer function used by :func:`propagate_window` (float64-accurate, complex128).

    Returns ``(G, (My, Mx))`` with, on the ``fftfreq`` grid of the FFT size ``(My, Mx)``,
    ``G = W(f) · H(f + f_c) · exp(i2π f·(out_origin − in_origin))`` with
    ``H(f) = exp(i2π z sqrt((n/λ)² − |f|²))`` and ``f_c = n·carrier/λ``. The band-limit weight ``W`` is a
    function of the geometric lateral shift per axis, ``Δ = z (f + f_c)/sqrt((n/λ)² − |f + f_c|²)``
    (= z·tanθ in x resp. y):

    * ``W = 1`` where Δ lies in ``[out_min − in_max − margin·p, out_max − in_min + margin·p]`` in both axes
      (exactly the directions that carry light from the input window into the output window; pixel centres);
    * beyond, ``W`` rolls off smoothly (quintic smoothstep, C²) to 0 over ``T = guard·F`` with the Fresnel-zone
      width ``F = sqrt(λ/n · |z| / cos³θ_c)`` (``θ_c`` the carrier angle); ``guard = 0`` gives the sharp
      band limit of Matsushima (2010);
    * ``W = 0`` for evanescent components.

    The FFT size is the smallest fast size ≥ ``N_in + N_out − 1 + 2·ceil(margin + T/p)`` per axis, so the
    circular convolution equals the linear one for the whole (rolled-off) kernel. Only the rows/columns that
    can be non-zero are evaluated (a 1-D pre-selection), so building ``G`` costs little beyond the FFTs.
    Exposed so that a caller propagating many fields between the same windows can reuse ``G``.

    ``weight_derivative=True`` returns ``(G, (My, Mx), R)`` with ``R`` float64 ``(3, My, Mx)`` (1/mm), the
    relative first-order changes ``(∂W/∂z, ∂W/∂s_x, ∂W/∂s_y) / W`` of the roll-off weights (0 where ``W = 0``,
    where the derivatives vanish too) with the distance (Δ ∝ z, T ∝ sqrt|z|) and with a translation ``s`` of
    the output window (the band follows it): :func:`propagate_window` adds ``(dz·R_z + s·R_s)·G`` for its
    ``dz`` and ``shift`` so that their derivatives are those of the whole discrete model.
    """
    px, py = _pair(pitch, "pitch")
    _positive(px, "pitch"), _positive(py, "pitch")
    lam = _positive(wavelength, "wavelength") * _UM_TO_MM
    n = _positive(n, "n")
    zf, zt = _z_value(z)
    (niy, nix), (noy, nox) = (int(s) for s in in_shape), (int(s) for s in out_shape)
    if min(niy, nix, noy, nox) < 1:
        raise ValueError(f"window shapes must be positive, got {tuple(in_shape)} and {tuple(out_shape)}")
    xi0, yi0 = _xy(in_origin, "in_origin")
    xo0, yo0 = _xy(out_origin, "out_origin")
    ax, ay = _xy(carrier, "carrier")
    margin, guard = float(margin), float(guard)
    if not (margin >= 0 and guard >= 0 and math.isfinite(margin) and math.isfinite(guard)):
        raise ValueError("margin and guard must be finite and >= 0")

    cos2 = max(1.0 - ax * ax - ay * ay, 0.1)  # clamp: grazing/invalid carriers do not blow the guard up
    fresnel = math.sqrt(lam / n * abs(zf) / cos2**1.5)
    # roll-off widths (mm) per axis: dΔx/dfx = z (k² − fy²)/w³ → the x zone narrows by sqrt(1 − β²)
    tx = guard * fresnel * math.sqrt(max(1.0 - ay * ay, 0.1))
    ty = guard * fresnel * math.sqrt(max(1.0 - ax * ax, 0.1))
    ex = int(math.ceil(margin + tx / px - 1e-9))
    ey = int(math.ceil(margin + ty / py - 1e-9))
    mx, my = fast_fft_size(nix + nox - 1 + 2 * ex), fast_fft_size(niy + noy - 1 + 2 * ey)

    dx, dy = xo0 - xi0, yo0 - yi0
    k = n / lam
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=device)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=device)
    gx, gy = fx + k * ax, fy + k * ay  # physical spatial frequencies (cycles/mm)
    bx = (dx - (nix - 1 + margin) * px, dx + (nox - 1 + margin) * px, tx)  # (lo, hi, roll-off) of Δx
    by = (dy - (niy - 1 + margin) * py, dy + (noy - 1 + margin) * py, ty)

    def candidates(g: torch.Tensor, lo: float, hi: float, taper: float) -> torch.Tensor:
        # |Δx| = |z gx|/w ≥ |z gx|/sqrt(k² − gx²) whatever gy is: only these columns (rows) can be non-zero
        q = k * k - g * g
        s1 = zf * g / torch.sqrt(q.clamp_min(1e-300))
        at_zero = torch.full_like(s1, lo - taper <= 0.0 <= hi + taper, dtype=torch.bool)
        ok = torch.where(s1 > 0, s1 <= hi + taper, torch.where(s1 < 0, s1 >= lo - taper, at_zero))
        return torch.nonzero((q > 0) & ok).squeeze(1)

    cols, rows = candidates(gx, *bx), candidates(gy, *by)
    out = torch.zeros((my, mx), dtype=torch.complex128, device=device)
    d_out = torch.zeros((3, my, mx), dtype=torch.float64, device=device) if weight_derivative else None
    if cols.numel() == 0 or rows.numel() == 0:
        return (out, (my, mx), d_out) if weight_derivative else (out, (my, mx))
    gxs, gys = gx[cols], gy[rows]
    arg = k * k - gxs[None, :] ** 2 - gys[:, None] ** 2
    prop = arg > 0
    w = _sqrt_kz(arg, prop)  # (n/λ)·cosθ; 1 on evanescent entries
    inv_w = 1.0 / w
    weight = prop.to(torch.float64)  # evanescent: exactly 0
    factors = []  # per axis (roll-off factor, its z-derivative) for weight_derivative
    for shift, (lo, hi, taper) in (((zf * gxs)[None, :] * inv_w, bx), ((zf * gys)[:, None] * inv_w, by)):
        if weight_derivative:
            # Δ ∝ z and T ∝ sqrt|z|: ∂dist/∂z = sign(Δ − mid)·Δ/z and ∂T/∂z = T/(2z) where dist > 0
            sgn = torch.sign(shift - 0.5 * (lo + hi))
            dshift = sgn * shift / zf if zf != 0 else torch.zeros_like(shift)
        # how far Δ lies outside [lo, hi] (0 inside)
        dist = shift.sub_(0.5 * (lo + hi)).abs_().sub_(0.5 * (hi - lo)).clamp_(min=0.0)
        if taper > 0:
            if weight_derivative:
                ramp = (dist > 0) & (dist < taper)
                dt_z = torch.where(ramp, (dshift - dist / (2.0 * zf)) / taper, torch.zeros_like(dist))
                dt_s = torch.where(ramp, -sgn / taper, torch.zeros_like(dist))  # the band moves with the window
            t = dist.div_(taper).clamp_(max=1.0)
            if weight_derivative:
                # d(log(1 − S))/dt, S' = 30 t²(1 − t)², 1 − S = (1 − t)³(1 + 3t + 6t²): finite up to t = 1
                dlog = torch.where(t < 1, -30.0 * t * t / ((1.0 - t) * (1.0 + t * (3.0 + 6.0 * t))).clamp_min(1e-300),
                                   torch.zeros_like(t))
                factors.append((dlog * dt_z, dlog * dt_s))
            # the quintic smoothstep roll-off S(t) = t³(10 + t(6t − 15)), W ← W − W·S, evaluated only where it
            # changes W (0 < t: S(0) = 0; at t = 1, S = 1 exactly): most of the band lies inside (t = 0)
            ramp_idx = (t > 0).nonzero(as_tuple=True)
            if ramp_idx[0].numel():
                tr = t[ramp_idx]
                s = tr * tr * tr * (10.0 + tr * (6.0 * tr - 15.0))
                wr = weight[ramp_idx]
                weight.index_put_(ramp_idx, wr - wr * s)
        else:
            if weight_derivative:
                factors.append((torch.zeros_like(dist), torch.zeros_like(dist)))
            weight.mul_(dist <= 0)
    phase = _TWO_PI * zt * w + _TWO_PI * ((fx[cols] * dx)[None, :] + (fy[rows] * dy)[:, None])
    idx = (rows[:, None], cols[None, :])
    out.index_put_(idx, torch.polar(weight, phase))
    if not weight_derivative:
        return out, (my, mx)
    (rz_x, rs_x), (rz_y, rs_y) = factors
    live = weight > 0
    zero = torch.zeros((), dtype=torch.float64, device=weight.device)
    for i, r in enumerate((rz_x + rz_y, rs_x.expand_as(weight), rs_y.expand_as(weight))):
        d_out[i].index_put_(idx, torch.where(live, r, zero))
    return out, (my, mx), d_out


def propagate_window(
    u: torch.Tensor,
    pitch,
    wavelength: float,
    z,
    in_origin,
    out_origin,
    out_shape: Sequence[int],
    n: float = 1.0,
    carrier=(0.0, 0.0),
    margin: float = 0.5,
    guard: float = 2.0,
    shift: torch.Tensor | None = None,
    transfer: tuple | None = None,
    dz: torch.Tensor | None = None,
) -> torch.Tensor:
    """Propagate an envelope from an input window to an output window (shifted band-limited ASM).

    The true field is ``U(x, y) = u(x, y) · exp(i k n (α x + β y))`` with ``k = 2π/λ`` and
    ``carrier = (α, β)`` direction cosines (typically the chief ray's); removing the carrier keeps the sampled
    envelope far below Nyquist for off-axis light. Method (Matsushima 2010, Opt. Express 18, 18453):
    linear convolution by FFTs of size ≥ N_in + N_out − 1 (+ the guard) per axis with the transfer function
    ``H(f + f_c)·exp(i2π f·(out_origin − in_origin))`` restricted to the frequencies whose geometric shift
    ``z·tanθ`` (per axis) can carry light from the input window into the output window, then rolled off
    smoothly over ``guard`` Fresnel zones (see :func:`window_transfer`). This removes wrap-around and
    kernel aliasing, and the cost scales with ``(N_in + N_out + 4·guard·F/p)²`` instead of the full DOE grid:
    crop ``u`` to the lit footprint before calling.

    Args:
        u: envelope ``(..., Ny_in, Nx_in)``; pixel (0, 0) centred at ``in_origin``.
        pitch: sample spacing in mm (float or ``(px, py)``), shared by input and output grids.
        wavelength: vacuum wavelength in µm.
        z: propagation distance in mm (negative allowed; float or 0-d tensor).
        in_origin: ``(x0, y0)`` mm, centre of the input pixel (0, 0).
        out_origin: ``(x0, y0)`` mm, centre of the output pixel (0, 0) (any real offset, not only multiples
            of the pitch).
        out_shape: ``(Ny_out, Nx_out)``.
        n: index of the homogeneous medium.
        carrier: ``(α, β)`` direction cosines of the carrier (in the medium), same for input and output.
        margin: tolerance of the band limit in pixels beyond the pixel-centre extremes (default ½ pixel).
        guard: width of the smooth roll-off of the band limit beyond that range, in Fresnel zones
            ``sqrt(λ|z|/(n cos³θ_c))`` (default 2; the FFT grows by the same amount). ``guard=0`` is the sharp
            band limit of the paper, whose truncation error decays only like 1/distance: for a hard-edged
            aperture whose edge lies within a Fresnel zone of the window extremes it reaches ~6e-3 of the peak
            amplitude, against ~1e-4 with ``guard=2`` (see tests/test_propagation.py).

        shift: optional ``(2,)`` tensor (mm), an extra translation of the output window added to
            ``out_origin`` through a phase ramp on the spectrum; pass a zero-valued tensor that carries a
            derivative to make the result differentiable with respect to where the window sits (a PSF crop
            that follows a chief ray). Keep it well below the margin (sub-sample). With a ``transfer`` built by
            ``weight_derivative=True`` (the default when ``transfer`` is None) the derivative includes the band
            limit's roll-off following the window.
        transfer: a precomputed ``window_transfer(...)`` result for exactly these arguments (a caller that
            propagates many fields between the same windows builds it once).
        dz: optional 0-d tensor (mm), an extra propagation distance added to ``z``: the transfer function
            becomes ``(G + dz·D)·exp(i2π·dz·w)``, ``w = sqrt((n/λ)² − |f + f_c|²)`` the axial frequency at the
            true spatial frequency (0 where evanescent) and ``D`` the first-order change of the roll-off weights
            (:func:`window_transfer` ``weight_derivative=True``; the FFT size and the band's rows/columns stay
            those of ``z``). Pass a zero-valued tensor that carries a derivative (``d − d.detach()``): the result
            is unchanged and differentiable with respect to the distance, exactly to first order, while reusing
            a cached ``transfer`` (a sensor plane that moves with the lens). ``transfer`` must then be the
            3-tuple of ``weight_derivative=True`` (a 2-tuple is rebuilt).

    Returns:
        The output envelope ``(..., Ny_out, Nx_out)`` (true field divided by ``exp(i k n (α x + β y))`` at the
        output coordinates), same dtype as ``u``.
    """
    u = _as_field(u)
    noy, nox = (int(s) for s in out_shape)
    if transfer is None or (dz is not None and len(transfer) < 3):
        transfer = window_transfer(u.shape[-2:], (noy, nox), pitch, wavelength, z, in_origin, out_origin, n, carrier,
                                   margin, guard, u.device, weight_derivative=dz is not None or shift is not None)
    h, (my, mx) = transfer[:2]
    rel = transfer[2] if len(transfer) > 2 else None
    # fft2(u, s=(my, mx)) one axis at a time: the first pass transforms only the Ny_in rows that hold data
    spec = torch.fft.fft(torch.fft.fft(u, n=mx, dim=-1), n=my, dim=-2)
    h = h.to(u.dtype)
    if shift is not None or dz is not None:
        px, py = _pair(pitch, "pitch")
        fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=u.device)
        fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=u.device)
        zero = torch.zeros((), dtype=torch.float64, device=u.device)
        sx, sy = (zero, zero) if shift is None else shift.to(device=u.device, dtype=torch.float64).reshape(2).unbind()
        dz = _dz_tensor(dz, u.device) if dz is not None else zero
        w = _axial_frequency(fx, fy, wavelength, n, carrier) if dz.requires_grad or float(dz) != 0 else None
        h = _Perturbed.apply(h, sx, sy, dz, fx, fy, w, rel)
    # ifft2(spec·h)[..., :Ny_out, :Nx_out] one axis at a time: the second pass transforms only the Ny_out rows kept
    out = torch.fft.ifft(torch.fft.ifft(spec * h, dim=-2)[..., :noy, :], dim=-1)
    return out[..., :nox]


class _Perturbed(torch.autograd.Function):
    """``h·a·exp(iφ)`` with ``φ = 2π(f_x s_x + f_y s_y + w·dz)`` and ``a = 1 + s_x R_x + s_y R_y + dz R_z`` (the
    window shift, the extra distance and the roll-off weights' first-order change), with a hand-written
    backward: the scalars' gradients are a few reductions instead of autograd's chain of full-size complex
    temporaries. ``w`` None: no distance term; ``rel`` None: no weight terms (a = 1)."""

    @staticmethod
    def forward(ctx, h, sx, sy, dz, fx, fy, w, rel):
        phase = _TWO_PI * (fy[:, None] * sy + fx[None, :] * sx)
        if w is not None:
            phase = phase + _TWO_PI * dz * w
        e = torch.polar(torch.ones_like(phase), phase).to(h.dtype)  # exp(iφ)
        amp = None if rel is None else 1.0 + (sx * rel[1] + sy * rel[2] + dz * rel[0])
        ctx.save_for_backward(h, e, amp, fx, fy, w, rel)
        return h * e if amp is None else h * e * amp.to(h.real.dtype)

    @staticmethod
    def backward(ctx, g):
        h, e, amp, fx, fy, w, rel = ctx.saved_tensors
        grads = [None] * 8
        if ctx.needs_input_grad[0]:
            grads[0] = g * e.conj() if amp is None else g * e.conj() * amp.to(g.real.dtype)
        if any(ctx.needs_input_grad[1:4]):
            # the real gradient of s is Re Σ conj(g)·∂(h·a·e^{iφ})/∂s = Re Σ conj(g)·h·e^{iφ}·(∂a/∂s + i a ∂φ/∂s)
            q = (g.conj() * h * e).to(torch.complex128)
            qa = q.imag if amp is None else q.imag * amp

            def red(r_chan, freq):
                out = -_TWO_PI * (qa * freq).sum() if freq is not None else q.real.new_zeros(())
                return out + (q.real * rel[r_chan]).sum() if rel is not None else out

            if ctx.needs_input_grad[1]:
                grads[1] = red(1, fx[None, :])
            if ctx.needs_input_grad[2]:
                grads[2] = red(2, fy[:, None])
            if ctx.needs_input_grad[3]:
                grads[3] = red(0, w)
        return tuple(grads)


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


# ----------------------------------------------------------------------------------------------------------
# 3. sampling check
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class NyquistReport:
    """Result of :func:`nyquist_check`.

    ``max_ratio``: largest local fringe frequency / Nyquist frequency (per axis, |Δφ|/π between neighbours);
    ``index``: index (including batch dims) of the worst pixel; ``position``: its ``(x, y)`` in mm;
    ``ratio``: the per-pixel map ``(..., Ny, Nx)`` (0 where nothing is lit); ``limit``: the threshold of ``ok``.
    """

    max_ratio: float
    index: tuple[int, ...]
    position: tuple[float, float]
    ratio: torch.Tensor
    limit: float = 1.0

    @property
    def ok(self) -> bool:
        return self.max_ratio < self.limit

    def __str__(self) -> str:
        x, y = self.position
        return (
            f"local fringe frequency up to {self.max_ratio:.3g}× Nyquist at index {self.index} "
            f"(x = {x:.6g} mm, y = {y:.6g} mm)" + ("" if self.ok else ": grid too coarse")
        )


def nyquist_check(
    phase_or_field: torch.Tensor,
    pitch,
    wavelength: float | None = None,
    *,
    n: float = 1.0,
    carrier=(0.0, 0.0),
    origin=(0.0, 0.0),
    mask: torch.Tensor | None = None,
    threshold: float = 1e-6,
    limit: float = 1.0,
) -> NyquistReport:
    """Local fringe frequency of a sampled phase relative to the Nyquist frequency ``1/(2p)``.

    Args:
        phase_or_field: either a real **unwrapped** phase (rad), e.g. a DOE/lens phase profile, or a complex
            field (its neighbour phase steps ``angle(u[i+1]·conj(u[i]))`` are used; these are wrapped to
            ``(-π, π]`` so a complex field can only show aliasing as ratios approaching 1 — pass the unwrapped
            phase where available). Shape ``(..., Ny, Nx)``.
        pitch: sample spacing in mm (float or ``(px, py)``).
        wavelength: vacuum wavelength in µm; required only when ``carrier`` is non-zero.
        n: medium index (for the carrier).
        carrier: ``(α, β)`` direction cosines removed before the check (the envelope is what is sampled in
            :func:`propagate_window`).
        origin: ``(x0, y0)`` of pixel (0, 0) in mm, used for ``position``.
        mask: optional boolean ``(Ny, Nx)`` (broadcastable) of lit pixels; a neighbour pair counts only if
            both pixels are lit. For a complex field, pixels with ``|u| ≤ threshold·max|u|`` are unlit too.
        limit: ``ok`` is ``max_ratio < limit``.

    Returns:
        :class:`NyquistReport`. The ratio per axis is ``|Δφ|/π`` (= local frequency / (1/(2p)));
        a pixel's value is the largest over its four neighbour steps.
    """
    t = phase_or_field.detach()
    if t.ndim < 2:
        raise ValueError("expected shape (..., Ny, Nx)")
    px, py = _pair(pitch, "pitch")
    ax, ay = _xy(carrier, "carrier")
    x0, y0 = _xy(origin, "origin")
    if (ax or ay) and wavelength is None:
        raise ValueError("a non-zero carrier needs the wavelength")
    kc = _TWO_PI * n / (wavelength * _UM_TO_MM) if wavelength is not None else 0.0
    cx, cy = kc * ax * px, kc * ay * py  # carrier phase step per pixel

    if t.is_complex():
        t = t.to(torch.complex128)
        amp = t.abs()
        lit = amp > threshold * amp.amax(dim=(-2, -1), keepdim=True).clamp_min(1e-300)
        stepx = torch.angle(t[..., :, 1:] * t[..., :, :-1].conj() * complex(math.cos(cx), -math.sin(cx)))
        stepy = torch.angle(t[..., 1:, :] * t[..., :-1, :].conj() * complex(math.cos(cy), -math.sin(cy)))
    else:
        t = t.to(torch.float64)
        lit = torch.ones_like(t, dtype=torch.bool)
        stepx = t[..., :, 1:] - t[..., :, :-1] - cx
        stepy = t[..., 1:, :] - t[..., :-1, :] - cy
    if mask is not None:
        lit = lit & mask.to(device=t.device, dtype=torch.bool)
    okx = lit[..., :, 1:] & lit[..., :, :-1]
    oky = lit[..., 1:, :] & lit[..., :-1, :]
    rx = torch.where(okx, stepx.abs() / math.pi, torch.zeros_like(stepx))
    ry = torch.where(oky, stepy.abs() / math.pi, torch.zeros_like(stepy))
    pad = torch.nn.functional.pad
    ratio = torch.maximum(
        torch.maximum(pad(rx, (1, 0)), pad(rx, (0, 1))),
        torch.maximum(pad(ry, (0, 0, 1, 0)), pad(ry, (0, 0, 0, 1))),
    )
    flat = int(torch.argmax(ratio.reshape(-1)))
    index = tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), ratio.shape))
    max_ratio = float(ratio.reshape(-1)[flat])
    position = (x0 + index[-1] * px, y0 + index[-2] * py)
    return NyquistReport(max_ratio, index, position, ratio, float(limit))


# ----------------------------------------------------------------------------------------------------------
# 4. energy-conserving resampling to sensor pixels
# ----------------------------------------------------------------------------------------------------------
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
    ipx, ipy = _pair(in_pitch, "in_pitch")
    opx, opy = _pair(out_pitch, "out_pitch")
    for v in (ipx, ipy, opx, opy):
        _positive(v, "pitch")
    xi0, yi0 = _xy(in_origin, "in_origin")
    if isinstance(out_origin, torch.Tensor) and out_origin.requires_grad:
        # keep the output origin in the graph: d(out)/d(origin) is the exact derivative of the overlaps
        # (the intensity at the moving pixel edges), so a PSF crop that follows a chief ray differentiates
        xo0, yo0 = out_origin.reshape(2).to(torch.float64).unbind()
    else:
        xo0, yo0 = _xy(out_origin, "out_origin")
    noy, nox = (int(s) for s in out_shape)
    niy, nix = intensity.shape[-2:]
    if not intensity.is_floating_point():
        intensity = intensity.to(torch.float64)
    dt, dev = intensity.dtype, intensity.device
    if kernel == "box":
        wx = _overlap_matrix(nix, ipx, xi0, nox, opx, xo0, torch.float64, dev)
        wy = _overlap_matrix(niy, ipy, yi0, noy, opy, yo0, torch.float64, dev)
    elif kernel == "cubic":
        wx = _cubic_overlap_matrix(nix, ipx, xi0, nox, opx, xo0, torch.float64, dev)
        wy = _cubic_overlap_matrix(niy, ipy, yi0, noy, opy, yo0, torch.float64, dev)
    else:
        raise ValueError(f"kernel must be 'box' or 'cubic', got {kernel!r}")
    if mode == "integral":
        pass
    elif mode == "sum":
        wx, wy = wx / ipx, wy / ipy
    elif mode == "mean":
        wx, wy = wx / opx, wy / opy
    else:
        raise ValueError(f"mode must be 'integral', 'sum' or 'mean', got {mode!r}")
    return wy.to(dt) @ (intensity @ wx.to(dt).transpose(0, 1))
