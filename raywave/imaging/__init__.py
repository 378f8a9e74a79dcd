"""Imaging: PSF maps over field, depth and colour; spatially-varying image simulation; the sensor; image data.

Data flow: a PSF model (``raywave.hybrid.HybridLens`` or a comparison model from ``raywave.models``) → PSF map
→ rendered image → sensor. This package never imports plotting, the CLI or ``raywave.training``.

* :mod:`raywave.imaging.psfmap`: :func:`field_grid`, :func:`psf_map` → :class:`PSFMap`, :func:`psf_map_points`
  (differentiable subsets for the training replay), :class:`DOEFieldCache` (frozen refractive lens).
* :mod:`raywave.imaging.color`: :class:`ColorSpec` (three wavelengths per channel, random draw for training,
  weighted average for evaluation).
* :mod:`raywave.imaging.render`: :func:`render` (spatially varying, seam-free, differentiable), :func:`render_map`,
  :func:`render_rgbd` (depth layers), :func:`render_reference` (per-pixel ground truth).
* :mod:`raywave.imaging.sensor`: :class:`Sensor` (Poisson–Gaussian noise, saturation, bit depth), sRGB.
* :mod:`raywave.imaging.data`: image folders, the offline sample-photo pool, dead leaves.
"""

from raywave.imaging.color import DEFAULT_CHANNEL_WAVELENGTHS, ColorSpec, shift_psf
from raywave.imaging.psfmap import (DOEFieldCache, PSFCropWarning, PSFMap, field_grid, fields_at, node_values,
                                    normalised_grid, psf_map, psf_map_points, sensor_size_of)
from raywave.imaging.render import (depth_layer_weights, pixel_positions, render, render_map, render_reference,
                                    render_rgbd, resample_psf)
from raywave.imaging.sensor import Sensor, apply_gamma, linear_to_srgb, srgb_to_linear

__all__ = ["DEFAULT_CHANNEL_WAVELENGTHS", "ColorSpec", "DOEFieldCache", "PSFCropWarning", "PSFMap", "Sensor",
           "apply_gamma", "depth_layer_weights", "field_grid", "fields_at", "linear_to_srgb", "node_values",
           "normalised_grid", "pixel_positions", "psf_map", "psf_map_points", "render", "render_map",
           "render_reference", "render_rgbd", "resample_psf", "sensor_size_of", "shift_psf", "srgb_to_linear"]
