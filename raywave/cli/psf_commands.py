"""The ``psf`` command: the ray-wave PSF of a hybrid lens (refractive lens + DOE) for one point source.

    raywave psf LENS [--field Y|X,Y] [--depth Z] [--wavelength W] [--ks N] [-o psf.npy|psf.npz] [--png psf.png]
                [--log] [--json] [--mode accurate|faithful] [--rays N] [--doe-pitch P] [--doe-size W [H]]
                [--doe-distance D] [--sensor-pitch P] [--oversample Q]
                [--doe-levels L] [--doe-wavelength W0] [--doe-material NAME]

LENS is a lens file (.json with or without a "doe" section, .zmx with or without a diffractive last surface,
DeepLens .json) or a bundled lens name. A lens without a DOE gets a blank one (see
:mod:`raywave.assembly.build` for the default distance, pitch and size). Warnings (sampling, vignetting, a DOE
phase not applied) are printed to stderr as one line each.

``--doe-levels L --doe-wavelength W0 --doe-material NAME`` fabricate the DOE on the fly (any one of them is
enough): its phase at W0 (µm, default 0.55) is wrapped to [0, 2π), quantised to L levels (default: not
quantised, a continuous kinoform) and becomes a dispersive height map in NAME (default FUSED_SILICA), see
:meth:`raywave.doe.DOE.fabricate`.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from raywave.cli.errors import (DEVICE_HELP, CommandError, device_arg, integer_arg as _integer, json_dumps,
                                number_arg as _number, pitch_arg, report_warnings,
                                wavelength_arg)
from raywave.cli.fields import add_field_arguments, check_angles, single_field
from raywave.cli.progress import bar, ticking

OUTPUT_EXTENSIONS = (".npy", ".npz")


# ---------------------------------------------------------------------------- argument parsing
_wavelength = wavelength_arg
pitch_option = pitch_arg


def parse_doe_options(args) -> dict:
    """The DOE and sensor options shared by ``psf``, ``psfmap``, ``render`` and ``compare`` (``--doe-pitch``,
    ``--doe-size``, ``--doe-distance``, ``--sensor-pitch``, ``--oversample``, ``--doe-levels``, ``--doe-wavelength``,
    ``--doe-material``), checked: lengths in mm, wavelengths in µm; absent options are None."""
    out = {}
    out["doe_pitch"] = None if args.doe_pitch is None else pitch_option(args.doe_pitch, "--doe-pitch")
    if args.doe_size is not None:
        if len(args.doe_size) not in (1, 2):
            raise CommandError(f"--doe-size: give W [H] (mm), got {len(args.doe_size)} values")
        out["doe_size"] = tuple(_number(t, "--doe-size", positive=True) for t in args.doe_size)
    else:
        out["doe_size"] = None
    out["doe_distance"] = (None if args.doe_distance is None
                           else _number(args.doe_distance, "--doe-distance", nonneg=True))
    out["sensor_pitch"] = (None if args.sensor_pitch is None
                           else pitch_option(args.sensor_pitch, "--sensor-pitch"))
    out["oversample"] = None if args.oversample is None else _integer(args.oversample, "--oversample")
    out["doe_levels"] = None if args.doe_levels is None else _integer(args.doe_levels, "--doe-levels", minimum=2)
    out["doe_wavelength"] = (None if args.doe_wavelength is None
                             else _wavelength(args.doe_wavelength, "--doe-wavelength"))
    out["doe_material"] = None
    if args.doe_material is not None:
        if not args.doe_material.strip():
            raise CommandError("--doe-material: give a glass name (e.g. FUSED_SILICA)")
        out["doe_material"] = args.doe_material.strip()
    return out


def parse_psf_args(args) -> dict:
    """Check and convert the command's arguments (strings) -> a dict; bad input raises :class:`CommandError`."""
    from raywave.lens.build import resolve_lens_path

    try:
        path = resolve_lens_path(args.lens)
    except FileNotFoundError as e:
        raise CommandError(str(e)) from None
    out: dict = {"path": path}
    out["field"] = single_field(args, (0.0, 0.0), "psf")
    check_angles([out["field"]])
    out["depth"] = None if args.depth is None else _number(args.depth, "--depth", positive=True, allow_inf=True)
    out["wavelength"] = None if args.wavelength is None else _wavelength(args.wavelength, "--wavelength")
    out["ks"] = _integer(args.ks, "--ks")
    out["rays"] = None if args.rays is None else _integer(args.rays, "--rays")
    out.update(parse_doe_options(args))
    out["stop_edge"] = getattr(args, "stop_edge", None)
    out["edge_step"] = getattr(args, "edge_step", None)
    out["device"] = device_arg(getattr(args, "device", "cpu"))
    out["clip_apertures"] = bool(getattr(args, "clip_apertures", False))
    if args.output is not None and Path(args.output).suffix.lower() not in OUTPUT_EXTENSIONS:
        raise CommandError(f"-o: the PSF is written as .npy (the array) or .npz (psf, center, pitch, "
                           f"energy_outside, ...), got {args.output!r}")
    if args.png is not None and Path(args.png).suffix.lower() != ".png":
        raise CommandError(f"--png: the image is a .png file, got {args.png!r}")
    return out


def add_clip_apertures_argument(p) -> None:
    """``--clip-apertures`` (shared by the commands that read a lens file)."""
    p.add_argument("--clip-apertures", action="store_true",
                   help="vignette at every surface's semi-diameter, as the lens's mounts do (a semi-diameter alone "
                        "does not clip, as in OpticStudio: a fast camera lens off axis then passes rays outside its "
                        "elements)")


def add_edge_arguments(p) -> None:
    """``--stop-edge`` and ``--edge-step`` (shared by ``psf`` and ``compare``)."""
    p.add_argument("--stop-edge", choices=("exit_pupil", "doe"), default=None,
                   help="where the accurate field's sharp stop edge sits: exit_pupil (default: the stop's image, where "
                        "the edge is physically sharp; off-axis PSFs independent of the DOE distance) or doe (on the "
                        "DOE plane: the paper's model, its off-axis PSFs depend on the DOE distance); "
                        "docs/ray-wave.md")
    p.add_argument("--edge-step", choices=("adaptive", "fresnel", "asm", "auto"), default=None,
                   help="with the exit-pupil edge, how the edge's diffraction reaches the DOE plane: adaptive (default: "
                        "fresnel, or with a blank DOE and a spherical wave at the stop's edge the edge cut on the DOE "
                        "plane, exact there), fresnel (the knife-edge step, any beam), asm (the exact angular-spectrum "
                        "construction, ~4x the cost, beams up to 8192 samples), auto (asm where the beam fits)")


# ---------------------------------------------------------------------------- the computation
def compute_psf(path, field=(0.0, 0.0), depth=None, wavelength=None, ks: int = 64, mode: str = "accurate",
                rays: int | None = None, doe_pitch=None, doe_size=None, doe_distance=None, sensor_pitch=None,
                oversample=None, doe_levels=None, doe_wavelength=None, doe_material=None, stop_edge=None,
                edge_step=None, device: str = "cpu", clip_apertures: bool = False) -> dict:
    """The PSF of one point source through the hybrid lens of ``path`` and its metrics.

    Field angles in degrees (whatever the file's field type), ``depth`` object distance in mm (None: the lens
    file's, ``inf``: distant), ``wavelength`` µm (None: the lens's primary). Returns a dict with ``psf``
    (ks, ks) float64 numpy, ``center`` (2,) mm, ``pitch`` mm, ``energy_outside``, ``rays``, ``metrics``
    (:func:`raywave.hybrid.metrics.psf_metrics`, lengths in mm), ``wavelength``, ``depth``, ``hybrid``.
    ``doe_levels`` / ``doe_wavelength`` / ``doe_material``: fabricate the DOE first (see the module docstring).
    ``stop_edge`` / ``edge_step``: the engine's stop edge (None: the default, the exit pupil with the adaptive step;
    "doe": the paper's model), see :class:`raywave.hybrid.HybridLens`. ``device``: where to compute (the result
    is on the CPU). ``clip_apertures``: vignette at the surfaces' semi-diameters
    (:func:`raywave.lens.build.clip_at_semi_diameters`)."""
    import torch

    from raywave.assembly.build import load_hybrid
    from raywave.hybrid.metrics import psf_metrics

    # the default DOE must hold the requested source's beam (and the on-axis one)
    wl_list = None if wavelength is None else [wavelength]
    hl = load_hybrid(path, doe_pitch, doe_size, doe_distance, sensor_pitch=sensor_pitch, oversample=oversample,
                     fields=[list(field), [0.0, 0.0]], wavelengths=wl_list, depth=depth, field_type="angle",
                     stop_edge=stop_edge, edge_step=edge_step, clip_apertures=clip_apertures)
    if doe_levels is not None or doe_wavelength is not None or doe_material is not None:
        fabricate_doe(hl, doe_levels, doe_wavelength, doe_material)
    wl = hl.lens.primary_wavelength if wavelength is None else float(wavelength)
    check_sources_lit(hl, [field], [wl], depth)  # before the minutes of work a dark PSF would cost
    hl = hl.to(device)
    with torch.no_grad():
        res = hl.psf_result(fields=tuple(field), wavelengths=wl, ks=ks, depth=depth, mode=mode, rays=rays)
    psf = res.psf[0, 0].detach().cpu()
    if not float(psf.sum()) > 0:
        raise CommandError(f"no light reaches the sensor for field {list(field)} deg at {wl:g} µm (every ray is "
                           "vignetted or misses the DOE aperture)")
    metrics = psf_metrics(psf, res.pitch)
    d = hl.lens.object_distance if depth is None else float(depth)
    return {
        "psf": psf.numpy(),
        "center": [float(v) for v in res.center[0, 0].detach()],
        "pitch": float(res.pitch),
        "energy_outside": float(res.energy_outside[0, 0].detach()),
        "rays": int(res.rays[0, 0]),
        "metrics": metrics,
        "wavelength": wl,
        "depth": d,
        "field": [float(field[0]), float(field[1])],
        "mode": mode,
        "ks": ks,
        "hybrid": hl,
    }


def check_sources_lit(hl, fields, wavelengths, depth=None, flag: str = "--field") -> None:
    """Refuse, before any wave computation, a source (``fields`` (F, 2) degrees × ``wavelengths`` µm) none of whose
    rays (pupil rim and a hexapolar grid, :func:`raywave.lens.analysis.beam_rays_at`) both pass the lens and land
    inside the DOE aperture: its PSF would be all zeros after minutes of work (a fully vignetted field, or a beam
    that misses the DOE)."""
    import torch

    from raywave.lens.analysis import beam_rays_at

    at, _, wls = beam_rays_at(hl.optics, hl.doe_z(), [list(f) for f in fields], list(wavelengths), depth)
    xy = at.o[..., :2].detach()
    ok = at.valid & torch.isfinite(xy).all(-1)
    w, h = hl.doe.size
    if hl.doe.aperture == "circle":
        inside = (xy ** 2).sum(-1) <= (0.5 * min(w, h)) ** 2
    else:
        inside = (xy[..., 0].abs() <= 0.5 * w) & (xy[..., 1].abs() <= 0.5 * h)
    for i, f in enumerate(fields):
        for j, wl in enumerate(wls):
            where = f"field ({f[0]:g}, {f[1]:g}) deg at {wl:g} µm"
            if not bool(ok[i, j].any()):
                raise CommandError(f"{flag}: {where}: every ray is vignetted by the lens's apertures (no light "
                                   f"reaches the DOE plane); the lens's fields reach {max(hl.lens.fields):g}")
            if not bool((ok & inside)[i, j].any()):
                r = float(xy[i, j][ok[i, j]].norm(dim=-1).min())
                raise CommandError(f"{flag}: {where}: the beam misses the {w:g}×{h:g} mm DOE aperture (its nearest "
                                   f"ray lands {r:.3g} mm from the axis on the DOE plane); the lens's fields reach "
                                   f"{max(hl.lens.fields):g}")


#: a PSF whose crop misses more than this fraction of its energy is reported (as ``raywave train`` does)
CROP_WARN = 0.01


class CropWarning(UserWarning):
    """The PSF crop (``--ks``) misses a notable part of the PSF's energy: its radii are underestimated."""


def warn_crop(energy_outside: float, ks: int, what: str) -> None:
    """Warn (:class:`CropWarning`) when ``energy_outside`` (fraction) exceeds :data:`CROP_WARN`."""
    if energy_outside > CROP_WARN:
        warnings.warn(f"{what}: {energy_outside:.1%} of its energy falls outside the {ks}×{ks}-pixel crop, so its RMS "
                      f"and EE radii (measured in the crop) are underestimated: raise --ks (e.g. --ks {2 * ks})",
                      CropWarning, stacklevel=2)


def fabricate_doe(hl, levels=None, wavelength=None, material=None) -> None:
    """Make ``hl.doe`` the fabricated element: wrapped at ``wavelength`` (µm, default 0.55), quantised to ``levels``
    (None: continuous), a height map in ``material`` (default FUSED_SILICA); records it in ``hl.doe_info``."""
    from raywave.doe import DEFAULT_DESIGN_WAVELENGTH, DEFAULT_MATERIAL
    from raywave.materials import GlassNotFoundError

    try:
        hl.doe.fabricate(levels=levels, wavelength=DEFAULT_DESIGN_WAVELENGTH if wavelength is None else wavelength,
                         material=DEFAULT_MATERIAL if material is None else material)
    except GlassNotFoundError as e:
        raise CommandError(f"--doe-material: {e}") from None
    hl.doe_info.update(levels=hl.doe.quant_levels, material=hl.doe.material_name,
                       design_wavelength=hl.doe.design_wavelength, dispersion=hl.doe.dispersion)


def summary(result: dict, lens_name: str) -> dict:
    """The JSON summary: centre and pitch in mm, radii and offsets in µm (keys carry their unit)."""
    m = result["metrics"]
    info = result["hybrid"].doe_info
    um = 1e3
    out = {
        "lens": lens_name,
        "field_deg": result["field"],
        "depth_mm": "inf" if math.isinf(result["depth"]) else result["depth"],
        "wavelength_um": result["wavelength"],
        "mode": result["mode"],
        "rays": result["rays"],
        "ks": result["ks"],
        "center_mm": result["center"],
        "pitch_mm": result["pitch"],
        "energy_outside": result["energy_outside"],
        "rms_radius_um": m["rms_radius"] * um,
        "centroid_offset_um": [v * um for v in m["centroid"]],
        "r50_um": m["r50"] * um,
        "r80_um": m["r80"] * um,
        "r90_um": m["r90"] * um,
        "peak": m["peak"],
        "doe": {
            "source": info["source"],
            "distance_mm": info["distance"],
            "pitch_mm": info["pitch"],
            "pitch_rule": info.get("pitch_rule"),
            "distance_rule": info.get("distance_rule"),
            "caustic_distance_mm": info.get("caustic_distance"),
            "shape": info["shape"],
            "size_mm": info["size"],
            "aperture": info["aperture"],
            "phase": info["phase"],
            "oversample": info["oversample"],
            "phase_model": info.get("phase_model"),
            "material": info.get("material"),
            "levels": info.get("levels"),
            "design_wavelength_um": info.get("design_wavelength"),
            "dispersion": info.get("dispersion"),
        },
    }
    return out


def _write_array(result: dict, path: Path) -> None:
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".npy":
        np.save(path, result["psf"])
    else:
        np.savez(path, psf=result["psf"], center=np.array(result["center"]), pitch=np.float64(result["pitch"]),
                 energy_outside=np.float64(result["energy_outside"]), wavelength=np.float64(result["wavelength"]),
                 field=np.array(result["field"]), depth=np.float64(result["depth"]), rays=np.int64(result["rays"]),
                 mode=np.str_(result["mode"]))


def _format_text(s: dict) -> str:
    d = s["doe"]
    lines = [
        f"PSF of {s['lens']}: field ({s['field_deg'][0]:g}, {s['field_deg'][1]:g}) deg, depth {s['depth_mm']} mm, "
        f"{s['wavelength_um']:g} µm, {s['mode']} mode, {s['rays']} rays",
        f"  DOE ({d['source']}): {d['shape'][1]} × {d['shape'][0]} pixels of {d['pitch_mm'] * 1e3:g} µm, "
        f"{d['distance_mm']:g} mm after the last vertex"
        + (f" (kept before the rays' first crossing, {d['caustic_distance_mm']:g} mm)"
           if d.get("distance_rule") == "before_caustic" else "")
        + (" (moved back from the rays' focus, where the geometric-optics field holds)"
           if d.get("distance_rule") == "go_field" else "") + f", {d['aperture']}, "
        + (f"phase {d['phase']}" if d["phase"] is not None else f"{d['phase_model']} phase"
           if d.get("phase_model") else "blank")
        + (f", {d['levels']} levels" if d.get("levels") else "")
        + (f", height map in {d['material']} at {d['design_wavelength_um']:g} µm" if d.get("material") else ""),
        f"  centre (chief ray)       ({s['center_mm'][0]:.6f}, {s['center_mm'][1]:.6f}) mm",
        f"  pixel pitch              {s['pitch_mm'] * 1e3:g} µm, {s['ks']} × {s['ks']} pixels",
        f"  centroid offset          ({s['centroid_offset_um'][0]:.4f}, {s['centroid_offset_um'][1]:.4f}) µm",
        f"  RMS radius (centroid)    {s['rms_radius_um']:.4f} µm",
        f"  EE radii r50 r80 r90     {s['r50_um']:.4f} {s['r80_um']:.4f} {s['r90_um']:.4f} µm",
        f"  peak pixel               {s['peak']:.6g}",
        f"  energy outside the crop  {s['energy_outside']:.3g}",
    ]
    return "\n".join(lines)


def cmd_psf(args) -> int:
    a = parse_psf_args(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # an error leaves its warnings unprinted: the error names the problem in one line (e.g. a vignetted
        # field's VignettingWarning would repeat "no light reaches the sensor")
        pbar = bar(args, 1, "PSF", "psf")
        with pbar, ticking(pbar):
            result = compute_psf(a["path"], a["field"], a["depth"], a["wavelength"], a["ks"], args.mode, a["rays"],
                                 a["doe_pitch"], a["doe_size"], a["doe_distance"], a["sensor_pitch"],
                                 a["oversample"], a["doe_levels"], a["doe_wavelength"], a["doe_material"],
                                 a["stop_edge"], a["edge_step"], a["device"], a["clip_apertures"])
            pbar.update(1)
        warn_crop(result["energy_outside"], a["ks"], f"the PSF of field ({a['field'][0]:g}, {a['field'][1]:g}) deg")
    report_warnings(caught)
    s = summary(result, str(args.lens))
    wrote = []
    if args.output is not None:
        _write_array(result, Path(args.output))
        wrote.append(args.output)
        s["output"] = args.output
    if args.png is not None:
        from raywave.plotting.psf import plot_psf

        f = s["field_deg"]
        title = (f"{Path(str(args.lens)).stem}: field ({f[0]:g}, {f[1]:g})°, {s['wavelength_um']:g} µm, depth "
                 f"{s['depth_mm']} mm\nRMS {s['rms_radius_um']:.3g} µm, r80 {s['r80_um']:.3g} µm")
        plot_psf(result["psf"], result["pitch"], args.png, log=args.log, title=title, metrics=result["metrics"])
        wrote.append(args.png)
        s["png"] = args.png
    if args.json:
        print(json_dumps(s))
    else:
        print(_format_text(s))
        for w in wrote:
            print(f"wrote {w}")
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub) -> None:
    p = sub.add_parser(
        "psf", help="ray-wave PSF of a hybrid lens (refractive lens + DOE) for one point source",
        description="Ray-wave PSF of one point source through a hybrid lens: the refractive lens, the DOE of the "
        "lens file (a blank one if it has none) and the sensor. Writes the (ks, ks) float64 PSF [iy, ix] (sum 1, "
        "pixel [ks//2, ks//2] centred on the chief ray, both indices increasing with the coordinate).")
    p.add_argument("lens", help="lens file (.json raywave with an optional \"doe\", .zmx, DeepLens .json) or a "
                                "bundled lens name (e.g. hybrid_asphere)")
    add_field_arguments(p, "0, on axis; degrees, OpticStudio signs: +Y images at +y; the older --field X Y is "
                           "accepted")
    p.add_argument("--depth", default="inf", metavar="MM",
                   help="object distance in mm from the first vertex, or 'inf' (default: inf, a distant object)")
    p.add_argument("--wavelength", default=None, metavar="UM", help="µm (default: the lens's primary wavelength)")
    p.add_argument("--ks", default="64", metavar="N", help="PSF size in sensor pixels (default 64)")
    p.add_argument("-o", "--output", default=None, metavar="FILE",
                   help=".npy (the PSF array) or .npz (psf, center, pitch, energy_outside, wavelength, field, depth, "
                        "rays, mode)")
    p.add_argument("--png", default=None, metavar="FILE", help="PSF image (µm about the centre, origin lower)")
    p.add_argument("--log", action="store_true", help="logarithmic colour scale for --png")
    p.add_argument("--json", action="store_true", help="print one JSON object (centre, pitch, radii, ...)")
    p.add_argument("--mode", choices=("accurate", "faithful"), default="accurate",
                   help="DOE-plane field: accurate (exactly aimed rays, interpolated; default) or faithful (the "
                        "paper's ray splatting)")
    p.add_argument("--rays", default=None, metavar="N",
                   help="accurate: traced nodes across the beam (default 64); faithful: number of rays (default 1e5)")
    p.add_argument("--doe-pitch", default=None, metavar="MM",
                   help="DOE pixel pitch in mm (overrides the file's; default for a lens without a DOE: 0.001)")
    p.add_argument("--doe-size", nargs="+", default=None, metavar="MM",
                   help="DOE width [height] in mm (overrides the file's; default for a lens without a DOE: a square "
                        "1.2 × the beam's extent on the DOE plane)")
    p.add_argument("--doe-distance", default=None, metavar="MM",
                   help="last vertex to DOE plane in mm (overrides the file's; default for a lens without a DOE: half "
                        "way to the sensor, or nearer the sensor where the beam would span over 2048 DOE pixels)")
    add_edge_arguments(p)
    add_clip_apertures_argument(p)
    p.add_argument("--sensor-pitch", default=None, metavar="MM",
                   help="PSF pixel pitch in mm (default: the lens's sensor pixel pitch, else the DOE pitch)")
    p.add_argument("--oversample", default=None, metavar="Q",
                   help="simulation samples per DOE pixel per axis (default: the file's, else 1)")
    p.add_argument("--doe-levels", default=None, metavar="L",
                   help="fabricate the DOE: wrap its phase at --doe-wavelength to [0, 2π) and quantise it to L levels")
    p.add_argument("--doe-wavelength", default=None, metavar="UM",
                   help="fabricate the DOE: design wavelength λ0 in µm of the kinoform and height map (default 0.55)")
    p.add_argument("--doe-material", default=None, metavar="NAME",
                   help="fabricate the DOE: a dispersive height map in this glass (default FUSED_SILICA), "
                        "φ(λ) = 2π(n(λ) − 1)h/λ")
    p.add_argument("--device", default="cpu", metavar="DEV", help=DEVICE_HELP)
    p.set_defaults(func=cmd_psf)
