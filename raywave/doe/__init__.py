"""Diffractive optical elements (thin phase elements on a pixel grid): parametrisations, dispersion (height
maps in a material), kinoform wrapping and quantisation; docs/ray-wave.md, "DOEs"."""

from raywave.doe.base import (DEFAULT_DESIGN_WAVELENGTH, DEFAULT_LEVELS, DEFAULT_MATERIAL, DOE, BlankDOE, PixelDOE,
                              check_levels, phase_levels, quantize_phase)
from raywave.doe.efficiency import detuning, period_efficiency, staircase_efficiency
from raywave.doe.params import (Binary2DOE, CubicDOE, FresnelDOE, GratingDOE, RadialDOE, SumDOE, ZernikeDOE,
                                noll_to_nm, zernike_noll)
from raywave.doe.spec import MODEL_TYPES, doe_from_phase_model, doe_from_spec, load_doe, save_doe

__all__ = ["DEFAULT_DESIGN_WAVELENGTH", "DEFAULT_LEVELS", "DEFAULT_MATERIAL", "DOE", "MODEL_TYPES", "Binary2DOE",
           "BlankDOE", "CubicDOE", "FresnelDOE", "GratingDOE", "PixelDOE", "RadialDOE", "SumDOE", "ZernikeDOE",
           "check_levels", "detuning", "doe_from_phase_model", "doe_from_spec", "load_doe", "noll_to_nm",
           "period_efficiency", "phase_levels", "quantize_phase", "save_doe", "staircase_efficiency", "zernike_noll"]
