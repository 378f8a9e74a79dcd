"""DOE mask export benchmark: time and file size of the lithography masks of a 3000×3000, 16-level DOE.

Case (issue 4): a 3 mm square DOE at 1 µm pitch (3000×3000 pixels) whose phase at λ0 = 0.55 µm is a Fresnel
lens (f = 100 mm at λ0; the outer zones are 37–26 µm wide, about 2 µm per level) plus a smooth random
aberration (low-order polynomials, ~20 rad peak to valley), wrapped and quantised to 16 levels, fused silica:
4 masks. For GDSII and OASIS: the time of each stage (quantise + masks, feature sizes / report, rectangles +
file), the number of rectangles and the file size; the files are read back and compared with the masks; and
the whole ``raywave doe export`` work (GDS + PNG previews + report).

Prints one JSON object (and writes it with ``-o``).

    python benchmarks/doe_export.py [--n 3000] [--levels 16] [--repeat 1] [-o doe_export.json]
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from _report import emit_json  # noqa: E402  (benchmarks/ is on sys.path)


def test_phase(n: int, pitch: float = 1e-3, focal: float = 100.0, wavelength: float = 0.55, seed: int = 0):
    """(n, n) phase (rad at ``wavelength`` µm): a Fresnel lens of ``focal`` mm + a smooth random aberration."""
    c = (np.arange(n) - (n - 1) / 2) * pitch
    x, y = np.meshgrid(c, c)
    k = 2 * np.pi / (wavelength * 1e-3)
    phase = -k * (x ** 2 + y ** 2) / (2 * focal)
    rng = np.random.default_rng(seed)
    u, v = x / c[-1], y / c[-1]
    terms = [u, v, u * v, u ** 2 - v ** 2, u ** 3 - 3 * u * v ** 2, (u ** 2 + v ** 2) ** 2, u * (u ** 2 + v ** 2)]
    for t in terms:
        phase += rng.normal(0, 5.0) * t
    return phase


def run(n: int = 3000, levels: int = 16, repeat: int = 1, pitch: float = 1e-3) -> dict:
    from raywave.doe import fabrication as fab

    phase = test_phase(n, pitch)
    out = {"case": {"shape": [n, n], "pitch_um": pitch * 1e3, "levels": levels, "material": "FUSED_SILICA",
                    "wavelength_um": 0.55, "phase": "Fresnel lens f = 100 mm + smooth random aberration"},
           "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()}}
    t = time.perf_counter()
    lv = fab.quantise_phase(phase, levels)
    masks = fab.masks_from_levels(lv, levels)
    out["masks_s"] = time.perf_counter() - t
    t = time.perf_counter()
    depths = fab.etch_depths(levels, "fused_silica", 0.55)
    report = fab.mask_report(masks, pitch, depths)
    out["report_s"] = time.perf_counter() - t
    out["min_feature_um"] = [m["min_feature_um"] for m in report["per_mask"]]
    out["fill_factor"] = [round(m["fill_factor"], 4) for m in report["per_mask"]]
    t = time.perf_counter()
    rects = [fab.rectangles_from_mask(m) for m in masks]
    out["rectangles_s"] = time.perf_counter() - t
    out["rectangles"] = [len(r) for r in rects]
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("gds", "oas"):
            path = Path(tmp) / f"masks.{fmt}"
            times = []
            for _ in range(repeat):
                t = time.perf_counter()
                info = fab.write_mask_file(path, masks, pitch, name="bench", label=f"{levels} levels")
                times.append(time.perf_counter() - t)
            t = time.perf_counter()
            back = fab.read_mask_file(path, (n, n), pitch, masks=masks.shape[0])
            read_s = time.perf_counter() - t
            out[fmt] = {"write_s": float(np.median(times)), "export_s": out["masks_s"] + float(np.median(times)),
                        "size_mb": info["bytes"] / 1e6, "read_back_s": read_s,
                        "read_back_identical": bool((back == masks).all())}
        # the whole command (raywave doe export: quantise, masks, report, GDS, 4 PNG previews, report.json)
        from raywave.cli.doe_commands import export_masks
        from raywave.doe import PixelDOE

        doe = PixelDOE(phase, pitch, design_wavelength=0.55, trainable=False)
        t = time.perf_counter()
        export_masks(doe, levels, "fused_silica", 0.55, Path(tmp) / "cli", "gds", "bench")
        out["command_gds_with_png_s"] = time.perf_counter() - t
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=3000, help="DOE pixels per side (default 3000)")
    ap.add_argument("--levels", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=1, help="file writes per format (median time)")
    ap.add_argument("-o", "--output", default=None)
    a = ap.parse_args(argv)
    res = run(a.n, a.levels, a.repeat)
    emit_json(res, a.output)


if __name__ == "__main__":
    main()
