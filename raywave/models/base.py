"""The common base of the PSF models (:mod:`raywave.models.interface` builds them by name).

:class:`PSFModel` (the interface every model implements), :class:`ModelPSFResult`, the ray-wave engine behind the
interface (:class:`RayWaveModel`) and the helpers the wave models share (lit windows, propagation of DOE-plane
fields through the engine's steps 3–4). The model modules import this module, never :mod:`~raywave.models.interface`
(which imports them): no import cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from raywave.hybrid.coherent.geometry import lit_box
from raywave.hybrid.coherent.record import DOEField
from raywave.hybrid.hybrid_lens import HybridLens, PSFResult

__all__ = ["ModelPSFResult", "PSFModel", "RayWaveModel", "lit_window", "propagate_fields", "relative_l1",
           "window_field", "window_xy"]

@dataclass
class ModelPSFResult(PSFResult):
    """A :class:`~raywave.hybrid.PSFResult` plus ``model`` (its name) and ``info`` (model-specific diagnostics,
    e.g. the pupil model's Zernike coefficients and fit residual, the ray model's discontinuity report)."""

    model: str = ""
    info: dict = field(default_factory=dict)


def relative_l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Relative L1 distance ``Σ|a − b| / Σ|b|`` over the last two axes (``b`` the reference); (..., ks, ks)."""
    return (a - b).abs().sum((-2, -1)) / b.abs().sum((-2, -1)).clamp_min(1e-300)


def require_straight_axis(hybrid, name: str) -> None:
    """The comparison models read the lens along one straight +z axis: refuse a folded, decentred, tilted or
    mirrored lens (only the ray-wave engine traces it, in its image-space frame) instead of a wrong PSF."""
    from raywave.lens.frames import image_space

    lens = getattr(hybrid, "lens", None)
    if lens is not None and image_space(lens) is not lens:
        raise ValueError(f"the {name!r} model assumes one straight optical axis, but this lens has coordinate breaks "
                         "or mirrors; only the ray-wave model ('raywave', HybridLens.psf) traces it, in its "
                         "image-space frame")


class PSFModel(nn.Module):
    """Base class: holds the :class:`HybridLens` whose lens, DOE, DOE distance and sensor every model shares."""

    name = "base"
    straight_axis_only = True  # reads the lens along one straight +z axis (the ray-wave engine does not)

    def __init__(self, hybrid: HybridLens):
        super().__init__()
        if not isinstance(hybrid, HybridLens):
            raise TypeError(f"a comparison model is built on a raywave.hybrid.HybridLens, got {type(hybrid).__name__}")
        if self.straight_axis_only:
            require_straight_axis(hybrid, self.name)
        self.hybrid = hybrid

    @property
    def lens(self):
        return self.hybrid.lens

    @property
    def doe(self):
        return self.hybrid.doe

    def _wavelengths(self, wavelengths) -> list[float]:
        return self.hybrid.wavelength_list(wavelengths)

    @property
    def doe_field_source(self):
        """The :class:`HybridLens` whose DOE-plane fields (:meth:`HybridLens.doe_fields`) this model's PSFs are
        computed from, so that a cache of them (``psf_result(cache=)``, :class:`raywave.imaging.DOEFieldCache`)
        applies; None (the default) for a model that builds its own fields."""
        return None

    def _fields(self, fields) -> torch.Tensor:
        from raywave.lens.sources import _as_fields

        return _as_fields(fields, torch.float64, self.lens.device)

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> ModelPSFResult:
        """PSFs ``(F, W, ks, ks)`` with centres, energy outside the crop and diagnostics."""
        raise NotImplementedError

    def psf(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> torch.Tensor:
        """PSFs ``(F, W, ks, ks)`` (float64, each summing to 1)."""
        return self.psf_result(fields, wavelengths, ks, depth).psf

    def forward(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> torch.Tensor:
        return self.psf(fields, wavelengths, ks, depth)

    @staticmethod
    def _check_ks(ks) -> int:
        if isinstance(ks, bool) or int(ks) != ks or int(ks) < 1:
            raise ValueError(f"ks must be a positive integer (PSF size in sensor pixels), got {ks!r}")
        return int(ks)


class RayWaveModel(PSFModel):
    """The ray-wave engine itself (:meth:`HybridLens.psf_result`, accurate mode) behind the common interface.

    ``rays``: traced nodes across the lit footprint (default 64, see :meth:`HybridLens.doe_fields`)."""

    name = "raywave"
    straight_axis_only = False  # the engine traces folded / mirrored lenses in their image-space frame

    def __init__(self, hybrid: HybridLens, rays: int | None = None):
        super().__init__(hybrid)
        self.rays = rays

    @property
    def doe_field_source(self) -> HybridLens:
        """The engine itself: its DOE-plane fields are this model's (a field cache applies)."""
        return self.hybrid

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> ModelPSFResult:
        r = self.hybrid.psf_result(fields, wavelengths, self._check_ks(ks), depth, rays=self.rays)
        return ModelPSFResult(r.psf, r.center, r.energy_outside, r.pitch, r.rays, r.doe_clipped, model=self.name)


class PaperRayWaveModel(RayWaveModel):
    """The ray-wave engine as the paper builds it: the stop's sharp edge cut on the DOE plane
    (``HybridLens(stop_edge="doe")``), whatever the edge of the hybrid lens it is given (the default edge is the
    exit pupil's). Shares that hybrid's refractive lens and DOE."""

    name = "raywave_doe"

    def __init__(self, hybrid: HybridLens, rays: int | None = None):
        super().__init__(hybrid if hybrid.stop_edge == "doe" else hybrid.with_doe(hybrid.doe, stop_edge="doe"), rays)


# ------------------------------------------------------------------ shared helpers of the wave models
def lit_window(doe, oversample: int, bbox, margin: float):
    """Simulation-grid window ``(iy0, ix0, ny, nx)`` covering ``bbox = (xmin, xmax, ymin, ymax)`` ± ``margin``
    (mm), clamped to the DOE grid, and the (x, y) mm centre of its pixel (0, 0); None if it misses the grid."""
    sim = doe.sim_grid(oversample)
    box = lit_box(sim, bbox, margin)
    if box is None:
        return None, None
    iy0, iy1, ix0, ix1 = box
    return (iy0, ix0, iy1 - iy0, ix1 - ix0), sim.position(iy0, ix0)


def window_field(envelope: torch.Tensor, window, sim, wave: tuple, z: float, center: tuple, info) -> DOEField:
    """A model's :class:`~raywave.hybrid.DOEField`: ``envelope`` on the simulation-grid ``window``
    ``(iy0, ix0, ny, nx)`` (:func:`lit_window`; None: the empty 1×1 field at the grid's corner) of ``sim``
    (:meth:`raywave.doe.DOE.sim_grid`); ``wave`` = ``(wavelength µm, n, carrier)``; ``info`` a
    :class:`~raywave.hybrid.coherent.FieldInfo`."""
    iy0, ix0, ny, nx = (0, 0, 1, 1) if window is None else window
    return DOEField.on_box(envelope, (iy0, iy0 + ny, ix0, ix0 + nx), sim, wave, z, center, info)


def window_xy(window, origin, pitch: float, device=None):
    """Coordinates (mm, float64) of a window's samples: ``x`` (1, nx) and ``y`` (ny, 1)."""
    _, _, ny, nx = window
    x = origin[0] + torch.arange(nx, dtype=torch.float64, device=device) * pitch
    y = origin[1] + torch.arange(ny, dtype=torch.float64, device=device) * pitch
    return x[None, :], y[:, None]


def propagate_fields(hybrid: HybridLens, doe_fields, ks: int, name: str, info=None) -> ModelPSFResult:
    """Apply the DOE, propagate to the sensor and crop (the engine's steps 3–4, :meth:`HybridLens.propagate`)
    for a nested list ``[F][W]`` of :class:`~raywave.hybrid.DOEField` built by another model
    (:meth:`HybridLens.propagate_fields`)."""
    psf, center, outside, nr = hybrid.propagate_fields(doe_fields, ks)
    return ModelPSFResult(psf, center, outside, hybrid.sensor_pitch, nr, model=name, info=info or {})
