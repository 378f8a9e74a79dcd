"""Make the README's figure, docs/img/hybrid_asphere.png, from the bundled hybrid lens.

Left: the section of ``hybrid_asphere`` (the H-K51 even asphere, a 3 mm DOE 0.7 mm behind it) with its ray fans
and the DOE plane. Right: its ray-wave PSFs on axis and at 0.7 of the field, the lens's three wavelengths as the
red, green and blue channels of one picture (each wavelength's PSF scaled to its own peak, square-root scale).

    PYTHONPATH=$PWD python docs/img/make_figures.py        # ~1 min on one CPU core

Nothing here is measured for the docs: the figure only shows what ``raywave demo`` computes.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from raywave.assembly.build import load_hybrid  # noqa: E402
from raywave.hybrid.hybrid_lens import DOEApertureWarning  # noqa: E402
from raywave.lens.build import resolve_lens_path  # noqa: E402
from raywave.plotting import plot_layout  # noqa: E402

HERE = Path(__file__).resolve().parent
KS = 48  # PSF crop (sensor pixels)


def rgb_psf(psf: np.ndarray, order: list[int]) -> np.ndarray:
    """(W, ks, ks) PSFs -> (ks, ks, 3) picture: wavelength ``order[c]`` in colour channel c (R, G, B), each
    scaled to its own peak, square-root scale."""
    chans = [np.sqrt(psf[w] / max(float(psf[w].max()), 1e-300)) for w in order]
    return np.clip(np.stack(chans, axis=-1), 0.0, 1.0)


def make_hybrid_figure(path: Path) -> Path:
    """The layout + RGB PSF figure of the bundled hybrid lens; returns the PNG's path."""
    hl = load_hybrid(resolve_lens_path("hybrid_asphere"))
    lens = hl.lens
    wls = list(lens.wavelengths)
    order = sorted(range(len(wls)), key=lambda i: -wls[i])  # longest wavelength -> red
    fields = [(0.0, 0.0), (0.7 * max(lens.fields), 0.0)]
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DOEApertureWarning)  # 1.4 % of the 12.25° red beam misses the 3 mm DOE
        res = hl.psf_result(fields, wls, ks=KS)
    psf = res.psf.detach().cpu().numpy()

    fig = plt.figure(figsize=(11.0, 3.9), constrained_layout=True)
    gs = fig.add_gridspec(1, 4, width_ratios=[2.4, 0.05, 1, 1])
    ax = fig.add_subplot(gs[0, 0])
    plot_layout(lens, ax=ax)
    zd = hl.doe_z()
    half = 0.5 * max(hl.doe.size)
    ax.plot([zd, zd], [-half, half], color="tab:purple", lw=2.5, label=f"DOE ({2 * half:g} mm)")
    ax.legend(loc="lower left", fontsize=8, frameon=False)
    ax.set_title("section and ray fans (fields along y)", fontsize=10)
    um = res.pitch * 1e3
    ext = [(-(KS // 2) - 0.5) * um, (KS - 1 - KS // 2 + 0.5) * um] * 2
    for k, f in enumerate(fields):
        a = fig.add_subplot(gs[0, 2 + k])
        a.imshow(rgb_psf(psf[k], order), origin="lower", extent=ext, interpolation="nearest")
        a.set_title("PSF on axis" if k == 0 else f"PSF at {f[0]:g}° (x)", fontsize=10)
        a.set_xlabel("x − x₀ (µm)", fontsize=8)
        if k == 0:
            a.set_ylabel("y − y₀ (µm)", fontsize=8)
        a.tick_params(labelsize=7)
    fig.suptitle(f"The bundled hybrid_asphere (H-K51 asphere + {2 * half:g} mm DOE {hl.doe_distance:g} mm behind it) "
                 f"and its ray-wave PSFs\nR / G / B = {' / '.join(f'{wls[i]:g}' for i in order)} µm, each to its "
                 f"own peak, √ scale, {um:g} µm pixels", fontsize=9)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


if __name__ == "__main__":
    out = make_hybrid_figure(HERE / "hybrid_asphere.png")
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KB)")
