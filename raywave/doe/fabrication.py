"""Fabrication of a quantised DOE by binary lithography: masks, etch depths, mask files (GDSII / OASIS).

An L-level DOE (L = 2^k) is made with k lithography + etch steps. Step j (j = 1..k) exposes binary mask j and
etches the exposed areas by

    d_j = h_2π / 2^j,        h_2π = λ0 / (n(λ0) − 1)

(the relief height that delays the phase by 2π at the design wavelength λ0; fused silica at 0.55 µm:
h_2π = 1196 nm, d = 598, 299, 150, 75 nm).

Conventions (chosen here, used by every function of this module, the mask files and ``raywave doe export``):

* **Levels and heights.** Level ℓ ∈ [0, L) is the phase 2πℓ/L at λ0, made by the relief height (material
  thickness above the deepest etch floor) ``h(ℓ) = ℓ·h_2π/L``, so that φ = 2π(n − 1)h/λ0 (surrounding medium:
  air). Level L − 1 is the unetched top surface; level 0 is etched by every mask.
* **Masks: True = etched.** ``masks[j-1]`` is True where step j etches (the polygons written to the mask file
  are the areas to etch: openings of a positive-tone resist). The etch depth of a pixel is
  ``e = Σ_j masks[j-1]·d_j = (L − 1 − ℓ)·h_2π/L``, i.e. ``h(ℓ) = h(L − 1) − e``.
* **Bit order: mask 1 is the most significant bit and the deepest etch.** With e/(h_2π/L) = L − 1 − ℓ
  = Σ_j b_j·2^(k−j), ``masks[j-1] = b_j``: mask j holds bit (k − j) of L − 1 − ℓ (= the complement of that
  bit of ℓ).
* **Geometry.** A mask array is indexed ``[iy, ix]`` like the DOE (:mod:`raywave.doe.base`): pixel
  ``[iy, ix]`` is centred at ``((ix − (nx−1)/2)·pitch, (iy − (ny−1)/2)·pitch)``, the grid centred on the axis.
  Outside the DOE grid the substrate is not etched (the unetched field of every mask).
* **Feature sizes.** A mask's features are its runs of equal pixels along rows and columns: etched runs
  ("lines") and unetched runs between two etched ones ("spaces"). Runs that reach the edge of the grid are not
  counted: an unetched one merges with the unetched field outside, an etched one is cut by the DOE's edge (its
  width is where the DOE ends, not a width of the design).

Mask files (:func:`write_mask_file`, gdstk): units µm (unit 1e-6 m, precision 1e-9 m), the DOE centred at the
origin. Top cell ``TOP`` references cell ``DOE`` (mask j on layer j, datatype 0: one rectangle per run of
etched pixels along a row, runs identical in consecutive rows merged into one rectangle — no global boolean
merge), cell ``ALIGN`` (a cross in each of the four corners outside the DOE, on every mask layer, at the same
place, for layer-to-layer alignment) and cell ``LABEL`` (the name, levels, λ0, material, depths and pitch as
polygon text and as a text element, on layer :data:`LABEL_LAYER`). :func:`read_mask_file` reads the masks back
(rasterising cell ``DOE`` at the pitch).

Lengths are mm in the API (pitch, depths); reports give µm (pitch, feature sizes) and nm (depths).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from raywave.utils.checks import positive_float

__all__ = ["LABEL_LAYER", "MASK_FORMATS", "check_min_feature", "etch_depths", "etch_profile", "height_2pi",
           "level_heights", "levels_from_masks", "mask_bits", "mask_report", "masks_from_levels", "min_features",
           "quantise_phase", "read_mask_file", "rectangles_from_mask", "write_mask_file"]

#: GDS / OASIS layer of the text label (mask j is on layer j).
LABEL_LAYER = 100
#: File formats of :func:`write_mask_file`: extension -> name.
MASK_FORMATS = {"gds": "GDSII", "oas": "OASIS"}
_UNIT = 1e-6        # file unit: µm
_PRECISION = 1e-9   # database unit: 1 nm


# ---------------------------------------------------------------------------- levels, bits, depths
def mask_bits(levels: int) -> int:
    """k for L = 2^k levels; anything else (L = 12, 1, 2.5, ...) is a ValueError naming L."""
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)):
        if isinstance(levels, float) and levels.is_integer():
            levels = int(levels)
        else:
            raise ValueError(f"the number of levels must be an integer power of two (2, 4, 8, 16, ...), got "
                             f"{levels!r}")
    L = int(levels)
    if L < 2 or L & (L - 1):
        raise ValueError(f"mask export needs a number of levels that is a power of two (2, 4, 8, 16, ...: k binary "
                         f"masks make 2^k levels), got L = {L}")
    return L.bit_length() - 1


def _material(material):
    from raywave.materials import Material, get_material

    if isinstance(material, Material):
        return material
    return get_material(str(material))


def _index(material, wavelength0: float) -> float:
    import torch

    w = float(wavelength0)
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"the design wavelength must be > 0 µm, got {wavelength0!r}")
    with torch.no_grad():
        n = float(_material(material).n(torch.tensor(w, dtype=torch.float64, device="cpu")))
    if not (math.isfinite(n) and n > 1):
        raise ValueError(f"the DOE material must have n > 1 at {w:g} µm (n = {n:g}): a relief in it cannot delay "
                         "the phase")
    return n


def height_2pi(material, wavelength0: float) -> float:
    """h_2π = λ0 / (n(λ0) − 1) in mm: the relief height that delays the phase by 2π at ``wavelength0`` (µm).

    ``material``: a :class:`~raywave.materials.Material` or a name for :func:`~raywave.materials.get_material`."""
    return float(wavelength0) / (_index(material, wavelength0) - 1.0) * 1e-3


def etch_depths(levels: int, material, wavelength0: float) -> np.ndarray:
    """Etch depth of each mask step (mm), ``d_j = h_2π / 2^j`` for j = 1..k: a (k,) float64 array, deepest first."""
    k = mask_bits(levels)
    h = height_2pi(material, wavelength0)
    return np.array([h / 2.0 ** j for j in range(1, k + 1)], dtype=np.float64)


def _check_level_map(level_map, levels: int) -> np.ndarray:
    try:
        import torch

        if isinstance(level_map, torch.Tensor):
            level_map = level_map.detach().cpu().numpy()
    except ImportError:  # pragma: no cover
        pass
    a = np.asarray(level_map)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"a level map must be a non-empty 2-D (ny, nx) array, got shape {a.shape}")
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"a level map must hold integers, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.floating):
        if not np.isfinite(a).all() or (a != np.round(a)).any():
            raise ValueError("a level map must hold integers in [0, L); it holds non-integer or non-finite values")
    lo, hi = a.min(), a.max()
    if lo < 0 or hi >= levels:
        bad = np.argwhere((a < 0) | (a >= levels))[0]
        raise ValueError(f"level map values must lie in [0, {levels}) for L = {levels} levels; found values from "
                         f"{lo:g} to {hi:g} (first outside at [{bad[0]}, {bad[1]}]: {a[bad[0], bad[1]]:g})")
    return a.astype(np.int64, copy=False)


def quantise_phase(phase, levels: int) -> np.ndarray:
    """Level map (int64 numpy array, values in [0, L)) of a phase map (rad, array-like): the nearest level of the
    phase wrapped to [0, 2π), level L folding to 0 — :func:`raywave.doe.base.phase_levels` (the one quantiser)
    on numpy arrays."""
    import torch

    from raywave.doe.base import phase_levels

    ph = np.asarray(phase, dtype=np.float64)
    if not np.isfinite(ph).all():
        raise ValueError("the phase map contains NaN or inf values")
    return phase_levels(torch.from_numpy(ph), levels).numpy()


def masks_from_levels(level_map, levels: int) -> np.ndarray:
    """The k binary masks of an L-level map: a (k, ny, nx) bool array, ``masks[j-1]`` True where step j etches
    (module docstring: mask 1 = most significant bit of L − 1 − ℓ = the deepest etch)."""
    k = mask_bits(levels)
    a = _check_level_map(level_map, levels)
    e = (levels - 1) - a   # etch in units of h_2π / L
    return np.stack([((e >> (k - j)) & 1).astype(bool) for j in range(1, k + 1)])


def _check_masks(masks) -> np.ndarray:
    m = np.asarray(masks)
    if m.ndim != 3 or m.shape[0] < 1 or m.shape[1] < 1 or m.shape[2] < 1:
        raise ValueError(f"masks must be a (k, ny, nx) array, got shape {m.shape}")
    if m.dtype != bool:
        if not (np.issubdtype(m.dtype, np.integer) and ((m == 0) | (m == 1)).all()):
            raise ValueError(f"masks must be boolean (True = etched), got dtype {m.dtype}")
        m = m.astype(bool)
    return m


def levels_from_masks(masks) -> np.ndarray:
    """Inverse of :func:`masks_from_levels`: the (ny, nx) int64 level map of k masks (L = 2^k)."""
    m = _check_masks(masks)
    k = m.shape[0]
    e = np.zeros(m.shape[1:], dtype=np.int64)
    for j in range(1, k + 1):
        e += m[j - 1].astype(np.int64) << (k - j)
    return (2 ** k - 1) - e


def level_heights(level_map, levels: int, material, wavelength0: float) -> np.ndarray:
    """Relief height (mm) of a level map: ``h(ℓ) = ℓ·h_2π/L`` (float64 (ny, nx))."""
    a = _check_level_map(level_map, levels)
    return a * (height_2pi(material, wavelength0) / levels)


def etch_profile(masks, depths) -> np.ndarray:
    """Total etch depth (mm) of every pixel after all steps: ``Σ_j masks[j-1]·depths[j-1]`` (float64 (ny, nx))."""
    m = _check_masks(masks)
    d = np.asarray(depths, dtype=np.float64).reshape(-1)
    if d.shape[0] != m.shape[0]:
        raise ValueError(f"{m.shape[0]} masks need {m.shape[0]} etch depths, got {d.shape[0]}")
    out = np.zeros(m.shape[1:], dtype=np.float64)
    for j in range(m.shape[0]):
        out += m[j] * d[j]
    return out


# ---------------------------------------------------------------------------- feature sizes, report
def _check_pitch(pitch) -> float:
    return positive_float(pitch, "the pixel pitch", "mm")


def _runs(mask2d: np.ndarray):
    """Along rows: (line lengths, space lengths) in pixels (spaces: unetched runs between two etched runs)."""
    ny, nx = mask2d.shape
    padded = np.zeros((ny, nx + 2), dtype=np.int8)
    padded[:, 1:-1] = mask2d
    d = np.diff(padded, axis=1)
    rs, s = np.nonzero(d == 1)
    _, e = np.nonzero(d == -1)     # row-major order: the i-th end closes the i-th start
    inside = (s > 0) & (e < nx)    # a run cut by the grid edge has the width of the cut, not of the design
    lines = (e - s)[inside]
    same = rs[1:] == rs[:-1]
    spaces = (s[1:] - e[:-1])[same]
    return lines, spaces


def min_features(mask) -> dict:
    """Smallest line (etched run) and space (unetched run between etched ones) of one (ny, nx) mask along rows
    and columns, in pixels, not counting runs that reach the grid edge (module docstring): ``{"line": int | None, "space": int | None, "feature": min of both | None}``
    (None: no such run, e.g. an empty mask)."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"a mask must be 2-D (ny, nx), got shape {m.shape}")
    lr, sr = _runs(m)
    lc, sc = _runs(m.T)
    line = min((int(x.min()) for x in (lr, lc) if x.size), default=None)
    space = min((int(x.min()) for x in (sr, sc) if x.size), default=None)
    feats = [v for v in (line, space) if v is not None]
    return {"line": line, "space": space, "feature": min(feats) if feats else None}


def mask_report(masks, pitch: float, depths, features: list | None = None) -> dict:
    """A JSON-ready description of the masks: levels, depths (nm), pitch (µm), and for every mask its layer,
    depth, minimum feature / line / space (µm; None where the mask has none) and fill factor (etched fraction
    of the grid).

    Args:
        masks: (k, ny, nx) bool, True = etched.
        pitch: pixel pitch (mm).
        depths: (k,) etch depths (mm), e.g. :func:`etch_depths`.
        features: precomputed :func:`min_features` of every mask (optional).
    """
    m = _check_masks(masks)
    p = _check_pitch(pitch)
    d = np.asarray(depths, dtype=np.float64).reshape(-1)
    k = m.shape[0]
    if d.shape[0] != k:
        raise ValueError(f"{k} masks need {k} etch depths, got {d.shape[0]}")
    if features is None:
        features = [min_features(m[j]) for j in range(k)]
    um = p * 1e3

    def _um(v):
        return None if v is None else v * um

    per = []
    for j in range(k):
        f = features[j]
        per.append({
            "mask": j + 1, "layer": j + 1, "datatype": 0, "depth_nm": float(d[j] * 1e6),
            "min_feature_um": _um(f["feature"]), "min_line_um": _um(f["line"]), "min_space_um": _um(f["space"]),
            "min_feature_px": f["feature"], "fill_factor": float(m[j].mean()),
        })
    feats = [f["feature"] for f in features if f["feature"] is not None]
    ny, nx = m.shape[1:]
    return {
        "levels": 2 ** k,
        "masks": k,
        "depths_nm": [float(x * 1e6) for x in d],
        "total_depth_nm": float(d.sum() * 1e6),
        "pitch_um": um,
        "shape": [int(ny), int(nx)],
        "size_mm": [nx * p, ny * p],
        "min_feature_um": _um(min(feats)) if feats else None,
        "polarity": "True / polygons = etched; mask 1 = deepest etch (most significant bit of L-1-level); "
                    "level L-1 = unetched top surface",
        "per_mask": per,
    }


def check_min_feature(masks, pitch: float, min_feature: float, features: list | None = None) -> None:
    """Raise a ValueError if the fab cannot make the masks: ``min_feature`` (µm, the smallest feature the
    lithography resolves) is larger than the pixel pitch and some mask has a line or space narrower than it.
    The message names the mask, its smallest feature, the limit and the pitch."""
    m = _check_masks(masks)
    p_um = _check_pitch(pitch) * 1e3
    f = float(min_feature)
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"the minimum feature size must be > 0 µm, got {min_feature!r}")
    if f <= p_um * (1 + 1e-9):
        return          # every feature is at least one pixel
    if features is None:
        features = [min_features(m[j]) for j in range(m.shape[0])]
    for j, ft in enumerate(features):
        v = ft["feature"]
        if v is not None and v * p_um < f * (1 - 1e-9):
            raise ValueError(f"the DOE pitch {p_um:g} µm is finer than the fab's minimum feature {f:g} µm: mask "
                             f"{j + 1} (etch {j + 1} of {m.shape[0]}) has a feature of {v} pixel(s) = "
                             f"{v * p_um:g} µm; resample the DOE to a pitch >= {f:g} µm or use fewer levels")


# ---------------------------------------------------------------------------- mask files
def rectangles_from_mask(mask) -> np.ndarray:
    """Rectangles (int64 (n, 4): ix0, iy0, ix1, iy1, pixel-index corners, ends exclusive) covering the etched
    pixels of one (ny, nx) mask exactly, without overlaps: every run of etched pixels along a row, runs with
    the same columns in consecutive rows merged into one rectangle. Vectorised, O(pixels)."""
    m = np.asarray(mask, dtype=bool)
    ny, nx = m.shape
    padded = np.zeros((ny, nx + 2), dtype=np.int8)
    padded[:, 1:-1] = m
    d = np.diff(padded, axis=1)
    rows, s = np.nonzero(d == 1)
    _, e = np.nonzero(d == -1)
    if rows.size == 0:
        return np.zeros((0, 4), dtype=np.int64)
    order = np.lexsort((rows, e, s))          # by start, then end, then row
    s, e, rows = s[order], e[order], rows[order]
    new = np.ones(rows.size, dtype=bool)
    new[1:] = (s[1:] != s[:-1]) | (e[1:] != e[:-1]) | (rows[1:] != rows[:-1] + 1)
    first = np.flatnonzero(new)
    last = np.append(first[1:] - 1, rows.size - 1)
    return np.stack([s[first], rows[first], e[first], rows[last] + 1], axis=1).astype(np.int64)


def _cross(cx, cy, arm, width, layer):
    """A cross (one 12-vertex polygon) of total arm length ``arm`` and bar ``width`` centred at (cx, cy)."""
    import gdstk

    a, w = arm / 2, width / 2
    pts = [(w, w), (a, w), (a, -w), (w, -w), (w, -a), (-w, -a), (-w, -w), (-a, -w), (-a, w), (-w, w), (-w, a),
           (w, a)]
    return gdstk.Polygon([(cx + x, cy + y) for x, y in pts], layer=layer)


#: GDSII stores coordinates as signed 32-bit integers of the database unit
_GDS_MAX_INT = 2**31 - 1


def _check_database_grid(p_um: float, ny: int, nx: int, fmt: str) -> None:
    """Refuse a pixel pitch (µm) that the mask file cannot represent: finer than the database unit (1 nm: the
    pixels would collapse to zero-area polygons), or (GDSII) a layout whose outermost coordinate — the DOE, its
    alignment crosses and label — overflows the 32-bit integer coordinates."""
    db_um = _PRECISION / _UNIT  # database unit in µm
    if p_um < db_um:
        raise ValueError(f"the DOE pitch {p_um * 1e-3:g} mm is finer than the mask file's database unit "
                         f"({db_um * 1e3:g} nm): its pixels would be zero-area polygons; resample the DOE to a pitch "
                         f">= {db_um * 1e-3:g} mm")
    if fmt == "gds":
        side = max(nx, ny) * p_um
        arm = max(20.0, 0.02 * side)
        reach = side / 2 + 2 * arm + 3 * max(10.0, 0.015 * side) + 1.0  # crosses and label lines beyond the DOE
        if reach / db_um > _GDS_MAX_INT:
            raise ValueError(f"the {nx}×{ny}-pixel DOE at pitch {p_um * 1e-3:g} mm spans ±{reach * 1e-3:.4g} mm with its "
                             f"marks, beyond GDSII's 32-bit coordinates (±{_GDS_MAX_INT * db_um * 1e-3:.4g} mm at the "
                             f"{db_um * 1e3:g} nm database unit); use a finer pitch or write OASIS (.oas)")


def write_mask_file(path, masks, pitch: float, *, name: str = "DOE", label: str | None = None,
                    fmt: str | None = None) -> dict:
    """Write the masks as a GDSII (``.gds``) or OASIS (``.oas``) file (module docstring: layers, cells, units).

    Args:
        path: output file; the format follows ``fmt`` ("gds" / "oas") or the extension.
        masks: (k, ny, nx) bool, True = etched.
        pitch: pixel pitch (mm).
        name: design name (first line of the label).
        label: further label text (e.g. levels, λ0, material, depths, pitch).
    Returns ``{"file", "format", "rectangles": [per mask], "bytes"}``.
    """
    import gdstk

    m = _check_masks(masks)
    p = _check_pitch(pitch) * 1e3          # µm
    path = Path(path)
    fmt = _mask_format(path, fmt)
    k, ny, nx = m.shape
    _check_database_grid(p, ny, nx, fmt)
    lib = gdstk.Library(name=str(name)[:60] or "DOE", unit=_UNIT, precision=_PRECISION)
    doe, counts = _mask_cell(lib, m, p)
    w_doe, h_doe = nx * p, ny * p
    arm = max(20.0, 0.02 * max(w_doe, h_doe))
    align = _alignment_cell(lib, k, w_doe, h_doe, arm)
    lab = _label_cell(lib, name, label, w_doe, h_doe, off=arm)
    top = lib.new_cell("TOP")
    for c in (doe, align, lab):
        top.add(gdstk.Reference(c))
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "gds":
        lib.write_gds(str(path))
    else:
        lib.write_oas(str(path))
    return {"file": str(path), "format": MASK_FORMATS[fmt], "rectangles": counts, "bytes": path.stat().st_size}


def _mask_format(path: Path, fmt: str | None) -> str:
    """The mask file format key ("gds" / "oas"): ``fmt``, else the extension of ``path``; checked."""
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt not in MASK_FORMATS:
        raise ValueError(f"mask files are {' or '.join('.' + f for f in MASK_FORMATS)} "
                         f"({', '.join(MASK_FORMATS.values())}), got {str(path)!r}")
    return fmt


def _mask_cell(lib, m: np.ndarray, p: float):
    """The cell ``DOE`` of ``lib``: mask j's etched areas as rectangles on layer j + 1, the DOE centred at the
    origin (``p``: pixel pitch in µm). Returns ``(cell, rectangles per mask)``."""
    import gdstk

    k, ny, nx = m.shape
    x0, y0 = -nx / 2 * p, -ny / 2 * p      # lower-left corner of pixel [0, 0]; the DOE is centred at 0
    doe = lib.new_cell("DOE")
    counts = []
    for j in range(k):
        r = rectangles_from_mask(m[j]).astype(np.float64)
        counts.append(int(r.shape[0]))
        xa, ya, xb, yb = (x0 + r[:, 0] * p).tolist(), (y0 + r[:, 1] * p).tolist(), \
            (x0 + r[:, 2] * p).tolist(), (y0 + r[:, 3] * p).tolist()
        layer = j + 1
        doe.add(*[gdstk.rectangle((a, b), (c, d), layer=layer, datatype=0) for a, b, c, d in zip(xa, ya, xb, yb)])
    return doe, counts


def _alignment_cell(lib, k: int, w_doe: float, h_doe: float, arm: float):
    """The cell ``ALIGN`` of ``lib``: alignment crosses (arm length ``arm`` µm) in the four corners, outside the
    ``w_doe`` × ``h_doe`` µm DOE by one arm length, on every mask layer 1..k."""
    width = arm / 10
    align = lib.new_cell("ALIGN")
    off = arm
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (w_doe / 2 + off), sy * (h_doe / 2 + off)
            for j in range(k):
                align.add(_cross(cx, cy, arm, width, j + 1))
    return align


def _label_cell(lib, name, label: str | None, w_doe: float, h_doe: float, off: float):
    """The cell ``LABEL`` of ``lib`` (layer :data:`LABEL_LAYER`): ``name`` and ``label`` as polygon text below the
    ``w_doe`` × ``h_doe`` µm DOE (``off`` µm: the alignment crosses' offset) and as one text label above it."""
    import gdstk

    lab = lib.new_cell("LABEL")
    text = str(name) if label is None else f"{name}\n{label}"
    size = max(10.0, 0.015 * max(w_doe, h_doe))
    ty = -h_doe / 2 - 2 * off - size
    for i, line in enumerate(text.splitlines()):
        lab.add(*gdstk.text(line, size, (-w_doe / 2, ty - i * 1.5 * size), layer=LABEL_LAYER))
    lab.add(gdstk.Label(text.replace("\n", "; "), (-w_doe / 2, h_doe / 2 + 2 * off), layer=LABEL_LAYER))
    return lab


def read_mask_file(path, shape, pitch: float, masks: int | None = None) -> np.ndarray:
    """Read the masks back from a file of :func:`write_mask_file`: cell ``DOE`` rasterised at ``pitch`` (mm) on
    the ``shape = (ny, nx)`` grid centred at the origin -> (k, ny, nx) bool (k: ``masks`` or the highest mask
    layer found). Every polygon must be an axis-aligned rectangle on whole pixels; overlaps are errors."""
    import gdstk

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mask file {str(path)!r} not found")
    lib = gdstk.read_oas(str(path)) if path.suffix.lower() == ".oas" else gdstk.read_gds(str(path))
    cells = {c.name: c for c in lib.cells}
    if "DOE" not in cells:
        raise ValueError(f"{str(path)!r} has no cell 'DOE' (found: {', '.join(cells) or 'none'})")
    ny, nx = (int(s) for s in shape)
    p = _check_pitch(pitch) * 1e3
    x0, y0 = -nx / 2 * p, -ny / 2 * p
    polys = cells["DOE"].polygons
    layers = np.array([q.layer for q in polys], dtype=np.int64)
    k = int(masks) if masks is not None else (int(layers.max()) if layers.size else 0)
    out = np.zeros((k, ny, nx), dtype=bool)
    if not polys:
        return out
    boxes = np.array([q.bounding_box() for q in polys], dtype=np.float64).reshape(-1, 4)  # x0 y0 x1 y1
    areas = np.array([abs(q.area()) for q in polys])
    if not np.allclose(areas, (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]), rtol=1e-9, atol=1e-6):
        raise ValueError(f"{str(path)!r}: cell 'DOE' holds polygons that are not axis-aligned rectangles")
    ix = (boxes[:, [0, 2]] - x0) / p
    iy = (boxes[:, [1, 3]] - y0) / p
    ixr, iyr = np.rint(ix).astype(np.int64), np.rint(iy).astype(np.int64)
    tol = 2 * _PRECISION / _UNIT / p
    if np.abs(ix - ixr).max() > tol or np.abs(iy - iyr).max() > tol:
        raise ValueError(f"{str(path)!r}: rectangles do not lie on the {p:g} µm pixel grid of a {nx} × {ny} DOE")
    if (ixr.min() < 0 or iyr.min() < 0 or ixr.max() > nx or iyr.max() > ny or layers.min() < 1
            or layers.max() > k):
        raise ValueError(f"{str(path)!r}: rectangles or layers outside the {nx} × {ny} grid / {k} masks")
    for j in range(k):
        sel = layers == j + 1
        acc = np.zeros((ny + 1, nx + 1), dtype=np.int64)
        a, b, c, d = ixr[sel, 0], iyr[sel, 0], ixr[sel, 1], iyr[sel, 1]
        np.add.at(acc, (b, a), 1)
        np.add.at(acc, (b, c), -1)
        np.add.at(acc, (d, a), -1)
        np.add.at(acc, (d, c), 1)
        cover = acc.cumsum(0).cumsum(1)[:ny, :nx]
        if cover.max(initial=0) > 1:
            raise ValueError(f"{str(path)!r}: overlapping rectangles on layer {j + 1}")
        out[j] = cover > 0
    return out
