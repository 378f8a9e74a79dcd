"""Issue 19 must-show: ``raywave psf`` with ``stop_edge="exit_pupil"`` (and the default DOE rules: Nyquist pitch,
beam-fitted distance before the first caustic) on real lenses, against the Huygens exit-pupil model
(raywave.models.exit_pupil) at 0, 0.7 and 1.0 of each lens's largest field. Prints one JSON line per case (rel L1,
time, DOE grid, warnings). Without ``--n-pupil`` / ``--sensor-pitch`` each case takes the reference settings of
tests/test_stop_edge_real_lenses.py (384² cells and 3 µm pixels where 192² cells at the DOE pitch do not settle it).

    PYTHONPATH=. python benchmarks/stop_edge_real_lenses.py [--ks 32] [--lens NAME ...] [-o FILE]
"""

import argparse
import time
import warnings
from pathlib import Path

import torch

from _report import emit_row  # noqa: E402  (benchmarks/ is on sys.path)

ROOT = Path(__file__).resolve().parents[1]
#: (lens, field fraction) → (Huygens pupil cells, sensor pitch mm): as tests/test_stop_edge_real_lenses.py SETTINGS
SETTINGS = {("asphere_f13", 0.7): (384, 3e-3), ("asphere_f13", 1.0): (384, 3e-3), ("double_gauss", 0.7): (384, 3e-3),
            ("double_gauss", 1.0): (384, 3e-3), ("singlet_nbk7_50", 1.0): (384, 3e-3)}
LENSES = {
    "cooke_triplet": "cooke_triplet",  # bundled (Optiland's sample Cooke triplet)
    "cooke_floa": str(ROOT / "tests/data/zmx/cooke_floa.zmx"),
    "double_gauss": str(ROOT / "tests/data/zmx/double_gauss_ohara_cdgm_hoya.zmx"),
    "singlet_nbk7_50": str(ROOT / "tests/data/real_lenses/singlet_nbk7_50.zmx"),
    "asphere_f13": str(ROOT / "tests/data/real_lenses/asphere_f13_nsf11.zmx"),
}


def run_case(path, frac, ks=32, n_pupil=None, sensor_pitch=None):
    from raywave.cli.psf_commands import compute_psf
    from raywave.lens.build import load_lens, resolve_lens_path
    from raywave.models.exit_pupil import ExitPupilModel

    lens = load_lens(resolve_lens_path(path))
    fmax = max(float(f) for f in lens.fields)
    fld = (0.0, frac * fmax)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = time.perf_counter()
        out = compute_psf(path, field=fld, ks=ks, stop_edge="exit_pupil", sensor_pitch=sensor_pitch)
        dt = time.perf_counter() - t
        hl = out["hybrid"]
        m = ExitPupilModel(hl, **({} if n_pupil is None else {"n_pupil": n_pupil}))
        t = time.perf_counter()
        ref = m.psf_result(fld, hl.lens.primary_wavelength, ks=ks).psf[0, 0].numpy()
        dt_ref = time.perf_counter() - t
    err = float(abs(out["psf"] - ref).sum())
    names = sorted({f"{w.category.__name__}: {str(w.message)[:120]}" for w in caught
                    if w.category.__name__ not in ("SensorCropWarning",)})
    return dict(field_deg=fld[1], rel_l1=err, time_s=dt, huygens_s=dt_ref, doe=hl.doe_info, warnings=names,
                energy_outside=out["energy_outside"], sensor_pitch=out["pitch"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ks", type=int, default=32)
    ap.add_argument("--lens", nargs="*", default=list(LENSES))
    ap.add_argument("--fields", nargs="*", type=float, default=[0.0, 0.7, 1.0])
    ap.add_argument("--n-pupil", type=int, default=None, help="Huygens pupil cells a side (default 192)")
    ap.add_argument("--sensor-pitch", type=float, default=None, help="mm (default: the lens's, else the DOE pitch)")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    rows = []
    for name in a.lens:
        for frac in a.fields:
            n_pupil, pitch = SETTINGS.get((name, frac), (None, None))
            n_pupil, pitch = a.n_pupil or n_pupil, a.sensor_pitch or pitch
            r = dict(lens=name, field_frac=frac, ks=a.ks, n_pupil=n_pupil or 192,
                     **run_case(LENSES[name], frac, a.ks, n_pupil, pitch))
            emit_row(rows, r, a.output)
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
