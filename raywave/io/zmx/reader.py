"""A .zmx file -> a validated lens spec (:func:`read_zmx`): the system data, the surfaces, the DOE plane."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import FORMAT_NAME, FORMAT_VERSION, UNITS, validate_spec
from raywave.io.spec import DEFAULT_WAVELENGTHS, shape_entry
from raywave.io.zmx.diffractive import _doe_from_surface
from raywave.io.zmx.surface import _surface
from raywave.io.zmx.tables import IGNORED_SYSTEM_KEYS, SYSTEM_APERTURE_KEYS, UNIT_SCALE
from raywave.io.zmx.tokens import _float, _int, _parse_lines, _state, decode_zmx_bytes


def read_zmx(path) -> dict:
    """Read a Zemax .zmx file into a validated lens spec (:mod:`raywave.io.zmx` says what is read)."""
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
        self.wavm: dict[int, float] = {}  # WAVM index -> µm
        self.wavl: list[float] = []
        self.pwav = 1


def _interpret(text: str, path: str) -> dict:
    """The lens spec (not yet validated) of the .zmx ``text``; ``path`` names the file in errors and warnings."""
    system, surfs = _parse_lines(text)
    unknown: dict[str, int] = {}
    st = _System()
    for ln, key, rest in system:
        _state.line = (ln, key, rest)
        _system_entry(st, ln, key, rest, path, unknown)
    _check_numbering(surfs, path)
    parsed = [_surface(s, path, st.scale, unknown) for s in surfs]
    obj, img = parsed[0], parsed[-1]
    lens, doe = _split_doe(parsed, path, st.scale)
    distance = _object_distance(obj, img, path)

    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    if st.name:
        spec["name"] = st.name
    if st.catalogs:
        spec["catalogs"] = st.catalogs
    spec["object"] = {"distance": distance}
    if st.sys_ap is not None:
        spec["system_aperture"] = _system_aperture(st.sys_ap, distance, st.scale, path)
    spec["fields"] = _fields(st, path)
    spec["wavelengths"] = _wavelengths(st, path)
    spec["surfaces"] = [_lens_surface(p, "system_aperture" in spec, path) for p in lens]
    if doe is not None:
        spec["doe"] = doe
    if st.floating and st.sys_ap is not None:
        warnings.warn(LensFileWarning(f"{path}: both {st.sys_ap[0]} (line {st.sys_ap[2]}) and FLOA given; using "
                                      f"{st.sys_ap[0]}"), stacklevel=3)

    if unknown:
        listed = ", ".join(f"{k} (line {ln})" for k, ln in sorted(unknown.items(), key=lambda kv: kv[1]))
        warnings.warn(LensFileWarning(f"{path}: ignored unknown .zmx keys: {listed}"), stacklevel=3)
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
    elif key in ("YFLN", "YFLD"):
        st.yfln = [_float(t, path, ln, key) for t in toks]
    elif key == "WAVM":
        if len(toks) < 2:
            raise LensFileError("WAVM needs an index and a wavelength", path, ln)
        st.wavm[_int(toks[0], path, ln, "WAVM index", 1, 10**6)] = _float(toks[1], path, ln, "WAVM")
    elif key == "WAVL":
        st.wavl = [_float(t, path, ln, "WAVL") for t in toks]
    elif key == "PWAV":
        st.pwav = _int(toks[0], path, ln, "PWAV", 1, 10**6) if toks else 1
    elif key == "MNUM" and toks and toks[0].isdigit() and int(toks[0]) > 1:
        warnings.warn(LensFileWarning(f"{path}:{ln}: multi-configuration file ({toks[0]} configurations); "
                                      "the prescription as written (current configuration) is read"),
                      stacklevel=4)
    elif key in IGNORED_SYSTEM_KEYS:
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


def _check_numbering(surfs: list, path: str) -> None:
    """The SURF blocks exist, are numbered 0, 1, 2, ... and hold an object, a surface and an image at least."""
    if not surfs:
        raise LensFileError("no surfaces (SURF lines) in the file", path, None)
    nums = [s.number for s in surfs]
    if nums != list(range(len(surfs))):
        raise LensFileError(f"surfaces must be numbered 0, 1, 2, ... in order; got {nums}", path, surfs[0].line)
    if len(surfs) < 3:
        raise LensFileError("a lens needs an object surface, at least one surface and an image surface", path,
                            surfs[-1].line)


def _split_doe(parsed: list, path: str, scale: float):
    """``(lens surfaces, doe section or None)``: the parsed surfaces between object and image, without a
    diffractive last surface, which becomes the DOE plane of a hybrid lens (its thickness, mm, is added to the
    surface before it, so that the refractive lens reaches the sensor); a diffractive surface elsewhere is an
    error."""
    obj, lens = parsed[0], parsed[1:-1]
    doe = None
    for p in parsed[:-1]:
        if p["kind"] == "diffractive" and p is not parsed[-2]:
            raise LensFileError(f"surface {p['number']}: diffractive surface type {p['zemax_type']} is supported "
                                "only as the last surface before the image (the DOE plane of a hybrid lens)", path,
                                p["line"])
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


def _medium_after(lens: list):
    """The medium after the last of the parsed ``lens`` surfaces: a coordinate break and a mirror keep the medium
    before them (the object space is air)."""
    medium = "air"
    for p in lens:
        if p["kind"] != "coordinate_break" and p["material"] != "mirror":
            medium = p["material"]
    return medium


def _object_distance(obj: dict, img: dict, path: str):
    """The spec's object distance (mm, or "inf") from surface 0, after checking that the object and image surfaces
    are flat standard planes, not the stop, the object in air and the image no mirror."""
    for p, what in ((obj, "object"), (img, "image")):
        if p["kind"] != "standard" or p["curv"] != 0.0:
            raise LensFileError(f"surface {p['number']} ({what}): a curved or non-standard {what} surface is not "
                                "supported (raywave's object and image are planes)", path, p["line"])
        if p["stop"]:
            raise LensFileError(f"surface {p['number']} ({what}) cannot be the stop", path, p["line"])
    if img["material"] == "mirror":
        raise LensFileError(f"surface {img['number']} (image): the image surface cannot be a mirror", path,
                            img["line"])
    if obj["material"] != "air":
        raise LensFileError("surface 0 (object): the object space must be air", path, obj["line"])
    dist = obj["disz"]
    if dist is None or math.isinf(dist):
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


def _fields(st: _System, path: str) -> dict:
    """The spec's "fields": FTYP 0 (angles, degrees) or 1 (object heights, scaled to mm); the first FTYP-count
    XFLN / YFLN entries (default: up to the last non-zero one), x components folded into radial fields."""
    ftyp, xfln, yfln = st.ftyp, st.xfln, st.yfln
    nfld = ftyp[0][2] if ftyp and len(ftyp[0]) >= 3 else None
    ftype = ftyp[0][0] if ftyp and ftyp[0] else 0
    if ftype not in (0, 1):
        names = {2: "paraxial image height", 3: "real image height", 4: "theodolite angle"}
        raise LensFileError(f"FTYP {ftype}: field type {names.get(ftype, ftype)} is not supported (raywave: angle = "
                            "0, object height = 1)", path, ftyp[1])
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
    values = [math.hypot(x, y) if x else y for x, y in zip(xs, ys)]
    if ftype == 1:
        values = [v * st.scale for v in values]
    return {"type": "angle" if ftype == 0 else "object_height", "values": values}


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
    s["aperture"] = aperture
    if p["diam"] is not None:
        s["semi_diameter"] = p["diam"]
    s["stop"] = p["stop"]
    if p["comment"]:
        s["comment"] = p["comment"]
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
