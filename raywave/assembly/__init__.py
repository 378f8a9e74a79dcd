"""The assembly layer: whole systems built from parts, above :mod:`raywave.hybrid` (docs/architecture.md).

* :mod:`raywave.assembly.build`: lens files (specs) → :class:`~raywave.hybrid.HybridLens` (the file's DOE or a
  default blank one sized to the beam): :func:`load_hybrid`, :func:`hybrid_from_spec`, :func:`default_doe_size`.
* :mod:`raywave.assembly.tolerance`: the fabrication-tolerance Monte Carlo with the PSF change through a hybrid
  lens (:func:`tolerance_monte_carlo`; the efficiency part is :mod:`raywave.doe.tolerance`).
"""

from raywave.assembly.build import beam_half_extent, default_doe_size, hybrid_from_spec, load_hybrid
from raywave.assembly.tolerance import tolerance_monte_carlo

__all__ = ["beam_half_extent", "default_doe_size", "hybrid_from_spec", "load_hybrid", "tolerance_monte_carlo"]
