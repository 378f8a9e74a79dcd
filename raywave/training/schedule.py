"""Optimiser and learning-rate schedule: Adam with one parameter group per part of the system (refractive
lens, DOE, network; paper defaults 1e-4, 1e-1, 1e-4) and a linear warm-up followed by cosine annealing."""

from __future__ import annotations

import math
from typing import Iterable

import torch
from torch.optim.lr_scheduler import LambdaLR

__all__ = ["WarmupCosine", "warmup_cosine_scheduler", "param_groups", "build_optimizer", "DEFAULT_LR"]

DEFAULT_LR = {"lens": 1e-4, "doe": 1e-1, "network": 1e-4}


class WarmupCosine:
    """Learning-rate factor of optimizer step ``s`` (0-based): ``(s + 1) / warmup`` for the first ``warmup``
    steps, then ``min_ratio + (1 − min_ratio)·½(1 + cos(π t))`` with t going from 0 to 1 over the remaining
    steps up to ``total`` (and ``min_ratio`` after). A callable object, so ``LambdaLR.state_dict`` saves it."""

    def __init__(self, total: int, warmup: int = 0, min_ratio: float = 0.0):
        if total < 1 or warmup < 0 or not 0 <= min_ratio <= 1:
            raise ValueError(f"need total >= 1, warmup >= 0, 0 <= min_ratio <= 1; got total={total}, "
                             f"warmup={warmup}, min_ratio={min_ratio}")
        self.total, self.warmup, self.min_ratio = int(total), int(warmup), float(min_ratio)

    def __call__(self, step: int) -> float:
        if step < self.warmup:
            return (step + 1) / self.warmup
        span = max(self.total - self.warmup - 1, 1)
        t = min(max(step - self.warmup, 0) / span, 1.0)
        return self.min_ratio + (1.0 - self.min_ratio) * 0.5 * (1.0 + math.cos(math.pi * t))


def warmup_cosine_scheduler(optimizer: torch.optim.Optimizer, total: int, warmup: int = 0,
                            min_ratio: float = 0.0) -> LambdaLR:
    """A ``LambdaLR`` applying :class:`WarmupCosine` to every group (call ``.step()`` after each
    ``optimizer.step()``)."""
    return LambdaLR(optimizer, WarmupCosine(total, warmup, min_ratio))


def _trainable(params: Iterable[torch.nn.Parameter] | torch.nn.Module | None) -> list:
    if params is None:
        return []
    if isinstance(params, torch.nn.Module):
        params = params.parameters()
    return [p for p in params if p.requires_grad]


def param_groups(lens=None, doe=None, network=None, lr_lens: float = DEFAULT_LR["lens"],
                 lr_doe: float = DEFAULT_LR["doe"], lr_network: float = DEFAULT_LR["network"]) -> list[dict]:
    """Adam parameter groups named ``"lens"``, ``"doe"``, ``"network"`` (modules or parameter iterables; parts
    that are None, frozen (no parameter requiring grad) or have lr 0 are left out). A parameter may belong to
    one group only."""
    groups, seen = [], set()
    for name, part, lr in (("lens", lens, lr_lens), ("doe", doe, lr_doe), ("network", network, lr_network)):
        if lr < 0:
            raise ValueError(f"learning rate of {name!r} must be >= 0, got {lr!r}")
        ps = _trainable(part)
        dup = [p for p in ps if id(p) in seen]
        if dup:
            raise ValueError(f"group {name!r} shares {len(dup)} parameter(s) with an earlier group")
        seen.update(id(p) for p in ps)
        if ps and lr > 0:
            groups.append({"name": name, "params": ps, "lr": float(lr)})
    return groups


def build_optimizer(groups: list[dict], betas=(0.9, 0.999), eps: float = 1e-8) -> torch.optim.Adam:
    """Adam over :func:`param_groups` (an empty list is an error: nothing to train)."""
    if not groups:
        raise ValueError("nothing to optimise: every parameter group is empty, frozen or has lr 0")
    return torch.optim.Adam(groups, betas=betas, eps=eps)
