"""PSF maps as one mosaic image: the N×M PSFs placed at their sensor positions (+y up, +x right)."""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.plotting._mpl import new_figure, save

__all__ = ["plot_psf_map", "psf_mosaic"]


def _np(a) -> np.ndarray:
    return torch.as_tensor(a).detach().to(torch.float64).cpu().numpy() if not isinstance(a, np.ndarray) else a


def psf_mosaic(psf, gap: int = 1, normalise: str = "each", gamma: float = 1.0) -> np.ndarray:
    """Tile ``(N, M, ks, ks)`` (one channel) or ``(C, N, M, ks, ks)`` PSFs into one ``(N·(ks+gap), M·(ks+gap)[, C])``
    array, indexed ``[iy, ix]`` (show with ``origin="lower"``): node row i along +y, column j along +x.

    ``normalise="each"`` scales every PSF (and every channel) to its own peak, ``"global"`` by the map's peak;
    ``gamma`` < 1 brightens the wings (display only)."""
    a = _np(psf)
    if a.ndim == 4:
        a = a[None]
    if a.ndim != 5:
        raise ValueError(f"psf_mosaic: expected (N, M, ks, ks) or (C, N, M, ks, ks), got shape {a.shape}")
    C, N, M, ky, kx = a.shape
    if normalise == "each":
        peak = a.max(axis=(-1, -2), keepdims=True)
    elif normalise == "global":
        peak = a.max(axis=(1, 2, 3, 4), keepdims=True)
    else:
        raise ValueError(f"normalise must be 'each' or 'global', got {normalise!r}")
    a = np.where(peak > 0, a / np.where(peak > 0, peak, 1), 0.0) ** gamma
    out = np.zeros((C, N * (ky + gap), M * (kx + gap)))
    for i in range(N):
        for j in range(M):
            out[:, i * (ky + gap): i * (ky + gap) + ky, j * (kx + gap): j * (kx + gap) + kx] = a[:, i, j]
    return out[0] if C == 1 else np.moveaxis(out, 0, -1)


def plot_psf_map(psf_map, path=None, depth_index: int = 0, wavelength_index: int | None = None,
                 gamma: float = 0.5, title: str | None = None, gap: int = 1):
    """Mosaic of one depth of a :class:`~raywave.imaging.psfmap.PSFMap`, sensor orientation (``origin="lower"``),
    axes labelled with the nodes' normalised positions.

    Args:
        psf_map: the map.
        path: PNG to write (None: only return the figure).
        depth_index: which depth.
        wavelength_index: one wavelength (greyscale); None: an RGB composite of three wavelengths/channels in the
            map's order (R, G, B for :class:`~raywave.imaging.color.ColorSpec` maps), else the first one.
        gamma: display gamma on each PSF (normalised to its own peak); 0.5 shows the wings.
    Returns the figure.
    """
    psf = psf_map.psf[depth_index]
    W = psf.shape[0]
    wl = psf_map.wavelengths.tolist()
    if wavelength_index is None and W == 3:
        img = psf_mosaic(psf, gap=gap, gamma=gamma)
        label = "RGB " + "/".join(f"{w:g}" for w in wl) + " µm"
    else:
        k = 0 if wavelength_index is None else int(wavelength_index)
        img = psf_mosaic(psf[k], gap=gap, gamma=gamma)
        label = f"{wl[k]:g} µm"
    N, M = psf_map.grid
    ks = psf.shape[-1]
    side = 7.0
    fig, ax = new_figure(side * max(1.0, M / N) + 0.5, side * max(1.0, N / M))
    ax.imshow(img, origin="lower", cmap="inferno" if img.ndim == 2 else None, interpolation="nearest")
    pos = _np(psf_map.positions)
    if M <= 12:
        ax.set_xticks([j * (ks + gap) + (ks - 1) / 2 for j in range(M)])
        ax.set_xticklabels([f"{u:.2g}" for u in pos[0, :, 0]], fontsize=7)
    if N <= 12:
        ax.set_yticks([i * (ks + gap) + (ks - 1) / 2 for i in range(N)])
        ax.set_yticklabels([f"{v:.2g}" for v in pos[:, 0, 1]], fontsize=7)
    else:
        ax.set_yticks([])
    if M > 12:
        ax.set_xticks([])
    ax.set_xlabel("normalised sensor x (u)")
    ax.set_ylabel("normalised sensor y (v)")
    d = float(psf_map.depths[depth_index])
    depth = "inf" if math.isinf(d) else f"{d:g} mm"
    ax.set_title(title or (f"PSF map {N}×{M}, depth {depth}, {label}; {ks}×{ks} px of "
                           f"{psf_map.pitch * 1e3:g} µm, each PSF to its peak, gamma {gamma:g}"), fontsize=9)
    if path is not None:
        save(fig, path)
    return fig
