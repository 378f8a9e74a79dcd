"""Multi-process training: the :class:`~raywave.training.trainer.Trainer` on N ranks of a ``torch.distributed``
process group (gloo on CPU, nccl on GPUs), under ``torchrun`` or :func:`spawn` (``raywave train --nproc N``).

How one optimizer step is split (every rank holds the whole model; see :mod:`raywave.training.distributed`):

* every rank draws the **same** randomness (one seeded generator: wavelengths, patch positions, chunk seeds,
  sensor noise); the PSF map's forward pass without autograd is split by chunks too and the chunks are
  exchanged, so every rank holds the whole map (the stage-2 / evaluation map is computed on every rank);
* **pre-stage**: every rank evaluates the PSF objective on the whole map (∂L/∂PSF is the same everywhere) and
  **replays only its share of the chunks** (:func:`~raywave.training.distributed.shard`: round robin);
* **stage 1**: the batch's micro-batches (``stage1.micro_batches``; the batch split evenly when there are fewer
  micro-batches than ranks) are dealt to the ranks; each renders, reconstructs and backpropagates its own,
  ∂L/∂PSF is summed over the ranks, each rank replays its chunks;
* **stage 2** (optics frozen): each rank renders its share of the batch, the simulated images are gathered so
  that the sensor noise is drawn for the whole batch from the shared generator (as in one process), each rank
  reconstructs its share;
* the gradients (network and optics) are summed over the ranks (:func:`allreduce_grads`), so every rank makes
  the same optimizer step: the **single-process step**, up to the order of floating-point sums.

Exactly the single-process step needs a loss that is a mean over images (``l1``, ``mse``) or, for the
root-mean-square losses (``rmse``/``edof``), a partition of the batch the single process uses too: stage 1 with
``micro_batches`` ≥ the number of ranks (each rank takes whole micro-batches); otherwise (and in stage 2, which
has no micro-batches) a nonlinear loss is computed per rank's share (a warning says so once).

Only rank 0 writes ``log.jsonl`` and the checkpoints; every rank reads the latest checkpoint when resuming
(all ranks then hold the same random states). The CLI evaluates and exports on rank 0 (or, with ``--nproc``, in
the launching process after the ranks finished).
"""

from __future__ import annotations

import os
import socket
import warnings

import torch
import torch.distributed as dist

from raywave.training.distributed import allreduce_, allreduce_grads, batch_share, shard
from raywave.training.replay import OpticsStep
from raywave.training.trainer import Trainer

__all__ = ["DistributedTrainer", "rank_and_world", "init_from_env", "spawn", "train_ranks"]


def rank_and_world() -> tuple[int, int]:
    """(rank, world size) of the initialised default process group, (0, 1) without one."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def init_from_env(backend: str | None = None) -> bool:
    """Join the process group that ``torchrun`` describes in the environment (``WORLD_SIZE`` > 1, ``RANK``,
    ``MASTER_ADDR``/``MASTER_PORT``); backend default gloo (nccl when CUDA is available). False (nothing done)
    outside torchrun or when a group is already initialised."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or (dist.is_available() and dist.is_initialized()):
        return False
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend)
    return True


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _entry(rank: int, world: int, port: int, backend: str, fn, args) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world))
    dist.init_process_group(backend, rank=rank, world_size=world)
    try:
        fn(*args)
    finally:
        dist.destroy_process_group()


def spawn(nproc: int, fn, *args, backend: str = "gloo") -> None:
    """Run ``fn(*args)`` in ``nproc`` new processes forming a local process group (``backend``, default gloo on
    CPU); ``fn`` must be a module-level function (it is pickled). Returns when all have finished; a failing rank
    raises here."""
    import torch.multiprocessing as mp

    nproc = int(nproc)
    if nproc < 1:
        raise ValueError(f"the number of processes must be >= 1, got {nproc}")
    mp.spawn(_entry, args=(nproc, _free_port(), backend, fn, args), nprocs=nproc, join=True)


class DistributedTrainer(Trainer):
    """A :class:`~raywave.training.trainer.Trainer` for one rank of the default process group (see the module
    docstring); without an initialised group it is the plain Trainer. Same arguments as the Trainer."""

    def __init__(self, *args, **kwargs):
        self.rank, self.world = rank_and_world()
        self._warned = False
        super().__init__(*args, **kwargs)
        if self.world > 1:  # every rank starts from rank 0's modules (they agree already: seeded initialisation)
            with torch.no_grad():
                for p in list(self.hl.parameters()) + list(self.net.parameters()):
                    dist.broadcast(p.data, 0)

    # ------------------------------------------------------------------ rank-0-only output
    def _log(self, rec: dict) -> None:
        if self.rank == 0:
            super()._log(rec)

    def _save(self, stage, step, opt, sched) -> None:
        if self.rank == 0:
            super()._save(stage, step, opt, sched)

    # ------------------------------------------------------------------ helpers
    def optics_step(self, grid_fields=None, wavelengths=None):
        """The Trainer's :class:`~raywave.training.replay.OpticsStep` whose forward pass is split over the ranks
        (each computes its chunks, then all ranks exchange them)."""
        step = super().optics_step(grid_fields, wavelengths)
        return _ShardedStep(step, self.rank, self.world) if self.world > 1 else step

    def _params(self) -> list:
        return list(self.hl.parameters()) + list(self.net.parameters())

    def _parts(self, batch: int, micro: int, loss: str) -> list[torch.Tensor]:
        """The index sets of the batch this rank renders (whole micro-batches when there are enough)."""
        if self.world == 1:
            return super()._parts(batch, micro, loss)
        micro = max(1, min(int(micro), batch))
        if micro >= self.world:
            parts = torch.arange(batch).chunk(micro)
            return [parts[k] for k in shard(len(parts), self.rank, self.world)]
        if loss not in ("l1", "mse") and not self._warned:
            self._warned = True
            if self.rank == 0:
                warnings.warn(f"{self.world} ranks but {micro} micro-batch(es): the {loss!r} loss is computed per "
                              "rank's share of the batch, not exactly the single-process loss (in stage 1, "
                              "micro_batches >= the number of ranks makes it exact)", stacklevel=3)
        return [torch.arange(batch)[batch_share(batch, self.rank, self.world)]]

    def _replay(self, step: OpticsStep, leaf_grads_partial: bool) -> None:
        """Replay only this rank's share of the chunks; a partial ∂L/∂PSF (stage 1: each rank rendered its
        share of the batch) is first summed over the ranks."""
        if self.world == 1:
            return super()._replay(step, leaf_grads_partial)
        if leaf_grads_partial:
            for leaf in step.leaves():
                if leaf.grad is None:
                    leaf.grad = torch.zeros_like(leaf)
                allreduce_(leaf.grad)
        step.backward(chunks=shard(step.n_chunks, self.rank, self.world))

    def _sync_grads(self) -> None:
        if self.world > 1:
            allreduce_grads(self._params())

    def _sum(self, value: float) -> float:
        if self.world == 1:
            return value
        t = torch.tensor([value], dtype=torch.float64, device=self.device)  # nccl reduces device tensors only
        return float(allreduce_(t)[0])

    # ------------------------------------------------------------------ stage 2: the batch split, noise shared
    def _recon_loss_map(self, img, pm, extents, sc, sensor):
        if self.world == 1:
            return super()._recon_loss_map(img, pm, extents, sc, sensor)
        from raywave.imaging.render import render
        from raywave.training.losses import edof_loss, image_loss

        B = img.shape[0]
        mine = self._parts(B, 1, sc.loss)[0]
        share = batch_share(B, self.rank, self.world)
        recon = []
        for d in range(pm.psf.shape[0]):
            with torch.no_grad():
                own = torch.cat([render(img[i:i + 1], pm.psf[d], positions=pm.positions, centers=pm.centers[d],
                                        sensor_size=pm.sensor_size, pitch=pm.pitch, extent=extents[i])
                                 for i in mine.tolist()]) if len(mine) else img[:0]
                sims = self._gather_batch(own, B)
                if sensor is not None:  # the whole batch's noise from the shared generator (ranks stay in step)
                    sims = sensor(sims, generator=self.gen)
            recon.append(self.reconstruct(sims[share], pm.psf, pm.centers,
                                          [extents[i] for i in range(share.start, share.stop)], pm.positions))
        target = img[share]
        if len(mine) == 0:
            return sum(r.sum() for r in recon) * 0.0  # nothing here: a zero that still reaches the network
        if sc.loss == "edof":
            loss = edof_loss(recon, target, alpha=sc.edof_alpha)
        else:
            loss = sum(image_loss(sc.loss)(r, target) for r in recon) / len(recon)
        return loss * (len(mine) / B)

    def _gather_batch(self, own: torch.Tensor, batch: int) -> torch.Tensor:
        """The ranks' shares (each ``batch_share``) concatenated in rank order: ``(batch, ...)``."""
        sizes = [batch_share(batch, r, self.world) for r in range(self.world)]
        width = max(s.stop - s.start for s in sizes)
        pad = torch.zeros((width, *own.shape[1:]), dtype=own.dtype, device=own.device)
        pad[:own.shape[0]] = own
        out = [torch.empty_like(pad) for _ in range(self.world)]
        dist.all_gather(out, pad)
        return torch.cat([o[:s.stop - s.start] for o, s in zip(out, sizes)])


class _ShardedStep(OpticsStep):
    """An :class:`OpticsStep` (same compute function, draws and chunk seed) whose no-autograd forward pass is
    split: each rank computes its chunks (:func:`shard`), the chunk outputs are exchanged
    (``all_gather_object``), so every rank holds the whole map, bit-identical to one process's. The replay
    (``backward(chunks=...)``) is unchanged."""

    def __init__(self, step: OpticsStep, rank: int, world: int):
        super().__init__(step.compute_chunk, step.n_chunks, draws=step.draws, seed=step.seed, check=step.check)
        self.rank, self.world = rank, world
        self._received: dict | None = None

    def _chunk(self, k: int):
        if self._received is not None and k in self._received:
            return self._received.pop(k)
        return super()._chunk(k)

    def forward(self):
        if self._values is None:
            with torch.no_grad():
                mine = {k: self._chunk(k) for k in shard(self.n_chunks, self.rank, self.world)}
            device = next(iter(mine.values()))[0].device if mine else torch.device("cpu")
            everyone = [None] * self.world
            dist.all_gather_object(everyone, mine)
            self._received = {k: tuple(t.to(device) for t in out) for part in everyone for k, out in part.items()}
            super().forward()  # concatenates the received chunks (nothing is recomputed)
            self._received = None
        return self._values


def train_ranks(cfg, run_dir, resume: bool = True, baseline: bool = True, progress: bool = False) -> None:
    """The training part of ``raywave train`` on this rank: the designed run, then (``baseline``) the baseline
    run in ``run_dir/baseline``; progress bars on rank 0 only. Evaluation and export are left to the caller."""
    from pathlib import Path

    rank, _ = rank_and_world()
    show = bool(progress) and rank == 0
    DistributedTrainer(cfg, Path(run_dir), progress=show).run(resume=resume)
    if baseline:
        DistributedTrainer(cfg, Path(run_dir) / "baseline", baseline=True, progress=show).run(resume=resume)
