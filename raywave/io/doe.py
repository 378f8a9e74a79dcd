"""The ``"doe"`` section of a lens spec: schema, phase-map files (.npy / .npz) and the DOE grid.

A hybrid lens file names its diffractive optical element (DOE) in an optional top-level ``"doe"`` object
(docs/lens-format.md, "DOE"): the plane's distance after the last vertex, the pixel grid (pitch and size or
shape), the aperture and the phase (``null`` = a blank DOE, or a path to a ``.npy`` / ``.npz`` phase map in
radians, relative to the lens file, or a parametric ``phase_model``), and optionally a ``material`` and
``levels`` (a fabricated, dispersive height map) or ``wrap`` (a continuous kinoform). Everything here works on
plain dicts and numpy arrays and never imports torch; :mod:`raywave.assembly.build` turns a :class:`DOEData`
into a :class:`~raywave.doe.DOE`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from raywave.io.errors import LensFileError, suggestion
from raywave.utils.checks import MAX_WAVELENGTH_UM as _MAX_WAVELENGTH_UM, wavelength_problem as _wavelength_problem

#: Keys of the "doe" object.
DOE_KEYS = ("distance", "pitch", "size", "shape", "aperture", "phase", "design_wavelength", "oversample",
            "phase_model", "material", "levels", "wrap")
DOE_APERTURES = ("square", "circle")
PHASE_EXTENSIONS = (".npy", ".npz")
#: Parametric phase models (raywave.doe: Binary2DOE, RadialDOE, ZernikeDOE, FresnelDOE, GratingDOE, CubicDOE,
#: SumDOE): type -> (required keys, optional keys). Lengths in mm, phases in rad, wavelengths in µm, angles in deg.
PHASE_MODELS = {
    "binary_2": (("order", "norm_radius", "coefficients"), ()),
    "radial": (("radius", "profile"), ()),
    "zernike": (("coefficients",), ("radius",)),
    "fresnel": (("focal_length",), ("wavelength",)),
    "grating": (("period",), ("angle",)),
    "cubic": (("alpha",), ("radius",)),
    "sum": (("terms",), ()),
}
#: Allowed keys of each phase-model type.
PHASE_MODEL_KEYS = {k: ("type",) + req + opt for k, (req, opt) in PHASE_MODELS.items()}
#: A size must be this close (in pixels) to a whole number of pixels.
PIXEL_TOLERANCE = 1e-6
#: Wavelengths above this (µm) are taken for a unit mistake (as raywave.io.json_format).


@dataclass
class DOEData:
    """A lens file's DOE, resolved: numbers, the grid and the phase map (numpy), no torch.

    Attributes:
        distance: mm from the last vertex to the DOE plane (None: not given).
        pitch: DOE pixel pitch (mm), from the file or the .npz (None: not given).
        shape: ``(ny, nx)`` pixels (from ``shape``, ``size`` / ``pitch`` or the phase map; None: not given).
        size: ``(width, height)`` mm as written (None: not given).
        aperture: "square" or "circle".
        phase: ``(ny, nx)`` float64 phase map (rad) or None for a blank DOE.
        phase_path: the phase file (absolute) or None.
        design_wavelength: µm or None.
        oversample: simulation samples per DOE pixel per axis.
        phase_model: a parametric phase (``{"type": "binary_2", ...}``, see :data:`PHASE_MODELS`), or None.
        material: the DOE's material (a glass name): the DOE is a dispersive height map in it; None: not given.
        levels: fabricate the DOE: wrap its phase at the design wavelength and quantise it to this many levels.
        wrap: wrap the phase to [0, 2π) at the design wavelength without quantising it (a continuous kinoform;
            implied by ``levels``).
    """

    distance: float | None = None
    pitch: float | None = None
    shape: tuple[int, int] | None = None
    size: tuple[float, float] | None = None
    aperture: str = "square"
    phase: object = None
    phase_path: str | None = None
    design_wavelength: float | None = None
    oversample: int = 1
    phase_model: dict | None = None
    material: str | None = None
    levels: int | None = None
    wrap: bool = False


# --------------------------------------------------------------------------------------- schema
def validate_doe(v, doe, spec) -> None:
    """Check the ``"doe"`` object with the validator ``v`` of :mod:`raywave.io.json_format` (which reports
    each problem with its key path and line). ``spec`` is the whole spec (for the last thickness)."""
    path = ("doe",)
    if not v.obj(doe, path):
        return
    v.keys(doe, path, DOE_KEYS)
    if "distance" not in doe:
        v.err(path, "missing 'distance' (mm from the last surface's vertex to the DOE plane)")
    elif v.number(doe["distance"], path + ("distance",), nonneg=True):
        last = _last_thickness(spec)
        if last is not None and not doe["distance"] < last:
            v.err(path + ("distance",), f"the DOE plane must lie between the last surface and the sensor: "
                                        f"0 <= distance < {last!r} mm (the last surface's thickness, along the light), got "
                                        f"{doe['distance']!r}")
    if "pitch" in doe:
        v.number(doe["pitch"], path + ("pitch",), positive=True)
    if "size" in doe and "shape" in doe:
        v.err(path + ("shape",), "give either 'size' (mm) or 'shape' (pixels), not both")
    if "size" in doe:
        if v.number_list(doe["size"], path + ("size",), n=2, positive=True) and _is_pos(doe.get("pitch")):
            for i, (s, name) in enumerate(zip(doe["size"], ("width", "height"))):
                n = s / doe["pitch"]
                if abs(n - round(n)) > PIXEL_TOLERANCE * max(1.0, n) or round(n) < 1:
                    v.err(path + ("size", i), f"the {name} {s!r} mm is not a whole number of {doe['pitch']!r} mm "
                                              f"pixels ({n:.6g}); give a multiple of the pitch or 'shape'")
    if "shape" in doe:
        v.number_list(doe["shape"], path + ("shape",), n=2, positive=True, integer=True)
    if "aperture" in doe and doe["aperture"] not in DOE_APERTURES:
        a = doe["aperture"]
        v.err(path + ("aperture",), f"must be 'square' or 'circle', got {_describe(a)}"
                                    + (suggestion(a, DOE_APERTURES) if isinstance(a, str) else ""))
    if "phase" in doe and doe["phase"] is not None:
        ph = doe["phase"]
        if v.string(ph, path + ("phase",), nonempty=True):
            if Path(ph).suffix.lower() not in PHASE_EXTENSIONS:
                v.err(path + ("phase",), f"a phase map is a .npy file (the (ny, nx) phase in radians) or a .npz "
                                         f"file (key 'phase', optionally 'pitch'), got {ph!r}")
            if doe.get("phase_model") is not None:
                v.err(path + ("phase_model",), "give either 'phase' (a phase map) or 'phase_model', not both")
    if "design_wavelength" in doe and doe["design_wavelength"] is not None:
        w = doe["design_wavelength"]
        if v.number(w, path + ("design_wavelength",), positive=True) and w > _MAX_WAVELENGTH_UM:
            v.err(path + ("design_wavelength",), _wavelength_problem(w))
    if "oversample" in doe:
        o = doe["oversample"]
        if not (isinstance(o, int) and not isinstance(o, bool) and o >= 1):
            v.err(path + ("oversample",), f"must be a positive integer, got {_describe(o)}")
    if "phase_model" in doe and doe["phase_model"] is not None:
        _validate_phase_model(v, doe["phase_model"], path + ("phase_model",))
    if doe.get("material") is not None:
        v.string(doe["material"], path + ("material",), nonempty=True)
    if doe.get("levels") is not None:
        lv = doe["levels"]
        if not (isinstance(lv, int) and not isinstance(lv, bool) and lv >= 2):
            v.err(path + ("levels",), f"must be an integer number of phase levels >= 2, got {_describe(lv)}")
    if "wrap" in doe and not isinstance(doe["wrap"], bool):
        v.err(path + ("wrap",), f"must be true or false, got {_describe(doe['wrap'])}")


def _validate_phase_model(v, m, path, depth: int = 0) -> None:
    if not v.obj(m, path):
        return
    kind = m.get("type")
    if not isinstance(kind, str) or kind not in PHASE_MODELS:
        hint = suggestion(kind, PHASE_MODELS) if isinstance(kind, str) else ""
        v.err(path + ("type",) if "type" in m else path,
              f"phase model type must be one of {', '.join(map(repr, PHASE_MODELS))}, got {_describe(kind)}{hint}")
        return
    v.keys(m, path, PHASE_MODEL_KEYS[kind])
    for k in PHASE_MODELS[kind][0]:
        if k not in m:
            v.err(path, f"a {kind} phase model needs {k!r}")
    for k in ("order", "alpha", "angle"):
        if k in m:
            v.number(m[k], path + (k,))
    for k in ("norm_radius", "radius", "period"):
        if k in m:
            v.number(m[k], path + (k,), positive=True)
    if "focal_length" in m:
        v.number(m["focal_length"], path + ("focal_length",), nonzero=True)
    if "wavelength" in m and v.number(m["wavelength"], path + ("wavelength",), positive=True) \
            and m["wavelength"] > _MAX_WAVELENGTH_UM:
        v.err(path + ("wavelength",), _wavelength_problem(m["wavelength"]))
    for k in ("coefficients", "profile"):
        if k in m:
            c = m[k]
            if not isinstance(c, list):
                v.err(path + (k,), f"must be a list, got {_describe(c)}")
            else:
                for i, x in enumerate(c):
                    v.number(x, path + (k, i))
                if k == "profile" and len(c) < 2:
                    v.err(path + (k,), f"a radial profile needs at least 2 samples, got {len(c)}")
                if k == "coefficients" and kind == "zernike" and not c:
                    v.err(path + (k,), "must not be empty")
    if "terms" in m:
        t = m["terms"]
        if not isinstance(t, list) or not t:
            v.err(path + ("terms",), f"must be a non-empty list of phase models, got {_describe(t)}")
        elif depth > 4:
            v.err(path + ("terms",), "phase models nest too deep")
        else:
            for i, x in enumerate(t):
                _validate_phase_model(v, x, path + ("terms", i), depth + 1)


def phase_model_canonical(m: dict) -> dict:
    """A phase model with numbers as floats (and, for binary_2, the order written out)."""
    out: dict = {"type": m["type"]}
    if m["type"] == "binary_2":
        return {"type": "binary_2", "order": float(m.get("order", 1.0)), "norm_radius": float(m["norm_radius"]),
                "coefficients": [float(c) for c in m["coefficients"]]}
    for k, x in m.items():
        if k == "type":
            continue
        if k == "terms":
            out[k] = [phase_model_canonical(t) for t in x]
        elif isinstance(x, list):
            out[k] = [float(c) for c in x]
        else:
            out[k] = float(x)
    return out


def _is_pos(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _describe(x) -> str:
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "a boolean"
    if isinstance(x, str):
        return f"the string {x!r}"
    if isinstance(x, (int, float)):
        return f"the number {x!r}"
    return "a list" if isinstance(x, list) else "an object" if isinstance(x, dict) else type(x).__name__


def _last_thickness(spec):
    surfs = spec.get("surfaces") if isinstance(spec, dict) else None
    if not isinstance(surfs, list) or not surfs or not isinstance(surfs[-1], dict):
        return None
    t = surfs[-1].get("thickness")
    if not (isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t)):
        return None
    # after an odd number of mirrors the light travels toward -z and the thickness is negative: the distance to
    # the sensor along the light is -t (the DOE plane lies in the image-space frame, raywave.lens.frames)
    mirrors = sum(1 for s in surfs if isinstance(s, dict) and isinstance(s.get("material"), str)
                  and s["material"].lower() == "mirror")
    return -t if mirrors % 2 else t


def doe_canonical(doe: dict) -> dict:
    """The ``"doe"`` object with defaults written out (numbers as floats, aperture, phase, oversample)."""
    out: dict = {"distance": float(doe["distance"])}
    if doe.get("pitch") is not None:
        out["pitch"] = float(doe["pitch"])
    if doe.get("size") is not None:
        out["size"] = [float(s) for s in doe["size"]]
    if doe.get("shape") is not None:
        out["shape"] = [int(s) for s in doe["shape"]]
    out["aperture"] = doe.get("aperture", "square")
    out["phase"] = doe.get("phase")
    if doe.get("design_wavelength") is not None:
        out["design_wavelength"] = float(doe["design_wavelength"])
    out["oversample"] = int(doe.get("oversample", 1))
    if doe.get("phase_model") is not None:
        out["phase_model"] = phase_model_canonical(doe["phase_model"])
    if doe.get("material") is not None:
        out["material"] = str(doe["material"])
    if doe.get("levels") is not None:
        out["levels"] = int(doe["levels"])
    if doe.get("wrap"):
        out["wrap"] = True
    return out


# --------------------------------------------------------------------------------------- phase files
def _line(lines, *path):
    lines = lines or {}
    path = tuple(path)
    while path:
        if path in lines:
            return lines[path]
        path = path[:-1]
    return None


def phase_file_path(doe: dict, base_dir) -> Path | None:
    """The phase map's path (relative paths are relative to ``base_dir``, the lens file's folder)."""
    ph = doe.get("phase")
    if ph is None:
        return None
    p = Path(ph)
    return p if p.is_absolute() or base_dir is None else Path(base_dir) / p


def _load_phase_file(path: Path, source, line, header_only: bool):
    """-> (array or shape, npz pitch or None). Errors name the lens file, its line and the phase file."""
    import numpy as np

    where = "doe.phase"
    if not path.is_file():
        raise LensFileError(f"{where}: phase map file {str(path)!r} not found (relative paths are relative to "
                            "the lens file)", source, line)
    pitch = None
    try:
        if path.suffix.lower() == ".npy":
            arr = np.load(path, mmap_mode="r" if header_only else None, allow_pickle=False)
        else:
            with np.load(path, allow_pickle=False) as z:
                if "phase" not in z.files:
                    raise LensFileError(f"{where}: {str(path)!r} holds no array 'phase' (found: "
                                        f"{', '.join(z.files) or 'nothing'})", source, line)
                arr = z["phase"]
                if "pitch" in z.files:
                    pv = z["pitch"]
                    if pv.size != 1 or not np.issubdtype(pv.dtype, np.number):
                        raise LensFileError(f"{where}: {str(path)!r}: 'pitch' must be one number (mm)", source, line)
                    pitch = float(pv.reshape(()))
                    if not (math.isfinite(pitch) and pitch > 0):
                        raise LensFileError(f"{where}: {str(path)!r}: pitch must be > 0 mm, got {pitch!r}",
                                            source, line)
    except LensFileError:
        raise
    except (OSError, ValueError) as e:
        raise LensFileError(f"{where}: cannot read phase map {str(path)!r}: {e}", source, line) from None
    if arr.ndim != 2:
        raise LensFileError(f"{where}: the phase map in {str(path)!r} must be 2-D (ny, nx), got shape "
                            f"{tuple(arr.shape)}", source, line)
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise LensFileError(f"{where}: the phase map in {str(path)!r} is empty (shape {tuple(arr.shape)})",
                            source, line)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise LensFileError(f"{where}: the phase map in {str(path)!r} must hold real numbers (radians), got "
                            f"dtype {arr.dtype}", source, line)
    if header_only:
        return tuple(arr.shape), pitch
    arr = np.asarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise LensFileError(f"{where}: the phase map in {str(path)!r} contains NaN or inf (first at "
                            f"[{bad[0]}, {bad[1]}])", source, line)
    return arr, pitch


def resolve_doe(spec: dict, source="<spec>", base_dir=None, lines: dict | None = None,
                load: bool = True) -> DOEData | None:
    """The spec's DOE as :class:`DOEData` (None without a ``"doe"`` object), its phase file read and checked.

    Checks what the schema cannot: the phase file exists, holds a 2-D finite real array, and its shape agrees
    with ``shape`` / ``size`` and the pitch (from the file's ``"pitch"`` or the .npz's ``pitch``, which must
    agree when both are given). ``load=False`` reads only the array header (no finiteness check). Errors are
    :class:`LensFileError` naming ``source``, the line of the key (with ``lines``) and the key path.
    """
    doe = spec.get("doe")
    if doe is None:
        return None
    data = DOEData(
        distance=float(doe["distance"]) if "distance" in doe else None,
        pitch=float(doe["pitch"]) if doe.get("pitch") is not None else None,
        size=tuple(float(s) for s in doe["size"]) if doe.get("size") is not None else None,
        aperture=doe.get("aperture", "square"),
        design_wavelength=float(doe["design_wavelength"]) if doe.get("design_wavelength") is not None else None,
        oversample=int(doe.get("oversample", 1)),
        phase_model=doe.get("phase_model"),
        material=doe.get("material"),
        levels=int(doe["levels"]) if doe.get("levels") is not None else None,
        wrap=bool(doe.get("wrap", False)),
    )
    if doe.get("shape") is not None:
        data.shape = (int(doe["shape"][0]), int(doe["shape"][1]))
    path = phase_file_path(doe, base_dir)
    if path is not None:
        if base_dir is None and not path.is_absolute():
            raise LensFileError(f"doe.phase: the relative path {doe['phase']!r} needs the lens file's folder "
                                "(read the lens from a file)", source, _line(lines, "doe", "phase"))
        arr, npz_pitch = _load_phase_file(path, source, _line(lines, "doe", "phase"), header_only=not load)
        shape = arr if isinstance(arr, tuple) else tuple(arr.shape)
        data.phase = None if isinstance(arr, tuple) else arr
        data.phase_path = str(path)
        if npz_pitch is not None:
            if data.pitch is not None and abs(npz_pitch - data.pitch) > 1e-9 * data.pitch:
                raise LensFileError(f"doe.pitch: {data.pitch!r} mm disagrees with the pitch {npz_pitch!r} mm stored "
                                    f"in {str(path)!r}", source, _line(lines, "doe", "pitch"))
            data.pitch = npz_pitch if data.pitch is None else data.pitch
        if data.shape is not None and data.shape != shape:
            raise LensFileError(f"doe.shape: {list(data.shape)} disagrees with the phase map's shape {list(shape)} "
                                f"(ny, nx) in {str(path)!r}", source, _line(lines, "doe", "shape"))
        if data.size is not None:
            if data.pitch is None:
                raise LensFileError("doe.size: with a phase map, give 'pitch' (or store it in the .npz) to check "
                                    "the size", source, _line(lines, "doe", "size"))
            want = (shape[1] * data.pitch, shape[0] * data.pitch)
            if any(abs(s - w) > PIXEL_TOLERANCE * data.pitch * max(1, n)
                   for s, w, n in zip(data.size, want, (shape[1], shape[0]))):
                raise LensFileError(f"doe.size: {list(data.size)} mm disagrees with the phase map: {shape[1]} × "
                                    f"{shape[0]} pixels (nx × ny) of {data.pitch!r} mm are {want[0]:.9g} × "
                                    f"{want[1]:.9g} mm", source, _line(lines, "doe", "size"))
        data.shape = shape
    elif data.size is not None and data.pitch is not None:
        data.shape = (round(data.size[1] / data.pitch), round(data.size[0] / data.pitch))
    return data


def check_doe_files(spec: dict, source, lines: dict | None = None) -> None:
    """The cheap file checks of :func:`resolve_doe` for a lens file being read (phase file exists, header,
    shape): the map itself is read when the hybrid lens is built."""
    if isinstance(spec.get("doe"), dict) and spec["doe"].get("phase") is not None:
        resolve_doe(spec, source, Path(source).parent, lines, load=False)


def rebase_phase_path(spec: dict, from_dir, to_dir) -> dict:
    """``spec`` with a relative ``doe.phase`` path rewritten from ``from_dir`` to ``to_dir`` (when a lens file
    is written to another folder); absolute paths and specs without a phase map are returned unchanged."""
    doe = spec.get("doe")
    if not isinstance(doe, dict) or not isinstance(doe.get("phase"), str) or Path(doe["phase"]).is_absolute():
        return spec
    target = (Path(from_dir) / doe["phase"]).resolve()
    try:
        rel = os.path.relpath(target, Path(to_dir).resolve())
    except ValueError:  # another drive (Windows)
        rel = str(target)
    out = dict(spec)
    out["doe"] = dict(doe, phase=Path(rel).as_posix())
    return out
