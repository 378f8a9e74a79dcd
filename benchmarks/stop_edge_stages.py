"""Issue 47: where the default stop edge's time goes, stage by stage, against the DOE-plane edge (``stop_edge="doe"``)
on the bundled ``hybrid_asphere`` (ks 64): a single warm PSF at 12.25° and 0.53 µm, or (``--map``) a 3×3×3 map per
PSF. Each stage's user and system CPU time and minor page faults (``resource.getrusage``, one process, the two edges
interleaved, medians over ``--repeat``) from wrappers around the engine's stage functions (a stage's time includes
the stages it calls). Prints one JSON object (and writes it with ``-o``).

    PYTHONPATH=. python benchmarks/stop_edge_stages.py [--map] [--repeat 5] [-o F]
"""

import argparse
import functools
import resource
import statistics
import warnings

import torch

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)

_HL, _ACC = "raywave.hybrid.hybrid_lens", "raywave.hybrid.coherent.accurate"
#: (module, name) of the wrapped stages: where the module looks them up
STAGES = ((_HL, "HybridLens._accurate_geometry"), (_HL, "HybridLens._ray_stage"), (_HL, "HybridLens._accurate_group"),
          (_HL, "HybridLens.propagate_fields"), (_HL, "stop_rim_images_all"), (_HL, "adaptive_edge_steps"),
          (_HL, "go_phase_errors"), (_ACC, "upsample_nodes"), (_ACC, "_envelope"),
          ("raywave.hybrid.batched", "batch_transfer"), ("raywave.wave.propagation.window", "convolve_band"),
          ("raywave.hybrid.batched", "sensor_psfs"))


def _usage():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime, r.ru_stime, r.ru_minflt


def _wrap(acc: dict, module: str, name: str) -> None:
    """Replace ``module.name`` (``Class.method`` allowed) by a wrapper adding its usage to ``acc[name]``."""
    import importlib

    owner = importlib.import_module(module)
    *path, attr = name.split(".")
    for p in path:
        owner = getattr(owner, p)
    fn = getattr(owner, attr)

    @functools.wraps(fn)
    def timed(*args, **kw):
        t0 = _usage()
        try:
            return fn(*args, **kw)
        finally:
            t1 = _usage()
            acc[name] = [a + b - c for a, b, c in zip(acc.get(name, (0.0, 0.0, 0)), t1, t0)]

    setattr(owner, attr, timed)


def edge_lenses() -> dict:
    """One thread, no autograd, warnings off (a timing run), and the bundled asphere with each edge:
    ``{"default": exit-pupil edge, "doe": DOE-plane edge}``."""
    torch.set_num_threads(1)
    torch.set_grad_enabled(False)
    warnings.simplefilter("ignore")
    from raywave.assembly.build import load_hybrid
    from raywave.lens.build import bundled_lens_path

    return {"default": load_hybrid(bundled_lens_path("hybrid_asphere")),
            "doe": load_hybrid(bundled_lens_path("hybrid_asphere"), stop_edge="doe")}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", action="store_true", help="a 3×3×3 map per PSF instead of a single PSF")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    from raywave.imaging import psf_map

    acc: dict = {}
    for module, name in STAGES:
        _wrap(acc, module, name)
    hls = edge_lenses()
    if a.map:
        n = 27

        def run(hl):
            psf_map(hl, (3, 3), wavelengths=(0.66, 0.53, 0.47), ks=64, progress=False)
    else:
        n = 1

        def run(hl):
            hl.psf_result((0.0, 12.25), 0.53, ks=64)
    for hl in hls.values():  # warm
        run(hl)
        run(hl)
    rows = {k: [] for k in hls}
    for _ in range(a.repeat):
        for k, hl in hls.items():
            acc.clear()
            t0 = _usage()
            run(hl)
            acc["total"] = [b - c for b, c in zip(_usage(), t0)]
            rows[k].append(dict(acc))
    out = {"case": "hybrid_asphere ks 64, " + ("3x3x3 map, per PSF" if a.map else "single PSF at 12.25 deg 0.53 um"),
           "threads": 1, "repeat": a.repeat, "unit": "ms CPU (user, system), minor page faults; per PSF"}
    for k, rs in rows.items():
        out[k] = {s: {f: statistics.median([r.get(s, (0.0, 0.0, 0))[i] for r in rs]) / n * (1e3 if i < 2 else 1)
                      for i, f in enumerate(("user_ms", "sys_ms", "minflt"))} for s in rs[0]}
    tot = {k: out[k]["total"]["user_ms"] + out[k]["total"]["sys_ms"] for k in hls}
    out["ratio_vs_doe"] = tot["default"] / tot["doe"]
    emit_json(out, a.output)
    return out


if __name__ == "__main__":
    main()
