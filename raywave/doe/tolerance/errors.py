"""Fabrication errors of an L = 2^k level DOE (one etch-depth error and one mask shift per mask) and their
random draws (:func:`sample_errors`); the argument checks that the tolerance modules share. The model is in
:mod:`raywave.doe.tolerance`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

#: Distributions of :func:`sample_errors` for a tolerance ±x: normal with σ = x/2, or uniform in [−x, x].
DISTRIBUTIONS = ("normal", "uniform")


@dataclass(frozen=True)
class FabricationErrors:
    """The errors of one fabricated element (k = number of masks).

    Attributes:
        depth: (k,) relative etch-depth errors ε_j (fractions: 0.02 = +2 %): step j etches ``d_j (1 + ε_j)``.
        shift: (k, 2) lateral shift (δx, δy) of mask j in DOE pixels (+x: the pattern moves toward +x).
    """

    depth: np.ndarray
    shift: np.ndarray

    def __post_init__(self):
        d = np.asarray(self.depth, dtype=np.float64).reshape(-1)
        s = np.asarray(self.shift, dtype=np.float64).reshape(-1, 2) if np.size(self.shift) else \
            np.zeros((d.size, 2))
        if s.shape[0] != d.size:
            raise ValueError(f"fabrication errors: {d.size} depth errors but {s.shape[0]} mask shifts")
        if not (np.isfinite(d).all() and np.isfinite(s).all()):
            raise ValueError("fabrication errors must be finite numbers")
        if (d <= -1).any():
            raise ValueError(f"a relative etch-depth error must be > −1 (−100 %), got {d.min():g}")
        object.__setattr__(self, "depth", d)
        object.__setattr__(self, "shift", s)

    @property
    def masks(self) -> int:
        return int(self.depth.size)

    @classmethod
    def nominal(cls, k: int) -> "FabricationErrors":
        """No errors for k masks."""
        return cls(np.zeros(k), np.zeros((k, 2)))

    @classmethod
    def common_depth(cls, k: int, eps: float) -> "FabricationErrors":
        """Every step etched ``(1 + eps)`` times too deep (a common etch-rate error), no misalignment."""
        return cls(np.full(k, float(eps)), np.zeros((k, 2)))


def _nonneg(x, name: str, unit: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number >= 0 ({unit}), got {x!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite number >= 0 ({unit}), got {x!r}")
    return v


def _count(n, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) and not (isinstance(n, float) and n.is_integer()):
        raise ValueError(f"{name} must be an integer >= 1, got {n!r}")
    if int(n) < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {n!r}")
    return int(n)


def _generator(seed, generator) -> torch.Generator:
    if generator is not None:
        if not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        return generator
    g = torch.Generator()
    g.manual_seed(0 if seed is None else int(seed))
    return g


def sample_errors(k: int, depth_error: float, misalignment: float, n_samples: int = 1, seed: int | None = 0,
                  generator: torch.Generator | None = None, distribution: str = "normal") -> list:
    """``n_samples`` random :class:`FabricationErrors` for k masks.

    Args:
        depth_error: tolerance ±x of every step's etch depth, in **percent** (≥ 0).
        misalignment: tolerance ±m of every mask's shift (mask 2..k; mask 1 is the reference), **DOE pixels**,
            independent in x and y.
        distribution: "normal" (±x = ±2σ) or "uniform" (in [−x, x]).
        seed / generator: a CPU ``torch.Generator`` (or its seed); per sample the k depth errors are drawn first,
            then the (k − 1, 2) shifts.
    """
    k = _count(k, "the number of masks")
    x = _nonneg(depth_error, "the etch-depth error", "percent") / 100.0
    m = _nonneg(misalignment, "the misalignment", "DOE pixels")
    n = _count(n_samples, "the number of samples")
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {', '.join(map(repr, DISTRIBUTIONS))}, got {distribution!r}")
    if x >= 1 and distribution == "uniform" or x >= 0.5 and distribution == "normal":
        raise ValueError(f"an etch-depth tolerance of ±{100 * x:g} % is not a small error (depths could become "
                         "negative): use < 100 % (uniform) or < 50 % (normal, ±2σ)")
    g = _generator(seed, generator)
    out = []
    for _ in range(n):
        if distribution == "normal":
            e = torch.randn(k, generator=g, dtype=torch.float64) * (x / 2)
            s = torch.randn((k - 1, 2), generator=g, dtype=torch.float64) * (m / 2)
        else:
            e = (torch.rand(k, generator=g, dtype=torch.float64) * 2 - 1) * x
            s = (torch.rand((k - 1, 2), generator=g, dtype=torch.float64) * 2 - 1) * m
        shift = np.concatenate([np.zeros((1, 2)), s.numpy()], axis=0)
        out.append(FabricationErrors(e.numpy(), shift))
    return out


def _orders(orders) -> list[int]:
    out = []
    for m in ([orders] if isinstance(orders, (int, np.integer)) else list(orders)):
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
            raise ValueError(f"diffraction orders are integers, got {m!r}")
        out.append(int(m))
    if not out:
        raise ValueError("give at least one diffraction order")
    return out
