"""Classical analyses as PNGs: MTF curves, ray fans, OPD maps with their Zernike fit."""

from __future__ import annotations

import math

import numpy as np

from raywave.plotting._mpl import plt, save

FIELD_COLOURS = ["tab:blue", "tab:green", "tab:red", "tab:orange", "tab:purple", "tab:brown"]
WAVELENGTH_COLOURS = ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:orange"]


def _field_label(f, unit: str) -> str:
    x, y = float(f[0]), float(f[1])
    return f"{y:g}{unit}" if x == 0 else f"({x:g}, {y:g}){unit}"


def plot_mtf(result, path=None, field_unit: str = "°", title: str | None = None, reference=None):
    """MTF curves of a :class:`raywave.lens.mtf.MTFResult`: one colour per field, tangential solid, sagittal dashed;
    ``reference`` (K,) (e.g. the diffraction limit) in black dotted. Writes a PNG if ``path``; returns the figure."""
    fig, ax = plt.subplots(figsize=(7.5, 4.5), constrained_layout=True)
    nu = result.frequencies.cpu().numpy()
    for i, f in enumerate(result.fields.cpu().numpy()):
        c = FIELD_COLOURS[i % len(FIELD_COLOURS)]
        lab = _field_label(f, field_unit)
        ax.plot(nu, result.tangential[i].cpu().numpy(), color=c, label=f"{lab} T")
        ax.plot(nu, result.sagittal[i].cpu().numpy(), color=c, ls="--", label=f"{lab} S")
    if reference is not None:
        ax.plot(nu, np.asarray(reference), color="k", ls=":", label="diffraction limit")
    ax.set_xlim(0, float(nu.max()) if nu.size else 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("spatial frequency (cycles/mm)")
    ax.set_ylabel("modulation")
    wl = ", ".join(f"{w:.4g}" for w in result.wavelengths)
    ax.set_title(title or f"{result.kind} MTF, {wl} µm")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    if path is not None:
        save(fig, path)
    return fig


def plot_fans(fan, path=None, field_unit: str = "°", title: str | None = None, opd=None):
    """Ray fans of a :class:`raywave.lens.fans.RayFan` (µm): one row per field, tangential (ey vs py) left and
    sagittal (ex vs px) right, wavelengths in colour; with ``opd`` (an :class:`raywave.lens.fans.OPDFan`) a second
    pair of columns with the OPD fans (waves)."""
    nf = fan.fields.shape[0]
    ncol = 2 if opd is None else 4
    fig, axes = plt.subplots(nf, ncol, figsize=(3.3 * ncol, 2.6 * nf), squeeze=False, constrained_layout=True)
    p = fan.pupil.cpu().numpy()
    for i in range(nf):
        lab = _field_label(fan.fields[i].cpu().numpy(), field_unit)
        panels = [(fan.ey, "py", "ey (µm)", 1e3), (fan.ex, "px", "ex (µm)", 1e3)]
        if opd is not None:
            panels += [(opd.w_t, "py", "OPD (waves)", 1.0), (opd.w_s, "px", "OPD (waves)", 1.0)]
        for j, (data, xl, yl, scale) in enumerate(panels):
            ax = axes[i][j]
            for w, wl in enumerate(fan.wavelengths):
                ax.plot(p, data[i, w].cpu().numpy() * scale, color=WAVELENGTH_COLOURS[w % 5], label=f"{wl:.4g} µm")
            ax.axhline(0, color="0.6", lw=0.6)
            ax.set_title(f"{lab} {'tangential' if j % 2 == 0 else 'sagittal'}", fontsize=9)
            ax.set_xlabel(xl)
            ax.set_ylabel(yl)
    axes[0][0].legend(fontsize=7)
    if title:
        fig.suptitle(title)
    if path is not None:
        save(fig, path)
    return fig


def plot_opd(opd_map, fit=None, path=None, n: int | None = None, title: str | None = None):
    """An OPD map (waves) of a :class:`raywave.lens.opd.OPDMap` sampled on a square grid (``n`` × ``n``, inferred
    when the samples are one), with the first Zernike coefficients of ``fit`` as a bar chart beside it."""
    ncol = 1 if fit is None else 2
    fig, axes = plt.subplots(1, ncol, figsize=(5.0 * ncol, 4.3), squeeze=False, constrained_layout=True)
    ax = axes[0][0]
    m = opd_map.opd.cpu().numpy()
    n = int(round(math.sqrt(m.size))) if n is None else n
    if n * n == m.size:
        im = ax.imshow(m.reshape(n, n), origin="lower", extent=(-1, 1, -1, 1), cmap="RdBu_r")
    else:  # scattered samples (e.g. hexapolar)
        v = opd_map.valid.cpu().numpy()
        im = ax.scatter(opd_map.px.cpu().numpy()[v], opd_map.py.cpu().numpy()[v], c=m[v], s=12, cmap="RdBu_r")
        ax.set_aspect("equal")
    fig.colorbar(im, ax=ax, label="OPD (waves)")
    ax.set_xlabel("px")
    ax.set_ylabel("py")
    ax.set_title(title or f"OPD, field {opd_map.field}, {opd_map.wavelength:g} µm\n"
                 f"RMS {opd_map.rms():.4g}, P-V {opd_map.peak_to_valley():.4g} waves", fontsize=9)
    if fit is not None:
        c = fit.coefficients.cpu().numpy()
        ax2 = axes[0][1]
        ax2.bar(np.arange(1, c.size + 1), c, color="tab:blue")
        ax2.set_xlabel(f"{fit.ordering} Zernike term")
        ax2.set_ylabel("coefficient (waves)")
        ax2.set_title(f"Zernike fit, residual RMS {fit.residual_rms:.3g} waves", fontsize=9)
        ax2.grid(alpha=0.3)
    if path is not None:
        save(fig, path)
    return fig
