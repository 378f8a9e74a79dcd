"""Import of DeepLens lens files (github.com/singer-yang/DeepLens, ``GeoLens.read_lens_json``).

A DeepLens file is JSON with ``"surfaces"``: a list of dicts with ``"type"`` (Spheric, Aspheric,
Aperture / Stop, Plane, ThinLens), ``"r"`` (semi-aperture, mm), ``"roc"`` or ``"c"`` / ``"(c)"``
(radius / curvature), ``"d_next"`` (distance to the next surface, or to the sensor for the last one)
and/or ``"d"`` / ``"(d)"`` (absolute z of the vertex), ``"k"`` (conic), ``"ai"`` (aspheric terms) and
``"mat2"`` (the medium after the surface: ``"air"``, a glass name, or ``"nd/vd"``); plus top-level
``"r_sensor"`` (sensor half-diagonal), ``"sensor_res"`` ([W, H] pixels), ``"d_sensor"`` / ``"(d_sensor)"``,
``"foclen"``, ``"fnum"``, ``"enpd"`` and ``"info"``. Keys in parentheses are values DeepLens derives and
writes for information only.

Aspheric convention (DeepLens ``Aspheric`` / ``AsphericNorm``): ``ai[i]`` multiplies ``r^(2i+2)``, i.e.
``ai = [a2, a4, a6, ...]`` (the list starts at the r² term) — the same convention as raywave's
``"aspheric": {"a2": .., "a4": ..}`` and Zemax EVENASPH, so the values are copied unchanged.
See docs/lens-format.md, "DeepLens JSON" for every conversion rule.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import (FORMAT_NAME, FORMAT_VERSION, UNITS, key_path, parse_json_text, read_text,
                                    validate_spec)
from raywave.io.spec import DEFAULT_WAVELENGTHS, aspheric_canonical, shape_entry

TOP_KEYS = {"info", "foclen", "fnum", "r_last", "r_sensor", "d_sensor", "(d_sensor)", "sensor_size",
            "(sensor_size)", "sensor_res", "enpd", "surfaces", "hfov", "(hfov)", "rfov", "(rfov)",
            "obj_depth", "(obj_depth)"}
SURFACE_KEYS = {"idx", "surf_idx", "type", "r", "c", "(c)", "roc", "d", "(d)", "d_next", "k", "ai", "mat1", "mat2",
                "is_square", "diffraction", "f", "(l)", "l"}
_AI_KEY = re.compile(r"^\(?ai(\d+)\)?$")
_MODEL_GLASS = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*/\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*$")
#: DeepLens's default sensor resolution when a file gives none.
DEFAULT_SENSOR_RES = (2000, 2000)
#: Fields (fractions of the half field of view) given to an imported lens.
FIELD_FRACTIONS = (0.0, 0.7, 1.0)


def looks_like_deeplens(data) -> bool:
    """Whether parsed JSON ``data`` is a DeepLens lens file (and not a raywave one)."""
    if not isinstance(data, dict) or "format" in data:
        return False
    surfs = data.get("surfaces")
    if not isinstance(surfs, list):
        return False
    if any(k in data for k in ("d_sensor", "(d_sensor)", "r_sensor", "foclen", "r_last", "sensor_res")):
        return True
    return any(isinstance(s, dict) and any(k in s for k in ("d_next", "mat2", "roc")) for s in surfs)


def deeplens_material(m, where, path, line):
    """DeepLens ``mat2`` -> raywave material spec."""
    if isinstance(m, (int, float)) and not isinstance(m, bool):
        return {"index": float(m)}
    if not isinstance(m, str) or not m.strip():
        raise LensFileError(f"{where}.mat2: expected a material name or \"nd/vd\", got {m!r}", path, line)
    if m.strip().lower() in ("air", "vacuum"):
        return "air"
    g = _MODEL_GLASS.match(m)
    if g:
        nd, vd = float(g.group(1)), float(g.group(2))
        return {"index": nd} if vd == 0 else {"model": {"nd": nd, "vd": vd}}
    return m.strip()


def _num(sd, key, where, path, line, default=None):
    v = sd.get(key, default)
    if v is None:
        raise LensFileError(f"{where}: missing {key!r}", path, line)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise LensFileError(f"{where}.{key}: must be a number, got {v!r}", path, line)
    return float(v)


def _curvature_entry(sd, where, path, line) -> dict:
    roc = sd.get("roc")
    if roc is not None and roc != 0:
        return {"radius": _num(sd, "roc", where, path, line)}
    for k in ("c", "(c)"):
        if k in sd:
            return shape_entry(_num(sd, k, where, path, line))
    return {"radius": "inf"}


def _ai(sd, where, path, line) -> dict:
    if "ai" in sd and sd["ai"] is not None:
        ai = sd["ai"]
        if not isinstance(ai, list) or any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in ai):
            raise LensFileError(f"{where}.ai: must be a list of numbers", path, line)
        if len(ai) > 10:
            raise LensFileError(f"{where}.ai: {len(ai)} terms; raywave even aspheres stop at a20 (10 terms)",
                                path, line)
        return aspheric_canonical({f"a{2 * (i + 1)}": float(a) for i, a in enumerate(ai)})
    terms = {}
    for k, v in sd.items():
        m = _AI_KEY.match(k)
        if m:
            p = int(m.group(1))
            if p % 2 or not 2 <= p <= 20:
                raise LensFileError(f"{where}.{k}: not an even aspheric term a2..a20", path, line)
            terms[f"a{p}"] = float(v)
    return aspheric_canonical(terms)


def read_deeplens(path, clip_apertures: bool = False) -> dict:
    """Read a DeepLens lens JSON file into a validated raywave lens spec.

    Conversions (docs/lens-format.md, "DeepLens JSON"): thicknesses from ``d_next`` (else from the
    absolute ``d`` / ``(d)`` positions and ``d_sensor``); Aperture / Stop -> flat air surface with a
    circular (or square) aperture of radius ``r``, marked as the stop; Spheric / Aspheric / Plane ->
    standard / even_asphere surfaces whose ``r`` becomes the semi-diameter (with ``clip_apertures=True``
    also a clipping circular aperture, as DeepLens clips every surface at ``r``); ThinLens -> paraxial;
    ``mat2`` "nd/vd" -> model glass; sensor from ``r_sensor`` + ``sensor_res`` (DeepLens's rule) or
    ``sensor_size``; fields 0, 0.7, 1 × the half field of view atan(r_sensor / foclen) in degrees;
    wavelengths F, d, C (primary d); object at infinity; ``enpd`` -> entrance pupil diameter.
    Other surface types (Cubic, Phase, DOEs, mirrors, ...) raise :class:`LensFileError`.
    """
    path = str(path)
    data, lines = parse_json_text(read_text(path), path)
    if not looks_like_deeplens(data):
        raise LensFileError("not a DeepLens lens file (expected an object with \"surfaces\" entries having "
                            "\"d_next\" / \"mat2\" / \"roc\", or \"d_sensor\" / \"r_sensor\")", path, 1)

    def ln(*p):
        p = tuple(p)
        while p:
            if p in lines:
                return lines[p]
            p = p[:-1]
        return 1

    if "DOE" in data:
        raise LensFileError("DOE: DeepLens hybrid (DOE) lenses are not supported by lens-format v1 "
                            "(no diffractive surface type)", path, ln("DOE"))
    unknown = [k for k in data if k not in TOP_KEYS]
    surfs = data["surfaces"]
    if not surfs:
        raise LensFileError("surfaces: the lens has no surfaces (empty list)", path, ln("surfaces"))

    # absolute positions, for files without d_next
    def z_of(i):
        sd = surfs[i]
        for k in ("d", "(d)"):
            if k in sd:
                return _num(sd, k, key_path(("surfaces", i)), path, ln("surfaces", i, k))
        return None

    d_sensor = None
    for k in ("d_sensor", "(d_sensor)"):
        if k in data:
            d_sensor = _num(data, k, "", path, ln(k))
            break

    out_surfs = []
    stop_done = False
    for i, sd in enumerate(surfs):
        where = key_path(("surfaces", i))
        line = ln("surfaces", i)
        if not isinstance(sd, dict):
            raise LensFileError(f"{where}: must be an object", path, line)
        kind = sd.get("type")
        extra = [k for k in sd if k not in SURFACE_KEYS and not _AI_KEY.match(k)]
        unknown += [f"{where}.{k}" for k in extra]
        # thickness
        if "d_next" in sd:
            t = _num(sd, "d_next", where, path, ln("surfaces", i, "d_next"))
        else:
            z0 = z_of(i)
            z1 = z_of(i + 1) if i + 1 < len(surfs) else d_sensor
            if z0 is None or z1 is None:
                raise LensFileError(f"{where}: no 'd_next' and no absolute positions ('d' of this and the next "
                                    "surface, or 'd_sensor' for the last) to compute the thickness", path, line)
            t = z1 - z0
        r = sd.get("r")
        if r is not None:
            r = _num(sd, "r", where, path, ln("surfaces", i, "r"))
        mat_line = ln("surfaces", i, "mat2")
        if kind in ("Aperture", "Stop"):
            if r is None or not r > 0:
                raise LensFileError(f"{where}: empty aperture ('r' must be > 0, got {r!r})", path, line)
            if sd.get("is_square"):
                ap = {"shape": "square", "half_width": r / math.sqrt(2.0)}
            else:
                ap = {"shape": "circle", "radius": r}
            s = {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": t, "material": "air",
                 "aperture": ap, "stop": not stop_done}
            if stop_done:
                warnings.warn(LensFileWarning(f"{path}:{line}: {where}: a second aperture surface; kept as a "
                                              "clipping aperture, the first one is the stop"), stacklevel=2)
            stop_done = True
        elif kind in ("Spheric", "Aspheric", "Plane"):
            s = {"type": "even_asphere" if kind == "Aspheric" else "standard"}
            if kind == "Plane":
                s["radius"] = "inf"
            else:
                s.update(_curvature_entry(sd, where, path, line))
            s["conic"] = _num(sd, "k", where, path, line, default=0.0) if kind == "Aspheric" else 0.0
            if kind == "Aspheric":
                s["aspheric"] = _ai(sd, where, path, line)
            s["thickness"] = t
            s["material"] = deeplens_material(sd.get("mat2", "air"), where, path, mat_line)
            ap = None
            if sd.get("is_square") and r:
                ap = {"shape": "square", "half_width": r / math.sqrt(2.0)}
            elif clip_apertures and r:
                ap = {"shape": "circle", "radius": r}
            s["aperture"] = ap
            if r:
                s["semi_diameter"] = r
            s["stop"] = False
        elif kind == "ThinLens":
            f = _num(sd, "f", where, path, line)
            if f == 0:
                raise LensFileError(f"{where}.f: a thin lens needs a non-zero focal length", path, line)
            s = {"type": "paraxial", "focal_length": f, "thickness": t, "material": "air",
                 "aperture": {"shape": "circle", "radius": r} if (clip_apertures and r) else None}
            if r:
                s["semi_diameter"] = r
            s["stop"] = False
        else:
            raise LensFileError(f"{where}: DeepLens surface type {kind!r} is not supported (supported: Spheric, "
                                "Aspheric, Aperture, Stop, Plane, ThinLens)", path, ln("surfaces", i, "type"))
        out_surfs.append(s)

    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    spec["name"] = Path(path).stem
    info = data.get("info")
    if isinstance(info, str) and info.strip() and info != "None":
        spec["description"] = info
    spec["object"] = {"distance": "inf"}
    enpd = data.get("enpd")
    if enpd is not None:
        spec["system_aperture"] = {"epd": _num(data, "enpd", "", path, ln("enpd"))}

    # sensor (DeepLens: sensor size follows from r_sensor and the resolution's aspect ratio)
    res = data.get("sensor_res")
    if res is not None:
        if (not isinstance(res, list) or len(res) != 2
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0 for v in res)):
            raise LensFileError(f"sensor_res: expected [W, H] pixels, got {res!r}", path, ln("sensor_res"))
        res = [int(res[0]), int(res[1])]
    r_sensor = None
    if "r_sensor" in data:
        r_sensor = _num(data, "r_sensor", "", path, ln("r_sensor"))
        rw, rh = res or DEFAULT_SENSOR_RES
        diag = math.hypot(rw, rh)
        spec["sensor"] = {"size": [2 * r_sensor * rw / diag, 2 * r_sensor * rh / diag]}
        if res:
            spec["sensor"]["resolution"] = res
    else:
        for k in ("sensor_size", "(sensor_size)"):
            if k in data:
                size = data[k]
                spec["sensor"] = {"size": [float(size[0]), float(size[1])]}
                if res:
                    spec["sensor"]["resolution"] = res
                r_sensor = 0.5 * math.hypot(*spec["sensor"]["size"])
                break
    foclen = data.get("foclen")
    if r_sensor and isinstance(foclen, (int, float)) and not isinstance(foclen, bool) and foclen > 0:
        hfov = math.degrees(math.atan(r_sensor / foclen))
        spec["fields"] = {"type": "angle", "values": [f * hfov for f in FIELD_FRACTIONS]}
    else:
        spec["fields"] = {"type": "angle", "values": [0.0]}
    spec["wavelengths"] = {"values": list(DEFAULT_WAVELENGTHS["values"]), "primary": DEFAULT_WAVELENGTHS["primary"]}
    spec["surfaces"] = out_surfs
    if unknown:
        warnings.warn(LensFileWarning(f"{path}: ignored DeepLens keys: {', '.join(unknown)}"), stacklevel=2)
    return validate_spec(spec, path)
