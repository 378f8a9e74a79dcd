"""One fabrication export path: a DOE → its L-level map → k = log2(L) binary masks → a mask file + report.

:func:`level_map` is the level map of a DOE at its design wavelength as the simulation sees a fabricated DOE
(:meth:`raywave.doe.DOE.fabricate`: wrap, then the nearest of L levels, L folding to 0), so the masks written
by :func:`export_design` are the element that :meth:`~raywave.doe.DOE.phase` simulates (``raywave doe export``
and :meth:`raywave.training.Trainer.export` both use it; no second quantiser). Mask previews (PNG) are the
CLI's business (plotting is not imported here).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

__all__ = ["level_map", "export_design"]


def level_map(doe, levels: int, wavelength0: float | None = None) -> np.ndarray:
    """``(ny, nx)`` int64 level map (0..L−1) of ``doe`` at ``wavelength0`` (µm; default the DOE's design
    wavelength): :meth:`DOE.levels` (the phase at λ0 wrapped to [0, 2π), nearest of L levels)."""
    with torch.no_grad():
        return np.asarray(doe.levels(levels, wavelength0).detach().cpu().numpy(), dtype=np.int64)


def export_design(doe, levels: int = 16, material="fused_silica", wavelength0: float = 0.55, folder="masks",
                  fmt: str = "gds", name: str = "DOE", min_feature: float | None = None,
                  info: dict | None = None) -> dict:
    """Quantise ``doe`` at ``wavelength0`` to ``levels`` levels, split the level map into binary masks and write
    ``folder/masks.<fmt>`` (GDSII / OASIS, :func:`~raywave.doe.fabrication.write_mask_file`) and
    ``folder/report.json`` (etch depths, feature sizes, level histogram, file facts, ``info``).

    Args:
        doe: a :class:`~raywave.doe.DOE` (any parametrisation).
        levels: L = 2^k phase levels.
        material: the relief's material (glass name or Material): sets the etch depths.
        wavelength0: design wavelength (µm).
        folder: output folder (created).
        fmt: "gds" or "oas".
        name: design name (mask label).
        min_feature: refuse masks with features below this (µm), or None.
        info: extra keys for the report.

    Returns:
        the report (dict, as written, plus ``"report"``: the JSON file's path). The written level map is
        :func:`level_map` ``(doe, levels, wavelength0)``.
    """
    from raywave.doe import fabrication as fab
    from raywave.materials import get_material

    k = fab.mask_bits(levels)  # L not a power of two: error before any work
    mat = get_material(material) if isinstance(material, str) else material
    depths = fab.etch_depths(levels, mat, wavelength0)
    n0 = fab._index(mat, wavelength0)
    t0 = time.perf_counter()
    lv = level_map(doe, levels, wavelength0)
    masks, report = _masks_and_report(lv, levels, k, doe.pitch, depths, min_feature)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"masks.{fmt}"
    label = _mask_label(levels, k, wavelength0, mat, n0, doe.pitch, depths)
    written, t_write = _write_masks(out, masks, doe.pitch, name, label, fmt, report)
    full = {
        "name": name,
        **(info or {}),
        **_material_facts(mat, wavelength0, n0),
        **report,
        "level_histogram": [int(c) for c in np.bincount(lv.reshape(-1), minlength=levels)],
        "min_feature_limit_um": min_feature,
        "file": str(out),
        "format": written["format"],
        "file_bytes": written["bytes"],
        "rectangles": sum(written["rectangles"]),
        "write_seconds": t_write,
        "export_seconds": time.perf_counter() - t0,
    }
    return _write_report(folder / "report.json", full)


def _write_report(rp: Path, full: dict) -> dict:
    """Write ``full`` as the JSON file ``rp``; returns ``full`` plus ``"report"``: that file's path."""
    rp.write_text(json.dumps(full, indent=2) + "\n", encoding="utf-8")
    full["report"] = str(rp)
    return full


def _masks_and_report(lv: np.ndarray, levels: int, k: int, pitch: float, depths, min_feature: float | None):
    """``(masks (k, ny, nx) bool, report)`` of the level map ``lv``: the binary masks and
    :func:`~raywave.doe.fabrication.mask_report` (``pitch`` mm, ``depths`` mm); refuses features below
    ``min_feature`` (µm) when given."""
    from raywave.doe import fabrication as fab

    masks = fab.masks_from_levels(lv, levels)
    features = [fab.min_features(masks[j]) for j in range(k)]
    if min_feature is not None:
        fab.check_min_feature(masks, pitch, min_feature, features)
    return masks, fab.mask_report(masks, pitch, depths, features)


def _mask_label(levels: int, k: int, wavelength0: float, mat, n0: float, pitch: float, depths) -> str:
    """The mask file's label: levels, masks, λ0 (µm), material and index, pitch (µm, from ``pitch`` in mm) and
    the etch depths (nm, from ``depths`` in mm)."""
    return (f"{levels} levels, {k} masks, lambda0 {wavelength0:g} um, {mat.name} (n {n0:.5f}), "
            f"pitch {pitch * 1e3:g} um\netch " + ", ".join(f"L{j + 1} {d * 1e6:.1f}" for j, d in
                                                        enumerate(depths)) + " nm; polygons = etched")


def _write_masks(out: Path, masks, pitch: float, name: str, label: str, fmt: str, report: dict):
    """Write the mask file (:func:`~raywave.doe.fabrication.write_mask_file`, ``pitch`` mm), add each mask's
    rectangle count to ``report["per_mask"]``; returns ``(what write_mask_file returned, seconds it took)``."""
    from raywave.doe import fabrication as fab

    t1 = time.perf_counter()
    written = fab.write_mask_file(out, masks, pitch, name=name, label=label, fmt=fmt)
    t_write = time.perf_counter() - t1
    for j, c in enumerate(written["rectangles"]):
        report["per_mask"][j]["rectangles"] = c
    return written, t_write


def _material_facts(mat, wavelength0: float, n0: float) -> dict:
    """The report's material keys: name, λ0 (µm), index n at λ0 and the 2π height (nm)."""
    from raywave.doe import fabrication as fab

    return {
        "material": mat.name,
        "wavelength_um": float(wavelength0),
        "n_at_wavelength": n0,
        "h_2pi_nm": fab.height_2pi(mat, wavelength0) * 1e6,
    }
