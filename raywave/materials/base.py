"""The material interface every optical medium in raywave implements.

A material maps a vacuum wavelength (µm) to a real refractive index, in float64, differentiably.
Indices are relative to air (catalog convention), so air itself has n = 1 exactly.
"""

from __future__ import annotations

import torch
from torch import nn


class Material(nn.Module):
    """Base class of optical media.

    Subclasses implement :meth:`n`. Coefficients live in buffers (or parameters, for model glasses
    that a design may optimise), so ``.to(device)`` and ``state_dict`` work.

    Attributes:
        name: the catalog name (e.g. ``"N-BK7"``), used in messages and when a lens is saved.
        wavelength_range: ``(lo, hi)`` in µm where the data are valid; ``(0, inf)`` if unbounded.
    """

    def __init__(self, name: str, wavelength_range: tuple[float, float] = (0.0, float("inf"))):
        super().__init__()
        self.name = name
        self.wavelength_range = (float(wavelength_range[0]), float(wavelength_range[1]))

    def n(self, wavelength: torch.Tensor) -> torch.Tensor:
        """Refractive index at vacuum wavelength ``wavelength`` (µm, any shape) -> same shape.

        The result has the wavelength tensor's floating dtype (float64 for a Python number), so a
        float64 trace stays float64 and a float32 benchmark trace stays float32.
        """
        raise NotImplementedError

    def forward(self, wavelength: torch.Tensor) -> torch.Tensor:
        return self.n(wavelength)

    @property
    def is_air(self) -> bool:
        return False

    def to_spec(self):
        """What a lens file stores for this material: a catalog name or a dict (see docs/lens-format.md)."""
        return self.name

    def extra_repr(self) -> str:
        return f"name={self.name!r}"


class ConstantIndex(Material):
    """A non-dispersive medium of fixed index ``index`` (e.g. an ideal-lens test, or a frozen glass)."""

    def __init__(self, index: float, name: str | None = None):
        super().__init__(name or f"n={index!r}")
        self.register_buffer("index", torch.tensor(float(index), dtype=torch.float64))

    def n(self, wavelength: torch.Tensor) -> torch.Tensor:
        if not isinstance(wavelength, torch.Tensor) or not wavelength.is_floating_point():
            wavelength = torch.as_tensor(wavelength, dtype=torch.float64, device="cpu")
        return self.index.to(device=wavelength.device, dtype=wavelength.dtype).expand(wavelength.shape)

    @property
    def is_air(self) -> bool:
        return bool(self.index.item() == 1.0)

    def to_spec(self):
        if self.is_air and self.name.lower() == "air":
            return "air"
        return {"index": float(self.index.item())}


class Air(ConstantIndex):
    """Air at catalog conditions: n = 1 by definition of relative indices."""

    def __init__(self):
        super().__init__(1.0, name="air")
