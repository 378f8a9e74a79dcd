"""Figures (matplotlib, PNG). Physics modules never import this package (tests/test_layering.py)."""

from raywave.plotting.analysis import plot_fans, plot_mtf, plot_opd
from raywave.plotting.layout import plot_hybrid_layout, plot_layout, plot_midsystem_layout
from raywave.plotting.masks import plot_mask, plot_masks
from raywave.plotting.psf import plot_psf, plot_psf_grid
from raywave.plotting.spot import plot_spots

__all__ = ["plot_fans", "plot_hybrid_layout", "plot_layout", "plot_mask", "plot_masks", "plot_midsystem_layout", "plot_mtf", "plot_opd", "plot_psf",
           "plot_psf_grid", "plot_spots"]
