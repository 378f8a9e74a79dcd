"""One ``SURF`` block of a .zmx file -> a parsed surface dict (type, curvature, thickness, material, aperture,
PARM / XDAT data read per type)."""

from __future__ import annotations

import math

from raywave.io.errors import LensFileError
from raywave.io.spec import aspheric_canonical
from raywave.io.zmx.apertures import APERTURE_KEYS, finish_aperture, surface_aperture
from raywave.io.zmx.tables import (EXTENDED_TYPES, IGNORED_SURFACE_KEYS, KNOWN_UNSUPPORTED_TYPES,
                                   MAX_BINARY2_TERMS, MAX_EVENASPH_PARM, MAX_EXTENDED_TERMS, MAX_ODDASPHE_PARM,
                                   SURFACE_TYPES, UNSUPPORTED_APERTURES, is_diffractive_type)
from raywave.io.zmx.tokens import _float, _int, _state, _Surf


def _surface(s: _Surf, path, scale, unknown) -> dict:
    """The parsed surface of one SURF block: a dict with its number, line (of its TYPE entry, else of SURF), kind
    (a spec type, or "diffractive" with its Zemax type), curvature (1/mm), thickness ``disz`` (mm), material,
    semi-diameter ``diam`` (mm), conic, stop, comment, aperture (spec form), and per kind the PARM data (aspheric
    terms in mm units, radius of rotation, focal length, coordinate break) and XDAT (diffractive).

    ``scale``: lens unit -> mm; keys no table knows are recorded in ``unknown`` ("KEY (surface n)" -> line)."""
    p = {"number": s.number, "line": s.line, "kind": "standard", "curv": 0.0, "disz": None, "material": "air",
         "diam": None, "conic": 0.0, "parms": {}, "stop": False, "comment": "", "aperture": None,
         "focal": None, "aspheric": {}, "xdat": {}, "zemax_type": None, "notes": []}
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
        p["disz_line"] = ln
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
        if p["material"] == "mirror" and toks[0].upper() != "MIRROR":
            p["notes"].append((NEGATIVE_INDEX_MIRROR_NOTE, ln))
    elif key in APERTURE_KEYS:
        surface_aperture(p, where, ln, key, rest, path, scale)
    elif key == "XDAT" and (p["kind"] == "diffractive" or p["zemax_type"] in EXTENDED_TYPES):
        if len(toks) < 2:
            raise LensFileError(f"{where}: XDAT needs an index and a value", path, ln)
        # XDAT 1 = N, 2 = normalisation radius, 3.. = coefficients: any other index would be dropped
        top = MAX_BINARY2_TERMS if p["kind"] == "diffractive" else MAX_EXTENDED_TERMS
        v = _float(toks[1], path, ln, f"{where}: XDAT")
        p["xdat"][_int(toks[0], path, ln, f"{where}: XDAT index", 1, top + 2)] = v if p["kind"] == "diffractive" \
            else (v, ln)
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
    if typ in EXTENDED_TYPES:
        p["kind"] = EXTENDED_TYPES[typ]
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
    if p["zemax_type"] in EXTENDED_TYPES:
        _extended_asphere(p, where, path, scale)
    elif p["kind"] == "even_asphere":
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


def _extended_asphere(p: dict, where: str, path, scale: float) -> None:
    """XASPHERE / XOSPHERE: XDAT 1 = number of terms N, XDAT 2 = normalisation radius R (lens units), XDAT 3..N+2 =
    A_1..A_N on (r/R)^(2i) (XASPHERE) or (r/R)^i (XOSPHERE), lens units; they become the mm terms of an even / odd
    asphere, a_(2i) = A_i·s / (R·s)^(2i) (s: lens unit -> mm). Terms past N are not used (as OpticStudio). PARM 1
    (extrapolate) only affects rays outside R. An XASPHERE with PARM 1..8 terms and no XDAT terms (as some
    converters write it) is read as an EVENASPH, PARM i on r^(2i), noted for a warning."""
    typ, parms, xdat = p["zemax_type"], p["parms"], p["xdat"]
    odd = typ == "XOSPHERE"
    terms = {i: v for i, v in parms.items() if i >= 1 and v[0] != 0.0}
    if not any(v for i, (v, _) in xdat.items() if i >= 3) and typ == "XASPHERE" and terms:
        bad = [(i, ln) for i, (v, ln) in terms.items() if i > MAX_EVENASPH_PARM]
        if bad:
            raise LensFileError(f"{where}: XASPHERE PARM {bad[0][0]} has no meaning (its terms are XDAT 3.., or "
                                f"as an EVENASPH PARM 1..{MAX_EVENASPH_PARM})", path, bad[0][1])
        p["notes"].append(("XASPHERE with terms in PARM 1..8 and none in XDAT: read as EVENASPH terms (PARM i on "
                           "r^(2i)), as the file's writer meant them", min(ln for _, ln in terms.values())))
        coeffs = {f"a{2 * i}": v * scale ** (1 - 2 * i) for i, (v, _) in terms.items()}
        p["aspheric"] = aspheric_canonical(coeffs, range(2, 2 * MAX_EVENASPH_PARM + 1, 2))
        return
    bad = [(i, ln) for i, (v, ln) in parms.items() if i != 1 and v != 0.0]
    if bad:
        raise LensFileError(f"{where}: {typ} PARM {bad[0][0]} is not an extended-asphere parameter (PARM 1 = "
                            "extrapolate; the terms are XDAT 1 = N, 2 = normalisation radius, 3.. = coefficients)",
                            path, bad[0][1])
    n_val, n_ln = xdat.get(1, (0.0, p["line"]))
    if n_val != int(n_val) or not 0 <= n_val <= MAX_EXTENDED_TERMS:
        raise LensFileError(f"{where}: {typ} XDAT 1 (number of terms) {n_val!r} must be an integer in "
                            f"0..{MAX_EXTENDED_TERMS}", path, n_ln)
    n = int(n_val)
    r_norm, r_ln = xdat.get(2, (1.0, p["line"]))
    coeffs_file = {i - 2: v for i, (v, _) in xdat.items() if 3 <= i <= n + 2 and v != 0.0}
    if coeffs_file and not (math.isfinite(r_norm) and r_norm > 0):
        raise LensFileError(f"{where}: {typ} normalisation radius (XDAT 2) {r_norm!r} must be > 0", path, r_ln)
    r_mm = r_norm * scale
    step = 1 if odd else 2
    coeffs = {f"a{step * i}": a * scale / r_mm ** (step * i) for i, a in coeffs_file.items()}
    p["aspheric"] = aspheric_canonical(coeffs, range(step, step * max(n, 1) + 1, step))


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


#: The note (a warning) on a model glass nd -1 read as a mirror.
NEGATIVE_INDEX_MIRROR_NOTE = (
    "model glass nd -1 read as a mirror (GLAS MIRROR): the old way of writing a reflection as a medium of index -1; "
    "the surface after it, at the same place, refracts out of the mirror's medium as written")


def _glass(toks, where, path, ln):
    """The material of a GLAS entry: a catalog name, "mirror", "air", or a model glass ({"index": nd} without
    dispersion, else {"model": {"nd", "vd"}}). A model glass of index exactly -1 is a mirror (old files write a
    reflection as a medium of index -1, the negative-index convention of paraxial optics; the surface after it, at
    the same place, leaves that medium); any other index <= 0 is an error."""
    if not toks:
        raise LensFileError(f"{where}: GLAS without a glass name", path, ln)
    name = toks[0]
    if name.upper() == "MIRROR":
        return "mirror"
    flag = toks[1] if len(toks) > 1 else "0"
    if name == "___BLANK" or flag == "1":
        if len(toks) < 4:
            raise LensFileError(f"{where}: model glass needs nd and vd (GLAS {name} 1 0 nd vd ...)", path, ln)
        nd = _float(toks[3], path, ln, f"{where}: GLAS nd")
        # a missing vd is 0, as OpticStudio reads the line: a constant index (no dispersion)
        vd = _float(toks[4], path, ln, f"{where}: GLAS vd") if len(toks) > 4 else 0.0
        if nd == -1.0:
            return "mirror"
        if not nd > 0:
            raise LensFileError(f"{where}: model glass index nd {toks[3]} is not supported (an index must be > 0; "
                                "a mirror is GLAS MIRROR)", path, ln)
        if vd == 0.0:
            return {"index": nd}
        return {"model": {"nd": nd, "vd": vd}}
    if name.upper() == "AIR":
        return "air"
    return name

