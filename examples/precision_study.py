"""The precision study of the ray-wave paper (Fig. S2): the DOE-plane field traced in float32 vs float64.

The bundled asphere, a point source 1 m away (its optical paths are ~10⁶ waves long), the faithful
(ray-splatting) field on the DOE plane from the *same* rays traced in float32 and in float64, their PSFs,
and the measured per-ray phase errors. Writes precision_study.png and precision_study.json.

    python examples/precision_study.py [-o examples_out/precision] [--depth 1000] [--rays 400000]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from raywave.doe import BlankDOE  # noqa: E402
from raywave.hybrid import HybridLens  # noqa: E402
from raywave.hybrid.precision import ray_phase_error  # noqa: E402
from raywave.lens.build import bundled_lens_path, load_lens  # noqa: E402


def _on_doe_grid(fd, hl) -> torch.Tensor:
    """The field's envelope placed on the whole DOE grid (so that two windows compare)."""
    full = torch.zeros(hl.doe.sim_shape(hl.oversample), dtype=torch.complex128)
    iy0, iy1, ix0, ix1 = fd.box
    full[iy0:iy1, ix0:ix1] = fd.envelope
    return full


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/precision")
    ap.add_argument("--depth", type=float, default=1000.0, help="object distance (mm)")
    ap.add_argument("--rays", type=int, default=400_000)
    ap.add_argument("--wavelength", type=float, default=0.55)
    args = ap.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    hl = HybridLens(lens, BlankDOE(1000, 1e-3), 0.7)
    fields, psfs, report = {}, {}, {}
    for dt in tqdm((torch.float64, torch.float32), desc="precisions"):  # float64 is the reference
        name = str(dt).replace("torch.", "")
        fd = hl.doe_fields((0, 0), args.wavelength, depth=args.depth, mode="faithful", rays=args.rays,
                           generator=torch.Generator().manual_seed(0), trace_dtype=dt)[0][0]
        fields[name] = fd.detach()
        psfs[name] = hl.psf(ks=64, cache=[[fd]])[0, 0].detach()
    err = ray_phase_error(lens, hl.doe_z(), (0, 0), args.wavelength, n=201, dtype=torch.float32, depth=args.depth)
    report["float32_phase_error_rms_rad"] = err["rms"]  # per ray, against the same rays traced in float64
    report["float32_phase_error_max_rad"] = err["max"]
    report["psf_l1_difference"] = float((psfs["float32"] - psfs["float64"]).abs().sum())
    a, b = (_on_doe_grid(fields[k], hl) for k in ("float32", "float64"))
    report["field_relative_l2_difference"] = float((a - b).norm() / b.norm())
    report.update(depth_mm=args.depth, wavelength_um=args.wavelength, rays=args.rays)
    (out / "precision_study.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))

    # show the phase relative to a smooth fit (piston, tilt, defocus, primary spherical) of the float64 phase:
    # what is left is the wavefront's fine structure (smooth for float64, ray-to-ray noise for float32)
    x, y = err["xy"].unbind(-1)
    r2 = x * x + y * y
    basis = torch.stack([torch.ones_like(x), x, y, r2, r2 * r2, r2 ** 3], -1)
    coef = torch.linalg.lstsq(basis, err["phase64"][:, None]).solution
    smooth = (basis @ coef)[:, 0]
    ph64 = err["phase64"] - smooth
    ph32 = ph64 + err["error"]
    xy = err["xy"].numpy()
    fig, axes = plt.subplots(2, 3, figsize=(13, 8), constrained_layout=True)
    lim = float(ph32.abs().max())
    panels = [(ph64, "float64: phase at the DOE − smooth fit (rad)", "RdBu_r", (-lim, lim)),
              (ph32, "float32: phase at the DOE − smooth fit (rad)", "RdBu_r", (-lim, lim)),
              (err["error"], "float32 − float64 phase (rad)", "RdBu_r", None)]
    for ax, (val, title, cmap, lim) in zip(axes[0], panels):
        vmin, vmax = lim if lim else (-float(val.abs().max()), float(val.abs().max()))
        sc = ax.scatter(xy[:, 0], xy[:, 1], c=val.numpy(), s=1.0, cmap=cmap, vmin=vmin, vmax=vmax, linewidths=0)
        ax.set_aspect("equal"), ax.set_title(title), ax.set_xlabel("x (mm)"), ax.set_ylabel("y (mm)")
        fig.colorbar(sc, ax=ax, shrink=0.8)
    diff = psfs["float32"] - psfs["float64"]
    for ax, (img, title, cmap) in zip(axes[1], [(psfs["float64"], "PSF, float64 tracing", "inferno"),
                                               (psfs["float32"], "PSF, float32 tracing", "inferno"),
                                               (diff, "PSF difference", "RdBu_r")]):
        v = float(img.abs().max())
        im = ax.imshow(img.numpy(), origin="lower", cmap=cmap, vmin=-v if cmap == "RdBu_r" else 0, vmax=v)
        ax.set_title(title + " (3 µm pixels)"), ax.set_xticks([]), ax.set_yticks([])
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"Coherent tracing precision, object at {args.depth:g} mm: float32 phase error "
                 f"{report['float32_phase_error_rms_rad']:.2f} rad RMS (max {report['float32_phase_error_max_rad']:.2f})"
                 " against float64")
    fig.savefig(out / "precision_study.png", dpi=130)
    print(f"wrote {out}/precision_study.png")


if __name__ == "__main__":
    main()
