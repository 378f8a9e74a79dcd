"""Efficiency of a general perturbed DOE relative to its design: the design maps (unwrapped phase and its
gradients) and the exact overlap with the design's order-m wave (:mod:`raywave.doe.tolerance`, "Efficiency")."""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.doe.base import DOE
from raywave.doe.tolerance.errors import FabricationErrors, _orders
from raywave.doe.tolerance.profile import PerturbedDOE, profile_parts

_TWO_PI = 2.0 * math.pi
_TILE_SAMPLES = 2_000_000   # simulation samples per tile of the efficiency overlap (bounds memory)


def _design_phase(doe: DOE, wavelength0: float) -> torch.Tensor:
    """The unwrapped, unquantised design phase (rad) at λ0 of every DOE pixel, (ny, nx) float64."""
    with torch.no_grad():
        p = doe.design_phase_pixels(slice(None), slice(None)) * doe.phase_scale
        if wavelength0 != doe.design_wavelength:
            r = doe.dispersion_ratio(wavelength0)
            if r is not None:
                p = p * r
    return p.detach().to(torch.float64)


def _wrapped_gradient(p: torch.Tensor, dim: int) -> torch.Tensor:
    """Phase change per pixel along ``dim`` (rad), from wrapped central differences (one-sided at the edges)."""
    n = p.shape[dim]
    if n < 2:
        return torch.zeros_like(p)
    d = torch.diff(p, dim=dim)
    d = torch.atan2(torch.sin(d), torch.cos(d))
    first = d.narrow(dim, 0, 1)
    last = d.narrow(dim, n - 2, 1)
    if n == 2:
        return torch.cat([first, last], dim=dim)
    mid = 0.5 * (d.narrow(dim, 0, n - 2) + d.narrow(dim, 1, n - 2))
    return torch.cat([first, mid, last], dim=dim)


def _sample_maps(a: torch.Tensor, q: int, rows: slice) -> torch.Tensor:
    """A per-pixel map's rows ``rows`` repeated over q × q samples."""
    return a[rows].repeat_interleave(q, 0).repeat_interleave(q, 1)


def _sample_offsets(ny_px: int, nx_px: int, q: int, device):
    """Offsets (pixels) of every sample centre from its pixel centre: ``(ox (1, nx·q), oy (ny·q, 1))``."""
    off = (torch.arange(q, dtype=torch.float64, device=device) + 0.5) / q - 0.5
    return off.repeat(nx_px)[None, :], off.repeat(ny_px)[:, None]


class ToleranceWarning(UserWarning):
    """A tolerance analysis whose input makes a result unreliable (e.g. an undersampled design phase)."""


def design_maps(doe: DOE, wavelength0: float | None = None):
    """``(φ_u, gx, gy)``: the DOE's unwrapped design phase at λ0 (rad) on its pixels and its gradients (rad per
    pixel, from wrapped central differences: valid while the phase changes by < π per pixel; a
    :class:`ToleranceWarning` says when it comes close)."""
    import warnings

    lam0 = doe.design_wavelength if wavelength0 is None else float(wavelength0)
    p = _design_phase(doe, lam0)
    gx, gy = _wrapped_gradient(p, 1), _wrapped_gradient(p, 0)
    g = max(float(gx.abs().max()), float(gy.abs().max())) if p.numel() else 0.0
    if g > 0.9 * math.pi:
        warnings.warn(f"the DOE's design phase changes by up to {g:.3g} rad per pixel (Nyquist: π): the DOE is "
                      "(nearly) undersampled, so its local gradients and the design-order efficiencies are "
                      "unreliable", ToleranceWarning, stacklevel=2)
    return p, gx, gy


def doe_efficiency(pdoe: PerturbedDOE, wavelengths, orders=(1,), oversample: int = 1, design=None,
                   nominal: PerturbedDOE | None = None):
    """Efficiency of a perturbed DOE relative to its design, η_m (module docstring), and ``relative``, its overlap
    with the nominal fabricated element, computed in tiles of DOE rows.

    Exact for any shifts and a design phase linear inside each DOE pixel: the perturbed transmittance is constant
    on the sub-rectangles of :func:`profile_parts`, and the design wave's integral over each is
    ``area · exp(i m φ_u(centre)) · sinc(m gx du/2πq) · sinc(m gy dv/2πq)``. ``oversample`` (samples per pixel)
    only refines the aperture's edge (a circle); 1 suffices for a square aperture.

    Args:
        pdoe: the perturbed element (:class:`PerturbedDOE`).
        wavelengths: µm, scalar or list.
        orders: design orders m (the wave ``exp(i m φ_u)``).
        design: ``(φ_u, gx, gy)`` of :func:`design_maps` for the DOE that ``pdoe`` fabricates (required).
        nominal: the nominal element (default ``pdoe`` without errors), for ``relative``.
    Returns ``(eta (W, M), relative (W,))`` numpy float64.
    """
    wls = [float(w) for w in np.atleast_1d(np.asarray(wavelengths, dtype=np.float64))]
    ords = _orders(orders)
    q = int(oversample)
    if q < 1:
        raise ValueError(f"oversample must be an integer >= 1, got {oversample!r}")
    if design is None:
        raise ValueError("doe_efficiency needs the design maps (φ_u, gx, gy) of design_maps(doe)")
    phi_u, gx, gy = (torch.as_tensor(v, dtype=torch.float64, device=pdoe.device) for v in design)
    if tuple(phi_u.shape) != tuple(pdoe.shape):
        raise ValueError(f"the design maps ({tuple(phi_u.shape)}) and the DOE ({pdoe.shape}) differ in shape")
    nom = pdoe.with_errors(FabricationErrors.nominal(pdoe.errors.masks)) if nominal is None else nominal
    ny, nx = pdoe.shape
    dev = pdoe.device
    rows_per_tile = max(1, _TILE_SAMPLES // max(1, nx * q * q))
    cs = [_TWO_PI * pdoe.alpha(w) / pdoe.L for w in wls]
    acc = torch.zeros((len(wls), len(ords)), dtype=torch.complex128, device=dev)
    acc_rel = torch.zeros(len(wls), dtype=torch.complex128, device=dev)
    wsum = torch.zeros((), dtype=torch.float64, device=dev)
    for r0 in range(0, ny, rows_per_tile):
        rows = slice(r0, min(ny, r0 + rows_per_tile))
        wsum = wsum + _overlap_tile(pdoe, nom, (phi_u, gx, gy), rows, q, cs, ords, acc, acc_rel)
    a2 = float(wsum) ** 2
    eta = (acc.abs() ** 2 / a2).cpu().numpy()
    rel = (acc_rel.abs() ** 2 / a2).cpu().numpy()
    return eta, rel


def _overlap_tile(pdoe: PerturbedDOE, nom: PerturbedDOE, design, rows: slice, q: int, cs: list, ords: list,
                  acc: torch.Tensor, acc_rel: torch.Tensor) -> torch.Tensor:
    """Add the DOE rows ``rows`` (one tile) to the overlaps of :func:`doe_efficiency`, in place.

    Args:
        pdoe, nom: the perturbed and the nominal element; design: ``(φ_u, gx, gy)``, (ny, nx) float64 on the
            element's device (rad, rad per pixel).
        q: samples per DOE pixel; cs: per wavelength ``2π α(λ) / L`` (rad per level unit); ords: the orders m.
        acc: (W, M) complex128 overlaps with the design waves; acc_rel: (W,) complex128 overlaps with ``nom``.
    Returns the tile's aperture weight (a 0-d float64 tensor, in samples).
    """
    phi_u, gx, gy = design
    r0, r1 = rows.start, rows.stop
    nx = pdoe.shape[1]
    win = (r0 * q, 0, (r1 - r0) * q, nx * q)
    w = pdoe.coverage(win, q, device=pdoe.device)
    h0 = nom.height_levels(win, q)
    p, ax, ay = _sample_maps(phi_u, q, rows), _sample_maps(gx, q, rows), _sample_maps(gy, q, rows)
    ox, oy = _sample_offsets(r1 - r0, nx, q, pdoe.device)
    p = p + ax * ox + ay * oy                     # φ_u at the sample centres
    t0c = [torch.polar(torch.ones_like(h0), -h0 * c).reshape(-1) for c in cs]   # conj of the nominal element
    for area, (cu, cv), (du, dv), h in profile_parts(pdoe.masks, pdoe.errors, q, win, pdoe.periodic):
        pc = p + (ax * cu + ay * cv) / q          # ... at the sub-rectangle's centre
        ds = [torch.polar(torch.sinc(m * ax * du / (_TWO_PI * q)) * torch.sinc(m * ay * dv / (_TWO_PI * q)),
                          -m * pc).reshape(-1) for m in ords]
        wa = w * area
        for i, c in enumerate(cs):
            t = torch.polar(wa, h * c).reshape(-1)
            for jm, d in enumerate(ds):
                acc[i, jm] += torch.dot(t, d)
            acc_rel[i] += torch.dot(t, t0c[i])
    return w.sum()
