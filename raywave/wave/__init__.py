"""Scalar wave optics: free-space propagation of sampled complex fields (see :mod:`raywave.wave.propagation`)."""

from raywave.wave.propagation import (
    NyquistReport,
    WindowTransfer,
    angular_spectrum,
    fast_fft_size,
    grid_coordinates,
    nyquist_check,
    pixel_integrate,
    propagate_window,
    window_transfer,
)

__all__ = [
    "NyquistReport",
    "WindowTransfer",
    "angular_spectrum",
    "fast_fft_size",
    "grid_coordinates",
    "nyquist_check",
    "pixel_integrate",
    "propagate_window",
    "window_transfer",
]
