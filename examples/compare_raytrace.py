"""Ray tracing with the local grating approximation vs ray-wave, for a low- and a high-frequency DOE (the paper's
Fig. S4).

The bundled asphere (asphere_hk51) with three DOEs 0.7 mm behind it (1 µm pixels):

* ``blank``: no phase;
* ``low``: a smooth, low-frequency BINARY_2 phase (60 rad of (r/1.5 mm)⁴, continuous, unwrapped);
* ``high``: a chirped phase, 250 rad of (r/1.5 mm)⁴, whose local frequency rises from zero at the centre to
  1/9 µm⁻¹ at r = 1.5 mm,
  fabricated as a 4-level kinoform (the usual fabricated DOE): its phase steps grow denser toward the edge.

Every DOE is simulated by the ray-wave engine and by ray tracing through the DOE's local phase gradient
(:class:`raywave.models.local_grating.LocalGratingModel`, rays binned on the 3 µm sensor pixels) at 0°, 7° and
14° (the off-axis beams cross the DOE further out). The two agree where the DOE is smooth and part where its
steps get dense; the ray model warns where the phase has no gradient.

Writes compare_raytrace.png (rows: DOE × model, columns: fields; log scale), compare_raytrace_does.png (the DOE
phase maps at 0.53 µm) and compare_raytrace.json (relative L1 ray tracing vs ray-wave, the fraction of rays on
phase steps, the radii of the steps).

    python examples/compare_raytrace.py [-o examples_out/compare_raytrace] [--quick]
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

from raywave.doe import Binary2DOE, BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens, SensorCropWarning  # noqa: E402
from raywave.lens.build import bundled_lens_path, load_lens  # noqa: E402
from raywave.models.interface import make_model, relative_l1  # noqa: E402
from raywave.models.local_grating import DiscontinuousPhaseWarning  # noqa: E402
from raywave.plotting.psf import plot_psf_grid  # noqa: E402

WL = 0.53
NORM_R = 1.5  # mm


def make_does(n: int, pitch: float) -> dict:
    """The three DOEs on an n×n grid of ``pitch`` mm."""
    low = Binary2DOE([0.0, 60.0], NORM_R, n, pitch)  # 60 rad of ρ⁴: ≤ 0.16 rad per pixel, continuous
    high = Binary2DOE([0.0, 250.0], NORM_R, n, pitch)  # 250 ρ⁴: 0.67 rad per pixel at the rim
    high.fabricate(levels=4, wavelength=WL)
    return {"blank": BlankDOE(n, pitch), "low": low, "high (4 levels)": high}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/compare_raytrace")
    ap.add_argument("--quick", action="store_true", help="two fields, fewer rays, small crops (for the tests)")
    args = ap.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    warnings.filterwarnings("ignore", category=SensorCropWarning)  # 14° images beyond the 16:9 sensor's height

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    fields = (0.0, 14.0) if args.quick else (0.0, 7.0, 14.0)
    ks = 32 if args.quick else 64
    rays = 201 if args.quick else 601
    pitch, n = 1e-3, 3800
    does = make_does(n, pitch)
    pts = [(0.0, f) for f in fields]
    grid, labels, report = [], [], {"fields_deg": list(fields), "wavelength_um": WL, "ks": ks, "doe": {}}
    for name, doe in does.items():
        hl = HybridLens(lens, doe, 0.7)
        with torch.no_grad():
            rw = make_model("raywave", hl).psf_result(pts, WL, ks=ks)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", DiscontinuousPhaseWarning)
                rt = make_model("raytrace", hl, rays=rays).psf_result(pts, WL, ks=ks)
        steps = [str(w.message) for w in caught if issubclass(w.category, DiscontinuousPhaseWarning)]
        err = relative_l1(rt.psf[:, 0], rw.psf[:, 0]).tolist()
        disc = [row[0] for row in rt.info["discontinuity"]]
        report["doe"][name] = {
            "l1_raytrace_vs_raywave": err,
            "fraction_of_rays_on_phase_steps": [d["fraction_on_discontinuity"] for d in disc],
            "step_radii_mm": [[d.get("doe_r_min"), d.get("doe_r_max")] for d in disc],
            "warnings": steps[:1]}
        grid += [[rt.psf[i, 0] for i in range(len(fields))], [rw.psf[i, 0] for i in range(len(fields))]]
        labels += [f"{name}: ray tracing", f"{name}: ray-wave"]
        print(f"DOE {name:16s} L1 ray tracing vs ray-wave: "
              + ", ".join(f"{f:g}°: {e:.3f}" for f, e in zip(fields, err))
              + "; rays on phase steps: " + ", ".join(f"{100 * d['fraction_on_discontinuity']:.0f} %" for d in disc))
    fig = plot_psf_grid(grid, 3e-3, labels, [f"{f:g}°" for f in fields], out / "compare_raytrace.png", log=True,
                        title="asphere_hk51 at 0.53 µm: ray tracing (local grating) vs ray-wave")
    plt.close(fig)

    # the DOE phase maps (the central 3 mm, where the beams land)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), constrained_layout=True)
    c = slice(n // 2 - 1500, n // 2 + 1500, 2)  # 2 µm steps resolve the 9 µm rim period
    for ax, (name, doe) in zip(axes, does.items()):
        with torch.no_grad():
            ph = torch.remainder(doe.phase_pixels(WL, c, c), 2 * torch.pi).numpy()
        im = ax.imshow(ph, origin="lower", extent=[-1.5, 1.5, -1.5, 1.5], cmap="twilight", vmin=0, vmax=2 * torch.pi,
                       interpolation="antialiased")
        ax.set_title(f"{name} (phase mod 2π)", fontsize=9)
        ax.set_xlabel("x (mm)")
    axes[0].set_ylabel("y (mm)")
    fig.colorbar(im, ax=axes[-1], shrink=0.8, label="rad")
    fig.savefig(out / "compare_raytrace_does.png", dpi=110)
    plt.close(fig)
    report["seconds"] = round(time.time() - t0, 1)
    (out / "compare_raytrace.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {out} in {report['seconds']} s")


if __name__ == "__main__":
    main()
