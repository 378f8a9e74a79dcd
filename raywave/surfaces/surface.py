"""A sequential surface = geometry × aperture × interaction, followed by a medium and a gap."""

from __future__ import annotations

import torch
from torch import nn

from raywave.materials.base import Material
from raywave.surfaces.aperture import Aperture
from raywave.surfaces.geometry import Geometry
from raywave.surfaces.interaction import Interaction, Refraction


class Surface(nn.Module):
    """One surface of a sequential lens.

    Args:
        geometry: the shape (local frame at the vertex).
        material: the medium *after* the surface (Zemax convention).
        thickness: distance (mm) from this vertex to the next one (for the last surface: to the image
            plane). A real parameter, so a design can optimise it.
        aperture: hard clear aperture (rays outside become invalid) or None.
        interaction: what happens at the surface (default: refraction).
        is_stop: whether this surface is the aperture stop.
        semi_diameter: drawing/mechanical size (mm), does not clip; None = computed from the rays.
        comment: free text kept in lens files.
    """

    def __init__(
        self,
        geometry: Geometry,
        material: Material,
        thickness: float,
        aperture: Aperture | None = None,
        interaction: Interaction | None = None,
        is_stop: bool = False,
        semi_diameter: float | None = None,
        comment: str = "",
    ):
        super().__init__()
        self.geometry = geometry
        self.material = material
        self.thickness = nn.Parameter(torch.tensor(float(thickness), dtype=torch.float64))
        self.aperture = aperture
        self.interaction = interaction if interaction is not None else Refraction()
        self.is_stop = bool(is_stop)
        self.semi_diameter = semi_diameter
        self.comment = comment

    @property
    def kind(self) -> str:
        """Lens-file type name: 'standard', 'even_asphere', 'odd_asphere', 'toroidal', 'paraxial' or 'coordinate_break'
        (a mirror is any of the shapes with a reflecting interaction)."""
        from raywave.surfaces.geometry import EvenAsphere, OddAsphere, Toroidal

        if self.interaction.kind == "ideal_lens":
            return "paraxial"
        if self.interaction.kind == "coordinate_break":
            return "coordinate_break"
        if isinstance(self.geometry, EvenAsphere):
            return "even_asphere"
        if isinstance(self.geometry, OddAsphere):
            return "odd_asphere"
        if isinstance(self.geometry, Toroidal):
            return "toroidal"
        return "standard"

    def clear_radius(self) -> float | None:
        """Largest radius that transmits (mm), from the aperture, else the semi-diameter, else None."""
        if self.aperture is not None and self.aperture.extent is not None:  # None: an obscuration alone
            return self.aperture.extent
        return self.semi_diameter

    def extra_repr(self):
        stop = ", stop" if self.is_stop else ""
        return f"thickness={float(self.thickness.detach()):.6g}, material={self.material.name!r}{stop}"
