"""The window propagation's pre-issue-43 argument lists on its Field / Grid API (issue 43), for the tests that state
their cases in those terms: ``window(u, pitch, wavelength, z, in_origin, out_origin, out_shape, ...)`` is
``propagate_window(Field(u, Grid(in_origin, pitch, u.shape[-2:]), wavelength, n, carrier), Grid(out_origin, pitch,
out_shape), z, ...).envelope``, and ``transfer(...)`` the same for :func:`window_transfer`."""

import torch

from raywave.wave import Field, Grid
from raywave.wave.propagation import propagate_window, window_transfer


def field_of(u: torch.Tensor, pitch, wavelength: float, in_origin, n: float = 1.0, carrier=(0.0, 0.0)) -> Field:
    """The envelope ``u`` ``(..., ny, nx)`` as a Field (sample (0, 0) at ``in_origin``)."""
    return Field(u, Grid(in_origin, pitch, tuple(u.shape[-2:])), wavelength, n, carrier)


def window(u, pitch, wavelength, z, in_origin, out_origin, out_shape, n=1.0, carrier=(0.0, 0.0), **kw):
    """:func:`propagate_window` of the envelope ``u``: the output envelope."""
    out = Grid(out_origin, pitch, tuple(out_shape))
    return propagate_window(field_of(u, pitch, wavelength, in_origin, n, carrier), out, z, **kw).envelope


def transfer(in_shape, out_shape, pitch, wavelength, z, in_origin, out_origin, n=1.0, carrier=(0.0, 0.0), margin=0.5,
             guard=2.0, device=None, weight_derivative=False):
    """:func:`window_transfer` of the window pair (a zero Field of ``in_shape`` stands for the input)."""
    u = torch.zeros(tuple(in_shape), dtype=torch.complex128, device=device)
    return window_transfer(field_of(u, pitch, wavelength, in_origin, n, carrier), Grid(out_origin, pitch, out_shape),
                           z, margin=margin, guard=guard, weight_derivative=weight_derivative)
