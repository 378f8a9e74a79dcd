"""The ray-wave model: coherent tracing to the DOE plane, DOE modulation, propagation to the sensor."""

from raywave.hybrid.coherent import DOEField, SamplingWarning
from raywave.hybrid.hybrid_lens import HybridLens, PSFResult, SensorCropWarning

__all__ = ["DOEField", "HybridLens", "PSFResult", "SamplingWarning", "SensorCropWarning"]
