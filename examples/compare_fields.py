"""Paraxial wave optics vs the pupil aberration model vs ray-wave across the field (the paper's Fig. S3).

The bundled asphere (asphere_hk51, F/4, f = 7.9 mm) with a blank DOE 0.7 mm behind it (a square grid that holds
the beam at every field; 1 µm pitch), PSFs at 0°, 3.5°, 7°, 10.5°, 14°, 17.5° on its 3 µm sensor pixels, by

* ``paraxial``: the lens as a perfect thin lens of its paraxial EFL (no aberrations at all);
* ``pupil``: a 37-term Zernike (Noll) fit of the traced DOE-plane wavefront on a circular uniform pupil;
* ``raywave``: the ray-wave engine (the reference).

Writes compare_fields.png (rows: models, columns: fields; log scale), compare_fields_linear.png and
compare_fields.json (relative L1 of each model to ray-wave per field and wavelength, the Zernike fit residuals).

    python examples/compare_fields.py [-o examples_out/compare_fields] [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from raywave.doe import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens, SensorCropWarning  # noqa: E402
from raywave.assembly.build import default_doe_size  # noqa: E402
from raywave.lens.build import bundled_lens_path, load_lens  # noqa: E402
from raywave.models.interface import make_model, relative_l1  # noqa: E402
from raywave.plotting.psf import plot_psf_grid  # noqa: E402

FIELDS = (0.0, 3.5, 7.0, 10.5, 14.0, 17.5)
MODELS = ("paraxial", "pupil", "raywave")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/compare_fields")
    ap.add_argument("--quick", action="store_true", help="3 fields, one wavelength, small crops (for the tests)")
    ap.add_argument("--ks", type=int, default=None, help="PSF size in 3 µm pixels (default 48; quick 24)")
    args = ap.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    fields = (0.0, 7.0, 14.0) if args.quick else FIELDS
    wls = [0.53] if args.quick else [0.47, 0.53, 0.66]
    ks = args.ks or (24 if args.quick else 48)
    pitch, dist = 1e-3, 0.7
    size = default_doe_size(lens, dist, [[0.0, f] for f in FIELDS], lens.wavelengths)[0]
    n = int(round(size / pitch)) // 2 * 2
    hl = HybridLens(lens, BlankDOE(n, pitch), dist)
    pts = [(0.0, f) for f in fields]

    res = {}
    # the 16:9 sensor is 3.24 mm tall: the 14° and 17.5° images (y = 2.0, 2.5 mm) lie beyond its edge, which does
    # not change their PSFs
    warnings.filterwarnings("ignore", category=SensorCropWarning)
    with torch.no_grad():
        for m in MODELS:
            res[m] = make_model(m, hl).psf_result(pts, wls, ks=ks)
    ref = res["raywave"].psf
    report = {"lens": "asphere_hk51", "doe": f"blank {n}x{n} at {pitch * 1e3:g} um, {dist} mm after the lens",
              "fields_deg": list(fields), "wavelengths_um": wls, "ks": ks, "pitch_mm": hl.sensor_pitch,
              "l1_vs_raywave": {m: relative_l1(res[m].psf, ref).tolist() for m in MODELS if m != "raywave"},
              "zernike_residual_rms_waves": res["pupil"].info["residual_rms_waves"].tolist()}
    j = wls.index(0.53)
    grid = [[res[m].psf[i, j] for i in range(len(fields))] for m in MODELS]
    labels = [f"{f:g}°" for f in fields]
    for log, name in ((True, "compare_fields.png"), (False, "compare_fields_linear.png")):
        fig = plot_psf_grid(grid, hl.sensor_pitch, list(MODELS), labels, out / name, log=log,
                            title="asphere_hk51 at 0.53 µm: paraxial wave optics (top), pupil aberration model "
                                  "(middle), ray-wave (bottom)")
        plt.close(fig)
    report["seconds"] = round(time.time() - t0, 1)
    (out / "compare_fields.json").write_text(json.dumps(report, indent=1))
    for m, errs in report["l1_vs_raywave"].items():
        print(f"{m:9s} L1 vs ray-wave at 0.53 µm: " + ", ".join(f"{f:g}°: {e[j]:.3f}" for f, e in zip(fields, errs)))
    print("Zernike residual (waves RMS) at 0.53 µm: "
          + ", ".join(f"{r[j]:.1e}" for r in report["zernike_residual_rms_waves"]))
    print(f"wrote {out} in {report['seconds']} s")


if __name__ == "__main__":
    main()
