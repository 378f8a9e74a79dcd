"""Compatibility re-export: the hybrid-lens builders moved to :mod:`raywave.assembly.build` (issue 17: building a
hybrid from a spec sits in the assembly layer above :mod:`raywave.hybrid`, docs/architecture.md). New code uses
``raywave.load_hybrid`` or :mod:`raywave.assembly.build`; this module is a thin alias kept for old imports
(allow-listed in tests/test_layering.py)."""

from raywave.assembly.build import (BEAM_MARGIN, DEFAULT_DISTANCE_FRACTION, DEFAULT_DOE_PITCH, MAX_DEFAULT_PITCH,
                                    NYQUIST_FILL, beam_half_extent, default_doe_size, hybrid_from_spec, load_hybrid,
                                    nyquist_doe_pitch)

__all__ = ["BEAM_MARGIN", "DEFAULT_DISTANCE_FRACTION", "DEFAULT_DOE_PITCH", "MAX_DEFAULT_PITCH", "NYQUIST_FILL",
           "beam_half_extent", "default_doe_size", "hybrid_from_spec", "load_hybrid", "nyquist_doe_pitch"]
