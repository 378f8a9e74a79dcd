"""Classical analysis commands: mtf, fan, opd (tables or JSON on stdout, PNG with -o)."""

from __future__ import annotations

import math
import warnings

import torch

from raywave.cli.errors import CommandError, integer_arg, json_dumps, number_arg
from raywave.cli.fields import add_field_argument, field_points

LENS_HELP = "lens file (.json raywave or DeepLens-style, .zmx) or a bundled lens name"


def _load(name_or_path):
    from raywave.lens.build import load_lens, resolve_lens_path

    return load_lens(resolve_lens_path(name_or_path))


def _numbers(text, flag, positive=False):
    if text is None:
        return None
    vals = [number_arg(v, flag, nonneg=not positive, positive=positive) for v in str(text).replace(",", " ").split()]
    if not vals:
        raise CommandError(f"{flag}: no values given")
    return vals


def _wavelengths(args, lens):
    wls = _numbers(args.wavelength, "--wavelength", positive=True)
    if wls is None:
        return None
    for w in wls:
        if w > 100:
            raise CommandError(f"--wavelength: {w:g} is in µm (raywave's unit): {w:g} µm is not light; "
                               f"did you mean {w / 1000:g} µm ({w:g} nm)?")
    return wls


def _unit(lens) -> str:
    return "°" if lens.field_type == "angle" else " mm"


def _nan_none(rows):
    return [[None if (isinstance(v, float) and math.isnan(v)) else v for v in row] for row in rows]


# ---------------------------------------------------------------------------- mtf
def has_doe(path) -> bool:
    from raywave.io import read_lens_spec
    from raywave.lens.build import resolve_lens_path

    return bool(read_lens_spec(resolve_lens_path(path)).get("doe"))


def _mtf_frequencies(args, lens):
    """(every frequency to compute (K,), the indices of the table's rows): the ``--freq`` values, plus a curve of 65
    from 0 to the cutoff for the PNG; without ``--freq`` the table shows every 8th of the curve."""
    from raywave.lens.mtf import cutoff_frequency

    table = _numbers(args.freq, "--freq")
    top = cutoff_frequency(lens)
    if args.model != "pupil" and args.kind == "diffraction" and args.pitch is not None:
        top = min(top, 0.5 / number_arg(args.pitch, "--pitch", positive=True))
    curve = torch.linspace(0.0, top, 65, dtype=torch.float64).tolist() if (args.output or table is None) else []
    allf = sorted(set(curve) | set(table or []))
    rows = [allf.index(v) for v in (table if table is not None else curve[::8])]
    return allf, rows


def compute_mtf(args):
    """(MTFResult, lens, note, table rows) for ``raywave mtf``'s arguments."""
    from raywave.lens.mtf import diffraction_mtf, geometric_mtf

    lens = _load(args.lens)
    fields = field_points(args, lens)
    wls = _wavelengths(args, lens)
    freqs, rows = _mtf_frequencies(args, lens)
    model = args.model
    if model == "auto":
        model = "raywave" if (args.kind == "diffraction" and has_doe(args.lens)) else "pupil"
    if args.kind == "geometric":
        if model == "raywave":
            raise CommandError("--model raywave: the geometric MTF has no wave model; use --kind diffraction")
        n = integer_arg(args.pupil, "--pupil", minimum=4)
        res = geometric_mtf(lens, fields, freqs, wls, pupil=("grid", n), scale=not args.no_scale)
        note = (f"geometric MTF from a {n}×{n} pupil grid" + ("" if args.no_scale else ", × the diffraction limit"))
        return res, lens, note, rows
    if model == "raywave":
        from raywave.assembly.build import load_hybrid
        from raywave.imaging.mtf import raywave_mtf
        from raywave.lens.build import resolve_lens_path

        hl = load_hybrid(resolve_lens_path(args.lens))
        pitch = None if args.pitch is None else number_arg(args.pitch, "--pitch", positive=True)
        res, outside = raywave_mtf(hl, fields, freqs, wls, pitch=pitch, ks=integer_arg(args.ks, "--ks", minimum=8))
        note = ("diffraction MTF through the ray-wave PSF (lens + DOE), PSF energy outside the crop "
                + ", ".join(f"{100 * float(o):.2g} %" for o in outside))
        return res, hl.lens, note, rows
    n = integer_arg(args.pupil, "--pupil", minimum=8)
    res = diffraction_mtf(lens, fields, freqs, wls, n=n)
    note = f"diffraction (pupil FFT) MTF, {n}×{n} pupil grid"
    if has_doe(args.lens):
        note += "; the DOE is NOT included (use --model raywave)"
    return res, lens, note, rows


def cmd_mtf(args) -> int:
    res, lens, note, rows = compute_mtf(args)
    unit = _unit(lens)
    table = {"kind": res.kind, "note": note, "unit": "cycles/mm", "wavelengths_um": res.wavelengths,
             "weights": res.weights, "cutoff": res.cutoff, "frequencies": res.frequencies[rows].tolist(),
             "fields": res.fields.tolist(), "field_type": lens.field_type,
             "tangential": _nan_none(res.tangential[:, rows].tolist()),
             "sagittal": _nan_none(res.sagittal[:, rows].tolist())}
    if args.json:
        print(json_dumps(table))
    else:
        print(f"MTF of {lens.name or args.lens}: {note}; {', '.join(f'{w:g}' for w in res.wavelengths)} µm; "
              f"cutoff {res.cutoff:.1f} cycles/mm")
        print(f"  {'cycles/mm':>10s}" + "".join(f"{f'{f[1]:g}{unit} T':>11s}{f'{f[1]:g}{unit} S':>11s}"
                                                   for f in res.fields.tolist()))
        for k in rows:
            nu = float(res.frequencies[k])
            cells = []
            for i in range(res.fields.shape[0]):
                for v in (float(res.tangential[i, k]), float(res.sagittal[i, k])):
                    cells.append(f"{'vignetted' if math.isnan(v) else f'{v:.4f}':>11s}")
            print(f"  {nu:>10.4g}" + "".join(cells))
    if args.output:
        from raywave.lens.mtf import diffraction_limited_mtf
        from raywave.plotting import plot_mtf

        ref = diffraction_limited_mtf(res.frequencies, res.cutoff).numpy()
        plot_mtf(res, args.output, unit, title=f"{lens.name or args.lens}: {note}", reference=ref)
        if not args.json:
            print(f"wrote {args.output}")
    return 0


# ---------------------------------------------------------------------------- fan
def cmd_fan(args) -> int:
    from raywave.lens.fans import opd_fan, ray_fan

    lens = _load(args.lens)
    fields = field_points(args, lens)
    wls = _wavelengths(args, lens)
    n = integer_arg(args.rays, "--rays", minimum=3)
    fan = ray_fan(lens, fields, wls, n)
    opd = opd_fan(lens, fields, wls, n)
    out = {"unit": "um", "opd_unit": "waves", "pupil": fan.pupil.tolist(), "fields": fan.fields.tolist(),
           "field_type": lens.field_type, "wavelengths_um": fan.wavelengths,
           "ey": _nan3(fan.ey * 1e3), "ex": _nan3(fan.ex * 1e3), "opd_tangential": _nan3(opd.w_t),
           "opd_sagittal": _nan3(opd.w_s)}
    if args.json:
        print(json_dumps(out))
    else:
        unit = _unit(lens)
        print(f"ray fans of {lens.name or args.lens} (µm, relative to the primary wavelength's chief ray; "
              f"{n} rays per fan)")
        for i, f in enumerate(fan.fields.tolist()):
            for w, wl in enumerate(fan.wavelengths):
                ey, ex = fan.ey[i, w] * 1e3, fan.ex[i, w] * 1e3
                print(f"  field {f[1]:g}{unit}" + (f" (x {f[0]:g})" if f[0] else "") + f", {wl:g} µm: "
                      f"ey at py=-1/0/+1: {_fmt(ey[0])} / {_fmt(ey[n // 2])} / {_fmt(ey[-1])}; "
                      f"ex at px=+1: {_fmt(ex[-1])}; OPD P-V {_ptv(opd.w_t[i, w], opd.w_s[i, w])} waves")
    if args.output:
        from raywave.plotting import plot_fans

        plot_fans(fan, args.output, _unit(lens), title=f"{lens.name or args.lens}: ray fans", opd=opd)
        if not args.json:
            print(f"wrote {args.output}")
    return 0


def _nan3(t):
    return [[[None if math.isnan(v) else v for v in row] for row in plane] for plane in t.tolist()]


def _fmt(v) -> str:
    v = float(v)
    return "vignetted" if math.isnan(v) else f"{v:.4g}"


def _ptv(a, b) -> str:
    v = torch.cat([a, b])
    v = v[torch.isfinite(v)]
    return "n/a" if v.numel() == 0 else f"{float(v.max() - v.min()):.4g}"


# ---------------------------------------------------------------------------- opd
def cmd_opd(args) -> int:
    from raywave.lens.opd import opd_map, square_pupil_grid, zernike_fit

    lens = _load(args.lens)
    fields = field_points(args, lens)
    if len(fields) != 1:
        raise CommandError("--field: the OPD map takes one field point")
    wls = _wavelengths(args, lens)
    if wls is not None and len(wls) != 1:
        raise CommandError("--wavelength: the OPD map takes one wavelength")
    n = integer_arg(args.grid, "--grid", minimum=4)
    terms = integer_arg(args.zernike, "--zernike", minimum=1)
    m = opd_map(lens, fields[0], None if wls is None else wls[0], pupil=square_pupil_grid(n, lens.device))
    if not bool(m.valid.any()):
        raise CommandError(f"field {fields[0]}: every ray is vignetted; there is no wavefront")
    fit = zernike_fit(m, terms, args.ordering)
    out = {"field": list(fields[0]), "field_type": lens.field_type, "wavelength_um": m.wavelength, "unit": "waves",
           "rms": m.rms(), "peak_to_valley": m.peak_to_valley(), "zernike_ordering": fit.ordering,
           "zernike": fit.coefficients.tolist(), "zernike_residual_rms": fit.residual_rms}
    if args.json:
        print(json_dumps(out))
    else:
        print(f"OPD of {lens.name or args.lens} at field {fields[0]}, {m.wavelength:g} µm (waves, chief-ray "
              f"reference sphere): RMS {m.rms():.4f}, P-V {m.peak_to_valley():.4f}")
        print(f"{fit.ordering} Zernike fit, {terms} terms (residual RMS {fit.residual_rms:.2e} waves):")
        for name, c in zip(fit.names(), fit.coefficients.tolist()):
            if abs(c) >= args.show_above:
                print(f"  {name:<20s} {c:>12.6f}")
    if args.output:
        from raywave.plotting import plot_opd

        plot_opd(m, fit, args.output, n)
        if not args.json:
            print(f"wrote {args.output}")
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub) -> None:
    p = sub.add_parser("mtf", help="MTF (diffraction or geometric) per field, tangential and sagittal")
    p.add_argument("lens", help=LENS_HELP)
    add_field_argument(p)
    p.add_argument("--wavelength", default=None, help="µm, one or several comma-separated (default: the primary)")
    p.add_argument("--freq", default=None, help="frequencies, cycles/mm, comma-separated (default: 0 … cutoff)")
    p.add_argument("--kind", choices=["diffraction", "geometric"], default="diffraction")
    p.add_argument("--model", choices=["auto", "pupil", "raywave"], default="auto",
                   help="diffraction MTF from the pupil FFT of the refractive lens, or through the ray-wave PSF "
                        "(lens + DOE); auto: raywave for lens files with a DOE")
    p.add_argument("--pupil", default="64", help="pupil samples across (FFT grid / geometric ray grid)")
    p.add_argument("--no-scale", action="store_true", help="geometric MTF without the diffraction limit factor")
    p.add_argument("--pitch", default=None, help="ray-wave PSF pixel pitch, mm (default λN/4)")
    p.add_argument("--ks", default="128", help="ray-wave PSF size, pixels")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="MTF plot PNG")
    p.set_defaults(func=cmd_mtf)

    p = sub.add_parser("fan", help="ray fans (transverse aberration) and OPD fans per field and wavelength")
    p.add_argument("lens", help=LENS_HELP)
    add_field_argument(p)
    p.add_argument("--wavelength", default=None, help="µm, comma-separated (default: the lens's)")
    p.add_argument("--rays", default="21", help="rays per fan")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="fan plot PNG")
    p.set_defaults(func=cmd_fan)

    p = sub.add_parser("opd", help="wavefront (OPD) map of one field with its Zernike fit")
    p.add_argument("lens", help=LENS_HELP)
    add_field_argument(p, "the field point (one)")
    p.add_argument("--wavelength", default=None, help="µm (default: the primary)")
    p.add_argument("--grid", default="65", help="pupil samples across")
    p.add_argument("--zernike", default="37", help="Zernike terms to fit")
    p.add_argument("--ordering", choices=["fringe", "noll"], default="fringe")
    p.add_argument("--show-above", type=float, default=1e-4, help="list coefficients above this (waves)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-o", "--output", default=None, help="OPD map PNG")
    p.set_defaults(func=cmd_opd)
