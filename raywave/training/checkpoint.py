"""Checkpoints: atomic save and exact resume of a training run.

A checkpoint holds the state dicts of named modules, the optimizer and the LR scheduler, the step counter, any
extra JSON-like data (epoch, loss history, ...) and **every random state** the run uses: torch's global CPU
(and CUDA, where present) generators, numpy's and Python's global generators, and the run's own named
``torch.Generator`` objects. Restoring all of them makes the continuation bit-identical to an uninterrupted run.

Files are written atomically (a temporary file in the same folder, flushed and fsynced, then ``os.replace``), so
a run killed while saving leaves the previous checkpoint intact. Everything is stored as tensors and plain
Python values, so :func:`load_checkpoint` reads with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import os
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["rng_state", "set_rng_state", "save_checkpoint", "load_checkpoint", "latest_checkpoint",
           "checkpoint_path"]

FORMAT = 1


def rng_state(generators: dict[str, torch.Generator] | None = None) -> dict[str, Any]:
    """All random states: torch CPU (+ CUDA), numpy, Python ``random`` and the named generators."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"name": np_state[0], "keys": torch.from_numpy(np_state[1].astype(np.int64)),
                  "pos": int(np_state[2]), "has_gauss": int(np_state[3]), "cached_gaussian": float(np_state[4])},
        "python": {"version": py_state[0], "state": list(py_state[1]), "gauss_next": py_state[2]},
        "generators": {k: g.get_state() for k, g in (generators or {}).items()},
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any], generators: dict[str, torch.Generator] | None = None) -> None:
    """Restore :func:`rng_state` (the named generators must be the same set as saved)."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["name"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["state"]), p["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    saved = state.get("generators", {})
    generators = generators or {}
    if set(saved) != set(generators):
        raise ValueError(f"checkpoint has generators {sorted(saved)}, the run has {sorted(generators)}")
    for k, g in generators.items():
        g.set_state(saved[k])


def checkpoint_path(run_dir, step: int) -> Path:
    """``run_dir/checkpoints/step_000123.pt``."""
    return Path(run_dir) / "checkpoints" / f"step_{int(step):06d}.pt"


def save_checkpoint(path, *, modules: dict[str, torch.nn.Module], optimizer=None, scheduler=None, step: int = 0,
                    generators: dict[str, torch.Generator] | None = None, extra: dict | None = None) -> Path:
    """Write a checkpoint atomically to ``path`` (parents created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {
        "format": FORMAT,
        "step": int(step),
        "modules": {k: m.state_dict() for k, m in modules.items()},
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "rng": rng_state(generators),
        "extra": extra or {},
    }
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            torch.save(blob, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def load_checkpoint(path, *, modules: dict[str, torch.nn.Module], optimizer=None, scheduler=None,
                    generators: dict[str, torch.Generator] | None = None, map_location="cpu",
                    restore_rng: bool = True) -> dict[str, Any]:
    """Restore a checkpoint into the given objects (same names as saved); returns ``{"step", "extra"}``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    blob = torch.load(path, map_location=map_location, weights_only=True)
    if blob.get("format") != FORMAT:
        raise ValueError(f"{path}: unknown checkpoint format {blob.get('format')!r}")
    if set(blob["modules"]) != set(modules):
        raise ValueError(f"{path}: checkpoint has modules {sorted(blob['modules'])}, expected {sorted(modules)}")
    for k, m in modules.items():
        m.load_state_dict(blob["modules"][k])
    if optimizer is not None:
        if blob["optimizer"] is None:
            raise ValueError(f"{path}: no optimizer state saved")
        optimizer.load_state_dict(blob["optimizer"])
    if scheduler is not None:
        if blob["scheduler"] is None:
            raise ValueError(f"{path}: no scheduler state saved")
        scheduler.load_state_dict(blob["scheduler"])
    if restore_rng:
        set_rng_state(blob["rng"], generators)
    return {"step": blob["step"], "extra": blob["extra"]}


def latest_checkpoint(run_dir) -> Path | None:
    """The checkpoint of ``run_dir/checkpoints`` with the highest step (None if there is none)."""
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return None
    best, best_step = None, -1
    for p in folder.iterdir():
        m = re.fullmatch(r"step_(\d+)\.pt", p.name)
        if m and int(m.group(1)) > best_step:
            best, best_step = p, int(m.group(1))
    return best
