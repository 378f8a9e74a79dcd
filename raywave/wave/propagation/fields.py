"""The propagation functions on the value types of :mod:`raywave.wave.grid`: a :class:`~raywave.wave.grid.Field`
in, a Field out (the tensor functions of this package, unchanged, do the work)."""

from __future__ import annotations

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation.full_grid import angular_spectrum
from raywave.wave.propagation.transfer import WindowTransfer, window_transfer
from raywave.wave.propagation.window import propagate_window


def _check(field: Field, where: str) -> None:
    if not isinstance(field, Field):
        raise TypeError(f"{where}: expected a Field, got {type(field).__name__}")


def field_transfer(field: Field, z, out: Grid, margin: float = 0.5, guard: float = 2.0,
                   weight_derivative: bool = False) -> WindowTransfer:
    """:func:`window_transfer` for propagating ``field`` by ``z`` mm onto ``out`` (reusable for every field of
    the same grid, wavelength, index and carrier)."""
    _check(field, "field_transfer")
    return window_transfer(field, out, z, margin=margin, guard=guard, weight_derivative=weight_derivative)


def propagate_field(field: Field, z, out: Grid, *, margin: float = 0.5, guard: float = 2.0, shift=None,
                    transfer=None, dz=None) -> Field:
    """Propagate ``field`` by ``z`` mm (float or 0-d tensor) onto the window ``out`` (same pitch, any origin and
    shape): :func:`propagate_window` (the same with ``z`` after ``out``); the result keeps the wavelength, index and
    carrier (its envelope is the true field divided by the same carrier at the output)."""
    _check(field, "propagate_field")
    return propagate_window(field, out, z, margin=margin, guard=guard, shift=shift, transfer=transfer, dz=dz)


def angular_spectrum_field(field: Field, z, pad: float = 2, band_limit: bool = True) -> Field:
    """:func:`angular_spectrum` on the field's own grid (full grid; the field must have no carrier: the full-grid
    path samples the true field)."""
    _check(field, "angular_spectrum_field")
    if not field.shared:
        raise ValueError("angular_spectrum_field: the field's elements differ in wavelength, index, carrier or window")
    if field.carrier != (0.0, 0.0):
        raise ValueError(f"angular_spectrum_field: the field has the carrier {field.carrier}; the full-grid path "
                         "propagates true fields: use propagate_field, or multiply the carrier in (Field.total)")
    u = angular_spectrum(field.envelope, field.grid.pitch, field.wavelength, z, field.n, pad, band_limit)
    return field.with_envelope(u)
