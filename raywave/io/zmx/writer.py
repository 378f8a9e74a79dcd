"""Lens specs -> .zmx text and files (:func:`zmx_text`, :func:`write_zmx`): UTF-16 LE with BOM and CRLF line
ends by default, as OpticStudio writes; a binary_2 DOE becomes a BINARY_2 surface, and a DOE inside the lens (a
surface's ``"doe"``, issue 46) a BINARY_2 / DGRATING surface (:mod:`raywave.io.zmx.surface_doe_writer`)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import validate_spec
from raywave.io.spec import (DEFAULT_WAVELENGTHS, aspheric_canonical, curvature_of, resized_stop_aperture,
                             rotation_radius_canonical, system_aperture_canonical)
from raywave.io.zmx.surface_doe_writer import (doe_aperture_lines, doe_extras, phase_lines, surface_doe_plan,
                                               zemax_type)
from raywave.io.zmx.tables import MAX_EVENASPH_PARM, MAX_ODDASPHE_PARM, SURFACE_TYPES, SYSTEM_APERTURE_KEYS


def _num(x) -> str:
    return repr(float(x))


def zmx_text(spec: dict, source="<spec>") -> str:
    """The .zmx text for ``spec`` (see :func:`write_zmx`)."""
    validate_spec(spec, source)
    out: list[str] = []
    w = out.append
    _system_lines(w, spec)
    d = (spec.get("object") or {}).get("distance", "inf")
    obj = spec.get("object") or {}
    w("SURF 0")
    w("  TYPE STANDARD")
    w(f"  CURV {_num(obj.get('curvature', 0.0))}")
    w("  DISZ " + ("INFINITY" if d == "inf" else _num(d)))
    if obj.get("material") not in (None, "air"):
        glas = _glas_line(obj["material"])
        if glas:
            w("  " + glas)
    doe = spec.get("doe")
    model = (doe or {}).get("phase_model")
    binary2 = doe is not None and model is not None and model.get("type") == "binary_2" and doe.get("phase") is None
    nsurf = len(spec["surfaces"])
    sign, medium = _doe_side(spec["surfaces"])
    resized = resized_stop_aperture(spec["surfaces"]) if system_aperture_canonical(spec.get("system_aperture")) \
        else None
    last_doe = sign * float(doe["distance"]) + 0.0 if binary2 else None  # DISZ to the DOE plane (+ 0.0: no -0.0)
    plan, lost_inside = surface_doe_plan(spec["surfaces"], resized, last_doe, source)
    n = 1
    for i, s in enumerate(spec["surfaces"]):
        own, planes = plan.get(i, (None, []))
        # the DISZ after the surface: to its first DOE plane, else to the DOE before the sensor, else its thickness
        ends = [d for d, _ in planes] + ([last_doe] if binary2 and i == nsurf - 1 else []) + [float(s["thickness"])]
        # a diffractive surface last before the image would be read as the DOE before the sensor (the top-level
        # "doe"): a plain plane half way from the last DOE to the image keeps the DOEs inside the lens
        plain = i == nsurf - 1 and not binary2 and (own is not None or planes)
        if plain:
            at = planes[-1][0] if planes else 0.0
            ends.insert(-1, at + 0.5 * (ends[-1] - at))
        _surface_lines(w, n, i, s, ends[0], source, resized=resized == i, own_doe=own)
        n += 1
        for k, (d, pdoe) in enumerate(planes):
            _doe_plane(w, n, i, pdoe, ends[k + 1] - d, s.get("material", "air"), source)
            n += 1
        if plain:
            _plain_plane(w, n, ends[-1] - ends[-2], s.get("material", "air"))
            n += 1
    if binary2:
        _write_binary2(w, n, doe, spec["surfaces"][-1], source, sign, medium)
        n += 1
    w(f"SURF {n}")
    w("  TYPE STANDARD")
    w(f"  CURV {_num((spec.get('image') or {}).get('curvature', 0.0))}")
    w("  DISZ 0.0")
    sensor = spec.get("sensor")
    if sensor:
        w(f'  DIAM {_num(0.5 * math.hypot(*sensor["size"]))} 1 0 0 1 ""')
    _warn_left_out(spec, doe, binary2, lost_inside, source)
    return "\r\n".join(out) + "\r\n"


def _system_lines(w, spec: dict) -> None:
    """The system data (version, mode, name, units, system aperture, glass catalogs, fields, wavelengths) through
    ``w`` (one line per call)."""
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
    ftyp = {"angle": 0, "object_height": 1, "paraxial_image_height": 2, "real_image_height": 3}
    w(f"FTYP {ftyp[fields.get('type', 'angle')]} 0 {len(fv)} {len(wv)} 0 0 0")
    pad = [0.0] * max(0, 12 - len(fv))
    w("XFLN " + " ".join(_num(0.0) for _ in fv + pad))
    w("YFLN " + " ".join(_num(v) for v in fv + pad))
    w("FWGN " + " ".join("1" for _ in fv + pad))
    for i, v in enumerate(wv, start=1):
        w(f"WAVM {i} {_num(v)} 1")
    w(f"PWAV {int(wls.get('primary', 0)) + 1}")


def _doe_side(surfaces: list) -> tuple[float, object]:
    """``(sign, medium)`` after the last spec surface: −1 after an odd number of mirrors (the thicknesses there
    are negative, the DOE's distance is along the light), and the medium there (a mirror or a coordinate break
    keeps the medium before it)."""
    mirrors, medium = 0, "air"
    for s in surfaces:
        m = s.get("material")
        if isinstance(m, str) and m.lower() == "mirror":
            mirrors += 1
        elif s.get("type", "standard") != "coordinate_break":
            medium = m if m is not None else "air"
    return (-1.0 if mirrors % 2 else 1.0), medium


def _surface_lines(w, number: int, i: int, s: dict, disz: float, source, resized: bool = False,
                   own_doe: dict | None = None) -> None:
    """The SURF block (``SURF number``) of spec surface ``s`` (``surfaces[i]``) through ``w``; ``disz``: its DISZ
    (mm: its thickness, or the distance to a DOE plane after it, signed: negative after an odd number of mirrors);
    ``own_doe``: a DOE written on the surface itself (a BINARY_2 / DGRATING surface,
    :mod:`raywave.io.zmx.surface_doe_writer`)."""
    w(f"SURF {number}")
    kind = s.get("type", "standard")
    if s.get("stop"):
        w("  STOP")
    if s.get("comment"):
        w("  COMM " + " ".join(str(s["comment"]).split()))
    extended = _extended_terms(s)
    typ = zemax_type(own_doe)[0] if own_doe is not None else None
    w("  TYPE " + (typ or (extended[0] if extended else {v: k for k, v in SURFACE_TYPES.items()}[kind])))
    if kind == "coordinate_break":
        dec, tilt = s.get("decenter", [0.0, 0.0]), s.get("tilt", [0.0, 0.0, 0.0])
        for j, v in enumerate(list(dec) + list(tilt) + [s.get("order", 0)], start=1):
            w(f"  PARM {j} {_num(v)}")
        w(f"  DISZ {_num(disz)}")
        return
    if kind != "paraxial":
        w(f"  CURV {_num(curvature_of(s))}")
    w(f"  DISZ {_num(disz)}")
    g = _glas_line(s.get("material", "air"))
    if g:
        w("  " + g)
    if s.get("semi_diameter") is not None:
        w(f'  DIAM {_num(s["semi_diameter"])} 1 0 0 1 ""')
    if kind != "paraxial":
        w(f"  CONI {_num(s.get('conic', 0.0))}")
    if own_doe is not None:
        phase_lines(w, own_doe, f"surfaces[{i}].doe", source)
    else:
        _parm_lines(w, i + 1, kind, s, source)
    ap = s.get("aperture")
    if ap is not None and not resized:  # a stop's plain circle a system aperture resizes: no CLAP (it would fix it)
        _aperture_lines(w, i + 1, ap, source)


def _doe_plane(w, number: int, i: int, doe: dict, disz: float, medium, source) -> None:
    """A DOE inside the lens on a plane of its own (``SURF number``, BINARY_2 / DGRATING) in the gap after
    ``surfaces[i]`` (``medium``: the medium there; ``disz``: mm to the next DOE plane or surface): the reader gives
    it back as a plane surface carrying the DOE 0 mm after it, its clear aperture the DOE's size."""
    _plain_plane(w, number, disz, medium, zemax_type(doe)[0])
    phase_lines(w, doe, f"surfaces[{i}].doe", source)
    doe_aperture_lines(w, doe)


def _plain_plane(w, number: int, disz: float, medium, kind: str = "STANDARD") -> None:
    """A plane surface of Zemax type ``kind`` (``SURF number``) in ``medium``, ``disz`` mm before the next surface (a
    STANDARD one changes no ray)."""
    w(f"SURF {number}")
    w("  TYPE " + kind)
    w("  CURV 0.0")
    w(f"  DISZ {_num(disz)}")
    g = _glas_line(medium)
    if g:
        w("  " + g)
    w("  CONI 0.0")


def _aperture_lines(w, i: int, ap: dict, source) -> None:
    """The aperture lines of surface ``i``: CLAP / SQAP, an annulus as CLAP rmin rmax, an obscuration alone as
    OBSC 0 r / OBSQ hx hy with OBDC for its decentre. OpticStudio has one aperture type per surface: a clear
    aperture with a decentred or rectangular obscuration, or a square one with any obscuration, is an error."""
    obs = ap.get("obscuration")
    if ap["shape"] == "none":
        if obs["shape"] == "circle":
            w(f"  OBSC 0 {_num(obs['radius'])}")
        elif obs["shape"] == "annulus":
            w(f"  OBSC {_num(obs['inner_radius'])} {_num(obs['radius'])}")
        else:
            w(f"  OBSQ {_num(obs['half_width_x'])} {_num(obs['half_width_y'])}")
        d = obs.get("decenter")
        if d and any(d):
            w(f"  OBDC {_num(d[0])} {_num(d[1])}")
        return
    if obs is not None and (ap["shape"] != "circle" or obs.get("shape", "circle") != "circle"
                            or any(obs.get("decenter") or ())):
        raise LensFileError(f"surfaces[{i - 1}].aperture: a .zmx surface has one aperture type; only a circle "
                            "with a centred circular obscuration (CLAP rmin rmax) or an obscuration alone can be "
                            "written", source)
    if ap["shape"] == "circle":
        w(f"  CLAP {_num(obs['radius']) if obs is not None else 0} {_num(ap['radius'])} 0")
    elif ap["shape"] == "rectangle":
        w(f"  SQAP {_num(ap['half_width_x'])} {_num(ap['half_width_y'])}")
    else:
        w(f"  SQAP {_num(ap['half_width'])} {_num(ap['half_width'])}")
    d = ap.get("decenter")
    if d and any(d):
        w(f"  OBDC {_num(d[0])} {_num(d[1])}")


def _extended_terms(s: dict):
    """``(type, [A_1..A_N])`` when an even / odd asphere has more terms than EVENASPH / ODDASPHE hold (a16 / a8):
    it is written as an XASPHERE / XOSPHERE with normalisation radius 1 mm (its XDAT terms are the mm terms); else
    None."""
    kind = s.get("type", "standard")
    if kind not in ("even_asphere", "odd_asphere"):
        return None
    odd = kind == "odd_asphere"
    asph = aspheric_canonical(s.get("aspheric"), range(1, 241) if odd else range(2, 481, 2))
    top = max((int(k[1:]) for k in asph), default=0)
    if top <= (MAX_ODDASPHE_PARM if odd else 2 * MAX_EVENASPH_PARM):
        return None
    step = 1 if odd else 2
    return ("XOSPHERE" if odd else "XASPHERE"), [asph.get(f"a{p}", 0.0) for p in range(step, top + 1, step)]


def _parm_lines(w, i: int, kind: str, s: dict, source) -> None:
    """The PARM lines of surface ``i`` by kind: even (a2..a16) / odd (b1..b8) aspheric terms, a toroid's radius of
    rotation (mm) and a2..a14, a paraxial focal length (mm)."""
    extended = _extended_terms(s)
    if extended:
        terms = extended[1]
        for j, v in enumerate([float(len(terms)), 1.0] + terms, start=1):
            w(f'  XDAT {j} {_num(v)} 0 0 1 0 0 ""')
        return
    if kind == "even_asphere":
        asph = aspheric_canonical(s.get("aspheric"), range(2, 481, 2))
        for k, v in asph.items():
            if int(k[1:]) > 2 * MAX_EVENASPH_PARM and v != 0.0:
                raise LensFileError(f"surfaces[{i - 1}].aspheric.{k}: .zmx EVENASPH surfaces stop at a16 "
                                    "(PARM 8)", source)
        for j in range(1, MAX_EVENASPH_PARM + 1):
            w(f"  PARM {j} {_num(asph.get(f'a{2 * j}', 0.0))}")
    if kind == "odd_asphere":
        asph = aspheric_canonical(s.get("aspheric"), range(1, 241))
        for k, v in asph.items():
            if int(k[1:]) > MAX_ODDASPHE_PARM and v != 0.0:
                raise LensFileError(f"surfaces[{i - 1}].aspheric.{k}: .zmx ODDASPHE surfaces stop at a8 "
                                    "(PARM 8)", source)
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


def _warn_left_out(spec: dict, doe, binary2: bool, lost_inside: list, source) -> None:
    """One :class:`LensFileWarning` naming what a .zmx file cannot store (sensor, description, a DOE that is not a
    binary_2 model, or the DOE's grid and fabrication data; ``lost_inside``: the same for the DOEs inside the lens,
    :func:`raywave.io.zmx.surface_doe_writer.surface_doe_plan`)."""
    lost = [k for k in ("sensor", "description") if spec.get(k)]
    if doe is not None and not binary2:
        lost.append("doe (only a binary_2 phase model becomes a BINARY_2 surface)")
    elif doe is not None:
        extra = doe_extras(doe)
        if extra:
            lost.append(f"the DOE's {', '.join(extra)}")
    lost += lost_inside
    if lost:
        warnings.warn(LensFileWarning(f"{source}: .zmx files do not store {' and '.join(lost)}; "
                                      "they are left out"), stacklevel=4)


def _system_aperture_line(ap) -> str:
    """The .zmx line of a spec's "system_aperture" (FLOA without one)."""
    if not ap or ap.get("float_by_stop_size"):
        return "FLOA"
    for key, kinds in SYSTEM_APERTURE_KEYS.items():
        for flag, kind in kinds.items():
            if kind in ap:
                return f"ENPD {_num(ap[kind])}" if key == "ENPD" else f"{key} {_num(ap[kind])} {flag}"
    raise ValueError(f"unknown system aperture {ap!r}")  # validate_spec rejects it first


def _write_binary2(w, number: int, doe: dict, last: dict, source, sign: float = 1.0, medium=None) -> None:
    """The DOE plane as a BINARY_2 surface (PARM 0 = diffraction order, XDAT 1 = N, XDAT 2 = normalisation
    radius, XDAT 3.. = A_i in rad: :func:`raywave.io.zmx.surface_doe_writer.phase_lines`) between the last lens
    surface and the image (``sign``, ``medium``: see :func:`_doe_side`)."""
    rest = float(last["thickness"]) - sign * float(doe["distance"])
    w(f"SURF {number}")
    w("  TYPE BINARY_2")
    w("  CURV 0.0")
    w(f"  DISZ {_num(rest)}")
    g = _glas_line(last.get("material", "air") if medium is None else medium)
    if g:
        w("  " + g)
    size = doe.get("size")
    if size is not None and size[0] == size[1]:
        doe_aperture_lines(w, doe)
    phase_lines(w, doe, "doe", source)


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
    the image surface gets the sensor half-diagonal as its semi-diameter. A DOE inside the lens (a surface's
    ``"doe"``) becomes a BINARY_2 / DGRATING surface: on its surface, or on a plane of its own that reads back as
    one more plane surface (:mod:`raywave.io.zmx.surface_doe_writer`); what a .zmx cannot hold is named in the
    warning.
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
