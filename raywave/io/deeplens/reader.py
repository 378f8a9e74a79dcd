"""Reading a DeepLens (hybrid) lens file: :func:`read_deeplens` (the lens spec) and
:func:`read_deeplens_hybrid` (the spec and its DOE with a Pixel2D phase map loaded)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import (FORMAT_NAME, FORMAT_VERSION, UNITS, key_path, parse_json_text, read_text,
                                    validate_spec)
from raywave.io.spec import DEFAULT_WAVELENGTHS
from raywave.io.deeplens.doe_section import deeplens_doe
from raywave.io.deeplens.phase_map import load_pixel2d_map
from raywave.io.deeplens.surfaces import (DEFAULT_SENSOR_RES, FIELD_FRACTIONS, TOP_KEYS, _convert_surfaces, _num,
                                         looks_like_deeplens)


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
    """``(validated spec, Pixel2D source or None)`` of a DeepLens lens file (:func:`read_deeplens`)."""
    path = str(path)
    data, lines = parse_json_text(read_text(path), path)
    if not looks_like_deeplens(data):
        raise LensFileError("not a DeepLens lens file (expected an object with \"surfaces\" entries having "
                            "\"d_next\" / \"mat2\" / \"roc\", or \"d_sensor\" / \"r_sensor\")", path, 1)
    ln = _line_finder(lines)
    unknown = [k for k in data if k not in TOP_KEYS]
    surfs = data["surfaces"]
    if not surfs:
        raise LensFileError("surfaces: the lens has no surfaces (empty list)", path, ln("surfaces"))
    z_of = _positions(surfs, path, ln)
    d_sensor = None
    for k in ("d_sensor", "(d_sensor)"):
        if k in data:
            d_sensor = _num(data, k, "", path, ln(k))
            break
    out_surfs = _convert_surfaces(surfs, z_of, d_sensor, clip_apertures, path, ln, unknown)

    spec = _spec_head(data, path, ln)
    r_sensor = _sensor(spec, data, path, ln)
    spec["fields"] = _fields(data, r_sensor)
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


def _line_finder(lines: dict):
    """``ln(*key_path)``: the line of a JSON key path, else of its nearest parent present in ``lines``, else 1."""

    def ln(*p):
        p = tuple(p)
        while p:
            if p in lines:
                return lines[p]
            p = p[:-1]
        return 1

    return ln


def _positions(surfs: list, path, ln):
    """``z_of(i)``: surface i's absolute vertex position (mm) from its ``d`` / ``(d)``, or None (files without
    ``d_next`` give these)."""

    def z_of(i):
        sd = surfs[i]
        for k in ("d", "(d)"):
            if k in sd:
                return _num(sd, k, key_path(("surfaces", i)), path, ln("surfaces", i, k))
        return None

    return z_of


def _spec_head(data: dict, path, ln) -> dict:
    """The spec's format, name (the file's stem), description (``info``), object at infinity and entrance pupil
    diameter (``enpd``, mm)."""
    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    spec["name"] = Path(path).stem
    info = data.get("info")
    if isinstance(info, str) and info.strip() and info != "None":
        spec["description"] = info
    spec["object"] = {"distance": "inf"}
    enpd = data.get("enpd")
    if enpd is not None:
        spec["system_aperture"] = {"epd": _num(data, "enpd", "", path, ln("enpd"))}
    return spec


def _sensor(spec: dict, data: dict, path, ln):
    """Set ``spec["sensor"]`` (size mm, resolution pixels) and return the sensor half-diagonal (mm, or None).

    DeepLens's rule: the size follows from ``r_sensor`` and the aspect ratio of ``sensor_res`` (default
    :data:`DEFAULT_SENSOR_RES`); else from ``sensor_size``."""
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
    return r_sensor


def _fields(data: dict, r_sensor) -> dict:
    """The spec's fields (degrees): :data:`FIELD_FRACTIONS` of the half field of view atan(r_sensor / foclen),
    or the axis alone without them."""
    foclen = data.get("foclen")
    if r_sensor and isinstance(foclen, (int, float)) and not isinstance(foclen, bool) and foclen > 0:
        hfov = math.degrees(math.atan(r_sensor / foclen))
        return {"type": "angle", "values": [f * hfov for f in FIELD_FRACTIONS]}
    return {"type": "angle", "values": [0.0]}
