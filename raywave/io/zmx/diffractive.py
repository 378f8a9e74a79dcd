"""Diffractive surfaces: right before the image, the spec's ``"doe"`` (the DOE plane of a hybrid lens); anywhere
else in the lens (issue 46), a plane surface carrying a ``"doe"`` at distance 0 after its vertex (a DOE inside the
lens, :mod:`raywave.io.surface_doe`). BINARY_2 coefficients become a ``binary_2`` ``phase_model``, a DGRATING's
line density and order a ``grating`` one."""

from __future__ import annotations

import math
import warnings

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.zmx.tables import MAX_BINARY2_TERMS


def _diffractive_phase(p, where, path, scale, line, curved_ok: bool = False):
    """The phase model of a diffractive surface (BINARY_2 and DGRATING; None for the other types, with a
    warning)."""
    typ = p["zemax_type"]
    if p["curv"] != 0.0 and not curved_ok:  # inside the lens a curved one is a conformal DOE (doe_inside)
        raise LensFileError(f"{where}: {typ} surface with curvature {p['curv']!r}: raywave's DOE is a thin phase "
                            "element on a plane (CURV 0)", path, line)
    if typ == "DGRATING":
        return _grating_phase(p, where, path, scale, line)
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


def _grating_phase(p, where, path, scale, line):
    """A DGRATING's phase model: PARM 1 = T lines per µm, PARM 2 = order M; the rulings run along the local x axis,
    so the surface adds ``M·T·λ`` to ``n·sin`` of the ray along y (OpticStudio's grating equation): the linear phase
    ``φ = 2π M T y`` (T in lines per mm), a ``grating`` phase model of period ``1/|M T|`` mm at 90° (−90° for
    ``M T < 0``); None (a blank DOE) for ``M T = 0``. The line density is per µm whatever the lens unit."""
    parms = p["parms"]
    bad = [(i, ln) for i, (v, ln) in parms.items() if i not in (1, 2) and v != 0.0]
    if bad:
        raise LensFileError(f"{where}: DGRATING PARM {bad[0][0]} is not a grating parameter (PARM 1 = lines per "
                            "µm, PARM 2 = diffraction order)", path, bad[0][1])
    t = parms.get(1, (0.0, line))
    m = parms.get(2, (1.0, line))
    for (v, ln), what in ((t, "line density (PARM 1, lines per µm)"), (m, "diffraction order (PARM 2)")):
        if not math.isfinite(v):
            raise LensFileError(f"{where}: DGRATING {what} must be a finite number, got {v!r}", path, ln)
    density = t[0] * m[0] * 1e3  # lines per mm of the traced order
    if density == 0.0:
        return None
    return {"type": "grating", "period": 1.0 / abs(density), "angle": 90.0 if density > 0 else -90.0}


def _surface_aperture_size(d) -> dict:
    """``aperture`` and ``size`` of a DOE from the diffractive surface ``d``'s aperture (CLAP, SQAP; a rectangle is
    the whole rectangular grid); ``{"aperture": "square"}`` without one."""
    ap = d["aperture"]
    if ap is not None and ap["shape"] == "circle":
        return {"aperture": "circle", "size": [2.0 * ap["radius"], 2.0 * ap["radius"]]}
    if ap is not None and ap["shape"] == "square":
        return {"aperture": "square", "size": [2.0 * ap["half_width"], 2.0 * ap["half_width"]]}
    if ap is not None and ap["shape"] == "rectangle":
        return {"aperture": "square", "size": [2.0 * ap["half_width_x"], 2.0 * ap["half_width_y"]]}
    return {"aperture": "square"}


def doe_inside(d, path, scale) -> dict:
    """The parsed diffractive surface ``d`` inside the lens (issue 46) as a parsed plane surface with ``"doe"``:
    its thickness, glass (a change of medium is the plane's refraction, then the DOE in the medium after it: the
    same ray bending, ``n2 sinθ2 − n1 sinθ1 = M λ ∂φ/∂s / 2π``, on a plane), aperture, stop and comment stay the
    surface's; the DOE (``phase_model`` of BINARY_2 / DGRATING, else blank) sits 0 mm after the vertex, sized by
    the surface's aperture (else its semi-diameter, as a circle). A curved one (a DOE on a curved substrate) keeps
    its curvature and conic (CONI) and carries a conformal DOE (``"conformal": true``): the phase, a function of
    the surface's x, y as OpticStudio defines it, on the sag, refracting in the same step. :func:`write_zmx` writes
    such DOEs back (:mod:`raywave.io.zmx.surface_doe_writer`)."""
    where = f"surface {d['number']}"
    model = _diffractive_phase(d, where, path, scale, d["line"], curved_ok=True)
    if d["curv"] == 0.0 and (d["disz"] is None or not math.isfinite(d["disz"]) or not d["disz"] > 0):
        raise LensFileError(f"{where}: a diffractive surface inside the lens needs a thickness (DISZ) > 0 mm to the "
                            f"next surface (its DOE plane lies in that gap), got {d['disz']!r}", path, d["line"])
    doe: dict = {"distance": 0.0} if d["curv"] == 0.0 else {"conformal": True}
    doe.update(_surface_aperture_size(d))
    if "size" not in doe and d["diam"]:
        doe.update(aperture="circle", size=[2.0 * d["diam"], 2.0 * d["diam"]])
    doe["phase"] = None
    if model is not None:
        doe["phase_model"] = model
    return dict(d, kind="standard", parms={}, surface_doe=doe)  # its CONI kept (a conic substrate)


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
    doe.update(_surface_aperture_size(d))
    doe["phase"] = None
    if model is not None:
        doe["phase_model"] = model
    return doe

