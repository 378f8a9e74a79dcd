"""The ``psfmap`` and ``render`` commands: PSF maps of a hybrid lens and images simulated through it.

    raywave psfmap LENS [--grid N [M]] [--depths Z ...] [--wavelengths W ...] [--ks N] [-o map.npz] [--png map.png]
                   [--mapping chief_ray|paraxial] [--batch B] [--checkpoint DIR] [--quiet] [--json] [DOE options]
    raywave render LENS IMAGE [--depth Z] [--grid N [M]] [--ks N] [--wavelengths R G B | --average] -o out.png
                   [--map map.npz] [--noise] [--seed S] [--save-map map.npz] [--quiet] [--json] [DOE options]

LENS is a lens file or a bundled lens name as for ``raywave psf``, with the same DOE options (``--doe-pitch``,
``--doe-size``, ``--doe-distance``, ``--sensor-pitch``, ``--oversample``, ``--doe-levels``, ``--doe-wavelength``,
``--doe-material``, ``--mode``, ``--rays``). The map's nodes are the centres of an N×M tiling of the sensor,
their fields found through the real chief ray (see :mod:`raywave.imaging.psfmap`).

``render`` reads IMAGE (any format imageio reads; 8/16-bit, greyscale, RGB, RGBA), decodes sRGB to linear,
stretches it over the whole sensor (its pixel pitch = sensor width / image width; PSFs are resampled to it),
renders it upright (the photograph of the scene: :mod:`raywave.imaging.render`), optionally adds sensor noise,
and writes it sRGB-encoded (8-bit PNG/JPEG, or 16-bit for .tif/.tiff). ``--average`` uses the three wavelengths
per channel averaged with the sensor-response weights (evaluation) instead of one wavelength per channel.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.cli.errors import (DEVICE_HELP, CommandError, device_arg, integer_arg as _integer, json_dumps,
                                number_arg as _number, report_warnings)
from raywave.cli.psf_commands import _wavelength, fabricate_doe, parse_doe_options

IMAGE_OUTPUTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


# ---------------------------------------------------------------------------- shared arguments
def _add_lens_options(p) -> None:
    p.add_argument("--ks", default="64", metavar="N", help="PSF size in sensor pixels (default 64)")
    p.add_argument("--grid", nargs="+", default=None, metavar="N",
                   help="nodes N [M]: rows along y, columns along x (one value: N × N)")
    p.add_argument("--mapping", choices=("chief_ray", "paraxial"), default="chief_ray",
                   help="normalised sensor position → field: real chief-ray height (default) or rectilinear "
                        "(paraxial; the render then shows the lens's distortion)")
    p.add_argument("--batch", default=None, metavar="B", help="field points per model call (default: ~24 fields)")
    p.add_argument("--progress", action="store_true",
                   help="show a progress bar (the default now; --quiet turns it off)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--mode", choices=("accurate", "faithful"), default="accurate",
                   help="DOE-plane field: accurate (default) or faithful (the paper's ray splatting)")
    p.add_argument("--rays", default=None, metavar="N",
                   help="accurate: traced nodes across the beam (default 64); faithful: number of rays (default 1e5)")
    p.add_argument("--doe-pitch", default=None, metavar="MM", help="DOE pixel pitch in mm (overrides the file's)")
    p.add_argument("--doe-size", nargs="+", default=None, metavar="MM", help="DOE width [height] in mm")
    p.add_argument("--doe-distance", default=None, metavar="MM", help="last vertex to DOE plane in mm")
    p.add_argument("--sensor-pitch", default=None, metavar="MM",
                   help="PSF pixel pitch in mm (default: the lens's sensor pixel pitch, else the DOE pitch)")
    p.add_argument("--oversample", default=None, metavar="Q", help="simulation samples per DOE pixel per axis")
    p.add_argument("--doe-levels", default=None, metavar="L", help="fabricate the DOE: quantise it to L levels")
    p.add_argument("--doe-wavelength", default=None, metavar="UM",
                   help="fabricate the DOE: design wavelength in µm (default 0.55)")
    p.add_argument("--doe-material", default=None, metavar="NAME",
                   help="fabricate the DOE: a dispersive height map in this glass (default FUSED_SILICA)")
    p.add_argument("--device", default="cpu", metavar="DEV", help=DEVICE_HELP)
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="resumable map: each finished chunk of PSFs is written to DIR; run the same command again "
                        "after an interruption and it computes only the rest (a DIR of another map is refused)")


def _grid(values, default=(10, 10)) -> tuple[int, int]:
    if values is None:
        return default
    if len(values) not in (1, 2):
        raise CommandError(f"--grid: give N [M] (nodes along y and x), got {len(values)} values")
    g = [_integer(v, "--grid") for v in values]
    return (g[0], g[0]) if len(g) == 1 else (g[0], g[1])


def _depths(values, flag: str) -> list[float]:
    return [_number(v, flag, positive=True, allow_inf=True) for v in values]


def parse_lens_args(args) -> dict:
    """The lens and map arguments shared by both commands (strings → numbers), or a :class:`CommandError`."""
    from raywave.lens.build import resolve_lens_path

    try:
        path = resolve_lens_path(args.lens)
    except FileNotFoundError as e:
        raise CommandError(str(e)) from None
    out = {"path": path, "ks": _integer(args.ks, "--ks"), "mode": args.mode, "mapping": args.mapping,
           "batch": None if args.batch is None else _integer(args.batch, "--batch"),
           "rays": None if args.rays is None else _integer(args.rays, "--rays"), "device": device_arg(args.device),
           "checkpoint": getattr(args, "checkpoint", None)}
    out.update(parse_doe_options(args))
    return out


def load_lens_for_map(a: dict, grid, depth, wavelengths):
    """The HybridLens of the parsed arguments, and the map's field grid (deg). A lens file without a DOE gets a
    default blank DOE sized to hold the beams of every node of the map."""
    from raywave.assembly.build import load_hybrid
    from raywave.imaging.psfmap import field_grid

    common = dict(sensor_pitch=a["sensor_pitch"], oversample=a["oversample"], wavelengths=wavelengths, depth=depth,
                  field_type="angle")
    hl = load_hybrid(a["path"], a["doe_pitch"], a["doe_size"], a["doe_distance"], **common)
    try:
        fields = field_grid(hl, grid, depth=depth, mapping=a["mapping"])
    except ValueError as e:
        raise CommandError(f"{a['path']}: {e}") from None
    if hl.doe_info.get("source") == "default" and a["doe_size"] is None:
        hl = load_hybrid(a["path"], a["doe_pitch"], None, a["doe_distance"],
                         fields=fields.reshape(-1, 2).tolist() + [[0.0, 0.0]], **{**common, "depth": depth})
    if a["doe_levels"] is not None or a["doe_wavelength"] is not None or a["doe_material"] is not None:
        fabricate_doe(hl, a["doe_levels"], a["doe_wavelength"], a["doe_material"])
    return hl.to(a.get("device", "cpu")), fields


def _compute_map(a: dict, grid, depths, wavelengths, progress: bool):
    from raywave.imaging.psfmap import psf_map

    hl, fields = load_lens_for_map(a, grid, depths[0], wavelengths)
    kw = {"mode": a["mode"]}
    if a["rays"] is not None:
        kw["rays"] = a["rays"]
    try:
        pmap = psf_map(hl, grid, depths, wavelengths, ks=a["ks"], batch=a["batch"], progress=progress,
                       fields=fields, sensor_size=hl.lens.sensor_size, checkpoint=a.get("checkpoint"), **kw)
    except ValueError as e:
        if a.get("checkpoint") is None or not str(e).startswith("checkpoint:"):
            raise
        raise CommandError(f"--checkpoint: {str(e).removeprefix('checkpoint: ')}") from None
    pmap.info["mapping"] = a["mapping"]
    return hl, pmap


def _map_summary(pmap, lens_name: str) -> dict:
    eo = pmap.energy_outside
    return {
        "lens": lens_name,
        "grid": list(pmap.grid),
        "depths_mm": ["inf" if math.isinf(d) else d for d in pmap.depths.tolist()],
        "wavelengths_um": pmap.wavelengths.tolist(),
        "ks": pmap.ks,
        "pitch_mm": pmap.pitch,
        "sensor_size_mm": list(pmap.sensor_size),
        "mapping": pmap.info.get("mapping"),
        "max_field_deg": float(pmap.fields.norm(dim=-1).max()),
        "energy_outside_max": None if eo is None else float(eo.max()),
    }


# ---------------------------------------------------------------------------- psfmap
def cmd_psfmap(args) -> int:
    a = parse_lens_args(args)
    grid = _grid(args.grid)
    depths = _depths(args.depths, "--depths") if args.depths else [math.inf]
    wls = None if args.wavelengths is None else [_wavelength(t, "--wavelengths") for t in args.wavelengths]
    if args.output is not None and Path(args.output).suffix.lower() != ".npz":
        raise CommandError(f"-o: the PSF map is written as .npz (psf, centers, fields, positions, depths, wavelengths, "
                           f"pitch, sensor_size, energy_outside), got {args.output!r}")
    if args.png is not None and Path(args.png).suffix.lower() != ".png":
        raise CommandError(f"--png: the image is a .png file, got {args.png!r}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # an error exit prints only the error (one line; its warnings would repeat it)
        _, pmap = _compute_map(a, grid, depths, wls, not args.quiet)
        report_warnings(caught)
    s = _map_summary(pmap, str(args.lens))
    wrote = []
    if args.output is not None:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        pmap.save(args.output)
        wrote.append(args.output)
        s["output"] = args.output
    if args.png is not None:
        from raywave.plotting.psfmap import plot_psf_map

        for d in range(len(depths)):
            p = Path(args.png) if len(depths) == 1 else Path(args.png).with_name(f"{Path(args.png).stem}_d{d}.png")
            plot_psf_map(pmap, p, depth_index=d, title=None)
            wrote.append(str(p))
        s["png"] = wrote[-len(depths):]
    if args.json:
        print(json_dumps(s))
    else:
        print(f"PSF map of {s['lens']}: {grid[0]}×{grid[1]} nodes, depths {s['depths_mm']} mm, wavelengths "
              f"{s['wavelengths_um']} µm, {s['ks']}×{s['ks']} px of {s['pitch_mm'] * 1e3:g} µm")
        print(f"  sensor {s['sensor_size_mm'][0]:g} × {s['sensor_size_mm'][1]:g} mm, fields up to "
              f"{s['max_field_deg']:.4g} deg ({s['mapping']}), energy outside the crops "
              f"≤ {s['energy_outside_max']:.3g}")
        for w in wrote:
            print(f"wrote {w}")
    return 0


# ---------------------------------------------------------------------------- render
def _read_image(path):
    """(3, H, W) float64 linear image in [0, 1] from an sRGB file."""
    import imageio.v3 as iio
    import numpy as np
    import torch

    from raywave.imaging.sensor import srgb_to_linear

    p = Path(path)
    if not p.exists():
        raise CommandError(f"IMAGE: {str(path)!r} not found")
    try:
        a = np.asarray(iio.imread(p))
    except Exception as e:  # imageio raises many types for unreadable files
        raise CommandError(f"IMAGE: cannot read {str(path)!r} ({e})") from None
    if a.ndim == 3 and a.shape[0] in (1, 3, 4) and a.shape[-1] not in (1, 3, 4):
        a = np.moveaxis(a, 0, -1)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in (1, 2, 3, 4):
        raise CommandError(f"IMAGE: {str(path)!r} has shape {a.shape}: expected a greyscale, RGB or RGBA image")
    if a.shape[-1] in (2, 4):
        a = a[..., :-1]  # drop alpha
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, axis=-1)
    if np.issubdtype(a.dtype, np.integer):
        x = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    else:
        x = np.clip(a.astype(np.float64), 0, 1)
    t = torch.from_numpy(np.ascontiguousarray(np.moveaxis(x, -1, 0)))
    return srgb_to_linear(t)


def _write_image(img, path) -> None:
    import imageio.v3 as iio
    import numpy as np

    from raywave.imaging.sensor import linear_to_srgb

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    enc = linear_to_srgb(img).detach().cpu().numpy()
    enc = np.moveaxis(enc, 0, -1)
    if p.suffix.lower() in (".tif", ".tiff"):
        iio.imwrite(p, np.round(enc * 65535).astype(np.uint16))
    else:
        iio.imwrite(p, np.round(enc * 255).astype(np.uint8))


def _check_render_outputs(args) -> None:
    """A :class:`CommandError` unless ``-o`` names an image file and ``--save-map`` (if given) an .npz."""
    if args.output is None:
        raise CommandError("-o: give the output image (e.g. -o out.png)")
    if Path(args.output).suffix.lower() not in IMAGE_OUTPUTS:
        raise CommandError(f"-o: write .png, .jpg, .tif or .bmp, got {args.output!r}")
    if args.save_map is not None and Path(args.save_map).suffix.lower() != ".npz":
        raise CommandError(f"--save-map: the PSF map is written as .npz, got {args.save_map!r}")


def _render_wavelengths(args, color) -> list[float]:
    """The wavelengths (µm) of the map to compute: ``--wavelengths`` (three, R G B), else the channel centres of
    ``color`` (a ColorSpec), or all its wavelengths with ``--average``."""
    if args.wavelengths is not None:
        if len(args.wavelengths) != 3:
            raise CommandError(f"--wavelengths: give three wavelengths (R G B, µm), got {len(args.wavelengths)}")
        if args.average:
            raise CommandError("--wavelengths and --average exclude each other")
        return [_wavelength(t, "--wavelengths") for t in args.wavelengths]
    return color.all_wavelengths().tolist() if args.average else color.centers().tolist()


def _saved_map(args, depth: float, color):
    """The PSF map read from ``--map`` (averaged per channel with ``--average`` when it holds 9 wavelengths) and
    the index of its depth ``depth`` (mm, inf); a :class:`CommandError` when it cannot serve the render."""
    from raywave.imaging.psfmap import PSFMap

    try:
        pmap = PSFMap.load(args.map)
    except (OSError, KeyError, ValueError) as e:
        raise CommandError(f"--map: cannot read {args.map!r} ({e})") from None
    di = [i for i, d in enumerate(pmap.depths.tolist())
          if d == depth or (math.isinf(d) and math.isinf(depth))]
    if not di:
        raise CommandError(f"--map: {args.map!r} has depths {pmap.depths.tolist()} mm, not --depth "
                           f"{depth:g}")
    if pmap.psf.shape[1] == 9 and args.average:
        pmap = pmap.channel_average(color)
    if pmap.psf.shape[1] != 3:
        raise CommandError(f"--map: {args.map!r} has {pmap.psf.shape[1]} wavelengths; the render needs 3 "
                           "(one per colour channel) or the 9 of --average")
    return pmap, di[0]


def _computed_map(args, depth: float, wls, color):
    """The PSF map of the lens at the one depth ``depth`` (mm, inf) and wavelengths ``wls`` (µm), averaged per
    channel with ``--average`` and written to ``--save-map`` if given, and its depth index (0)."""
    a = parse_lens_args(args)
    grid = _grid(args.grid, default=(5, 5))
    _, pmap = _compute_map(a, grid, [depth], wls, not args.quiet)
    if args.average:
        pmap = pmap.channel_average(color)
    if args.save_map is not None:
        pmap.save(args.save_map)
    return pmap, 0


def _render_image(img, pmap, d_index: int, noise: bool, seed: int):
    """The image ``img`` (3, H, W) linear rendered through ``pmap`` at its depth ``d_index`` (3, H, W), with
    Poisson–Gaussian sensor noise (generator seeded ``seed``) if ``noise``; warns (UserWarning) when the image's
    aspect ratio is not the sensor's. Returns (image, sensor width mm, sensor height mm)."""
    import torch

    from raywave.imaging.render import render_map
    from raywave.imaging.sensor import Sensor

    h, w = img.shape[-2:]
    if pmap.sensor_size is None:
        raise CommandError("--map: the PSF map has no sensor size (write it with raywave psfmap)")
    sw, sh = pmap.sensor_size
    if abs((w / h) / (sw / sh) - 1) > 0.01:
        warnings.warn(f"the image's aspect ratio {w / h:.3g} differs from the sensor's {sw / sh:.3g}: it is "
                      "stretched over the whole sensor", UserWarning)
    with torch.no_grad():
        out = render_map(img[None].to(pmap.psf.device), pmap, d_index)[0]
        if noise:
            gen = torch.Generator().manual_seed(seed)
            out = Sensor(noise="poisson")(out, generator=gen)
    return out, sw, sh


def cmd_render(args) -> int:
    from raywave.imaging.color import ColorSpec

    _check_render_outputs(args)
    depth = _number(args.depth, "--depth", positive=True, allow_inf=True)
    seed = _integer(args.seed, "--seed", minimum=0)
    img = _read_image(args.image)
    color = ColorSpec()
    wls = _render_wavelengths(args, color)
    lens_name = str(args.lens)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # an error exit prints only the error (one line; its warnings would repeat it)
        if args.map is not None:
            pmap, d_index = _saved_map(args, depth, color)
        else:
            pmap, d_index = _computed_map(args, depth, wls, color)
        out, sw, sh = _render_image(img, pmap, d_index, args.noise, seed)
        report_warnings(caught)
    _write_image(out, args.output)
    h, w = img.shape[-2:]
    s = {**_map_summary(pmap, lens_name), "image": str(args.image), "image_size": [int(w), int(h)],
         "image_pitch_mm": [sw / w, sh / h], "depth_mm": "inf" if math.isinf(depth) else depth,
         "average": bool(args.average), "noise": bool(args.noise), "output": args.output}
    if args.json:
        print(json_dumps(s))
    else:
        colour = ("3-wavelength average" if args.average
                  else f"wavelengths {[round(v, 4) for v in pmap.wavelengths.tolist()]} µm")
        print(f"rendered {args.image} ({w}×{h}) through {lens_name} at depth {s['depth_mm']} mm with a "
              f"{pmap.grid[0]}×{pmap.grid[1]} PSF map ({colour})")
        print(f"wrote {args.output}")
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub) -> None:
    p = sub.add_parser(
        "psfmap", help="PSF map of a hybrid lens on an N×M grid of sensor positions, depths and wavelengths",
        description="PSFs of a hybrid lens (refractive lens + DOE + sensor) at the centres of an N×M tiling of the "
        "sensor (fields through the real chief ray), for each depth and wavelength. Writes an .npz (psf (D, W, N, M, "
        "ks, ks), centers (D, W, N, M, 2) mm, fields (N, M, 2) deg, positions, depths, wavelengths, pitch, "
        "sensor_size, energy_outside) and a mosaic PNG (+y up).")
    p.add_argument("lens", help="lens file or bundled lens name (e.g. hybrid_asphere)")
    p.add_argument("--depths", nargs="+", default=None, metavar="MM",
                   help="object distances in mm from the first vertex, or inf (default: inf)")
    p.add_argument("--wavelengths", nargs="+", default=None, metavar="UM",
                   help="µm (default: the channel centres 0.66 0.53 0.47, R G B)")
    p.add_argument("-o", "--output", default=None, metavar="FILE", help=".npz")
    p.add_argument("--png", default=None, metavar="FILE", help="mosaic of the map (one PNG per depth)")
    _add_lens_options(p)
    p.set_defaults(func=cmd_psfmap)

    r = sub.add_parser(
        "render", help="simulate the photograph of an image through a hybrid lens (spatially varying blur)",
        description="Render IMAGE (an upright sRGB picture of the scene, stretched over the whole sensor) through a "
        "hybrid lens at one object depth: PSF map (default 5×5, one wavelength per channel), seam-free spatially "
        "varying blur, optional sensor noise; writes the upright sRGB result.")
    r.add_argument("lens", help="lens file or bundled lens name")
    r.add_argument("image", help="input image (PNG, JPEG, TIFF, ...)")
    r.add_argument("--depth", default="inf", metavar="MM", help="object distance in mm, or inf (default inf)")
    r.add_argument("--wavelengths", nargs="+", default=None, metavar="UM",
                   help="R G B wavelengths in µm (default 0.66 0.53 0.47)")
    r.add_argument("--average", action="store_true",
                   help="three wavelengths per channel averaged with the sensor-response weights (evaluation)")
    r.add_argument("--map", default=None, metavar="NPZ", help="use a saved PSF map (raywave psfmap -o) instead")
    r.add_argument("--save-map", default=None, metavar="NPZ", help="also write the computed PSF map")
    r.add_argument("--noise", action="store_true", help="add Poisson–Gaussian sensor noise and 10-bit quantisation")
    r.add_argument("--seed", default="0", metavar="S", help="noise seed (default 0)")
    r.add_argument("-o", "--output", default=None, metavar="FILE", help="output image (.png, .jpg, .tif: 16-bit)")
    _add_lens_options(r)
    r.set_defaults(func=cmd_render)
