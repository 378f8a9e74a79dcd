"""PSF-aware deconvolution for spatially varying blur (multi-Wiener), the inverse partner of :func:`render`.

The renderer models ``out = Σ_n (w_n·I) ⊛ K_n`` (bilinear partition-of-unity weights ``w_n`` of the PSF-map
nodes, :mod:`raywave.imaging.render`). Its standard inverse in computational imaging is the **multi-Wiener**
deconvolution: deconvolve the whole image with every node's PSF, in the Fourier domain,

    X̂_n(f) = conj(K̂_n(f))·Ŷ(f) / (|K̂_n(f)|² + R_c(f)),   R_c(f) = λ_c + μ_c·|L̂(f)|²

(Tikhonov regularisation per colour channel c: a constant λ_c and a smoothness term μ_c with ``L̂`` the discrete
Laplacian's transfer function, |L̂| ≤ 1), then blend the node results with the **same weights** as the renderer,
``X = Σ_n w_n·X_n``, and finally undo the distortion warp (the map's chief-ray centres). Every step is
differentiable with respect to the image, the PSFs (so a lens / DOE can learn to be *restorable*) and the
regularisation (learned per channel by :class:`WienerDeconv`).

**Unknown depth (EDoF).** When the blur is one of S maps (the PSFs of S object distances; the camera does not
know which), the filter that minimises the *expected* squared error over the S maps (equal priors) is

    G_n(f) = mean_s conj(K̂_sn(f)) / (mean_s |K̂_sn(f)|² + R_c(f)),

i.e. the mean transfer function over the mean power, ``mean|K̂|² = |mean K̂|² + Var K̂``: frequencies where the
depths disagree are damped instead of being boosted for a PSF that none of the depths has (deconvolving with
the depth-averaged PSF over-sharpens the in-focus depth). Give ``psf`` as ``(S, C, N, M, ks, ks)`` for it;
S = 1 is the ordinary filter.

**Colour prior (``chroma``).** The per-channel filter treats R, G and B as independent, so where it boosts a
frequency it boosts each channel's noise separately: colour speckle and colour ringing. Natural images are
strongly correlated across channels; with the Gaussian prior whose covariance across channels has the luminance
direction ``(1, 1, 1)/√3`` at full power and the two chroma directions at ``ρ`` times it (``chroma = ρ``, 0 < ρ ≤ 1;
the regularisation in channel space is ``R^½·M·R^½`` with ``M = P_L + (I − P_L)/ρ``, ``P_L = 11ᵀ/3``), the
filter becomes a 3×3 linear solve per frequency and node (the multichannel Wiener filter):

    X̂_n(f) = (mean_s diag|K̂_sn(f)|² + R^½ M R^½)⁻¹ · (mean_s conj(K̂_sn(f)) ⊙ Ŷ(f)).

``ρ = 1`` (or None) is the per-channel filter above exactly; smaller ρ lets chroma be restored less sharply than
luminance. Measured on the EDoF demo's designed optics (held-out photos, deconvolution only, the learned λ and
μ, 2026-11-27): ρ = 0.1 raises the gain over the sensor image at 200 mm / 300 mm / 10 m from +1.82 / +2.89 / +1.17 dB
to +2.03 / +3.57 / +1.31 dB; on the aberration demo's designed optics the centre from 27.71 to 29.73 dB, the edge
21.05 → 20.92 dB (ρ = 0.3: 28.88 / 21.14 dB). The demos start at ρ = 0.06, :func:`chroma_ratio` of their
training photos, and learn it (end-to-end results: docs/training.md, "Demo results").

Orientation, extents, pitches and centres are those of :func:`~raywave.imaging.render.render`; the image is
reflect-padded by the PSF size before the FFTs (no wrap-around ringing from the frame).
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from raywave.imaging.render import (_GRID_PADDING, _PADDING, _fast, _hat_weights, _image_pitch, _node_grid,
                                    _node_offsets, _windows, prepare_map_arguments)

__all__ = ["wiener_deconvolve", "WienerDeconv", "chroma_ratio", "laplacian_power"]


def laplacian_power(fy: int, fx: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """``|L̂(f)|²`` of the 5-point Laplacian on an ``fy×fx`` FFT grid, normalised to max 1; ``(fy, fx//2+1)``
    (the ``rfft2`` half-plane)."""
    ky = torch.fft.fftfreq(fy, dtype=dtype, device=device)
    kx = torch.fft.rfftfreq(fx, dtype=dtype, device=device)
    ly = 2 - 2 * torch.cos(2 * math.pi * ky)
    lx = 2 - 2 * torch.cos(2 * math.pi * kx)
    return ((ly[:, None] + lx[None, :]) / 8.0) ** 2


def _kernel_spectrum(k: torch.Tensor, fy: int, fx: int) -> torch.Tensor:
    """rfft2 of kernels ``(..., ky, kx)`` zero-padded to ``(fy, fx)`` with their centre pixel ``[ky//2, kx//2]``
    moved to the origin (so that filtering does not shift the image)."""
    ky, kx = k.shape[-2:]
    kp = F.pad(k, (0, fx - kx, 0, fy - ky))
    kp = torch.roll(kp, shifts=(-(ky // 2), -(kx // 2)), dims=(-2, -1))
    return torch.fft.rfft2(kp)


def _regulariser(reg, C: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """``reg`` → (λ (C,), μ (C,)): a float (λ, μ = 0), a pair, or tensors of shape (C,) / (2, C)."""
    if isinstance(reg, (int, float)):
        lam, mu = torch.full((C,), float(reg), dtype=dtype, device=device), torch.zeros(C, dtype=dtype, device=device)
    elif isinstance(reg, tuple) and len(reg) == 2:
        lam, mu = (torch.as_tensor(v, dtype=dtype, device=device).expand(C) for v in reg)
    else:
        r = torch.as_tensor(reg, dtype=dtype, device=device)
        if r.ndim == 1 and r.shape[0] == C:
            lam, mu = r, torch.zeros_like(r)
        elif r.ndim == 2 and tuple(r.shape) == (2, C):
            lam, mu = r[0], r[1]
        else:
            raise ValueError(f"reg: give a float, a (λ, μ) pair, or a tensor of shape ({C},) or (2, {C}); got "
                             f"shape {tuple(r.shape)}")
    if not bool(torch.isfinite(lam.detach()).all() and (lam.detach() > 0).all() and (mu.detach() >= 0).all()):
        raise ValueError("reg: the Wiener regularisation must be finite, λ > 0 and μ >= 0")
    return lam, mu


def _unwarp(x, centers, positions, sensor_size, extent, cy, cx, padding):
    """Inverse of the renderer's warp: the renderer moved content from ``s`` to ``s + D(s)``; here output pixel
    ``p`` reads ``x(p + D(p))`` (sensor orientation; D interpolated bilinearly between nodes, per channel)."""
    B, C, H, W = x.shape
    off = _node_offsets(x, centers, positions, sensor_size, extent)
    if off is None:
        return x
    yy, xx = torch.meshgrid(torch.arange(H, dtype=x.dtype, device=x.device),
                            torch.arange(W, dtype=x.dtype, device=x.device), indexing="ij")
    g = torch.stack([_node_grid(cx, xx), _node_grid(cy, yy)], -1)[None].expand(C, H, W, 2)
    disp = F.grid_sample(off.permute(0, 3, 1, 2), g, mode="bilinear", padding_mode="border", align_corners=True)
    sx, sy = xx + disp[:, 0], yy + disp[:, 1]
    grid = torch.stack([(2 * sx + 1) / W - 1, (2 * sy + 1) / H - 1], -1)
    grid = grid[None].expand(B, C, H, W, 2).reshape(B * C, H, W, 2)
    out = F.grid_sample(x.reshape(B * C, 1, H, W), grid, mode="bilinear", padding_mode=_GRID_PADDING[padding],
                        align_corners=False)
    return out.reshape(B, C, H, W)


def wiener_deconvolve(image: torch.Tensor, psf: torch.Tensor, reg=1e-3, *, positions: torch.Tensor | None = None,
                      centers: torch.Tensor | None = None, sensor_size=None, pitch: float | None = None,
                      extent=(-1.0, 1.0, -1.0, 1.0), orientation: str = "picture",
                      padding: str = "reflect", chroma=None) -> torch.Tensor:
    """Multi-Wiener deconvolution of an image blurred by a PSF map (see the module docstring).

    Args:
        image: ``(B, C, H, W)`` or ``(C, H, W)`` the blurred (and possibly noisy) image, linear irradiance.
        psf: ``(C, N, M, ks, ks)`` node PSFs as given to :func:`~raywave.imaging.render.render` (also the
            shorter forms it takes), or ``(S, C, N, M, ks, ks)``: S candidate maps (e.g. one per object distance)
            for the expected-error filter of the module docstring.
        reg: Tikhonov regularisation: a float λ, a pair (λ, μ), or tensors (C,) / (2, C) per channel (λ > 0 is
            about the noise-to-signal power ratio; μ weights the Laplacian smoothness term).
        positions, centers, sensor_size, pitch, extent, orientation, padding: as :func:`render`.
        chroma: ρ of the colour prior (module docstring; a float or a 0-d tensor in (0, 1], 3 channels): the
            chroma's prior power relative to the luminance's. None: the per-channel filter.

    Returns:
        the deconvolved image, the shape, dtype and orientation of ``image``; differentiable w.r.t. the image,
        the PSFs, the centres and ``reg``.
    """
    squeeze = image.ndim == 3
    maps = psf if torch.is_tensor(psf) and psf.ndim == 6 else None
    x, k, positions, sensor_size, extent, cy, cx = prepare_map_arguments(
        image, psf if maps is None else maps[0], positions, sensor_size, pitch, extent, orientation, padding)
    if maps is not None:
        if maps.shape[0] < 1:
            raise ValueError("psf: an (S, C, N, M, ks, ks) set of maps needs S >= 1")
        k = torch.stack([k] + [prepare_map_arguments(image, m, positions, sensor_size, pitch, extent, orientation,
                                                     padding)[1] for m in maps[1:]])
    lam, mu = _regulariser(reg, x.shape[1], x.dtype, x.device)
    flip = orientation == "picture"
    rho = _chroma(chroma, x.shape[1], x.dtype, x.device)
    out = _multi_wiener(x, k, lam, mu, cy, cx, padding, rho)
    if centers is not None:
        if sensor_size is None:
            raise ValueError("centers: give sensor_size (mm) to convert the PSF centres to pixels")
        out = _unwarp(out, centers, positions, sensor_size, extent, cy, cx, padding)
    if flip:
        out = out.flip(-1)
    return out[0] if squeeze else out


def chroma_ratio(images: torch.Tensor) -> float:
    """ρ of the colour prior measured on ``images (B, 3, H, W)`` (linear RGB): the power of their chroma per
    chroma direction (the part orthogonal to (1, 1, 1), two directions) over the power of their luminance
    direction, each image's mean removed. 0 for grey images, ~1 for independent channels; the bundled training
    photos give ~0.06, the same in every frequency band from 0.02 to 0.5 cycles per pixel."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"chroma_ratio: give images of shape (B, 3, H, W), got {tuple(images.shape)}")
    x = images.double() - images.double().mean((-2, -1), keepdim=True)
    lum = x.mean(1, keepdim=True)
    p_lum = 3 * lum.square().sum()  # |P_L x|² with P_L = 11ᵀ/3
    p_chroma = (x - lum).square().sum() / 2
    if float(p_lum) == 0.0:
        raise ValueError("chroma_ratio: the images have no luminance contrast")
    return float(p_chroma / p_lum)


def _chroma(chroma, C: int, dtype, device):
    """ρ of the colour prior as a 0-d tensor, or None (the per-channel filter); checks its range and C = 3."""
    if chroma is None:
        return None
    rho = torch.as_tensor(chroma, dtype=dtype, device=device).reshape(())
    if not (0.0 < float(rho.detach()) <= 1.0):
        raise ValueError(f"chroma: the colour prior's chroma-to-luminance power ratio must lie in (0, 1], got "
                         f"{float(rho.detach()):g}")
    if C != 3:
        raise ValueError(f"chroma: the colour prior needs 3 channels (RGB), the image has {C}")
    return rho


def _colour_solve(Y, Kc, P2, R, rho):
    """The multichannel Wiener estimate (module docstring) per node: ``Y (B, 3, fy, fx')`` the image spectrum,
    ``Kc (3, n, m, fy, fx')`` mean_s conj K̂, ``P2`` the same shape mean_s |K̂|², ``R (3, 1, 1, fy, fx')`` the
    regularisation per channel, ``rho`` 0-d. Returns ``(B, 3, n, m, fy, fx')``.

    ``M = I/ρ + β·11ᵀ`` with ``β = (1 − 1/ρ)/3``, so the system is a diagonal plus a rank-one matrix,
    ``A = diag(P2 + R/ρ) + β·ssᵀ`` (``s = R^½``), and Sherman–Morrison solves it elementwise:
    ``x_c = w_c z_c − β u_c (Σ_d u_d z_d) / (1 + β Σ_d s_d u_d)``, ``w = 1/(P2 + R/ρ)``, ``u = w s``,
    ``z = conj K̂ ⊙ Ŷ`` (A is positive definite: the denominator is > 0)."""
    s = R.sqrt()
    beta = (1 - 1 / rho) / 3
    w = 1 / (P2 + R / rho)  # (3, n, m, fy, fx'): the per-channel filter's denominator with R/ρ
    u = w * s
    r = u * (beta / (1 + beta * (s * u).sum(0)))  # (3, n, m, fy, fx')
    t = (Y[:, :, None, None] * (u * Kc)[None]).sum(1, keepdim=True)  # Σ_d u_d z_d: (B, 1, n, m, fy, fx')
    return Y[:, :, None, None] * (w * Kc)[None] - r[None] * t


def _multi_wiener(x, k, lam, mu, cy, cx, padding, rho=None):
    """Deconvolve ``x (B, C, H, W)`` (sensor orientation) with each node kernel of ``k (C, N, M, ky, kx)`` (or the
    expected-error filter of a set ``k (S, C, N, M, ky, kx)``) whose weight reaches the image, and blend with the
    renderer's bilinear weights; with ``rho`` (0-d) the colour prior's 3×3 solve instead of the per-channel
    filter."""
    if k.ndim == 5:
        k = k[None]
    B, C, H, W = x.shape
    ky, kx = k.shape[-2:]
    dev, dt = x.device, x.dtype
    wy = _hat_weights(cy, torch.arange(H, dtype=dt, device=dev), "bilinear")  # (N, H)
    wx = _hat_weights(cx, torch.arange(W, dtype=dt, device=dev), "bilinear")  # (M, W)
    _, _, has_y = _windows(wy)
    _, _, has_x = _windows(wx)
    iy, ix = torch.nonzero(has_y).reshape(-1), torch.nonzero(has_x).reshape(-1)
    wy, wx = wy[iy], wx[ix]
    k = k[:, :, iy][:, :, :, ix]  # (S, C, n, m, ky, kx)
    py, px = ky, kx  # a PSF's reach on every side
    mode = _PADDING[padding]
    if mode == "reflect" and (py >= H or px >= W):
        mode = "replicate"
    xp = F.pad(x, (px, px, py, py), mode=mode)
    Hp, Wp = xp.shape[-2:]
    fy, fx = _fast(Hp), _fast(Wp)
    Y = torch.fft.rfft2(xp, s=(fy, fx))  # (B, C, fy, fx//2+1)
    K = _kernel_spectrum(k, fy, fx)  # (S, C, n, m, fy, fx//2+1)
    lap = laplacian_power(fy, fx, dtype=dt, device=dev)
    R = lam[:, None, None, None, None] + mu[:, None, None, None, None] * lap  # (C, 1, 1, fy, fx')
    kc, p2 = K.conj().mean(0), (K.real.square() + K.imag.square()).mean(0)  # over the S maps
    if rho is None:
        XF = Y[:, :, None, None] * (kc / (p2 + R))[None]  # the expected-error filter over S
    else:
        XF = _colour_solve(Y, kc, p2, R, rho)
    X = torch.fft.irfft2(XF, s=(fy, fx))[..., py:py + H, px:px + W]  # (B, C, n, m, H, W)
    return torch.einsum("bcnmhw,nh,mw->bchw", X, wy, wx)


class WienerDeconv(nn.Module):
    """:func:`wiener_deconvolve` with a learned regularisation per colour channel: ``λ_c = exp(log_lambda_c)``
    and ``μ_c = exp(log_mu_c)`` (``nn.Parameter``; positive by construction).

    Args:
        channels: colour channels.
        init_lambda, init_mu: initial λ and μ (the noise-to-signal ratio of a well-exposed image is ~1e-4 –
            1e-2).
        init_chroma: initial ρ of the colour prior (module docstring; 3 channels), learned as
            ``ρ = min(exp(log_chroma), 1)``; None: the per-channel filter (no parameter).
    """

    def __init__(self, channels: int = 3, init_lambda: float = 1e-3, init_mu: float = 1e-2,
                 init_chroma: float | None = None):
        super().__init__()
        if not (init_lambda > 0 and init_mu > 0):
            raise ValueError("WienerDeconv: init_lambda and init_mu must be > 0")
        self.log_lambda = nn.Parameter(torch.full((channels,), math.log(init_lambda)))
        self.log_mu = nn.Parameter(torch.full((channels,), math.log(init_mu)))
        self.log_chroma = None
        if init_chroma is not None:
            _chroma(init_chroma, channels, torch.float64, None)  # range and channel count, now
            self.log_chroma = nn.Parameter(torch.tensor(math.log(init_chroma)))

    def chroma(self) -> torch.Tensor | None:
        """ρ of the colour prior (0-d, ≤ 1), or None."""
        return None if self.log_chroma is None else self.log_chroma.exp().clamp(max=1.0)

    def regularisation(self) -> torch.Tensor:
        """``(2, C)``: λ and μ per channel."""
        return torch.stack([self.log_lambda.exp(), self.log_mu.exp()])

    def forward(self, image: torch.Tensor, psf: torch.Tensor, **kw) -> torch.Tensor:
        """Deconvolve ``image (B, C, H, W)`` with the map ``psf (C, N, M, ks, ks)`` (or a set of maps
        ``(S, C, N, M, ks, ks)``, e.g. one per depth: the expected-error filter); ``kw`` as
        :func:`wiener_deconvolve` (positions, centers, sensor_size, pitch, extent, ...)."""
        reg = self.regularisation().to(image.dtype)
        rho = self.chroma()
        return wiener_deconvolve(image, psf, reg, chroma=None if rho is None else rho.to(image.dtype), **kw)
