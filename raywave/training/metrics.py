"""Image-quality metrics: PSNR and SSIM through torchmetrics' functional API (which needs no torchvision),
per image, for images in [0, 1] (``data_range`` 1). torchmetrics is imported on first use (it is slow to
import)."""

from __future__ import annotations

import torch

__all__ = ["psnr", "ssim", "zone_masks", "zone_metrics"]


def _check(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 4:
        raise ValueError(f"metrics need two (B, C, H, W) images of the same shape, got {tuple(pred.shape)} and "
                         f"{tuple(target.shape)}")


def psnr(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """PSNR (dB) of each image of a batch ``(B, C, H, W)`` → ``(B,)``."""
    from torchmetrics.functional.image import peak_signal_noise_ratio

    _check(pred, target)
    return peak_signal_noise_ratio(pred.detach(), target.detach(), data_range=data_range, reduction="none",
                                   dim=(1, 2, 3))


def ssim(pred: torch.Tensor, target: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """SSIM (Gaussian window σ = 1.5, 11 px; Wang et al. 2004) of each image ``(B, C, H, W)`` → ``(B,)``."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    _check(pred, target)
    return structural_similarity_index_measure(pred.detach(), target.detach(), data_range=data_range,
                                               reduction="none")


def zone_masks(h: int, w: int, centre_fraction: float = 0.5, device=None) -> dict[str, torch.Tensor]:
    """Boolean masks ``(h, w)`` of the field zones: ``"centre"`` = normalised radius r = √(u² + v²)/√2 below
    ``centre_fraction`` (u, v ∈ [-1, 1] across the image), ``"edge"`` = the rest."""
    v = (torch.arange(h, dtype=torch.float64, device=device) + 0.5) / h * 2 - 1
    u = (torch.arange(w, dtype=torch.float64, device=device) + 0.5) / w * 2 - 1
    r = torch.sqrt(v[:, None] ** 2 + u[None, :] ** 2) / 2 ** 0.5
    return {"centre": r < centre_fraction, "edge": r >= centre_fraction}


def zone_metrics(pred: torch.Tensor, target: torch.Tensor, centre_fraction: float = 0.5,
                 data_range: float = 1.0) -> dict[str, dict[str, float]]:
    """Mean PSNR (dB, from the zone's MSE per image) and SSIM (mean of the SSIM map over the zone) of a batch,
    for the centre and edge zones of :func:`zone_masks`: ``{"centre": {"psnr": .., "ssim": ..}, "edge": ..}``."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    _check(pred, target)
    pred, target = pred.detach(), target.detach()
    _, smap = structural_similarity_index_measure(pred, target, data_range=data_range, reduction="none",
                                                  return_full_image=True)
    out = {}
    for zone, m in zone_masks(*pred.shape[-2:], centre_fraction, pred.device).items():
        mse = ((pred - target).square() * m).sum((1, 2, 3)) / (m.sum() * pred.shape[1])
        p = 10 * torch.log10(data_range ** 2 / mse.clamp_min(1e-30))
        out[zone] = {"psnr": float(p.mean()), "ssim": float((smap * m).sum((1, 2, 3)).mean() / (m.sum() * pred.shape[1]))}
    return out
