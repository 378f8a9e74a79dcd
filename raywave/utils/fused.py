"""Elementwise chains as one compiled loop: :func:`fused` wraps a function of tensors in ``torch.compile`` (inductor,
dynamic shapes), with the plain function as the fallback.

Why: the engine's memory-bound stages (the knife-edge factor, transfer functions, phasors) are chains of tens of
elementwise passes over arrays of 10⁵–10⁶ samples; one compiled loop reads and writes each array once (5–7× on a
CPU for a chain of ~15 float64 passes, the values within a few ulp of the eager chain's: the compiled loop's vector
``sin`` / ``cos`` / ``exp`` round differently from ATen's).

Rules for a fused function (issue 43):
- real tensors in and out (float64 for phase work); a complex result is returned as its real and imaginary parts,
  two arrays, and joined with :func:`torch.complex` by the caller (inductor has no complex kernels; a stacked
  ``(..., 2)`` output blocks the loop's vector stores on a CPU: a phasor took 24 ms stacked against 2.9 ms as two
  arrays, h47c);
- contiguous inputs where they can be (each stride pattern is its own graph; a function keeps up to
  :data:`RECOMPILE_LIMIT` of them);
- Python floats may be passed (compiled as symbolic values, not one graph per value); no data-dependent control flow
  (``.item()``, ``if tensor``): one graph, ``fullgraph=True``.

The compiled loop is used on CPUs, and on CUDA where ``triton`` is importable; ``RAYWAVE_COMPILE=0`` in the
environment (read when a function is first called) keeps every function eager. A first call compiles (~10 s on a
fresh machine, ~1 s from inductor's disk cache); a compiler that fails leaves that function eager for the process,
with one :class:`FusedFallbackWarning` naming it and the reason. Gradients flow through the compiled loop (its
backward compiled as well).
"""

from __future__ import annotations

import importlib.util
import os
import warnings

import torch
import torch.fx.experimental._config as fx_config

__all__ = ["fused", "FusedFallbackWarning", "compile_enabled"]

#: environment variable that switches the compiled loops off ("0", "false", "off", "no")
ENV = "RAYWAVE_COMPILE"
#: graphs (shapes' specialisations, stride patterns) one fused function may keep: torch.compile's own limit (8) is
#: raised for the fused call alone (a long test session used 8 up on the knife-edge loop, h47c), not process-wide
RECOMPILE_LIMIT = 64


class FusedFallbackWarning(RuntimeWarning):
    """A fused function runs eagerly (slower, same physics) because its compilation failed."""


def compile_enabled() -> bool:
    """Whether :func:`fused` functions compile (``RAYWAVE_COMPILE`` not set to 0 / false / off / no)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "off", "no")


def _device_supported(args) -> bool:
    """Whether the tensors of ``args`` live where inductor can compile: the CPU, or CUDA with triton."""
    for a in args:
        if isinstance(a, torch.Tensor):
            if a.device.type == "cpu":
                return True
            if a.device.type == "cuda":
                return importlib.util.find_spec("triton") is not None
            return False
    return True


class _Fused:
    """A function of tensors with a lazily compiled twin (see the module's docstring)."""

    def __init__(self, fn):
        self.fn = fn
        self.__name__ = getattr(fn, "__name__", "fused")
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn
        self._compiled = None
        self._failed = False

    def __call__(self, *args, **kwargs):
        if self._failed or not compile_enabled() or torch.compiler.is_compiling() or not _device_supported(args):
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=True, fullgraph=True)
        try:
            # no duck sizing: two sizes equal on the first call (a square window) are not assumed equal, so a later
            # rectangular one does not compile a graph of its own (~1–3 s with inductor's disk cache warm, ~15 s
            # cold; the bundled lens's first 10×10×3 map after a one-PSF warm-up compiled the knife edge's loop twice
            # more, once now: a crop at its array's corner, whose storage offset 0 inductor compiles as a constant)
            with torch._dynamo.config.patch(cache_size_limit=RECOMPILE_LIMIT), fx_config.patch(use_duck_shape=False):
                return self._compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 (any compiler failure: the eager function is the same physics)
            out = self.fn(*args, **kwargs)  # bad input raises its own error here, not a compiler's
            self._failed = True
            warnings.warn(f"raywave: compiling {self.__name__} failed ({type(exc).__name__}: {str(exc)[:200]}); "
                          f"it runs eagerly from now on (slower, same results to rounding; {ENV}=0 skips compiling)",
                          FusedFallbackWarning, stacklevel=2)
            return out


def fused(fn):
    """``fn`` (tensors and Python numbers in, real tensors out; one graph) compiled into one loop on first use, with
    ``fn`` itself as the fallback (module docstring). Use as a decorator on a module-level function."""
    return _Fused(fn)
