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
