"""A DeepLens hybrid lens's ``"DOE"`` object -> raywave's ``"doe"`` section (:func:`deeplens_doe`;
docs/lens-format.md, "DeepLens hybrid lenses")."""

from __future__ import annotations

import math
import warnings

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.deeplens.phase_map import _find_side_file, _torch_load

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
    kind_raw, kind, legacy, model = _doe_kind(dd, path, ln)
    params = _LEGACY_PARAMS[model] if legacy else _DOE_PARAMS[kind]
    unknown = [f"DOE.{k}" for k in dd if k not in _DOE_COMMON_KEYS and k not in params
               and not (legacy and model == "fresnel" and k == "fresnel_wvln")]
    # ---- grid: pitch, shape, oversample
    pitch = _doe_num(dd, "fab_ps", path, ln("DOE", "fab_ps"), DEEPLENS_FAB_PS, positive=True)
    res = _res(dd, kind)
    if legacy:
        shape, oversample, width, half_diag = _legacy_grid(dd, res, pitch, path, ln)
    else:
        shape, oversample, width, half_diag = _class_grid(dd, res, pitch, path, ln)
    distance = _doe_distance(dd, last_thickness, z_last, path, ln)
    # ---- optics: design wavelength, material, fabrication
    doe = _doe_optics(dd, kind, legacy, pitch, shape, distance, oversample, path, ln)
    # ---- phase model
    pp = _Params(_phase_params(dd, legacy, params, path, ln), kind_raw if not legacy else model, path, line, ln)
    pixel = None
    if model == "pixel2d":
        pixel = _pixel2d_source(pp, dd, legacy, path, ln)
    else:
        phase_model = _phase_model(pp, model, legacy, doe["design_wavelength"], width, half_diag)
        if phase_model is not None:
            doe["phase_model"] = phase_model
    return doe, pixel, unknown


def _doe_kind(dd, path, ln):
    """``(type as written, type lower-case, legacy, parameter model)`` of the "DOE" object: a DeepLens DOE class
    (:data:`DOE_CLASS_TYPES`), or the legacy ``"DOE"`` with a ``param_model`` of :data:`DOE_LEGACY_MODELS`."""
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
    return kind_raw, kind, legacy, model


def _res(dd, kind: str):
    """The "DOE" object's ``res`` (default [2000, 2000] for Pixel2D; a number n: [n, n]), not yet checked."""
    res = dd.get("res", [2000, 2000] if kind == "pixel2d" else None)
    if isinstance(res, (int, float)) and not isinstance(res, bool):
        res = [res, res]
    return res


def _res_ok(res) -> bool:
    """Whether ``res`` is a DOE resolution [H, W] of positive integers."""
    return (isinstance(res, list) and len(res) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res))


def _legacy_grid(dd, res, pitch: float, path, ln):
    """``(shape [n, n], oversample, width mm, half-diagonal mm)`` of the legacy DOE: side ``l`` (mm) in whole
    ``pitch`` (mm) pixels, simulated at ``res[0] / n`` samples per pixel when that is whole (else 1, warned)."""
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
    oversample = 1
    if _res_ok(res) and res[0] % n == 0:
        oversample = res[0] // n
    elif res is not None:
        # stacklevel: the caller of read_deeplens / read_deeplens_hybrid
        warnings.warn(LensFileWarning(f"{path}:{ln('DOE', 'res')}: DOE.res {res!r} is not a whole multiple of the "
                                      f"{n} fabrication pixels; simulated at oversample 1"), stacklevel=5)
    return [n, n], oversample, side, side / math.sqrt(2.0)


def _class_grid(dd, res, pitch: float, path, ln):
    """``(shape [H, W], 1, width mm, None)`` of a DOE class: ``res`` pixels of ``pitch`` mm (DeepLens: the width
    is ``res[0]·fab_ps``); a non-square ``res`` or a disagreeing ``size`` is warned about."""
    if not _res_ok(res):
        raise LensFileError(f"DOE.res: expected the DOE resolution [H, W] (pixels), got {res!r}", path,
                            ln("DOE", "res") if "res" in dd else ln("DOE"))
    shape = [int(res[0]), int(res[1])]
    if shape[0] != shape[1]:
        warnings.warn(LensFileWarning(
            f"{path}:{ln('DOE', 'res')}: DOE.res {res!r} is not square: DeepLens's own grid is inconsistent then "
            f"(its width res[0]·fab_ps spans res[1] samples); raywave uses {shape[0]} rows × {shape[1]} "
            f"columns of {pitch:g} mm pixels"), stacklevel=5)
    width = shape[0] * pitch  # DeepLens: w = res[0] * ps
    for k in ("size", "(size)"):
        sz = dd.get(k)
        if isinstance(sz, list) and len(sz) == 2 and all(isinstance(v, (int, float)) for v in sz):
            want = (shape[0] * pitch, shape[1] * pitch)
            if any(abs(a - b) > 1e-3 for a, b in zip(sz, want)):
                warnings.warn(LensFileWarning(
                    f"{path}:{ln('DOE', k)}: DOE.{k} {sz!r} mm disagrees with res × fab_ps = "
                    f"[{want[0]:g}, {want[1]:g}] mm; the grid follows res and fab_ps, as in DeepLens"),
                    stacklevel=5)
    return shape, 1, width, None


def _doe_distance(dd, last_thickness: float, z_last, path, ln) -> float:
    """The DOE plane's distance after the last vertex (mm, rounded to 1e-12): ``last_thickness − d_next``, or
    ``d − z_last``; it must lie in [0, last_thickness)."""
    line = ln("DOE")
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
    return distance


def _doe_optics(dd, kind: str, legacy: bool, pitch: float, shape: list, distance: float, oversample: int, path,
                ln) -> dict:
    """The doe section without its phase model: grid (pitch mm, shape, square aperture, oversample), position
    (mm), design wavelength (µm), and material and levels (``fab_step``) or wrapping (legacy); a ThinLens DOE is a
    fixed optical path (no material, no quantisation)."""
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
    return doe


def _phase_params(dd, legacy: bool, params: tuple, path, ln) -> dict:
    """The phase parameters: the "DOE" object itself, or for the legacy ``DOE`` its keys completed by the
    checkpoint at ``doe_path`` when one of ``params`` is missing."""
    if not legacy:
        return dd
    p = dict(dd)
    if any(k not in p for k in params):
        p.update({k: v for k, v in _legacy_checkpoint(dd, path, ln("DOE", "doe_path")).items() if k not in p})
    return p


class _Params:
    """The phase parameters of a "DOE" object (its keys, plus a legacy checkpoint's), read with errors that name
    the DOE type ``what`` and the key's line."""

    def __init__(self, p: dict, what: str, path, line: int, ln):
        self.p, self.what, self.path, self.line, self.ln = p, what, path, line, ln

    def need(self, k):
        """The value of ``k``; missing (DeepLens would initialise it randomly): a :class:`LensFileError`."""
        if k not in self.p or self.p[k] is None:
            raise LensFileError(f"DOE: a DeepLens {self.what} DOE without {k!r} (DeepLens "
                                "would initialise it randomly): nothing to import", self.path, self.line)
        return self.p[k]

    def num(self, k, default=None) -> float:
        """``k`` as a finite number (a one-element array too); ``default`` when given and ``k`` is missing."""
        v = self.p.get(k, default) if default is not None else self.need(k)
        if hasattr(v, "ndim") and getattr(v, "size", 2) == 1:
            v = float(v.reshape(()))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise LensFileError(f"DOE.{k}: must be a number, got {v!r}", self.path, self.ln("DOE", k))
        return float(v)


def _phase_model(pp: _Params, model: str, legacy: bool, wvln0: float, width: float, half_diag) -> dict | None:
    """The spec phase model of a DeepLens parameter model (all but pixel2d): Binary2 (π α_2i on r^2i, r in mm;
    legacy: order_2i on (r / half-diagonal)^2i), Fresnel / ThinLens (a quadratic phase), cubic, grating (None when
    its α is 0), Zernike; lengths in mm, phases in rad at λ0 = ``wvln0`` µm."""
    if model == "binary2" and not legacy:
        keys = _DOE_PARAMS["binary2"]
        if not any(k in pp.p for k in keys):
            pp.need("alpha2")
        return {"type": "binary_2", "order": 1.0, "norm_radius": 1.0,
                "coefficients": [math.pi * pp.num(k, 0.0) for k in keys]}
    if model in ("binary2", "binary2_fast"):  # legacy: Σ order_2i ρ^2i, ρ = r / (half-diagonal)
        keys = _LEGACY_PARAMS[model]
        if not any(k in pp.p for k in keys):
            pp.need("order2")
        a = [pp.num(k, 0.0) for k in keys]
        if model == "binary2_fast":
            if any(x == 0 for x in a):
                raise LensFileError("DOE: a binary2_fast DOE's orders are the inverse coefficients; none may be 0",
                                    pp.path, pp.line)
            a = [1.0 / x for x in a]
        return {"type": "binary_2", "order": 1.0, "norm_radius": half_diag, "coefficients": a}
    if model == "fresnel":
        lam = pp.num("fresnel_wvln", DEEPLENS_WVLN0) if legacy else wvln0
        return _quadratic(pp, pp.num("f0"), lam)
    if model == "thinlens":
        return _quadratic(pp, pp.num("f0"), wvln0)
    if model == "cubic":  # legacy: a3 (x³ + y³), x, y in mm
        return {"type": "cubic", "alpha": pp.num("a3"), "radius": 1.0}
    if model == "grating":  # α (x sinθ + y cosθ) / (w/2), θ in rad from +y
        alpha, theta = pp.num("alpha", 0.0), pp.num("theta", 0.0)
        if alpha == 0:
            return None
        angle = 90.0 - math.degrees(theta) + (180.0 if alpha < 0 else 0.0)
        angle = (angle + 180.0) % 360.0 - 180.0
        return {"type": "grating", "period": 2 * math.pi * (0.5 * width) / abs(alpha), "angle": angle}
    if model == "zernike":
        return _zernike(pp, half_diag if legacy else 0.5 * width)
    return None


def _quadratic(pp: _Params, f0: float, lam_um: float) -> dict:
    """The thin-lens phase −π r² / (λ f0) (r, f0 in mm, λ in µm) as a binary_2 model."""
    if f0 == 0:
        raise LensFileError("DOE.f0: the focal length must not be 0", pp.path, pp.ln("DOE", "f0"))
    return {"type": "binary_2", "order": 1.0, "norm_radius": 1.0,
            "coefficients": [-math.pi / (lam_um * 1e-3 * f0)]}


def _zernike(pp: _Params, radius: float) -> dict:
    """DeepLens's up to 37 Zernike terms (``z_coeff``, rad) on ``radius`` (mm) as a Noll-ordered zernike model."""
    c = pp.need("z_coeff")
    if hasattr(c, "tolist"):
        c = c.tolist()
    if (not isinstance(c, list) or not c or len(c) > 37
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in c)):
        raise LensFileError(f"DOE.z_coeff: expected a list of 1 to 37 numbers (DeepLens's Zernike terms), got "
                            f"{c!r}", pp.path, pp.ln("DOE", "z_coeff"))
    c = [float(x) for x in c]
    noll = [0.0] * (max(len(c), 3) if len(c) >= 2 else len(c))
    for i, x in enumerate(c):
        noll[ZERNIKE_DEEPLENS_TO_NOLL[i] - 1] = x
    if any(c[i] != 0 for i in (28, 29) if i < len(c)):
        # stacklevel: the caller of read_deeplens / read_deeplens_hybrid
        warnings.warn(LensFileWarning(
            f"{pp.path}:{pp.ln('DOE', 'z_coeff')}: DOE.z_coeff: DeepLens's terms 29 and 30 use the radial polynomial "
            "35ρ⁷ − 60ρ⁵ + 30ρ³ − 4 (a typo for … − 4ρ); raywave uses the correct Zernike polynomial, "
            "so their phase differs"), stacklevel=6)
    return {"type": "zernike", "radius": radius, "coefficients": noll}


def _pixel2d_source(pp: _Params, dd, legacy: bool, path, ln) -> dict:
    """Where a Pixel2D DOE's phase map comes from: ``{"array": ...}`` (a legacy checkpoint's ``pmap``) or
    ``{"ref": file name}``, with the line that names it (the map is read by :func:`load_pixel2d_map`)."""
    if legacy:
        if "pmap" in pp.p and hasattr(pp.p["pmap"], "ndim"):
            return {"array": pp.p["pmap"], "ref": dd.get("doe_path"), "line": ln("DOE", "doe_path")}
        pp.need("doe_path")
        raise LensFileError(f"DOE.doe_path: no 'pmap' phase map found in {dd.get('doe_path')!r}", path,
                            ln("DOE", "doe_path"))
    ref = pp.need("phase_map_path")
    if not isinstance(ref, str) or not ref.strip():
        raise LensFileError(f"DOE.phase_map_path: expected a file name, got {ref!r}", path,
                            ln("DOE", "phase_map_path"))
    return {"ref": ref, "line": ln("DOE", "phase_map_path")}
