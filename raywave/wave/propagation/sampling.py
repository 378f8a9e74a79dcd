"""Sampling check: local fringe frequency of a sampled phase or field against the Nyquist frequency."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from raywave.wave.propagation._common import _TWO_PI, _UM_TO_MM, _pair, _xy


@dataclass(frozen=True)
class NyquistReport:
    """Result of :func:`nyquist_check`.

    ``max_ratio``: largest local fringe frequency / Nyquist frequency (per axis, |Δφ|/π between neighbours);
    ``index``: index (including batch dims) of the worst pixel; ``position``: its ``(x, y)`` in mm;
    ``ratio``: the per-pixel map ``(..., Ny, Nx)`` (0 where nothing is lit); ``limit``: the threshold of ``ok``.
    """

    max_ratio: float
    index: tuple[int, ...]
    position: tuple[float, float]
    ratio: torch.Tensor
    limit: float = 1.0

    @property
    def ok(self) -> bool:
        return self.max_ratio < self.limit

    def __str__(self) -> str:
        x, y = self.position
        return (
            f"local fringe frequency up to {self.max_ratio:.3g}× Nyquist at index {self.index} "
            f"(x = {x:.6g} mm, y = {y:.6g} mm)" + ("" if self.ok else ": grid too coarse")
        )


def nyquist_check(
    phase_or_field: torch.Tensor,
    pitch,
    wavelength: float | None = None,
    *,
    n: float = 1.0,
    carrier=(0.0, 0.0),
    origin=(0.0, 0.0),
    mask: torch.Tensor | None = None,
    threshold: float = 1e-6,
    limit: float = 1.0,
) -> NyquistReport:
    """Local fringe frequency of a sampled phase relative to the Nyquist frequency ``1/(2p)``.

    Args:
        phase_or_field: either a real **unwrapped** phase (rad), e.g. a DOE/lens phase profile, or a complex
            field (its neighbour phase steps ``angle(u[i+1]·conj(u[i]))`` are used; these are wrapped to
            ``(-π, π]`` so a complex field can only show aliasing as ratios approaching 1 — pass the unwrapped
            phase where available). Shape ``(..., Ny, Nx)``.
        pitch: sample spacing in mm (float or ``(px, py)``).
        wavelength: vacuum wavelength in µm; required only when ``carrier`` is non-zero.
        n: medium index (for the carrier).
        carrier: ``(α, β)`` direction cosines removed before the check (the envelope is what is sampled in
            :func:`propagate_window`).
        origin: ``(x0, y0)`` of pixel (0, 0) in mm, used for ``position``.
        mask: optional boolean ``(Ny, Nx)`` (broadcastable) of lit pixels; a neighbour pair counts only if
            both pixels are lit. For a complex field, pixels with ``|u| ≤ threshold·max|u|`` are unlit too.
        limit: ``ok`` is ``max_ratio < limit``.

    Returns:
        :class:`NyquistReport`. The ratio per axis is ``|Δφ|/π`` (= local frequency / (1/(2p)));
        a pixel's value is the largest over its four neighbour steps.
    """
    t = phase_or_field.detach()
    if t.ndim < 2:
        raise ValueError("expected shape (..., Ny, Nx)")
    px, py = _pair(pitch, "pitch")
    ax, ay = _xy(carrier, "carrier")
    x0, y0 = _xy(origin, "origin")
    cx, cy = _carrier_steps((ax, ay), (px, py), wavelength, n)
    lit, stepx, stepy = _phase_steps(t, cx, cy, threshold)
    if mask is not None:
        lit = lit & mask.to(device=t.device, dtype=torch.bool)
    ratio = _ratio_map(lit, stepx, stepy)
    return _report(ratio, (x0, y0), (px, py), limit)


def _carrier_steps(carrier, pitch, wavelength: float | None, n: float) -> tuple[float, float]:
    """The carrier's phase steps ``(cx, cy)`` (rad per pixel) of direction cosines ``carrier`` ``(α, β)`` on the
    pitch ``(px, py)`` (mm) at the vacuum wavelength (µm) in a medium of index ``n``."""
    ax, ay = carrier
    px, py = pitch
    if (ax or ay) and wavelength is None:
        raise ValueError("a non-zero carrier needs the wavelength")
    kc = _TWO_PI * n / (wavelength * _UM_TO_MM) if wavelength is not None else 0.0
    return kc * ax * px, kc * ay * py  # carrier phase step per pixel


def _phase_steps(t: torch.Tensor, cx: float, cy: float, threshold: float):
    """``(lit, stepx, stepy)`` of a detached phase (rad) or field ``t`` ``(..., Ny, Nx)``: the lit pixels (bool
    ``(..., Ny, Nx)``, all of a phase) and the neighbour phase steps less the carrier's (rad, ``(..., Ny, Nx−1)``
    and ``(..., Ny−1, Nx)``; wrapped to ``(-π, π]`` for a field)."""
    if t.is_complex():
        t = t.to(torch.complex128)
        amp = t.abs()
        lit = amp > threshold * amp.amax(dim=(-2, -1), keepdim=True).clamp_min(1e-300)
        stepx = torch.angle(t[..., :, 1:] * t[..., :, :-1].conj() * complex(math.cos(cx), -math.sin(cx)))
        stepy = torch.angle(t[..., 1:, :] * t[..., :-1, :].conj() * complex(math.cos(cy), -math.sin(cy)))
    else:
        t = t.to(torch.float64)
        lit = torch.ones_like(t, dtype=torch.bool)
        stepx = t[..., :, 1:] - t[..., :, :-1] - cx
        stepy = t[..., 1:, :] - t[..., :-1, :] - cy
    return lit, stepx, stepy


def _ratio_map(lit: torch.Tensor, stepx: torch.Tensor, stepy: torch.Tensor) -> torch.Tensor:
    """The per-pixel ratio ``(..., Ny, Nx)`` to Nyquist, ``|Δφ|/π``: the largest over a pixel's four neighbour
    steps (rad, see :func:`_phase_steps`) whose two pixels are both ``lit``; 0 where none is."""
    okx = lit[..., :, 1:] & lit[..., :, :-1]
    oky = lit[..., 1:, :] & lit[..., :-1, :]
    rx = torch.where(okx, stepx.abs() / math.pi, torch.zeros_like(stepx))
    ry = torch.where(oky, stepy.abs() / math.pi, torch.zeros_like(stepy))
    pad = torch.nn.functional.pad
    return torch.maximum(
        torch.maximum(pad(rx, (1, 0)), pad(rx, (0, 1))),
        torch.maximum(pad(ry, (0, 0, 1, 0)), pad(ry, (0, 0, 0, 1))),
    )


def _report(ratio: torch.Tensor, origin, pitch, limit: float) -> NyquistReport:
    """The :class:`NyquistReport` of the ratio map ``(..., Ny, Nx)``: its worst pixel (the first of equal ones)
    and that pixel's position (mm) on the grid of pixel (0, 0) at ``origin`` ``(x0, y0)`` (mm), pitch ``(px, py)``
    (mm)."""
    (x0, y0), (px, py) = origin, pitch
    flat = int(torch.argmax(ratio.reshape(-1)))
    index = tuple(int(i) for i in torch.unravel_index(torch.tensor(flat), ratio.shape))
    max_ratio = float(ratio.reshape(-1)[flat])
    position = (x0 + index[-1] * px, y0 + index[-2] * py)
    return NyquistReport(max_ratio, index, position, ratio, float(limit))
