"""Ray-wave PSF benchmark: accuracy against ray count, time and peak memory, for both field modes.

Case (issue 3): the bundled asphere (EFL 7.93 mm, F/3.97) + a 3 mm square DOE at 1 µm pitch (3000×3000
pixels, a trainable pixel phase map) 0.7 mm after the last surface, sensor at focus (3 µm pixels), ks = 128,
λ = 0.489 and 0.55 µm, on axis and at 0.7 of the full field (along the sensor diagonal).

* **error vs rays**: L1 distance ``Σ|psf − ref|`` (0 … 2) of both modes against (a) the ground truth of an
  ideal lens of the same EFL and F-number (the non-paraxial Debye PSF, on axis) and (b) a converged
  reference for the asphere (the accurate mode at 256 nodes, itself checked against the faithful mode);
* **time and peak memory per PSF**, forward and forward + backward (gradient w.r.t. the 9 M DOE pixels; the
  refractive lens frozen), for
  the accurate mode and for the faithful mode at 1e6 rays on the paper's full 2×-padded grid (6000² FFTs),
  each in its own process (median wall time; peak resident memory above the process's baseline), with the time
  its FFT kernels
  take (forward and backward, from torch.profiler); also with the DOE-plane field cached (a frozen lens
  traced once, the DOE-training step).

* **both stop edges** (issue 19, ``--edges``; bundled hybrid_asphere: 3 mm DOE at 1 µm, 0.7 mm after the
  lens, ks 128, λ 0.53 µm, default 64 nodes): ``stop_edge="doe"`` (the paper's model), ``"exit_pupil"`` with the
  exact angular-spectrum construction (``edge_step="asm"``) and with the Fresnel step (``"fresnel"``): time and
  peak memory per PSF (a fresh ``HybridLens`` per call: no transfer function reused), uncached and with the
  DOE-plane field cached, forward and forward + backward (gradient w.r.t. the DOE pixels, lens frozen; and,
  uncached, w.r.t. the lens too); L1 error against the exit-pupil Huygens PSF (``raywave.models.exit_pupil``,
  n_pupil 512, ks 32) on axis and at 0.7 and 1.0 of the full field (17.5°), and against the Debye truth of an ideal
  lens of the same EFL and F-number on axis (off axis: against its Huygens PSF). Peak memory is the resident peak
  (freed blocks that glibc keeps count); ``--live-memory`` measures the live peak instead (for memory only: every
  large block is then mapped afresh, which makes the times ~1.5–2× slower).

Prints one JSON object (and writes it with ``-o``).

    python benchmarks/psf.py [--threads 2] [--quick] [--edges] [-o psf.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time

from _memory import reset_peak, status_mb  # noqa: E402  (benchmarks/ is on sys.path)
from _report import emit_json  # noqa: E402

WAVELENGTHS = (0.489, 0.55)
KS = 128
DOE_N, DOE_PITCH, DOE_DIST = 3000, 1e-3, 0.7


def _fields(lens):
    """On axis and 0.7 of the full field along the sensor diagonal (degrees)."""
    full = max(lens.fields)
    w, h = lens.sensor_size
    phi = math.atan2(h, w)
    t = math.tan(math.radians(0.7 * full))
    return [(0.0, 0.0), (math.degrees(math.atan(t * math.cos(phi))), math.degrees(math.atan(t * math.sin(phi))))]


def _setup(pixel_doe: bool = False):
    import torch

    from raywave.doe import BlankDOE, PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import bundled_lens_path, load_lens

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    doe = PixelDOE(torch.zeros(DOE_N, DOE_N), DOE_PITCH) if pixel_doe else BlankDOE(DOE_N, DOE_PITCH)
    return HybridLens(lens, doe, DOE_DIST), lens


def _l1(a, b) -> float:
    return float((a - b).abs().sum())


def accuracy(quick: bool) -> dict:
    """Error against ray count for both modes (window propagation; identical to the full grid, see tests)."""
    import torch

    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens
    from raywave.models.debye import debye_psf

    hl, lens = _setup()
    fields = _fields(lens)
    nodes = [8, 12, 16, 24, 32, 48, 64] if not quick else [8, 16, 32]
    rays = [10_000, 30_000, 100_000, 300_000, 1_000_000] if not quick else [10_000, 100_000]
    out = {"fields_deg": fields, "wavelengths_um": list(WAVELENGTHS), "metric": "L1 = sum|psf - ref| (0..2)"}

    # (a) ground truth: an ideal lens of the same EFL and F-number, DOE at the same distance from the sensor
    efl = float(lens.paraxial().efl)
    fno = efl / float(lens.paraxial().epd)
    z_doe_sensor = float(lens.surfaces[-1].thickness.detach()) - DOE_DIST
    ideal = HybridLens(ideal_lens(efl, f_number=fno, wavelengths=WAVELENGTHS), BlankDOE(DOE_N, DOE_PITCH),
                       efl - z_doe_sensor, sensor_pitch=hl.sensor_pitch)
    truth = {}
    for wl in WAVELENGTHS:
        na = math.sin(math.atan(0.5 / fno))
        res = debye_psf(na, wl, KS, hl.sensor_pitch, oversample=15)  # 0.2 µm sub-samples: converged to ~1e-4
        truth[wl] = (res[0] if isinstance(res, tuple) else getattr(res, "psf", res)).to(torch.float64)
    rows = []
    for wl in WAVELENGTHS:
        for n in nodes:
            r = ideal.psf_result((0, 0), wl, ks=KS, rays=n)
            rows.append({"mode": "accurate", "wavelength": wl, "nodes": n, "rays": int(r.rays[0, 0]),
                         "l1": _l1(r.psf[0, 0].detach(), truth[wl])})
        for nr in rays:
            p = ideal.psf((0, 0), wl, ks=KS, mode="faithful", rays=nr, generator=torch.Generator().manual_seed(0))
            rows.append({"mode": "faithful", "wavelength": wl, "rays": nr, "l1": _l1(p[0, 0].detach(), truth[wl])})
    out["ideal_lens_vs_debye"] = rows

    # (b) the asphere against a converged reference
    rows = []
    for fi, fld in enumerate(fields):
        for wl in WAVELENGTHS:
            ref = hl.psf(fld, wl, ks=KS, rays=256)[0, 0].detach()
            for n in nodes:
                r = hl.psf_result(fld, wl, ks=KS, rays=n)
                rows.append({"mode": "accurate", "field": fi, "wavelength": wl, "nodes": n, "rays": int(r.rays[0, 0]),
                             "l1": _l1(r.psf[0, 0].detach(), ref)})
            for nr in rays:
                p = hl.psf(fld, wl, ks=KS, mode="faithful", rays=nr, generator=torch.Generator().manual_seed(0))
                rows.append({"mode": "faithful", "field": fi, "wavelength": wl, "rays": nr,
                             "l1": _l1(p[0, 0].detach(), ref)})
    out["asphere_vs_converged"] = rows
    return out


def _rays_to_match(rows, key_filter, target: float):
    """Fewest accurate-mode rays whose error is at most ``target`` for every field/wavelength."""
    import collections

    worst = collections.defaultdict(float)
    for r in rows:
        if r["mode"] == "accurate" and key_filter(r):
            worst[r["nodes"]] = max(worst[r["nodes"]], r["l1"])
    rays = {r["nodes"]: r["rays"] for r in rows if r["mode"] == "accurate"}
    ok = [n for n in sorted(worst) if worst[n] <= target]
    return (ok[0], rays[ok[0]]) if ok else (None, None)


def _fft_seconds(fn) -> float:
    """Self CPU time of the FFT kernels (forward and backward) while ``fn`` runs (torch.profiler)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return sum(e.self_cpu_time_total for e in prof.key_averages() if "fft" in e.key.lower()) / 1e6


def timing_case(mode: str, backward: bool, nodes: int, threads: int, repeat: int, cached: bool = False) -> dict:
    """Wall time, FFT time and peak memory of one PSF (λ = 0.55, 0.7 field) in this process.

    ``cached``: the DOE-training step of a frozen refractive lens (the DOE-plane field is traced once and
    reused, as ``HybridLens.psf(cache=...)`` does); otherwise the whole pipeline runs every time."""
    import torch

    torch.set_num_threads(threads)
    hl, lens = _setup(pixel_doe=True)
    lens.requires_grad_(False)  # gradients w.r.t. the DOE pixels only (the case)
    fld = _fields(lens)[1]
    if mode == "accurate":
        kw = dict(rays=nodes)
    else:
        kw = dict(mode="faithful", rays=1_000_000, full_grid=True, generator=torch.Generator().manual_seed(0))
    cache = [[f.detach() for f in row] for row in hl.doe_fields(fld, 0.55, **kw)] if cached else None
    weight = torch.linspace(0, 1, KS * KS, dtype=torch.float64).reshape(KS, KS)

    def once():
        hl.zero_grad(set_to_none=True)
        if cached:
            psf = hl.psf(ks=KS, cache=cache)
        else:
            if "generator" in kw:
                kw["generator"].manual_seed(0)
            psf = hl.psf(fld, 0.55, ks=KS, **kw)
        if backward:
            (psf * weight).sum().backward()
        else:
            psf = psf.detach()
        return psf

    base = status_mb("VmRSS")
    reset_peak()
    with torch.set_grad_enabled(backward):
        once()  # warm-up (and the peak)
        peak = status_mb("VmHWM") - base
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            once()
            times.append(time.perf_counter() - t0)
        ffts = sorted(_fft_seconds(once) for _ in range(repeat))
    times.sort()
    median = times[len(times) // 2]
    fft = ffts[len(ffts) // 2]
    return {"mode": mode, "backward": backward, "cached_doe_field": cached,
            ("nodes" if mode == "accurate" else "rays"): nodes if mode == "accurate" else 1_000_000,
            "seconds": median, "seconds_min": times[0], "fft_seconds": fft, "peak_extra_memory_mb": peak,
            "repeat": repeat, "threads": threads}


EDGE_CASES = (("doe", "auto"), ("exit_pupil", "asm"), ("exit_pupil", "fresnel"))
EDGE_WL, EDGE_FIELDS = 0.53, (0.0, 0.7, 1.0)
#: the Huygens reference's pupil samples: converged to ~1e-4 at 17.5° (384 → 512: 1.8e-4, 512 → 640: 8e-5; at 192
#: it was itself ~1e-3 off, as much as the Fresnel step it measures)
EDGE_HUYGENS_PUPIL = 512
#: the errors' crop (3 µm pixels): the tests' (tests/test_hybrid_stop_edge.py); the Huygens PSF at n_pupil 512 costs
#: ~1 min per field at ks 32
EDGE_ERROR_KS = 32


def _edge_lens(edge: str, step: str, pixel_doe: bool = False):
    import torch

    from raywave.doe import BlankDOE, PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import bundled_lens_path, load_lens

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    doe = PixelDOE(torch.zeros(DOE_N, DOE_N), DOE_PITCH) if pixel_doe else BlankDOE(DOE_N, DOE_PITCH)
    return HybridLens(lens, doe, DOE_DIST, stop_edge=edge, edge_step=step), lens


def edge_timing_case(edge: str, step: str, backward: bool, cached: bool, lens_grad: bool, threads: int,
                     repeat: int, field: float) -> dict:
    """Median wall time and peak memory of one PSF (ks 128, λ 0.53) with a fresh HybridLens per call."""
    import torch

    torch.set_num_threads(threads)
    weight = torch.linspace(0, 1, KS * KS, dtype=torch.float64).reshape(KS, KS)
    fld = (0.0, field)
    cache = None
    if cached:
        hl, lens = _edge_lens(edge, step, pixel_doe=True)
        lens.requires_grad_(False)
        cache = [[f.detach() for f in row] for row in hl.doe_fields(fld, EDGE_WL)]

    def once():
        hl, lens = _edge_lens(edge, step, pixel_doe=True)
        lens.requires_grad_(lens_grad)
        psf = hl.psf(ks=KS, cache=cache) if cached else hl.psf(fld, EDGE_WL, ks=KS)
        if backward:
            (psf * weight).sum().backward()
        return psf.detach()

    base = status_mb("VmRSS")
    reset_peak()
    with torch.set_grad_enabled(backward):
        once()
        peak = status_mb("VmHWM") - base
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            once()
            times.append(time.perf_counter() - t0)
    times.sort()
    return {"stop_edge": edge, "edge_step": step if edge == "exit_pupil" else None, "field_deg": field,
            "backward": backward, "lens_grad": lens_grad, "cached_doe_field": cached,
            "seconds": times[len(times) // 2], "seconds_min": times[0], "peak_extra_memory_mb": peak,
            "repeat": repeat, "threads": threads}


def edge_errors(cases=EDGE_CASES, fields=EDGE_FIELDS, lenses=("asphere_hk51", "ideal")) -> dict:
    """L1 of each edge against the Huygens PSF (asphere) and the Debye truth (ideal lens, on axis)."""
    import torch

    from raywave.doe import BlankDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens
    from raywave.models import huygens_psf
    from raywave.models.debye import debye_psf

    out = {"metric": "L1 = sum|psf - ref| (0..2)", "wavelength_um": EDGE_WL, "ks": EDGE_ERROR_KS,
           "huygens_n_pupil": EDGE_HUYGENS_PUPIL, "rows": []}
    _, lens = _edge_lens("doe", "auto")
    full = max(lens.fields)
    efl, epd = float(lens.paraxial().efl), float(lens.paraxial().epd)
    ideal = ideal_lens(efl, f_number=efl / epd, wavelengths=(EDGE_WL,))
    z_doe_sensor = float(lens.surfaces[-1].thickness.detach()) - DOE_DIST
    ps = 3e-3
    for name, base in (("asphere_hk51", lens), ("ideal", ideal)):
        if name not in lenses:
            continue
        for fr in fields:
            fld = (0.0, fr * full)
            ref = huygens_psf(base, fld, EDGE_WL, ks=EDGE_ERROR_KS, pitch=ps,
                              n_pupil=EDGE_HUYGENS_PUPIL).psf.to(torch.float64)
            debye = None
            if name == "ideal" and fr == 0.0:
                res = debye_psf(math.sin(math.atan(0.5 * epd / efl)), EDGE_WL, EDGE_ERROR_KS, ps, oversample=15)
                debye = (res[0] if isinstance(res, tuple) else getattr(res, "psf", res)).to(torch.float64)
            for edge, step in cases:
                d = DOE_DIST if name == "asphere_hk51" else efl - z_doe_sensor
                hl = HybridLens(base, BlankDOE(6000, DOE_PITCH), d, sensor_pitch=ps, stop_edge=edge, edge_step=step)
                t0 = time.perf_counter()
                p = hl.psf(fld, EDGE_WL, ks=EDGE_ERROR_KS)[0, 0].detach()
                row = {"lens": name, "field": fr, "field_deg": fld[1], "stop_edge": edge,
                       "edge_step": step if edge == "exit_pupil" else None, "l1_vs_huygens": _l1(p, ref),
                       "seconds": time.perf_counter() - t0}
                if debye is not None:
                    row["l1_vs_debye"] = _l1(p, debye)
                    row["huygens_l1_vs_debye"] = _l1(ref, debye)
                out["rows"].append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    return out


def _median_of_processes(rows: list) -> dict:
    """One case's result over fresh processes: the median time and peak memory (a single process's peak RSS
    scatters by ~±10 %), with every process's values kept."""
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return rows[0]
    if len(ok) == 1:
        return ok[0]
    out = dict(ok[0])
    for key in ("seconds", "seconds_min", "peak_extra_memory_mb"):
        vals = sorted(r[key] for r in ok)
        out[key] = vals[len(vals) // 2]
        out[f"{key}_processes"] = [r[key] for r in ok]
    out["processes"] = len(ok)
    return out


def _memory_env(live: bool) -> dict:
    """The child processes' environment: with ``live``, glibc serves every allocation of 64 KB or more by mmap and
    returns it when freed, so the resident peak is the live peak (by default glibc keeps freed large blocks once it
    has raised its threshold, and the resident peak includes them)."""
    env = dict(os.environ)
    if live:
        env["MALLOC_MMAP_THRESHOLD_"] = "65536"
    return env


def edges_main(args) -> dict:
    cases = []
    steps = args.edge_steps.split(",")
    edge_cases = [(e, s) for e, s in EDGE_CASES if (s if e == "exit_pupil" else "doe") in steps]
    configs = ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 1, 0), (1, 1, 0))
    if args.edge_quick:  # uncached forward only
        configs = ((0, 0, 0),)
    for edge, step in edge_cases:
        for bwd, cached, lens_grad in configs:
            cases.append((edge, step, bwd, cached, lens_grad))
    runs = {c: [] for c in cases}
    for _ in range(max(1, args.processes)):  # the cases interleaved: a drifting machine affects both edges alike
        for edge, step, bwd, cached, lens_grad in cases:
            cmd = [sys.executable, __file__, "--edge-case",
                   f"{edge},{step},{bwd},{cached},{lens_grad},{args.edge_field}", "--threads", str(args.threads),
                   "--repeat", str(args.repeat)]
            res = subprocess.run(cmd, capture_output=True, text=True, env=_memory_env(args.live_memory))
            if res.returncode != 0:
                row = {"stop_edge": edge, "edge_step": step, "error": res.stderr.strip().splitlines()[-1]}
            else:
                row = json.loads(res.stdout.strip().splitlines()[-1])
            runs[(edge, step, bwd, cached, lens_grad)].append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    timings = [_median_of_processes(rows) for rows in runs.values()]
    t = {(x["stop_edge"], x.get("edge_step"), x.get("backward"), x.get("cached_doe_field"), x.get("lens_grad")): x
         for x in timings}
    ratios = {}
    for step in ("asm", "fresnel"):
        for key in ((False, False, False), (True, False, False), (True, False, True), (False, True, False),
                    (True, True, False)):
            a, b = t.get(("exit_pupil", step) + key, {}), t.get(("doe", None) + key, {})
            if "seconds" in a and "seconds" in b:
                name = (f"{step}: {'fwd+bwd' if key[0] else 'fwd'}{', cached' if key[1] else ''}"
                        f"{', lens grad' if key[2] else ''}")
                ratios[name] = {"time": a["seconds"] / b["seconds"],
                                "memory": a["peak_extra_memory_mb"] / max(b["peak_extra_memory_mb"], 1e-9)}
    out = {"benchmark": "psf stop edges", "lens": "hybrid_asphere (3 mm DOE, 1 µm, 0.7 mm)", "ks": KS,
           "threads": args.threads, "timing_field_deg": args.edge_field,
           "memory": ("live: glibc returns every block of 64 KB or more when freed (MALLOC_MMAP_THRESHOLD_=65536)"
                      if args.live_memory else "resident (VmHWM): includes freed blocks the allocator keeps"),
           "timing": timings,
           "exit_pupil_over_doe (goal: time <= 2, memory <= 1.5)": ratios}
    if not args.no_errors:
        fields = tuple(float(f) for f in args.edge_error_fields.split(","))
        out["errors"] = edge_errors(edge_cases, fields, args.edge_error_lenses.split(","))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=5, help="timed repetitions per case (median reported)")
    ap.add_argument("--quick", action="store_true", help="fewer ray counts, no faithful full-grid timing")
    ap.add_argument("--nodes", type=int, default=None, help="accurate-mode nodes for the timing (default: the "
                    "fewest that reach the faithful mode's 1e6-ray error)")
    ap.add_argument("-o", "--output", default=None)
    ap.add_argument("--case", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--edges", action="store_true", help="only the stop-edge comparison (issue 19)")
    ap.add_argument("--edge-field", type=float, default=12.25, help="field (deg) of the stop-edge timing")
    ap.add_argument("--no-errors", action="store_true", help="stop-edge comparison: timings only")
    ap.add_argument("--edge-case", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--edge-steps", default="doe,asm,fresnel", help="stop-edge comparison: the cases, a subset of "
                    "doe,asm,fresnel (cheap: doe,fresnel)")
    ap.add_argument("--edge-quick", action="store_true", help="stop-edge timing: uncached forward only")
    ap.add_argument("--live-memory", action="store_true", help="stop-edge timing: peak memory of live allocations "
                    "(glibc returns every freed block of 64 KB or more) instead of the resident peak; slows the times")
    ap.add_argument("--processes", type=int, default=1, help="stop-edge timing: run every case in this many fresh "
                    "processes (interleaved) and report the medians (peak memory scatters by ~±10 %% per process)")
    ap.add_argument("--edge-error-fields", default="0,0.7,1", help="stop-edge errors: fractions of the full field")
    ap.add_argument("--edge-error-lenses", default="asphere_hk51,ideal", help="stop-edge errors: asphere_hk51, ideal")
    args = ap.parse_args()
    if args.edge_case:
        edge, step, bwd, cached, lens_grad, fld = args.edge_case.split(",")
        print(json.dumps(edge_timing_case(edge, step, bwd == "1", cached == "1", lens_grad == "1", args.threads,
                                          args.repeat, float(fld))))
        return
    if args.edges:
        emit_json(edges_main(args), args.output)
        return
    if args.case:
        mode, bwd, nodes, cached = args.case.split(",")
        print(json.dumps(timing_case(mode, bwd == "1", int(nodes), args.threads, args.repeat, cached == "1")))
        return
    import torch

    torch.set_num_threads(args.threads)
    acc = accuracy(args.quick)
    rows = acc["asphere_vs_converged"]
    faithful_1e6 = max((r["l1"] for r in rows if r["mode"] == "faithful" and r["rays"] == max(
        x["rays"] for x in rows if x["mode"] == "faithful")), default=float("nan"))
    n_match, rays_match = _rays_to_match(rows, lambda r: True, faithful_1e6)
    nodes = args.nodes or n_match or 32
    timings = []
    cases = [("accurate", 0, 0), ("accurate", 1, 0), ("accurate", 0, 1), ("accurate", 1, 1)]
    if not args.quick:
        cases += [("faithful", 0, 0), ("faithful", 1, 0), ("faithful", 1, 1)]
    for mode, bwd, cached in cases:
        cmd = [sys.executable, __file__, "--case", f"{mode},{bwd},{nodes},{cached}", "--threads", str(args.threads),
               "--repeat", str(args.repeat)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            timings.append({"mode": mode, "backward": bool(bwd), "error": res.stderr.strip().splitlines()[-1]})
        else:
            timings.append(json.loads(res.stdout.strip().splitlines()[-1]))
    t = {(x["mode"], x["backward"], x.get("cached_doe_field", False)): x for x in timings}
    acc_fb, fai_fb = t.get(("accurate", True, False), {}), t.get(("faithful", True, False), {})
    acc_fb_c, fai_fb_c = t.get(("accurate", True, True), {}), t.get(("faithful", True, True), {})

    def ratio(a, b, key_a="seconds", key_b="seconds"):
        return (a[key_a] / b[key_b]) if key_a in a and key_b in b else None

    max_faithful_rays = max(r["rays"] for r in rows if r["mode"] == "faithful")
    summary = {
        "benchmark": "psf", "lens": "asphere_hk51 + 3 mm square DOE, 1 µm pitch (3000²), 0.7 mm after the lens",
        "ks": KS, "sensor_pitch_um": 3.0, "threads": args.threads, "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
        "accuracy": acc,
        "timing": timings,
        "goals": {
            "faithful_error_at_max_rays": faithful_1e6, "faithful_max_rays": max_faithful_rays,
            "accurate_nodes_to_match": n_match, "accurate_rays_to_match": rays_match,
            "ray_ratio (goal >= 10)": (max_faithful_rays / rays_match) if rays_match else None,
            "fwd_bwd_speedup_vs_faithful_full_grid (goal >= 20)": ratio(fai_fb, acc_fb),
            "fwd_bwd_speedup_vs_faithful_full_grid, cached DOE field": ratio(fai_fb_c, acc_fb_c),
            "accurate_fwd_bwd_time_over_its_fft_time (goal <= 2.5)": ratio(acc_fb, acc_fb, "seconds", "fft_seconds"),
            "accurate_fwd_bwd_time_over_its_fft_time, cached DOE field": ratio(acc_fb_c, acc_fb_c, "seconds",
                                                                               "fft_seconds"),
            "accurate_fwd_time_over_its_fft_time": ratio(t.get(("accurate", False, False), {}),
                                                         t.get(("accurate", False, False), {}), "seconds", "fft_seconds"),
            "accurate_peak_memory_mb (goal < 1024)": max(x.get("peak_extra_memory_mb", 0) for x in timings
                                                         if x["mode"] == "accurate"),
        },
    }
    emit_json(summary, args.output)


if __name__ == "__main__":
    main()
