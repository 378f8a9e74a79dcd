"""Import of DeepLens lens files (github.com/singer-yang/DeepLens, ``GeoLens.read_lens_json``).

A DeepLens file is JSON with ``"surfaces"``: a list of dicts with ``"type"`` (Spheric, Aspheric,
Aperture / Stop, Plane, ThinLens), ``"r"`` (semi-aperture, mm), ``"roc"`` or ``"c"`` / ``"(c)"``
(radius / curvature), ``"d_next"`` (distance to the next surface, or to the sensor for the last one)
and/or ``"d"`` / ``"(d)"`` (absolute z of the vertex), ``"k"`` (conic), ``"ai"`` (aspheric terms) and
``"mat2"`` (the medium after the surface: ``"air"``, a glass name, or ``"nd/vd"``); plus top-level
``"r_sensor"`` (sensor half-diagonal), ``"sensor_res"`` ([W, H] pixels), ``"d_sensor"`` / ``"(d_sensor)"``,
``"foclen"``, ``"fnum"``, ``"enpd"`` and ``"info"``. Keys in parentheses are values DeepLens derives and
writes for information only.

Aspheric convention (DeepLens ``Aspheric`` / ``AsphericNorm``): ``ai[i]`` multiplies ``r^(2i+2)``, i.e.
``ai = [a2, a4, a6, ...]`` (the list starts at the r² term) — the same convention as raywave's
``"aspheric": {"a2": .., "a4": ..}`` and Zemax EVENASPH, so the values are copied unchanged.
A hybrid lens file (``HybridLens.write_lens_json``) adds a top-level ``"DOE"``: its DOE class's dict
(``Binary2``, ``Pixel2D``, ``Fresnel``, ``Zernike``, ``Grating``, ``ThinLens``, or the 2024 ``"DOE"`` with a
``param_model``), imported into raywave's ``"doe"`` section by :func:`deeplens_doe`; :func:`read_deeplens_hybrid`
also loads a ``Pixel2D`` phase map (.pth / .pt / .npy / .npz).
See docs/lens-format.md, "DeepLens JSON" and "DeepLens hybrid lenses", for every conversion rule.
"""

# Split by concern (issue 17): surfaces (keys, materials, surfaces), reader (read_deeplens, read_deeplens_hybrid),
# doe_section (the "DOE" object), phase_map (side files: Pixel2D maps, legacy checkpoints). Every name stays
# importable here.
from raywave.io.deeplens.doe_section import (DEEPLENS_DOE_MATERIAL, DEEPLENS_FAB_PS, DEEPLENS_FAB_STEP,
                                            DEEPLENS_WVLN0, DOE_CLASS_TYPES, DOE_LEGACY_MODELS,
                                            ZERNIKE_DEEPLENS_TO_NOLL, deeplens_doe)
from raywave.io.deeplens.phase_map import load_pixel2d_map
from raywave.io.deeplens.reader import read_deeplens, read_deeplens_hybrid
from raywave.io.deeplens.surfaces import (DEFAULT_SENSOR_RES, FIELD_FRACTIONS, SURFACE_KEYS, TOP_KEYS,
                                         deeplens_material, looks_like_deeplens)

__all__ = ["DEEPLENS_DOE_MATERIAL", "DEEPLENS_FAB_PS", "DEEPLENS_FAB_STEP", "DEEPLENS_WVLN0", "DEFAULT_SENSOR_RES",
           "DOE_CLASS_TYPES", "DOE_LEGACY_MODELS", "FIELD_FRACTIONS", "SURFACE_KEYS", "TOP_KEYS",
           "ZERNIKE_DEEPLENS_TO_NOLL", "deeplens_doe", "deeplens_material", "load_pixel2d_map", "looks_like_deeplens",
           "read_deeplens", "read_deeplens_hybrid"]
