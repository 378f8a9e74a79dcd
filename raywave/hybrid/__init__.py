"""The ray-wave model: coherent tracing to the DOE plane, DOE modulation, propagation to the sensor.

Building a :class:`HybridLens` from a lens file is the assembly layer's (:mod:`raywave.assembly.build`, or
``raywave.load_hybrid``); ``raywave.hybrid.load_hybrid`` / ``hybrid_from_spec`` remain as lazy aliases of it.
"""

from raywave.hybrid.coherent import CausticWarning, DOEField, SamplingWarning, VignettingEdgeWarning
from raywave.hybrid.hybrid_lens import (DEFAULT_EDGE_STEP, DEFAULT_STOP_EDGE, DOEApertureWarning, HybridLens, PSFResult,
                                        SensorCropWarning, StopEdgeWarning)
from raywave.hybrid.metrics import psf_metrics

__all__ = ["CausticWarning", "DEFAULT_EDGE_STEP", "DEFAULT_STOP_EDGE", "DOEApertureWarning", "DOEField", "HybridLens",
           "PSFResult", "SamplingWarning", "SensorCropWarning", "StopEdgeWarning", "VignettingEdgeWarning",
           "psf_metrics"]

_MOVED = {"load_hybrid", "hybrid_from_spec"}  # compatibility aliases of raywave.assembly.build (issue 17)


def __getattr__(name):
    if name in _MOVED:
        from raywave.assembly import build

        return getattr(build, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
