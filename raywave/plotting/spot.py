"""Spot diagrams: one panel per field, wavelengths in colour, RMS radius in the title."""

from __future__ import annotations

import numpy as np
import torch

from raywave.lens.analysis import spot
from raywave.plotting._mpl import plt, save

WAVELENGTH_COLOURS = ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:orange"]


def plot_spots(lens, path=None, fields=None, wavelengths=None, pupil=("hexapolar", 6)):
    """Spot diagram per field (columns), all wavelengths overlaid, in µm about the centroid of the
    primary wavelength. Writes a PNG if ``path`` is given; returns the figure."""
    fields = list(lens.fields) if fields is None else list(fields)
    wls = list(lens.wavelengths) if wavelengths is None else list(wavelengths)
    with torch.no_grad():
        dx, dy, v, ref = spot(lens, fields, wls, pupil)
    # Common reference: the primary wavelength's centroid (so lateral colour shows).
    ip = lens.primary if wavelengths is None else 0
    x = (dx + ref[..., None, 0] - ref[:, ip, None, None, 0]).numpy() * 1e3
    y = (dy + ref[..., None, 1] - ref[:, ip, None, None, 1]).numpy() * 1e3
    v = v.numpy()
    fig, axes = plt.subplots(1, len(fields), figsize=(3.2 * len(fields), 3.9), constrained_layout=True, squeeze=False)
    w = v.astype(float)
    rms = np.sqrt(((dx.numpy() ** 2 + dy.numpy() ** 2) * w).sum(-1) / np.maximum(w.sum(-1), 1)) * 1e3
    rms = np.where(w.sum(-1) > 0, rms, np.nan)  # a fully vignetted field has no spot (never RMS 0)
    lim = max(float(np.abs(np.concatenate([x[v], y[v]])).max()) if v.any() else 1.0, 1e-3) * 1.1
    unit = "°" if lens.field_type == "angle" else " mm"
    for fi, ax in enumerate(axes[0]):
        for wi, wl in enumerate(wls):
            m = v[fi, wi]
            ax.scatter(x[fi, wi][m], y[fi, wi][m], s=3, color=WAVELENGTH_COLOURS[wi % 5], label=f"{wl:.4g} µm")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_title(f"field {_label(fields[fi])}{unit}\nRMS " + ", ".join("vignetted" if np.isnan(r) else f"{r:.3g}"
                                                                for r in rms[fi]) + " µm", fontsize=9)
        ax.set_xlabel("x (µm)")
    axes[0][0].set_ylabel("y (µm)")
    axes[0][0].legend(fontsize=7, loc="upper left")
    if path is not None:
        save(fig, path)
    return fig


def _label(f) -> str:
    """A field's label: ``14`` for a y value, ``3,14`` for an (x, y) pair."""
    return f"{f[0]:g},{f[1]:g}" if isinstance(f, (list, tuple)) else f"{f:g}"
