"""Optical models besides the ray-wave engine: reference models (ground truth in tests) and the paper's comparison
models (Table S.I), all behind one interface (:mod:`raywave.models.interface`, :func:`make_model`).

* :mod:`raywave.models.debye`: the non-paraxial scalar Debye integral of an aberration-free focus.
* :mod:`raywave.models.exit_pupil`: exit-pupil (Huygens) diffraction from traced rays on a reference sphere
  (Chen et al. 2021), and :class:`ExitPupilModel` (a blank DOE only).
* :mod:`raywave.models.paraxial`: paraxial wave optics (thin ideal lens of the paraxial EFL + DOE + ASM).
* :mod:`raywave.models.pupil`: the pupil aberration model (Zernike Noll fit of the DOE-plane wavefront).
* :mod:`raywave.models.local_grating`: ray tracing with the local grating approximation, PSF by ray binning.
"""

from raywave.models.debye import DebyePSF, debye_field, debye_psf, debye_total_power
from raywave.models.exit_pupil import ExitPupilModel, HuygensPSF, huygens_psf
from raywave.models.base import ModelPSFResult, PaperRayWaveModel, PSFModel, RayWaveModel, relative_l1
from raywave.models.interface import MODEL_NAMES, MODELS, make_model
from raywave.models.local_grating import DiscontinuousPhaseWarning, LocalGratingModel
from raywave.models.paraxial import ParaxialModel
from raywave.models.pupil import PupilModel, fit_zernike

__all__ = ["MODELS", "MODEL_NAMES", "DebyePSF", "DiscontinuousPhaseWarning", "ExitPupilModel", "HuygensPSF", "LocalGratingModel",
           "ModelPSFResult", "PaperRayWaveModel", "PSFModel", "ParaxialModel", "PupilModel", "RayWaveModel", "debye_field", "debye_psf",
           "debye_total_power", "fit_zernike", "huygens_psf", "make_model", "relative_l1"]
