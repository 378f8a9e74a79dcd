"""Issue 43: how far an accelerator's batching plan moves the PSFs of a map, measured on the CPU.

On a GPU :func:`raywave.hybrid.batched.plan_groups` lets the resolved sources of a wavelength share one FFT size in
large batches, the fields are built in larger groups (``FIELD_GROUP_BYTES_ACCELERATOR``) and the field stage is
batched. This computes the bundled ``hybrid_asphere``'s N×N × R, G, B map (default edge, ks 64, no autograd)
with the CPU's plan and with the accelerator's whole plan forced on the CPU (:func:`raywave.utils.devices.
accelerator`; ``--batch-bytes``: its propagation batch cap, smaller than a GPU's for a CPU's memory), and prints the relative L1 difference of every PSF (max, median, how many moved)
as JSON (``-o`` writes it too).

    OMP_NUM_THREADS=1 python benchmarks/accelerator_plan_accuracy.py [--grid 10] [--batch-bytes 1e9] [-o F]
"""

from __future__ import annotations

import argparse
import warnings

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

RGB = [0.66, 0.53, 0.47]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--batch-bytes", type=float, default=1e9)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)

    import torch

    import raywave.hybrid.batched as batched
    from raywave.assembly.build import load_hybrid
    from raywave.imaging import psf_map
    from raywave.lens.build import bundled_lens_path

    warnings.simplefilter("ignore")
    torch.set_num_threads(args.threads)
    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    n = args.grid
    with torch.no_grad():
        cpu = psf_map(hl, (n, n), wavelengths=RGB, ks=64, progress=False).psf
        try:  # this process only: the whole accelerator plan (trees before the one switch: the FFT sizes' plan)
            import raywave.utils.devices as devices
            devices.accelerator = lambda x: True
        except ImportError:
            batched._accelerator = lambda planned: bool(planned)
        batched.BATCH_BYTES_ACCELERATOR = int(args.batch_bytes)
        accel = psf_map(hl, (n, n), wavelengths=RGB, ks=64, progress=False).psf
    rel = (accel - cpu).abs().sum((-2, -1)) / cpu.abs().sum((-2, -1)).clamp_min(1e-300)
    out = {"benchmark": "accelerator_plan_accuracy", "map": f"{n}x{n}x3 hybrid_asphere, ks 64, default edge",
           "batch_bytes": int(args.batch_bytes), "psfs": rel.numel(), "max_rel_l1": float(rel.max()),
           "median_rel_l1": float(rel.median()), "changed_psfs": int((rel > 0).sum()),
           "max_abs_over_peak": float((accel - cpu).abs().max() / cpu.max()), "torch": torch.__version__}
    emit_json(out, args.output)
    return out


if __name__ == "__main__":
    main()
