"""Zemax OpticStudio .zmx files (sequential subset) <-> lens specs.

What is read (see docs/lens-format.md, "Zemax .zmx"): system data (NAME, UNIT, the system aperture: ENPD, FNUM
(image-space or paraxial working F/#), OBNA (object NA or cone angle), FLOA; GCAT, FTYP, XFLN/YFLN, WAVM/WAVL,
PWAV) and the surfaces ``SURF n`` of types STANDARD, EVENASPH, ODDASPHE, TOROIDAL and PARAXIAL with
STOP, CURV, DISZ, GLAS (``GLAS MIRROR``: a mirror), DIAM, CONI, PARM, COMM and CLAP / SQAP / FLAP apertures, and
coordinate breaks (``TYPE COORDBRK``: PARM 1..6 = decentre x, decentre y, tilt x, tilt y, tilt z, order flag). Surface 0 is the object
(its DISZ is the object distance), the last surface is the image plane (dropped: the thickness before it
is the distance to the image). A diffractive surface (BINARY_2, DGRATING, ...) as the last surface before the
image becomes the spec's "doe" (the DOE plane of a hybrid lens; BINARY_2 coefficients become its
``phase_model``, and :func:`write_zmx` writes such a DOE back as a BINARY_2 surface). Anything raywave
cannot model (other surface types, decentred
apertures, curved object or image, non-sequential mode) raises
:class:`LensFileError` naming the surface and line; known bookkeeping keys are skipped and unknown keys
give one :class:`LensFileWarning` listing them.

Files are decoded from bytes: UTF-16 (BOM, or NUL bytes: what OpticStudio writes), else UTF-8, else
Latin-1. :func:`write_zmx` writes UTF-16 LE with BOM and CRLF line ends by default, as OpticStudio does.
"""

from __future__ import annotations

import math
import threading
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import FORMAT_NAME, FORMAT_VERSION, UNITS, validate_spec
from raywave.io.spec import (DEFAULT_WAVELENGTHS, aspheric_canonical, curvature_of, rotation_radius_canonical,
                             shape_entry)

#: Zemax surface types raywave models, and their spec type.
SURFACE_TYPES = {"STANDARD": "standard", "EVENASPH": "even_asphere", "ODDASPHE": "odd_asphere",
                 "TOROIDAL": "toroidal", "PARAXIAL": "paraxial", "COORDBRK": "coordinate_break"}
#: Types raywave cannot trace yet, with what they are (a clearer error than "not supported").
KNOWN_UNSUPPORTED_TYPES = {
    "BICONIC": "biconic", "SZERNSAG": "Zernike standard sag", "FZERNSAG": "Zernike fringe sag",
    "XPOLYNOM": "extended polynomial", "POLYNOMI": "polynomial", "GRID_SAG": "grid sag", "CYLINDER": "cylinder",
    "IRREGULA": "irregular", "USERSURF": "user-defined (DLL)", "GRADIENT": "gradient index",
}
#: Zemax diffractive surface types: as the last surface before the image, such a surface is the DOE plane of
#: a hybrid lens (spec "doe"); anywhere else it is an error. Also any type whose name says diffractive.
DIFFRACTIVE_TYPES = {"BINARY_1", "BINARY_2", "BINARY_3", "BINARY_4", "DGRATING", "RADGRATI", "ELGRATIN", "ELGRAT2",
                     "TOROGRAT", "HOLOGRM1", "HOLOGRM2", "VLSGRATI"}
#: ... and any type whose name contains one of these.
DIFFRACTIVE_NAME_PARTS = ("BINARY", "GRAT", "HOLOG", "DIFFRACT", "PHAS")
#: BINARY_2: PARM 0 = diffraction order, PARM 1..8 = even-asphere substrate terms (must be 0: the DOE is a plane);
#: XDAT 1 = number of terms N, XDAT 2 = normalisation radius, XDAT 3.. = A_i on (r / R_norm)^(2i), radians.
MAX_BINARY2_TERMS = 230


def is_diffractive_type(typ: str) -> bool:
    """A Zemax surface type that adds a diffractive phase (binary optics, gratings, holograms, phase maps)."""
    t = typ.upper()
    return t in DIFFRACTIVE_TYPES or any(part in t for part in DIFFRACTIVE_NAME_PARTS)


#: Lens units -> mm.
UNIT_SCALE = {"MM": 1.0, "CM": 10.0, "IN": 25.4, "INCH": 25.4, "M": 1000.0, "METER": 1000.0, "METERS": 1000.0}
#: EVENASPH: PARM i multiplies r^(2i) (PARM 1 = a2, ..., PARM 8 = a16).
MAX_EVENASPH_PARM = 8
#: ODDASPHE: PARM i multiplies r^i (PARM 1 = b1, ..., PARM 8 = b8).
MAX_ODDASPHE_PARM = 8

#: Surface keys skipped on purpose: they do not change the rays raywave traces.
IGNORED_SURFACE_KEYS = {
    "HIDE": "drawing visibility",
    "MIRR": "mirror substrate drawing (a reflecting surface is GLAS MIRROR)",
    "SLAB": "surface label",
    "POPS": "physical optics settings",
    "MAZH": "mechanical aperture settings",
    "COAT": "coating (raywave traces uncoated surfaces)",
    "PPAR": "extra parameter data",
    "VPAR": "variable flags",
    "VCON": "variable flags",
    "EDGE": "edge drawing",
    "BLNK": "blank line",
    "PZUP": "pickup data",
    "PKUP": "pickup solve (the solved values are in the file)",
    "FLWR": "glass weight data",
    "TCE": "thermal expansion",
    "MEMA": "mechanical semi-diameter",
    "NOTE": "note text",
}
#: Surface apertures raywave has no model for.
UNSUPPORTED_APERTURES = {
    "ELAP": "elliptical aperture",
    "OBSC": "circular obscuration",
    "OBSQ": "rectangular obscuration",
    "ELOB": "elliptical obscuration",
    "UDAP": "user-defined aperture",
    "USAP": "user-defined aperture",
    "SPID": "spider obscuration",
}
#: System keys skipped on purpose (settings that do not change the prescription raywave reads).
IGNORED_SYSTEM_KEYS = {
    "VERS", "PFIL", "LANG", "ENVD", "GFAC", "RAIM", "PUSH", "SDMA", "ROPD", "PICB", "POLS", "GLRS", "GSTD",
    "NSCD", "COFN", "BLNK", "TOL", "TOLE", "MOFF", "CONF", "DMFS", "ISNA", "VDSZ", "ZVDX", "ZVDY", "ZVCX",
    "ZVCY", "ZVAN", "MNCA", "MNEA", "MNCG", "MNEG", "MXCA", "MXCG", "RGLA", "TRAC", "TCMM", "PMAG", "TOTR",
    "OPDX", "EFFL", "PUPD", "TCED", "FWGN", "FWGT", "VDXN", "VDYN", "VCXN", "VCYN", "VANN", "WWGN", "WWGT",
    "WAVN", "MNUM", "NOTE", "FIMP", "SCOL", "SCTH",
}
#: System aperture keys -> spec "system_aperture" key, by the flag after the value (FNUM v 0 = image-space F/#,
#: FNUM v 1 = paraxial working F/#; OBNA v 0 = object-space NA, OBNA v 1 = object cone angle in degrees).
SYSTEM_APERTURE_KEYS = {
    "ENPD": {0: "epd"},
    "FNUM": {0: "f_number", 1: "working_f_number"},
    "OBNA": {0: "object_na", 1: "object_cone_angle"},
}


def decode_zmx_bytes(raw: bytes) -> tuple[str, str]:
    """(text, encoding name) of a .zmx file: UTF-16 by BOM or NUL bytes, else UTF-8, else Latin-1."""
    if raw.startswith(b"\xff\xfe"):
        return raw[2:].decode("utf-16-le"), "utf-16-le"
    if raw.startswith(b"\xfe\xff"):
        return raw[2:].decode("utf-16-be"), "utf-16-be"
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8"), "utf-8"
    head = raw[:400]
    if b"\x00" in head:
        even_nuls = head[0::2].count(0)
        odd_nuls = head[1::2].count(0)
        enc = "utf-16-le" if odd_nuls >= even_nuls else "utf-16-be"
        return raw.decode(enc, errors="replace"), enc
    try:
        return raw.decode("utf-8"), "utf-8"
    except UnicodeDecodeError:
        return raw.decode("latin-1"), "latin-1"


def _float(tok: str, path, line, what) -> float:
    try:
        if tok.upper() in ("INFINITY", "INF"):
            return math.inf
        if tok.upper() in ("-INFINITY", "-INF"):
            return -math.inf
        return float(tok)
    except ValueError:
        raise LensFileError(f"{what}: {tok!r} is not a number", path, line) from None


def _int(tok: str, path, line, what, lo: int | None = None, hi: int | None = None) -> int:
    """An integer token (``3`` or ``3.0``) in ``lo..hi``, or a :class:`LensFileError` naming ``what``."""
    try:
        v = float(tok)
    except ValueError:
        raise LensFileError(f"{what}: {tok!r} is not a number", path, line) from None
    if not (math.isfinite(v) and v == int(v)):
        raise LensFileError(f"{what}: {tok!r} is not an integer", path, line)
    v = int(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"{lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
        raise LensFileError(f"{what}: {v} is out of range {rng}", path, line)
    return v


class _Surf:
    def __init__(self, number: int, line: int):
        self.number = number
        self.line = line
        self.entries: list[tuple[int, str, str]] = []


def _parse_lines(text: str):
    """-> (system entries [(line, key, rest)], surfaces [_Surf])."""
    system: list[tuple[int, str, str]] = []
    surfaces: list[_Surf] = []
    for ln, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip().lstrip("\ufeff")
        if not s:
            continue
        key, _, rest = s.partition(" ")
        key = key.upper()
        rest = rest.strip()
        if key == "SURF":
            try:
                n = int(rest.split()[0])
            except (ValueError, IndexError):
                raise LensFileError(f"SURF needs a surface number, got {rest!r}", None, ln) from None
            surfaces.append(_Surf(n, ln))
        elif surfaces and raw[:1] in (" ", "\t"):
            surfaces[-1].entries.append((ln, key, rest))
        elif surfaces and key not in _SYSTEM_KEYS_AFTER_SURFACES:
            # unindented key after the surfaces started (hand-written files): still a surface key
            surfaces[-1].entries.append((ln, key, rest))
        else:
            system.append((ln, key, rest))
    return system, surfaces


#: System keys that may appear after the SURF blocks (OpticStudio writes some there).
_SYSTEM_KEYS_AFTER_SURFACES = {"TOL", "TOLE", "MNUM", "MOFF", "BLNK", "CONF", "NSCD", "COFN", "VERS"}


def read_zmx(path) -> dict:
    """Read a Zemax .zmx file into a validated lens spec (see the module docstring for what is read)."""
    path = str(path)
    text, _enc = decode_zmx_bytes(Path(path).read_bytes())
    _state.line = None
    try:
        spec = _interpret(text, path)
    except LensFileError as e:
        if e.path == "<spec>":  # raised below without the path
            raise LensFileError(e.reason, path, e.line, e.column) from None
        raise
    except (ValueError, IndexError, ArithmeticError) as e:  # a malformed value that no check above caught
        ln, key, rest = _state.line or (None, "", "")
        raise LensFileError(f"cannot read {key} {rest!r}: {e}", path, ln) from None
    return validate_spec(spec, path)


class _LineState(threading.local):
    """The line being interpreted, per thread (for errors from malformed values)."""

    def __init__(self):
        self.line = None


_state = _LineState()


def _interpret(text: str, path: str) -> dict:
    system, surfs = _parse_lines(text)
    unknown: dict[str, int] = {}

    def err(msg, line):
        return LensFileError(msg, path, line)

    scale = 1.0
    name = ""
    mode_seq = None
    sys_ap = None  # (spec key, value in file units, line)
    floating = False
    catalogs: list[str] = []
    ftyp = None
    xfln: list[float] = []
    yfln: list[float] = []
    wavm: dict[int, float] = {}
    wavl: list[float] = []
    pwav = 1
    for ln, key, rest in system:
        _state.line = (ln, key, rest)
        toks = rest.split()
        if key == "MODE":
            mode_seq = rest.upper().startswith("SEQ")
            if not mode_seq:
                raise err(f"MODE {rest}: only sequential (MODE SEQ) files can be read", ln)
        elif key == "NAME":
            name = rest.strip().strip('"')
        elif key == "UNIT":
            u = toks[0].upper() if toks else "MM"
            if u not in UNIT_SCALE:
                raise err(f"UNIT {u}: unknown lens unit (known: {', '.join(UNIT_SCALE)})", ln)
            scale = UNIT_SCALE[u]
        elif key in SYSTEM_APERTURE_KEYS:
            if not toks:
                raise err(f"{key} needs a value", ln)
            flag = int(float(toks[1])) if len(toks) > 1 and key != "ENPD" else 0
            kinds = SYSTEM_APERTURE_KEYS[key]
            if flag not in kinds:
                raise err(f"{key} {rest}: unknown system aperture flag {flag} (known: "
                          f"{', '.join(f'{f} = {k}' for f, k in kinds.items())})", ln)
            value = _float(toks[0], path, ln, key)
            if not (math.isfinite(value) and value > 0):
                raise err(f"{key} {rest}: the system aperture value must be > 0", ln)
            if sys_ap is not None and sys_ap[0] != kinds[flag]:
                raise err(f"{key}: a second system aperture (line {sys_ap[2]} already gives {sys_ap[0]}); "
                          "a .zmx file has one system aperture type", ln)
            sys_ap = (kinds[flag], value, ln)
        elif key == "FLOA":
            floating = True
        elif key == "GCAT":
            catalogs = toks
        elif key == "FTYP":
            # FTYP type, telecentric, number of fields, number of wavelengths, ...
            ftyp = ([_int(t, path, ln, f"FTYP entry {i + 1}", 0, 10**6) for i, t in enumerate(toks)], ln)
        elif key in ("XFLN", "XFLD"):
            xfln = [_float(t, path, ln, key) for t in toks]
        elif key in ("YFLN", "YFLD"):
            yfln = [_float(t, path, ln, key) for t in toks]
        elif key == "WAVM":
            if len(toks) < 2:
                raise err("WAVM needs an index and a wavelength", ln)
            wavm[_int(toks[0], path, ln, "WAVM index", 1, 10**6)] = _float(toks[1], path, ln, "WAVM")
        elif key == "WAVL":
            wavl = [_float(t, path, ln, "WAVL") for t in toks]
        elif key == "PWAV":
            pwav = _int(toks[0], path, ln, "PWAV", 1, 10**6) if toks else 1
        elif key == "MNUM" and toks and toks[0].isdigit() and int(toks[0]) > 1:
            warnings.warn(LensFileWarning(f"{path}:{ln}: multi-configuration file ({toks[0]} configurations); "
                                          "the prescription as written (current configuration) is read"),
                          stacklevel=3)
        elif key in IGNORED_SYSTEM_KEYS:
            pass
        else:
            unknown.setdefault(key, ln)

    if not surfs:
        raise err("no surfaces (SURF lines) in the file", None)
    nums = [s.number for s in surfs]
    if nums != list(range(len(surfs))):
        raise err(f"surfaces must be numbered 0, 1, 2, ... in order; got {nums}", surfs[0].line)
    if len(surfs) < 3:
        raise err("a lens needs an object surface, at least one surface and an image surface", surfs[-1].line)

    parsed = [_surface(s, path, scale, unknown) for s in surfs]
    obj, img, lens = parsed[0], parsed[-1], parsed[1:-1]

    # a diffractive surface right before the image is the DOE plane of a hybrid lens
    doe = None
    for p in parsed[:-1]:
        if p["kind"] == "diffractive" and p is not parsed[-2]:
            raise err(f"surface {p['number']}: diffractive surface type {p['zemax_type']} is supported only as the "
                      "last surface before the image (the DOE plane of a hybrid lens)", p["line"])
    if lens and lens[-1]["kind"] == "diffractive":
        if len(lens) < 2 or parsed[-2] is obj:
            raise err(f"surface {lens[-1]['number']}: a DOE plane needs a refractive lens in front of it",
                      lens[-1]["line"])
        d, lens = lens[-1], lens[:-1]
        if lens[-1]["kind"] == "coordinate_break" or lens[-1]["material"] == "mirror":
            what = "a coordinate break" if lens[-1]["kind"] == "coordinate_break" else "a mirror"
            raise err(f"surface {d['number']}: the DOE plane follows {what} (surface {lens[-1]['number']}); "
                      "raywave's DOE plane lies a distance after the last refractive surface on its axis, so a DOE "
                      "after a coordinate break or a mirror is not supported (put the break before a refractive "
                      "surface)", d["line"])
        doe = _doe_from_surface(d, lens[-1], path, scale)
        lens[-1] = dict(lens[-1], disz=lens[-1]["disz"] + d["disz"])  # the refractive lens reaches the sensor

    # object and image surfaces: flat, in air
    for p, what in ((obj, "object"), (img, "image")):
        if p["kind"] != "standard" or p["curv"] != 0.0:
            raise err(f"surface {p['number']} ({what}): a curved or non-standard {what} surface is not "
                      "supported (raywave's object and image are planes)", p["line"])
        if p["stop"]:
            raise err(f"surface {p['number']} ({what}) cannot be the stop", p["line"])
    if img["material"] == "mirror":
        raise err(f"surface {img['number']} (image): the image surface cannot be a mirror", img["line"])
    if obj["material"] != "air":
        raise err("surface 0 (object): the object space must be air", obj["line"])
    dist = obj["disz"]
    if dist is None or math.isinf(dist):
        distance = "inf"
    elif dist <= 0:
        raise err(f"surface 0 (object): object distance {dist!r} mm must be > 0 (or INFINITY)", obj["line"])
    else:
        distance = dist

    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    if name:
        spec["name"] = name
    if catalogs:
        spec["catalogs"] = catalogs
    spec["object"] = {"distance": distance}
    if sys_ap is not None:
        kind, value, ln = sys_ap
        if kind in ("object_na", "object_cone_angle"):
            if distance == "inf":
                raise err(f"{'OBNA' if kind == 'object_na' else 'OBNA (cone angle)'}: an object-space "
                          f"{'NA' if kind == 'object_na' else 'cone angle'} needs an object at a finite distance "
                          "(surface 0 DISZ is INFINITY)", ln)
            limit = 1.0 if kind == "object_na" else 90.0
            if not value < limit:
                raise err(f"OBNA {value!r}: must be < {limit:g} ({'NA in air' if limit == 1.0 else 'degrees'})", ln)
        spec["system_aperture"] = {kind: value * scale if kind == "epd" else value}

    # fields
    nfld = ftyp[0][2] if ftyp and len(ftyp[0]) >= 3 else None
    ftype = ftyp[0][0] if ftyp and ftyp[0] else 0
    if ftype not in (0, 1):
        names = {2: "paraxial image height", 3: "real image height", 4: "theodolite angle"}
        raise err(f"FTYP {ftype}: field type {names.get(ftype, ftype)} is not supported (raywave: angle = 0, "
                  "object height = 1)", ftyp[1])
    n = max(len(xfln), len(yfln))
    xs = xfln + [0.0] * (n - len(xfln))
    ys = yfln + [0.0] * (n - len(yfln))
    if nfld is None:
        nz = [i for i in range(n) if xs[i] or ys[i]]
        nfld = (nz[-1] + 1) if nz else 1
    nfld = max(1, min(nfld, n)) if n else 1
    xs, ys = xs[:nfld] or [0.0], ys[:nfld] or [0.0]
    if any(x != 0.0 for x in xs):
        warnings.warn(LensFileWarning(f"{path}: fields with an x component are folded to radial fields "
                                      "sqrt(x² + y²) (raywave lenses are rotationally symmetric)"), stacklevel=3)
    values = [math.hypot(x, y) if x else y for x, y in zip(xs, ys)]
    if ftype == 1:
        values = [v * scale for v in values]
    spec["fields"] = {"type": "angle" if ftype == 0 else "object_height", "values": values}

    # wavelengths
    nwav = ftyp[0][3] if ftyp and len(ftyp[0]) >= 4 else None
    if wavm:
        wls = [wavm[k] for k in sorted(wavm)]
    else:
        wls = wavl
    if nwav:
        wls = wls[:nwav]
    if not wls:
        wls = list(DEFAULT_WAVELENGTHS["values"])
        pwav = DEFAULT_WAVELENGTHS["primary"] + 1
    if not 1 <= pwav <= len(wls):
        raise err(f"PWAV {pwav}: primary wavelength out of range 1..{len(wls)}", None)
    spec["wavelengths"] = {"values": wls, "primary": pwav - 1}

    # lens surfaces
    surfaces = []
    for p in lens:
        s: dict = {"type": p["kind"]}
        if p["kind"] == "coordinate_break":
            if p["stop"]:
                raise err(f"surface {p['number']}: a coordinate break cannot be the stop", p["line"])
            if p["disz"] is None or math.isinf(p["disz"]):
                raise err(f"surface {p['number']}: thickness (DISZ) must be finite", p["line"])
            s.update(p["break"])
            s["thickness"] = p["disz"]
            if p["comment"]:
                s["comment"] = p["comment"]
            surfaces.append(s)
            continue
        if p["kind"] == "paraxial":
            if p["focal"] is None or p["focal"] == 0.0:
                raise err(f"surface {p['number']}: a PARAXIAL surface needs a non-zero focal length (PARM 1)",
                          p["line"])
            s["focal_length"] = p["focal"]
        else:
            s.update(shape_entry(p["curv"]))
            s["conic"] = p["conic"]
            if p["kind"] == "toroidal":
                s["radius_of_rotation"] = p["rotation"]
            if p["kind"] in ("even_asphere", "odd_asphere", "toroidal"):
                s["aspheric"] = p["aspheric"]
        if p["disz"] is None or math.isinf(p["disz"]):
            raise err(f"surface {p['number']}: thickness (DISZ) must be finite", p["line"])
        s["thickness"] = p["disz"]
        s["material"] = p["material"]
        if p["material"] == "mirror" and p["kind"] == "paraxial":
            raise err(f"surface {p['number']}: a PARAXIAL surface cannot be a mirror (GLAS MIRROR)", p["line"])
        aperture = p["aperture"]
        if aperture is None and p["stop"] and "system_aperture" not in spec and p["diam"]:
            aperture = {"shape": "circle", "radius": p["diam"]}  # float by stop size: the stop's semi-diameter
        s["aperture"] = aperture
        if p["diam"] is not None:
            s["semi_diameter"] = p["diam"]
        s["stop"] = p["stop"]
        if p["comment"]:
            s["comment"] = p["comment"]
        surfaces.append(s)
    spec["surfaces"] = surfaces
    if doe is not None:
        spec["doe"] = doe
    if floating and sys_ap is not None:
        warnings.warn(LensFileWarning(f"{path}: both {sys_ap[0]} (line {sys_ap[2]}) and FLOA given; using "
                                      f"{sys_ap[0]}"), stacklevel=3)

    if unknown:
        listed = ", ".join(f"{k} (line {ln})" for k, ln in sorted(unknown.items(), key=lambda kv: kv[1]))
        warnings.warn(LensFileWarning(f"{path}: ignored unknown .zmx keys: {listed}"), stacklevel=3)
    return spec


def _surface(s: _Surf, path, scale, unknown) -> dict:
    p = {"number": s.number, "line": s.line, "kind": "standard", "curv": 0.0, "disz": None, "material": "air",
         "diam": None, "conic": 0.0, "parms": {}, "stop": False, "comment": "", "aperture": None,
         "focal": None, "aspheric": {}, "xdat": {}, "zemax_type": None}
    where = f"surface {s.number}"
    typ_line = s.line
    for ln, key, rest in s.entries:
        _state.line = (ln, key, rest)
        toks = rest.split()

        def num(i, what=key):
            if len(toks) <= i:
                raise LensFileError(f"{where}: {key} needs a value", path, ln)
            return _float(toks[i], path, ln, f"{where}: {what}")

        if key == "TYPE":
            typ = toks[0].upper() if toks else "STANDARD"
            if is_diffractive_type(typ):
                p["kind"] = "diffractive"
                p["zemax_type"] = typ
                typ_line = ln
                continue
            if typ not in SURFACE_TYPES:
                what = f" ({KNOWN_UNSUPPORTED_TYPES[typ]})" if typ in KNOWN_UNSUPPORTED_TYPES else ""
                raise LensFileError(f"{where}: surface type {typ}{what} is not supported by raywave (supported: "
                                    f"{', '.join(SURFACE_TYPES)}, and a diffractive last surface)", path, ln)
            p["kind"] = SURFACE_TYPES[typ]
            typ_line = ln
        elif key == "CURV":
            p["curv"] = num(0) / scale
            if not math.isfinite(p["curv"]):
                raise LensFileError(f"{where}: curvature CURV {toks[0]} is not a finite number (a flat surface "
                                    "is CURV 0)", path, ln)
        elif key == "DISZ":
            p["disz"] = num(0) * scale
        elif key == "CONI":
            p["conic"] = num(0)
        elif key == "DIAM":
            d = num(0) * scale
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
        elif key in ("CLAP", "FLAP"):
            vals = [_float(t, path, ln, f"{where}: {key}") for t in toks[:2]]
            rmin, rmax = (0.0, vals[0]) if len(vals) == 1 else (vals[0], vals[1])
            if rmin != 0.0:
                raise LensFileError(f"{where}: {key} with minimum radius {rmin} (an annular aperture) is not "
                                    "supported", path, ln)
            if key == "FLAP" and rmax == 0.0:
                p["aperture"] = ("FLAP", ln)  # resolved from DIAM below
                continue
            if not rmax > 0:
                raise LensFileError(f"{where}: empty aperture ({key} radius {rmax})", path, ln)
            p["aperture"] = {"shape": "circle", "radius": rmax * scale}
        elif key == "SQAP":
            vals = [_float(t, path, ln, f"{where}: SQAP") for t in toks[:2]]
            if not vals:
                raise LensFileError(f"{where}: SQAP needs half widths", path, ln)
            hx = vals[0]
            hy = vals[1] if len(vals) > 1 else hx
            if hx != hy:
                raise LensFileError(f"{where}: rectangular aperture {hx} x {hy} is not supported (only square "
                                    "apertures, equal half widths)", path, ln)
            if not hx > 0:
                raise LensFileError(f"{where}: empty aperture (SQAP half width {hx})", path, ln)
            p["aperture"] = {"shape": "square", "half_width": hx * scale}
        elif key == "OBDC":
            vals = [_float(t, path, ln, f"{where}: OBDC") for t in toks[:2]]
            if any(v != 0.0 for v in vals):
                raise LensFileError(f"{where}: decentred aperture (OBDC {rest}) is not supported", path, ln)
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
            unknown.setdefault(f"{key} (surface {s.number})", ln)

    if isinstance(p["aperture"], tuple):  # FLAP: floating aperture at the semi-diameter
        if p["diam"] is None:
            raise LensFileError(f"{where}: floating aperture without a semi-diameter (DIAM)", path,
                                p["aperture"][1])
        p["aperture"] = {"shape": "circle", "radius": p["diam"]}

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
        # PARM 0 = extrapolate flag (tracing only), 1 = radius of rotation (0: infinite), 2..8 = a2..a14 on y^2..y^14,
        # 13 = number of Zernike terms (must be 0), 14 = their normalisation radius
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
    elif p["kind"] == "coordinate_break":
        bad = [(i, ln) for i, (v, ln) in parms.items() if not 1 <= i <= 6 and v != 0.0]
        if bad:
            raise LensFileError(f"{where}: COORDBRK PARM {bad[0][0]} is not a coordinate-break parameter (PARM 1..6 = "
                                "decentre x, decentre y, tilt x, tilt y, tilt z, order)", path, bad[0][1])
        v = {i: parms.get(i, (0.0, None))[0] for i in range(1, 7)}
        p["material"] = "air"  # OpticStudio ignores a coordinate break's glass: the medium before it continues
        p["break"] = {"decenter": [v[1] * scale, v[2] * scale], "tilt": [v[3], v[4], v[5]],
                      "order": 0 if v[6] == 0.0 else 1}
    elif p["kind"] == "paraxial":
        if 1 in parms:
            p["focal"] = parms[1][0] * scale
    elif p["kind"] == "diffractive":
        pass  # checked and read by _doe_from_surface once its position is known to be right
    else:
        bad = [(i, ln) for i, (v, ln) in parms.items() if v != 0.0]
        if bad:
            raise LensFileError(f"{where}: STANDARD surface with non-zero PARM {bad[0][0]}", path, bad[0][1])
    p["line"] = typ_line if typ_line else s.line
    return p


def _diffractive_phase(p, where, path, scale, line):
    """The phase model of a diffractive surface (BINARY_2 only; None for the other types, with a warning)."""
    typ = p["zemax_type"]
    if p["curv"] != 0.0:
        raise LensFileError(f"{where}: {typ} surface with curvature {p['curv']!r}: raywave's DOE is a thin phase "
                            "element on a plane (CURV 0)", path, line)
    if typ != "BINARY_2":
        warnings.warn(LensFileWarning(f"{path}:{line}: {where}: the phase of a {typ} surface is not read; its plane "
                                      "becomes the DOE plane with a blank DOE"), stacklevel=4)
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


def _doe_from_surface(d, before, path, scale) -> dict:
    """The spec "doe" of the diffractive surface ``d`` (the last before the image) after surface ``before``."""
    where = f"surface {d['number']}"
    model = _diffractive_phase(d, where, path, scale, d["line"])
    if d["stop"]:
        raise LensFileError(f"{where}: the diffractive surface cannot be the stop (raywave's DOE plane lies after "
                            "the refractive lens)", path, d["line"])
    if d["material"] != before["material"]:
        raise LensFileError(f"{where}: the diffractive surface changes the medium ({before['material']!r} before, "
                            f"{d['material']!r} after): raywave's DOE is a thin element in one medium", path, d["line"])
    if d["disz"] is None or not math.isfinite(d["disz"]) or not d["disz"] > 0:
        raise LensFileError(f"{where}: the DOE plane must lie before the image: its thickness (DISZ) must be > 0 mm, "
                            f"got {d['disz']!r}", path, d["line"])
    t = before["disz"]
    if t is None or not math.isfinite(t) or t < 0:
        raise LensFileError(f"surface {before['number']}: the distance to the DOE plane (DISZ) must be >= 0 mm, got "
                            f"{t!r}", path, before["line"])
    doe: dict = {"distance": t}
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


# --------------------------------------------------------------------------------------- writer
def _num(x) -> str:
    return repr(float(x))


def zmx_text(spec: dict, source="<spec>") -> str:
    """The .zmx text for ``spec`` (see :func:`write_zmx`)."""
    validate_spec(spec, source)
    out: list[str] = []
    w = out.append
    w("VERS 190513 80 123457 L123457")
    w("MODE SEQ")
    w(f"NAME {spec.get('name', '')}".rstrip())
    w("UNIT MM X W X CM MR CPMM")
    w(_system_aperture_line(spec.get("system_aperture")))
    catalogs = list(spec.get("catalogs") or [])
    for s in spec["surfaces"]:
        m = s.get("material")
        if isinstance(m, dict) and "catalog" in m and m["catalog"] not in catalogs:
            catalogs.append(m["catalog"])
    if catalogs:
        w("GCAT " + " ".join(catalogs))
    fields = spec.get("fields") or {"type": "angle", "values": [0.0]}
    wls = spec.get("wavelengths") or DEFAULT_WAVELENGTHS
    fv = [float(v) for v in fields["values"]]
    wv = [float(v) for v in wls["values"]]
    w(f"FTYP {0 if fields.get('type', 'angle') == 'angle' else 1} 0 {len(fv)} {len(wv)} 0 0 0")
    pad = [0.0] * max(0, 12 - len(fv))
    w("XFLN " + " ".join(_num(0.0) for _ in fv + pad))
    w("YFLN " + " ".join(_num(v) for v in fv + pad))
    w("FWGN " + " ".join("1" for _ in fv + pad))
    for i, v in enumerate(wv, start=1):
        w(f"WAVM {i} {_num(v)} 1")
    w(f"PWAV {int(wls.get('primary', 0)) + 1}")

    d = (spec.get("object") or {}).get("distance", "inf")
    w("SURF 0")
    w("  TYPE STANDARD")
    w("  CURV 0.0")
    w("  DISZ " + ("INFINITY" if d == "inf" else _num(d)))
    doe = spec.get("doe")
    model = (doe or {}).get("phase_model")
    binary2 = doe is not None and model is not None and model.get("type") == "binary_2" and doe.get("phase") is None
    nsurf = len(spec["surfaces"])
    for i, s in enumerate(spec["surfaces"], start=1):
        w(f"SURF {i}")
        kind = s.get("type", "standard")
        if s.get("stop"):
            w("  STOP")
        if s.get("comment"):
            w("  COMM " + " ".join(str(s["comment"]).split()))
        w("  TYPE " + {v: k for k, v in SURFACE_TYPES.items()}[kind])
        if kind == "coordinate_break":
            dec, tilt = s.get("decenter", [0.0, 0.0]), s.get("tilt", [0.0, 0.0, 0.0])
            for j, v in enumerate(list(dec) + list(tilt) + [s.get("order", 0)], start=1):
                w(f"  PARM {j} {_num(v)}")
            w(f"  DISZ {_num(s['thickness'])}")
            continue
        if kind != "paraxial":
            w(f"  CURV {_num(curvature_of(s))}")
        w(f"  DISZ {_num(doe['distance'] if binary2 and i == nsurf else s['thickness'])}")
        g = _glas_line(s.get("material", "air"))
        if g:
            w("  " + g)
        if s.get("semi_diameter") is not None:
            w(f'  DIAM {_num(s["semi_diameter"])} 1 0 0 1 ""')
        if kind != "paraxial":
            w(f"  CONI {_num(s.get('conic', 0.0))}")
        if kind == "even_asphere":
            asph = aspheric_canonical(s.get("aspheric"))
            for k in ("a18", "a20"):
                if k in asph:
                    raise LensFileError(f"surfaces[{i - 1}].aspheric.{k}: .zmx EVENASPH surfaces stop at a16 "
                                        "(PARM 8)", source)
            for j in range(1, MAX_EVENASPH_PARM + 1):
                w(f"  PARM {j} {_num(asph.get(f'a{2 * j}', 0.0))}")
        if kind == "odd_asphere":
            asph = aspheric_canonical(s.get("aspheric"), range(1, MAX_ODDASPHE_PARM + 1))
            for j in range(1, MAX_ODDASPHE_PARM + 1):
                w(f"  PARM {j} {_num(asph.get(f'a{j}', 0.0))}")
        if kind == "toroidal":
            r = rotation_radius_canonical(s.get("radius_of_rotation"))
            w(f"  PARM 1 {_num(0.0 if r == 'inf' else r)}")
            asph = aspheric_canonical(s.get("aspheric"), range(2, 15, 2))
            for j in range(2, 9):
                w(f"  PARM {j} {_num(asph.get(f'a{2 * (j - 1)}', 0.0))}")
        if kind == "paraxial":
            w(f"  PARM 1 {_num(s['focal_length'])}")
        ap = s.get("aperture")
        if ap is not None:
            if ap["shape"] == "circle":
                w(f"  CLAP 0 {_num(ap['radius'])} 0")
            else:
                w(f"  SQAP {_num(ap['half_width'])} {_num(ap['half_width'])}")
    n = len(spec["surfaces"]) + 1
    if binary2:
        _write_binary2(w, n, doe, spec["surfaces"][-1], source)
        n += 1
    w(f"SURF {n}")
    w("  TYPE STANDARD")
    w("  CURV 0.0")
    w("  DISZ 0.0")
    sensor = spec.get("sensor")
    if sensor:
        w(f'  DIAM {_num(0.5 * math.hypot(*sensor["size"]))} 1 0 0 1 ""')
    lost = [k for k in ("sensor", "description") if spec.get(k)]
    if doe is not None and not binary2:
        lost.append("doe (only a binary_2 phase model becomes a BINARY_2 surface)")
    elif doe is not None:
        extra = [k for k in ("pitch", "shape", "design_wavelength", "material", "levels", "wrap") if doe.get(k)]
        if doe.get("oversample", 1) != 1:
            extra.append("oversample")
        if extra:
            lost.append(f"the DOE's {', '.join(extra)}")
    if lost:
        warnings.warn(LensFileWarning(f"{source}: .zmx files do not store {' and '.join(lost)}; "
                                      "they are left out"), stacklevel=3)
    return "\r\n".join(out) + "\r\n"


def _system_aperture_line(ap) -> str:
    """The .zmx line of a spec's "system_aperture" (FLOA without one)."""
    if not ap or ap.get("float_by_stop_size"):
        return "FLOA"
    for key, kinds in SYSTEM_APERTURE_KEYS.items():
        for flag, kind in kinds.items():
            if kind in ap:
                return f"ENPD {_num(ap[kind])}" if key == "ENPD" else f"{key} {_num(ap[kind])} {flag}"
    raise ValueError(f"unknown system aperture {ap!r}")  # validate_spec rejects it first


def _write_binary2(w, number: int, doe: dict, last: dict, source) -> None:
    """The DOE plane as a BINARY_2 surface (PARM 0 = diffraction order, XDAT 1 = N, XDAT 2 = normalisation
    radius, XDAT 3.. = A_i in rad) between the last lens surface and the image."""
    model = doe["phase_model"]
    coeffs = [float(c) for c in model["coefficients"]]
    if len(coeffs) > MAX_BINARY2_TERMS:
        raise LensFileError(f"doe.phase_model: a .zmx BINARY_2 surface holds at most {MAX_BINARY2_TERMS} terms, got "
                            f"{len(coeffs)}", source)
    rest = float(last["thickness"]) - float(doe["distance"])
    w(f"SURF {number}")
    w("  TYPE BINARY_2")
    w("  CURV 0.0")
    w(f"  DISZ {_num(rest)}")
    g = _glas_line(last.get("material", "air"))
    if g:
        w("  " + g)
    size = doe.get("size")
    if size is not None and size[0] == size[1]:
        if doe.get("aperture", "square") == "circle":
            w(f"  CLAP 0 {_num(0.5 * size[0])} 0")
        else:
            w(f"  SQAP {_num(0.5 * size[0])} {_num(0.5 * size[1])}")
    w(f"  PARM 0 {_num(model.get('order', 1.0))}")
    for j in range(1, 9):
        w(f"  PARM {j} 0.0")
    for j, v in enumerate([float(len(coeffs)), float(model["norm_radius"])] + coeffs, start=1):
        w(f'  XDAT {j} {_num(v)} 0 0 1 0 0 ""')


def _glas_line(m) -> str | None:
    if m is None or (isinstance(m, str) and m.lower() == "air"):
        return None
    if isinstance(m, str) and m.lower() == "mirror":
        return "GLAS MIRROR 0 0 1.5 40 0 0 0 0 0 0"
    if isinstance(m, str):
        return f"GLAS {m} 0 0 0 0 0 0 0 0 0 0"
    if "index" in m:
        return f"GLAS ___BLANK 1 0 {_num(m['index'])} 0 0 0 0 0 0 0"
    if "model" in m:
        return f"GLAS ___BLANK 1 0 {_num(m['model']['nd'])} {_num(m['model']['vd'])} 0 0 0 0 0 0"
    return f"GLAS {m['name']} 0 0 0 0 0 0 0 0 0 0"


def write_zmx(spec: dict, path, encoding: str = "utf-16") -> None:
    """Write ``spec`` as a Zemax .zmx file that :func:`read_zmx` reads back to ``canonical_spec(spec)``.

    ``encoding``: "utf-16" (default; UTF-16 LE with BOM, as OpticStudio writes) or "utf-8".
    Lines end with CRLF. The sensor and description are not stored (a :class:`LensFileWarning` says so);
    the image surface gets the sensor half-diagonal as its semi-diameter.
    """
    text = zmx_text(spec, str(path))
    enc = encoding.lower().replace("_", "-")
    if enc in ("utf-16", "utf-16-le", "utf16"):
        data = b"\xff\xfe" + text.encode("utf-16-le")
    elif enc in ("utf-8", "utf8"):
        data = text.encode("utf-8")
    else:
        raise ValueError(f"encoding must be 'utf-16' or 'utf-8', got {encoding!r}")
    Path(path).write_bytes(data)
