"""Argument checks shared by the physics modules (clear errors that name the quantity and its unit)."""

from __future__ import annotations

import math


def positive_float(x, name: str, unit: str = "mm") -> float:
    """``float(x)`` if it is a finite number > 0, else a ValueError naming ``name`` and ``unit``."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number > 0 ({unit}), got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be > 0 {unit}, got {x!r}")
    return v


#: The largest wavelength (µm) raywave accepts anywhere (lens files, DOEs, the CLI): a larger number is almost
#: certainly a wavelength given in nm. Defined once here.
MAX_WAVELENGTH_UM = 100.0
#: Field angles (degrees) must be smaller than this in magnitude (lens files, traced sources): at 90° the chief
#: ray travels across the axis. Defined once here.
MAX_FIELD_ANGLE = 90.0
#: For an object at infinity a field angle may go beyond 90° (a fisheye sees light from behind its first vertex), up
#: to this (degrees, exclusive: 180° is the axis seen backward).
MAX_WIDE_FIELD_ANGLE = 180.0


def wavelength_um(w, name: str = "wavelength") -> float:
    """``float(w)`` if it is a wavelength in µm (finite, 0 < λ <= :data:`MAX_WAVELENGTH_UM`), else a ValueError
    naming ``name`` (and, when the number looks like nanometres, the value in µm). The one wavelength check of
    every entry point: lens construction and paraxial data, the hybrid lens's PSFs, the CLI, the file readers."""
    try:
        v = float(w)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a wavelength in µm, got {w!r}") from None
    if not (math.isfinite(v) and 0 < v <= MAX_WAVELENGTH_UM):
        hint = ""
        if math.isfinite(v) and v > MAX_WAVELENGTH_UM:
            hint = (f": not a plausible wavelength: wavelengths are in µm, not nm ({v:g} looks like nanometres: "
                    f"{v:g} nm = {v * 1e-3:g} µm)")
        raise ValueError(f"{name} must be a wavelength in µm (0 < λ <= {MAX_WAVELENGTH_UM:g}), got {w!r}{hint}")
    return v


def wavelength_problem(w, name: str = "the value") -> str | None:
    """What :func:`wavelength_um` says about ``w`` (None when it is a wavelength in µm): for validators that collect
    problems instead of raising (the lens-file readers)."""
    try:
        wavelength_um(w, name)
    except ValueError as e:
        return str(e)
    return None


def wavelengths_um(ws, name: str = "wavelengths") -> list[float]:
    """Every wavelength of ``ws`` (a number, a sequence or a tensor, µm) checked by :func:`wavelength_um`, as a
    list of floats."""
    if hasattr(ws, "detach"):
        ws = ws.detach().reshape(-1).tolist()
    elif isinstance(ws, (str, bytes)):
        ws = [ws]
    elif not isinstance(ws, (list, tuple)):
        try:
            ws = list(ws)
        except TypeError:
            ws = [ws]
    return [wavelength_um(w, name) for w in ws]


#: The largest pixel pitch (mm) raywave accepts for a DOE or a sensor (0.1 mm = 100 µm): a larger number is
#: almost certainly a pitch in µm given where mm are expected (``--doe-pitch 1`` meaning 1 µm). Defined once here.
MAX_PITCH_MM = 0.1


def pitch_mm(p, name: str = "pitch") -> float:
    """``float(p)`` if it is a pixel pitch in mm (finite, 0 < p <= :data:`MAX_PITCH_MM`), else a ValueError naming
    ``name``, mm and µm (a pitch of 1 "mm" is 1000 µm: almost certainly µm given as mm)."""
    v = positive_float(p, name, "mm")
    if v > MAX_PITCH_MM:
        msg = f"{name} is {v:g} mm, larger than any DOE or sensor pixel (at most {MAX_PITCH_MM:g} mm = 100 µm)"
        if v <= 1e4:  # a number a slip of units explains
            msg = (f"{name} is {v:g} mm = {v * 1e3:g} µm, larger than any DOE or sensor pixel (at most "
                   f"{MAX_PITCH_MM:g} mm): pitches are in mm, not µm (did you mean {v * 1e-3:g} mm = {v:g} µm?)")
        raise ValueError(msg)
    return v
