"""Training losses: image losses (L1, MSE, RMSE), the EDoF loss of the paper (eq. 1 of the supplement), and the
PSF-only losses of the pre-stage (PSF size; similarity across depths; restorability).

**Mean-square-root error.** The paper uses "mean-square-root errors" for both EDoF terms; we read it as the
root-mean-square error ``sqrt(mean((a − b)²))`` (the square root of the MSE; it weights large errors less than
the MSE and, unlike the L1, is smooth). Its gradient at a zero error is made finite with ``eps``.
"""

from __future__ import annotations

import itertools
import math

import torch

__all__ = ["l1_loss", "mse_loss", "rmse_loss", "image_loss", "edof_loss", "psf_size", "psf_size_loss",
           "psf_similarity_loss", "wiener_restoration_error", "psf_restorability_loss", "RESTORE_FILTERS"]

RESTORE_FILTERS = ("shared", "own")  # the restorability term's Wiener filter: one for all depths, or each depth's


def l1_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean absolute error."""
    return (a - b).abs().mean()


def mse_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean squared error."""
    return (a - b).square().mean()


def rmse_loss(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Root-mean-square error ``sqrt(mean((a − b)²) + eps)`` (the paper's "mean-square-root error")."""
    return torch.sqrt((a - b).square().mean() + eps)


_IMAGE_LOSSES = {"l1": l1_loss, "mse": mse_loss, "rmse": rmse_loss}


def image_loss(name: str):
    """An image loss by name: ``"l1"``, ``"mse"`` or ``"rmse"``."""
    if name not in _IMAGE_LOSSES:
        raise ValueError(f"unknown image loss {name!r}; known: {', '.join(_IMAGE_LOSSES)}")
    return _IMAGE_LOSSES[name]


def edof_loss(recon: torch.Tensor | list, target: torch.Tensor, alpha: float = 0.3, loss=rmse_loss) -> torch.Tensor:
    """The EDoF loss  L = Σ_{i≠j} ℓ(N(PSF_di ∗ I), N(PSF_dj ∗ I)) + α Σ_i ℓ(N(PSF_di ∗ I), I).

    Args:
        recon: reconstructions at the D depths, ``(D, B, C, H, W)`` or a list of D ``(B, C, H, W)``.
        target: the sharp image ``(B, C, H, W)``.
        alpha: weight of the fidelity term (paper 0.3).
        loss: ℓ, default :func:`rmse_loss`.
    The first sum runs over ordered pairs (i, j), i ≠ j, as written in the paper (each unordered pair twice for
    a symmetric ℓ)."""
    recon = list(recon)
    if len(recon) < 1:
        raise ValueError("edof_loss needs reconstructions at one depth at least")
    sim = sum((loss(recon[i], recon[j]) for i, j in itertools.permutations(range(len(recon)), 2)),
              torch.zeros((), dtype=target.dtype, device=target.device))
    fid = sum(loss(r, target) for r in recon)
    return sim + alpha * fid


def psf_size(psf: torch.Tensor, about: str = "centroid", eps: float = 1e-20) -> torch.Tensor:
    """RMS radius (pixels) of PSFs ``(..., ks, ks)``: sqrt(Σ p·r²/Σ p) with r measured from the PSF's centroid
    (``about="centroid"``: sharpness only) or from the chief-ray pixel ``[ks//2, ks//2]`` (``"center"``: also
    penalises a DOE that moves the image point). Shape ``(...)``."""
    if about not in ("centroid", "center"):
        raise ValueError(f"about must be 'centroid' or 'center', got {about!r}")
    ky, kx = psf.shape[-2:]
    y = torch.arange(ky, dtype=psf.dtype, device=psf.device) - ky // 2
    x = torch.arange(kx, dtype=psf.dtype, device=psf.device) - kx // 2
    tot = psf.sum((-2, -1)).clamp_min(eps)
    py, px = psf.sum(-1), psf.sum(-2)
    if about == "centroid":
        cy = (py * y).sum(-1) / tot
        cx = (px * x).sum(-1) / tot
    else:
        cy = cx = torch.zeros_like(tot)
    var = ((py * (y - cy[..., None]).square()).sum(-1) + (px * (x - cx[..., None]).square()).sum(-1)) / tot
    return torch.sqrt(var + eps)


def psf_size_loss(psf: torch.Tensor, about: str = "centroid") -> torch.Tensor:
    """Mean RMS radius (pixels) of a stack of PSFs (the pre-stage objective for aberration correction)."""
    return psf_size(psf, about).mean()


def psf_similarity_loss(psf_by_depth: torch.Tensor) -> torch.Tensor:
    """Mean L1 distance Σ|PSF_di − PSF_dj| (0 … 2 for normalised PSFs) over depth pairs i < j and all other
    leading dimensions; ``psf_by_depth`` is ``(D, ..., ks, ks)`` (the EDoF pre-stage's similarity term)."""
    d = psf_by_depth.shape[0]
    if d < 2:
        return torch.zeros((), dtype=psf_by_depth.dtype, device=psf_by_depth.device)
    pairs = [(psf_by_depth[i] - psf_by_depth[j]).abs().sum((-2, -1)).mean()
             for i, j in itertools.combinations(range(d), 2)]
    return torch.stack(pairs).mean()


def _image_spectrum(ky: int, kx: int, dtype, device) -> torch.Tensor:
    """A natural-image power spectrum on the ``ky × kx`` DFT grid, ``P(f) ∝ 1/(|f|² + f0²)`` (f in cycles per
    pixel, f0 = 1/max(ky, kx)), normalised to mean 1 (unit signal variance per pixel). Shape ``(ky, kx)``."""
    fy = torch.fft.fftfreq(ky, dtype=dtype, device=device)
    fx = torch.fft.fftfreq(kx, dtype=dtype, device=device)
    f0 = 1.0 / max(ky, kx)
    p = 1.0 / (fy[:, None].square() + fx[None, :].square() + f0 ** 2)
    return p / p.mean()


def wiener_restoration_error(psf_by_depth: torch.Tensor, noise: float = 1e-3, filter: str = "shared") -> torch.Tensor:
    """Expected error (dB, relative to the signal variance) of restoring each depth's image with **one** Wiener
    filter, the one of least error averaged over the depths (the camera does not know the distance; the filter of
    :func:`raywave.imaging.deconv.wiener_deconvolve` given a set of maps).

    For OTFs ``K_d`` (the PSFs' DFTs about the chief-ray pixel ``[ks//2, ks//2]``), an image spectrum ``P``
    (:func:`_image_spectrum`) and white noise of variance ``noise`` (relative to the image's):
    ``G = mean_d conj(K_d) P / (mean_d |K_d|² P + noise)`` and depth d's error per frequency is
    ``|G K_d − 1|² P + |G|² noise``; the result is ``10 log10`` of its mean over the frequencies.

    ``filter="own"``: each depth restored with **its own** Wiener filter (a reconstruction that knows, or finds
    from the image, the depth: ``network.deconv: wiener_select``), ``G_d = conj(K_d) P / (|K_d|² P + noise)``,
    whose error per frequency is ``noise · P / (|K_d|² P + noise)``.

    Args:
        psf_by_depth: ``(D, ..., ky, kx)`` PSFs (each normalised to sum 1), D depths first.
        noise: noise variance relative to the image variance (> 0).
        filter: ``"shared"`` (one filter for all depths) or ``"own"`` (each depth's filter).

    Returns:
        ``(D, ...)`` errors in dB (lower is better; −PSNR-like).
    """
    if not noise > 0:
        raise ValueError(f"noise must be > 0, got {noise}")
    if filter not in RESTORE_FILTERS:
        raise ValueError(f"filter must be one of {', '.join(RESTORE_FILTERS)}, got {filter!r}")
    ky, kx = psf_by_depth.shape[-2:]
    k = torch.fft.fft2(torch.fft.ifftshift(psf_by_depth, dim=(-2, -1)))
    p = _image_spectrum(ky, kx, psf_by_depth.dtype, psf_by_depth.device)
    if filter == "own":
        # |K|² as Re² + Im²: differentiable where a frequency is exactly zero (abs() is not)
        a = k.real.square() + k.imag.square()
        return 10 * torch.log10((noise * p / (a * p + noise)).mean((-2, -1)))
    a = k.abs().square().mean(0)
    g = k.mean(0).conj() * p / (a * p + noise)
    err = (g * k - 1).abs().square() * p + g.abs().square() * noise
    return 10 * torch.log10(err.mean((-2, -1)))


def psf_restorability_loss(psf_by_depth: torch.Tensor, noise: float = 1e-3, temperature: float = 1.0,
                           filter: str = "shared") -> torch.Tensor:
    """The pre-stage's restorability term: a soft maximum over depths (log-mean-exp with ``temperature`` dB) of
    :func:`wiener_restoration_error`, averaged over the other leading dimensions (fields, colours). It
    favours PSFs that the deconvolution (one filter, or each depth's with ``filter="own"``) restores well at
    *every* depth, the worst depth most. dB, scalar.

    Args:
        psf_by_depth: ``(D, ..., ky, kx)`` normalised PSFs.
        noise: noise variance relative to the image variance.
        temperature: dB; → 0 gives the worst depth, large values the mean over depths.
        filter: ``"shared"`` (one filter for all depths) or ``"own"`` (each depth's;
            :func:`wiener_restoration_error`).
    """
    e = wiener_restoration_error(psf_by_depth, noise, filter)
    d = e.shape[0]
    soft = temperature * (torch.logsumexp(e / temperature, dim=0) - math.log(d))
    return soft.mean()
