"""Lens commands: info, layout, spot, convert, demo."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from raywave.cli.errors import CommandError, integer_arg, json_dumps, wavelength_arg
from raywave.cli.fields import add_field_arguments, field_list
from raywave.cli.psf_commands import add_clip_apertures_argument


def _load(name_or_path, config=None, clip_apertures: bool = False):
    """The lens of a file or bundled name; ``config``: the configuration of a multi-configuration .zmx file
    (``--config N``, 1-based; default 1); ``clip_apertures``: vignette at the semi-diameters
    (``--clip-apertures``)."""
    from raywave.lens.build import load_lens, resolve_lens_path

    if config is not None:
        config = integer_arg(config, "--config")
        if config < 1:
            raise CommandError(f"--config: configurations are numbered from 1, got {config}")
    return load_lens(resolve_lens_path(name_or_path), config=config, clip_apertures=clip_apertures)


def _load_shown(args, inside_doe: bool = False):
    """:func:`_load` of ``args.lens`` (``--config``) under a ticking bar: solving a file's real-image-height fields
    can take a minute on a fisheye, and no command stays silent that long (``--quiet`` hides it). ``inside_doe``:
    the command shows a DOE inside the lens itself (no :class:`~raywave.lens.build.SurfaceDOEWarning`)."""
    import warnings

    from raywave.cli.progress import bar, ticking
    from raywave.lens.build import SurfaceDOEWarning

    with bar(args, 1, "lens", "reading the lens (solving its fields)") as pbar, ticking(pbar), \
            warnings.catch_warnings():
        if inside_doe:
            warnings.simplefilter("ignore", SurfaceDOEWarning)
        lens = _load(args.lens, getattr(args, "config", None), getattr(args, "clip_apertures", False))
        pbar.update(1)
    return lens


def _y_fields(args, command: str):
    """The ``--field`` / ``--fields`` of a command that draws the meridional (y-z) section: Y values (None: the
    lens's fields); an X other than 0 is a :class:`CommandError`."""
    fields = field_list(args)
    if fields is None:
        return None
    if any(x != 0 for x, _ in fields):
        raise CommandError(f"--field: {command} draws the meridional (y-z) section: give Y values only, got "
                           + ", ".join(f"{x:g},{y:g}" for x, y in fields if x != 0))
    return [y for _, y in fields]


def _spot_fields(args):
    """The fields of ``spot``: Y values when every X is 0 (the table's rows), else (x, y) pairs; None: the lens's."""
    fields = field_list(args)
    if fields is None or all(x == 0 for x, _ in fields):
        return None if fields is None else [y for _, y in fields]
    return [list(f) for f in fields]


def png_path(output, default_name: str) -> Path:
    """``-o`` of a command that writes one PNG: a ``.png`` file as given, else a folder (created) that receives
    ``default_name``; another suffix is a :class:`CommandError`."""
    out = Path(output)
    if out.suffix.lower() == ".png":
        return out
    if out.suffix and not out.is_dir():
        raise CommandError(f"-o: give a .png file or a folder, got {str(output)!r}")
    out.mkdir(parents=True, exist_ok=True)
    return out / default_name


def _wavelength(text):
    return None if text is None else wavelength_arg(text, "--wavelength")


# ---------------------------------------------------------------------------- info
INFO_KEYS = ["efl", "efl_real", "bfl", "ffl", "fnum", "epd", "ep_z", "xpd", "xp_z", "fov_deg", "image_height", "total_track"]
INFO_LABELS = {
    "efl": ("Effective focal length (paraxial)", "mm"),
    "efl_real": ("Effective focal length (real ray)", "mm"),
    "bfl": ("Back focal length (last vertex to focus)", "mm"),
    "ffl": ("Front focal point z", "mm"),
    "fnum": ("F-number (EFL / EPD)", ""),
    "working_fnum": ("Working F-number", ""),
    "epd": ("Entrance pupil diameter", "mm"),
    "ep_z": ("Entrance pupil z", "mm"),
    "xpd": ("Exit pupil diameter", "mm"),
    "xp_z": ("Exit pupil z", "mm"),
    "fov_deg": ("Full field of view", "deg"),
    "image_height": ("Paraxial image height", "mm"),
    "total_track": ("Total track (first vertex to image)", "mm"),
    "image_z_paraxial": ("Paraxial image z", "mm"),
}


def lens_info(lens, wavelength: float | None = None) -> dict:
    """The paraxial table plus the real-ray EFL (mm, degrees; z from the first vertex)."""
    from raywave.lens.analysis import real_ray_efl

    p = lens.paraxial(wavelength)
    d = p.as_dict()
    notes = []
    try:
        with torch.no_grad():
            d["efl_real"] = float(real_ray_efl(lens, wavelength))
    except ValueError as err:  # e.g. a central obscuration blocks the near-axis ray: say so, print the rest
        d["efl_real"] = math.nan
        notes.append(f"real-ray EFL: {err}")
    out = {k: d[k] for k in INFO_KEYS}
    if notes:
        out["notes"] = notes
    out.update({k: d[k] for k in ("working_fnum", "image_z_paraxial", "wavelength")})
    out["name"] = lens.name
    out["section"] = p.section
    return out


def field_table(lens) -> list[dict]:
    """Per field of the lens: the field angle (degrees: of the real chief ray in object space), the object height (mm,
    finite object), the real chief ray's image height (mm, at the primary wavelength, on the image surface) and the
    paraxial image height (mm), plus the file's own definition (an image height) when it has one. Values that
    cannot be computed (a vignetted chief ray, no paraxial model) are NaN."""
    from raywave.lens.fields import paraxial_image_height_per_field
    from raywave.lens.sources import chief_ray

    fields = [float(f) for f in lens.fields]
    f = torch.tensor([[0.0, v] for v in fields], dtype=torch.float64, device=lens.device)
    with torch.no_grad():
        rays = chief_ray(lens, f, [lens.primary_wavelength])
        out = lens.image_coordinates(lens.trace_to_image(rays))
    try:
        k = paraxial_image_height_per_field(lens)
    except ValueError:
        k = math.nan
    rows = []
    definition = getattr(lens, "field_definition", None) or {}
    for i, v in enumerate(fields):
        d = rays.d[i, 0, 0]
        angle = math.degrees(math.atan2(math.hypot(float(d[0]), float(d[1])), float(d[2]))) * (1 if float(d[1]) >= 0 else -1)
        row = {"field": v, "angle_deg": angle if lens.field_type != "angle" else v}
        if lens.field_type == "object_height":
            row["object_height_mm"] = v
        ok = bool(out.valid[i, 0, 0])
        row["real_image_height_mm"] = float(out.o[i, 0, 0, 1]) if ok else math.nan
        row["paraxial_image_height_mm"] = k * (math.tan(math.radians(v)) if lens.field_type == "angle" else v)
        if lens.field_type == "angle" and abs(v) >= 90.0:  # a fisheye's field beyond 90°: no paraxial image
            row["paraxial_image_height_mm"] = math.nan
        if definition.get("values") is not None and i < len(definition["values"]):
            row[definition["type"] + "_mm"] = float(definition["values"][i])
        rows.append(row)
    return rows


def format_field_table(lens, rows: list[dict]) -> str:
    """The field table as text: one line per field, in degrees and in image height."""
    definition = getattr(lens, "field_definition", None)
    how = (f"defined by {definition['type'].replace('_', ' ')} (file)" if definition else
           f"defined by {'angle' if lens.field_type == 'angle' else 'object height'}")
    lines = [f"  Fields ({how}; chief rays at {lens.primary_wavelength:g} µm):"]
    head = f"    {'#':>2s} {'angle (deg)':>12s}"
    if lens.field_type == "object_height":
        head += f" {'object h (mm)':>14s}"
    head += f" {'real image h (mm)':>18s} {'paraxial image h (mm)':>22s}"
    lines.append(head)
    for i, r in enumerate(rows):
        line = f"    {i + 1:>2d} {r['angle_deg']:>12.6f}"
        if lens.field_type == "object_height":
            line += f" {r['object_height_mm']:>14.6f}"
        line += f" {r['real_image_height_mm']:>18.6f} {r['paraxial_image_height_mm']:>22.6f}"
        lines.append(line)
    return "\n".join(lines)


def format_info(info: dict) -> str:
    lines = [f"{info.get('name') or 'lens'} at {info['wavelength']:g} µm (z from the first vertex)"]
    if info.get("section", "rotational") != "rotational":
        lines.append("  (not rotationally symmetric: paraxial values of the y-z section; the x-z section differs)")
    for k in INFO_KEYS + ["working_fnum", "image_z_paraxial"]:
        label, unit = INFO_LABELS[k]
        v = info[k]
        shown = "n/a" if math.isnan(v) else "inf"
        lines.append(f"  {label:<42s} {v:>14.6f} {unit}" if math.isfinite(v) else f"  {label:<42s} {shown:>14s} {unit}")
    lines += [f"  note: {n}" for n in info.get("notes", [])]
    return "\n".join(lines)


def _no_paraxial_reason(lens, wavelength) -> str | None:
    """Why a tilted or decentred lens has no paraxial data (the paraxial trace's own message), or None."""
    if not lens.is_folded:
        return None
    try:
        lens.paraxial(wavelength)
    except ValueError as err:
        return str(err)
    return None


def real_ray_info(lens, wavelength: float | None = None) -> dict:
    """What real rays say of a lens without paraxial data (tilted or decentred): per field the chief ray's image
    point (x, y mm in the image plane's frame) and, for the first field, the real-ray working F/# 1 / (2 n' sin θ')
    from the four marginal rays through the stop's rim (±x, ±y), θ' their mean angle to the chief ray in image space.
    Rays are aimed at the stop by Newton iteration from the first vertex plane (no paraxial pupil)."""
    from raywave.lens.sources import _newton_aim, rays_through

    wl = lens.primary_wavelength if wavelength is None else float(wavelength)
    fields = torch.tensor([[0.0, float(f)] for f in (list(lens.fields) or [0.0])], dtype=torch.float64,
                          device=lens.device)
    r = lens.stop_radius()
    target = torch.tensor([[0.0, 0.0], [r, 0.0], [-r, 0.0], [0.0, r], [0.0, -r]], dtype=torch.float64,
                          device=lens.device).expand(len(fields), 1, 5, 2)
    wls = torch.tensor([wl], dtype=torch.float64, device=lens.device)
    with torch.no_grad():
        uv, ok = _newton_aim(lens, target.clone(), target, fields, lens.field_type, wls, 1e-6 * max(r, 1.0), ep_z=0.0)
        out = lens.image_coordinates(lens.trace_to_image(rays_through(lens, uv, fields, lens.field_type, wls,
                                                                      ep_z=0.0)))
        ok = ok & out.valid
        d = out.d[0, 0]
        sin_t = torch.linalg.vector_norm(torch.linalg.cross(d[1:], d[:1].expand(4, 3)), dim=-1)
        n_img = float(lens.surfaces[-1].material.n(wl))
    fnum = 1.0 / (2.0 * n_img * float(sin_t.mean())) if bool(ok[0, 0].all()) else math.nan
    chief = [[float(v) for v in out.o[i, 0, 0, :2]] if bool(ok[i, 0, 0]) else None for i in range(len(fields))]
    return {"name": lens.name, "wavelength": wl, "fields": [float(f[1]) for f in fields],
            "field_type": lens.field_type, "chief_image_xy": chief, "fnum_real": fnum}


def format_real_ray_info(info: dict, reason: str) -> str:
    unit = "deg" if info["field_type"] == "angle" else "mm"
    lines = [f"{info.get('name') or 'lens'} at {info['wavelength']:g} µm: no paraxial data", f"  ({reason})",
             "  Real rays (chief rays aimed at the stop's centre):",
             f"  {'field (' + unit + ')':>14s} {'image x (mm)':>14s} {'image y (mm)':>14s}"]
    for f, xy in zip(info["fields"], info["chief_image_xy"]):
        lines.append(f"  {f:>14g} " + (f"{xy[0]:>14.6f} {xy[1]:>14.6f}" if xy else f"{'vignetted':>29s}"))
    fn = info["fnum_real"]
    lines.append(f"  {'Real-ray working F/# (first field)':<42s} " + (f"{fn:>14.6f}" if math.isfinite(fn) else
                                                                        f"{'n/a':>14s}"))
    return "\n".join(lines)


def prescription_rows(lens, wavelength=None) -> list[dict]:
    """The surface table (:func:`raywave.lens.prescription.surface_table`) as JSON-ready dicts."""
    from dataclasses import asdict

    from raywave.lens.prescription import surface_table

    return [asdict(r) for r in surface_table(lens, wavelength)]


def lens_file_doe(path) -> dict | None:
    """The ``"doe"`` section of the lens file (or bundled lens) ``path``, None without one."""
    from raywave.io import read_lens_spec
    from raywave.lens.build import resolve_lens_path

    return read_lens_spec(resolve_lens_path(path)).get("doe") or None


def doe_power_info(path, lens, wavelength=None) -> dict | None:
    """The DOE of the lens file ``path`` (its spec's ``"doe"``): None without one; else a dict with ``"note"`` and,
    for a BINARY_2 DOE, its paraxial ``power`` (1/mm), ``focal_length`` and the ``efl_with_doe`` (mm)
    (:func:`raywave.lens.prescription.doe_power`); a phase map's power is not paraxial data (excluded, said so)."""
    from raywave.lens.prescription import doe_power

    doe = lens_file_doe(path)
    if not doe:
        return None
    p = doe_power(lens, doe, wavelength)
    if p is None:
        return {"distance": float(doe.get("distance", 0.0)),
                "note": "the DOE (a phase map) is excluded from the paraxial table: its power is not paraxial data"}
    return {"distance": p.distance, "wavelength": p.wavelength, "power": p.power, "focal_length": p.focal_length,
            "efl_with_doe": p.efl,
            "note": "the paraxial table above is the refractive lens alone; the BINARY_2 DOE's power is added here"}


def surface_doe_rows(path, lens, wavelength=None) -> list[dict]:
    """The DOEs placed inside the lens of the file ``path`` (a surface's ``"doe"``; a .zmx BINARY_2 / DGRATING
    surface inside the lens): :func:`raywave.assembly.midsystem.surface_doe_info` (surface index, distance after
    its vertex, z, type, a BINARY_2's paraxial power and the EFL with it); empty without one."""
    from raywave.assembly.midsystem import surface_doe_info
    from raywave.io import read_lens_spec
    from raywave.lens.build import resolve_lens_path

    spec = read_lens_spec(resolve_lens_path(path))
    return surface_doe_info(spec, lens, wavelength)


def format_surface_does(rows: list[dict]) -> str:
    """The ``raywave info`` lines of the DOEs inside the lens (:func:`surface_doe_rows`)."""
    lines = []
    for r in rows:
        place = ("on the surface itself (conformal: its phase on the sag)" if r.get("conformal") else
                 f"{r['distance']:g} mm after its vertex")
        head = f"DOE inside the lens at surface {r['surface']}, {place} (z {r['z']:g} mm): {r['type']}"
        if r.get("aperture") and r.get("size"):
            head += f", {r['aperture']} {r['size'][0]:g} × {r['size'][1]:g} mm"
        lines.append(head)
        if "power" in r:
            lines.append(f"  {'DOE paraxial power (BINARY_2, order M)':<42s} {r['power']:>14.6g} 1/mm")
            lines.append(f"  {'DOE focal length':<42s} {r['focal_length']:>14.6f} mm")
            lines.append(f"  {'Effective focal length, lens + DOE':<42s} {r['efl_with_doe']:>14.6f} mm")
            lines.append("  (the tables above are the refractive lens alone; the DOE's power is added here)")
        elif "period" in r:
            lines.append(f"  {'grating period':<42s} {r['period'] * 1e3:>14.6g} µm")
            lines.append(f"  {'first-order deflection in air':<42s} {r['deflection_deg']:>14.6f} deg "
                         f"(toward {r['angle_deg']:g}° from +x)")
        else:
            lines.append("  (no paraxial power: the tables above are the refractive lens alone)")
    return "\n".join(lines)


def format_doe_power(d: dict) -> str:
    lines = [f"DOE plane {d['distance']:g} mm after the last surface: {d['note']}"]
    if "power" in d:
        lines.append(f"  {'DOE paraxial power (BINARY_2, order M)':<42s} {d['power']:>14.6g} 1/mm")
        lines.append(f"  {'DOE focal length':<42s} {d['focal_length']:>14.6f} mm")
        lines.append(f"  {'Effective focal length, lens + DOE':<42s} {d['efl_with_doe']:>14.6f} mm")
    return "\n".join(lines)


def cmd_info(args) -> int:
    from raywave.lens.prescription import table

    lens = _load_shown(args, inside_doe=True)  # a DOE inside the lens: its own block below
    wl = _wavelength(args.wavelength)
    reason = _no_paraxial_reason(lens, wl)
    if reason is not None:  # tilted / decentred: what real rays tell
        info = real_ray_info(lens, wl)
        print(json_dumps(dict(info, paraxial=None, reason=reason)) if args.json else format_real_ray_info(info, reason))
        return 0
    info = lens_info(lens, wl)
    doe = doe_power_info(args.lens, lens, wl)
    inside = surface_doe_rows(args.lens, lens, wl)
    if args.json:
        out = {k: info[k] for k in INFO_KEYS}
        out["surfaces"] = prescription_rows(lens, wl)
        if doe is not None:
            out["doe"] = doe
        if inside:
            out["surface_does"] = inside
        print(json_dumps(out))
    else:
        print(format_info(info))
        try:
            print(format_field_table(lens, field_table(lens)))
        except ValueError as err:  # no chief ray to trace (e.g. a lens whose paraxial pupil is undefined)
            print(f"  Fields: {', '.join(f'{v:g}' for v in lens.fields)} "
                  f"({'deg' if lens.field_type == 'angle' else 'mm'}); no chief-ray table: {err}")
        print(table(lens, wl))
        if doe is not None:
            print(format_doe_power(doe))
        if inside:
            print(format_surface_does(inside))
    return 0


# ---------------------------------------------------------------------------- layout / spot
def _inside_doe_parts(path):
    """``(lens, doe, after, distance)`` of the file ``path``'s DOE inside the lens
    (:func:`raywave.assembly.midsystem.does_lens`; with several DOEs, lists of them and of their places), or None
    when no surface carries a DOE."""
    from raywave.assembly.midsystem import does_lens, surface_doe_positions
    from raywave.io import read_lens_spec
    from raywave.lens.build import resolve_lens_path

    p = resolve_lens_path(path)
    spec = read_lens_spec(p)
    if not surface_doe_positions(spec):
        return None
    lens, does, afters, distances = does_lens(spec, str(p), p.parent)
    return (lens, does[0], afters[0], distances[0]) if len(does) == 1 else (lens, does, afters, distances)


def _lens_with_inside_doe(path, wavelength: float | None = None):
    """The lens of the file ``path`` with its DOE inside the lens in place (the strongest order at ``wavelength``,
    default the primary: :func:`raywave.assembly.midsystem.lens_with_doe`), or None when no surface carries a
    DOE."""
    from raywave.assembly.midsystem import lens_with_doe

    parts = _inside_doe_parts(path)
    return None if parts is None else lens_with_doe(*parts, wavelength=wavelength)


def cmd_layout(args) -> int:
    from raywave.plotting import plot_layout

    fields = _y_fields(args, "layout")
    out = png_path(args.output, "layout.png")
    lens = _load_shown(args, inside_doe=True)
    inside = _lens_with_inside_doe(args.lens)  # a DOE inside the lens (issue 46): drawn where it sits, rays bent
    if inside is not None:
        lens = inside
    plot_layout(lens, out, fields=fields, n_rays=integer_arg(args.rays, "--rays"), doe=lens_file_doe(args.lens))
    print(f"wrote {out}")
    return 0


def spot_table(lens, fields=None, lens_at=None) -> dict:
    """RMS spot radius (µm) per field and wavelength, about each spot's centroid; ``None`` (JSON null) where every
    ray is vignetted, and those (field, wavelength) pairs listed under ``"vignetted"``. ``lens_at``: a callable
    ``wavelength (µm) -> Lens`` giving the lens each wavelength's rays see (a DOE inside the lens: its strongest
    order at that wavelength); default ``lens`` for all."""
    import warnings

    from raywave.lens.analysis import rms_spot_radius
    from raywave.lens.sources import VignettingWarning

    fields = list(lens.fields) if fields is None else list(fields)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # reported in the table ("vignetted")
        if lens_at is None:
            rms = rms_spot_radius(lens, fields, lens.wavelengths)
        else:
            rms = torch.cat([rms_spot_radius(lens_at(w), fields, [w]) for w in lens.wavelengths], 1)
    rows = [[None if math.isnan(v) else v * 1e3 for v in row] for row in rms.tolist()]
    return {
        "unit": "um",
        "fields": fields,
        "field_type": lens.field_type,
        "wavelengths": list(lens.wavelengths),
        "rms_radius": rows,
        "vignetted": [[f, w] for f, row in zip(fields, rows) for w, v in zip(lens.wavelengths, row) if v is None],
    }


def cmd_spot(args) -> int:
    fields = _spot_fields(args)
    out = None if not args.output else png_path(args.output, "spot.png")
    lens = _load_shown(args, inside_doe=True)
    parts = _inside_doe_parts(args.lens)  # a DOE inside the lens (issue 46): the rays see its strongest order
    lens_at = None
    if parts is not None:
        from raywave.assembly.midsystem import lens_with_doe

        def lens_at(w):
            return lens_with_doe(*parts, wavelength=w)
    table = spot_table(lens, fields, lens_at)
    if parts is not None:
        table["doe_inside"] = {"surface": parts[2], "distance": parts[3],
                               "note": "each wavelength's rays carry the DOE's strongest order at that wavelength"}
    if args.json:
        print(json_dumps(table))
    else:
        unit = "deg" if lens.field_type == "angle" else "mm"
        print("RMS spot radius (µm), centroid reference")
        if parts is not None:
            where = "; ".join(f"on surface {a}" if d is None else f"{d:g} mm after surface {a}" for a, d in zip(*(
                (v if isinstance(v, list) else [v]) for v in parts[2:])))
            print(f"  with the DOE inside the lens ({where}; each wavelength's strongest order)")
        print(f"  {'field (' + unit + ')':>12s}" + "".join(f"{w:>12.4g}" for w in table["wavelengths"]))
        for f, row in zip(table["fields"], table["rms_radius"]):
            label = f"{f[0]:g},{f[1]:g}" if isinstance(f, (list, tuple)) else f"{f:g}"
            print(f"  {label:>12s}" + "".join(f"{'vignetted':>12s}" if r is None else f"{r:>12.4f}" for r in row))
    if out is not None:
        from raywave.plotting import plot_spots

        plot_spots(lens if lens_at is None else lens_at(lens.primary_wavelength), out, fields=fields)
        if not args.json:
            print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------------------- convert
def cmd_convert(args) -> int:
    from raywave.io import read_lens_spec, rebase_phase_path, write_lens_spec
    from raywave.lens.build import lens_from_spec, resolve_lens_path

    src = resolve_lens_path(args.input)
    spec = read_lens_spec(src)
    lens_from_spec(spec)  # validates glasses and geometry before anything is written
    spec = rebase_phase_path(spec, src.parent, Path(args.output).parent)  # a DOE phase map stays findable
    write_lens_spec(spec, args.output)
    print(f"wrote {args.output}")
    return 0


# ---------------------------------------------------------------------------- demo
def run_demo(out_dir: Path, lens_name: str = "cooke_triplet") -> dict:
    """Analyse a bundled lens: paraxial table (txt + json), layout and spot diagram PNGs."""
    from raywave.plotting import plot_layout, plot_spots

    out_dir.mkdir(parents=True, exist_ok=True)
    lens = _load(lens_name)
    info = lens_info(lens)
    (out_dir / "paraxial.txt").write_text(format_info(info) + "\n")
    spots = spot_table(lens)
    (out_dir / "paraxial.json").write_text(json_dumps({"paraxial": info, "spot": spots}, indent=2) + "\n")
    plot_layout(lens, out_dir / "layout.png")
    plot_spots(lens, out_dir / "spot.png")
    return {"info": info, "spot": spots}


def run_psf_demo(out_dir: Path, lens_name: str = "hybrid_asphere", ks: int = 64, pbar=None) -> dict:
    """Ray-wave PSFs of a bundled hybrid lens on axis and at 0.7 of its field, at each of its wavelengths:
    ``psf.png`` (log scale) and ``psf.json`` (centre, energy outside the crop, RMS and EE80 radii, the fraction of
    each beam that the DOE aperture blocks). ``pbar``: a tqdm bar of the 2 × W PSFs (or None). Returns
    ``{"psfs": rows, "doe_size": (w, h) mm}``."""
    import torch

    from raywave.assembly.build import load_hybrid
    from raywave.hybrid.metrics import psf_metrics
    from raywave.lens.build import resolve_lens_path
    from raywave.plotting import plot_psf_grid

    hl = load_hybrid(resolve_lens_path(lens_name))
    lens = hl.lens
    fields = [(0.0, 0.0), (0.7 * max(lens.fields), 0.0)]  # along x: the long side of the 16:9 sensor
    results = []
    for f in fields:  # one field at a time: the bar moves per field (a field alone gives the same PSFs)
        with torch.no_grad():
            results.append(hl.psf_result([list(f)], lens.wavelengths, ks=ks))
        if pbar is not None:
            pbar.update(len(lens.wavelengths))
    rows = []
    for i, f in enumerate(fields):
        res = results[i]
        for j, wl in enumerate(lens.wavelengths):
            m = psf_metrics(res.psf[0, j], res.pitch)
            clipped = None if res.doe_clipped is None else float(res.doe_clipped[0, j])
            rows.append({"field_deg": list(f), "wavelength_um": wl, "center_mm": res.center[0, j].tolist(),
                         "energy_outside": float(res.energy_outside[0, j]), "rms_radius_um": m["rms_radius"] * 1e3,
                         "r80_um": m["r80"] * 1e3, "doe_blocked": clipped})
    pitch = results[0].pitch
    psf = torch.cat([r.psf for r in results])
    (out_dir / "psf.json").write_text(json_dumps({"lens": lens_name, "ks": ks, "pitch_mm": pitch,
                                                  "doe_size_mm": list(hl.doe.size), "psfs": rows}, indent=2) + "\n")
    plot_psf_grid(psf, pitch, [f"field ({f[0]:g}°, {f[1]:g}°)" for f in fields], [f"{w:g} µm" for w in lens.wavelengths],
                  out_dir / "psf.png", title=f"{lens_name}: ray-wave PSFs (log scale, {pitch * 1e3:g} µm pixels)")
    return {"psfs": rows, "doe_size": tuple(hl.doe.size)}


def demo_notes(psf: dict) -> list[str]:
    """What the demo's output should say about itself: the bundled hybrid lens's DOE (the paper's 3 mm element)
    is a little smaller than the beam at the demo's outer field, so it blocks a little of that beam's light; this
    is the lens as bundled, not a fault of the run."""
    blocked = [(r["doe_blocked"], r) for r in psf["psfs"] if r.get("doe_blocked") and r["doe_blocked"] > 0.01]
    if not blocked:
        return []
    frac, r = max(blocked, key=lambda t: t[0])
    w, h = psf["doe_size"]
    return [f"note: the bundled hybrid lens's {w:g}×{h:g} mm DOE (the paper's element) is slightly smaller than the "
            f"beam at field ({r['field_deg'][0]:g}°, {r['field_deg'][1]:g}°): it blocks up to {100 * frac:.1f} % of "
            f"the light there ({r['wavelength_um']:g} µm), as intended for this example; a lens file without a DOE "
            "gets one that covers every beam"]


def cmd_demo(args) -> int:
    import warnings

    from raywave.cli.errors import report_warnings
    from raywave.cli.progress import bar, ticking
    from raywave.hybrid import DOEApertureWarning

    out = Path(args.output)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_demo(out, args.lens)
        pbar = bar(args, 6, "PSF", "demo: ray-wave PSFs")
        with pbar, ticking(pbar):
            psf = run_psf_demo(out, pbar=pbar)
    # the DOE aperture's clipping is stated by the demo's note (intended: the bundled element), not warned about
    report_warnings([w for w in caught if not issubclass(w.category, DOEApertureWarning)])
    print(format_info(res["info"]))
    for r in psf["psfs"]:
        print(f"ray-wave PSF field ({r['field_deg'][0]:5.2f}°, {r['field_deg'][1]:g}°) {r['wavelength_um']:.3f} µm: RMS radius "
              f"{r['rms_radius_um']:6.2f} µm, EE80 radius {r['r80_um']:6.2f} µm")
    for line in demo_notes(psf):
        print(line)
    names = ["paraxial.txt", "paraxial.json", "layout.png", "spot.png", "psf.png", "psf.json"]
    print("wrote " + ", ".join(str(out / n) for n in names))
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub) -> None:
    lens_help = "lens file (.json raywave or DeepLens-style, .zmx) or a bundled lens name"
    p = sub.add_parser("info", help="paraxial table and real-ray EFL of a lens")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--wavelength", default=None, help="µm (default: the lens's primary)")
    p.add_argument("--config", default=None, help="configuration of a multi-configuration .zmx file (1-based; "
                                                  "default 1)")
    add_clip_apertures_argument(p)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("layout", help="2D section with ray fans (PNG)")
    p.add_argument("lens", help=lens_help)
    p.add_argument("-o", "--output", required=True, help="PNG file, or a folder (receives layout.png)")
    add_field_arguments(p, "the lens's fields; Y values: the y-z section", legacy_y_list=True)
    p.add_argument("--rays", default="7", help="rays per fan")
    p.add_argument("--config", default=None, help="configuration of a multi-configuration .zmx file (1-based)")
    add_clip_apertures_argument(p)
    p.set_defaults(func=cmd_layout)

    p = sub.add_parser("spot", help="RMS spot radius per field and wavelength")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="spot diagram PNG, or a folder (receives spot.png)")
    add_field_arguments(p, "the lens's fields", legacy_y_list=True)
    p.add_argument("--config", default=None, help="configuration of a multi-configuration .zmx file (1-based)")
    add_clip_apertures_argument(p)
    p.set_defaults(func=cmd_spot)

    p = sub.add_parser("convert", help="convert a lens file (.json <-> .zmx; DeepLens .json in)")
    p.add_argument("input")
    p.add_argument("output")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("demo", help="analyse a bundled lens (table, layout, spot diagram) and show ray-wave PSFs "
                                    "of the bundled hybrid lens")
    p.add_argument("-o", "--output", default="raywave-demo", help="output folder")
    p.add_argument("--lens", default="cooke_triplet", help="bundled lens name or lens file")
    p.set_defaults(func=cmd_demo)
