"""Lens files with a DOE inside the lens (issue 46): a surface's ``"doe"`` key → :class:`~raywave.hybrid.
midsystem.MidSystemLens`.

The DOE plane sits ``distance`` mm after the surface's vertex (:mod:`raywave.io.surface_doe`; a ``.zmx`` BINARY_2 /
DGRATING surface inside the lens is read as such a DOE 0 mm after a plane surface, :mod:`raywave.io.zmx`). The
blank plane near the sensor where the engine builds its field is chosen as for a lens file's default DOE
(:mod:`raywave.assembly.build`: before the first caustic, sized to the beam, at the pitch that samples it), on the
lens with the DOE's strongest order in place.

**The DOE's grid** when the file does not give it (a ``.zmx`` surface never does): the size is the surface's clear
aperture (CLAP / SQAP, else its semi-diameter) or ``doe_size``, else the beam's footprint on the DOE plane
(:data:`BEAM_MARGIN` × the widest traced ray); the pitch samples the DOE's own phase (:func:`surface_doe_pitch`:
:data:`PHASE_STEP` rad per pixel at its steepest, so that the engine's interpolated phase map carries it, well
inside :data:`raywave.hybrid.midsystem.MAX_STEP`), at most a 64th of the size, refused beyond
:data:`MAX_SIDE_PIXELS` a side (give ``doe_pitch``).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import torch

from raywave.assembly.build import (_make_doe, _spec_lens, caustic_free_distance, default_doe_size,
                                    nyquist_doe_pitch)
from raywave.doe import doe_from_phase_model
from raywave.hybrid.hybrid_lens import BEAM_MARGIN
from raywave.hybrid.midsystem import DOEPhaseSurface, MidSystemLens, doe_orders, insert_doe
from raywave.io import read_lens_spec
from raywave.io.doe import resolve_doe
from raywave.io.errors import LensFileError
from raywave.io.surface_doe import is_conformal, surface_does, without_conformal
from raywave.lens.lens import Lens
from raywave.lens.prescription import binary2_power
from raywave.lens.sources import point_source_rays
from raywave.rays.bundle import RayBundle
from raywave.rays.pupil import rim_and_grid

__all__ = ["MAX_SIDE_PIXELS", "PHASE_STEP", "doe_lens", "does_lens", "lens_with_doe", "load_midsystem", "midsystem_from_spec",
           "midsystem_of", "surface_doe_info", "surface_doe_pitch", "surface_doe_positions"]

#: the default pitch of a DOE inside the lens: its phase steps by at most this much (rad) between pixels (below the
#: ~0.49 rad at which the pixels' flat steps cost 1 % of the amplitude, the engine's warning)
PHASE_STEP = 0.4
#: a default DOE grid inside the lens larger than this many pixels a side is refused (give ``doe_pitch``)
MAX_SIDE_PIXELS = 8192
_PROBE_SIDE = 257  # samples a side of the first grid on which the default pitch probes the phase's steepest slope
_PROBE_MAX = 4097  # ... and of the finest (what it does not resolve needs more than MAX_SIDE_PIXELS)


def surface_doe_positions(spec: dict) -> list:
    """``[(surface index, distance mm, doe dict)]`` of every DOE placed at a surface of ``spec`` (distance None: a
    conformal DOE, on the surface itself)."""
    return [(i, None if is_conformal(d) else float(d["distance"]), d) for i, s in enumerate(spec.get("surfaces", []))
            for d in surface_does(s)]


def _steepest_slope(model: dict, size: tuple[float, float], data) -> float:
    """The largest |∇φ| (rad/mm) of the phase model ``model`` over a DOE of ``size`` (w, h) mm: a grating's
    2π/period; else the largest step between neighbouring samples of ever finer probe grids (each twice as fine,
    from :data:`_PROBE_SIDE` to :data:`_PROBE_MAX` a side) once the steps are small enough (π/4) to be read without
    aliasing; inf when even the finest probe does not resolve them."""
    if model["type"] == "grating":
        return 2 * math.pi / float(model["period"])
    side = _PROBE_SIDE
    while True:
        pitch = max(size) / (side - 1)
        shape = (int(math.ceil(size[1] / pitch)) + 1, int(math.ceil(size[0] / pitch)) + 1)
        probe = doe_from_phase_model(model, shape, pitch, "square", design_wavelength=data.design_wavelength,
                                     material=data.material)
        with torch.no_grad():
            p = probe.design_phase_pixels(slice(None), slice(None)) * probe.phase_scale
            step = max(float((p[:, 1:] - p[:, :-1]).abs().max()), float((p[1:, :] - p[:-1, :]).abs().max()))
        if step <= math.pi / 4:
            return step / pitch
        if side >= _PROBE_MAX:
            return math.inf
        side = 2 * side - 1


def surface_doe_pitch(data, size: tuple[float, float], where: str, source: str) -> float:
    """The default pitch (mm) of a DOE inside the lens (``data``: its :class:`~raywave.io.DOEData`, ``size`` (w, h)
    mm): :data:`PHASE_STEP` over the steepest slope of its phase model, rounded down to 2 significant digits, at
    most a 64th of the size; a blank DOE a 64th of the size. A :class:`LensFileError` beyond
    :data:`MAX_SIDE_PIXELS` pixels a side."""
    coarse = max(size) / 64
    if data.phase_model is None:
        return coarse
    slope = _steepest_slope(data.phase_model, size, data)
    if not slope > 0:
        return coarse
    if not math.isfinite(slope):
        raise LensFileError(f"{where}: the DOE's phase ({data.phase_model['type']}) is not resolved by "
                            f"{_PROBE_MAX} samples a side over {max(size):g} mm: give a pitch (doe_pitch) or a "
                            "smaller size", source)
    pitch = PHASE_STEP / slope
    e = math.floor(math.log10(pitch)) - 1
    pitch = min(math.floor(pitch / 10.0 ** e) * 10.0 ** e, coarse)
    if max(size) / pitch > MAX_SIDE_PIXELS:
        raise LensFileError(f"{where}: the DOE's phase ({data.phase_model['type']}) needs {pitch * 1e3:.3g} µm pixels "
                            f"to be sampled ({PHASE_STEP:g} rad per pixel), {max(size) / pitch:.0f} a side over "
                            f"{max(size):g} mm: give a pitch (doe_pitch) or a smaller size", source)
    return pitch


def _footprint(lens: Lens, after: int, distance: float | None, fields=None) -> tuple[float, float]:
    """(w, h) mm of the beam on the plane ``distance`` mm after surface ``after`` of ``lens`` (None: on the
    surface itself): :data:`BEAM_MARGIN` × twice the widest |x|, |y| of the pupil's rim and a grid inside, for
    ``fields`` ((F, 2) in the lens's field type; default the lens's fields along y) and on axis, at its
    wavelengths."""
    probe = insert_doe(lens, after, distance, lambda x, y, w: (0 * x, 0 * x, 0 * x))
    px, py = rim_and_grid(36, 7)
    fields = [(0.0, 0.0)] + ([(0.0, float(f)) for f in probe.fields] if fields is None else
                             [tuple(float(v) for v in row) for row in torch.as_tensor(fields).reshape(-1, 2)])
    with torch.no_grad():
        rays = point_source_rays(probe, torch.tensor(fields, dtype=torch.float64), list(probe.wavelengths),
                                 pupil=(px, py))
        out = probe.trace(rays, stop=after + (1 if distance is None else 2))
    ok = out.valid
    if not bool(ok.any()):
        raise ValueError(f"no ray of the lens reaches the plane {distance:g} mm after surface {after}")
    w = 2 * BEAM_MARGIN * float(out.o[..., 0][ok].abs().max())
    h = 2 * BEAM_MARGIN * float(out.o[..., 1][ok].abs().max())
    return max(w, h, 1e-3), max(w, h, 1e-3)


def _doe_data(spec: dict, after: int, dspec: dict, source: str, base_dir, lens: Lens, doe_pitch, doe_size,
              fields=None):
    """The :class:`~raywave.io.DOEData` of the DOE ``dspec`` at surface ``after``, its grid completed: the file's
    pitch / shape, else ``doe_pitch`` / ``doe_size`` (mm), else the defaults of the module docstring."""
    where = f"surfaces[{after}].doe"
    conformal = is_conformal(dspec)
    data = resolve_doe({"doe": without_conformal(dspec) if conformal else dspec}, source, base_dir)
    if doe_size is not None and data.phase is None:
        size = tuple(float(s) for s in (doe_size if isinstance(doe_size, (list, tuple)) else (doe_size, doe_size)))
        data.size, data.shape = size, None
    if doe_pitch is not None and data.phase is None:
        data.pitch, data.shape = float(doe_pitch), None
    if data.shape is None:
        size = data.size if data.size is not None else _footprint(
            lens, after, None if conformal else float(dspec["distance"]), fields)
        data.size = size
        if data.pitch is None:
            data.pitch = surface_doe_pitch(data, size, where, source)
        data.shape = (int(math.ceil(size[1] / data.pitch - 1e-9)), int(math.ceil(size[0] / data.pitch - 1e-9)))
    if data.pitch is None:
        raise LensFileError(f"{where}: give 'pitch' (the phase map's pixel pitch)", source)
    return data


def doe_lens(spec: dict, source: str = "<spec>", base_dir=None, doe_pitch: float | None = None, doe_size=None,
             fields=None):
    """``(lens, doe, after, distance)``: the refractive lens of ``spec`` (its surface DOEs left out), the
    :class:`~raywave.doe.DOE` of its one surface DOE, and where it sits (:func:`does_lens` for several).
    ``fields``: (F, 2) field points whose beams a DOE without a size must hold (default the lens's fields along
    y)."""
    found = surface_doe_positions(spec)
    if len(found) > 1 and spec.get("doe") is None:
        raise ValueError(f"{source}: {len(found)} DOEs inside the lens: doe_lens gives one; use does_lens "
                         "(raywave.load_midsystem builds them all)")
    lens, does, afters, distances = does_lens(spec, source, base_dir, doe_pitch, doe_size, fields)
    return lens, does[0], afters[0], distances[0]


def does_lens(spec: dict, source: str = "<spec>", base_dir=None, doe_pitch: float | None = None, doe_size=None,
              fields=None):
    """``(lens, does, afters, distances)``: the refractive lens of ``spec`` (its surface DOEs left out) and every
    DOE placed at a surface, in the file's order (surface by surface, a surface's list in order), with where each
    sits. A DOE inside the lens together with one before the sensor (the top-level ``"doe"``) is refused (the
    engine's plane near the sensor is blank). ``doe_pitch`` / ``doe_size`` apply to every DOE without a grid;
    ``fields``: as :func:`doe_lens` (a DOE's default size is the beam's footprint on the refractive lens)."""
    found = surface_doe_positions(spec)
    if not found:
        raise ValueError(f"{source}: no surface carries a 'doe': use raywave.load_hybrid for a DOE before the sensor")
    if spec.get("doe") is not None:
        raise ValueError(f"{source}: {len(found) + 1} DOEs: a DOE inside the lens together with one before the "
                         "sensor (the top-level 'doe') is not supported (issue 46: the engine's plane near the "
                         "sensor is blank); place the last one at a surface too")
    plain = copy.deepcopy(spec)
    for s in plain.get("surfaces", []):
        s.pop("doe", None)
    lens = _spec_lens(plain, None, source)
    does, afters, distances = [], [], []
    for after, distance, dspec in found:
        data = _doe_data(spec, after, dspec, source, base_dir, lens, doe_pitch, doe_size, fields)
        does.append(_make_doe(data, data.shape, data.pitch, source))
        afters.append(after)
        distances.append(distance)
    return lens, does, afters, distances


def lens_with_doe(lens: Lens, doe, after, distance, wavelength: float | None = None) -> Lens:
    """``lens`` with ``doe``'s plane ``distance`` mm after surface ``after``, carrying its strongest order at
    ``wavelength`` µm (default the primary): the lens a layout draws and its rays see. Several DOEs: lists of
    ``doe``, ``after`` and ``distance`` (each its strongest order)."""
    wl = lens.primary_wavelength if wavelength is None else float(wavelength)
    if isinstance(doe, (list, tuple)):
        scales = [doe_orders(d, wl)[0][0] for d in doe]
        return MidSystemLens(lens, list(doe), list(after), list(distance), 1.0, 1.0, 1.0).build_lens(scales)[0]
    scale = doe_orders(doe, wl)[0][0]
    return insert_doe(lens, after, distance, DOEPhaseSurface(doe, float(scale)), 1.0, doe)


def midsystem_from_spec(spec: dict, source: str = "<spec>", base_dir=None, final_distance: float | None = None,
                        sensor_pitch: float | None = None, doe_pitch: float | None = None, doe_size=None,
                        **kwargs) -> MidSystemLens:
    """The :class:`MidSystemLens` of a validated spec with DOEs at its surfaces (one or several, :func:`does_lens`;
    the top-level ``"doe"``, the DOE before the sensor, must then be absent). ``doe_pitch`` / ``doe_size`` (mm):
    the DOEs' grid where the file gives none (a phase map fixes its own); ``sensor_pitch``: the PSF pixel (default
    the lens's sensor pixel, else the engine plane's pitch); ``kwargs``: passed to :class:`MidSystemLens`
    (``stop_edge``, ``edge_step``, ``min_efficiency``, ``orders``)."""
    lens, does, afters, distances = does_lens(spec, source, base_dir, doe_pitch, doe_size)
    if len(does) == 1:
        return midsystem_of(lens, does[0], afters[0], distances[0], final_distance, sensor_pitch, **kwargs)
    return midsystem_of(lens, does, afters, distances, final_distance, sensor_pitch, **kwargs)


def midsystem_of(lens: Lens, doe, after: int, distance: float, final_distance: float | None = None,
                 sensor_pitch: float | None = None, fields=None, **kwargs) -> MidSystemLens:
    """A :class:`MidSystemLens` of ``lens`` with ``doe`` ``distance`` mm after surface ``after``, its engine plane
    placed, sized and sampled as a lens file's default DOE (on the lens with the DOE's strongest order; for the
    field points ``fields`` (F, 2), default the lens's fields along y), its sensor pitch resolved
    (``sensor_pitch``, else the lens's pixel, else the plane's pitch). Several DOEs: lists of ``doe``, ``after``
    and ``distance``."""
    lens1 = lens_with_doe(lens, doe, after, distance)
    pitch0 = min(d.pitch for d in doe) if isinstance(doe, (list, tuple)) else doe.pitch
    last = float(lens.surfaces[-1].thickness.detach())
    if fields is not None:
        fields = torch.cat([torch.zeros(1, 2, dtype=torch.float64),
                            torch.as_tensor(fields, dtype=torch.float64).reshape(-1, 2)])
    if final_distance is None:
        free = caustic_free_distance(lens1, fields)
        final_distance = min(0.5 * last, free if free is not None and math.isfinite(free) else 0.5 * last)
    pitch = nyquist_doe_pitch(lens1, final_distance, fields) or pitch0
    size = max(default_doe_size(lens1, final_distance, fields))
    if sensor_pitch is None:
        sensor_pitch = lens.pixel_pitch if lens.pixel_pitch is not None else pitch
    return MidSystemLens(lens, doe, after, distance, final_distance, size, pitch, sensor_pitch=float(sensor_pitch),
                         **kwargs)


def load_midsystem(path, final_distance: float | None = None, sensor_pitch: float | None = None,
                   doe_pitch: float | None = None, doe_size=None, **kwargs) -> MidSystemLens:
    """:func:`midsystem_from_spec` of a lens file (raywave JSON with a surface ``"doe"``, or a ``.zmx`` with a
    BINARY_2 / DGRATING surface inside the lens)."""
    path = Path(path)
    return midsystem_from_spec(read_lens_spec(path), str(path), path.parent, final_distance, sensor_pitch,
                               doe_pitch, doe_size, **kwargs)


# ---------------------------------------------------------------------------- what `raywave info` says
def _with_thin_power(lens: Lens, after: int, distance: float, power: float) -> Lens:
    """``lens`` with a thin element of paraxial ``power`` (1/mm; it adds ``−y·power`` to the ray's ``n·u``, as a
    diffractive surface does in any medium) ``distance`` mm after surface ``after``: a quadratic phase surface."""
    def phase(x, y, wavelength):
        k = 2 * math.pi / (wavelength * 1e-3)
        return -0.5 * k * power * (x * x + y * y), -k * power * x, -k * power * y

    return insert_doe(lens, after, distance, phase)


def _real_efl(lens: Lens, wavelength: float) -> float:
    """EFL (mm) from a collimated on-axis ray at 1e-4 of the entrance pupil's radius: ``−h / tan u`` in the image
    space medium (a distant object; inf for an afocal result)."""
    epd = float(lens.paraxial(wavelength).epd)
    h = 1e-4 * 0.5 * epd
    o = torch.tensor([[0.0, h, float(lens.vertex_z()[0].detach()) - 1.0]], dtype=torch.float64)
    rays = RayBundle.create(o, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([wavelength]))
    with torch.no_grad():
        out = lens.trace(rays, apertures=False)
    uy, uz = float(out.d[..., 1].reshape(-1)[0]), float(out.d[..., 2].reshape(-1)[0])
    return math.inf if uy == 0 else -h * uz / uy


def _model_summary(model: dict | None, wavelength: float) -> dict:
    """Type and paraxial data of a DOE's phase model at ``wavelength`` µm: a BINARY_2's ``power`` (1/mm,
    :func:`raywave.lens.prescription.binary2_power`), a grating's ``period`` (mm), orientation and first-order
    ``deflection_deg`` in air; other models their type only."""
    if model is None:
        return {"type": "blank"}
    t = model["type"]
    out: dict = {"type": t}
    if t == "binary_2":
        out["power"] = binary2_power(model, wavelength)
    elif t == "grating":
        out["period"] = float(model["period"])
        s = wavelength * 1e-3 / float(model["period"])
        out["deflection_deg"] = math.degrees(math.asin(s)) if abs(s) <= 1 else math.nan
        out["angle_deg"] = float(model.get("angle", 0.0))
    return out


def surface_doe_info(spec: dict, lens: Lens, wavelength: float | None = None) -> list[dict]:
    """One dict per DOE placed at a surface of ``spec`` (``lens``: its refractive lens), for ``raywave info``:
    ``surface`` (index), ``distance`` (mm after its vertex), ``z`` (mm from the first vertex), ``type`` (the phase
    model's, ``"phase map"`` or ``"blank"``), the pitch / size when given, and for a BINARY_2 its paraxial ``power``
    (1/mm), ``focal_length`` (mm) and ``efl_with_doe`` (mm: the lens with the DOE as a thin element of that power,
    traced with a paraxial-height real ray); a grating its ``period`` (mm) and first-order ``deflection_deg``."""
    wl = lens.primary_wavelength if wavelength is None else float(wavelength)
    zv = lens.vertex_z().detach()
    rows = []
    for after, distance, d in surface_doe_positions(spec):
        row = {"surface": after, "distance": distance, "z": float(zv[after]) + (distance or 0.0), "wavelength": wl,
               "conformal": distance is None}
        if d.get("phase") is not None:
            row["type"] = "phase map"
        else:
            row.update(_model_summary(d.get("phase_model"), wl))
        for k in ("pitch", "size", "shape", "aperture", "levels", "material"):
            if d.get(k) is not None:
                row[k] = d[k]
        if "power" in row:
            p = row["power"]
            row["focal_length"] = math.inf if p == 0 else 1.0 / p
            row["efl_with_doe"] = _real_efl(_with_thin_power(lens, after, distance, p), wl)
        rows.append(row)
    return rows
