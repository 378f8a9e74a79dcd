"""A .zmx file -> a validated lens spec (:func:`read_zmx`): the system data, the surfaces, the DOE plane."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import FORMAT_NAME, FORMAT_VERSION, UNITS, validate_spec
from raywave.io.spec import DEFAULT_WAVELENGTHS, shape_entry
from raywave.io.zmx.diffractive import _doe_from_surface, doe_inside
from raywave.io.zmx.surface import _surface
from raywave.io.zmx.tables import (IGNORED_SYSTEM_KEYS, MERIT_OPERANDS, MULTI_CONFIG_APPLIED, MULTI_CONFIG_IGNORED,
                                   SURFACE_TYPES, SYSTEM_APERTURE_KEYS, UNIT_SCALE)
from raywave.io.zmx.tokens import _float, _int, _parse_lines, _state, decode_zmx_bytes
from raywave.utils.checks import MAX_FIELD_ANGLE, MAX_WIDE_FIELD_ANGLE


def read_zmx(path, config: int | None = None) -> dict:
    """Read a Zemax .zmx file into a validated lens spec (:mod:`raywave.io.zmx` says what is read).

    ``config``: the configuration of a multi-configuration file (zoom, focus), 1-based; default 1. Its
    multi-configuration operands THIC, SDIA, YFIE and APER are applied; the choice is reported in a warning."""
    path = str(path)
    text, _enc = decode_zmx_bytes(Path(path).read_bytes())
    _state.line = None
    _state.decimal_commas = []
    try:
        spec = _interpret(text, path, config)
    except LensFileError as e:
        if e.path == "<spec>":  # raised below without the path
            raise LensFileError(e.reason, path, e.line, e.column) from None
        raise
    except (ValueError, IndexError, ArithmeticError) as e:  # a malformed value that no check above caught
        ln, key, rest = _state.line or (None, "", "")
        raise LensFileError(f"cannot read {key} {rest!r}: {e}", path, ln) from None
    if _state.decimal_commas:
        lines = _state.decimal_commas
        warnings.warn(LensFileWarning(f"{path}: numbers with a decimal comma read as decimals (line "
                                      f"{', '.join(map(str, lines[:5]))}{', ...' if len(lines) > 5 else ''})"),
                      stacklevel=2)
    return validate_spec(spec, path)



class _System:
    """The system data of a .zmx file (the entries before the first ``SURF``), in file units."""

    def __init__(self):
        self.scale = 1.0  # lens unit -> mm
        self.name = ""
        self.sys_ap = None  # (spec key, value in file units, line)
        self.floating = False
        self.catalogs: list[str] = []
        self.ftyp = None  # ([FTYP integers], line)
        self.xfln: list[float] = []
        self.yfln: list[float] = []
        self.field_lines: dict[int, int] = {}  # field index (0-based) -> the line that gives its value
        self.yfln_line = None  # line of YFLN / XFLN
        self.wavm: dict[int, float] = {}  # WAVM index -> µm
        self.wavl: list[float] = []
        self.pwav = 1
        self.mnum = None  # (number of configurations, current configuration, line)
        self.mce: list[tuple[int, str, list[str]]] = []  # multi-configuration operands: (line, key, tokens)


def _warn(message: str) -> None:
    warnings.warn(LensFileWarning(message), stacklevel=4)


def _interpret(text: str, path: str, config: int | None = None) -> dict:
    """The lens spec (not yet validated) of the .zmx ``text``; ``path`` names the file in errors and warnings."""
    system, surfs = _parse_lines(text)
    unknown: dict[str, int] = {}
    st = _System()
    for ln, key, rest in system:
        _state.line = (ln, key, rest)
        _system_entry(st, ln, key, rest, path, unknown)
    surfs = _check_numbering(surfs, path)
    parsed = [_surface(s, path, st.scale, unknown) if s is not None else None for s in surfs]
    parsed = _complete_object_and_image(parsed, surfs, path)
    notes: dict[str, list] = {}
    for p in parsed:
        for note, ln in p.get("notes", []):
            notes.setdefault(note, []).append(f"{p['number']} (line {ln})")
    for note, where in notes.items():
        _warn(f"{path}: surface{'s' if len(where) > 1 else ''} {', '.join(where)}: {note}")
    _apply_configuration(st, parsed, config, path)
    obj, img = parsed[0], parsed[-1]
    lens, doe = _split_doe(parsed, path, st.scale)
    _check_axial_order(lens, path)
    distance = _object_distance(obj, img, path)

    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    if st.name:
        spec["name"] = st.name
    if st.catalogs:
        spec["catalogs"] = st.catalogs
    spec["object"] = {"distance": distance}
    if obj["material"] != "air":
        spec["object"]["material"] = obj["material"]
    if obj["curv"] != 0.0:
        spec["object"]["curvature"] = obj["curv"]
    if img["curv"] != 0.0:
        spec["image"] = {"curvature": img["curv"]}
    if st.sys_ap is not None:
        spec["system_aperture"] = _system_aperture(st.sys_ap, distance, st.scale, path)
    elif not st.floating:
        stop = next((p for p in lens if p["stop"]), None)
        where = f"surface {stop['number']} (the stop)" if stop else "the first surface (the stop by default)"
        _warn(f"{path}: no system aperture line (ENPD, FNUM, OBNA or FLOA): the stop's semi-diameter (DIAM of "
              f"{where}) sets the pupil (float by stop size), as OpticStudio does with a fixed stop size")
    spec["fields"] = _fields(st, path, distance)
    spec["wavelengths"] = _wavelengths(st, path)
    spec["surfaces"] = [_lens_surface(p, "system_aperture" in spec, path) for p in lens]
    if doe is not None:
        spec["doe"] = doe
    if st.floating and st.sys_ap is not None:
        warnings.warn(LensFileWarning(f"{path}: both {st.sys_ap[0]} (line {st.sys_ap[2]}) and FLOA given; using "
                                      f"{st.sys_ap[0]}"), stacklevel=3)

    if unknown:
        listed = ", ".join(f"{k} (line {ln})" for k, ln in sorted(unknown.items(), key=lambda kv: kv[1]))
        warnings.warn(LensFileWarning(f"{path}: ignored .zmx keys that may change the optics (not modelled by "
                                      f"raywave): {listed}"), stacklevel=3)
    return spec


def _system_entry(st: _System, ln: int, key: str, rest: str, path: str, unknown: dict) -> None:
    """Read one system entry (line ``ln``: ``key rest``) into ``st``; an unknown key is recorded in ``unknown``."""
    toks = rest.split()
    if key == "MODE":
        if not rest.upper().startswith("SEQ"):
            raise LensFileError(f"MODE {rest}: only sequential (MODE SEQ) files can be read", path, ln)
    elif key == "NAME":
        st.name = rest.strip().strip('"')
    elif key == "UNIT":
        u = toks[0].upper() if toks else "MM"
        if u not in UNIT_SCALE:
            raise LensFileError(f"UNIT {u}: unknown lens unit (known: {', '.join(UNIT_SCALE)})", path, ln)
        st.scale = UNIT_SCALE[u]
    elif key in SYSTEM_APERTURE_KEYS:
        st.sys_ap = _system_aperture_entry(st.sys_ap, ln, key, rest, path)
    elif key == "FLOA":
        st.floating = True
    elif key == "GCAT":
        st.catalogs = toks
    elif key == "FTYP":
        # FTYP type, telecentric, number of fields, number of wavelengths, ...
        st.ftyp = ([_int(t, path, ln, f"FTYP entry {i + 1}", 0, 10**6) for i, t in enumerate(toks)], ln)
    elif key in ("XFLN", "XFLD"):
        st.xfln = [_float(t, path, ln, key) for t in toks]
        st.yfln_line = st.yfln_line or ln
    elif key in ("YFLN", "YFLD"):
        st.yfln = [_float(t, path, ln, key) for t in toks]
        st.yfln_line = ln
    elif key == "WAVM":
        if len(toks) < 2:
            raise LensFileError("WAVM needs an index and a wavelength", path, ln)
        st.wavm[_int(toks[0], path, ln, "WAVM index", 1, 10**6)] = _float(toks[1], path, ln, "WAVM")
    elif key == "WAVL":
        st.wavl = [_float(t, path, ln, "WAVL") for t in toks]
    elif key == "PWAV":
        st.pwav = _int(toks[0], path, ln, "PWAV", 1, 10**6) if toks else 1
    elif key == "MNUM":
        n = _int(toks[0], path, ln, "MNUM (number of configurations)", 0, 10**6) if toks else 1
        cur = _int(toks[1], path, ln, "MNUM (current configuration)", 0, 10**6) if len(toks) > 1 else 1
        st.mnum = (max(n, 1), max(cur, 1), ln)
    elif st.mnum is not None and key not in MULTI_CONFIG_IGNORED:
        if key in MERIT_OPERANDS or key in IGNORED_SYSTEM_KEYS:
            return
        st.mce.append((ln, key, toks))
    elif key in IGNORED_SYSTEM_KEYS or key in MERIT_OPERANDS or key in MULTI_CONFIG_IGNORED:
        pass
    else:
        unknown.setdefault(key, ln)


def _system_aperture_entry(sys_ap, ln: int, key: str, rest: str, path: str) -> tuple:
    """``(spec key, value in file units, line)`` of a system aperture entry (ENPD / FNUM / OBNA, line ``ln``);
    ``sys_ap``: the one read before (None), which must be of the same kind."""
    toks = rest.split()
    if not toks:
        raise LensFileError(f"{key} needs a value", path, ln)
    flag = int(float(toks[1])) if len(toks) > 1 and key != "ENPD" else 0
    kinds = SYSTEM_APERTURE_KEYS[key]
    if flag not in kinds:
        raise LensFileError(f"{key} {rest}: unknown system aperture flag {flag} (known: "
                            f"{', '.join(f'{f} = {k}' for f, k in kinds.items())})", path, ln)
    value = _float(toks[0], path, ln, key)
    if not (math.isfinite(value) and value > 0):
        raise LensFileError(f"{key} {rest}: the system aperture value must be > 0", path, ln)
    if sys_ap is not None and sys_ap[0] != kinds[flag]:
        raise LensFileError(f"{key}: a second system aperture (line {sys_ap[2]} already gives {sys_ap[0]}); "
                            "a .zmx file has one system aperture type", path, ln)
    return (kinds[flag], value, ln)


def _check_numbering(surfs: list, path: str) -> list:
    """The SURF blocks in file order, as OpticStudio reads them: numbered 0, 1, 2, ... or not (a gap, a repeated
    number, a suffix such as ``SURF 5AS``: warned, read in order). A file whose first block is ``SURF 1`` has no
    object surface: a None is put first for the default object (at infinity, in air)."""
    if not surfs:
        raise LensFileError("no surfaces (SURF lines) in the file", path, None)
    nums = [s.number for s in surfs]
    out = list(surfs)
    if nums[0] != 0:
        out = [None] + out
    if nums != list(range(nums[0], nums[0] + len(nums))) or nums[0] not in (0, 1):
        _warn(f"{path}:{surfs[0].line}: surfaces are not numbered 0, 1, 2, ... ({_ranges(nums)}): read in file "
              "order, as OpticStudio does")
    for s in surfs:
        if s.suffix:
            _warn(f"{path}:{s.line}: SURF {s.number}{s.suffix}: read as a surface in file order (the suffix "
                  f"{s.suffix!r} is ignored)")
    if len(out) < 3 and out[0] is not None:
        raise LensFileError("a lens needs an object surface, at least one surface and an image surface", path,
                            surfs[-1].line)
    return out


def _ranges(nums: list) -> str:
    """``[1, 2, 3, 5]`` -> ``"1-3, 5"``."""
    parts, start = [], 0
    for i in range(1, len(nums) + 1):
        if i == len(nums) or nums[i] != nums[i - 1] + 1:
            a, b = nums[start], nums[i - 1]
            parts.append(str(a) if a == b else f"{a}-{b}")
            start = i
    return ", ".join(parts)


def _default_surface(number: int, line: int, disz) -> dict:
    """A parsed flat air surface (OpticStudio's default object / image)."""
    return {"number": number, "line": line, "kind": "standard", "curv": 0.0, "disz": disz, "material": "air",
            "diam": None, "conic": 0.0, "parms": {}, "stop": False, "comment": "", "aperture": None, "focal": None,
            "aspheric": {}, "xdat": {}, "zemax_type": None, "notes": []}


def _complete_object_and_image(parsed: list, surfs: list, path: str) -> list:
    """A file without ``SURF 0`` lists lens surfaces only (hand-converted patent data): the object is OpticStudio's
    default (at infinity, air) and, unless the last block is a plain image plane (flat, air, no thickness), an image
    plane is added its DISZ after it. Both are reported in a warning."""
    if parsed[0] is not None:
        return parsed
    first = next(s for s in surfs if s is not None)
    lens = parsed[1:]
    last = lens[-1]
    added = ["an object at infinity (OpticStudio's default object surface 0)"]
    plain_image = (last["curv"] == 0.0 and last["material"] == "air" and not last["disz"] and not last["stop"]
                   and last["kind"] == "standard")
    if not plain_image:
        lens = lens + [_default_surface(last["number"] + 1, last["line"], 0.0)]
        added.append(f"an image plane {last['disz'] or 0:g} mm after surface {last['number']} (its DISZ)")
    if len(lens) < 2:
        raise LensFileError("a lens needs at least one surface and an image surface", path, first.line)
    _warn(f"{path}:{first.line}: the surfaces start at SURF {first.number} (no object surface 0): read as lens "
          f"surfaces with {' and '.join(added)}")
    return [_default_surface(0, first.line, None)] + lens


def _apply_configuration(st: _System, parsed: list, config: int | None, path: str) -> None:
    """Apply the multi-configuration operands of configuration ``config`` (default 1): THIC (thickness, file units),
    SDIA (semi-diameter), YFIE (y field) and APER (system aperture value); report the choice, and name any operand
    that changes the optics but is not modelled. A single-configuration file with ``config`` > 1 is an error."""
    n = st.mnum[0] if st.mnum else 1
    chosen = 1 if config is None else int(config)
    if not 1 <= chosen <= n:
        raise LensFileError(f"configuration {chosen} does not exist: the file has {n} configuration"
                            f"{'s' if n != 1 else ''} (MNUM)", path, st.mnum[2] if st.mnum else None)
    if n <= 1 and not st.mce:
        return
    by_number = {}
    for i, p in enumerate(parsed):
        by_number.setdefault(p["number"], i)
    applied, skipped = [], {}
    for ln, key, toks in st.mce:
        if len(toks) < 3:
            continue
        target = _int(toks[0], path, ln, f"{key} (surface / field number)", 0, 10**6)
        cfg = _int(toks[1], path, ln, f"{key} (configuration)", 0, 10**6)
        if cfg != chosen:
            continue
        if key not in MULTI_CONFIG_APPLIED:
            skipped.setdefault(key, ln)
            continue
        value = _float(toks[2], path, ln, key)
        if key == "YFIE":
            while len(st.yfln) < target:
                st.yfln.append(0.0)
            if target >= 1:
                st.yfln[target - 1] = value
                st.field_lines[target - 1] = ln
        elif key == "APER":
            if st.sys_ap is not None:
                st.sys_ap = (st.sys_ap[0], value, ln)
        elif target in by_number:
            p = parsed[by_number[target]]
            if key == "THIC":
                p["disz"] = math.inf if abs(value) >= 1e10 and p is parsed[0] else value * st.scale
                p["disz_line"] = ln
            else:
                p["diam"] = value * st.scale if value > 0 else None
                if isinstance(p["aperture"], dict) and p.get("floating_aperture"):
                    p["aperture"] = {"shape": "circle", "radius": p["diam"]}
        applied.append(key)
    what = f"{n} configurations" if n > 1 else "1 configuration"
    if n > 1:
        counts = ", ".join(f"{applied.count(k)} {k}" for k in dict.fromkeys(applied)) or "no operands"
        _warn(f"{path}:{st.mnum[2]}: multi-configuration file ({what}, current {st.mnum[1]}): configuration "
              f"{chosen} is read ({counts} applied){'' if config is not None else '; choose another with config=N'}")
    if skipped:
        listed = ", ".join(f"{k} (line {ln})" for k, ln in skipped.items())
        _warn(f"{path}: multi-configuration operands of configuration {chosen} that change the optics are not "
              f"modelled and were ignored: {listed}")


def _split_doe(parsed: list, path: str, scale: float):
    """``(lens surfaces, doe section or None)``: the parsed surfaces between object and image, without a
    diffractive last surface, which becomes the DOE plane of a hybrid lens (its thickness, mm, is added to the
    surface before it, so that the refractive lens reaches the sensor); a diffractive surface elsewhere becomes a
    plane surface with a DOE 0 mm after it (:func:`raywave.io.zmx.diffractive.doe_inside`, issue 46)."""
    obj, lens = parsed[0], parsed[1:-1]
    doe = None
    lens = [doe_inside(p, path, scale) if p["kind"] == "diffractive" and p is not parsed[-2] else p for p in lens]
    if lens and lens[-1]["kind"] == "diffractive":
        if len(lens) < 2 or parsed[-2] is obj:
            raise LensFileError(f"surface {lens[-1]['number']}: a DOE plane needs a refractive lens in front of it",
                                path, lens[-1]["line"])
        d, lens = lens[-1], lens[:-1]
        if all(p["kind"] == "coordinate_break" for p in lens):
            raise LensFileError(f"surface {d['number']}: a DOE plane needs a refractive lens in front of it (only "
                                "coordinate breaks precede it)", path, d["line"])
        # the DOE plane lies on the local axis after the surface before it (a coordinate break or a mirror too: the
        # image-space frame of raywave.lens.frames); after an odd number of mirrors the light travels toward -z
        # and the thicknesses are negative, the distances along the light -DISZ
        sign = -1.0 if sum(p["material"] == "mirror" for p in lens) % 2 else 1.0
        doe = _doe_from_surface(d, lens[-1], path, scale, sign=sign, medium=_medium_after(lens))
        lens[-1] = dict(lens[-1], disz=lens[-1]["disz"] + d["disz"])  # the refractive lens reaches the sensor
    return lens, doe


def _check_axial_order(lens: list, path: str) -> None:
    """A line-numbered error for a negative thickness (DISZ) while the light travels toward +z (before the first
    mirror, or after an even number): the next surface's vertex lies before this one on the axis. OpticStudio
    traces such a gap virtually (backward); raywave's surfaces must follow each other along the light
    (:meth:`raywave.lens.lens.Lens.check_geometry` refuses it; here it is named with its line). Files with
    coordinate breaks are left to that check (their surfaces lie in other frames)."""
    if any(p["kind"] == "coordinate_break" for p in lens):
        return
    forward = True
    for p, nxt in zip(lens[:-1], lens[1:]):
        if p["material"] == "mirror":
            forward = not forward
        d = p["disz"]
        if forward and d is not None and d < -1e-9:
            medium = "air" if p["material"] == "air" else "glass"
            raise LensFileError(f"surface {p['number']}: negative thickness DISZ {d:g} mm in {medium} while the "
                                f"light travels toward +z: surface {nxt['number']} lies {-d:g} mm before it on the "
                                "axis (OpticStudio traces such a gap backward, virtually; raywave needs the surfaces "
                                "in the order the light meets them)", path, p.get("disz_line", p["line"]))


def _medium_after(lens: list):
    """The medium after the last of the parsed ``lens`` surfaces: a coordinate break and a mirror keep the medium
    before them (the object space is air)."""
    medium = "air"
    for p in lens:
        if p["kind"] != "coordinate_break" and p["material"] != "mirror":
            medium = p["material"]
    return medium


def _object_distance(obj: dict, img: dict, path: str):
    """The spec's object distance (mm, or "inf": also a DISZ of 1e10 lens units or more, as OpticStudio takes it)
    from surface 0, after checking that the object and image surfaces are standard surfaces (a curved one is kept in
    the spec), not the stop, and the image no mirror. The object space may be a medium (immersion)."""
    for p, what in ((obj, "object"), (img, "image")):
        if p["kind"] != "standard" or p["conic"] != 0.0:
            typ = p["zemax_type"] or {v: k for k, v in SURFACE_TYPES.items()}.get(p["kind"], p["kind"])
            raise LensFileError(f"surface {p['number']} ({what}): a non-standard {what} surface (type {typ}, conic "
                                f"{p['conic']:g}) is not supported (raywave's {what} is a plane or a sphere)",
                                path, p["line"])
        if p["stop"]:
            raise LensFileError(f"surface {p['number']} ({what}) cannot be the stop", path, p["line"])
    if img["material"] == "mirror" or obj["material"] == "mirror":
        which = img if img["material"] == "mirror" else obj
        raise LensFileError(f"surface {which['number']}: the object and image surfaces cannot be mirrors", path,
                            which["line"])
    dist = obj["disz"]
    if dist is None or math.isinf(dist) or dist >= 1e10:
        if obj["curv"] != 0.0:
            _warn(f"{path}:{obj['line']}: surface 0: the curvature of an object at infinity has no effect")
            obj["curv"] = 0.0
        return "inf"
    if dist <= 0:
        raise LensFileError(f"surface 0 (object): object distance {dist!r} mm must be > 0 (or INFINITY)", path,
                            obj["line"])
    return dist


def _system_aperture(sys_ap: tuple, distance, scale: float, path: str) -> dict:
    """The spec's "system_aperture" of ``(spec key, value in file units, line)`` (an EPD scaled to mm); an
    object-space NA or cone angle needs a finite object ``distance`` and must be < 1 (NA) or < 90°."""
    kind, value, ln = sys_ap
    if kind in ("object_na", "object_cone_angle"):
        if distance == "inf":
            raise LensFileError(f"{'OBNA' if kind == 'object_na' else 'OBNA (cone angle)'}: an object-space "
                                f"{'NA' if kind == 'object_na' else 'cone angle'} needs an object at a finite "
                                "distance (surface 0 DISZ is INFINITY)", path, ln)
        limit = 1.0 if kind == "object_na" else 90.0
        if not value < limit:
            raise LensFileError(f"OBNA {value!r}: must be < {limit:g} "
                                f"({'NA in air' if limit == 1.0 else 'degrees'})", path, ln)
    return {kind: value * scale if kind == "epd" else value}


#: OpticStudio's field types (FTYP) -> the spec's "fields" type.
FIELD_TYPES_BY_FTYP = {0: "angle", 1: "object_height", 2: "paraxial_image_height", 3: "real_image_height"}


def _fields(st: _System, path: str, distance) -> dict:
    """The spec's "fields": FTYP 0 (angles, degrees), 1 (object heights), 2 (paraxial image heights), 3 (real image
    heights; heights scaled to mm); the first FTYP-count XFLN / YFLN entries (default: up to the last non-zero one),
    x components folded into radial fields; FTYP 4 (theodolite angles, azimuth x and elevation y) become the angle
    from the axis, acos(cos x · cos y). An object at infinity may be seen beyond 90° (a fisheye's field, light from
    behind the first vertex) and below 180°; an angle out of range (at or beyond 90° for a finite object) is left out
    with a warning naming the field and its line."""
    ftyp, xfln, yfln = st.ftyp, st.xfln, st.yfln
    nfld = ftyp[0][2] if ftyp and len(ftyp[0]) >= 3 else None
    ftype = ftyp[0][0] if ftyp and ftyp[0] else 0
    if ftype not in FIELD_TYPES_BY_FTYP and ftype != 4:
        raise LensFileError(f"FTYP {ftype}: unknown field type (OpticStudio: angle = 0, object height = 1, paraxial "
                            "image height = 2, real image height = 3, theodolite angle = 4)", path, ftyp[1])
    if ftype == 4 and distance != "inf":
        raise LensFileError("FTYP 4: theodolite angles need an object at infinity (surface 0 DISZ is finite)", path,
                            ftyp[1])
    if ftype == 1 and distance == "inf":
        raise LensFileError("FTYP 1: object-height fields need an object at a finite distance (surface 0 DISZ is "
                            "INFINITY)", path, ftyp[1])
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
                                      "sqrt(x² + y²) (raywave lenses are rotationally symmetric)"), stacklevel=4)
    if ftype == 4:  # theodolite (azimuth x, elevation y): the angle from the axis is acos(cos x · cos y)
        values = [math.degrees(math.acos(math.cos(math.radians(x)) * math.cos(math.radians(y))))
                  * (-1.0 if (y or x) < 0 else 1.0) for x, y in zip(xs, ys)]
        ftype = 0
    else:
        values = [math.hypot(x, y) if x else y for x, y in zip(xs, ys)]
    if ftype == 0:
        limit = MAX_WIDE_FIELD_ANGLE if distance == "inf" else MAX_FIELD_ANGLE
        wide = [i for i, v in enumerate(values) if not abs(v) < limit]
        if wide:
            kept = [v for i, v in enumerate(values) if i not in wide] or [0.0]
            where = ", ".join(f"field {i + 1} ({values[i]:g}°, line {st.field_lines.get(i, st.yfln_line)})"
                              for i in wide)
            why = ("an object at infinity is seen at angles below 180°" if distance == "inf" else
                   f"a finite object's angles must lie below {MAX_FIELD_ANGLE:g}° (the object point is placed with "
                   "tan θ; beyond 90° only for an object at infinity)")
            _warn(f"{path}:{st.field_lines.get(wide[0], st.yfln_line)}: {where} left out: {why}; the fields read are "
                  f"{', '.join(f'{v:g}°' for v in kept)}")
            values = kept
    else:
        values = [v * st.scale for v in values]
    return {"type": FIELD_TYPES_BY_FTYP[ftype], "values": values}


def _wavelengths(st: _System, path: str) -> dict:
    """The spec's "wavelengths" (µm): WAVM entries in index order (else WAVL), the first FTYP-count of them
    (default: raywave's F, d, C), and the primary PWAV (1-based in the file, 0-based in the spec)."""
    ftyp, pwav = st.ftyp, st.pwav
    nwav = ftyp[0][3] if ftyp and len(ftyp[0]) >= 4 else None
    if st.wavm:
        wls = [st.wavm[k] for k in sorted(st.wavm)]
    else:
        wls = st.wavl
    if nwav:
        wls = wls[:nwav]
    if not wls:
        wls = list(DEFAULT_WAVELENGTHS["values"])
        pwav = DEFAULT_WAVELENGTHS["primary"] + 1
    if not 1 <= pwav <= len(wls):
        raise LensFileError(f"PWAV {pwav}: primary wavelength out of range 1..{len(wls)}", path, None)
    return {"values": wls, "primary": pwav - 1}


def _lens_surface(p: dict, has_system_aperture: bool, path: str) -> dict:
    """The spec entry of a parsed lens surface ``p`` (lengths in mm). Without a system aperture, the stop's
    semi-diameter becomes its aperture (float by stop size)."""
    if p["kind"] == "coordinate_break":
        return _coordinate_break(p, path)
    s: dict = {"type": p["kind"]}
    if p["kind"] == "paraxial":
        if p["focal"] is None or p["focal"] == 0.0:
            raise LensFileError(f"surface {p['number']}: a PARAXIAL surface needs a non-zero focal length (PARM 1)",
                                path, p["line"])
        s["focal_length"] = p["focal"]
    else:
        s.update(shape_entry(p["curv"]))
        s["conic"] = p["conic"]
        if p["kind"] == "toroidal":
            s["radius_of_rotation"] = p["rotation"]
        if p["kind"] in ("even_asphere", "odd_asphere", "toroidal"):
            s["aspheric"] = p["aspheric"]
    if p["disz"] is None or math.isinf(p["disz"]):
        raise LensFileError(f"surface {p['number']}: thickness (DISZ) must be finite", path, p["line"])
    s["thickness"] = p["disz"]
    s["material"] = p["material"]
    if p["material"] == "mirror" and p["kind"] == "paraxial":
        raise LensFileError(f"surface {p['number']}: a PARAXIAL surface cannot be a mirror (GLAS MIRROR)", path,
                            p["line"])
    aperture = p["aperture"]
    if aperture is None and p["stop"] and not has_system_aperture and p["diam"]:
        aperture = {"shape": "circle", "radius": p["diam"]}  # float by stop size: the stop's semi-diameter
    elif aperture is not None and aperture["shape"] == "none" and p["stop"]:
        if not p["diam"]:  # the stop needs a clear radius (sized from the pupil, or its own)
            raise LensFileError(f"surface {p['number']}: the stop has an obscuration (OBSC / OBSQ) but no "
                                "semi-diameter (DIAM) for its clear aperture", path, p["line"])
        aperture = {"shape": "circle", "radius": p["diam"], "obscuration": aperture["obscuration"]}
    elif (p["stop"] and has_system_aperture and aperture is not None and aperture["shape"] == "circle"
          and not p.get("floating_aperture")):
        # the stop's own CLAP: a hard edge the system aperture does not enlarge (OpticStudio vignettes at a surface
        # aperture whatever the system aperture says); the system aperture still sets the paraxial pupil
        aperture = dict(aperture, fixed=True)
    s["aperture"] = aperture
    if p["diam"] is not None:
        s["semi_diameter"] = p["diam"]
    s["stop"] = p["stop"]
    if p["comment"]:
        s["comment"] = p["comment"]
    if p.get("surface_doe") is not None:  # a diffractive surface inside the lens (issue 46)
        s["doe"] = p["surface_doe"]
    return s


def _coordinate_break(p: dict, path: str) -> dict:
    """The spec entry of a parsed coordinate break (decentre mm, tilts degrees, order, thickness mm)."""
    s: dict = {"type": p["kind"]}
    if p["stop"]:
        raise LensFileError(f"surface {p['number']}: a coordinate break cannot be the stop", path, p["line"])
    if p["disz"] is None or math.isinf(p["disz"]):
        raise LensFileError(f"surface {p['number']}: thickness (DISZ) must be finite", path, p["line"])
    s.update(p["break"])
    s["thickness"] = p["disz"]
    if p["comment"]:
        s["comment"] = p["comment"]
    return s
