"""Scalar diffraction efficiency of quantised (staircase) blazed gratings, at and away from the design wavelength.

An L-level staircase has L equal steps per period with phases ``2πk/L`` at the design wavelength λ0. A height
map in a material scales every phase at λ by the *detuning* ``α = φ(λ)/φ(λ0) = λ0 (n(λ) − n_m) / (λ (n(λ0) −
n_m))``, so step k has phase ``2πkα/L``. The Fourier coefficient of order m of one period is
``c_m = sinc(m/L) e^{−iπm/L} · (1/L) Σ_k e^{i2πk(α−m)/L}``, which gives

    η_m = sinc²(m/L) · [sin(π(α − m)) / (L sin(π(α − m)/L))]²      (sinc x = sin πx / πx),

``sinc²(1/L)`` for m = 1 at α = 1 (40.5 % per ±1 order of a binary grating, 98.7 % for 16 levels).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["detuning", "period_efficiency", "staircase_efficiency"]


def detuning(material, wavelength: float, wavelength0: float, n_medium: float = 1.0) -> float:
    """α = φ(λ)/φ(λ0) of a height map in ``material`` (a glass name or Material)."""
    import torch

    from raywave.materials import get_material

    m = get_material(material)
    n = lambda w: float(m.n(torch.tensor(float(w), dtype=torch.float64)).detach())  # noqa: E731
    return wavelength0 * (n(wavelength) - n_medium) / (wavelength * (n(wavelength0) - n_medium))


def staircase_efficiency(m: int, levels: int, alpha: float = 1.0) -> float:
    """η_m of an L-level blazed staircase at detuning ``alpha`` (see the module docstring)."""
    L = int(levels)
    d = alpha - m
    s = math.sin(math.pi * d / L)
    g = 1.0 if abs(s) < 1e-15 else (math.sin(math.pi * d) / (L * s)) ** 2
    return float(np.sinc(m / L) ** 2 * g)


def period_efficiency(phase_period, m: int) -> float:
    """|c_m|² of one sampled period of a phase grating (rad, 1-D, equal samples): the DFT coefficient of
    ``exp(iφ)`` for order m (a phase increasing with x puts light into m > 0)."""
    u = np.exp(1j * np.asarray(phase_period, dtype=np.float64))
    c = np.fft.fft(u) / u.size
    return float(abs(c[m % u.size]) ** 2)
