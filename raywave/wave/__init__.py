"""Scalar wave optics: free-space propagation of sampled complex fields (see :mod:`raywave.wave.propagation`);
the value types :class:`Grid` and :class:`Field` (:mod:`raywave.wave.grid`; a Field may carry leading batch axes on
one Grid, propagated together by :func:`propagate_batch`)."""

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation import (
    NyquistReport,
    WindowBatch,
    WindowTransfer,
    angular_spectrum,
    angular_spectrum_field,
    field_transfer,
    fast_fft_size,
    grid_coordinates,
    nyquist_check,
    pixel_integrate,
    propagate_batch,
    propagate_field,
    propagate_window,
    window_transfer,
)

__all__ = [
    "Field",
    "Grid",
    "NyquistReport",
    "WindowBatch",
    "WindowTransfer",
    "angular_spectrum",
    "angular_spectrum_field",
    "field_transfer",
    "fast_fft_size",
    "grid_coordinates",
    "nyquist_check",
    "pixel_integrate",
    "propagate_batch",
    "propagate_field",
    "propagate_window",
    "window_transfer",
]
