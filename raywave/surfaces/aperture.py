"""Clear apertures: which points (x, y) of a surface transmit light (local frame, mm)."""

from __future__ import annotations

import torch
from torch import nn


class Aperture(nn.Module):
    """Base class. ``contains(x, y)`` -> bool tensor; ``extent`` = largest |x| or |y| reached (mm)."""

    shape = "none"

    def contains(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def slack(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Signed distance (mm) from (x, y) to the aperture edge: > 0 inside, < 0 outside. Smooth across
        the edge, so the ray-wave model can place a vignetting edge with sub-pixel accuracy."""
        raise NotImplementedError

    @property
    def extent(self) -> float:
        raise NotImplementedError

    def to_spec(self) -> dict:
        raise NotImplementedError


class CircularAperture(Aperture):
    """A circle of ``radius`` (mm) about the axis."""

    shape = "circle"

    def __init__(self, radius: float):
        super().__init__()
        if not radius > 0:
            raise ValueError(f"circular aperture radius must be > 0 mm, got {radius!r}")
        self.register_buffer("radius", torch.tensor(float(radius), dtype=torch.float64))

    def contains(self, x, y):
        r = self.radius.to(x.dtype)
        return x * x + y * y <= r * r

    def slack(self, x, y):
        return self.radius.to(x.dtype) - torch.sqrt((x * x + y * y).clamp_min(1e-300))  # finite gradient at 0

    @property
    def extent(self) -> float:
        return float(self.radius)

    def set_radius(self, radius: float) -> None:
        self.radius.fill_(float(radius))

    def to_spec(self) -> dict:
        return {"shape": "circle", "radius": float(self.radius)}

    def extra_repr(self):
        return f"radius={float(self.radius)}"


class SquareAperture(Aperture):
    """A square |x|, |y| <= ``half_width`` (mm) (e.g. a square DOE or sensor)."""

    shape = "square"

    def __init__(self, half_width: float):
        super().__init__()
        if not half_width > 0:
            raise ValueError(f"square aperture half_width must be > 0 mm, got {half_width!r}")
        self.register_buffer("half_width", torch.tensor(float(half_width), dtype=torch.float64))

    def contains(self, x, y):
        h = self.half_width.to(x.dtype)
        return (x.abs() <= h) & (y.abs() <= h)

    def slack(self, x, y):
        return self.half_width.to(x.dtype) - torch.maximum(x.abs(), y.abs())

    @property
    def extent(self) -> float:
        return float(self.half_width) * 2**0.5

    def set_radius(self, radius: float) -> None:
        self.half_width.fill_(float(radius))

    def to_spec(self) -> dict:
        return {"shape": "square", "half_width": float(self.half_width)}

    def extra_repr(self):
        return f"half_width={float(self.half_width)}"


def aperture_from_spec(spec: dict | None) -> Aperture | None:
    """Build an aperture from the lens-file form ``{"shape": "circle", "radius": r}`` (or square, or None)."""
    if spec is None:
        return None
    if spec["shape"] == "circle":
        return CircularAperture(spec["radius"])
    if spec["shape"] == "square":
        return SquareAperture(spec["half_width"])
    raise ValueError(f"unknown aperture shape {spec['shape']!r} (expected 'circle' or 'square')")
