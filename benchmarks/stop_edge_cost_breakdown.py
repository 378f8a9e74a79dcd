"""Issue 47: the default stop edge's extra cost over the DOE-plane edge (``stop_edge="doe"``), stage by stage, on
the bundled ``hybrid_asphere`` (ks 64, 1 thread): a single warm PSF at 12.25° and 0.53 µm and a ``--grid``×``--grid``
×3 map (per PSF). Each stage's CPU time (user + system, ``resource.getrusage``; a stage's time includes the stages it
calls) from wrappers around the engine's functions, the two edges interleaved in one process (medians over
``--repeat``), and the sizes that set the cost: the field stage's windows and knife-edge band samples, the batches'
input windows, FFT sizes and transfer bands. Prints one JSON object (and writes it with ``-o``).

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/stop_edge_cost_breakdown.py [--grid 6] [--repeat 3] [-o F]
"""

import argparse
import functools
import importlib
import resource
import statistics

import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)
from stop_edge_stages import edge_lenses  # noqa: E402

_HL, _ACC, _SE = "raywave.hybrid.hybrid_lens", "raywave.hybrid.coherent.accurate", "raywave.hybrid.coherent.stop_edge"
_BAT, _BAND = "raywave.hybrid.batched", "raywave.wave.propagation.band"
#: (label, module, name): where the module looks the stage up; nested stages' times are included in their callers'
STAGES = (
    ("call geometry (rim images, adaptive step)", _HL, "HybridLens._accurate_geometry"),
    ("  rim images", _HL, "stop_rim_images_all"),
    ("  adaptive step's edge rays", _HL, "adaptive_edge_steps"),
    ("ray stage (node maps)", _HL, "HybridLens._ray_stage"),
    ("  caustic estimate", _HL, "go_phase_errors"),
    ("field stage (_fine_field)", _ACC, "_fine_field"),
    ("  node interpolation (upsample_nodes_window)", _ACC, "upsample_nodes_window"),
    ("  coverage and crop", _ACC, "_fine_coverage"),
    ("  envelope (_envelope)", _ACC, "_envelope"),
    ("    compiled loop (_envelope_dense)", _SE, "_envelope_dense"),
    ("    compiled loop with cov, k·φ (_envelope_dense_scaled)", _SE, "_envelope_dense_scaled"),
    ("    Fresnel integrals (scipy)", _SE, "_fresnel_integrals"),
    ("    knife-edge arithmetic (_EdgeBand._values)", _SE, "_EdgeBand._values"),
    ("    band masks", _SE, "_band_masks"),
    ("propagation (propagate_fields)", _HL, "HybridLens.propagate_fields"),
    ("  envelopes padded, DOE phase (modulated_batch)", _BAT, "modulated_batch"),
    ("  transfer functions (batch_transfer)", _BAT, "batch_transfer"),
    ("  band convolution (convolve_band)", "raywave.wave.propagation.window", "convolve_band"),
    ("    x transforms on the band's columns (_x_band)", _BAND, "_x_band"),
    ("  pixel integration (sensor_psfs)", _BAT, "sensor_psfs"),
)


def _usage():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _faults():
    """(system CPU s, minor page faults) of this process so far."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_stime, r.ru_minflt


def _wrap(acc: dict, label: str, module: str, name: str, hook=None) -> None:
    """Replace ``module.name`` (``Class.method`` allowed) by a wrapper adding its CPU time to ``acc[label]``."""
    owner = importlib.import_module(module)
    *path, attr = name.split(".")
    for p in path:
        owner = getattr(owner, p)
    fn = owner.__dict__[attr] if attr in owner.__dict__ else getattr(owner, attr)
    static = isinstance(fn, staticmethod)
    fn = fn.__func__ if static else fn

    @functools.wraps(fn)
    def timed(*args, **kw):
        t0, (s0, f0) = _usage(), _faults()
        try:
            out = fn(*args, **kw)
        finally:
            s1, f1 = _faults()
            acc[label] = acc.get(label, 0.0) + _usage() - t0
            acc["sys: " + label] = acc.get("sys: " + label, 0.0) + s1 - s0
            acc["minflt/1000: " + label] = acc.get("minflt/1000: " + label, 0.0) + (f1 - f0) * 1e-6
        if hook is not None:
            hook(args, kw, out)
        return out

    setattr(owner, attr, staticmethod(timed) if static else timed)


def _sizes_hooks(sizes: dict) -> dict:
    """Hooks recording the cost-setting sizes into ``sizes`` (lists per quantity)."""
    def envelope(args, kw, out):
        sizes.setdefault("envelope_windows", []).append(list(out.shape))

    def fresnel(args, kw, out):
        sizes["fresnel_values"] = sizes.get("fresnel_values", 0) + int(args[0].numel())

    def transfer(args, kw, out):
        wb = args[0]
        sizes.setdefault("batches", []).append(dict(
            fft=list(out.size), in_shape=list(wb.in_shape()), out_shape=list(wb.out_shape),
            windows=[list(s.in_shape) for s in wb.sources],
            own_fft=[list(g.size) for g in wb.geometries()],
            bands=[[int(p.rows.numel()), int(p.cols.numel())] for p in out.parts] if out.parts is not None
            else [[int(out.rows.numel()), int(out.cols.numel())]] * out.count))

    return {"_envelope": envelope, "_fresnel_integrals": fresnel, "batch_transfer": transfer}


def _summary(sizes: dict, n: int) -> dict:
    """Per-PSF means of the recorded sizes."""
    out = {}
    wins = sizes.get("envelope_windows", [])
    if wins:
        out["field_windows"] = len(wins)
        out["field_window_samples_mean"] = statistics.mean(a * b for a, b in wins)
        out["field_window_shapes"] = wins[:4]
    out["fresnel_values_per_psf"] = sizes.get("fresnel_values", 0) / n
    bs = sizes.get("batches", [])
    if bs:
        srcs = [(b, i) for b in bs for i in range(len(b["windows"]))]
        out["sources"] = len(srcs)
        out["fft_samples_mean"] = statistics.mean(b["fft"][0] * b["fft"][1] for b, _ in srcs)
        out["own_fft_samples_mean"] = statistics.mean(b["own_fft"][i][0] * b["own_fft"][i][1] for b, i in srcs)
        out["padded_input_samples_mean"] = statistics.mean(b["in_shape"][0] * b["in_shape"][1] for b, _ in srcs)
        out["own_input_samples_mean"] = statistics.mean(b["windows"][i][0] * b["windows"][i][1] for b, i in srcs)
        out["band_samples_mean"] = statistics.mean(b["bands"][i][0] * b["bands"][i][1] for b, i in srcs)
        out["out_shape"] = bs[0]["out_shape"]
        out["batches_first"] = [{k: b[k] for k in ("fft", "in_shape", "windows", "own_fft", "bands")} for b in bs[:2]]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=6, help="the map's N×N fields (0: no map)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--singles", type=int, default=3, help="single PSFs per edge per repetition")
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    from raywave.imaging import psf_map

    acc: dict = {}
    sizes: dict = {}
    hooks = _sizes_hooks(sizes)
    for label, module, name in STAGES:
        _wrap(acc, label, module, name, hooks.get(name.split(".")[-1]))
    hls = edge_lenses()
    wls = (0.66, 0.53, 0.47)
    runs = {"single": (1, lambda hl: hl.psf_result((0.0, 12.25), 0.53, ks=64))}
    if a.grid:
        runs["map"] = (a.grid * a.grid * 3,
                       lambda hl: psf_map(hl, (a.grid, a.grid), wavelengths=wls, ks=64, progress=False))
    for hl in hls.values():  # warm
        for _, run in runs.values():
            run(hl)
    rows = {w: {k: [] for k in hls} for w in runs}
    geo = {w: {} for w in runs}
    for rep in range(a.repeat):
        for what, (n, run) in runs.items():
            for k, hl in hls.items():
                for _ in range(a.singles if what == "single" else 1):
                    acc.clear()
                    sizes.clear()
                    t0, (s0, f0) = _usage(), _faults()
                    run(hl)
                    s1, f1 = _faults()
                    acc["total"] = _usage() - t0
                    acc["sys: total"], acc["minflt/1000: total"] = s1 - s0, (f1 - f0) * 1e-6
                    rows[what][k].append({s: v / n * 1e3 for s, v in acc.items()})
                    if rep == 0:
                        geo[what][k] = _summary(sizes, n)
    out = {"case": f"hybrid_asphere ks 64, 1 thread: single PSF at 12.25 deg 0.53 um; map {a.grid}x{a.grid}x3",
           "unit": "ms CPU (user + system) per PSF ('sys: ': the system part; 'minflt/1000: ' thousands of minor "
                   "page faults per PSF); medians over the repetitions, the edges interleaved",
           "repeat": a.repeat, "singles": a.singles, "torch": torch.__version__}
    labels = ["total"] + [s[0] for s in STAGES]
    labels += [f"{p}: {s}" for p in ("sys", "minflt/1000") for s in labels]
    for what in runs:
        res = {}
        for k in hls:
            res[k] = {s: statistics.median([r.get(s, 0.0) for r in rows[what][k]]) for s in labels}
        res["extra"] = {s: res["default"][s] - res["doe"][s] for s in labels}
        res["ratio_vs_doe"] = res["default"]["total"] / res["doe"]["total"]
        res["sizes"] = geo[what]
        out[what] = res
    emit_json(out, a.output)
    return out


if __name__ == "__main__":
    main()
