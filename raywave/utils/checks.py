"""Argument checks shared by the physics modules (clear errors that name the quantity and its unit)."""

from __future__ import annotations

import math


def positive_float(x, name: str, unit: str = "mm") -> float:
    """``float(x)`` if it is a finite number > 0, else a ValueError naming ``name`` and ``unit``."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number > 0 ({unit}), got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be > 0 {unit}, got {x!r}")
    return v


#: The largest wavelength (µm) raywave accepts anywhere (lens files, DOEs, the CLI): a larger number is almost
#: certainly a wavelength given in nm. Defined once here.
MAX_WAVELENGTH_UM = 100.0
#: Field angles (degrees) must be smaller than this in magnitude (lens files, traced sources): at 90° the chief
#: ray travels across the axis. Defined once here.
MAX_FIELD_ANGLE = 90.0


def wavelength_um(w, name: str = "wavelength") -> float:
    """``float(w)`` if it is a wavelength in µm (finite, 0 < λ <= :data:`MAX_WAVELENGTH_UM`), else a ValueError
    naming ``name`` (and suggesting µm when the number looks like nm)."""
    try:
        v = float(w)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a wavelength in µm, got {w!r}") from None
    if not (math.isfinite(v) and 0 < v <= MAX_WAVELENGTH_UM):
        raise ValueError(f"{name} must be a wavelength in µm (0 < λ <= {MAX_WAVELENGTH_UM:g}), got {w!r}")
    return v
