"""The propagation functions on the value types of :mod:`raywave.wave.grid`: a :class:`~raywave.wave.grid.Field`
in, a Field out (the tensor functions of this package, unchanged, do the work)."""

from __future__ import annotations

from raywave.wave.grid import Field, Grid
from raywave.wave.propagation.full_grid import angular_spectrum
from raywave.wave.propagation.transfer import WindowTransfer, window_transfer
from raywave.wave.propagation.window import propagate_window


def _check(field: Field, out: Grid | None, where: str) -> None:
    if not isinstance(field, Field):
        raise TypeError(f"{where}: expected a Field, got {type(field).__name__}")
    if out is not None and not isinstance(out, Grid):
        raise TypeError(f"{where}: the output window must be a Grid, got {type(out).__name__}")
    if out is not None and out.pitch != field.grid.pitch:
        raise ValueError(f"{where}: the output grid's pitch {out.pitch} differs from the field's {field.grid.pitch}")


def field_transfer(field: Field, z, out: Grid, margin: float = 0.5, guard: float = 2.0,
                   weight_derivative: bool = False) -> WindowTransfer:
    """:func:`window_transfer` for propagating ``field`` by ``z`` mm onto ``out`` (reusable for every field of
    the same grid, wavelength, index and carrier)."""
    _check(field, out, "field_transfer")
    g = field.grid
    return window_transfer(g.shape, out.shape, g.pitch, field.wavelength, z, g.origin, out.origin, field.n,
                           field.carrier, margin, guard, field.envelope.device, weight_derivative)


def propagate_field(field: Field, z, out: Grid, *, margin: float = 0.5, guard: float = 2.0, shift=None,
                    transfer=None, dz=None) -> Field:
    """Propagate ``field`` by ``z`` mm (float or 0-d tensor) onto the window ``out`` (same pitch, any origin and
    shape): :func:`propagate_window` with the field's grid, wavelength, index and carrier; the result keeps the
    carrier (its envelope is the true field divided by the same carrier at the output)."""
    _check(field, out, "propagate_field")
    g = field.grid
    u = propagate_window(field.envelope, g.pitch, field.wavelength, z, g.origin, out.origin, out.shape, n=field.n,
                         carrier=field.carrier, margin=margin, guard=guard, shift=shift, transfer=transfer, dz=dz)
    return field.with_envelope(u, out)


def angular_spectrum_field(field: Field, z, pad: float = 2, band_limit: bool = True) -> Field:
    """:func:`angular_spectrum` on the field's own grid (full grid; the field must have no carrier: the full-grid
    path samples the true field)."""
    _check(field, None, "angular_spectrum_field")
    if field.carrier != (0.0, 0.0):
        raise ValueError(f"angular_spectrum_field: the field has the carrier {field.carrier}; the full-grid path "
                         "propagates true fields: use propagate_field, or multiply the carrier in (Field.total)")
    u = angular_spectrum(field.envelope, field.grid.pitch, field.wavelength, z, field.n, pad, band_limit)
    return field.with_envelope(u)
