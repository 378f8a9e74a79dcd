"""A DOE at the aperture stop vs the same DOE before the sensor, each designed end to end (issue 46).

The bundled aspheric singlet ``hybrid_asphere`` (frozen), the central 2 × 2 mm of its sensor (the same field of view
for both), and the same learned DOE, a smooth phase of 15 Zernike terms over its disk (a DOE inside the lens carries
its phase by rays: a smooth phase, not a free pixel map),

* **at the stop** (surface 0, 0 mm after it): a :class:`raywave.MidSystemLens`; every DOE order is carried through
  the asphere as a phase surface by the accurate engine to the blank plane 0.7 mm after the lens
  (``configs/midsystem_stop_doe.yaml``; the disk holds the beams on the stop plane);
* **before the sensor**: the lens file's own DOE plane, 0.7 mm after the lens (a :class:`raywave.HybridLens`, its
  3 mm element; the disk is inscribed in it).

Both go through the same schedule (the PSF-size pre-stage, end-to-end stage 1 with the replay, stage 2 on the
network alone) with the same network, data and seed, and are evaluated on the held-out photos. Writes into the
output folder ``figures/psf_maps.png`` (the two PSF maps; ``psf_map_depth0.png`` as ``raywave train`` draws it),
``figures/reconstructions_centre.png`` /
``_edge.png`` (sensor images and restored images), ``figures/loss.png`` and ``doe_at_stop.json`` (PSNR / SSIM and
the timings), and prints the PSNR difference.

    python examples/doe_at_stop.py [-o examples_out/doe_at_stop] [--pre 3] [--stage1 2] [--stage2 20]

(about 5 minutes on 2 quiet CPU cores with the defaults, 20 on busy ones: the DOE at the stop traces every
DOE-plane field again at each step; the DOE before the sensor reuses the frozen lens's cached fields.)
"""

from __future__ import annotations

import argparse
import copy
import json
import time
import warnings
from pathlib import Path

import torch

from raywave.training.config import load_config
from raywave.training.trainer import Trainer

ROOT = Path(__file__).resolve().parent.parent


def configs(pre: int, stage1: int, stage2: int):
    """The two runs' configs: ``configs/midsystem_stop_doe.yaml`` (the DOE at the stop) and the same with the DOE
    on the lens file's plane before the sensor; ``pre`` / ``stage1`` / ``stage2`` steps."""
    stop = load_config(ROOT / "configs" / "midsystem_stop_doe.yaml")
    stop.pre_stage.steps, stop.stage1.max_steps, stop.stage2.max_steps = pre, stage1, stage2
    stop.stage1.epochs = stop.stage2.epochs = 100  # max_steps decides
    sensor = copy.deepcopy(stop)
    sensor.name = "doe_before_sensor"
    sensor.lens.doe_after = None
    sensor.lens.doe_distance = None  # the file's 0.7 mm
    return {"DOE at the stop": stop, "DOE before the sensor": sensor}


def _psf_maps_figure(path: Path, trainers: dict) -> None:
    """``path``: the two PSF maps side by side (the lens's own, infinite depth), each a mosaic of its 3 × 3 PSFs
    (√ scale, every channel to its own maximum), with a two-line title per panel (the placement; what is shown)."""
    from raywave.plotting._mpl import plt, save

    maps = {name: t.truth_map() for name, t in trainers.items()}
    fig, axes = plt.subplots(1, len(maps), figsize=(5.2 * len(maps), 5.8), squeeze=False)
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.02, top=0.88, wspace=0.06)  # room for two title lines
    for ax, (name, pm) in zip(axes[0], maps.items()):
        psf = pm.psf[0]  # (3, N, M, ks, ks)
        C, N, M, ks, _ = psf.shape
        mosaic = psf.permute(1, 3, 2, 4, 0).reshape(N * ks, M * ks, C)
        mosaic = mosaic / mosaic.amax(dim=(0, 1), keepdim=True).clamp_min(1e-30)
        ax.imshow(mosaic.clamp(0, 1).sqrt().numpy(), origin="lower")
        ax.set_title(f"{name}\nPSF map, object at infinity ({N} × {M}, √, per-channel max)", fontsize=10, pad=8)
        ax.set_xticks([]), ax.set_yticks([])
    save(fig, path)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default=str(ROOT / "examples_out" / "doe_at_stop"))
    ap.add_argument("--pre", type=int, default=3, help="pre-stage steps (PSF size)")
    ap.add_argument("--stage1", type=int, default=2, help="end-to-end steps")
    ap.add_argument("--stage2", type=int, default=20, help="network-only steps")
    args = ap.parse_args(argv)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    trainers, report = {}, {}
    for name, cfg in configs(args.pre, args.stage1, args.stage2).items():
        t0 = time.perf_counter()
        tr = Trainer(cfg, out / cfg.name, progress=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # each run writes its warnings into its folder (warnings.jsonl)
            tr.run(resume=False)
            m = tr.evaluate()
        trainers[name] = tr
        report[name] = {"psnr": m["mean"]["psnr"], "ssim": m["mean"]["ssim"],
                        "psnr_input": m["mean"].get("psnr_input"), "psf_rms_px": m["mean"].get("psf_rms_px_map"),
                        "zones": {k: {"psnr": v["psnr"]} for k, v in m.items() if k != "mean"},
                        "doe": {"type": type(tr.hl).__name__, "shape": list(tr.hl.doe.shape),
                                "pitch_mm": tr.hl.doe.pitch},
                        "seconds": time.perf_counter() - t0}
        print(f"{name}: PSNR {report[name]['psnr']:.2f} dB, SSIM {report[name]['ssim']:.4f} "
              f"({report[name]['seconds']:.0f} s)", flush=True)
    from raywave.cli.train_commands import _figures  # the figures `raywave train` writes, for both runs

    _figures(out, trainers)
    _psf_maps_figure(out / "figures" / "psf_maps.png", trainers)
    a, b = report["DOE at the stop"]["psnr"], report["DOE before the sensor"]["psnr"]
    report["psnr_difference_stop_minus_sensor_db"] = a - b
    (out / "doe_at_stop.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"PSNR difference (DOE at the stop − DOE before the sensor): {a - b:+.2f} dB; figures in {out / 'figures'}")
    return report


if __name__ == "__main__":
    main()
