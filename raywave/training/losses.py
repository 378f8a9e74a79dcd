"""Training losses: image losses (L1, MSE, RMSE), the EDoF loss of the paper (eq. 1 of the supplement), and the
PSF-only losses of the pre-stage (PSF size; similarity across depths).

**Mean-square-root error.** The paper uses "mean-square-root errors" for both EDoF terms; we read it as the
root-mean-square error ``sqrt(mean((a − b)²))`` (the square root of the MSE; it weights large errors less than
the MSE and, unlike the L1, is smooth). Its gradient at a zero error is made finite with ``eps``.
"""

from __future__ import annotations

import itertools

import torch

__all__ = ["l1_loss", "mse_loss", "rmse_loss", "image_loss", "edof_loss", "psf_size", "psf_size_loss",
           "psf_similarity_loss"]


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
