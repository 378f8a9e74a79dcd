"""Issue 43: does a source's PSF depend on the FFT size of its window propagation, and which size is right?

For each case the default-edge PSF (ks 32) is computed with the FFT size each source picks on its own (the smallest
fast size that keeps the circular convolution of the rolled-off kernel linear: ``scale`` 1) and with that size forced
larger per axis (``scale`` 1.25, 1.5, 2, … : :data:`raywave.wave.propagation.transfer.FFT_SIZE_SCALE`, rounded up to a
fast size). Each row gives the FFT size, the relative L1 change from the own-size PSF (``sum|a − b| / sum|b|``) and,
where the case has one, the relative L1 against the converged reference with the reference's own convergence
(``ref_error``: its last refinement's change).

Cases (the helpers of benchmarks/stop_edge_references.py build the engine and load the cached references):

- ``real:NAME:FRAC``: the four real lenses of tests/test_stop_edge_real_lenses.py at FRAC of their largest field,
  reference ``huygens_psf(sphere="rim_images")`` (``ref_CASE_ks32_rim_images.pt``);
- ``asphere:DEG``: the bundled asphere's lens (6 mm blank DOE of 1 µm pixels at 0.7 mm, 3 µm sensor pixels,
  λ 0.53 µm), reference ``huygens_psf`` on the paraxial sphere (``ref_asphere_DEG_ks32.pt``);
- ``coarse:DEG``: ``asphere:DEG`` on a 4 µm DOE grid (1500², the same 6 mm): a field the grid does not resolve (the
  engine's SamplingWarning: its phase slope passes the Nyquist limit), compared with the same reference;
- ``rgb:NAME:FRAC``: the lens at every one of its wavelengths (no reference: the change alone), for the sources where
  the FFT size matters most.

``--map-ab NxMxW`` instead times :data:`raywave.hybrid.batched.COMMON_FFT` off and on (A/B interleaved in this
process, ``--repeat`` rounds, ``time.process_time``): CPU seconds per PSF of the bundled ``hybrid_asphere``'s N×M map
at W of the R, G, B wavelengths (ks 64, default edge, no autograd, after a 1-PSF warm-up), the number of batches
the maps propagate, and the largest relative L1 change of a PSF between off and on.

A case whose estimated peak at a scale passes ``--max-gb`` is skipped at that scale (said in its row).

    PYTHONPATH=. python benchmarks/fft_size_convergence.py --cache /tmp/k47/cache [--scales 1 1.25 1.5 2] \
        [--cases real:cooke_triplet:1.0 asphere:0 ...] [-o F]
"""

import argparse
import math
import resource
import time
import warnings
from pathlib import Path

import torch

from _report import emit_json, emit_row  # noqa: E402  (benchmarks/ is on sys.path)
from stop_edge_references import _hybrid, l1, reference  # noqa: E402

import raywave.hybrid.batched as batched
import raywave.wave.propagation.transfer as transfer

CASES = ([f"real:{n}:{f}" for n in ("cooke_triplet", "double_gauss", "singlet_nbk7_50", "asphere_f13")
          for f in ("0", "0.7", "1.0")] + [f"asphere:{d}" for d in ("0", "7", "14", "17.5")]
         + ["rgb:cooke_triplet:1.0", "rgb:cooke_triplet:1.2"] + [f"coarse:{d}" for d in ("0", "7", "14")])
#: measured peaks (issue 47's sweep): these need more than any budget a shared 2-core machine gives
TOO_LARGE = {"real:asphere_f13:1.0": "needs ~12.6 GiB at its own FFT size"}


def _rel(a, b) -> float:
    return l1(a, b) / float(torch.as_tensor(b).abs().sum())


class _Sizes:
    """Records the FFT size and batch size of every batch that :mod:`raywave.hybrid.batched` propagates."""

    def __init__(self):
        self.seen = []

    def __enter__(self):
        self._orig = batched.batch_transfer

        def spy(wb, *a, **k):
            self.seen.append((wb.fft_size(), len(wb.sources), wb.in_shape(), wb.out_shape))
            return self._orig(wb, *a, **k)

        batched.batch_transfer = spy
        return self

    def __exit__(self, *exc):
        batched.batch_transfer = self._orig


def scaled_psf(case: str, scale: float, ks: int):
    """``(psf (W, ks, ks), centres, geometry for the reference, batches seen, seconds)`` of ``case`` with the FFT
    sizes multiplied by ``scale``."""
    kind, *rest = case.split(":")
    if kind == "coarse":
        from raywave.doe import BlankDOE
        from raywave.hybrid import HybridLens
        from raywave.lens.build import bundled_lens_path, load_lens

        hl = HybridLens(load_lens(bundled_lens_path("asphere_hk51")), BlankDOE(1500, 4e-3), 0.7, sensor_pitch=3e-3)
        fld, wl, depth = (0.0, float(rest[0])), 0.53, None
    else:
        hl, fld, wl, depth = _hybrid("real:" + ":".join(rest) if kind == "rgb" else case, {})
    wls = list(hl.lens.wavelengths) if kind == "rgb" else [wl]
    if kind == "rgb":
        fld = (0.0, float(rest[1]) * max(float(f) for f in hl.lens.fields))
    old = transfer.FFT_SIZE_SCALE
    transfer.FFT_SIZE_SCALE = float(scale)
    t = time.process_time()
    try:
        with _Sizes() as sizes, warnings.catch_warnings(record=True) as caught, torch.no_grad():
            warnings.simplefilter("always")
            r = hl.psf_result(fld, wls, ks=ks, depth=depth)
    finally:
        transfer.FFT_SIZE_SCALE = old
    center = tuple(float(c) for c in r.center[0, 0])
    sampling = sorted({str(w.message)[:110] for w in caught if w.category.__name__ == "SamplingWarning"})
    return r.psf[0].detach(), (hl, fld, wl, depth, center), sizes.seen, time.process_time() - t, wls, sampling


def run_case(case: str, scales, ks: int, cache: Path, max_gb: float, peak_per_sample: float | None):
    """One row: each scale's FFT sizes, change from the own size, and (real/asphere cases) error vs the reference."""
    if case in TOO_LARGE:
        return dict(case=case, skipped=TOO_LARGE[case])
    row = dict(case=case, ks=ks, scales={})
    base = None
    for s in scales:
        if base is not None and peak_per_sample is not None:
            my, mx = base["fft"]
            est = peak_per_sample * math.ceil(s * my) * math.ceil(s * mx) / 2**30
            if est > max_gb:
                row["scales"][str(s)] = dict(skipped=f"estimated peak {est:.1f} GiB > --max-gb {max_gb:g}")
                continue
        psf, geo, seen, sec, wls, sampling = scaled_psf(case, s, ks)
        ent = dict(fft=[list(x[0]) for x in seen], batch=[x[1] for x in seen], in_shape=[list(x[2]) for x in seen],
                   cpu_s=round(sec, 2), maxrss_gib=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2))
        if base is None:
            base = dict(psf=psf, fft=seen[0][0], geo=geo)
            row.update(wavelengths=wls, field=list(geo[1]), in_shape=list(seen[0][2]), out_shape=list(seen[0][3]),
                       sampling_warnings=sampling)
        else:
            ent["change_from_own"] = [_rel(psf[w], base["psf"][w]) for w in range(psf.shape[0])]
        if not case.startswith("rgb:"):
            sphere = "rim_images" if case.startswith("real:") else "paraxial"
            ref, rrow = reference(case.replace("coarse:", "asphere:"), base["geo"], ks, 432, cache, sphere)
            ent["vs_ref"] = _rel(psf[0], ref)
            row.update(ref_error=rrow.get("ref_error"), ref_n_pupil=rrow.get("ref_n_pupil"), ref_sphere=sphere)
        row["scales"][str(s)] = ent
    return row


class _Batches:
    """Counts the batches that :func:`raywave.hybrid.batched.propagate_group` runs (and their sizes)."""

    def __enter__(self):
        import raywave.hybrid.hybrid_lens as hm

        self.sizes, self._mod, self._orig = [], hm, hm.propagate_group

        def spy(engine, batch, *a, **k):
            self.sizes.append(len(batch))
            return self._orig(engine, batch, *a, **k)

        hm.propagate_group = spy
        return self

    def __exit__(self, *exc):
        self._mod.propagate_group = self._orig


def map_ab(spec: str, repeat: int) -> dict:
    """:data:`raywave.hybrid.batched.COMMON_FFT` off vs on for the ``spec`` = "NxMxW" map (module docstring)."""
    import statistics

    from imaging import _lens  # noqa: E402  (benchmarks/ is on sys.path)
    from raywave.imaging import psf_map

    n, m, w = (int(v) for v in spec.split("x"))
    wls = [0.66, 0.53, 0.47][:w]
    hl = _lens()
    hl.psf_result((0.0, 0.0), wls[:1], ks=64)  # warm-up
    times, psfs, batches = {False: [], True: []}, {}, {}
    old = batched.COMMON_FFT
    try:
        for _ in range(repeat):
            for flag in (False, True):
                batched.COMMON_FFT = flag
                with _Batches() as seen, warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    t = time.process_time()
                    pm = psf_map(hl, grid=(n, m), wavelengths=wls, ks=64, progress=False)
                    times[flag].append((time.process_time() - t) / (n * m * w))
                sampling = sorted({str(c.message)[:90] for c in caught if c.category.__name__ == "SamplingWarning"})
                psfs[flag], batches[flag] = pm.psf.detach(), seen.sizes
    finally:
        batched.COMMON_FFT = old
    a, b = psfs[False], psfs[True]
    rel = (a - b).abs().sum((-2, -1)) / a.abs().sum((-2, -1))  # (D, W, N, M)
    top = torch.topk(rel.reshape(-1), min(5, rel.numel()))
    worst = [dict(rel_l1=float(v), wavelength=wls[int(i) // (n * m) % w],
                  field_deg=[float(x) for x in pm.fields.reshape(-1, 2)[int(i) % (n * m)]])
             for v, i in zip(top.values, top.indices)]
    med = {k: statistics.median(v) for k, v in times.items()}
    return dict(map=[n, m], wavelengths=wls, ks=64, psfs=n * m * w, repeat=repeat, threads=torch.get_num_threads(),
                cpu_s_per_psf_off=med[False], cpu_s_per_psf_on=med[True], ratio_on_over_off=med[True] / med[False],
                cpu_s_per_psf_all={"off": times[False], "on": times[True]},
                batches_off=len(batches[False]), batches_on=len(batches[True]),
                batch_sizes_off=batches[False], batch_sizes_on=batches[True], max_rel_l1_on_vs_off=float(rel.max()),
                median_rel_l1_on_vs_off=float(rel.median()), worst=worst, sampling_warnings=sampling)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=CASES)
    ap.add_argument("--scales", nargs="+", type=float, default=[1.0, 1.25, 1.5, 2.0])
    ap.add_argument("--ks", type=int, default=32)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/k47/cache"), help="the cached references")
    ap.add_argument("--max-gb", type=float, default=8.0, help="skip a scale whose estimated peak passes this")
    ap.add_argument("--peak-per-sample", type=float, default=150.0,
                    help="bytes of peak per FFT-grid sample, for the estimate (50-110 B measured on these cases)")
    ap.add_argument("--map-ab", metavar="NxMxW", help="time COMMON_FFT off vs on on this map instead")
    ap.add_argument("--repeat", type=int, default=3, help="--map-ab: interleaved rounds")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    if a.map_ab:
        return emit_json(dict(benchmark="fft_size_convergence --map-ab", torch=torch.__version__,
                              **map_ab(a.map_ab, a.repeat)), a.output)
    rows = []
    for c in a.cases:
        emit_row(rows, run_case(c, a.scales, a.ks, a.cache, a.max_gb, a.peak_per_sample), None)
    emit_json(dict(benchmark="fft_size_convergence", torch=torch.__version__, threads=torch.get_num_threads(),
                   scales=a.scales, rows=rows), a.output)
    return rows


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
