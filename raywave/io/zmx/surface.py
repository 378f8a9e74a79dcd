"""One ``SURF`` block of a .zmx file -> a parsed surface dict (type, curvature, thickness, material, aperture,
PARM / XDAT data read per type)."""

from __future__ import annotations

import math

from raywave.io.errors import LensFileError
from raywave.io.spec import aspheric_canonical
from raywave.io.zmx.tables import (IGNORED_SURFACE_KEYS, KNOWN_UNSUPPORTED_TYPES, MAX_BINARY2_TERMS,
                                   MAX_EVENASPH_PARM, MAX_ODDASPHE_PARM, SURFACE_TYPES, UNSUPPORTED_APERTURES,
                                   is_diffractive_type)
from raywave.io.zmx.apertures import APERTURE_KEYS, finish_aperture, surface_aperture
from raywave.io.zmx.tokens import _float, _int, _state, _Surf


def _surface(s: _Surf, path, scale, unknown) -> dict:
    """The parsed surface of one SURF block: a dict with its number, line (of its TYPE entry, else of SURF), kind
    (a spec type, or "diffractive" with its Zemax type), curvature (1/mm), thickness ``disz`` (mm), material,
    semi-diameter ``diam`` (mm), conic, stop, comment, aperture (spec form), and per kind the PARM data (aspheric
    terms in mm units, radius of rotation, focal length, coordinate break) and XDAT (diffractive).

    ``scale``: lens unit -> mm; keys no table knows are recorded in ``unknown`` ("KEY (surface n)" -> line)."""
    p = {"number": s.number, "line": s.line, "kind": "standard", "curv": 0.0, "disz": None, "material": "air",
         "diam": None, "conic": 0.0, "parms": {}, "stop": False, "comment": "", "aperture": None,
         "focal": None, "aspheric": {}, "xdat": {}, "zemax_type": None}
    where = f"surface {s.number}"
    for ln, key, rest in s.entries:
        _state.line = (ln, key, rest)
        if not _surface_entry(p, where, ln, key, rest, path, scale):
            unknown.setdefault(f"{key} (surface {s.number})", ln)

    finish_aperture(p, where, path)  # FLAP at DIAM, OBDC (raywave/io/zmx/apertures.py)
    _read_parms(p, where, path, scale)
    return p


def _value(toks: list, i: int, where: str, key: str, path, ln: int) -> float:
    """Token ``i`` of entry ``key`` (line ``ln``) as a number, or a :class:`LensFileError` naming it."""
    if len(toks) <= i:
        raise LensFileError(f"{where}: {key} needs a value", path, ln)
    return _float(toks[i], path, ln, f"{where}: {key}")


def _surface_entry(p: dict, where: str, ln: int, key: str, rest: str, path, scale: float) -> bool:
    """Read one entry (line ``ln``: ``key rest``) of a SURF block into ``p`` (lengths scaled to mm); False for a
    key no table knows."""
    toks = rest.split()
    if key == "TYPE":
        _surface_type(p, where, ln, toks, path)
    elif key == "CURV":
        p["curv"] = _value(toks, 0, where, key, path, ln) / scale
        if not math.isfinite(p["curv"]):
            raise LensFileError(f"{where}: curvature CURV {toks[0]} is not a finite number (a flat surface "
                                "is CURV 0)", path, ln)
    elif key == "DISZ":
        p["disz"] = _value(toks, 0, where, key, path, ln) * scale
    elif key == "CONI":
        p["conic"] = _value(toks, 0, where, key, path, ln)
    elif key == "DIAM":
        d = _value(toks, 0, where, key, path, ln) * scale
        p["diam"] = d if d > 0 else None
    elif key == "STOP":
        p["stop"] = True
    elif key == "COMM":
        p["comment"] = rest.strip().strip('"')
    elif key == "PARM":
        if len(toks) < 2:
            raise LensFileError(f"{where}: PARM needs an index and a value", path, ln)
        p["parms"][_int(toks[0], path, ln, f"{where}: PARM index", 0, 10**6)] = (
            _float(toks[1], path, ln, f"{where}: PARM"), ln)
    elif key == "GLAS":
        p["material"] = _glass(toks, where, path, ln)
    elif key in APERTURE_KEYS:
        surface_aperture(p, where, ln, key, rest, path, scale)
    elif key == "XDAT" and p["kind"] == "diffractive":
        if len(toks) < 2:
            raise LensFileError(f"{where}: XDAT needs an index and a value", path, ln)
        # XDAT 1 = N, 2 = normalisation radius, 3.. = coefficients: any other index would be dropped
        p["xdat"][_int(toks[0], path, ln, f"{where}: XDAT index", 1, MAX_BINARY2_TERMS + 2)] = _float(
            toks[1], path, ln, f"{where}: XDAT")
    elif key in UNSUPPORTED_APERTURES:
        raise LensFileError(f"{where}: {UNSUPPORTED_APERTURES[key]} ({key}) is not supported", path, ln)
    elif key in IGNORED_SURFACE_KEYS:
        pass
    else:
        return False
    return True


def _surface_type(p: dict, where: str, ln: int, toks: list, path) -> None:
    """A TYPE entry: the surface's kind (a spec type, or "diffractive" with its Zemax type) and line."""
    typ = toks[0].upper() if toks else "STANDARD"
    if is_diffractive_type(typ):
        p["kind"] = "diffractive"
        p["zemax_type"] = typ
        p["line"] = ln
        return
    if typ not in SURFACE_TYPES:
        what = f" ({KNOWN_UNSUPPORTED_TYPES[typ]})" if typ in KNOWN_UNSUPPORTED_TYPES else ""
        raise LensFileError(f"{where}: surface type {typ}{what} is not supported by raywave (supported: "
                            f"{', '.join(SURFACE_TYPES)}, and a diffractive last surface)", path, ln)
    p["kind"] = SURFACE_TYPES[typ]
    p["line"] = ln


def _read_parms(p: dict, where: str, path, scale: float) -> None:
    """The PARM data of ``p`` by kind: aspheric terms (in mm units), radius of rotation (mm), coordinate break
    (decentre mm, tilts degrees), paraxial focal length (mm); non-zero PARMs a kind does not use are errors."""
    parms = p["parms"]
    if p["kind"] == "even_asphere":
        bad = [(i, ln) for i, (v, ln) in parms.items() if i > MAX_EVENASPH_PARM and v != 0.0]
        if bad:
            raise LensFileError(f"{where}: EVENASPH PARM {bad[0][0]} is not an even-asphere coefficient "
                                f"(PARM 1..{MAX_EVENASPH_PARM} = a2..a16)", path, bad[0][1])
        coeffs = {f"a{2 * i}": v * scale ** (1 - 2 * i) for i, (v, _) in parms.items()
                  if 1 <= i <= MAX_EVENASPH_PARM}
        p["aspheric"] = aspheric_canonical(coeffs)
    elif p["kind"] == "odd_asphere":
        bad = [(i, ln) for i, (v, ln) in parms.items() if not 1 <= i <= MAX_ODDASPHE_PARM and v != 0.0]
        if bad:
            raise LensFileError(f"{where}: ODDASPHE PARM {bad[0][0]} is not an odd-asphere coefficient "
                                f"(PARM 1..{MAX_ODDASPHE_PARM} = b1..b8 on r^1..r^8)", path, bad[0][1])
        coeffs = {f"a{i}": v * scale ** (1 - i) for i, (v, _) in parms.items() if 1 <= i <= MAX_ODDASPHE_PARM}
        p["aspheric"] = aspheric_canonical(coeffs, range(1, MAX_ODDASPHE_PARM + 1))
    elif p["kind"] == "toroidal":
        _toroidal_parms(p, where, path, scale)
    elif p["kind"] == "coordinate_break":
        _coordinate_break_parms(p, where, path, scale)
    elif p["kind"] == "paraxial":
        if 1 in parms:
            p["focal"] = parms[1][0] * scale
    elif p["kind"] == "diffractive":
        pass  # checked and read by _doe_from_surface once its position is known to be right
    else:
        bad = [(i, ln) for i, (v, ln) in parms.items() if v != 0.0]
        if bad:
            raise LensFileError(f"{where}: STANDARD surface with non-zero PARM {bad[0][0]}", path, bad[0][1])


def _toroidal_parms(p: dict, where: str, path, scale: float) -> None:
    """TOROIDAL: PARM 0 = extrapolate flag (tracing only), 1 = radius of rotation (0: infinite; -> mm), 2..8 =
    a2..a14 on y^2..y^14 (-> mm units), 13 = number of Zernike terms (must be 0), 14 = their normalisation radius."""
    parms = p["parms"]
    bad = [(i, ln) for i, (v, ln) in parms.items() if i not in (0, 1, 14) and not 2 <= i <= 8 and v != 0.0]
    if bad:
        what = "Zernike sag terms on a TOROIDAL surface are" if bad[0][0] == 13 else \
            f"TOROIDAL PARM {bad[0][0]} is"
        raise LensFileError(f"{where}: {what} not supported (PARM 1 = radius of rotation, PARM 2..8 = "
                            "a2..a14 on y^2..y^14)", path, bad[0][1])
    r = parms.get(1, (0.0, None))[0]
    p["rotation"] = "inf" if r == 0.0 or math.isinf(r) else r * scale
    coeffs = {f"a{2 * (i - 1)}": v * scale ** (1 - 2 * (i - 1)) for i, (v, _) in parms.items() if 2 <= i <= 8}
    p["aspheric"] = aspheric_canonical(coeffs, range(2, 15, 2))


def _coordinate_break_parms(p: dict, where: str, path, scale: float) -> None:
    """COORDBRK: PARM 1..6 = decentre x, y (-> mm), tilt x, y, z (degrees), order flag; the medium continues."""
    parms = p["parms"]
    bad = [(i, ln) for i, (v, ln) in parms.items() if not 1 <= i <= 6 and v != 0.0]
    if bad:
        raise LensFileError(f"{where}: COORDBRK PARM {bad[0][0]} is not a coordinate-break parameter (PARM 1..6 = "
                            "decentre x, decentre y, tilt x, tilt y, tilt z, order)", path, bad[0][1])
    v = {i: parms.get(i, (0.0, None))[0] for i in range(1, 7)}
    p["material"] = "air"  # OpticStudio ignores a coordinate break's glass: the medium before it continues
    p["break"] = {"decenter": [v[1] * scale, v[2] * scale], "tilt": [v[3], v[4], v[5]],
                  "order": 0 if v[6] == 0.0 else 1}


def _glass(toks, where, path, ln):
    if not toks:
        raise LensFileError(f"{where}: GLAS without a glass name", path, ln)
    name = toks[0]
    if name.upper() == "MIRROR":
        return "mirror"
    flag = toks[1] if len(toks) > 1 else "0"
    if name == "___BLANK" or flag == "1":
        if len(toks) < 5:
            raise LensFileError(f"{where}: model glass needs nd and vd (GLAS {name} 1 0 nd vd ...)", path, ln)
        nd = _float(toks[3], path, ln, f"{where}: GLAS nd")
        vd = _float(toks[4], path, ln, f"{where}: GLAS vd")
        if vd == 0.0:
            return {"index": nd}
        return {"model": {"nd": nd, "vd": vd}}
    if name.upper() == "AIR":
        return "air"
    return name

