"""Files a DeepLens hybrid lens names next to it: the Pixel2D phase map (:func:`load_pixel2d_map`, .pth / .pt /
.npy / .npz) and the legacy DOE's torch checkpoint (torch is imported only to read those)."""

from __future__ import annotations

from pathlib import Path

from raywave.io.errors import LensFileError


def _find_side_file(ref: str, lens_path) -> str | None:
    """A file DeepLens wrote next to the lens: ``ref`` as given when absolute, else relative to the lens file's
    folder, else its base name in that folder, else relative to the current directory."""
    p = Path(ref)
    base = Path(lens_path).parent
    cands = [p] if p.is_absolute() else [base / p, base / p.name, p]
    if p.is_absolute():
        cands.append(base / p.name)
    for c in cands:
        if c.is_file():
            return str(c)
    return None


def _torch_load(file, path, line):
    try:
        import torch

        return torch.load(file, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable checkpoint is the same error to the user
        raise LensFileError(f"DOE: cannot read the torch file {file!r}: {e}", path, line) from None


def load_pixel2d_map(pixel: dict, path):
    """The Pixel2D phase map (rad at λ0) as a float64 ``(ny, nx)`` array in raywave's row order, and its file.

    DeepLens stores row 0 at +y (its grid runs from +h/2 down to −h/2); raywave's row 0 is at −y, so the rows
    are flipped. Reads ``.pth`` / ``.pt`` (a tensor, or a dict holding ``pmap`` / ``phase_map`` / ``phase``),
    ``.npy`` and ``.npz`` (``phase`` / ``pmap`` / ``phase_map``, or its only array)."""
    import numpy as np

    line = pixel["line"]
    arr = pixel.get("array")
    file = pixel.get("ref")
    if arr is None:
        file = _find_side_file(pixel["ref"], path)
        if file is None:
            raise LensFileError(f"DOE.phase_map_path: phase map file {pixel['ref']!r} not found (looked for it as "
                                "given, relative to the lens file, and by its name next to the lens file)", path, line)
        arr = _read_map_file(file, path, line)
    if hasattr(arr, "detach"):
        arr = arr.detach().cpu().double().numpy()
    arr = np.asarray(arr)
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2 or 0 in arr.shape:
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} must be 2-D (H, W), got shape "
                            f"{list(arr.shape)}", path, line)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} must hold real numbers (rad), got "
                            f"{arr.dtype}", path, line)
    arr = np.asarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise LensFileError(f"DOE.phase_map_path: the phase map in {file!r} contains NaN or inf", path, line)
    return np.ascontiguousarray(arr[::-1]), str(file)


def _read_map_file(file: str, path, line):
    """The array in a phase map file (not yet checked; DeepLens's row order): a ``.pth`` / ``.pt`` tensor (or a
    dict's ``phase_map`` / ``pmap`` / ``phase``) as float64 numpy, or a ``.npy`` / ``.npz`` array."""
    import numpy as np

    ext = Path(file).suffix.lower()
    names = ("phase_map", "pmap", "phase")
    if ext in (".pth", ".pt"):
        obj = _torch_load(file, path, line)
        if isinstance(obj, dict):
            hit = [k for k in names if k in obj]
            if not hit:
                raise LensFileError(f"DOE.phase_map_path: {file!r} holds a dict without a phase map (keys: "
                                    f"{', '.join(map(str, obj)) or 'none'}; expected one of {', '.join(names)})",
                                    path, line)
            obj = obj[hit[0]]
        if not hasattr(obj, "detach"):
            raise LensFileError(f"DOE.phase_map_path: {file!r} holds no tensor (got {type(obj).__name__})",
                                path, line)
        return obj.detach().cpu().double().numpy()
    if ext == ".npy":
        try:
            return np.load(file, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise LensFileError(f"DOE.phase_map_path: cannot read {file!r}: {e}", path, line) from None
    if ext == ".npz":
        try:
            with np.load(file, allow_pickle=False) as z:
                hit = [k for k in names if k in z.files] or (z.files if len(z.files) == 1 else [])
                if not hit:
                    raise LensFileError(f"DOE.phase_map_path: {file!r} holds no array named "
                                        f"{' / '.join(names)} (found: {', '.join(z.files) or 'nothing'})",
                                        path, line)
                return z[hit[0]]
        except (OSError, ValueError) as e:
            raise LensFileError(f"DOE.phase_map_path: cannot read {file!r}: {e}", path, line) from None
    raise LensFileError(f"DOE.phase_map_path: {file!r}: a Pixel2D phase map is read from a .pth / .pt torch "
                        "tensor or a .npy / .npz array", path, line)
