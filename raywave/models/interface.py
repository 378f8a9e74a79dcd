"""One interface for the hybrid-lens simulation models of the paper (Table S.I).

Every model is an ``nn.Module`` built on the same :class:`~raywave.hybrid.HybridLens` (refractive lens, DOE,
DOE distance, sensor) and answers the same call::

    model.psf_result(fields, wavelengths, ks, depth) -> ModelPSFResult   # a raywave.hybrid.PSFResult
    model.psf(fields, wavelengths, ks, depth) -> (F, W, ks, ks)

batched over field points (F, 2) (the lens's field type, degrees for angles) and wavelengths (W,) µm, with
``depth`` the object distance (mm from the first vertex, ``inf`` distant; default the lens's). Every PSF
follows the engine's conventions: float64, ``[iy, ix]`` (origin lower), pixel ``[ks//2, ks//2]`` centred on
the model's own chief-ray image point (``center``), sensor pixel pitch of the hybrid lens, sum 1.

=========== =============================================== =======================================================
name        model                                           module
=========== =============================================== =======================================================
raywave     ray-wave engine (coherent tracing → DOE field)  :class:`RayWaveModel` (wraps ``HybridLens``)
raywave_doe the same, stop edge on the DOE plane (paper)    :class:`PaperRayWaveModel` (``stop_edge="doe"``)
paraxial    thin ideal lens of the paraxial EFL + DOE + ASM :class:`raywave.models.paraxial.ParaxialModel`
pupil       Zernike (Noll) fit of the traced wavefront      :class:`raywave.models.pupil.PupilModel`
raytrace    local grating approximation, ray binning        :class:`raywave.models.local_grating.LocalGratingModel`
exit_pupil  Chen et al. 2021 exit-pupil Huygens PSF         :class:`raywave.models.exit_pupil.ExitPupilModel`
=========== =============================================== =======================================================

:func:`make_model` builds one by name.
"""

from __future__ import annotations

from types import MappingProxyType

from raywave.hybrid.hybrid_lens import HybridLens
from raywave.models.base import (ModelPSFResult, PaperRayWaveModel, PSFModel, RayWaveModel, lit_window,
                                 propagate_fields, relative_l1, window_xy)
from raywave.models.exit_pupil import ExitPupilModel
from raywave.models.local_grating import LocalGratingModel
from raywave.models.paraxial import ParaxialModel
from raywave.models.pupil import PupilModel

__all__ = ["MODELS", "MODEL_NAMES", "ModelPSFResult", "PaperRayWaveModel", "PSFModel", "RayWaveModel", "lit_window",
           "make_model", "propagate_fields", "relative_l1", "window_xy"]

#: The registry: model name -> class (each class's ``name``), in the paper's order. Read-only.
MODELS = MappingProxyType({cls.name: cls for cls in (RayWaveModel, PaperRayWaveModel, ParaxialModel, PupilModel,
                                                     LocalGratingModel, ExitPupilModel)})
#: Names accepted by :func:`make_model`, in the paper's order.
MODEL_NAMES = tuple(MODELS)


def make_model(name: str, hybrid: HybridLens, **options) -> PSFModel:
    """The comparison model ``name`` (one of :data:`MODEL_NAMES`) on ``hybrid``; ``options`` go to its
    constructor (e.g. ``n_terms`` for "pupil", ``rays`` for "raytrace" / "raywave", ``n_pupil`` for
    "exit_pupil")."""
    key = str(name).strip().lower().replace("-", "_")
    if key not in MODELS:
        raise ValueError(f"unknown model {name!r}: choose one of {', '.join(MODEL_NAMES)}")
    return MODELS[key](hybrid, **options)
