"""Reference optical models, independent of the ray-wave engine, used as ground truth in tests.

* :mod:`raywave.models.debye`: the non-paraxial scalar Debye integral of an aberration-free focus.
* :mod:`raywave.models.exit_pupil`: exit-pupil (Huygens) diffraction from traced rays on a reference sphere.
"""

from raywave.models.debye import DebyePSF, debye_field, debye_psf, debye_total_power
from raywave.models.exit_pupil import HuygensPSF, huygens_psf

__all__ = ["DebyePSF", "HuygensPSF", "debye_field", "debye_psf", "debye_total_power", "huygens_psf"]
