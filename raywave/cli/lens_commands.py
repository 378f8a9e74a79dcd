"""Lens commands: info, layout, spot, convert, demo."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from raywave.cli.errors import CommandError, integer_arg, json_dumps, number_arg


def _load(name_or_path):
    from raywave.lens.build import load_lens, resolve_lens_path

    return load_lens(resolve_lens_path(name_or_path))


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


def cmd_info(args) -> int:
    lens = _load(args.lens)
    reason = _no_paraxial_reason(lens, _wavelength(args.wavelength))
    if reason is not None:  # tilted / decentred: what real rays tell
        info = real_ray_info(lens, _wavelength(args.wavelength))
        print(json_dumps(dict(info, paraxial=None, reason=reason)) if args.json else format_real_ray_info(info, reason))
        return 0
    info = lens_info(lens, _wavelength(args.wavelength))
    if args.json:
        print(json_dumps({k: info[k] for k in INFO_KEYS}))
    else:
        print(format_info(info))
    return 0


# ---------------------------------------------------------------------------- layout / spot
def cmd_layout(args) -> int:
    from raywave.plotting import plot_layout

    lens = _load(args.lens)
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
    lens = _load(args.lens)
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
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("layout", help="2D section with ray fans (PNG)")
    p.add_argument("lens", help=lens_help)
    p.add_argument("-o", "--output", required=True, help="PNG file")
    p.add_argument("--fields", default=None, help="field values, e.g. '0,10,14' (default: the lens's)")
    p.add_argument("--rays", default="7", help="rays per fan")
    p.set_defaults(func=cmd_layout)

    p = sub.add_parser("spot", help="RMS spot radius per field and wavelength")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="spot diagram PNG")
    p.add_argument("--fields", default=None, help="field values (default: the lens's)")
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
