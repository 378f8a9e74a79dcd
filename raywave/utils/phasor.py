"""``abs·exp(i·angle)`` as :func:`torch.polar`, faster on CPU, with the same values with and without autograd."""

from __future__ import annotations

import torch

__all__ = ["polar", "unit_phasor"]


def _polar_values(abs: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:  # noqa: A002
    """``abs·cos(angle) + i·abs·sin(angle)``, the vectorised ``cos``/``sin`` written into the output's real and
    imaginary parts in place (no autograd)."""
    dtype = torch.promote_types(abs.dtype, angle.dtype)
    shape = angle.shape if abs.shape == angle.shape or abs.ndim == 0 else torch.broadcast_shapes(abs.shape, angle.shape)
    out = torch.empty(shape, dtype=torch.complex128 if dtype == torch.float64 else torch.complex64, device=angle.device)
    parts = torch.view_as_real(out)
    torch.mul(torch.cos(angle), abs, out=parts[..., 0])
    torch.mul(torch.sin(angle), abs, out=parts[..., 1])
    return out


class _Polar(torch.autograd.Function):
    """:func:`_polar_values` with its derivatives: ``∂z/∂abs = e^{iθ}``, ``∂z/∂θ = i·z`` (real inputs, complex output:
    the gradient of a real input is ``Re(conj(∂z/∂x)·g)``)."""

    @staticmethod
    def forward(ctx, abs, angle):  # noqa: A002
        ctx.save_for_backward(abs, angle)
        return _polar_values(abs, angle)

    @staticmethod
    def backward(ctx, g):
        abs, angle = ctx.saved_tensors  # noqa: A001
        unit = _polar_values(torch.ones((), dtype=angle.dtype, device=angle.device), angle)
        grad_abs = grad_angle = None
        if ctx.needs_input_grad[0]:
            grad_abs = (unit.conj() * g).real.sum_to_size(abs.shape)
        if ctx.needs_input_grad[1]:
            grad_angle = ((unit * abs).conj() * g).imag.sum_to_size(angle.shape)
        return grad_abs, grad_angle


def polar(abs: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:  # noqa: A002  (torch.polar's argument names)
    """:func:`torch.polar` (same broadcasting, dtype, device and derivatives; complex128 from float64):
    ``abs·cos(angle) + i·abs·sin(angle)``, ~2.5× faster than ``torch.polar`` on CPU for phases below ~1e4 rad
    (740² float64: 2.5 vs 6.6 ms, 2 threads; as fast beyond, where the vectorised ``cos`` reduces its argument
    the slow way). The same values to round-off (≤ 1 ulp of each part), and bit for bit the same with and
    without autograd (a memory-saving replay compares the two)."""
    if torch.is_grad_enabled() and (abs.requires_grad or angle.requires_grad):
        return _Polar.apply(abs, angle)
    return _polar_values(abs, angle)


def unit_phasor(angle: torch.Tensor) -> torch.Tensor:
    """``exp(i·angle)``: :func:`polar` with ``abs = 1`` (the same values bit for bit, with and without autograd),
    without autograd written straight from ``cos``/``sin`` (no unit array, no product)."""
    if torch.is_grad_enabled() and angle.requires_grad:
        return _UnitPhasor.apply(angle)
    return _unit_values(angle)


def _unit_values(angle: torch.Tensor) -> torch.Tensor:
    """``cos(angle) + i·sin(angle)`` written into the output's parts (no autograd)."""
    out = torch.empty(angle.shape, dtype=torch.complex128 if angle.dtype == torch.float64 else torch.complex64,
                      device=angle.device)
    parts = torch.view_as_real(out)
    torch.cos(angle, out=parts[..., 0])
    torch.sin(angle, out=parts[..., 1])
    return out


class _UnitPhasor(torch.autograd.Function):
    """:func:`unit_phasor` with its derivative ``∂z/∂θ = i·z``; keeps only the angle (a unit array for
    :class:`_Polar` would double what the graph holds) and recomputes ``z`` in the backward (the same values as
    :class:`_Polar`'s with ``abs = 1``)."""

    @staticmethod
    def forward(ctx, angle):
        ctx.save_for_backward(angle)
        return _unit_values(angle)

    @staticmethod
    def backward(ctx, g):
        (angle,) = ctx.saved_tensors
        return (_unit_values(angle).conj() * g).imag
