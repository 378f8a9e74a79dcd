"""A photo through the bundled hybrid lens: its PSF map, the spatially-varying render, and the sensor.

The astronaut photo (scikit-image, shipped with the package) cut to the sensor's 16:9 and stretched over the whole
1/2.7" sensor of ``hybrid_asphere`` (aspheric singlet + blank 3 mm DOE), a distant object. Writes

* ``input.png``: the scene (upright picture, as the camera outputs it);
* ``psf_map.png``: the N×N ray-wave PSF map (R, G, B = 0.66 / 0.53 / 0.47 µm), sensor orientation (+y up);
* ``rendered.png``: the picture through the lens (seam-free blending between the map's nodes, distortion and
  lateral colour from the PSF centres); ``rendered_noisy.png``: plus Poisson–Gaussian noise and 10-bit ADC;
* ``rendered_rgbd.png``: an RGB-D scene, the same picture on a receding ground plane (the top at infinity, the
  bottom 300 mm away, where the lens focused at infinity blurs): two depth layers, interpolated in 1/z;
* ``comparison.png``: input, render and close-ups of the centre and a corner; ``render_demo.json``: timings.

    python examples/render_demo.py [-o examples_out/render] [--grid 5] [--ks 64] [--quick]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import imageio.v3 as iio  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from raywave.assembly.build import load_hybrid  # noqa: E402
from raywave.imaging import Sensor, linear_to_srgb, psf_map, render_map, render_rgbd, srgb_to_linear  # noqa: E402
from raywave.lens.build import bundled_lens_path  # noqa: E402
from raywave.plotting.psfmap import plot_psf_map  # noqa: E402


def scene(width: int) -> torch.Tensor:
    """(3, H, W) linear float64: the astronaut photo cut to 16:9 and resized to ``width`` pixels."""
    from skimage import data
    from skimage.transform import resize

    a = data.astronaut()  # 512 × 512 sRGB, shipped inside scikit-image
    a = a[60: 60 + 288]  # 16:9 band
    h = round(width * 9 / 16)
    a = resize(a, (h, width), anti_aliasing=True)  # float in [0, 1]
    return srgb_to_linear(torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1))).to(torch.float64))


def to_png(img: torch.Tensor, path) -> np.ndarray:
    enc = (linear_to_srgb(img).detach().numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    iio.imwrite(path, enc)
    return enc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default="examples_out/render")
    ap.add_argument("--grid", type=int, default=5, help="N×N PSF map")
    ap.add_argument("--ks", type=int, default=64, help="PSF size (3 µm sensor pixels)")
    ap.add_argument("--width", type=int, default=1024, help="image width in pixels (16:9)")
    ap.add_argument("--quick", action="store_true", help="3×3 map, ks 32, 384 px wide, fewer traced nodes")
    args = ap.parse_args()
    if args.quick:
        args.grid, args.ks, args.width = 3, 32, 384
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    img = scene(args.width)
    to_png(img, out / "input.png")
    t0 = time.perf_counter()
    near = 300.0  # mm
    pmap = psf_map(hl, (args.grid, args.grid), depths=(float("inf"), near), ks=args.ks, progress=True,
                   **({"rays": 24} if args.quick else {}))
    t_map = time.perf_counter() - t0
    plot_psf_map(pmap, out / "psf_map.png")
    t0 = time.perf_counter()
    with torch.no_grad():
        rendered = render_map(img[None], pmap)[0]
    t_render = time.perf_counter() - t0
    enc = to_png(rendered, out / "rendered.png")
    noisy = Sensor()(rendered, generator=torch.Generator().manual_seed(0))
    to_png(noisy, out / "rendered_noisy.png")
    # RGB-D: inverse depth from 0 (top row, infinity) to 1/300 mm⁻¹ (bottom row)
    H = img.shape[-2]
    inv = torch.linspace(0.0, 1.0 / near, H, dtype=torch.float64)[:, None].expand(H, img.shape[-1])
    depth = torch.where(inv > 0, 1.0 / inv.clamp_min(1e-300), torch.full_like(inv, float("inf")))
    with torch.no_grad():
        rgbd = render_rgbd(img[None], depth, pmap.psf, pmap.depths, centers=pmap.centers, positions=pmap.positions,
                           sensor_size=pmap.sensor_size, pitch=pmap.pitch)[0]
    to_png(rgbd, out / "rendered_rgbd.png")

    # comparison figure with close-ups (centre and top-left corner of the picture)
    src = (linear_to_srgb(img).numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    H, W = src.shape[:2]
    z = max(32, W // 8)
    crops = {"centre": (H // 2 - z // 2, W // 2 - z // 2), "top-left corner": (0, 0)}
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.2), constrained_layout=True)
    for ax, im, title in ((axes[0, 0], src, "input (scene)"), (axes[1, 0], enc, "rendered through hybrid_asphere")):
        ax.imshow(im)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    for k, (name, (r, c)) in enumerate(crops.items()):
        for row, im in enumerate((src, enc)):
            ax = axes[row, k + 1]
            ax.imshow(im[r: r + z, c: c + z], interpolation="nearest")
            ax.set_title(f"{name} ({'input' if row == 0 else 'rendered'})", fontsize=9)
            ax.axis("off")
    fig.suptitle(f"hybrid_asphere, distant scene, {args.grid}×{args.grid} PSF map (ks {args.ks}), image {W}×{H} "
                 f"({pmap.sensor_size[0] / W * 1e3:.2f} µm pixels)", fontsize=10)
    fig.savefig(out / "comparison.png", dpi=110)
    plt.close(fig)
    report = {"grid": [args.grid, args.grid], "ks": args.ks, "image": [W, H], "depths_mm": ["inf", near],
              "psf_map_seconds": t_map,
              "render_seconds": t_render, "energy_outside_max": float(pmap.energy_outside.max()),
              "max_field_deg": float(pmap.fields.norm(dim=-1).max())}
    (out / "render_demo.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
