"""Lens files with a DOE inside the lens (issue 46): a surface's ``"doe"`` key → :class:`~raywave.hybrid.
midsystem.MidSystemLens`.

The DOE plane sits ``distance`` mm after the surface's vertex (:mod:`raywave.io.surface_doe`). The blank plane near
the sensor where the engine builds its field is chosen as for a lens file's default DOE
(:mod:`raywave.assembly.build`: before the first caustic, sized to the beam, at the pitch that samples it), on the
lens with the DOE's strongest order in place.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

from raywave.assembly.build import (_make_doe, _spec_lens, caustic_free_distance, default_doe_size,
                                    nyquist_doe_pitch)
from raywave.hybrid.midsystem import DOEPhaseSurface, MidSystemLens, doe_orders, insert_doe
from raywave.io import read_lens_spec
from raywave.io.doe import resolve_doe
from raywave.io.errors import LensFileError
from raywave.io.surface_doe import surface_does

__all__ = ["midsystem_from_spec", "load_midsystem", "surface_doe_positions"]


def surface_doe_positions(spec: dict) -> list:
    """``[(surface index, distance mm, doe dict)]`` of every DOE placed at a surface of ``spec``."""
    return [(i, float(d["distance"]), d) for i, s in enumerate(spec.get("surfaces", []))
            for d in surface_does(s)]


def midsystem_from_spec(spec: dict, source: str = "<spec>", base_dir=None, final_distance: float | None = None,
                        sensor_pitch: float | None = None) -> MidSystemLens:
    """The :class:`MidSystemLens` of a validated spec with one DOE at a surface (the top-level ``"doe"``, the DOE
    before the sensor, must then be absent: one DOE per lens for now)."""
    found = surface_doe_positions(spec)
    if not found:
        raise ValueError(f"{source}: no surface carries a 'doe': use raywave.load_hybrid for a DOE before the sensor")
    if len(found) > 1 or spec.get("doe") is not None:
        raise ValueError(f"{source}: {len(found) + (spec.get('doe') is not None)} DOEs: a lens with several DOEs is "
                         "not supported yet (one DOE inside the lens, issue 46)")
    after, distance, dspec = found[0]
    plain = copy.deepcopy(spec)
    for s in plain.get("surfaces", []):
        s.pop("doe", None)
    lens = _spec_lens(plain, None, source)
    data = resolve_doe({"doe": dspec}, source, base_dir)
    if data.pitch is None or data.shape is None:
        raise LensFileError(f"surfaces[{after}].doe: give 'pitch' and 'size' or 'shape' (or a phase map with its "
                            "pitch): a DOE inside the lens has no default grid", source)
    doe = _make_doe(data, data.shape, data.pitch, source)
    scale = doe_orders(doe, lens.primary_wavelength)[0][0]
    lens1 = insert_doe(lens, after, distance, DOEPhaseSurface(doe, float(scale)), 1.0, doe)
    last = float(lens.surfaces[-1].thickness.detach())
    if final_distance is None:
        free = caustic_free_distance(lens1)
        final_distance = min(0.5 * last, free if free is not None and math.isfinite(free) else 0.5 * last)
    pitch = nyquist_doe_pitch(lens1, final_distance) or data.pitch
    size = max(default_doe_size(lens1, final_distance))
    return MidSystemLens(lens, doe, after, distance, final_distance, size, pitch, sensor_pitch=sensor_pitch)


def load_midsystem(path, final_distance: float | None = None, sensor_pitch: float | None = None) -> MidSystemLens:
    """:func:`midsystem_from_spec` of a raywave JSON lens file."""
    path = Path(path)
    return midsystem_from_spec(read_lens_spec(path), str(path), path.parent, final_distance, sensor_pitch)
