"""Multi-process training helpers (torch.distributed; gloo on CPU, nccl on GPUs).

Data parallelism for the network and work splitting for the optics:

* every rank draws the **same** optics randomness (the same seed → the same :class:`OpticsStep` draws) and
  computes the (cheap, no-autograd) PSF map forward, renders **its own share of the batch**, and backpropagates
  its loss (scaled by its share of the batch) to the network and to ∂L/∂PSF;
* ∂L/∂PSF is summed over the ranks (:func:`allreduce_`), then each rank **replays only its chunks**
  (:func:`shard`) of the PSF map;
* the parameters' gradients are summed over the ranks (:func:`allreduce_grads`): network (each rank saw part
  of the batch) and optics (each rank replayed part of the map) alike.

The result equals the single-process gradient of the whole batch (tested with two gloo processes). The
network's gradient sum is what ``DistributedDataParallel`` computes (with its mean convention undone by the
loss scaling), so a DDP-wrapped network may replace :func:`allreduce_grads` for the network parameters.
"""

from __future__ import annotations

from typing import Iterable

import torch
import torch.distributed as dist

__all__ = ["shard", "allreduce_", "allreduce_grads", "batch_share"]


def shard(n: int, rank: int, world: int) -> list[int]:
    """Indices ``0 … n−1`` handled by ``rank`` of ``world`` (round robin: balanced when chunk costs vary
    smoothly over the map)."""
    if not 0 <= rank < world:
        raise ValueError(f"rank {rank} out of range for world size {world}")
    return list(range(rank, n, world))


def batch_share(batch: int, rank: int, world: int) -> slice:
    """The contiguous slice of a batch of ``batch`` items that ``rank`` renders."""
    per, extra = divmod(batch, world)
    lo = rank * per + min(rank, extra)
    return slice(lo, lo + per + (1 if rank < extra else 0))


def allreduce_(t: torch.Tensor, group=None) -> torch.Tensor:
    """In-place sum over the ranks (no-op without an initialised process group)."""
    if dist.is_available() and dist.is_initialized():
        dist.all_reduce(t, op=dist.ReduceOp.SUM, group=group)
    return t


def allreduce_grads(params: Iterable[torch.nn.Parameter], group=None) -> None:
    """Sum the ``.grad`` of ``params`` over the ranks (missing grads count as zero, so every rank calls the
    collective with the same tensors)."""
    for p in params:
        if not p.requires_grad:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        allreduce_(p.grad, group)
