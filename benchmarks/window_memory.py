"""Peak memory per simulation sample of a PSF's DOE-plane field window (issue 47, class A): what
raywave.hybrid.coherent.geometry's window estimate guards, measured.

Each point is one PSF of a lens file's on-axis source in a fresh process (``--child``): the peak resident set size
(VmHWM, reset before the call) above the resident set before it, against the largest window any
``check_window_memory`` call of that PSF checked (simulation samples). Paths: the Fresnel edge step on the DOE plane
(``fresnel``), the exact angular-spectrum construction (``asm``), the caustic fallback (``fallback``: the DOE plane
near the rays' focus, the Fresnel step to an earlier plane and the angular spectrum beyond) and the DOE-plane edge
(``doe``); modes: ``nograd`` (torch.no_grad, the PSF/map path) and ``grad`` (the lens's parameters and a
BINARY_2 DOE's coefficients require grad; the PSF's weighted sum is backpropagated). The DOE pitch sets the window
size; a least-squares line over the pitches gives the bytes per sample (slope) and the constant (intercept).

    OMP_NUM_THREADS=1 python benchmarks/window_memory.py -o OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

#: the Zeiss Pro-Tessar 35 mm of the OpticExplorer database (issue 47's class A lens), its default (go_field) plane
#: and the beam-fit plane near the focus where the caustic fallback fires
LENS = "/tmp/optics/Optics/Photography/Zeiss/Zeiss Tessar/Zeiss Pro-Tessar 35mm f3.2.zmx"
PLANES = {"go_field": 3.871006143189959, "near_focus": 33.28752812603585}
PATHS = {"fresnel": dict(doe_distance=PLANES["go_field"], edge_step="fresnel"),
         "asm": dict(doe_distance=PLANES["go_field"], edge_step="asm"),
         "fallback": dict(doe_distance=PLANES["near_focus"]),
         "doe": dict(doe_distance=PLANES["go_field"], stop_edge="doe")}
PITCHES_UM = (9.6, 6.4, 4.8, 3.6)
#: :func:`fit`'s steepest rise counts neighbouring windows from this many samples on
RISE_FROM = 4e6


def child(lens: str, path: str, mode: str, pitch_um: float) -> dict:
    """One PSF (ks 32, 1.2 µm sensor pixels) of ``lens`` on axis at its primary wavelength, the DOE pitch
    ``pitch_um`` µm, the edge path ``path`` (:data:`PATHS`) and ``mode`` ("nograd" / "grad")."""
    import torch

    torch.set_num_threads(1)
    from _memory import peak_mb, reset_peak, rss_mb

    import raywave.hybrid.coherent.geometry as geometry
    from raywave.assembly.build import load_hybrid
    from raywave.doe.params import Binary2DOE

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(lens, doe_pitch=pitch_um * 1e-3, sensor_pitch=1.2e-3, **PATHS[path])
    if mode == "grad":
        hl.doe = Binary2DOE(torch.zeros(2, dtype=torch.float64), 5.0, hl.doe.shape, hl.doe.pitch)
    shapes, orig = [], geometry.check_window_memory

    def spy(ny, nx, p, *args, **kw):
        shapes.append((int(ny), int(nx)))
        return orig(ny, nx, p, *args, **kw)

    for mod in list(sys.modules.values()):  # every module that imported the check by name
        if mod is not None and getattr(mod, "check_window_memory", None) is orig:
            mod.check_window_memory = spy
    base = rss_mb()
    reset_peak()
    t = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        wl = hl.lens.primary_wavelength
        if mode == "nograd":
            with torch.no_grad():
                r = hl.psf_result((0.0, 0.0), wl, ks=32)
        else:
            r = hl.psf_result((0.0, 0.0), wl, ks=32)
            w = torch.linspace(0.0, 1.0, r.psf.numel(), dtype=r.psf.dtype).reshape(r.psf.shape)
            (r.psf * w).sum().backward()
    peak = peak_mb()
    samples = max((a * b for a, b in shapes), default=0)
    return dict(path=path, mode=mode, doe_pitch_um=pitch_um, windows=shapes, samples=samples, base_mb=base,
                peak_mb=peak, extra_mb=peak - base, bytes_per_sample=(peak - base) * 2**20 / max(samples, 1),
                s=time.perf_counter() - t, fallback=any("carried to it by the angular spectrum" in str(w.message)
                                                        for w in caught))


def fit(points: list) -> dict:
    """Least-squares line of the extra peak (bytes) against the window's samples (slope B/sample, intercept MiB), the
    whole extra peak per sample of the largest window, and the steepest rise (B/sample) between neighbouring sizes
    from :data:`RISE_FROM` samples on (below, the peak can sit in another stage: the rays, the graph)."""
    xs = [p["samples"] for p in points]
    ys = [p["extra_mb"] * 2**20 for p in points]
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx > 0 else float("nan")
    big = max(points, key=lambda p: p["samples"])
    srt = sorted(points, key=lambda p: p["samples"])
    rises = [(b["extra_mb"] - a["extra_mb"]) * 2**20 / (b["samples"] - a["samples"]) for a, b in zip(srt, srt[1:])
             if b["samples"] > a["samples"] and a["samples"] >= RISE_FROM]
    return dict(bytes_per_sample=slope, intercept_mb=(my - slope * mx) / 2**20, points=n, largest=big["samples"],
                largest_bytes_per_sample=big["bytes_per_sample"], steepest_rise=max(rises, default=float("nan")),
                rise_from=RISE_FROM)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default=LENS)
    ap.add_argument("--paths", nargs="*", default=list(PATHS), help="none: only --rows-from, fitted")
    ap.add_argument("--modes", nargs="+", default=["nograd", "grad"])
    ap.add_argument("--pitches", nargs="+", type=float, default=list(PITCHES_UM), help="DOE pitches, µm")
    ap.add_argument("--eager", action="store_true", help="RAYWAVE_COMPILE=0: the eager fallback of the fused kernels")
    ap.add_argument("--rows-from", nargs="*", type=Path, default=[], help="result files whose rows join the fits")
    ap.add_argument("--child", nargs=3, metavar=("PATH", "MODE", "PITCH_UM"), default=None)
    ap.add_argument("-o", "--output")
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.lens, a.child[0], a.child[1], float(a.child[2]))))
        return
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAYWAVE_MEMORY_LIMIT": os.environ.get("RAYWAVE_MEMORY_LIMIT",
                                                                                      "16GiB")}
    if a.eager:
        env["RAYWAVE_COMPILE"] = "0"
    rows = [r for f in a.rows_from for r in json.loads(f.read_text())["rows"]]
    for path in a.paths:
        for mode in a.modes:
            for pitch in a.pitches:
                out = subprocess.run([sys.executable, __file__, "--lens", a.lens, "--child", path, mode, str(pitch)],
                                     capture_output=True, text=True, env=env)
                line = [s for s in out.stdout.splitlines() if s.startswith("{")]
                if out.returncode or not line:
                    rows.append(dict(path=path, mode=mode, doe_pitch_um=pitch, error=out.stderr[-400:]))
                    continue
                rows.append(dict(json.loads(line[-1]), compile=not a.eager))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    fits = {}
    for key in sorted({(r["path"], r["mode"], r.get("compile", True)) for r in rows if "error" not in r}):
        pts = [r for r in rows if "error" not in r and (r["path"], r["mode"], r.get("compile", True)) == key]
        if len(pts) >= 2:
            fits["/".join((key[0], key[1]) + (() if key[2] else ("eager",)))] = fit(pts)
    res = dict(description=__doc__.split("\n\n")[0], lens=a.lens, command="OMP_NUM_THREADS=1 python "
               "benchmarks/window_memory.py " + " ".join(argv if argv is not None else sys.argv[1:]),
               memory_limit=env["RAYWAVE_MEMORY_LIMIT"], fits=fits, rows=rows)
    text = json.dumps(res, indent=1)
    print(text)
    if a.output:
        Path(a.output).write_text(text + "\n")


if __name__ == "__main__":
    main()
