"""Issue 47, "measure first": the default stop edge (exit pupil, Fresnel step), ``edge_step="asm"`` and
``stop_edge="doe"`` against a *converged* Huygens exit-pupil reference, with the reference's own convergence beside
every figure. The reference is :func:`raywave.models.exit_pupil.huygens_psf` at the pupil grids ``--levels``
(default 256 and 384 cells a side); its error falls as 1/n² (docs/ray-wave.md), so the last two levels give the
Richardson extrapolation (the reference used) and the estimate ``|P_n1 − P_n0| / ((n1/n0)² − 1)`` of the finer
level's error (``ref_error``; an upper bound for the extrapolation while the 1/n² law holds). With three levels the
extrapolations of the two pairs are also compared (``ref_richardson_change``).

Cases: ``asphere:DEG`` (the bundled hybrid_asphere's lens, 6 mm blank DOE of 1 µm pixels at 0.7 mm, 3 µm sensor
pixels, λ 0.53 µm) and ``real:NAME:FRAC`` (the lenses of tests/test_stop_edge_real_lenses.py through ``raywave psf``'s
defaults, at FRAC of the lens's largest field; sensor pitch as the slow test's SETTINGS, 3 µm where they say so).
One JSON line per case.

    PYTHONPATH=. python benchmarks/stop_edge_references.py asphere:0 real:double_gauss:0 [--levels 256 384] [-o F]
"""

import argparse
import json
import time
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
LENSES = {
    "cooke_triplet": "cooke_triplet",
    "double_gauss": str(ROOT / "tests/data/zmx/double_gauss_ohara_cdgm_hoya.zmx"),
    "singlet_nbk7_50": str(ROOT / "tests/data/real_lenses/singlet_nbk7_50.zmx"),
    "asphere_f13": str(ROOT / "tests/data/real_lenses/asphere_f13_nsf11.zmx"),
}
#: sensor pitch (mm) of the slow test where its default (the DOE pitch) leaves most of the PSF outside the crop
PITCH = {("asphere_f13", 0.7): 3e-3, ("asphere_f13", 1.0): 3e-3, ("double_gauss", 0.7): 3e-3,
         ("double_gauss", 1.0): 3e-3, ("singlet_nbk7_50", 1.0): 3e-3}
VARIANTS = {"default": {}, "asm": {"edge_step": "asm"}, "doe": {"stop_edge": "doe"}}


def l1(a, b) -> float:
    return float((torch.as_tensor(a) - torch.as_tensor(b)).abs().sum())


def engine_psfs(case: str, ks: int, variants):
    """{variant: (psf (ks, ks) tensor, seconds) or error string}, plus (lens, field, wavelength, pitch, sensor z,
    centre) for the reference."""
    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens

    kind, *rest = case.split(":")
    out = {}
    if kind == "asphere":
        from raywave.lens.build import bundled_lens_path, load_lens

        lens = load_lens(bundled_lens_path("asphere_hk51"))
        fld, wl, pitch = (0.0, float(rest[0])), 0.53, 3e-3
        for v in variants:
            hl = HybridLens(lens, BlankDOE(6000, 1e-3), 0.7, sensor_pitch=pitch, **VARIANTS[v])
            t = time.perf_counter()
            try:
                r = hl.psf_result(fld, wl, ks=ks)
                out[v] = (r.psf[0, 0].detach(), time.perf_counter() - t)
                center = tuple(float(c) for c in r.center[0, 0])
            except ValueError as e:
                out[v] = str(e)[:200]
        return out, (lens, fld, wl, pitch, float(hl.sensor_z()), center, {})
    from raywave.cli.psf_commands import compute_psf
    from raywave.lens.build import load_lens, resolve_lens_path

    name, frac = rest[0], float(rest[1])
    path = LENSES[name]
    lens = load_lens(resolve_lens_path(path))
    fld = (0.0, frac * max(float(f) for f in lens.fields))
    pitch = PITCH.get((name, frac))
    hl = None
    for v in variants:
        t = time.perf_counter()
        try:
            r = compute_psf(path, field=fld, ks=ks, sensor_pitch=pitch, **VARIANTS[v])
            out[v] = (torch.as_tensor(r["psf"]), time.perf_counter() - t)
            hl = r["hybrid"]
            center = tuple(float(c) for c in r["center"])
        except ValueError as e:
            out[v] = str(e)[:200]
    info = dict(doe_distance=hl.doe_distance, doe_pitch=float(hl.doe.pitch))
    return out, (hl.lens, fld, hl.lens.primary_wavelength, hl.sensor_pitch, float(hl.sensor_z()), center, info)


def reference(lens, fld, wl, pitch, z_s, center, ks, levels, sphere="paraxial"):
    """The Huygens PSFs at ``levels``, the Richardson extrapolation of the last two, its error estimate."""
    from raywave.models.exit_pupil import huygens_psf

    ps, times = {}, {}
    for n in levels:
        t = time.perf_counter()
        ps[n] = huygens_psf(lens, fld, wl, ks=ks, pitch=pitch, center=center, n_pupil=n, sensor_z=z_s,
                            sphere=sphere).psf
        times[n] = time.perf_counter() - t
    n0, n1 = levels[-2], levels[-1]
    r2 = (n1 / n0) ** 2
    ext = ((r2 * ps[n1] - ps[n0]) / (r2 - 1)).clamp_min(0)
    ext = ext / ext.sum()
    row = dict(levels=list(levels), huygens_s=times, ref_error=l1(ps[n1], ps[n0]) / (r2 - 1),
               ref_changes={f"{a}->{b}": l1(ps[b], ps[a]) for a, b in zip(levels, levels[1:])})
    if len(levels) >= 3:
        m0 = levels[-3]
        q2 = (n0 / m0) ** 2
        prev = ((q2 * ps[n0] - ps[m0]) / (q2 - 1)).clamp_min(0)
        row["ref_richardson_change"] = l1(prev / prev.sum(), ext)
    return ext, ps[n1], row


def run(case: str, ks: int, levels, variants, sphere="paraxial"):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        eng, (lens, fld, wl, pitch, z_s, center, info) = engine_psfs(case, ks, variants)
        ext, finest, row = reference(lens, fld, wl, pitch, z_s, center, ks, levels, sphere)
    res = dict(case=case, ks=ks, sphere=sphere, field=fld, wavelength=wl, pitch=pitch, **info, **row)
    for v, r in eng.items():
        if isinstance(r, str):
            res[v] = r
            continue
        res[v] = dict(l1_vs_extrapolated=l1(r[0], ext), l1_vs_finest=l1(r[0], finest), time_s=r[1])
    res["warnings"] = sorted({f"{w.category.__name__}: {str(w.message)[:100]}" for w in caught
                              if w.category.__name__ not in ("SensorCropWarning",)})
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--ks", type=int, default=32)
    ap.add_argument("--levels", type=int, nargs="+", default=[256, 384])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--sphere", default="paraxial", help="the reference sphere: paraxial (default) or rim")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    rows = []
    for c in a.cases:
        r = run(c, a.ks, a.levels, a.variants, a.sphere)
        print(json.dumps(r), flush=True)
        rows.append(r)
        if a.output:
            Path(a.output).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
