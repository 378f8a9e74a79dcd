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
A hybrid lens file (``HybridLens.write_lens_json``) adds a top-level ``"DOE"``: its DOE class's dict
(``Binary2``, ``Pixel2D``, ``Fresnel``, ``Zernike``, ``Grating``, ``ThinLens``, or the 2024 ``"DOE"`` with a
``param_model``), imported into raywave's ``"doe"`` section by :func:`deeplens_doe`; :func:`read_deeplens_hybrid`
also loads a ``Pixel2D`` phase map (.pth / .pt / .npy / .npz).
See docs/lens-format.md, "DeepLens JSON" and "DeepLens hybrid lenses", for every conversion rule.
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

    A hybrid lens file's top-level ``"DOE"`` (DeepLens ``HybridLens``) becomes the spec's ``"doe"`` section
    (:func:`deeplens_doe`; docs/lens-format.md, "DeepLens hybrid lenses"). A ``Pixel2D`` DOE's phase map lives in
    a separate file that a lens spec cannot name: :func:`read_deeplens_hybrid` (used by
    ``raywave.io.read_hybrid_spec`` / ``load_hybrid``) loads it; here the spec's DOE is left blank, with a
    :class:`LensFileWarning`.
    """
    spec, pixel = _read_deeplens(path, clip_apertures)
    if pixel is not None:
        warnings.warn(LensFileWarning(
            f"{path}:{pixel['line']}: DOE: the Pixel2D phase map ({pixel['ref']!r}) is not part of the lens spec "
            "(raywave lens files name .npy / .npz maps): the spec's DOE is blank; load_hybrid / "
            "read_hybrid_spec / raywave psf read the map"), stacklevel=2)
    return spec


def read_deeplens_hybrid(path, clip_apertures: bool = False):
    """Read a DeepLens (hybrid) lens file into ``(spec, doe)``: the validated spec of :func:`read_deeplens` and its
    DOE as a :class:`raywave.io.doe.DOEData` (None without a ``"DOE"``), a ``Pixel2D`` phase map loaded from its
    ``.pth`` / ``.pt`` / ``.npy`` / ``.npz`` file and flipped to raywave's row order (row 0 at −y)."""
    from raywave.io.doe import resolve_doe

    spec, pixel = _read_deeplens(path, clip_apertures)
    if spec.get("doe") is None:
        return spec, None
    data = resolve_doe(spec, str(path), Path(path).parent, None, load=True)
    if pixel is not None:
        arr, file = load_pixel2d_map(pixel, path)
        if tuple(arr.shape) != tuple(data.shape):
            raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} has shape {list(arr.shape)}, the DOE "
                                f"'res' is {list(data.shape)} (DeepLens would resample it, nearest, to 'res'; "
                                "resample the map first)", path, pixel["line"])
        data.phase = arr
        data.phase_path = file
    return spec, data


def _read_deeplens(path, clip_apertures: bool = False):
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
                                              "clipping aperture, the first one is the stop"), stacklevel=3)
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
    pixel = None
    if "DOE" in data:
        # the last vertex's z in DeepLens's frame (GeoLens puts the first vertex at 0 and adds d_next)
        if all(isinstance(sd, dict) and "d_next" in sd for sd in surfs):
            z_last = sum(s_["thickness"] for s_ in out_surfs[:-1])
        else:
            z_last = z_of(len(surfs) - 1)
        spec["doe"], pixel, extra = deeplens_doe(data["DOE"], out_surfs[-1]["thickness"], z_last, path, ln)
        unknown += extra
    if unknown:
        warnings.warn(LensFileWarning(f"{path}: ignored DeepLens keys: {', '.join(unknown)}"), stacklevel=3)
    return validate_spec(spec, path), pixel


# --------------------------------------------------------------------------------------- hybrid lenses (DOE)
#: DeepLens DOE classes (``"type"`` of the ``"DOE"`` object, case-insensitive) that raywave imports.
DOE_CLASS_TYPES = ("Binary2", "Pixel2D", "Fresnel", "Zernike", "Grating", "ThinLens")
#: ``param_model`` values of DeepLens's earlier single ``DOE`` class (``"type": "DOE"``, SIGGRAPH Asia 2024 code).
DOE_LEGACY_MODELS = ("binary2", "binary2_fast", "fresnel", "cubic", "zernike", "pixel2d")
#: DeepLens's defaults (``DiffractiveSurface``): fabrication pitch (mm), design wavelength (µm), material, levels.
DEEPLENS_FAB_PS = 0.001
DEEPLENS_WVLN0 = 0.55
DEEPLENS_DOE_MATERIAL = "fused_silica"
DEEPLENS_FAB_STEP = 16
#: Keys of the "DOE" object read silently (besides each type's parameters).
_DOE_COMMON_KEYS = {"type", "d", "(d)", "d_next", "res", "fab_ps", "fab_step", "wvln0", "mat", "is_square", "size",
                    "(size)", "l", "param_model", "doe_path", "r", "(r)", "idx", "zernike_order", "norm_radii"}
_DOE_PARAMS = {
    "binary2": ("alpha2", "alpha4", "alpha6", "alpha8", "alpha10"),
    "fresnel": ("f0",), "thinlens": ("f0",), "grating": ("theta", "alpha"), "zernike": ("z_coeff",),
    "pixel2d": ("phase_map_path",),
}
_LEGACY_PARAMS = {
    "binary2": ("order2", "order4", "order6", "order8"), "binary2_fast": ("order2", "order4", "order6", "order8"),
    "fresnel": ("f0", "fresnel_wvln"), "cubic": ("a3",), "zernike": ("z_coeff",), "pixel2d": ("pmap",),
}
#: Noll index j of DeepLens's 37 Zernike terms: DeepLens's Z2 is 2ρ sinθ and Z3 2ρ cosθ (Noll's j = 3 and 2);
#: every other term is Noll's.
ZERNIKE_DEEPLENS_TO_NOLL = tuple([1, 3, 2] + list(range(4, 38)))


def _doe_num(dd, key, path, line, default=None, positive=False):
    v = dd.get(key, default)
    if v is None:
        raise LensFileError(f"DOE: missing {key!r}", path, line)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise LensFileError(f"DOE.{key}: must be a number, got {v!r}", path, line)
    if positive and not v > 0:
        raise LensFileError(f"DOE.{key}: must be > 0, got {v!r}", path, line)
    return float(v)


def _legacy_checkpoint(dd, path, line) -> dict:
    """The parameters saved by DeepLens's legacy ``DOE.save_ckpt`` at ``doe_path`` (a torch file), as numbers."""
    ref = dd.get("doe_path")
    if not isinstance(ref, str) or not ref:
        return {}
    file = _find_side_file(ref, path)
    if file is None:
        return {}
    obj = _torch_load(file, path, line)
    if not isinstance(obj, dict):
        return {}
    out = {}
    for k, v in obj.items():
        if hasattr(v, "detach"):
            v = v.detach().cpu().double().numpy()
        if hasattr(v, "ndim"):
            v = float(v.reshape(())) if v.size == 1 and k != "pmap" else v
        out[k] = v
    return out


def deeplens_doe(dd, last_thickness: float, z_last: float | None, path, ln):
    """A DeepLens hybrid lens's ``"DOE"`` object -> ``(doe section, pixel2d source or None, unknown keys)``.

    ``last_thickness``: the refractive lens's last thickness (mm, to the sensor); ``z_last``: the last vertex's
    position in DeepLens's frame (first vertex at 0). See docs/lens-format.md, "DeepLens hybrid lenses", for every
    rule; the phase at the design wavelength is the one of DeepLens's ``phase_func`` (newer classes) or
    ``get_phase_map0`` (legacy ``DOE``), in raywave's pixel-centre coordinates.
    """
    line = ln("DOE")
    if not isinstance(dd, dict):
        raise LensFileError("DOE: must be an object", path, line)
    kind_raw = dd.get("type")
    if not isinstance(kind_raw, str) or not kind_raw.strip():
        raise LensFileError("DOE: missing 'type' (a DeepLens DOE class: "
                            + ", ".join(DOE_CLASS_TYPES) + ")", path, line)
    kind = kind_raw.strip().lower()
    legacy = kind == "doe"
    if legacy:
        model = dd.get("param_model")
        if not isinstance(model, str) or model.strip().lower() not in DOE_LEGACY_MODELS:
            raise LensFileError(f"DOE.param_model: DeepLens DOE parameter model {model!r} is not supported (supported: "
                                + ", ".join(DOE_LEGACY_MODELS) + ")", path, ln("DOE", "param_model"))
        model = model.strip().lower()
    elif kind not in _DOE_PARAMS:
        raise LensFileError(f"DOE.type: DeepLens DOE type {kind_raw!r} is not supported (supported: "
                            + ", ".join(DOE_CLASS_TYPES) + ", and \"DOE\" with a param_model)", path,
                            ln("DOE", "type"))
    else:
        model = kind
    params = _LEGACY_PARAMS[model] if legacy else _DOE_PARAMS[kind]
    unknown = [f"DOE.{k}" for k in dd if k not in _DOE_COMMON_KEYS and k not in params
               and not (legacy and model == "fresnel" and k == "fresnel_wvln")]

    # ---- grid: pitch, shape, oversample
    pitch = _doe_num(dd, "fab_ps", path, ln("DOE", "fab_ps"), DEEPLENS_FAB_PS, positive=True)
    oversample = 1
    res = dd.get("res", [2000, 2000] if kind == "pixel2d" else None)
    if isinstance(res, (int, float)) and not isinstance(res, bool):
        res = [res, res]
    res_ok = (isinstance(res, list) and len(res) == 2
              and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res))
    if legacy:
        side = dd.get("l", dd.get("(size)", dd.get("size")))
        if isinstance(side, list) and side:
            side = side[0]
        if isinstance(side, bool) or not isinstance(side, (int, float)) or not side > 0:
            raise LensFileError(f"DOE.l: the legacy DeepLens DOE needs its side length 'l' (mm) > 0, got {side!r}",
                                path, ln("DOE", "l"))
        n = round(side / pitch)
        if abs(n * pitch - side) > 1e-6 * side or n < 1:
            raise LensFileError(f"DOE.l: {side!r} mm is not a whole number of {pitch!r} mm fabrication pixels",
                                path, ln("DOE", "l"))
        shape = [n, n]
        if res_ok and res[0] % n == 0:
            oversample = res[0] // n
        elif res is not None:
            warnings.warn(LensFileWarning(f"{path}:{ln('DOE', 'res')}: DOE.res {res!r} is not a whole multiple of the "
                                          f"{n} fabrication pixels; simulated at oversample 1"), stacklevel=4)
        half_diag = side / math.sqrt(2.0)
        width = side
    else:
        if not res_ok:
            raise LensFileError(f"DOE.res: expected the DOE resolution [H, W] (pixels), got {res!r}", path,
                                ln("DOE", "res") if "res" in dd else line)
        shape = [int(res[0]), int(res[1])]
        if shape[0] != shape[1]:
            warnings.warn(LensFileWarning(
                f"{path}:{ln('DOE', 'res')}: DOE.res {res!r} is not square: DeepLens's own grid is inconsistent then "
                f"(its width res[0]·fab_ps spans res[1] samples); raywave uses {shape[0]} rows × {shape[1]} "
                f"columns of {pitch:g} mm pixels"), stacklevel=4)
        width = shape[0] * pitch  # DeepLens: w = res[0] * ps
        half_diag = None
        for k in ("size", "(size)"):
            sz = dd.get(k)
            if isinstance(sz, list) and len(sz) == 2 and all(isinstance(v, (int, float)) for v in sz):
                want = (shape[0] * pitch, shape[1] * pitch)
                if any(abs(a - b) > 1e-3 for a, b in zip(sz, want)):
                    warnings.warn(LensFileWarning(
                        f"{path}:{ln('DOE', k)}: DOE.{k} {sz!r} mm disagrees with res × fab_ps = "
                        f"[{want[0]:g}, {want[1]:g}] mm; the grid follows res and fab_ps, as in DeepLens"),
                        stacklevel=4)

    # ---- position: mm after the last vertex
    if "d_next" in dd:
        gap = _doe_num(dd, "d_next", path, ln("DOE", "d_next"))
        distance = last_thickness - gap
        how = f"the last thickness {last_thickness:g} mm − DOE.d_next {gap:g} mm"
    else:
        key = "d" if "d" in dd else "(d)" if "(d)" in dd else None
        if key is None:
            raise LensFileError("DOE: no position: give 'd' (the DOE plane's z, mm, first vertex at 0) or 'd_next' "
                                "(mm from the DOE to the sensor)", path, line)
        z = _doe_num(dd, key, path, ln("DOE", key))
        if z_last is None:
            raise LensFileError("DOE.d: the last surface's position is unknown (no 'd_next' and no 'd' / '(d)')",
                                path, ln("DOE", key))
        distance = z - z_last
        how = f"DOE.{key} {z:g} mm − the last vertex's z {z_last:g} mm"
    distance = round(distance, 12)
    if not 0 <= distance < last_thickness:
        raise LensFileError(f"DOE: the DOE plane must lie between the last surface and the sensor: {how} = "
                            f"{distance:g} mm, not in [0, {last_thickness:g})", path,
                            ln("DOE", "d_next") if "d_next" in dd else ln("DOE", "d") if "d" in dd else line)

    # ---- optics: design wavelength, material, fabrication
    wvln0 = _doe_num(dd, "wvln0", path, ln("DOE", "wvln0"), DEEPLENS_WVLN0, positive=True)
    mat = dd.get("mat", DEEPLENS_DOE_MATERIAL)
    if not isinstance(mat, str) or not mat.strip():
        raise LensFileError(f"DOE.mat: expected a material name, got {mat!r}", path, ln("DOE", "mat"))
    doe = {"distance": distance, "pitch": pitch, "shape": shape, "aperture": "square", "phase": None,
           "design_wavelength": wvln0, "oversample": oversample}
    if kind == "thinlens":
        pass  # a fixed optical path (φ ∝ 1/λ): no material, no quantisation
    elif legacy:
        doe["material"] = mat.strip()
        doe["wrap"] = True
    else:
        doe["material"] = mat.strip()
        lv = dd.get("fab_step", DEEPLENS_FAB_STEP)
        if isinstance(lv, bool) or not isinstance(lv, int) or lv < 2:
            raise LensFileError(f"DOE.fab_step: expected an integer number of levels >= 2, got {lv!r}", path,
                                ln("DOE", "fab_step"))
        doe["levels"] = lv

    # ---- phase model
    pixel = None
    if legacy:
        p = dict(dd)
        if any(k not in p for k in params):
            p.update({k: v for k, v in _legacy_checkpoint(dd, path, ln("DOE", "doe_path")).items() if k not in p})
    else:
        p = dd

    def need(k):
        if k not in p or p[k] is None:
            raise LensFileError(f"DOE: a DeepLens {kind_raw if not legacy else model} DOE without {k!r} (DeepLens "
                                "would initialise it randomly): nothing to import", path, line)
        return p[k]

    def num(k, default=None):
        v = p.get(k, default) if default is not None else need(k)
        if hasattr(v, "ndim") and getattr(v, "size", 2) == 1:
            v = float(v.reshape(()))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise LensFileError(f"DOE.{k}: must be a number, got {v!r}", path, ln("DOE", k))
        return float(v)

    def quad(f0, lam_um):  # −π r² / (λ f0), r in mm
        if f0 == 0:
            raise LensFileError("DOE.f0: the focal length must not be 0", path, ln("DOE", "f0"))
        return {"type": "binary_2", "order": 1.0, "norm_radius": 1.0,
                "coefficients": [-math.pi / (lam_um * 1e-3 * f0)]}

    def zernike(radius):
        c = need("z_coeff")
        if hasattr(c, "tolist"):
            c = c.tolist()
        if (not isinstance(c, list) or not c or len(c) > 37
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in c)):
            raise LensFileError(f"DOE.z_coeff: expected a list of 1 to 37 numbers (DeepLens's Zernike terms), got "
                                f"{c!r}", path, ln("DOE", "z_coeff"))
        c = [float(x) for x in c]
        noll = [0.0] * (max(len(c), 3) if len(c) >= 2 else len(c))
        for i, x in enumerate(c):
            noll[ZERNIKE_DEEPLENS_TO_NOLL[i] - 1] = x
        if any(c[i] != 0 for i in (28, 29) if i < len(c)):
            warnings.warn(LensFileWarning(
                f"{path}:{ln('DOE', 'z_coeff')}: DOE.z_coeff: DeepLens's terms 29 and 30 use the radial polynomial "
                "35ρ⁷ − 60ρ⁵ + 30ρ³ − 4 (a typo for … − 4ρ); raywave uses the correct Zernike polynomial, "
                "so their phase differs"), stacklevel=5)
        return {"type": "zernike", "radius": radius, "coefficients": noll}

    if model == "binary2" and not legacy:
        keys = _DOE_PARAMS["binary2"]
        if not any(k in p for k in keys):
            need("alpha2")
        doe["phase_model"] = {"type": "binary_2", "order": 1.0, "norm_radius": 1.0,
                              "coefficients": [math.pi * num(k, 0.0) for k in keys]}
    elif model in ("binary2", "binary2_fast"):  # legacy: Σ order_2i ρ^2i, ρ = r / (half-diagonal)
        keys = _LEGACY_PARAMS[model]
        if not any(k in p for k in keys):
            need("order2")
        a = [num(k, 0.0) for k in keys]
        if model == "binary2_fast":
            if any(x == 0 for x in a):
                raise LensFileError("DOE: a binary2_fast DOE's orders are the inverse coefficients; none may be 0",
                                    path, line)
            a = [1.0 / x for x in a]
        doe["phase_model"] = {"type": "binary_2", "order": 1.0, "norm_radius": half_diag, "coefficients": a}
    elif model == "fresnel":
        lam = num("fresnel_wvln", DEEPLENS_WVLN0) if legacy else wvln0
        doe["phase_model"] = quad(num("f0"), lam)
    elif model == "thinlens":
        doe["phase_model"] = quad(num("f0"), wvln0)
    elif model == "cubic":  # legacy: a3 (x³ + y³), x, y in mm
        doe["phase_model"] = {"type": "cubic", "alpha": num("a3"), "radius": 1.0}
    elif model == "grating":  # α (x sinθ + y cosθ) / (w/2), θ in rad from +y
        alpha, theta = num("alpha", 0.0), num("theta", 0.0)
        if alpha != 0:
            angle = 90.0 - math.degrees(theta) + (180.0 if alpha < 0 else 0.0)
            angle = (angle + 180.0) % 360.0 - 180.0
            doe["phase_model"] = {"type": "grating", "period": 2 * math.pi * (0.5 * width) / abs(alpha),
                                  "angle": angle}
    elif model == "zernike":
        doe["phase_model"] = zernike(half_diag if legacy else 0.5 * width)
    elif model == "pixel2d":
        if legacy:
            if "pmap" in p and hasattr(p["pmap"], "ndim"):
                pixel = {"array": p["pmap"], "ref": dd.get("doe_path"), "line": ln("DOE", "doe_path")}
            else:
                need("doe_path")
                raise LensFileError(f"DOE.doe_path: no 'pmap' phase map found in {dd.get('doe_path')!r}", path,
                                    ln("DOE", "doe_path"))
        else:
            ref = need("phase_map_path")
            if not isinstance(ref, str) or not ref.strip():
                raise LensFileError(f"DOE.phase_map_path: expected a file name, got {ref!r}", path,
                                    ln("DOE", "phase_map_path"))
            pixel = {"ref": ref, "line": ln("DOE", "phase_map_path")}
    return doe, pixel, unknown


def _find_side_file(ref: str, lens_path) -> str | None:
    """A file DeepLens wrote next to the lens: ``ref`` as given when absolute, else relative to the lens file's
    folder, else its base name in that folder, else relative to the current directory."""
    p = Path(ref)
    base = Path(lens_path).parent
    cands = [p] if p.is_absolute() else [base / p, base / p.name, p]
    if p.is_absolute():
        cands.append(base / p.name)
    for c in cands:
        if c.is_file():
            return str(c)
    return None


def _torch_load(file, path, line):
    try:
        import torch

        return torch.load(file, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable checkpoint is the same error to the user
        raise LensFileError(f"DOE: cannot read the torch file {file!r}: {e}", path, line) from None


def load_pixel2d_map(pixel: dict, path):
    """The Pixel2D phase map (rad at λ0) as a float64 ``(ny, nx)`` array in raywave's row order, and its file.

    DeepLens stores row 0 at +y (its grid runs from +h/2 down to −h/2); raywave's row 0 is at −y, so the rows
    are flipped. Reads ``.pth`` / ``.pt`` (a tensor, or a dict holding ``pmap`` / ``phase_map`` / ``phase``),
    ``.npy`` and ``.npz`` (``phase`` / ``pmap`` / ``phase_map``, or its only array)."""
    import numpy as np

    line = pixel["line"]
    arr = pixel.get("array")
    file = pixel.get("ref")
    if arr is None:
        file = _find_side_file(pixel["ref"], path)
        if file is None:
            raise LensFileError(f"DOE.phase_map_path: phase map file {pixel['ref']!r} not found (looked for it as "
                                "given, relative to the lens file, and by its name next to the lens file)", path, line)
        ext = Path(file).suffix.lower()
        names = ("phase_map", "pmap", "phase")
        if ext in (".pth", ".pt"):
            obj = _torch_load(file, path, line)
            if isinstance(obj, dict):
                hit = [k for k in names if k in obj]
                if not hit:
                    raise LensFileError(f"DOE.phase_map_path: {file!r} holds a dict without a phase map (keys: "
                                        f"{', '.join(map(str, obj)) or 'none'}; expected one of {', '.join(names)})",
                                        path, line)
                obj = obj[hit[0]]
            if not hasattr(obj, "detach"):
                raise LensFileError(f"DOE.phase_map_path: {file!r} holds no tensor (got {type(obj).__name__})",
                                    path, line)
            arr = obj.detach().cpu().double().numpy()
        elif ext == ".npy":
            try:
                arr = np.load(file, allow_pickle=False)
            except (OSError, ValueError) as e:
                raise LensFileError(f"DOE.phase_map_path: cannot read {file!r}: {e}", path, line) from None
        elif ext == ".npz":
            try:
                with np.load(file, allow_pickle=False) as z:
                    hit = [k for k in names if k in z.files] or (z.files if len(z.files) == 1 else [])
                    if not hit:
                        raise LensFileError(f"DOE.phase_map_path: {file!r} holds no array named "
                                            f"{' / '.join(names)} (found: {', '.join(z.files) or 'nothing'})",
                                            path, line)
                    arr = z[hit[0]]
            except (OSError, ValueError) as e:
                raise LensFileError(f"DOE.phase_map_path: cannot read {file!r}: {e}", path, line) from None
        else:
            raise LensFileError(f"DOE.phase_map_path: {file!r}: a Pixel2D phase map is read from a .pth / .pt torch "
                                "tensor or a .npy / .npz array", path, line)
    if hasattr(arr, "detach"):
        arr = arr.detach().cpu().double().numpy()
    arr = np.asarray(arr)
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2 or 0 in arr.shape:
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} must be 2-D (H, W), got shape "
                            f"{list(arr.shape)}", path, line)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} must hold real numbers (rad), got "
                            f"{arr.dtype}", path, line)
    arr = np.asarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} contains NaN or inf", path, line)
    return np.ascontiguousarray(arr[::-1]), str(file)
