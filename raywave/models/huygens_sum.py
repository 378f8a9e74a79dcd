"""The Huygens–Fresnel sum of :mod:`raywave.models.exit_pupil` on a tensor grid of sensor points, as matrix products.

    U(x_a, y_b) = Σ_j w_j exp(i k₀ (opl_j + n (r_abj − R))) / r_abj,   r_abj = |P_ab − Q_j|,  P_ab = (x_a, y_b, 0)

(Q_j on the reference sphere of radius R about the sensor point C = 0.) Evaluated point by point this costs a
square root, a sine and a cosine per (sensor point, sphere point) pair (~40 ns on one core). On a tile of sensor
points about its centre P₀ (a, b the offsets), the distance splits exactly into

    r(a, b) = r₀ + [r(a, 0) − r₀] + [r(0, b) − r₀] + h(a, b),   h(a, b) = −a b v_x v_y / r₀³ + O(δ³ / r₀²)

(v = Q − P₀, r₀ = |v|): the first three terms are separable, so ``exp(i k₀ n r)`` is a product of a row factor and a
column factor per sphere point, and the tile's sum is a matrix product (~0.4 ns per pair). The mixed term's
leading part ``exp(i k₀ n h₁₁ a b)`` is expanded in powers of ``a b`` (each one separable too: one product per
power), and the tiles are split until the rest of ``h`` (checked exactly at the tile's corners, for every sphere
point) is below :data:`PHASE_TOL` radians. The amplitude 1/r factors the same way (its mixed part, ~a b / r₀², is
below 1e-8 relative for tiles of tens of µm at R of millimetres). Compared with the point-by-point sum:
tests/test_exit_pupil.py.
"""

from __future__ import annotations

import math

import torch

#: the largest phase (radians) of the distance's mixed terms beyond the expanded one (a·b) left out on a tile
PHASE_TOL = 1e-5
#: the largest relative remainder of the series of exp(i k₀ n h₁₁ a b) in powers of a·b
SERIES_TOL = 1e-12
#: sphere points per block of the products (the row and column factors are (tile side × block) complex128)
_CHUNK = 1 << 15


def _dist_step(v_comp: torch.Tensor, r0: torch.Tensor, s) -> torch.Tensor:
    """r(s) − r₀ (…, N) for the point moved by ``s`` (a float or (…, 1)) along one axis, ``v_comp`` (N,) the
    component of v = Q − P₀ along it: r(s)² = r₀² − 2 s v + s², formed as (s² − 2 s v) / (r(s) + r₀) (no cancellation)."""
    num = s * s - 2.0 * s * v_comp
    return num / (torch.sqrt(r0 * r0 + num) + r0)


def _phasor(mag: torch.Tensor, phase: torch.Tensor) -> torch.Tensor:
    """mag·exp(i phase), complex128 (torch.polar is several times slower on the CPU)."""
    return torch.complex(mag * torch.cos(phase), mag * torch.sin(phase))


def _mixed_residual(q: torch.Tensor, r0: torch.Tensor, h11: torch.Tensor, ax: float, by: float, x0: float,
                    y0: float) -> float:
    """Largest |h(a, b) − h₁₁ a b| (mm) over the four corners (±ax, ±by) of a tile centred on (x0, y0) and every
    sphere point ``q`` (N, 3)."""
    vx, vy = q[:, 0] - x0, q[:, 1] - y0
    worst = 0.0
    for a in (-ax, ax):
        for b in (-by, by):
            ra, rb = _dist_step(vx, r0, a), _dist_step(vy, r0, b)
            num = a * a + b * b - 2.0 * (a * vx + b * vy)
            rab = num / (torch.sqrt(r0 * r0 + num) + r0)
            worst = max(worst, float((rab - ra - rb - h11 * (a * b)).abs().max()))
    return worst


def huygens_sum_grid(xs: torch.Tensor, ys: torch.Tensor, q: torch.Tensor, opl: torch.Tensor, amp: torch.Tensor,
                     radius: float, k0: float, n: float) -> torch.Tensor:
    """The Huygens sum (module docstring) at the sensor points (x_a, y_b): ``xs`` (Mx,), ``ys`` (My,) mm relative to
    the sphere's centre C (sensor plane through C), sphere points ``q`` (N, 3) mm relative to C, their OPL ``opl``
    (N,) mm and weights ``amp`` (N,); ``radius`` R mm, ``k0`` = 2π/λ (1/mm), ``n`` the image index. Returns
    (My, Mx) complex128, equal to the point-by-point sum to ~:data:`PHASE_TOL` relative."""
    out = torch.empty(ys.numel(), xs.numel(), dtype=torch.complex128, device=q.device)
    _tile(out, xs, ys, 0, xs.numel(), 0, ys.numel(), q, opl, amp, radius, k0, n)
    return out


def _halves(i0: int, i1: int):
    """The index range [i0, i1) in two halves, or (odd length) two halves about the middle index on its own: a
    partition that mirrors onto itself, so that a PSF symmetric in x, y or x ↔ y stays so to rounding."""
    m = (i1 - i0) // 2
    if i1 - i0 <= 1:
        return ((i0, i1),)
    if (i1 - i0) % 2 == 0:
        return (i0, i0 + m), (i0 + m, i1)
    return (i0, i0 + m), (i0 + m, i0 + m + 1), (i0 + m + 1, i1)


def _tile(out, xs, ys, i0: int, i1: int, j0: int, j1: int, q, opl, amp, radius: float, k0: float, n: float) -> None:
    """Fill ``out[j0:j1, i0:i1]`` (the tile of sensor points xs[i0:i1] × ys[j0:j1]), split in four while the mixed
    terms beyond a·b exceed :data:`PHASE_TOL`."""
    x, y = xs[i0:i1], ys[j0:j1]
    x0, y0 = 0.5 * float(x[0] + x[-1]), 0.5 * float(y[0] + y[-1])
    ax, by = 0.5 * float(x[-1] - x[0]), 0.5 * float(y[-1] - y[0])
    vx, vy = q[:, 0] - x0, q[:, 1] - y0
    # r0² − R² = |q|² − R² − 2 P0·q + |P0|² (|q| = R up to rounding): r0 − R without cancellation
    d2 = (q * q).sum(-1) - radius * radius - 2.0 * (x0 * q[:, 0] + y0 * q[:, 1]) + x0 * x0 + y0 * y0
    r0 = torch.sqrt(radius * radius + d2)
    h11 = -vx * vy / r0 ** 3
    if (i1 - i0 > 1 or j1 - j0 > 1) and k0 * n * _mixed_residual(q, r0, h11, ax, by, x0, y0) > PHASE_TOL:
        for a0, a1 in _halves(i0, i1):
            for b0, b1 in _halves(j0, j1):
                _tile(out, xs, ys, a0, a1, b0, b1, q, opl, amp, radius, k0, n)
        return
    a, b = (x - x0)[:, None], (y - y0)[:, None]
    mu = k0 * n * float(h11.abs().max()) * ax * by  # the largest phase of the expanded mixed term
    terms, t = 1, 1.0
    while t > SERIES_TOL:  # μ^K / K! ≤ SERIES_TOL
        t *= mu / terms
        terms += 1
    acc = torch.zeros(y.numel(), x.numel(), dtype=torch.complex128, device=q.device)
    ab = [(a.reshape(1, -1) ** k, b.reshape(-1, 1) ** k) for k in range(terms)]
    for c0 in range(0, q.shape[0], _CHUNK):
        s = slice(c0, c0 + _CHUNK)
        r0c = r0[s]
        w = _phasor(amp[s] / r0c, k0 * opl[s] + k0 * n * (d2[s] / (r0c + radius)))
        ra, rb = _dist_step(vx[s], r0c, a), _dist_step(vy[s], r0c, b)  # (tx, N), (ty, N)
        ex = _phasor(r0c / (r0c + ra), (k0 * n) * ra)
        ey = _phasor(r0c / (r0c + rb), (k0 * n) * rb)
        c = (1j * k0 * n) * h11[s]
        ck = torch.ones_like(c, dtype=torch.complex128)
        for k in range(terms):
            acc += (ey * (w * ck)) @ ex.T * ab[k][1] * ab[k][0]
            ck = ck * c / (k + 1)
    out[j0:j1, i0:i1] = acc
