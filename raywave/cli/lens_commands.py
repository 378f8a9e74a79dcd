"""Lens commands: info, layout, spot, convert, demo."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from raywave.cli.errors import CommandError, integer_arg, json_dumps, number_arg


def _load(name_or_path, config=None):
    """The lens of a file or bundled name; ``config``: the configuration of a multi-configuration .zmx file
    (``--config N``, 1-based; default 1)."""
    from raywave.lens.build import load_lens, resolve_lens_path

    if config is not None:
        config = integer_arg(config, "--config")
        if config < 1:
            raise CommandError(f"--config: configurations are numbered from 1, got {config}")
    return load_lens(resolve_lens_path(name_or_path), config=config)


def _floats(text: str | None, flag: str = "--fields"):
    """Comma- or space-separated finite numbers, or a one-line :class:`CommandError` naming ``flag``."""
    if text is None:
        return None
    vals = [number_arg(v, flag) for v in text.replace(",", " ").split()]
    if not vals:
        raise CommandError(f"{flag}: no values given")
    return vals


def _wavelength(text):
    return None if text is None else number_arg(text, "--wavelength", positive=True)


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
    with torch.no_grad():
        d["efl_real"] = float(real_ray_efl(lens, wavelength))
    out = {k: d[k] for k in INFO_KEYS}
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
        lines.append(f"  {label:<42s} {v:>14.6f} {unit}" if math.isfinite(v) else f"  {label:<42s} {'inf':>14s} {unit}")
    return "\n".join(lines)


def cmd_info(args) -> int:
    lens = _load(args.lens, getattr(args, "config", None))
    info = lens_info(lens, _wavelength(args.wavelength))
    if args.json:
        print(json_dumps({k: info[k] for k in INFO_KEYS}))
    else:
        print(format_info(info))
        try:
            print(format_field_table(lens, field_table(lens)))
        except ValueError as err:  # no chief ray to trace (e.g. a lens whose paraxial pupil is undefined)
            print(f"  Fields: {', '.join(f'{v:g}' for v in lens.fields)} "
                  f"({'deg' if lens.field_type == 'angle' else 'mm'}); no chief-ray table: {err}")
    return 0


# ---------------------------------------------------------------------------- layout / spot
def cmd_layout(args) -> int:
    from raywave.plotting import plot_layout

    lens = _load(args.lens, getattr(args, "config", None))
    plot_layout(lens, args.output, fields=_floats(args.fields), n_rays=integer_arg(args.rays, "--rays"))
    print(f"wrote {args.output}")
    return 0


def spot_table(lens, fields=None) -> dict:
    """RMS spot radius (µm) per field and wavelength, about each spot's centroid."""
    from raywave.lens.analysis import rms_spot_radius

    fields = list(lens.fields) if fields is None else list(fields)
    with torch.no_grad():
        rms = rms_spot_radius(lens, fields, lens.wavelengths)
    return {
        "unit": "um",
        "fields": fields,
        "field_type": lens.field_type,
        "wavelengths": list(lens.wavelengths),
        "rms_radius": (rms * 1e3).tolist(),
    }


def cmd_spot(args) -> int:
    lens = _load(args.lens, getattr(args, "config", None))
    fields = _floats(args.fields)
    table = spot_table(lens, fields)
    if args.json:
        print(json_dumps(table))
    else:
        unit = "deg" if lens.field_type == "angle" else "mm"
        print("RMS spot radius (µm), centroid reference")
        print(f"  {'field (' + unit + ')':>12s}" + "".join(f"{w:>12.4g}" for w in table["wavelengths"]))
        for f, row in zip(table["fields"], table["rms_radius"]):
            print(f"  {f:>12g}" + "".join(f"{r:>12.4f}" for r in row))
    if args.output:
        from raywave.plotting import plot_spots

        plot_spots(lens, args.output, fields=fields)
        if not args.json:
            print(f"wrote {args.output}")
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


def run_psf_demo(out_dir: Path, lens_name: str = "hybrid_asphere", ks: int = 64) -> dict:
    """Ray-wave PSFs of a bundled hybrid lens on axis and at 0.7 of its field, at each of its wavelengths:
    ``psf.png`` (log scale) and ``psf.json`` (centre, energy outside the crop, RMS and EE80 radii)."""
    import torch

    from raywave.assembly.build import load_hybrid
    from raywave.hybrid.metrics import psf_metrics
    from raywave.lens.build import resolve_lens_path
    from raywave.plotting import plot_psf_grid

    hl = load_hybrid(resolve_lens_path(lens_name))
    lens = hl.lens
    fields = [(0.0, 0.0), (0.7 * max(lens.fields), 0.0)]  # along x: the long side of the 16:9 sensor
    with torch.no_grad():
        res = hl.psf_result(fields, lens.wavelengths, ks=ks)
    rows = []
    for i, f in enumerate(fields):
        for j, wl in enumerate(lens.wavelengths):
            m = psf_metrics(res.psf[i, j], res.pitch)
            rows.append({"field_deg": list(f), "wavelength_um": wl, "center_mm": res.center[i, j].tolist(),
                         "energy_outside": float(res.energy_outside[i, j]), "rms_radius_um": m["rms_radius"] * 1e3,
                         "r80_um": m["r80"] * 1e3})
    (out_dir / "psf.json").write_text(json_dumps({"lens": lens_name, "ks": ks, "pitch_mm": res.pitch,
                                                  "psfs": rows}, indent=2) + "\n")
    plot_psf_grid(res.psf, res.pitch, [f"field ({f[0]:g}°, {f[1]:g}°)" for f in fields], [f"{w:g} µm" for w in lens.wavelengths],
                  out_dir / "psf.png", title=f"{lens_name}: ray-wave PSFs (log scale, {res.pitch * 1e3:g} µm pixels)")
    return {"psfs": rows}


def cmd_demo(args) -> int:
    out = Path(args.output)
    res = run_demo(out, args.lens)
    print(format_info(res["info"]))
    psf = run_psf_demo(out)
    for r in psf["psfs"]:
        print(f"ray-wave PSF field ({r['field_deg'][0]:5.2f}°, {r['field_deg'][1]:g}°) {r['wavelength_um']:.3f} µm: RMS radius "
              f"{r['rms_radius_um']:6.2f} µm, EE80 radius {r['r80_um']:6.2f} µm")
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
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("layout", help="2D section with ray fans (PNG)")
    p.add_argument("lens", help=lens_help)
    p.add_argument("-o", "--output", required=True, help="PNG file")
    p.add_argument("--fields", default=None, help="field values, e.g. '0,10,14' (default: the lens's)")
    p.add_argument("--rays", default="7", help="rays per fan")
    p.add_argument("--config", default=None, help="configuration of a multi-configuration .zmx file (1-based)")
    p.set_defaults(func=cmd_layout)

    p = sub.add_parser("spot", help="RMS spot radius per field and wavelength")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="spot diagram PNG")
    p.add_argument("--fields", default=None, help="field values (default: the lens's)")
    p.add_argument("--config", default=None, help="configuration of a multi-configuration .zmx file (1-based)")
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
