"""Efficiencies of one period of a perturbed 1-D grating: exact (closed-form Fourier coefficients of the
piecewise-constant period) and by an FFT of the sample-averaged transmittance (:mod:`raywave.doe.tolerance`,
"Efficiency")."""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.doe.base import check_levels
from raywave.doe.fabrication import masks_from_levels
from raywave.doe.tolerance.errors import FabricationErrors, _count, _orders
from raywave.doe.tolerance.profile import transmittance

_TWO_PI = 2.0 * math.pi


def blazed_grating_levels(levels: int, period_px: int | None = None) -> np.ndarray:
    """One period of a blazed L-level staircase, one level per pixel: ``(period_px,)`` int64, pixel i at level
    ``floor(i·L/period_px)`` (default ``period_px = L``; it must be a multiple of L)."""
    L = check_levels(levels)
    P = L if period_px is None else _count(period_px, "the grating period (pixels)")
    if P % L:
        raise ValueError(f"the grating period ({P} pixels) must be a multiple of the number of levels ({L})")
    return (np.arange(P) * L) // P


def _grating_masks(level_period, levels: int) -> np.ndarray:
    lv = np.asarray(level_period)
    if lv.ndim != 1 or lv.size < 1:
        raise ValueError(f"a grating period is a 1-D array of levels, got shape {lv.shape}")
    return masks_from_levels(lv[None, :], levels)[:, 0, :]


def grating_efficiency(level_period, levels: int, errors: FabricationErrors | None = None, alpha: float = 1.0,
                       orders=(1,)) -> np.ndarray:
    """η_m of one period of a perturbed 1-D grating (periodic; only the x-shifts matter), **exactly**: the
    period's transmittance is piecewise constant between the (shifted) mask edges, so
    ``c_m = (1/P) Σ_s exp(iφ_s) ∫_s exp(−2πimx/P) dx`` in closed form.

    Args:
        level_period: (P,) levels, one per pixel (e.g. :func:`blazed_grating_levels`).
        levels: L = 2^k.
        errors: :class:`FabricationErrors` (default none).
        alpha: detuning φ(λ)/φ(λ0) (:func:`raywave.doe.detuning`; 1 at λ0).
        orders: diffraction orders m.
    Returns (len(orders),) float64 efficiencies.
    """
    L = int(levels)
    masks = _grating_masks(level_period, L)
    k, P = masks.shape
    err = FabricationErrors.nominal(k) if errors is None else errors
    if err.masks != k:
        raise ValueError(f"{k} masks need {k} depth errors and shifts, got {err.masks}")
    dx = err.shift[:, 0]
    # breakpoints: every pixel edge of every shifted mask, folded into [0, P)
    edges = np.concatenate([np.mod(np.arange(P) + d, P) for d in dx] + [np.array([0.0, float(P)])])
    edges = np.unique(edges)
    a, b = edges[:-1], edges[1:]
    keep = b - a > 1e-12
    a, b = a[keep], b[keep]
    mid = 0.5 * (a + b)
    h = np.zeros_like(mid)
    for j in range(k):
        src = np.floor(np.mod(mid - dx[j], P)).astype(np.int64) % P
        h += 2.0 ** (k - 1 - j) * (1.0 + err.depth[j]) * (1.0 - masks[j, src])
    t = np.exp(1j * _TWO_PI * float(alpha) * h / L)
    out = []
    for m in _orders(orders):
        w = b - a
        c = np.sum(t * np.exp(-1j * _TWO_PI * m * mid / P) * w * np.sinc(m * w / P)) / P
        out.append(float(abs(c) ** 2))
    return np.array(out)


def grating_efficiency_fft(level_period, levels: int, errors: FabricationErrors | None = None, alpha: float = 1.0,
                           orders=(1,), oversample: int = 16) -> np.ndarray:
    """η_m of one period of a perturbed grating by an FFT of its sample-averaged transmittance
    (:func:`transmittance`, periodic) on the ``oversample``-times finer grid: ``|FFT_m/N|² sinc²(m/N)`` (N samples;
    the sinc integrates a constant sample exactly). Exact when every shift is a whole number of samples; otherwise
    the samples crossed by an edge are not constant, an error of order m/N there."""
    L = int(levels)
    masks = torch.as_tensor(_grating_masks(level_period, L))[:, None, :]
    k = masks.shape[0]
    err = FabricationErrors.nominal(k) if errors is None else errors
    t = transmittance(masks, err, L, alpha, oversample, (0, 0, 1, masks.shape[-1] * int(oversample)),
                      periodic=True)[0].numpy()
    N = t.size
    c = np.fft.fft(t) / N
    return np.array([float(abs(c[m % N]) ** 2 * np.sinc(m / N) ** 2) for m in _orders(orders)])
