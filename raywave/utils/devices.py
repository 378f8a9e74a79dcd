"""Which plan a computation takes: the CPU's (cache-sized blocks, work per source) or an accelerator's (one batched
kernel set per group; every op a kernel launch). One question, asked everywhere the two plans differ, so that a
benchmark can count an accelerator's ops on a CPU by answering it differently (``benchmarks/ops_breakdown.py
--accelerator``) and a test can force either plan."""

from __future__ import annotations

import torch

__all__ = ["accelerator"]


def accelerator(x) -> bool:
    """Whether ``x`` (a tensor, a :class:`torch.device`, a device string, or None: the CPU) lives on an accelerator
    (any device but the CPU): the engine then takes its accelerator plan (the same values to rounding, fewer and
    larger batched ops)."""
    if isinstance(x, torch.Tensor):
        return x.device.type != "cpu"
    return torch.device(x if x is not None else "cpu").type != "cpu"
