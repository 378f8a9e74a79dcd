"""Sampling patterns in the normalised pupil (the unit disk, or the unit square).

Each function returns ``(px, py)``: float64 tensors of shape (N,) with px² + py² <= 1 (disk patterns).

**The rim rule** (one for the whole engine): a sample on the pupil's rim (radius within :data:`RIM_TOL` of 1) is
aimed a hair inside it, at radius :data:`RIM_INSET` (:func:`inset_rim`). :func:`sample` applies it to every named
pattern, and the analyses that build their own samples (fans, MTF and OPD grids, the ray-wave footprint) apply it
too; explicit ``(px, py)`` given to :func:`raywave.lens.sources.point_source_rays` are traced as given (the stop
edge's image needs the exact rim). A ray aimed exactly at the stop's edge passes or is stopped by the last bit of
its aim's rounding, which depends on what else is traced in the same batch; inset by 1e-9 of the radius it always
passes, so the rim ring of a spot diagram, a fan or an MTF counts whatever the batch.
"""

from __future__ import annotations

import math

import torch

#: the radius (relative to the stop's) at which a rim sample is aimed: a hair inside the edge (module docstring)
RIM_INSET = 1.0 - 1e-9
#: samples whose radius is within this of 1 are rim samples (beyond it, outside the rim: left as given)
RIM_TOL = 1e-6


def inset_rim(px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rim rule: normalised pupil samples ``px, py`` (N,) with their rim samples (radius in
    (``RIM_INSET``, 1 + ``RIM_TOL``]) moved radially to radius ``RIM_INSET``; every other sample unchanged (bit for
    bit, so samples already inset stay as they are). Returns new tensors of the same shape and dtype."""
    r = torch.sqrt(px * px + py * py)
    rim = (r > RIM_INSET * (1.0 + 1e-12)) & (r <= 1.0 + RIM_TOL)
    if not bool(rim.any()):
        return px, py
    scale = torch.where(rim, RIM_INSET / torch.where(rim, r, torch.ones_like(r)), torch.ones_like(r))
    return torch.where(rim, px * scale, px), torch.where(rim, py * scale, py)


def rim_and_grid(n_rim: int, n_grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised pupil points (float64, shape (n_rim + K,)): ``n_rim`` points evenly round the rim, then the K points
    of an ``n_grid`` × ``n_grid`` square grid on [-1, 1]² inside the unit circle; all scaled by :data:`RIM_INSET`
    so that the rim rays pass the stop. A probe of a beam's extent (footprints)."""
    t = torch.linspace(0, 2 * math.pi, n_rim + 1, dtype=torch.float64)[:-1]
    g = torch.linspace(-1, 1, n_grid, dtype=torch.float64)
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    inside = gx**2 + gy**2 <= 1
    return torch.cat([torch.cos(t), gx[inside]]) * RIM_INSET, torch.cat([torch.sin(t), gy[inside]]) * RIM_INSET


def grid(n: int, shape: str = "circle", dtype=torch.float64, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """An n×n square grid over [-1, 1]² (pixel centres), keeping the points inside the unit circle
    (``shape="circle"``) or all of them (``shape="square"``)."""
    if n < 1:
        raise ValueError(f"pupil grid needs n >= 1, got {n}")
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) / n * 2 - 1
    py, px = torch.meshgrid(c, c, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    if shape == "circle":
        keep = px * px + py * py <= 1.0
        px, py = px[keep], py[keep]
    elif shape != "square":
        raise ValueError(f"pupil grid shape must be 'circle' or 'square', got {shape!r}")
    return px, py


def hexapolar(rings: int, dtype=torch.float64, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """The centre plus ``rings`` rings of 6, 12, 18, ... points at radii k/rings (Zemax hexapolar)."""
    xs, ys = [0.0], [0.0]
    for k in range(1, rings + 1):
        r = k / rings
        for j in range(6 * k):
            a = 2 * math.pi * j / (6 * k)
            xs.append(r * math.cos(a))
            ys.append(r * math.sin(a))
    return torch.tensor(xs, dtype=dtype, device=device), torch.tensor(ys, dtype=dtype, device=device)


def random(n: int, generator: torch.Generator | None = None, dtype=torch.float64, device=None):
    """``n`` points uniform in the unit disk. Pass a seeded ``generator`` for replayable samples."""
    u = torch.rand(n, generator=generator, dtype=dtype, device=device)
    a = torch.rand(n, generator=generator, dtype=dtype, device=device) * (2 * math.pi)
    r = torch.sqrt(u)
    return r * torch.cos(a), r * torch.sin(a)


def fans(n: int, dtype=torch.float64, device=None):
    """Tangential (y) fan and sagittal (x) fan of ``n`` points each across [-1, 1] (for layouts)."""
    t = torch.linspace(-1, 1, n, dtype=dtype, device=device)
    z = torch.zeros_like(t)
    return (z, t), (t, z)


def sample(pattern: str = "grid", n: int = 21, generator=None, dtype=torch.float64, device=None):
    """Dispatch by name: 'grid' (n per side), 'square', 'hexapolar' (n rings), 'random' (n points); rim samples inset
    by the rim rule (:func:`inset_rim`)."""
    if pattern == "grid":
        return inset_rim(*grid(n, "circle", dtype, device))
    if pattern == "square":
        return inset_rim(*grid(n, "square", dtype, device))
    if pattern == "hexapolar":
        return inset_rim(*hexapolar(n, dtype, device))
    if pattern == "random":
        return inset_rim(*random(n, generator, dtype, device))
    raise ValueError(f"unknown pupil pattern {pattern!r}: use 'grid', 'square', 'hexapolar' or 'random'")
