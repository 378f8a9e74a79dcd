"""The ``doe`` commands: fabrication of a DOE and its tolerance.

    raywave doe export DOE [--levels 16] [--material NAME] [--wavelength UM] [-o masks/] [--pitch MM]
                           [--format gds|oas] [--min-feature UM] [--name NAME] [--json]
    raywave doe report DOE [--levels 16] [--material NAME] [--wavelength UM] [--pitch MM] [--depth-error 5]
                           [--misalignment 0.1] [--distribution normal|uniform] [--samples 100] [--seed 0]
                           [--wavelengths UM ...] [--orders M ...] [--lens LENS] [--ks 64] [-o report/] [--json]

DOE is a phase map (``.npy``: the (ny, nx) phase in radians at the design wavelength, with ``--pitch``; ``.npz``:
the phase under ``phase`` and optionally the pitch (mm) under ``pitch``) or a lens file with a DOE (raywave .json
with a ``"doe"`` section, .zmx with a diffractive last surface). The design wavelength and material default to the
DOE's own (a lens file's DOE), else 0.55 µm and fused silica. The DOE's phase at the design wavelength is
quantised to L = 2^k levels (nearest level of the wrapped phase, L folding to 0) and split into k binary masks
(:mod:`raywave.doe.fabrication`: conventions, layers, etch depths). Writes ``masks.gds`` (or ``.oas``),
``mask_<j>.png`` previews and ``report.json`` into the output folder and prints a one-line summary.

``report`` loads the DOE the same way and runs the fabrication tolerance Monte Carlo of
:mod:`raywave.doe.tolerance` (etch-depth errors ±x % per step, mask misalignment ±m DOE pixels per mask and axis,
±x = 2σ of a normal distribution by default): it prints the levels, etch depths, minimum feature, the nominal
efficiency per order and wavelength and the statistics of the perturbed elements (and, with ``--lens``, of their
PSFs), and writes ``report.json`` and PNG histograms into the output folder.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from raywave.cli.errors import CommandError, integer_arg, json_dumps, number_arg, pitch_arg, wavelength_arg
from raywave.cli.fields import add_field_arguments, check_angles, single_field
from raywave.cli.progress import bar, ticking

PHASE_EXTENSIONS = (".npy", ".npz")
LENS_EXTENSIONS = (".json", ".zmx")
DEFAULT_WAVELENGTH = 0.55
DEFAULT_MATERIAL = "fused_silica"


def _number(text, flag: str) -> float:
    return number_arg(text, flag, positive=True)


# ---------------------------------------------------------------------------- loading the DOE
def _load_phase_map(path: Path):
    """-> (phase float64 (ny, nx), pitch mm or None)."""
    import numpy as np

    pitch = None
    try:
        if path.suffix.lower() == ".npy":
            arr = np.load(path, allow_pickle=False)
        else:
            with np.load(path, allow_pickle=False) as z:
                if "phase" not in z.files:
                    raise CommandError(f"{path}: holds no array 'phase' (found: {', '.join(z.files) or 'nothing'})")
                arr = z["phase"]
                if "pitch" in z.files:
                    pv = z["pitch"]
                    if pv.size != 1 or not np.issubdtype(pv.dtype, np.number):
                        raise CommandError(f"{path}: 'pitch' must be one number (mm)")
                    pitch = float(pv.reshape(()))
                    if not (math.isfinite(pitch) and pitch > 0):
                        raise CommandError(f"{path}: 'pitch' must be > 0 mm, got {pitch!r}")
    except CommandError:
        raise
    except (OSError, ValueError, EOFError) as e:
        raise CommandError(f"{path}: cannot read the phase map: {' '.join(str(e).split())}") from None
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise CommandError(f"{path}: a phase map must be a non-empty 2-D (ny, nx) array, got shape {arr.shape}")
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise CommandError(f"{path}: the phase map must hold real numbers (radians), got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise CommandError(f"{path}: the phase map contains NaN or inf (first at [{bad[0]}, {bad[1]}])")
    return arr, pitch


def load_doe(source: str, pitch: float | None = None, wavelength0: float = 0.55):
    """The DOE (a :class:`~raywave.doe.DOE`) of a phase map (radians at ``wavelength0``, µm) or a lens file, and a
    description of where it came from. ``pitch`` (mm) overrides the file's (a .npy needs it)."""
    from raywave.doe import BlankDOE, PixelDOE

    path = Path(source)
    ext = path.suffix.lower()
    if ext in PHASE_EXTENSIONS:
        if not path.is_file():
            raise CommandError(f"DOE file {source!r} not found")
        phase, file_pitch = _load_phase_map(path)
        p = pitch if pitch is not None else file_pitch
        if p is None:
            raise CommandError(f"{source}: the phase map has no pitch: give --pitch MM (or store 'pitch' in a .npz)")
        doe = PixelDOE(phase, p, design_wavelength=wavelength0, trainable=False)
        return doe, {"source": str(source), "kind": "phase map"}
    from raywave.lens.build import resolve_lens_path

    try:
        lens_path = resolve_lens_path(source)
    except FileNotFoundError:
        raise CommandError(f"DOE file {source!r} not found (a .npy / .npz phase map or a lens file with a DOE)") \
            from None
    if lens_path.suffix.lower() not in LENS_EXTENSIONS:
        raise CommandError(f"{source}: a DOE is a phase map ({' or '.join(PHASE_EXTENSIONS)}) or a lens file "
                           f"({' or '.join(LENS_EXTENSIONS)}) with a DOE")
    from raywave.assembly.build import load_hybrid

    hl = load_hybrid(lens_path, doe_pitch=pitch)
    if hl.doe_info.get("source") != "file":
        raise CommandError(f"{source}: the lens file has no DOE (a \"doe\" section or a .zmx diffractive surface)")
    if isinstance(hl.doe, BlankDOE):
        raise CommandError(f"{source}: the lens file's DOE is blank (no phase): nothing to fabricate")
    return hl.doe, {"source": str(source), "kind": "lens file", "aperture": hl.doe.aperture}


def doe_levels(doe, levels: int, wavelength0: float):
    """The DOE's (ny, nx) level map at ``wavelength0``: ``doe.levels`` where the DOE has it, else the nearest
    level of its wrapped phase (:func:`raywave.doe.fabrication.quantise_phase`)."""
    import numpy as np
    import torch

    from raywave.doe.fabrication import quantise_phase

    with torch.no_grad():
        if callable(getattr(doe, "levels", None)):
            return np.asarray(doe.levels(levels, wavelength0).detach().cpu().numpy(), dtype=np.int64)
        return quantise_phase(doe.phase(wavelength0).detach().cpu().numpy(), levels)


# ---------------------------------------------------------------------------- export
def export_masks(doe, levels: int = 16, material: str = "fused_silica", wavelength0: float = 0.55,
                 folder="masks", fmt: str = "gds", name: str = "DOE", min_feature: float | None = None,
                 png: bool = True, info: dict | None = None) -> dict:
    """:func:`raywave.doe.export.export_design` (``folder/masks.<fmt>``, ``report.json``) plus ``mask_<j>.png``
    previews; returns the report (a dict)."""
    from raywave.doe.export import export_design
    from raywave.doe.fabrication import etch_depths
    from raywave.materials import get_material

    full = export_design(doe, levels, material, wavelength0, folder, fmt, name, min_feature, info)
    pngs = []
    if png:
        from raywave.doe.fabrication import masks_from_levels
        from raywave.doe.export import level_map
        from raywave.plotting.masks import plot_masks

        masks = masks_from_levels(level_map(doe, levels, wavelength0), levels)
        depths = etch_depths(levels, get_material(material), wavelength0)
        pngs = [str(p) for p in plot_masks(masks, doe.pitch, Path(folder), depths_nm=[d * 1e6 for d in depths])]
    full["previews"] = pngs
    rp = Path(full.pop("report"))
    rp.write_text(json_dumps(full, indent=2) + "\n", encoding="utf-8")
    full["report"] = str(rp)
    return full


def _fabrication_args(args):
    """``--levels`` (a power of two), ``--wavelength`` (µm) and ``--pitch`` (mm) shared by ``doe export`` and
    ``doe report``, checked: returns ``(levels, wavelength or None, pitch or None)``."""
    from raywave.doe.fabrication import mask_bits

    try:
        L = int(args.levels)
    except ValueError:
        raise CommandError(f"--levels: {args.levels!r} is not an integer") from None
    try:
        mask_bits(L)
    except ValueError as e:
        raise CommandError(f"--levels: {e}") from None
    w = None if args.wavelength is None else wavelength_arg(args.wavelength, "--wavelength")
    pitch = None if args.pitch is None else pitch_arg(args.pitch, "--pitch")
    return L, w, pitch


def _check_material(name) -> None:
    """``--material``: nothing when not given, else a :class:`CommandError` unless ``name`` is a known material."""
    from raywave.materials import GlassNotFoundError, get_material

    if name is not None:
        try:
            get_material(name)
        except GlassNotFoundError as e:
            raise CommandError(f"--material: {' '.join(str(e).split())}") from None


def cmd_export(args) -> int:
    from raywave.doe.fabrication import MASK_FORMATS

    L, w, pitch = _fabrication_args(args)
    min_feature = None if args.min_feature is None else _number(args.min_feature, "--min-feature")
    fmt = args.format.lower()
    if fmt not in MASK_FORMATS:
        raise CommandError(f"--format: gds or oas, got {args.format!r}")
    _check_material(args.material)
    doe, info = load_doe(args.doe, pitch, DEFAULT_WAVELENGTH if w is None else w)
    # defaults: the DOE's own design wavelength and material (a lens file's DOE), else 0.55 µm, fused silica
    if w is None:
        w = float(getattr(doe, "design_wavelength", None) or DEFAULT_WAVELENGTH)
    material = args.material or getattr(doe, "material_name", None) or DEFAULT_MATERIAL
    name = args.name or Path(str(args.doe)).stem
    try:
        pbar = bar(args, None, "step", "doe export: masks and previews")  # elapsed time while a large grid is cut
        with pbar, ticking(pbar):
            r = export_masks(doe, L, material, w, args.output, fmt, name, min_feature, png=not args.no_png,
                             info=info)
    except ValueError as e:
        raise CommandError(" ".join(str(e).split())) from None
    if args.json:
        print(json_dumps(r))
        return 0
    mf = r["min_feature_um"]
    depths = "/".join(f"{d:.1f}" for d in r["depths_nm"])
    ny, nx = r["shape"]
    print(f"wrote {r['file']} ({r['format']}, {r['file_bytes'] / 1e6:.3g} MB, {r['rectangles']} rectangles): "
          f"{r['levels']} levels = {r['masks']} masks, etch {depths} nm in {r['material']} at "
          f"{r['wavelength_um']:g} µm, {nx} × {ny} pixels of {r['pitch_um']:g} µm, min feature "
          f"{'none' if mf is None else f'{mf:g} µm'}; {len(r['previews'])} previews and {r['report']}",
          file=sys.stdout)
    return 0


# ---------------------------------------------------------------------------- tolerance report
def tolerance_report(doe, levels: int = 16, material: str = "fused_silica", wavelength0: float = 0.55,
                     depth_error: float = 5.0, misalignment: float = 0.1, samples: int = 100, seed: int = 0,
                     distribution: str = "normal", wavelengths=None, orders=(0, 1, 2, -1), lens=None,
                     field=(0.0, 0.0), ks: int = 64, oversample: int = 1, folder="report", png: bool = True,
                     progress: bool = False, info: dict | None = None) -> dict:
    """Fabrication description + tolerance Monte Carlo of ``doe``; writes ``folder/report.json`` (and PNGs) and
    returns the report (a dict). ``lens``: a :class:`~raywave.hybrid.HybridLens` for the PSF statistics."""
    from raywave.doe import fabrication as fab
    from raywave.assembly.tolerance import tolerance_monte_carlo
    from raywave.materials import get_material

    k = fab.mask_bits(levels)
    mat = get_material(material)
    depths = fab.etch_depths(levels, mat, wavelength0)
    t0 = time.perf_counter()
    level_map = doe_levels(doe, levels, wavelength0)
    masks = fab.masks_from_levels(level_map, levels)
    masks_rep = fab.mask_report(masks, doe.pitch, depths)
    wls = [wavelength0] if wavelengths is None else [float(w) for w in wavelengths]
    res = tolerance_monte_carlo(doe, levels, depth_error, misalignment, samples, seed=seed, wavelengths=wls,
                                orders=orders, material=mat, wavelength0=wavelength0, distribution=distribution,
                                oversample=oversample, lens=lens, fields=tuple(field), ks=ks, progress=progress)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pngs = []
    if png:
        from raywave.plotting.tolerance import plot_tolerance

        pngs = [str(p) for p in plot_tolerance(res, folder)]
    report = {
        **(info or {}),
        "material": mat.name,
        "wavelength_um": float(wavelength0),
        "n_at_wavelength": fab._index(mat, wavelength0),
        "h_2pi_nm": fab.height_2pi(mat, wavelength0) * 1e6,
        "fabrication": {key: masks_rep[key] for key in ("levels", "masks", "depths_nm", "total_depth_nm", "pitch_um",
                                                         "shape", "size_mm", "min_feature_um", "per_mask")},
        "tolerance": res.summary(),
        "seconds": time.perf_counter() - t0,
        "previews": pngs,
    }
    if lens is not None:
        report["tolerance"]["lens"] = {"doe_distance_mm": lens.doe_distance, "sensor_pitch_um": lens.sensor_pitch * 1e3,
                                       "oversample": lens.oversample, "field_deg": [float(v) for v in field],
                                       "ks": int(ks)}
    rp = folder / "report.json"
    rp.write_text(json_dumps(report, indent=2) + "\n", encoding="utf-8")
    report["report"] = str(rp)
    return report


def _um(v) -> str:
    return "-" if v is None else f"{v:g} µm"


def format_report(r: dict) -> str:
    """The readable summary of a :func:`tolerance_report` dict."""
    f, t = r["fabrication"], r["tolerance"]
    ny, nx = f["shape"]
    mf = f["min_feature_um"]
    lines = [
        f"DOE {r.get('source', '')}: {nx} × {ny} pixels of {f['pitch_um']:g} µm, {f['levels']} levels = "
        f"{f['masks']} masks in {r['material']} (n = {r['n_at_wavelength']:.5f} at λ0 = {r['wavelength_um']:g} µm, "
        f"h_2π = {r['h_2pi_nm']:.1f} nm)",
        "  etch depths: " + ", ".join(f"mask {j + 1} {d:.1f} nm" for j, d in enumerate(f["depths_nm"]))
        + f"; min feature {'none' if mf is None else f'{mf:g} µm'} ("
        + ", ".join(f"mask {m['mask']} {_um(m['min_feature_um'])}" for m in f["per_mask"]) + ")",
        f"tolerance: etch depth ±{t['depth_error_percent']:g} % per step, misalignment ±{t['misalignment_px']:g} px "
        f"(= {t['misalignment_px'] * f['pitch_um']:.4g} µm) per mask and axis ({t['tolerance_meaning']}), "
        f"{t['samples']} samples, seed {t['seed']}",
        "  efficiency per order (theory: ideal L-level staircase; nominal: this DOE; samples mean ± std [p5, p95]):",
    ]
    for e in t["efficiency"]:
        lines.append(f"    λ {e['wavelength_um']:.4g} µm  order {e['order']:+d}: theory {e['theory']:.4f}  nominal "
                     f"{e['nominal']:.4f}  samples {e['mean']:.4f} ± {e['std']:.4f} [{e['p5']:.4f}, {e['p95']:.4f}]")
    for e in t.get("relative", []):
        lines.append(f"    λ {e['wavelength_um']:.4g} µm  overlap with the nominal element: {e['mean']:.4f} ± "
                     f"{e['std']:.4f} [{e['p5']:.4f}, {e['p95']:.4f}]")
    if "psf" in t:
        lines.append(f"  PSF (vs nominal; worst sample #{t['worst_sample']}):")
        for e in t["psf"]:
            lines.append(f"    λ {e['wavelength_um']:.4g} µm  {e['metric']:<14s} nominal {e['nominal']:.4g}  samples "
                         f"{e['mean']:.4g} ± {e['std']:.3g} [{e['p5']:.4g}, {e['p95']:.4g}]")
    lines.append(f"wrote {r['report']}" + (f" and {len(r['previews'])} PNGs" if r["previews"] else ""))
    return "\n".join(lines)


def _report_wavelengths(args) -> list[float] | None:
    """``--wavelengths`` (µm), checked, or None when not given."""
    if not args.wavelengths:
        return None
    return [wavelength_arg(v, "--wavelengths") for v in args.wavelengths]


def _report_options(args) -> dict:
    """The Monte Carlo options of ``doe report``, checked in this order: ``depth_error`` (percent),
    ``misalignment`` (DOE pixels, or µm with the suffix um: then ``mis_um`` is True), ``samples``, ``seed``,
    ``--distribution``, ``wls`` (µm or None), ``orders``, ``ks`` (sensor pixels), ``oversample``, ``field`` (deg)."""
    from raywave.doe.tolerance import DISTRIBUTIONS

    depth_error = number_arg(args.depth_error, "--depth-error", nonneg=True)
    mis_text = str(args.misalignment).strip()
    mis_um = mis_text.lower().endswith(("um", "µm"))
    misalignment = number_arg(mis_text[:-2] if mis_um else mis_text, "--misalignment", nonneg=True)
    samples = integer_arg(args.samples, "--samples", 1)
    try:
        seed = int(args.seed)
    except ValueError:
        raise CommandError(f"--seed: {args.seed!r} is not an integer") from None
    if args.distribution not in DISTRIBUTIONS:
        raise CommandError(f"--distribution: one of {', '.join(DISTRIBUTIONS)}, got {args.distribution!r}")
    wls = _report_wavelengths(args)
    try:
        orders = [int(v) for v in args.orders]
    except ValueError:
        raise CommandError(f"--orders: integers, got {' '.join(args.orders)}") from None
    ks = integer_arg(args.ks, "--ks", 1)
    oversample = integer_arg(args.oversample, "--oversample", 1)
    field = single_field(args, (0.0, 0.0), "doe report")
    check_angles([field])
    return {"depth_error": depth_error, "misalignment": misalignment, "mis_um": mis_um, "samples": samples,
            "seed": seed, "wls": wls, "orders": orders, "ks": ks, "oversample": oversample, "field": field}


def _report_lens(source: str):
    """The hybrid lens of ``--lens`` (a lens file or bundled name; angle fields) for the PSF statistics."""
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import resolve_lens_path

    try:
        lens_path = resolve_lens_path(source)
    except FileNotFoundError:
        raise CommandError(f"--lens: lens file {source!r} not found") from None
    return load_hybrid(lens_path, field_type="angle")


def cmd_report(args) -> int:
    """``raywave doe report``: check the options, load the DOE (and ``--lens``), run :func:`tolerance_report`
    and print its summary (or JSON)."""
    L, w, pitch = _fabrication_args(args)
    o = _report_options(args)
    misalignment, wls = o["misalignment"], o["wls"]
    _check_material(args.material)
    doe, info = load_doe(args.doe, pitch, DEFAULT_WAVELENGTH if w is None else w)
    if w is None:
        w = float(getattr(doe, "design_wavelength", None) or DEFAULT_WAVELENGTH)
    material = args.material or getattr(doe, "material_name", None) or DEFAULT_MATERIAL
    if o["mis_um"]:  # µm on the substrate -> DOE pixels
        misalignment = misalignment / (doe.pitch * 1e3)
    hl = None
    if args.lens is not None:
        hl = _report_lens(args.lens)
        if wls is None:
            wls = [float(v) for v in hl.lens.wavelengths]
    if wls is None:
        wls = [w]
    try:
        r = tolerance_report(doe, L, material, w, o["depth_error"], misalignment, o["samples"], o["seed"],
                             args.distribution, wls, o["orders"], hl, o["field"], o["ks"], o["oversample"],
                             args.output, png=not args.no_png, progress=not args.quiet, info=info)
    except ValueError as e:
        raise CommandError(" ".join(str(e).split())) from None
    if args.json:
        print(json_dumps(r))
    else:
        print(format_report(r), file=sys.stdout)
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub) -> None:
    """Add ``raywave doe`` and its subcommands ``export`` and ``report`` to the CLI's subparsers ``sub``."""
    p = sub.add_parser("doe", help="DOE fabrication (mask export, tolerance report)",
                       description="Diffractive optical elements: fabrication and its tolerance.")
    dsub = p.add_subparsers(dest="doe_command", metavar="SUBCOMMAND")
    dsub.required = True
    _register_export(dsub)
    _register_report(dsub)


def _register_export(dsub) -> None:
    """The ``doe export`` parser (mask files, previews, report) under the ``doe`` subparsers ``dsub``."""
    e = dsub.add_parser(
        "export", help="lithography masks (GDSII / OASIS), previews and a report for an L-level DOE",
        description="Quantise a DOE's phase at the design wavelength to L = 2^k levels and write its k binary "
        "masks: OUT/masks.gds (or .oas; mask j on layer j, polygons = etched areas, mask 1 the deepest etch "
        "h_2pi/2; alignment crosses in the corners; label on layer 100), OUT/mask_<j>.png and OUT/report.json "
        "(depths, pitch, minimum feature and fill factor per mask). See docs/fabrication.md.")
    e.add_argument("doe", metavar="DOE",
                   help=".npy phase map (radians at the design wavelength; needs --pitch), .npz (phase, optional "
                        "pitch in mm) or a lens file with a DOE (.json \"doe\" section, .zmx)")
    e.add_argument("--levels", default="16", metavar="L", help="number of phase levels, a power of two (default 16)")
    e.add_argument("--material", default=None, metavar="NAME",
                   help="substrate material (glass table / catalog name; default: the DOE's material, else "
                        "fused_silica)")
    e.add_argument("--wavelength", default=None, metavar="UM",
                   help="design wavelength λ0 in µm: the phase map's wavelength and the etch depths' (default: the "
                        "DOE's design wavelength, else 0.55)")
    e.add_argument("-o", "--output", default="masks", metavar="DIR", help="output folder (default masks/)")
    e.add_argument("--pitch", default=None, metavar="MM",
                   help="DOE pixel pitch in mm (required for a .npy; overrides the file's otherwise)")
    e.add_argument("--format", default="gds", metavar="gds|oas", help="mask file format: gds (GDSII, default) or "
                                                                      "oas (OASIS)")
    e.add_argument("--min-feature", default=None, metavar="UM",
                   help="the fab's minimum feature (µm): error if a mask has a narrower line or space")
    e.add_argument("--name", default=None, help="design name for the label (default: the file name)")
    e.add_argument("--no-png", action="store_true", help="do not write the mask previews")
    e.add_argument("--json", action="store_true", help="print the report as one JSON object")
    e.set_defaults(func=cmd_export)


def _register_report(dsub) -> None:
    """The ``doe report`` parser (fabrication tolerance Monte Carlo) under the ``doe`` subparsers ``dsub``."""
    r = dsub.add_parser(
        "report", help="fabrication tolerance: etch-depth errors and mask misalignment by Monte Carlo",
        description="Fabrication description and tolerance of an L = 2^k level DOE: etch depths, minimum feature, "
        "nominal diffraction efficiency per order and wavelength, and by Monte Carlo the efficiency (and, with "
        "--lens, the PSF) of elements made with random etch-depth errors (one per etch step) and mask "
        "misalignments (mask 1 the reference). Tolerances ±x are 2σ of a normal distribution (or the bounds of a "
        "uniform one). Prints a summary; writes OUT/report.json and PNG histograms. See docs/fabrication.md.")
    r.add_argument("doe", metavar="DOE", help="as for 'raywave doe export': .npy (with --pitch), .npz or a lens file "
                                              "with a DOE")
    r.add_argument("--levels", default="16", metavar="L", help="number of phase levels, a power of two (default 16)")
    r.add_argument("--material", default=None, metavar="NAME",
                   help="substrate material (default: the DOE's material, else fused_silica)")
    r.add_argument("--wavelength", default=None, metavar="UM",
                   help="design wavelength λ0 in µm (default: the DOE's design wavelength, else 0.55)")
    r.add_argument("--pitch", default=None, metavar="MM", help="DOE pixel pitch in mm (required for a .npy)")
    r.add_argument("--depth-error", default="5", metavar="PCT",
                   help="etch-depth tolerance ±x in percent of each step's depth (default 5)")
    r.add_argument("--misalignment", default="0.1", metavar="PX",
                   help="mask misalignment tolerance ±m in DOE pixels, per mask and axis (default 0.1); with the "
                        "suffix um (e.g. 0.2um) in µm")
    r.add_argument("--distribution", default="normal", metavar="normal|uniform",
                   help="normal: ±x = ±2σ (default); uniform: errors uniform in [−x, x]")
    r.add_argument("--samples", default="100", metavar="N", help="Monte Carlo samples (default 100)")
    r.add_argument("--seed", default="0", metavar="S", help="random seed (default 0)")
    r.add_argument("--wavelengths", nargs="+", default=None, metavar="UM",
                   help="wavelengths (µm) of the efficiencies (default: the lens's with --lens, else λ0)")
    r.add_argument("--orders", nargs="+", default=["0", "1", "2", "-1"], metavar="M",
                   help="diffraction orders (default 0 1 2 -1)")
    r.add_argument("--lens", default=None, metavar="LENS",
                   help="lens file (raywave .json / .zmx, or a bundled name) for the PSF statistics: its lens, DOE "
                        "distance, sensor pitch and oversampling, with this DOE")
    add_field_arguments(r, "0, on axis; degrees")
    r.add_argument("--ks", default="64", metavar="PX", help="PSF crop in sensor pixels (default 64)")
    r.add_argument("--oversample", default="1", metavar="Q",
                   help="samples per DOE pixel of the efficiency overlap (exact at 1 for a square aperture; "
                        "refines a circular aperture's edge)")
    r.add_argument("-o", "--output", default="report", metavar="DIR", help="output folder (default report/)")
    r.add_argument("--no-png", action="store_true", help="do not write the PNG figures")
    r.add_argument("--progress", action="store_true", help="show a progress bar (the default now; --quiet: none)")
    r.add_argument("--json", action="store_true", help="print the report as one JSON object")
    r.set_defaults(func=cmd_report)
