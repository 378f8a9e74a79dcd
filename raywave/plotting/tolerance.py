"""Figures of a fabrication tolerance Monte Carlo (:func:`raywave.assembly.tolerance.tolerance_monte_carlo`):
efficiency histograms, PSF-metric histograms, and the nominal vs the worst sample's PSF."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from raywave.plotting._mpl import save

__all__ = ["plot_efficiency_histograms", "plot_psf_comparison", "plot_psf_metric_histograms", "plot_tolerance"]

_PSF_LABELS = {"peak_ratio": "PSF peak / nominal peak", "l1": "Σ|PSF − nominal| / Σ nominal",
               "rms_radius_um": "RMS radius (µm)", "r80_um": "r80 (µm)", "crop_energy": "power in the crop"}


def _subplots(n: int, width: float = 3.4, height: float = 2.8):
    import matplotlib.pyplot as plt

    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols + 0.4, height * rows), constrained_layout=True,
                             squeeze=False)
    for ax in axes.reshape(-1)[n:]:
        ax.set_visible(False)
    return fig, axes.reshape(-1)


def _hist(ax, values, nominal=None, xlabel="", title=""):
    v = np.asarray(values, dtype=np.float64)
    bins = max(5, min(40, int(np.sqrt(v.size)) * 2))
    if np.ptp(v) == 0:
        bins = 1
    ax.hist(v, bins=bins, color="tab:blue", alpha=0.8)
    ax.axvline(v.mean(), color="k", lw=1, label=f"mean {v.mean():.4g}")
    if nominal is not None:
        ax.axvline(nominal, color="tab:red", ls="--", lw=1, label=f"nominal {nominal:.4g}")
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel("samples", fontsize=8)
    ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6)


def _suptitle(fig, text: str, fontsize: float = 9) -> None:
    """``fig.suptitle`` wrapped to the figure's width (a one-panel figure is ~3.8 inches wide: the settings line
    would be clipped at both ends)."""
    import textwrap

    chars = max(20, int(fig.get_figwidth() * 72 / (0.55 * fontsize)))  # average glyph ≈ 0.55 em
    fig.suptitle("\n".join(textwrap.wrap(text, chars)), fontsize=fontsize)


def _subtitle(res) -> str:
    tol = "2σ" if res.distribution == "normal" else "uniform"
    return (f"{res.levels} levels, depth ±{res.depth_error:g} %, misalignment ±{res.misalignment:g} px ({tol}), "
            f"{res.n_samples} samples, seed {res.seed}")


def plot_efficiency_histograms(res, path=None, orders=None):
    """Histograms of η_m of every sample, one panel per wavelength and order (default: order 1 if computed, else
    all), nominal value dashed. Returns the figure."""
    ords = [m for m in (orders if orders is not None else ([1] if 1 in res.orders else res.orders))
            if m in res.orders]
    panels = [(i, res.orders.index(m)) for i in range(len(res.wavelengths)) for m in ords]
    fig, axes = _subplots(len(panels))
    for ax, (i, j) in zip(axes, panels):
        _hist(ax, res.efficiency[:, i, j], float(res.nominal_efficiency[i, j]), f"η order {res.orders[j]}",
              f"{res.wavelengths[i]:g} µm")
    _suptitle(fig, "diffraction efficiency: " + _subtitle(res))
    if path is not None:
        save(fig, path)
    return fig


def plot_psf_metric_histograms(res, path=None, wavelength_index: int = 0):
    """Histograms of the PSF metrics of every sample at one wavelength. Returns the figure (None without PSFs)."""
    if res.psf is None:
        return None
    names = list(res.psf)
    fig, axes = _subplots(len(names))
    for ax, name in zip(axes, names):
        _hist(ax, res.psf[name][:, wavelength_index], float(res.nominal_psf_metrics[name][wavelength_index]),
              _PSF_LABELS.get(name, name))
    _suptitle(fig, f"PSF at {res.wavelengths[wavelength_index]:g} µm: " + _subtitle(res))
    if path is not None:
        save(fig, path)
    return fig


def plot_psf_comparison(res, path=None, log: bool = True, log_range: float = 1e-4):
    """The nominal PSF and the worst sample's (lowest peak ratio) side by side for every wavelength, one colour
    scale per wavelength (fractions of the incident power). Returns the figure (None without PSFs)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    if res.psf is None or res.worst_psf is None:
        return None
    W = len(res.wavelengths)
    fig, axes = plt.subplots(W, 2, figsize=(7.2, 3.2 * W), constrained_layout=True, squeeze=False)
    um = res.psf_pitch_um
    for i in range(W):
        a, b = res.nominal_psf[i], res.worst_psf[i]
        ny, nx = a.shape
        ext = [(-(nx // 2) - 0.5) * um, (nx - 1 - nx // 2 + 0.5) * um, (-(ny // 2) - 0.5) * um,
               (ny - 1 - ny // 2 + 0.5) * um]
        peak = float(max(a.max(), b.max()))
        norm = LogNorm(vmin=peak * log_range, vmax=peak) if log and peak > 0 else None
        for ax, img, label in ((axes[i][0], a, "nominal"),
                               (axes[i][1], b, f"worst sample #{res.worst_sample} (peak × "
                                               f"{res.psf['peak_ratio'][res.worst_sample, i]:.3f})")):
            shown = np.clip(img, peak * log_range, None) if norm is not None else img
            im = ax.imshow(shown, origin="lower", extent=ext, cmap="inferno", norm=norm, interpolation="nearest",
                           **({} if norm is not None else {"vmin": 0.0, "vmax": peak}))
            ax.set_title(f"{label}, {res.wavelengths[i]:g} µm", fontsize=8)
            ax.set_xlabel("x − x₀ (µm)", fontsize=8)
            ax.set_ylabel("y − y₀ (µm)", fontsize=8)
            ax.tick_params(labelsize=7)
        fig.colorbar(im, ax=axes[i][1], shrink=0.85, label="fraction of incident power").ax.tick_params(labelsize=7)
    _suptitle(fig, _subtitle(res))
    if path is not None:
        save(fig, path)
    return fig


def plot_tolerance(res, folder) -> list[Path]:
    """All tolerance figures into ``folder``: ``efficiency_hist.png``, and with PSFs ``psf_metrics_hist.png`` and
    ``psf_nominal_vs_worst.png``. Returns the paths written."""
    import matplotlib.pyplot as plt

    folder = Path(folder)
    out = []
    for name, fn in (("efficiency_hist.png", plot_efficiency_histograms),
                     ("psf_metrics_hist.png", plot_psf_metric_histograms),
                     ("psf_nominal_vs_worst.png", plot_psf_comparison)):
        fig = fn(res)
        if fig is not None:
            save(fig, folder / name)
            plt.close(fig)
            out.append(folder / name)
    return out
