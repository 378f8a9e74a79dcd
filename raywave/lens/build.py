"""Lens spec (the plain-dict lens-file form, docs/lens-format.md) <-> :class:`Lens`.

``raywave.io`` reads and writes files as specs without touching torch; this module turns a validated
spec into modules with real parameters, and a lens back into a spec (exact round trip).
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

from raywave.lens.fields import IMAGE_HEIGHT_TYPES, apply_image_height_fields
from raywave.lens.lens import Lens
from raywave.materials import get_material
from raywave.surfaces.aperture import aperture_from_spec
from raywave.surfaces.geometry import EvenAsphere, OddAsphere, Plane, Standard, Toroidal
from raywave.surfaces.interaction import CoordinateBreak, IdealLens, Reflection
from raywave.surfaces.surface import Surface


def _curvature(s: dict) -> float:
    if "curvature" in s:
        return float(s["curvature"])
    r = s.get("radius", "inf")
    if r == "inf" or (isinstance(r, float) and math.isinf(r)):
        return 0.0
    return 1.0 / float(r)


def _aspheric_list(asph: dict, first: int = 2, step: int = 2) -> list[float]:
    """{"a2":.., "a4":..} -> [a2, a4, ..., a_max] (zeros filled in); ``first=1, step=1``: [a1, a2, a3, ...]."""
    if not asph:
        return [0.0]
    top = max(int(k[1:]) for k in asph)
    return [float(asph.get(f"a{p}", 0.0)) for p in range(first, top + 1, step)]


def _rotation_curvature(r) -> float:
    """1 / radius of rotation of a toroid spec ("inf" -> 0)."""
    if r is None or r == "inf" or (isinstance(r, float) and math.isinf(r)):
        return 0.0
    return 1.0 / float(r)


def _is_mirror(m) -> bool:
    return isinstance(m, str) and m.lower() == "mirror"


def surface_from_spec(s: dict, catalogs=None, where: str = "surface", medium_before=None) -> Surface:
    """Build one :class:`Surface` from its spec dict.

    ``medium_before``: the :class:`~raywave.materials.base.Material` in front of the surface (default air). A mirror
    (``"material": "mirror"``) and a coordinate break keep it as the medium after them."""
    kind = s.get("type", "standard")
    if kind == "coordinate_break":
        if s.get("stop"):
            raise ValueError(f"{where}: a coordinate break cannot be the aperture stop")
        dec = s.get("decenter", [0.0, 0.0])
        tilt = s.get("tilt", [0.0, 0.0, 0.0])
        medium = medium_before if medium_before is not None else get_material("air")
        surf = Surface(Plane(), medium, float(s.get("thickness", 0.0)),
                       interaction=CoordinateBreak(dec[0], dec[1], tilt[0], tilt[1], tilt[2], s.get("order", 0)),
                       comment=s.get("comment", ""))
        return surf
    mirror = _is_mirror(s.get("material"))
    try:
        if mirror:
            material = medium_before if medium_before is not None else get_material("air")
        else:
            material = get_material(s.get("material", "air"), catalogs=catalogs)
    except (KeyError, ValueError) as err:
        new = type(err)(f"{where}: {err}")
        if getattr(err, "glass", None) is not None:  # an unknown glass keeps its name (load_lens finds its line)
            new.glass = err.glass
        raise new from None
    common = dict(
        thickness=float(s.get("thickness", 0.0)),
        aperture=aperture_from_spec(s.get("aperture")),
        is_stop=bool(s.get("stop", False)),
        semi_diameter=s.get("semi_diameter"),
        comment=s.get("comment", ""),
    )
    if kind == "standard":
        geom = Standard(_curvature(s), float(s.get("conic", 0.0)))
        surf = Surface(geom, material, **common)
    elif kind == "even_asphere":
        geom = EvenAsphere(_curvature(s), float(s.get("conic", 0.0)), _aspheric_list(s.get("aspheric", {})))
        surf = Surface(geom, material, **common)
    elif kind == "odd_asphere":
        geom = OddAsphere(_curvature(s), float(s.get("conic", 0.0)), _aspheric_list(s.get("aspheric", {}), 1, 1))
        surf = Surface(geom, material, **common)
    elif kind == "toroidal":
        geom = Toroidal(_curvature(s), float(s.get("conic", 0.0)), _rotation_curvature(s.get("radius_of_rotation")),
                        _aspheric_list(s.get("aspheric", {})))
        surf = Surface(geom, material, **common)
        surf._spec_rotation = s.get("radius_of_rotation")  # remembered for an exact round trip
    elif kind == "paraxial":
        surf = Surface(Plane(), material, interaction=IdealLens(float(s["focal_length"])), **common)
    else:
        raise ValueError(f"{where}: unknown surface type {kind!r}")
    if mirror:
        if kind == "paraxial":
            raise ValueError(f"{where}: a paraxial (ideal lens) surface cannot be a mirror")
        surf.interaction = Reflection()
    surf._spec_radius = s.get("radius")  # remembered for an exact round trip
    return surf


def lens_from_spec(spec: dict) -> Lens:
    """Build a :class:`Lens` from a (validated) lens spec."""
    catalogs = spec.get("catalogs")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        surfaces = []
        for i, s in enumerate(spec["surfaces"]):
            before = surfaces[-1].material if surfaces else None
            surfaces.append(surface_from_spec(s, catalogs, f"surfaces[{i}]", medium_before=before))
    seen = set()
    for w in caught:  # once per lens: a glass on several surfaces taken from an unnamed catalog warns once
        key = (w.category, str(w.message))
        if key not in seen:
            seen.add(key)
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    obj = spec.get("object", {}) or {}
    dist = obj.get("distance", "inf")
    dist = math.inf if dist == "inf" else float(dist)
    fields = spec.get("fields") or {"type": "angle", "values": [0.0]}
    field_type = fields.get("type", "angle")
    by_height = field_type in IMAGE_HEIGHT_TYPES
    wls = spec.get("wavelengths") or {"values": [0.4861327, 0.5875618, 0.6562725], "primary": 1}
    sensor = spec.get("sensor") or {}
    ap = spec.get("system_aperture") or None
    object_material = None
    if obj.get("material") is not None:
        try:
            object_material = get_material(obj["material"], catalogs=catalogs)
        except (KeyError, ValueError) as err:
            raise type(err)(f"object: {err}") from None
    lens = Lens(
        surfaces,
        object_distance=dist,
        object_material=object_material,
        fields=[0.0] if by_height else fields["values"],
        field_type=("angle" if math.isinf(dist) else "object_height") if by_height else field_type,
        wavelengths=wls["values"],
        primary=int(wls.get("primary", 0)),
        sensor_size=sensor.get("size"),
        sensor_resolution=sensor.get("resolution"),
        name=spec.get("name", ""),
        catalogs=catalogs,
        system_aperture=ap,
    )
    lens._spec_extra = {k: spec[k] for k in ("description",) if k in spec}
    if obj.get("curvature"):
        lens.object_curvature = float(obj["curvature"])
    lens.image_curvature = float((spec.get("image") or {}).get("curvature", 0.0))
    if by_height:  # solved on the finished lens: real image heights need its real chief rays
        apply_image_height_fields(lens, field_type, fields["values"], where=spec.get("name") or "lens")
    return lens


def _radius_entry(surface: Surface) -> dict:
    """'radius' when it round-trips exactly through the curvature, else 'curvature'."""
    c = float(surface.geometry.curvature.detach())
    if c == 0.0:
        return {"radius": "inf"}
    r = 1.0 / c
    remembered = getattr(surface, "_spec_radius", None)
    if isinstance(remembered, (int, float)) and 1.0 / float(remembered) == c:
        return {"radius": float(remembered)}
    if 1.0 / r == c:
        return {"radius": r}
    return {"curvature": c}


def surface_to_spec(surface: Surface) -> dict:
    """One surface as its spec dict.

    Raises:
        ValueError: the surface carries an interaction a lens file cannot describe (a ray-tracing
            ``Diffraction`` phase: save its DOE separately, see docs/lens-format.md "DOE").
    """
    if surface.interaction.kind == "coordinate_break":
        out = {"type": "coordinate_break", **surface.interaction.to_spec(),
               "thickness": float(surface.thickness.detach())}
        if surface.comment:
            out["comment"] = surface.comment
        return out
    if surface.interaction.kind not in ("refraction", "ideal_lens", "reflection"):
        raise ValueError(f"surface {surface.comment or ''!s}: its {surface.interaction.kind!r} interaction has no "
                         "lens-file form; writing it would silently drop the phase (save the DOE on its own, or "
                         "describe it in the file's \"doe\" section)")
    out: dict = {"type": surface.kind}
    g = surface.geometry
    if surface.kind == "paraxial":
        out["focal_length"] = float(surface.interaction.focal_length.detach())
    else:
        out.update(_radius_entry(surface))
        out["conic"] = float(g.conic.detach())
        if surface.kind == "toroidal":
            cr = float(g.rotation_curvature.detach())
            remembered = getattr(surface, "_spec_rotation", None)
            if cr == 0.0:
                out["radius_of_rotation"] = "inf"
            elif isinstance(remembered, (int, float)) and remembered != 0 and 1.0 / float(remembered) == cr:
                out["radius_of_rotation"] = float(remembered)
            else:
                out["radius_of_rotation"] = 1.0 / cr
        if surface.kind in ("even_asphere", "toroidal"):
            coeffs = g.coefficients.detach().tolist()
            out["aspheric"] = {f"a{2 * (i + 1)}": float(a) for i, a in enumerate(coeffs)}
        elif surface.kind == "odd_asphere":
            coeffs = g.coefficients.detach().tolist()
            out["aspheric"] = {f"a{i + 1}": float(a) for i, a in enumerate(coeffs)}
    out["thickness"] = float(surface.thickness.detach())
    out["material"] = "mirror" if surface.interaction.kind == "reflection" else surface.material.to_spec()
    out["aperture"] = None if surface.aperture is None else surface.aperture.to_spec()
    if surface.semi_diameter is not None:
        out["semi_diameter"] = float(surface.semi_diameter)
    out["stop"] = surface.is_stop
    if surface.comment:
        out["comment"] = surface.comment
    return out


def lens_to_spec(lens: Lens) -> dict:
    """The lens as a spec dict (raywave-lens format, version 1)."""
    spec: dict = {"format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"}}
    if lens.name:
        spec["name"] = lens.name
    spec.update(getattr(lens, "_spec_extra", {}))
    if lens.catalogs:
        spec["catalogs"] = list(lens.catalogs)
    spec["object"] = {"distance": "inf" if math.isinf(lens.object_distance) else lens.object_distance}
    if not lens.object_material.is_air:
        spec["object"]["material"] = lens.object_material.to_spec()
    if getattr(lens, "object_curvature", 0.0):
        spec["object"]["curvature"] = lens.object_curvature
    if getattr(lens, "image_curvature", 0.0):
        spec["image"] = {"curvature": lens.image_curvature}
    if lens.system_aperture:
        spec["system_aperture"] = dict(lens.system_aperture)
    elif lens.epd is not None:
        spec["system_aperture"] = {"epd": lens.epd}
    definition = getattr(lens, "field_definition", None)
    spec["fields"] = dict(definition) if definition else {"type": lens.field_type, "values": list(lens.fields)}
    spec["wavelengths"] = {"values": list(lens.wavelengths), "primary": lens.primary}
    if lens.sensor_size is not None:
        spec["sensor"] = {"size": list(lens.sensor_size), "resolution": list(lens.sensor_resolution or (0, 0))}
    spec["surfaces"] = [surface_to_spec(s) for s in lens.surfaces]
    return spec


class SurfaceDOEWarning(UserWarning):
    """A lens file places a DOE at a surface (inside the lens, issue 46), which the refractive :class:`Lens` of
    :func:`load_lens` leaves out: ``raywave.load_midsystem`` builds the lens with it."""


def clip_at_semi_diameters(spec: dict) -> dict:
    """The lens spec ``spec`` with each surface's semi-diameter made a hard circular aperture, as a lens's mounts
    and element rims vignette (OpticStudio's "convert semi-diameters to circular apertures"). A semi-diameter
    alone does not clip (OpticStudio's convention, and raywave's): a fast camera lens's file then passes rays
    outside its elements off axis, up to ~70° steep behind the lens, whose Nyquist pitch asks for a DOE grid of
    terabytes. Surfaces that have an aperture (a stop, an obscuration), the stop (sized by the system aperture)
    and coordinate breaks keep theirs; surfaces without a semi-diameter get none. The on-axis beam is never cut: a
    circle is at least the on-axis rim rays' height there (every wavelength), so the stop stays the aperture stop
    on axis where a file's semi-diameter is a rounding below its beam (the Nikkor 50 mm F/1.4 would lose 0.1 % of
    its on-axis pupil, and its default DOE pitch move 0.54 → 0.65 µm). Returns a new spec (``spec`` is not
    changed); see :func:`load_lens` (``clip_apertures=True``)."""
    heights = _on_axis_heights(spec)
    out = dict(spec)
    surfaces = []
    for i, s in enumerate(spec.get("surfaces", [])):
        sd = s.get("semi_diameter") if isinstance(s, dict) else None
        if (isinstance(s, dict) and s.get("aperture") is None and not s.get("stop")
                and s.get("type") != "coordinate_break" and isinstance(sd, (int, float)) and math.isfinite(sd)
                and sd > 0):
            h = heights[i] if heights is not None and math.isfinite(heights[i]) else 0.0
            s = dict(s, aperture={"shape": "circle", "radius": max(float(sd), h)})
        surfaces.append(s)
    out["surfaces"] = surfaces
    return out


def _on_axis_heights(spec: dict) -> list[float] | None:
    """The on-axis beam's rim height (mm) per surface of the lens of ``spec`` at every wavelength
    (:func:`raywave.lens.prescription.ray_heights`; NaN where no ray passes), or None where it cannot be traced (a
    folded lens). The lens is built with one on-axis field only: no real image height is solved."""
    from raywave.lens.prescription import ray_heights

    finite = (spec.get("object") or {}).get("distance", "inf") != "inf"
    probe = dict(spec, fields={"type": "object_height" if finite else "angle", "values": [0.0]})
    with warnings.catch_warnings():
        # a probe of the same spec: the lens's own warnings (glasses, geometry) come from the real build right after
        # it, the reader's came when the file was read, and ray_heights leaves vignetted rays out by their mask
        warnings.simplefilter("ignore")
        return ray_heights(lens_from_spec(probe), fields=[0.0])


def load_lens(path: str | Path, config: int | None = None, *, clip_apertures: bool = False) -> Lens:
    """Read any lens file raywave knows (.json raywave or DeepLens-style, .zmx), or a bundled lens by name
    (``"cooke_triplet"``, see :func:`bundled_lens_path`), into a :class:`Lens`.

    ``config``: the configuration of a multi-configuration .zmx file (1-based; default 1, reported in a warning).
    ``clip_apertures``: vignette at every surface's semi-diameter (:func:`clip_at_semi_diameters`; default off, as
    OpticStudio). A DOE placed at a surface (a surface's ``"doe"``, a ``.zmx`` BINARY_2 / DGRATING inside the lens)
    is not part of the refractive lens: :class:`SurfaceDOEWarning` names the surfaces that carry one."""
    from raywave.io import read_lens_spec
    from raywave.io.errors import with_location

    path = resolve_lens_path(path)
    spec = read_lens_spec(path) if config is None else read_lens_spec(path, config=config)
    try:
        if clip_apertures:
            spec = clip_at_semi_diameters(spec)
        lens = lens_from_spec(spec)
    except ValueError as err:  # a spec that validates but builds no lens: name the file
        raise with_location(_with_glass_line(err, path), path)
    _warn_surface_does(spec, path)
    _warn_stop_clear_aperture(lens, path)
    return lens


def _warn_stop_clear_aperture(lens: Lens, path) -> None:
    """A :class:`~raywave.io.errors.LensFileWarning` (``path:LINE:`` of the stop's CLAP in a .zmx file) where the
    stop's own clear aperture is smaller than the stop radius the system aperture gives it: which sets what."""
    from raywave.io.errors import LensFileWarning

    if lens.paraxial_stop_radius is None:
        return
    r_own, r_sys = lens.stop_radius(), lens.paraxial_stop_radius
    (kind, value), = lens.system_aperture.items()
    p = lens.paraxial()
    beam = lens.epd * r_own / r_sys
    warnings.warn(LensFileWarning(
        f"{path}{_stop_clap_line(path)}: the stop (surface {lens.stop_index}) has its own clear aperture of radius "
        f"{r_own:.6g} mm, smaller than the {r_sys:.6g} mm the system aperture ({kind} {value:g}) gives it: the "
        f"system aperture sets the paraxial pupil (EPD {p.epd:.6g} mm, F/# {p.fnum:.4g}), the stop's clear aperture "
        f"is its hard edge (the rays beyond it are vignetted at the stop; the beam fills an entrance pupil "
        f"{beam:.6g} mm wide), as OpticStudio does"), stacklevel=3)


def _stop_clap_line(path) -> str:
    """``":LINE"`` of the clear-aperture line (CLAP) of the stop's SURF block of a .zmx file, else ``""``."""
    from raywave.io.zmx.tokens import decode_zmx_bytes

    if Path(path).suffix.lower() != ".zmx":
        return ""
    try:
        text, _ = decode_zmx_bytes(Path(path).read_bytes())
    except OSError:
        return ""
    stop, clap = False, None
    for ln, line in enumerate(text.splitlines(), start=1):
        key = line.split("!", 1)[0].split()[:1]
        if key == ["SURF"]:
            if stop and clap:
                break
            stop, clap = False, None
        elif key == ["STOP"]:
            stop = True
        elif key == ["CLAP"]:
            clap = ln
    return f":{clap}" if stop and clap else ""


def _warn_surface_does(spec: dict, path) -> None:
    """:class:`SurfaceDOEWarning` naming the surfaces of ``spec`` that carry a ``"doe"``, if any."""
    inside = [i for i, s in enumerate(spec.get("surfaces", [])) if isinstance(s, dict) and s.get("doe")]
    if inside:
        where = ", ".join(str(i) for i in inside)
        warnings.warn(SurfaceDOEWarning(
            f"{path}: surface{'s' if len(inside) > 1 else ''} {where} carr{'y' if len(inside) > 1 else 'ies'} a DOE "
            "inside the lens, which this refractive lens leaves out (its rays do not see it): "
            "raywave.load_midsystem builds the lens with it"), stacklevel=3)


def _with_glass_line(err: Exception, path) -> Exception:
    """``err`` (an unknown glass, whose ``glass`` attribute names it) prefixed with ``path:LINE:`` of the first line
    of the lens file that names the glass (a .zmx GLAS line, a .seq surface line); other errors unchanged."""
    from raywave.io.zmx.tokens import decode_zmx_bytes

    name = getattr(err, "glass", None)
    if not name or not err.args or not isinstance(err.args[0], str) or Path(path).suffix.lower() == ".json":
        return err
    try:
        text, _ = decode_zmx_bytes(Path(path).read_bytes())
    except OSError:
        return err
    pat = re.compile(r"(?<![\w-])" + re.escape(name) + r"(?![\w-])", re.IGNORECASE)
    for ln, line in enumerate(text.splitlines(), start=1):
        if pat.search(line.split("!", 1)[0]):
            err.args = (f"{path}:{ln}: {err.args[0]}",) + tuple(err.args[1:])
            break
    return err


def save_lens(lens: Lens, path: str | Path) -> None:
    """Write ``lens`` as raywave JSON (.json) or Zemax (.zmx), by extension."""
    from raywave.io import write_lens_spec

    write_lens_spec(lens_to_spec(lens), path)


BUNDLED = Path(__file__).resolve().parent.parent / "data" / "lenses"


def bundled_lens_path(name: str) -> Path:
    """Path of a bundled example lens ('singlet', 'cooke_triplet', 'double_gauss', 'asphere_hk51',
    'hybrid_asphere')."""
    p = BUNDLED / f"{name}.json"
    if not p.exists():
        avail = sorted(q.stem for q in BUNDLED.glob("*.json"))
        raise FileNotFoundError(f"no bundled lens {name!r}; available: {', '.join(avail)}")
    return p


def resolve_lens_path(name_or_path: str | Path) -> Path:
    """A file path, or the name of a bundled lens (a folder of that name, e.g. a run folder, is not a lens file)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    if p.suffix == "" and (BUNDLED / f"{p.name}.json").exists():
        return BUNDLED / f"{p.name}.json"
    raise FileNotFoundError(f"lens file {str(name_or_path)!r} not found (nor a bundled lens of that name)")


def ideal_lens(focal_length: float, f_number: float | None = None, radius: float | None = None,
               wavelengths=(0.55,), sensor_distance: float | None = None, **lens_kwargs) -> Lens:
    """A perfect thin lens (Zemax paraxial surface) of ``focal_length`` mm, which is also the stop.

    Give the pupil as ``f_number`` (= f / D) or ``radius`` (mm). The sensor sits ``sensor_distance`` after
    it (default: at the focus). Its PSF for a distant on-axis point is the aberration-free Airy/Debye pattern,
    a ground truth for the ray-wave model (phase-exact for collimated light at any field angle)."""
    if (f_number is None) == (radius is None):
        raise ValueError("give exactly one of f_number and radius")
    r = radius if radius is not None else abs(focal_length) / (2.0 * f_number)
    from raywave.surfaces.aperture import CircularAperture

    surf = Surface(Plane(), get_material("AIR"), focal_length if sensor_distance is None else sensor_distance,
                   aperture=CircularAperture(r), interaction=IdealLens(focal_length), is_stop=True,
                   comment="ideal lens")
    return Lens([surf], wavelengths=wavelengths, primary=0, name=f"ideal f={focal_length:g}", **lens_kwargs)
