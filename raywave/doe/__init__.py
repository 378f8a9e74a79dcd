"""Diffractive optical elements (thin phase elements on a pixel grid)."""

from raywave.doe.base import DOE, BlankDOE, PixelDOE

__all__ = ["DOE", "BlankDOE", "PixelDOE"]
