"""Memory-saving gradient path for end-to-end optics (paper section 2.3; cf. path replay backpropagation,
Vicini et al. 2021).

A full autograd graph of a 10×10 PSF map holds every ray, field and FFT of 100+ PSFs at once. Instead:

1. **forward without autograd**: compute the PSF map chunk by chunk under ``torch.no_grad()``;
2. **render, network, loss with the PSFs as leaf tensors** (``requires_grad=True``); ``loss.backward()``
   gives the network's gradients and ∂L/∂PSF;
3. **replay**: recompute each chunk *with* autograd — from exactly the same random draws — and call
   ``torch.autograd.backward(chunk, ∂L/∂chunk)``, which accumulates ∂L/∂θ into the optics parameters' ``.grad``;
   the chunk's graph is freed before the next one.

By the chain rule ∂L/∂θ = Σ_k (∂PSF_k/∂θ)ᵀ ∂L/∂PSF_k, which is what the full graph computes, while peak memory
is that of one chunk's graph (plus the PSF values), whatever the number of PSFs.

Randomness (a wavelength drawn per colour channel, the faithful mode's random pupil samples) must be identical
in the forward pass and in the replay. :class:`OpticsStep` makes that structural rather than a convention:

* the step's random draws are made **once**, when the step is created (``OpticsStep.draw(...)`` calls the
  user's ``sampler(generator)``), stored in ``step.draws`` and handed to every evaluation of every chunk;
* each chunk gets its own ``torch.Generator`` seeded from a seed drawn at creation and the chunk index, built
  afresh for each evaluation, so chunk k sees the same random stream in the forward pass and in the replay,
  in any order;
* the replay compares each recomputed chunk with its forward value and raises :class:`ReplayMismatchError`
  if they differ (a compute function that used the global RNG, a parameter changed between forward and
  backward, ...).

A chunk function may return one tensor or a tuple of tensors (e.g. PSFs and their centres, which carry the
distortion); every output is concatenated over the chunks along dimension 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import torch

__all__ = ["OpticsStep", "ChunkContext", "ReplayMismatchError", "chunk_ranges", "auto_chunk"]


class ReplayMismatchError(RuntimeError):
    """A replayed chunk differs from its forward value: the replay would give a wrong gradient."""


@dataclass(frozen=True)
class ChunkContext:
    """What a chunk computation may depend on besides the parameters.

    Attributes:
        index: the chunk index k.
        draws: the step's random draws (whatever the sampler returned), identical in forward and replay.
        generator: a CPU ``torch.Generator`` private to this chunk of this step, freshly seeded for every
            evaluation (use it for any further randomness inside the chunk).
    """

    index: int
    draws: Any
    generator: torch.Generator = field(repr=False)


def chunk_ranges(n: int, chunk: int) -> list[range]:
    """Split ``range(n)`` into consecutive ranges of at most ``chunk`` items (e.g. PSF-map rows)."""
    if n < 0 or chunk < 1:
        raise ValueError(f"need n >= 0 and chunk >= 1, got n={n}, chunk={chunk}")
    return [range(i, min(i + chunk, n)) for i in range(0, n, chunk)]


#: field points per chunk that ``chunk: auto`` takes on a CPU: there the chunk's ops are compute-bound, and chunks of
#: 1, 5 and 25 field points of the paper's map ran at the same time per PSF (2026-11-30), while memory grows with
#: the chunk
CPU_AUTO_CHUNK = 4
#: bytes of autograd graph a replayed source (field point × wavelength) holds per sample of the DOE's simulation grid,
#: with the frozen lens's DOE fields cached (only their propagation replayed): an upper bound, measured 3.3–3.7 B on
#: the bundled asphere's 3000² and 2000² DOEs (CPU, 2026-11-30; a source's window covers part of the DOE)
REPLAY_BYTES_PER_DOE_SAMPLE = 8
#: the same with the lens traced in the replay (a trained lens: the rays, node maps and fine field in the graph):
#: measured 11 B (a 10×10×3 map forward + backward in calls of 100 field points on an H200: 29.9 GB, 2026-11-30)
REPLAY_BYTES_PER_DOE_SAMPLE_TRACED = 16
#: fraction of the accelerator's free memory that ``chunk: auto`` gives one chunk's graph
AUTO_CHUNK_MEMORY_FRACTION = 0.25


def auto_chunk(n_points: int, sources_per_point: int, doe_samples: int, device, traced: bool = False) -> int:
    """Field points per replay chunk for ``optics.chunk: auto``. On a GPU, as many as a quarter of its free memory
    holds at :data:`REPLAY_BYTES_PER_DOE_SAMPLE` (``traced``: :data:`REPLAY_BYTES_PER_DOE_SAMPLE_TRACED`) per DOE
    sample and source: each chunk is a few hundred kernel launches whatever its size, so the step's time falls with
    the chunk count. On a CPU (or without a DOE grid to size it by) :data:`CPU_AUTO_CHUNK`.

    Args:
        n_points: field points of the map (the most a chunk can hold).
        sources_per_point: sources per field point in one chunk (wavelengths: 3 in stage 1).
        doe_samples: samples of the DOE's simulation grid (0: unknown, e.g. a DOE inside the lens).
        device: the torch device of the optics.
        traced: the replay traces the lens (no DOE-field cache): :data:`REPLAY_BYTES_PER_DOE_SAMPLE_TRACED`.
    """
    dev = torch.device(device)
    if dev.type != "cuda" or doe_samples <= 0:
        return max(1, min(CPU_AUTO_CHUNK, n_points))
    free, _ = torch.cuda.mem_get_info(dev)
    per_sample = REPLAY_BYTES_PER_DOE_SAMPLE_TRACED if traced else REPLAY_BYTES_PER_DOE_SAMPLE
    per_point = max(1, sources_per_point) * doe_samples * per_sample
    return max(1, min(n_points, int(AUTO_CHUNK_MEMORY_FRACTION * free // per_point)))


def _as_tuple(x) -> tuple[torch.Tensor, ...]:
    return tuple(x) if isinstance(x, (tuple, list)) else (x,)


class OpticsStep:
    """One optics evaluation (a PSF map) that can be computed without autograd and replayed chunk by chunk.

    Args:
        compute_chunk: ``f(ctx: ChunkContext) -> Tensor | tuple[Tensor, ...]``; chunk ``ctx.index`` of the map,
            each output with the chunk's items along dimension 0. It must depend only on the parameters,
            ``ctx.draws`` and ``ctx.generator``.
        n_chunks: number of chunks.
        draws: the step's random draws (use :meth:`draw` to make them from a generator).
        seed: base seed of the per-chunk generators.
        check: compare replayed chunks with their forward values (``"exact"``: bit-identical; a float: relative
            tolerance on the max-abs difference, for nondeterministic GPU kernels; ``None``: no check).

    Typical use::

        step = OpticsStep.draw(compute_chunk, n_chunks, sampler, generator)
        psf, = step.leaves()                 # no autograd inside; psf.requires_grad is True
        loss = loss_fn(net(render(img, psf)), img)
        loss.backward()                      # network grads and psf.grad
        step.backward()                      # replay: optics grads accumulate in .grad
    """

    def __init__(self, compute_chunk: Callable[[ChunkContext], Any], n_chunks: int, draws: Any = None,
                 seed: int = 0, check: str | float | None = "exact"):
        if int(n_chunks) < 1:
            raise ValueError(f"n_chunks must be >= 1, got {n_chunks!r}")
        if not (check is None or check == "exact" or (isinstance(check, float) and check >= 0)):
            raise ValueError(f"check must be 'exact', a tolerance >= 0 or None, got {check!r}")
        self.compute_chunk = compute_chunk
        self.n_chunks = int(n_chunks)
        self.draws = draws
        self.seed = int(seed)
        self.check = check
        self._values: tuple[torch.Tensor, ...] | None = None
        self._sizes: list[int] | None = None
        self._leaves: tuple[torch.Tensor, ...] | None = None
        self._replayed = False

    @classmethod
    def draw(cls, compute_chunk, n_chunks: int, sampler: Callable[[torch.Generator], Any] | None,
             generator: torch.Generator, **kw) -> "OpticsStep":
        """A step whose draws are ``sampler(generator)`` and whose chunk seed is drawn from ``generator`` too
        (so one training generator drives everything, and its state after this call is reproducible)."""
        draws = sampler(generator) if sampler is not None else None
        seed = int(torch.randint(0, 2 ** 62, (1,), generator=generator, device=generator.device))
        return cls(compute_chunk, n_chunks, draws=draws, seed=seed, **kw)

    # ------------------------------------------------------------------ evaluation
    def context(self, k: int) -> ChunkContext:
        """A fresh context for chunk ``k`` (same generator state every time)."""
        g = torch.Generator()
        g.manual_seed((self.seed * 1_000_003 + int(k)) % (2 ** 63 - 1))
        return ChunkContext(int(k), self.draws, g)

    def _chunk(self, k: int) -> tuple[torch.Tensor, ...]:
        out = _as_tuple(self.compute_chunk(self.context(k)))
        if not out or not all(isinstance(t, torch.Tensor) for t in out):
            raise TypeError(f"compute_chunk must return a tensor or a tuple of tensors, chunk {k} returned "
                            f"{type(out).__name__}")
        return out

    def forward(self) -> tuple[torch.Tensor, ...]:
        """All chunks without autograd, concatenated along dim 0 (cached; a tuple, one per output)."""
        if self._values is None:
            with torch.no_grad():
                parts = [self._chunk(k) for k in range(self.n_chunks)]
            n_out = len(parts[0])
            if any(len(p) != n_out for p in parts):
                raise ValueError("every chunk must return the same number of outputs")
            self._sizes = [p[0].shape[0] if p[0].dim() else 1 for p in parts]
            self._values = tuple(torch.cat([p[i].reshape(-1, *p[i].shape[1:]) if p[i].dim() else p[i][None]
                                            for p in parts]) for i in range(n_out))
        return self._values

    def leaves(self) -> tuple[torch.Tensor, ...]:
        """The forward values as fresh leaf tensors with ``requires_grad=True`` (for floating outputs); their
        ``.grad`` after ``loss.backward()`` is what :meth:`backward` replays by default."""
        if self._leaves is None:
            self._leaves = tuple(v.detach().clone().requires_grad_(v.is_floating_point() or v.is_complex())
                                 for v in self.forward())
        return self._leaves

    def full_graph(self) -> tuple[torch.Tensor, ...]:
        """All chunks *with* autograd in one graph (the memory-hungry reference path; same draws)."""
        parts = [self._chunk(k) for k in range(self.n_chunks)]
        return tuple(torch.cat([p[i] if p[i].dim() else p[i][None] for p in parts]) for i in range(len(parts[0])))

    # ------------------------------------------------------------------ replay
    def backward(self, grads: Sequence[torch.Tensor | None] | torch.Tensor | None = None,
                 chunks: Sequence[int] | None = None) -> None:
        """Replay every chunk with autograd and backpropagate ``grads`` (∂L/∂output, default the leaves'
        ``.grad``) into the parameters, accumulating into their ``.grad``. One chunk's graph at a time.

        ``chunks``: replay only these chunk indices (multi-process training splits the chunks over the ranks
        and sums the parameters' gradients afterwards, see :mod:`raywave.training.distributed`)."""
        values = self.forward()
        if grads is None:
            if self._leaves is None:
                raise RuntimeError("no gradients: call leaves(), use them in the loss and call loss.backward() "
                                   "first, or pass grads=")
            grads = tuple(leaf.grad for leaf in self._leaves)
        grads = _as_tuple(grads)
        if len(grads) != len(values):
            raise ValueError(f"got {len(grads)} gradients for {len(values)} outputs")
        for g, v in zip(grads, values):
            if g is not None and g.shape != v.shape:
                raise ValueError(f"gradient of shape {tuple(g.shape)} for an output of shape {tuple(v.shape)}")
        if all(g is None for g in grads):
            return
        wanted = None if chunks is None else {int(k) for k in chunks}
        if wanted is not None and not wanted <= set(range(self.n_chunks)):
            raise ValueError(f"chunks {sorted(wanted - set(range(self.n_chunks)))} out of range 0…{self.n_chunks - 1}")
        start = 0
        for k, size in enumerate(self._sizes):
            sl = slice(start, start + size)
            start += size
            if wanted is not None and k not in wanted:
                continue
            gk = [None if g is None else g[sl] for g in grads]
            if all(g is None or not bool(g.any()) for g in gk):
                continue  # nothing flows back through this chunk (skips its recomputation)
            with torch.enable_grad():
                out = self._chunk(k)
                self._check(k, out, [v[sl] for v in values])
                pairs = [(o, g) for o, g in zip(out, gk) if g is not None and o.requires_grad]
                if pairs:
                    torch.autograd.backward([o for o, _ in pairs], [g.to(o.dtype) for o, g in pairs])
            del out, pairs
        self._replayed = True

    def _check(self, k: int, out, ref) -> None:
        if self.check is None:
            return
        for i, (o, r) in enumerate(zip(out, ref)):
            o = o.detach().reshape(r.shape)
            if self.check == "exact":
                ok = torch.equal(o, r)
            else:
                scale = float(r.abs().max()) if r.numel() else 0.0
                ok = float((o - r).abs().max()) <= self.check * max(scale, 1e-300) if r.numel() else True
            if not ok:
                diff = float((o - r).abs().max()) if r.numel() else 0.0
                raise ReplayMismatchError(
                    f"chunk {k}, output {i}: the replay differs from the forward pass by up to {diff:.3g}; the "
                    "chunk computation must depend only on the parameters, ctx.draws and ctx.generator (not on "
                    "torch's global RNG), and the parameters must not change between forward and backward")
