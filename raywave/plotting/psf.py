"""PSF images: the pixel-integrated PSF in µm about its centre pixel, linear or log colour scale."""

from __future__ import annotations

import numpy as np
import torch
from matplotlib.colors import LogNorm

from raywave.plotting._mpl import new_figure, save


def plot_psf(psf, pitch: float, path=None, log: bool = False, log_range: float = 1e-6, title: str | None = None,
             metrics: dict | None = None, cmap: str = "inferno"):
    """Image of a PSF ``[iy, ix]`` (pixel ``[ks//2, ks//2]`` = the centre, e.g. the chief ray) with
    ``origin="lower"`` (+y up), axes in µm relative to the centre, and a colour bar.

    Args:
        psf: (ks, ks) array (tensor or numpy), e.g. ``PSFResult.psf[f, w]``.
        pitch: pixel pitch (mm).
        path: PNG to write (None: only return the figure).
        log: logarithmic colour scale from ``log_range`` × the peak up to the peak.
        title: figure title.
        metrics: optional :func:`raywave.hybrid.metrics.psf_metrics` result (lengths in mm) to mark the
            centroid and the r80 circle.
    Returns the figure.
    """
    a = torch.as_tensor(psf).detach().to(torch.float64).cpu().numpy() if not isinstance(psf, np.ndarray) else psf
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"a PSF image is 2-D [iy, ix], got shape {a.shape}")
    ny, nx = a.shape
    um = pitch * 1e3
    extent = [(-(nx // 2) - 0.5) * um, (nx - 1 - nx // 2 + 0.5) * um,
              (-(ny // 2) - 0.5) * um, (ny - 1 - ny // 2 + 0.5) * um]
    fig, ax = new_figure(5.4, 4.6)
    peak = float(a.max()) if a.size else 0.0
    if log and peak > 0:
        norm = LogNorm(vmin=peak * log_range, vmax=peak)
        im = ax.imshow(np.clip(a, peak * log_range, None), origin="lower", extent=extent, cmap=cmap, norm=norm,
                       interpolation="nearest")
    else:
        im = ax.imshow(a, origin="lower", extent=extent, cmap=cmap, interpolation="nearest", vmin=0.0)
    fig.colorbar(im, ax=ax, label="energy per pixel" + (" (log)" if log else ""))
    if metrics is not None:
        cx, cy = (v * 1e3 for v in metrics["centroid"])
        ax.plot([cx], [cy], marker="+", color="cyan", ms=10, mew=1.2, label="centroid")
        if "r80" in metrics:
            t = np.linspace(0, 2 * np.pi, 181)
            r = metrics["r80"] * 1e3
            ax.plot(cx + r * np.cos(t), cy + r * np.sin(t), "--", color="cyan", lw=0.8, label="EE 80 %")
        ax.legend(fontsize=7, loc="upper right")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x − x₀ (µm)")
    ax.set_ylabel("y − y₀ (µm)")
    ax.set_aspect("equal")
    if title:
        ax.set_title(title, fontsize=9)
    if path is not None:
        save(fig, path)
    return fig


def plot_psf_grid(psfs, pitch: float, row_labels, col_labels, path=None, log: bool = True, log_range: float = 1e-5,
                  title: str | None = None, cmap: str = "inferno"):
    """A grid of PSF images ``psfs[r][c]`` (each (ks, ks), ``[iy, ix]``, ``origin="lower"``), axes in µm about
    the centre pixel; rows e.g. field points, columns wavelengths. Returns the figure."""
    import matplotlib.pyplot as plt

    rows, cols = len(psfs), len(psfs[0])
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols + 0.6, 2.9 * rows), constrained_layout=True,
                             squeeze=False)
    for r in range(rows):
        for c in range(cols):
            a = np.asarray(torch.as_tensor(psfs[r][c]).detach().to(torch.float64).cpu().numpy())
            ny, nx = a.shape
            um = pitch * 1e3
            extent = [(-(nx // 2) - 0.5) * um, (nx - 1 - nx // 2 + 0.5) * um,
                      (-(ny // 2) - 0.5) * um, (ny - 1 - ny // 2 + 0.5) * um]
            peak = float(a.max())
            ax = axes[r][c]
            if log and peak > 0:
                im = ax.imshow(np.clip(a, peak * log_range, None), origin="lower", extent=extent, cmap=cmap,
                               norm=LogNorm(vmin=peak * log_range, vmax=peak), interpolation="nearest")
            else:
                im = ax.imshow(a, origin="lower", extent=extent, cmap=cmap, interpolation="nearest", vmin=0.0)
            ax.set_title(f"{row_labels[r]}, {col_labels[c]}", fontsize=8)
            ax.tick_params(labelsize=7)
            if r == rows - 1:
                ax.set_xlabel("x − x₀ (µm)", fontsize=8)
            if c == 0:
                ax.set_ylabel("y − y₀ (µm)", fontsize=8)
        fig.colorbar(im, ax=axes[r][-1], shrink=0.85).ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    if path is not None:
        save(fig, path)
    return fig
