"""Scalar wave optics: free-space propagation of sampled complex fields (see :mod:`raywave.wave.propagation`);
the value types :class:`Grid` and :class:`Field` (:mod:`raywave.wave.grid`)."""

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import (
    NyquistReport,
    WindowTransfer,
    angular_spectrum,
    angular_spectrum_field,
    field_transfer,
    fast_fft_size,
    grid_coordinates,
    nyquist_check,
    pixel_integrate,
    propagate_field,
    propagate_window,
    window_transfer,
)

__all__ = [
    "Field",
    "Grid",
    "NyquistReport",
    "WindowTransfer",
    "angular_spectrum",
    "angular_spectrum_field",
    "field_transfer",
    "fast_fft_size",
    "grid_coordinates",
    "nyquist_check",
    "pixel_integrate",
    "propagate_field",
    "propagate_window",
    "window_transfer",
]
