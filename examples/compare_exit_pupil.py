"""Chen et al. (2021)'s exit-pupil diffraction model vs ray-wave on a clear aperture (the paper's Fig. S5).

Two lenses with a blank DOE (a clear square aperture larger than every beam):

* an ideal F/4 lens (f = 5 mm, DOE 1 mm behind it, 1 µm sensor pixels) at 0° and 5°: both models against each
  other and the on-axis Debye focus (the ground truth);
* the bundled asphere (asphere_hk51, DOE 0.7 mm behind it, 1 µm pixels) at 0°, 7°, 14° (17.5° without
  ``--quick``): with the default stop edge both models form the stop's edge at the exit pupil and agree to
  ~1e-3; the paper's ray-wave model (``HybridLens(stop_edge="doe")``) cuts it on the DOE plane, which shows in the
  fine interference detail of strongly aberrated fields (docs/ray-wave.md, "Where the stop's edge diffracts").

Writes compare_exit_pupil.png (rows: model per lens, columns: fields; log scale) and compare_exit_pupil.json
(relative L1 between the models per field, and to the Debye focus).

    python examples/compare_exit_pupil.py [-o examples_out/compare_exit_pupil] [--quick]
"""

from __future__ import annotations

import argparse
import json
import math
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
from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens  # noqa: E402
from raywave.models.debye import debye_psf  # noqa: E402
from raywave.models.interface import make_model, relative_l1  # noqa: E402
from raywave.plotting.psf import plot_psf_grid  # noqa: E402


def compare(hl, fields, wl, ks, n_pupil):
    pts = [(0.0, f) for f in fields]
    with torch.no_grad():
        rw = make_model("raywave", hl).psf(pts, wl, ks=ks)[:, 0]
        ep = make_model("exit_pupil", hl, n_pupil=n_pupil).psf(pts, wl, ks=ks)[:, 0]
    return rw, ep, relative_l1(ep, rw).tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/compare_exit_pupil")
    ap.add_argument("--quick", action="store_true", help="fewer fields, coarser pupil, small crops (for the tests)")
    args = ap.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    warnings.filterwarnings("ignore", category=SensorCropWarning)  # 14°+ images beyond the 16:9 sensor's height
    report = {}

    # ideal lens: ground truth on axis
    wl, ks = 0.55, (20 if args.quick else 32)
    ideal = HybridLens(ideal_lens(5.0, f_number=4.0, wavelengths=(wl,)), BlankDOE(1400, 1e-3), 1.0, sensor_pitch=1e-3)
    f_ideal = (0.0, 5.0)
    rw_i, ep_i, err_i = compare(ideal, f_ideal, wl, ks, 128 if args.quick else 192)
    truth = debye_psf(math.sin(math.atan(0.5 / 4.0)), wl, ks, 1e-3, oversample=15).psf
    report["ideal_f4"] = {"fields_deg": list(f_ideal), "wavelength_um": wl, "l1_exit_pupil_vs_raywave": err_i,
                          "l1_vs_debye_on_axis": {"raywave": float(relative_l1(rw_i[0], truth)),
                                                  "exit_pupil": float(relative_l1(ep_i[0], truth))}}

    # the bundled asphere
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    f_asph = (0.0, 7.0, 14.0) if args.quick else (0.0, 7.0, 14.0, 17.5)
    size = default_doe_size(lens, 0.7, [[0.0, f] for f in f_asph], [0.53])[0]
    asph = HybridLens(lens, BlankDOE(int(math.ceil(size / 1e-3)) // 2 * 2, 1e-3), 0.7, sensor_pitch=1e-3)
    ks_a = 24 if args.quick else 48
    rw_a, ep_a, err_a = compare(asph, f_asph, 0.53, ks_a, 128 if args.quick else 192)
    report["asphere_hk51"] = {"fields_deg": list(f_asph), "wavelength_um": 0.53, "l1_exit_pupil_vs_raywave": err_a}

    for name, rw, ep, fields in (("ideal F/4", rw_i, ep_i, f_ideal), ("asphere_hk51", rw_a, ep_a, f_asph)):
        fig = plot_psf_grid([[rw[i] for i in range(len(fields))], [ep[i] for i in range(len(fields))]], 1e-3,
                            [f"{name}: ray-wave", f"{name}: exit pupil (Chen et al.)"], [f"{f:g}°" for f in fields],
                            out / f"compare_exit_pupil_{name.split()[0].lower()}.png", log=True,
                            title=f"{name}: ray-wave vs exit-pupil diffraction, clear aperture")
        plt.close(fig)
    report["seconds"] = round(time.time() - t0, 1)
    (out / "compare_exit_pupil.json").write_text(json.dumps(report, indent=1))
    print("ideal F/4: L1 exit pupil vs ray-wave " + ", ".join(f"{f:g}°: {e:.2e}" for f, e in zip(f_ideal, err_i))
          + f"; on axis vs Debye: ray-wave {report['ideal_f4']['l1_vs_debye_on_axis']['raywave']:.2e}, "
          f"exit pupil {report['ideal_f4']['l1_vs_debye_on_axis']['exit_pupil']:.2e}")
    print("asphere_hk51: L1 exit pupil vs ray-wave " + ", ".join(f"{f:g}°: {e:.3f}" for f, e in zip(f_asph, err_a)))
    print(f"wrote {out} in {report['seconds']} s")


if __name__ == "__main__":
    main()
