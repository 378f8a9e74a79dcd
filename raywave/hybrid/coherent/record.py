"""The record of one DOE-plane field (:class:`DOEField`) and :class:`SamplingWarning`."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch



_NEWTON_TOL = 1e-10  # mm on the DOE plane
_NEWTON_ITERS = 25


class SamplingWarning(UserWarning):
    """A grid too coarse for the phase it must carry, or a ray map that cannot be interpolated."""


class StopEdgeWarning(UserWarning):
    """The exit-pupil stop edge is approximate or unavailable: the Fresnel edge step on an edge whose radius of
    curvature is not large against its Fresnel zone (a small obscuration), or a lens whose exit pupil lies at
    infinity (the DOE-plane edge is used instead)."""


@dataclass
class DOEField:
    """The field arriving at the DOE plane for one point source and one wavelength.

    Attributes:
        envelope: complex128 ``(ny, nx)``: the field just before the DOE on the simulation-grid window,
            divided by the carrier ``exp(i k n (α x + β y))``; DOE aperture applied, DOE phase not.
        window: ``(iy0, ix0, ny, nx)`` in simulation-grid indices (for the DOE phase map).
        origin: ``(x, y)`` mm of the centre of window pixel (0, 0).
        pitch: simulation-grid pitch (mm).
        carrier: ``(α, β)`` direction cosines of the chief ray after the lens.
        n: refractive index between the DOE and the sensor.
        wavelength: µm.
        z: DOE → sensor distance (mm).
        center: ``(x, y)`` mm where the chief ray (through the refractive lens only) meets the sensor.
        rays: number of rays traced to build the field.
        mode: "accurate" or "faithful".
        full_grid: the envelope is the whole DOE grid with no carrier removed, for the paper's full 2×-padded
            angular-spectrum propagation.
        clipped: fraction of the beam's power (leaving the lens) that falls outside the DOE aperture and is
            blocked there (from traced rays; :func:`doe_clipping`).
        beam_half: largest |x| or |y| (mm) of the beam's geometric footprint on the DOE plane.
        stop_edge: where the field's geometric-optics edge was formed: "doe" (at the DOE plane) or
            "exit_pupil" (at the exit pupil, then propagated to the DOE plane by the angular spectrum).
        chief_tan: ``(d_x/d_z, d_y/d_z)`` of the chief ray between the DOE and the sensor (how far ``center``
            moves per mm of sensor displacement), set by ``HybridLens.doe_fields``; None (fields built elsewhere,
            or detached for a cache): the PSF is not differentiated with respect to the sensor distance.
    """

    envelope: torch.Tensor
    window: tuple
    origin: tuple
    pitch: float
    carrier: tuple
    n: float
    wavelength: float
    z: float
    center: tuple
    rays: int
    mode: str
    full_grid: bool = False
    clipped: float = 0.0
    beam_half: float = 0.0
    stop_edge: str = "doe"
    chief_tan: tuple | None = None

    @property
    def power(self) -> torch.Tensor:
        """∫|U|² dA over the DOE plane (relative power reaching the DOE through its aperture)."""
        return (self.envelope.abs() ** 2).sum() * self.pitch**2

    def detach(self) -> "DOEField":
        """A copy cut from the autograd graph (for caching with a frozen refractive lens): its PSF is not
        differentiated with respect to the lens, the sensor distance included (``chief_tan`` dropped)."""
        center = tuple(c.detach() if isinstance(c, torch.Tensor) else c for c in self.center)
        return replace(self, envelope=self.envelope.detach(), center=center, chief_tan=None)

    def to(self, dtype) -> "DOEField":
        """A copy with the envelope cast to ``dtype`` (e.g. complex64 for propagation only)."""
        return replace(self, envelope=self.envelope.to(dtype))
