"""A PSF map that can be interrupted and resumed (issue 43: the paper's 40×40 × 9-wavelength stage-2 map, ~1 CPU
hour, computed in chunks that fit).

:func:`raywave.imaging.psf_map` with ``checkpoint=FOLDER`` writes each finished chunk (a model call's field points ×
wavelengths, at one depth) to ``FOLDER`` as it goes; run again with the same folder after an interruption, it loads
the finished chunks and computes only the others (its progress bar starts at the PSFs already done). The folder
remembers what it is a map of (:func:`map_key`: the model's parameters and buffers byte for byte and its optics
settings, the field points, depths, wavelengths, ks, chunks and PSF options): a folder of another map is refused
with an error that names what differs, before any PSF is computed.

Files: ``map.json`` (the key) and one ``d<depth>_<start>_<end>.pt`` per finished chunk (the PSFs ``(P, W, ks, ks)``,
centres ``(P, W, 2)`` mm, energies outside ``(P, W)`` and the pitch), each written to a temporary name and renamed, so
an interruption never leaves a half-written chunk behind.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

__all__ = ["MapCheckpoint", "map_key"]

KEY_FILE = "map.json"


def _digest(tensors) -> str:
    """A blake2b digest (hex) of the named tensors ``[(name, tensor)]``: their names, dtypes, shapes and bytes."""
    h = hashlib.blake2b(digest_size=16)
    for name, t in tensors:
        t = t.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def _model_key(model) -> dict:
    """What a model's PSFs depend on: its type, its parameters and buffers (bytes), and its optics settings
    (``field_signature()`` of a :class:`~raywave.hybrid.HybridLens`: lens structure, DOE grid, distances, stop edge)."""
    state = sorted(model.state_dict().items()) if isinstance(model, torch.nn.Module) else []
    own = getattr(model, "field_signature", None)
    return {"type": type(model).__name__, "state": _digest(state),
            "settings": repr(own()) if callable(own) else None}


def map_key(model, flat_fields: torch.Tensor, depths, wavelengths, ks: int, chunks, psf_kw: dict) -> dict:
    """The identity of a map computation (JSON-able): the model (:func:`_model_key`), the flat field points
    ``(F, 2)`` deg (bytes), the depths (mm), wavelengths (µm), ks, the chunks ``[(start, end)]`` and the PSF
    options."""
    return {"model": _model_key(model), "fields": _digest([("fields", flat_fields.to(torch.float64))]),
            "n_fields": int(flat_fields.shape[0]), "depths": [float(d) for d in depths],
            "wavelengths": [float(w) for w in wavelengths], "ks": int(ks), "chunks": [list(c) for c in chunks],
            "psf_kw": repr(sorted(psf_kw.items()))}


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """The keys (dotted) whose values differ between two :func:`map_key` s."""
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(prefix + k)
    return out


class MapCheckpoint:
    """The finished chunks of one map in ``folder`` (created if missing). ``key`` (:func:`map_key`) must equal the
    folder's own when it has one: otherwise a ValueError names the folder and what differs."""

    def __init__(self, folder, key: dict):
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise ValueError(f"checkpoint: {self.folder} is a file, not a folder")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"checkpoint: cannot make the folder {self.folder} ({e.strerror or e})") from None
        path = self.folder / KEY_FILE
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ValueError(f"checkpoint: {path} is unreadable ({e}); remove the folder to start over") from None
            diff = _differences(old, key)
            if diff:
                raise ValueError(f"checkpoint: {self.folder} holds another map (its {', '.join(diff)} differ); "
                                 "remove the folder or give another one")
        else:
            self._write_atomic(path, lambda tmp: tmp.write_text(json.dumps(key, indent=1)))
        self.key = key

    @staticmethod
    def _write_atomic(path: Path, write) -> None:
        tmp = path.with_name(path.name + ".tmp")
        write(tmp)
        os.replace(tmp, path)

    def _chunk_path(self, depth_index: int, chunk) -> Path:
        s, e = chunk
        return self.folder / f"d{depth_index}_{s}_{e}.pt"

    def done(self) -> int:
        """Finished chunk files in the folder (of this key's chunks)."""
        return sum(self._chunk_path(di, c).exists() for di in range(len(self.key["depths"]))
                   for c in self.key["chunks"])

    def load(self, depth_index: int, chunk):
        """The finished chunk ``(psf, center, energy_outside, pitch)`` (CPU tensors), or None if not yet done."""
        path = self._chunk_path(depth_index, chunk)
        if not path.exists():
            return None
        t = torch.load(path, map_location="cpu", weights_only=True)
        return t["psf"], t["center"], t["energy_outside"], float(t["pitch"])

    def save(self, depth_index: int, chunk, psf, center, energy_outside, pitch: float) -> None:
        """Write a finished chunk (detached, on the CPU)."""
        t = {"psf": psf.detach().cpu(), "center": center.detach().cpu(),
             "energy_outside": torch.as_tensor(energy_outside).detach().cpu(), "pitch": torch.tensor(float(pitch), dtype=torch.float64)}
        self._write_atomic(self._chunk_path(depth_index, chunk), lambda tmp: torch.save(t, tmp))
