"""A diffractive surface right before the image: the spec's ``"doe"`` (the DOE plane of a hybrid lens;
BINARY_2 coefficients become its ``phase_model``)."""

from __future__ import annotations

import math
import warnings

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.zmx.tables import MAX_BINARY2_TERMS


def _diffractive_phase(p, where, path, scale, line):
    """The phase model of a diffractive surface (BINARY_2 only; None for the other types, with a warning)."""
    typ = p["zemax_type"]
    if p["curv"] != 0.0:
        raise LensFileError(f"{where}: {typ} surface with curvature {p['curv']!r}: raywave's DOE is a thin phase "
                            "element on a plane (CURV 0)", path, line)
    if typ != "BINARY_2":
        warnings.warn(LensFileWarning(f"{path}:{line}: {where}: the phase of a {typ} surface is not read; its plane "
                                      "becomes the DOE plane with a blank DOE"),
                      stacklevel=5)  # read_zmx's frame, as before the split
        return None
    bad = [(i, ln) for i, (v, ln) in p["parms"].items() if 1 <= i <= 8 and v != 0.0]
    if bad:
        raise LensFileError(f"{where}: BINARY_2 with an aspheric substrate (PARM {bad[0][0]} != 0) is not supported: "
                            "raywave's DOE is a thin phase element on a plane", path, bad[0][1])
    order = p["parms"].get(0, (1.0, None))[0]
    xdat = p["xdat"]
    n_terms = xdat.get(1, 0.0)
    if not (math.isfinite(n_terms) and n_terms == int(n_terms) and 0 <= n_terms <= MAX_BINARY2_TERMS):
        raise LensFileError(f"{where}: BINARY_2 number of terms (XDAT 1) must be 0..{MAX_BINARY2_TERMS}, got "
                            f"{n_terms}", path, line)
    norm = xdat.get(2, 1.0)
    if not (math.isfinite(norm) and norm > 0):
        raise LensFileError(f"{where}: BINARY_2 normalisation radius (XDAT 2) must be > 0, got {norm!r}", path, line)
    n_terms = int(n_terms)
    extra = sorted(i for i, v in xdat.items() if i > 2 + n_terms and v != 0.0)
    if extra:
        raise LensFileError(f"{where}: BINARY_2 XDAT {extra[0]} = {xdat[extra[0]]!r} lies beyond the {n_terms} "
                            f"terms that XDAT 1 declares (XDAT 3..{2 + n_terms}); raise XDAT 1 or remove it", path,
                            line)
    coeffs = [xdat.get(3 + i, 0.0) for i in range(n_terms)]
    return {"type": "binary_2", "order": order, "norm_radius": norm * scale, "coefficients": coeffs}


def _doe_from_surface(d, before, path, scale, sign: float = 1.0, medium=None) -> dict:
    """The spec "doe" of the diffractive surface ``d`` (the last before the image) after surface ``before`` (a
    refractive surface, a mirror or a coordinate break).

    ``sign``: −1 after an odd number of mirrors (the light travels toward −z: the thicknesses are negative and the
    distances along the light are −DISZ); ``medium``: the medium in front of the DOE (default ``before``'s)."""
    where = f"surface {d['number']}"
    model = _diffractive_phase(d, where, path, scale, d["line"])
    if d["stop"]:
        raise LensFileError(f"{where}: the diffractive surface cannot be the stop (raywave's DOE plane lies after "
                            "the refractive lens)", path, d["line"])
    medium = before["material"] if medium is None else medium
    if d["material"] != medium:
        raise LensFileError(f"{where}: the diffractive surface changes the medium ({medium!r} before, "
                            f"{d['material']!r} after): raywave's DOE is a thin element in one medium", path, d["line"])
    along = " (negative after an odd number of mirrors: the light travels toward -z)" if sign < 0 else ""
    if d["disz"] is None or not math.isfinite(d["disz"]) or not sign * d["disz"] > 0:
        raise LensFileError(f"{where}: the DOE plane must lie before the image: its thickness (DISZ) must be "
                            f"{'< 0' if sign < 0 else '> 0'} mm{along}, got {d['disz']!r}", path, d["line"])
    t = before["disz"]
    if t is None or not math.isfinite(t) or sign * t < 0:
        raise LensFileError(f"surface {before['number']}: the distance to the DOE plane (DISZ) must be "
                            f"{'<= 0' if sign < 0 else '>= 0'} mm{along}, got {t!r}", path, before["line"])
    doe: dict = {"distance": sign * t + 0.0}  # mm along the light (+ 0.0: no -0.0)
    ap = d["aperture"]
    if ap is None:
        doe["aperture"] = "square"
    elif ap["shape"] == "circle":
        doe["aperture"] = "circle"
        doe["size"] = [2.0 * ap["radius"], 2.0 * ap["radius"]]
    else:
        doe["aperture"] = "square"
        doe["size"] = [2.0 * ap["half_width"], 2.0 * ap["half_width"]]
    doe["phase"] = None
    if model is not None:
        doe["phase_model"] = model
    return doe

