"""The ``compare`` command: one hybrid lens through the paper's simulation models (Table S.I), side by side.

    raywave compare LENS [--doe DOE] [--field Y|X,Y ...] [--fields 0 3.5 0,7 ...] [--models all|raywave,paraxial,...]
                    [--wavelength W] [--depth Z] [--ks 64] [--reference raywave] [-o out/] [--linear] [--json]
                    [--doe-pitch P] [--doe-size W [H]] [--doe-distance D] [--sensor-pitch P] [--oversample Q]
                    [--doe-levels L] [--doe-wavelength W0] [--doe-material NAME]

Models (:mod:`raywave.models.interface`): raywave, paraxial, pupil, raytrace, exit_pupil. ``--field`` (repeatable)
and ``--fields`` (a list) take field angles in degrees: ``Y`` or ``X,Y`` (:mod:`raywave.cli.fields`). ``--doe`` replaces the lens file's DOE by a phase map (.npy with
``--doe-pitch``, .npz) or the DOE of another lens file (the lens options of ``raywave psf`` apply otherwise).
``all`` leaves out exit_pupil when the DOE is not blank (it cannot carry one; naming it is an error).

Writes ``compare.png`` (a grid: models × fields, log scale unless ``--linear``), ``compare.csv`` and
``compare.json`` (per field and model: relative L1 ``Σ|psf − ref| / Σ|ref|`` to the reference model and to the
ground truth where one exists — an ideal-lens (paraxial surface) lens with a blank DOE on axis at a distant
object, whose truth is the Debye focus —, the centre's offset from the reference's, the energy outside the
crop, the pupil model's Zernike fit residual, the ray model's discontinuity fraction and the exit-pupil model's
pupil grid and its own error estimate (``n_pupil``, ``error_estimate``: it refines its pupil sampling until
converged, raywave.models.exit_pupil.huygens_psf); plus every pairwise
L1 between models) and prints the table.
"""

from __future__ import annotations

import csv
import math
import warnings
from pathlib import Path

from raywave.cli.errors import DEVICE_HELP, CommandError, json_dumps, report_warnings
from raywave.cli.fields import add_field_arguments, check_angles, field_list, parse_field_list
from raywave.cli.progress import bar, ticking

DEFAULT_FIELDS = ((0.0, 0.0),)


def parse_fields(tokens) -> list[tuple[float, float]]:
    """``Y`` or ``X,Y`` tokens (degrees) -> [(x, y), ...] (the list form of :mod:`raywave.cli.fields`)."""
    out = parse_field_list(tokens, "--fields")
    check_angles(out, "--fields")
    return out


def parse_models(text: str, doe_blank: bool) -> tuple[list[str], list[str]]:
    """``all`` or a comma list -> (models to run, notes about models left out)."""
    from raywave.models.interface import MODEL_NAMES

    notes = []
    if text.strip().lower() == "all":
        models = list(MODEL_NAMES)
        if not doe_blank:
            models.remove("exit_pupil")
            notes.append("exit_pupil left out: the DOE is not blank (Chen et al.'s model cannot carry a DOE)")
        return models, notes
    models = []
    for m in text.split(","):
        key = m.strip().lower().replace("-", "_")
        if not key:
            continue
        if key not in MODEL_NAMES:
            raise CommandError(f"--models: unknown model {m.strip()!r}; choose from {', '.join(MODEL_NAMES)} or all")
        if key not in models:
            models.append(key)
    if not models:
        raise CommandError("--models: give 'all' or a comma-separated list of models")
    if "exit_pupil" in models and not doe_blank:
        raise CommandError("--models: exit_pupil (Chen et al. 2021) cannot simulate a DOE and this DOE is not blank; "
                           "leave it out or compare on a blank DOE")
    return models, notes


def _is_blank(doe) -> bool:
    import torch

    from raywave.doe import BlankDOE

    if isinstance(doe, BlankDOE):
        return True
    with torch.no_grad():
        return not bool((doe.phase_pixels(doe.design_wavelength, slice(None), slice(None)) != 0).any())


def ground_truth(hl, field, wavelength: float, ks: int, depth):
    """The Debye focus when the hybrid lens is one ideal lens (paraxial surface) with a blank DOE, on axis, for a
    distant object; else None. (ks, ks) float64 torch, sum 1."""
    import torch

    from raywave.models.debye import debye_psf

    lens = hl.lens
    d = lens.object_distance if depth is None else float(depth)
    if (len(lens.surfaces) != 1 or lens.surfaces[0].interaction.kind != "ideal_lens" or not math.isinf(d)
            or tuple(field) != (0.0, 0.0) or not _is_blank(hl.doe)):
        return None
    s = lens.surfaces[0]
    f = float(s.interaction.focal_length.detach())
    r = s.clear_radius()
    if r is None or f <= 0:
        return None
    n = float(s.material.n(torch.tensor(wavelength, dtype=torch.float64, device="cpu")))
    half = 0.5 * min(hl.doe.size)
    # the DOE must not clip the cone: then the truth is the lens's own focus
    if r * (1 - hl.doe_distance / f) > half:
        return None
    na = n * math.sin(math.atan(r / f))
    defocus = hl.sensor_z() - f
    return debye_psf(na, wavelength, ks, hl.sensor_pitch, n=n, defocus=defocus, oversample=15).psf


def run_compare(hl, models, fields, wavelength: float, ks: int, depth, reference: str, pbar=None) -> dict:
    """Every model's PSFs and the comparison table (a dict; see the module docstring). ``results[model]`` is a list
    of one-field results (:class:`~raywave.models.base.ModelPSFResult`, ``psf (1, 1, ks, ks)``), computed one
    (model, field) at a time so that ``pbar`` (a tqdm bar of len(models) × len(fields) PSFs, or None) moves
    per PSF (a field alone gives the same PSF as in a batch)."""
    import torch

    from raywave.models.interface import make_model, relative_l1

    results = {}
    for name in models:
        model = make_model(name, hl)
        results[name] = []
        for f in fields:
            if pbar is not None:
                pbar.set_postfix_str(f"{name} ({f[0]:g}, {f[1]:g})°")
            with torch.no_grad():
                results[name].append(model.psf_result([list(f)], [wavelength], ks=ks, depth=depth))
            if pbar is not None:
                pbar.update(1)
    ref = results.get(reference)
    rows, pairs = [], []
    for i, f in enumerate(fields):
        truth = ground_truth(hl, f, wavelength, ks, depth)
        for name in models:
            r = results[name][i]
            psf = r.psf[0, 0].detach().cpu()  # (the ground truth is a CPU tensor)
            rf = None if ref is None else ref[i]
            row = {"field_x_deg": f[0], "field_y_deg": f[1], "model": name,
                   f"l1_vs_{reference}": (float(relative_l1(psf, rf.psf[0, 0].detach().cpu())) if rf is not None
                                          else None),
                   "l1_vs_truth": float(relative_l1(psf, truth)) if truth is not None else None,
                   "center_offset_um": (float(torch.linalg.vector_norm(r.center[0, 0].detach()
                                                                       - rf.center[0, 0].detach())) * 1e3
                                        if rf is not None else None),
                   "energy_outside": float(r.energy_outside[0, 0].detach()),
                   "zernike_residual_waves": None, "rays_on_discontinuity": None, "n_pupil": None,
                   "error_estimate": None}
            if "error_estimate" in r.info:  # a model that converges its own sampling (exit_pupil) says how far
                est = float(r.info["error_estimate"][0, 0])
                row["n_pupil"] = int(r.info["n_pupil"][0, 0])
                row["error_estimate"] = None if est != est else est
            if name == "pupil":
                row["zernike_residual_waves"] = float(r.info["residual_rms_waves"][0, 0])
            if name == "raytrace":
                row["rays_on_discontinuity"] = r.info["discontinuity"][0][0]["fraction_on_discontinuity"]
            rows.append(row)
        for a in range(len(models)):
            for b in range(a + 1, len(models)):
                pa, pb = results[models[a]][i].psf[0, 0].detach(), results[models[b]][i].psf[0, 0].detach()
                pairs.append({"field_x_deg": f[0], "field_y_deg": f[1], "a": models[a], "b": models[b],
                              "l1_a_vs_b": float(relative_l1(pa, pb))})
    return {"results": results, "rows": rows, "pairs": pairs}


def _fmt(v, spec=".3g"):
    return "—" if v is None else format(v, spec)


def format_table(rows, reference: str) -> str:
    head = f"{'field (deg)':>14}  {'model':<11} {'L1 vs ' + reference:>16} {'L1 vs truth':>12} {'Δcentre µm':>11} " \
           f"{'outside':>9} {'note':<s}"
    lines = [head]
    for r in rows:
        note = ""
        if r["zernike_residual_waves"] is not None:
            note = f"Zernike residual {r['zernike_residual_waves']:.2g} λ RMS"
        if r["rays_on_discontinuity"]:
            note = f"{100 * r['rays_on_discontinuity']:.1f} % rays on phase steps"
        if r.get("n_pupil") is not None:
            note = f"{r['n_pupil']}² pupil cells, own error ~{_fmt(r.get('error_estimate'), '.1e')}"
        lines.append(f"{'(' + format(r['field_x_deg'], 'g') + ', ' + format(r['field_y_deg'], 'g') + ')':>14}  "
                     f"{r['model']:<11} {_fmt(r['l1_vs_' + reference]):>16} {_fmt(r['l1_vs_truth']):>12} "
                     f"{_fmt(r['center_offset_um'], '.3f'):>11} {_fmt(r['energy_outside'], '.2e'):>9} {note}")
    return "\n".join(lines)


def _compare_lens(args, a: dict, fields):
    """The hybrid lens of ``raywave compare`` (angle fields): the lens file with ``fields`` (degrees) and the
    on-axis field, its DOE replaced by ``--doe`` and fabricated with ``--doe-levels`` etc. where given."""
    from raywave.cli.psf_commands import fabricate_doe
    from raywave.assembly.build import load_hybrid

    wl_list = None if a["wavelength"] is None else [a["wavelength"]]
    hl = load_hybrid(a["path"], a["doe_pitch"], a["doe_size"], a["doe_distance"],
                     sensor_pitch=a["sensor_pitch"], oversample=a["oversample"],
                     fields=[list(f) for f in fields] + [[0.0, 0.0]], wavelengths=wl_list, depth=a["depth"],
                     field_type="angle", stop_edge=a["stop_edge"], edge_step=a["edge_step"])
    if args.doe is not None:
        from raywave.cli.doe_commands import load_doe

        doe, _ = load_doe(args.doe, a["doe_pitch"])
        hl = hl.with_doe(doe, sensor_pitch=a["sensor_pitch"] or hl.sensor_pitch)
        hl.doe_info = {"source": str(args.doe)}
    if a["doe_levels"] is not None or a["doe_wavelength"] is not None or a["doe_material"] is not None:
        if not hasattr(hl, "doe_info"):
            hl.doe_info = {}
        fabricate_doe(hl, a["doe_levels"], a["doe_wavelength"], a["doe_material"])
    if hl.lens.field_type != "angle":
        raise CommandError("compare: the lens's fields are object heights; compare takes field angles")
    return hl.to(a.get("device", "cpu"))


def _write_csv(path: Path, rows: list[dict]) -> None:
    """The comparison rows as ``path`` (CSV, one column per row key)."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)


def _plot_compare(path: Path, results: dict, models, fields, pitch: float, title: str, log: bool) -> None:
    """The PSF grid (rows: models, columns: fields in degrees; ``pitch`` the sensor pitch, mm) as ``path``."""
    from raywave.plotting.psf import plot_psf_grid

    grid = [[results[m][i].psf[0, 0].detach() for i in range(len(fields))] for m in models]
    col_labels = [f"({f[0]:g}, {f[1]:g})°" for f in fields]
    import matplotlib.pyplot as plt

    fig = plot_psf_grid(grid, pitch, models, col_labels, path, log=log, title=title)
    plt.close(fig)


def cmd_compare(args) -> int:
    """``raywave compare``: the lens through every model, then compare.csv, compare.json, compare.png and the
    table (or the JSON report) on stdout."""
    from raywave.cli.psf_commands import check_sources_lit, parse_psf_args

    fields = field_list(args, list(DEFAULT_FIELDS))
    check_angles(fields)
    args.field, args.fields, args.output, args.png, args.rays = None, None, None, None, None  # not psf's here
    a = parse_psf_args(args)  # the lens and DOE options shared with `raywave psf`
    ks = a["ks"]
    out_dir = Path(args.out)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # an error exit prints only the error (one line; its warnings would repeat it)
        hl = _compare_lens(args, a, fields)
        models, notes = parse_models(args.models, _is_blank(hl.doe))
        reference = args.reference.strip().lower()
        if reference not in models:
            raise CommandError(f"--reference: {reference!r} is not among the models compared ({', '.join(models)})")
        wl = hl.lens.primary_wavelength if a["wavelength"] is None else a["wavelength"]
        check_sources_lit(hl, fields, [wl], a["depth"])  # a dark field fails now, not after every model ran
        pbar = bar(args, len(models) * len(fields), "PSF", "compare")
        with pbar, ticking(pbar):
            table = run_compare(hl, models, fields, wl, ks, a["depth"], reference, pbar)
        report_warnings(caught)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = table["rows"]
    _write_csv(out_dir / "compare.csv", rows)
    depth = hl.lens.object_distance if a["depth"] is None else a["depth"]
    report = {"lens": str(args.lens), "doe": args.doe, "wavelength_um": wl,
              "depth_mm": "inf" if math.isinf(depth) else depth, "ks": ks, "pitch_mm": hl.sensor_pitch,
              "models": models, "reference": reference, "notes": notes, "rows": rows, "pairs": table["pairs"]}
    (out_dir / "compare.json").write_text(json_dumps(report, indent=1))
    title = f"{Path(str(args.lens)).stem}: {wl:g} µm, depth {report['depth_mm']} mm (rows: models, columns: fields)"
    _plot_compare(out_dir / "compare.png", table["results"], models, fields, hl.sensor_pitch, title, not args.linear)
    if args.json:
        print(json_dumps(report))
    else:
        for n in notes:
            print(f"note: {n}")
        print(format_table(rows, reference))
        print(f"wrote {out_dir / 'compare.png'}, {out_dir / 'compare.csv'}, {out_dir / 'compare.json'}")
    return 0


def register(sub) -> None:
    from raywave.cli.psf_commands import add_edge_arguments

    p = sub.add_parser(
        "compare", help="PSFs of one hybrid lens through the paper's simulation models, with a table of their errors",
        description="Simulate one hybrid lens with the comparison models of the paper (raywave: the ray-wave engine; "
        "paraxial: thin ideal lens + DOE + propagation; pupil: Zernike-fitted wavefront; raytrace: local grating "
        "approximation with ray binning; exit_pupil: Chen et al. 2021, blank DOE only) and write a PSF grid "
        "(compare.png) and a table of relative L1 errors (compare.csv, compare.json). raywave uses the stop edge of "
        "--stop-edge (default: the exit pupil); raywave_doe is the same engine with the paper's DOE-plane edge.")
    p.add_argument("lens", help="lens file or bundled lens name (as for 'raywave psf')")
    p.add_argument("--doe", default=None, metavar="DOE",
                   help="replace the lens's DOE: a phase map (.npy with --doe-pitch, .npz) or a lens file with a DOE")
    add_field_arguments(p, "0, on axis; degrees")
    p.add_argument("--models", default="all", metavar="LIST",
                   help="'all' (default) or a comma list of raywave, raywave_doe, paraxial, pupil, raytrace, "
                        "exit_pupil")
    p.add_argument("--reference", default="raywave", metavar="MODEL",
                   help="the model the L1 errors are measured against (default raywave)")
    p.add_argument("--wavelength", default=None, metavar="UM", help="µm (default: the lens's primary wavelength)")
    p.add_argument("--depth", default="inf", metavar="MM",
                   help="object distance in mm from the first vertex, or 'inf' (default)")
    p.add_argument("--ks", default="64", metavar="N", help="PSF size in sensor pixels (default 64)")
    p.add_argument("-o", "--out", default="compare", metavar="DIR", help="output folder (default compare/)")
    p.add_argument("--linear", action="store_true", help="linear colour scale (default: logarithmic)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    for flag, meta, text in (
            ("--doe-pitch", "MM", "DOE pixel pitch in mm (overrides the file's)"),
            ("--doe-distance", "MM", "last vertex to DOE plane in mm (overrides the file's)"),
            ("--sensor-pitch", "MM", "PSF pixel pitch in mm (default: the lens's sensor pitch, else the DOE pitch)"),
            ("--oversample", "Q", "simulation samples per DOE pixel per axis"),
            ("--doe-levels", "L", "fabricate the DOE: wrap and quantise it to L levels"),
            ("--doe-wavelength", "UM", "fabricate the DOE: design wavelength in µm (default 0.55)"),
            ("--doe-material", "NAME", "fabricate the DOE: height map in this glass (default FUSED_SILICA)")):
        p.add_argument(flag, default=None, metavar=meta, help=text)
    p.add_argument("--doe-size", nargs="+", default=None, metavar="MM", help="DOE width [height] in mm")
    add_edge_arguments(p)
    p.add_argument("--device", default="cpu", metavar="DEV", help=DEVICE_HELP)
    p.set_defaults(func=cmd_compare)
