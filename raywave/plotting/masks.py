"""PNG previews of lithography masks (:mod:`raywave.doe.fabrication`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from raywave.plotting._mpl import new_figure, save

__all__ = ["MAX_PREVIEW_PIXELS", "downsample_mask", "plot_mask", "plot_masks"]

#: Masks larger than this (pixels along the longer side) are shown block-averaged.
MAX_PREVIEW_PIXELS = 1000


def downsample_mask(mask, max_pixels: int = MAX_PREVIEW_PIXELS) -> tuple[np.ndarray, int]:
    """(image, factor): the etched fraction of ``factor × factor`` blocks (float in [0, 1]), ``factor`` the
    smallest integer that brings the longer side to ``max_pixels`` or below (1: the mask as it is)."""
    m = np.asarray(mask, dtype=bool)
    ny, nx = m.shape
    f = max(1, -(-max(ny, nx) // int(max_pixels)))
    if f == 1:
        return m.astype(np.float64), 1
    py, px = -ny % f, -nx % f
    a = np.pad(m.astype(np.float32), ((0, py), (0, px)))
    cnt = np.pad(np.ones((ny, nx), np.float32), ((0, py), (0, px)))
    s = a.reshape(a.shape[0] // f, f, a.shape[1] // f, f).sum((1, 3))
    c = cnt.reshape(s.shape[0], f, s.shape[1], f).sum((1, 3))
    return (s / c).astype(np.float64), f


def plot_mask(mask, pitch: float, path, title: str | None = None) -> Path:
    """One mask as a PNG: etched pixels black, axes in mm about the DOE centre (origin lower, as the DOE grid)."""
    img, f = downsample_mask(mask)
    ny, nx = np.asarray(mask).shape
    w, h = nx * pitch / 2, ny * pitch / 2
    aspect = ny / nx
    fig, ax = new_figure(6.0, max(2.5, min(9.0, 5.0 * aspect + 1.0)))
    ax.imshow(img, cmap="gray_r", vmin=0, vmax=1, origin="lower", extent=(-w, w, -h, h),
              interpolation="nearest" if f == 1 else "antialiased")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    t = title or "mask"
    if f > 1:
        t += f"\n(preview: etched fraction of {f}×{f}-pixel blocks)"
    ax.set_title(t, fontsize=9)
    save(fig, path)
    return Path(path)


def plot_masks(masks, pitch: float, folder, depths_nm=None, stem: str = "mask") -> list[Path]:
    """``folder/{stem}_{j}.png`` for every mask j = 1..k (black = etched); returns the paths."""
    m = np.asarray(masks, dtype=bool)
    out = []
    for j in range(m.shape[0]):
        depth = "" if depths_nm is None else f", etch {depths_nm[j]:.1f} nm"
        title = (f"mask {j + 1} of {m.shape[0]} (layer {j + 1}{depth}), etched fraction {m[j].mean():.3f}, "
                 f"pitch {pitch * 1e3:g} µm")
        out.append(plot_mask(m[j], pitch, Path(folder) / f"{stem}_{j + 1}.png", title))
    return out
