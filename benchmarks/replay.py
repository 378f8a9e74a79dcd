"""Memory-saving replay vs the full autograd graph: peak memory and time per training iteration.

Case: a small ray-wave hybrid lens (ideal f = 4 mm lens at F/8, a trainable 256×256 pixel DOE at 2 µm pitch
0.5 mm behind it, 2 µm sensor pixels), PSF maps of 5×5 and 10×10 field points over ±5°, three wavelengths
(one per colour channel), ks = 32; an iteration renders a 480² RGB image in N×N tiles (each tile blurred by
its PSFs through an FFT convolution; the same image for every N, so only the number of PSFs changes), runs a
small UNet (width 8) and an L1 loss, and backpropagates into the DOE and the network:

* ``full``: the whole PSF map with autograd, one graph;
* ``replay``: :class:`raywave.training.replay.OpticsStep`: map without autograd, render + network + loss on
  leaf PSFs, then the PSFs recomputed one field at a time with autograd and ∂L/∂PSF backpropagated.

Each case runs in its own process; memory is the peak resident memory above the process's resident memory
before the first iteration (Linux VmHWM; the first iteration also holds one-time work such as torch.compile's
compiles and the compiler's own memory), and ``warm_peak_mb_above_its_start`` the second iteration's peak above the
resident memory before it; time the median of the following iterations. Prints JSON (``-o``
writes it too).

    OMP_NUM_THREADS=1 python benchmarks/replay.py [--grids 5 10] [--iters 3] [--device cuda] [-o replay.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time

from _memory import peak_mb, reset_peak, rss_mb  # noqa: E402  (benchmarks/ is on sys.path)
from _report import emit_json  # noqa: E402

KS, IMG, DOE_N, DOE_PITCH = 32, 480, 256, 2e-3
WAVELENGTHS = (0.66, 0.53, 0.47)


def _case(grid: int, mode: str, iters: int, device: str = "cpu") -> dict:
    import warnings

    import torch

    from raywave.doe import PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens
    from raywave.training.networks import UNet
    from raywave.training.replay import OpticsStep

    warnings.simplefilter("ignore")
    torch.manual_seed(0)
    lens = ideal_lens(4.0, f_number=8.0, wavelengths=(0.55,))
    lens.requires_grad_(False)
    doe = PixelDOE(0.3 * torch.randn(DOE_N, DOE_N, dtype=torch.float64), DOE_PITCH)
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    hl = HybridLens(lens, doe, 0.5, sensor_pitch=2e-3).to(dev)
    net = UNet(width=8, depth=2).double().to(dev)
    t = torch.linspace(-5.0, 5.0, grid, dtype=torch.float64)
    fields = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2).flip(-1)
    TILE = IMG // grid  # the image is the same for every grid: only the number of PSFs changes
    img = torch.rand(1, 3, IMG, IMG, dtype=torch.float64).to(dev)

    def compute(ctx):
        return hl.psf(fields[ctx.index:ctx.index + 1], WAVELENGTHS, ks=KS, rays=32)

    def render(psf):  # psf (F, 3, ks, ks) → blurred image, tile (i, j) with PSF i*grid + j
        tiles = img.reshape(3, grid, TILE, grid, TILE).permute(1, 3, 0, 2, 4).reshape(grid * grid, 3, TILE, TILE)
        pad = torch.zeros(grid * grid, 3, TILE, TILE, dtype=psf.dtype, device=psf.device)
        pad[..., :KS, :KS] = psf
        pad = torch.roll(pad, (-(KS // 2), -(KS // 2)), (-2, -1))
        out = torch.fft.irfft2(torch.fft.rfft2(tiles) * torch.fft.rfft2(pad), s=(TILE, TILE))
        return out.reshape(grid, grid, 3, TILE, TILE).permute(2, 0, 3, 1, 4).reshape(1, 3, grid * TILE, grid * TILE)

    def iteration():
        step = OpticsStep(compute, len(fields))
        if mode == "full":
            (psf,) = step.full_graph()
            (net(render(psf)) - img).abs().mean().backward()
        else:
            (psf,) = step.leaves()
            (net(render(psf)) - img).abs().mean().backward()
            step.backward()
        g = float(hl.doe.phase_map.grad.abs().sum())  # (a float: also the GPU's synchronisation)
        hl.doe.phase_map.grad = None
        net.zero_grad(set_to_none=True)
        return g

    rss0 = rss_mb()
    reset_peak()
    if cuda:
        torch.cuda.synchronize(dev)
        base = torch.cuda.memory_allocated(dev)
        torch.cuda.reset_peak_memory_stats(dev)
    t0 = time.perf_counter()
    iteration()
    first = time.perf_counter() - t0
    peak = peak_mb() - rss0
    gpu = {"gpu_peak_mb_above_baseline": round((torch.cuda.max_memory_allocated(dev) - base) / 1e6, 1),
           "device_name": torch.cuda.get_device_name(dev)} if cuda else {}
    times = []
    warm = None
    for i in range(max(iters - 1, 0)):
        if i == 0:  # a warm iteration's own peak: the first one also holds one-time work (torch.compile's compiles)
            rss1 = rss_mb()
            reset_peak()
        t0 = time.perf_counter()
        iteration()
        times.append(time.perf_counter() - t0)
        if i == 0:
            warm = peak_mb() - rss1
    return {"grid": f"{grid}x{grid}", "psfs": grid * grid * len(WAVELENGTHS), "mode": mode,
            "peak_mb_above_baseline": round(peak, 1),
            "warm_peak_mb_above_its_start": None if warm is None else round(warm, 1),
            "first_iteration_s": round(first, 3),
            "time_per_iteration_s": round(statistics.median(times), 3) if times else round(first, 3),
            "device": str(dev), **gpu}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grids", type=int, nargs="+", default=[5, 10])
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("-o", "--output")
    ap.add_argument("--device", default="cpu", help="torch device of the lens and network (cpu, cuda): on CUDA the "
                    "peak GPU memory above the baseline is reported as well")
    ap.add_argument("--case", nargs=2, help=argparse.SUPPRESS)  # internal: run one case in this process
    args = ap.parse_args(argv)
    if args.case:
        print(json.dumps(_case(int(args.case[0]), args.case[1], args.iters, args.device)))
        return
    import torch

    results = []
    for grid in args.grids:
        for mode in ("replay", "full"):
            out = subprocess.run([sys.executable, __file__, "--case", str(grid), mode, "--iters", str(args.iters),
                                  "--device", args.device],
                                 capture_output=True, text=True, check=True)
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(json.dumps(results[-1]), file=sys.stderr)
    report = {"benchmark": "replay", "case": {"doe": f"{DOE_N}x{DOE_N} px at {DOE_PITCH * 1e3:g} um", "ks": KS,
                                               "wavelengths_um": WAVELENGTHS, "image_px": IMG,
                                               "network": "UNet(width=8, depth=2), float64"},
              "threads": torch.get_num_threads(), "torch": torch.__version__, "platform": platform.platform(),
              "results": results}
    emit_json(report, args.output)


if __name__ == "__main__":
    main()
