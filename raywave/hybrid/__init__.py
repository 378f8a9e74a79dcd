"""The ray-wave model: coherent tracing to the DOE plane, DOE modulation, propagation to the sensor."""

from raywave.hybrid.build import DOEPhaseWarning, hybrid_from_spec, load_hybrid
from raywave.hybrid.coherent import DOEField, SamplingWarning
from raywave.hybrid.hybrid_lens import DOEApertureWarning, HybridLens, PSFResult, SensorCropWarning
from raywave.hybrid.metrics import psf_metrics

__all__ = ["DOEApertureWarning", "DOEField", "DOEPhaseWarning", "HybridLens", "PSFResult", "SamplingWarning", "SensorCropWarning",
           "hybrid_from_spec", "load_hybrid", "psf_metrics"]
