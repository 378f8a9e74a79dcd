"""NaN-free elementwise helpers for masked ray computations.

A ray that misses a surface must not produce NaN, neither in the forward pass nor in the backward pass.
``torch.where(ok, sqrt(x), 0)`` is not enough: the gradient of the discarded branch is still evaluated and
0·NaN = NaN. The helpers below first replace the invalid *inputs* by a harmless value ("double where").
"""

from __future__ import annotations

import torch


def safe_sqrt(x: torch.Tensor, ok: torch.Tensor | None = None, fill: float = 1.0) -> torch.Tensor:
    """sqrt(x) where ``ok`` (default: x > 0) and sqrt(fill) elsewhere; finite gradients everywhere."""
    if ok is None:
        ok = x > 0
    return torch.sqrt(torch.where(ok, x, torch.full_like(x, fill)))


def safe_div(num: torch.Tensor, den: torch.Tensor, ok: torch.Tensor | None = None, fill: float = 1.0) -> torch.Tensor:
    """num/den where ``ok`` (default: den != 0), num/fill elsewhere (finite gradients where ``den`` is 0)."""
    if ok is None:
        ok = den != 0
    return num / torch.where(ok, den, torch.full_like(den, fill))
