"""DeepLens surfaces -> raywave spec surfaces: the keys a DeepLens lens file may hold, materials, curvatures,
aspheric terms, and one spec surface per DeepLens surface (docs/lens-format.md, "DeepLens JSON")."""

from __future__ import annotations

import math
import re
import warnings

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import key_path
from raywave.io.spec import aspheric_canonical, shape_entry

TOP_KEYS = {"info", "foclen", "fnum", "r_last", "r_sensor", "d_sensor", "(d_sensor)", "sensor_size",
            "(sensor_size)", "sensor_res", "enpd", "surfaces", "hfov", "(hfov)", "rfov", "(rfov)",
            "obj_depth", "(obj_depth)", "DOE"}
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


def _convert_surfaces(surfs: list, z_of, d_sensor, clip_apertures: bool, path, ln, unknown: list) -> list:
    """The spec surfaces of the DeepLens ``surfs`` (thicknesses in mm); ``z_of(i)``: surface i's absolute position
    (mm, or None), ``d_sensor``: the sensor's (mm, or None); unknown keys are appended to ``unknown``. The first
    aperture surface is the stop."""
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
        t = _thickness(surfs, i, z_of, d_sensor, where, path, ln)
        out_surfs.append(_surface(sd, i, kind, t, stop_done, clip_apertures, where, path, ln))
        stop_done = stop_done or kind in ("Aperture", "Stop")
    return out_surfs


def _thickness(surfs: list, i: int, z_of, d_sensor, where: str, path, ln) -> float:
    """The thickness (mm) after surface i: its ``d_next``, else the next surface's absolute position (``d_sensor``
    after the last) minus its own."""
    sd = surfs[i]
    if "d_next" in sd:
        return _num(sd, "d_next", where, path, ln("surfaces", i, "d_next"))
    z0 = z_of(i)
    z1 = z_of(i + 1) if i + 1 < len(surfs) else d_sensor
    if z0 is None or z1 is None:
        raise LensFileError(f"{where}: no 'd_next' and no absolute positions ('d' of this and the next "
                            "surface, or 'd_sensor' for the last) to compute the thickness", path, ln("surfaces", i))
    return z1 - z0


def _surface(sd: dict, i: int, kind, t: float, stop_done: bool, clip_apertures: bool, where: str, path, ln) -> dict:
    """The spec surface of DeepLens surface ``sd`` (number i, type ``kind``, thickness ``t`` mm); ``stop_done``:
    whether an earlier aperture surface is the stop."""
    line = ln("surfaces", i)
    r = sd.get("r")
    if r is not None:
        r = _num(sd, "r", where, path, ln("surfaces", i, "r"))
    if kind in ("Aperture", "Stop"):
        return _aperture_surface(sd, r, t, stop_done, where, path, line)
    if kind in ("Spheric", "Aspheric", "Plane"):
        return _refractive_surface(sd, kind, r, t, clip_apertures, where, path, line, ln("surfaces", i, "mat2"))
    if kind == "ThinLens":
        f = _num(sd, "f", where, path, line)
        if f == 0:
            raise LensFileError(f"{where}.f: a thin lens needs a non-zero focal length", path, line)
        s = {"type": "paraxial", "focal_length": f, "thickness": t, "material": "air",
             "aperture": {"shape": "circle", "radius": r} if (clip_apertures and r) else None}
        if r:
            s["semi_diameter"] = r
        s["stop"] = False
        return s
    raise LensFileError(f"{where}: DeepLens surface type {kind!r} is not supported (supported: Spheric, "
                        "Aspheric, Aperture, Stop, Plane, ThinLens)", path, ln("surfaces", i, "type"))


def _aperture_surface(sd: dict, r, t: float, stop_done: bool, where: str, path, line) -> dict:
    """An Aperture / Stop: a flat air surface with a circular (``is_square``: square) aperture of radius ``r``
    (mm), the stop unless an earlier aperture is (then a clipping aperture, with a warning)."""
    if r is None or not r > 0:
        raise LensFileError(f"{where}: empty aperture ('r' must be > 0, got {r!r})", path, line)
    if sd.get("is_square"):
        ap = {"shape": "square", "half_width": r / math.sqrt(2.0)}
    else:
        ap = {"shape": "circle", "radius": r}
    s = {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": t, "material": "air",
         "aperture": ap, "stop": not stop_done}
    if stop_done:
        # stacklevel: the caller of read_deeplens / read_deeplens_hybrid
        warnings.warn(LensFileWarning(f"{path}:{line}: {where}: a second aperture surface; kept as a "
                                      "clipping aperture, the first one is the stop"), stacklevel=6)
    return s


def _refractive_surface(sd: dict, kind: str, r, t: float, clip_apertures: bool, where: str, path, line,
                        mat_line) -> dict:
    """A Spheric / Aspheric / Plane: a standard or even-asphere surface whose ``r`` (mm) is the semi-diameter
    (a clipping aperture with ``clip_apertures``; a square one for ``is_square``)."""
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
    return s
