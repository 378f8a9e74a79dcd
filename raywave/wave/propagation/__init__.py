"""Free-space (homogeneous-medium) scalar propagation of sampled complex fields.

Pure functions; no state, no caching. The window propagation speaks :class:`~raywave.wave.grid.Field` /
:class:`~raywave.wave.grid.Grid` (issue 43): :func:`propagate_window` takes a Field and the output Grid and returns a
Field, :func:`propagate_batch` the same for a batched Field whose elements differ (wavelength, index, carrier,
window); the full-grid :func:`angular_spectrum` and the resampling work on tensors. Conventions shared by every
function here:

* Lengths (pitch, origins, z) in **mm**, wavelengths in **µm** (vacuum), ``n`` is the (real) medium index.
* Fields have shape ``(..., Ny, Nx)`` (any leading batch dims) and are indexed ``[iy, ix]``; the sample
  ``[iy, ix]`` sits at ``(x0 + ix·px, y0 + iy·py)`` where ``origin = (x0, y0)`` is the centre of pixel (0, 0),
  so coordinates increase with the index.
* ``pitch`` is a float (square pixels) or a pair ``(px, py)``.
* Time dependence ``exp(-iωt)``: a plane wave travelling towards +z is ``exp(+i k n z)``, so the transfer
  function is ``H(f) = exp(+i 2π z sqrt((n/λ)² - |f|²))``; evanescent components are set to 0 (never
  exponentially amplified, never NaN).
* complex128 by default, complex64 accepted (real input is promoted). The transfer function is always
  evaluated in float64 (the absolute phase 2π z n/λ reaches ~1e5 rad) and cast to the field's dtype.
* Differentiable with respect to the input field; ``z`` may also be a (0-d) tensor, in which case the result
  is differentiable with respect to it too (the band-limit weights and FFT sizes use its detached value and
  are held fixed in the derivative).

Split by concern (issue 17), every name importable from here as before: ``_common`` (argument checks, FFT sizes,
coordinates), ``full_grid`` (:func:`angular_spectrum`), ``transfer`` (:func:`window_transfer`), ``window``
(:func:`propagate_window`: a Field in, a Grid out), ``batch`` (:func:`propagate_batch`: many windows as one batch,
issue 43), ``sampling``
(:func:`nyquist_check`), ``resample`` (:func:`pixel_integrate`, :func:`integrated_upsampled_intensity` and its :func:`upsampled_pixel_weights`), ``fields`` (the same on :class:`~raywave.wave.grid.Field` values:
:func:`propagate_field`, :func:`angular_spectrum_field`, :func:`field_transfer`).
"""

from raywave.wave.propagation._common import (_TWO_PI, _UM_TO_MM, _as_field, _pair, _positive, _sqrt_kz,
                                              _transfer, _xy, _z_value, fast_fft_size, grid_coordinates)
from raywave.wave.propagation.batch import (BatchTransfer, WindowBatch, WindowSource, batch_transfer,
                                             propagate_batch)
from raywave.wave.propagation.fields import angular_spectrum_field, field_transfer, propagate_field
from raywave.wave.propagation.full_grid import angular_spectrum
from raywave.wave.propagation.resample import (_cubic_overlap_matrix, _keys_antiderivative, _overlap_matrix,
                                               integrated_upsampled_intensity, pixel_integrate,
                                               upsampled_pixel_weights)
from raywave.wave.propagation.sampling import NyquistReport, nyquist_check
from raywave.wave.propagation.transfer import WindowTransfer, window_transfer
from raywave.wave.propagation.window import _axial_frequency, _dz_tensor, _Perturbed, propagate_window

__all__ = [
    "BatchTransfer",
    "NyquistReport",
    "WindowBatch",
    "WindowSource",
    "WindowTransfer",
    "angular_spectrum",
    "batch_transfer",
    "angular_spectrum_field",
    "fast_fft_size",
    "field_transfer",
    "grid_coordinates",
    "integrated_upsampled_intensity",
    "nyquist_check",
    "pixel_integrate",
    "propagate_batch",
    "propagate_field",
    "propagate_window",
    "upsampled_pixel_weights",
    "window_transfer",
    # private names that were importable from the single module before the split (tests import _Perturbed)
    "_Perturbed",
    "_TWO_PI",
    "_UM_TO_MM",
    "_as_field",
    "_axial_frequency",
    "_cubic_overlap_matrix",
    "_dz_tensor",
    "_keys_antiderivative",
    "_overlap_matrix",
    "_pair",
    "_positive",
    "_sqrt_kz",
    "_transfer",
    "_xy",
    "_z_value",
]
