"""Error types shared by the physics sub-packages, and the memory check (no I/O besides /proc/meminfo).

Every error raywave raises on purpose is a ``ValueError`` subclass whose message names the problem and where
it is (the CLI prints it as one line and exits with status 2). See docs/conventions.md, "Errors".
"""

from __future__ import annotations

import os

__all__ = ["MEMORY_LIMIT_ENV", "MemoryLimitError", "NonFiniteError", "available_memory", "check_allocation",
           "format_bytes", "memory_limit", "parse_bytes"]


class NonFiniteError(ValueError):
    """A computation produced NaN or infinite values from inputs that were accepted (e.g. a DOE phase model
    whose phase overflows float64 on its grid); the message names the quantity and the input to change."""


class MemoryLimitError(ValueError):
    """An array that would not fit in memory was about to be allocated; the message gives the size needed,
    the memory available and the setting to change."""


def format_bytes(n: float) -> str:
    """``1.5e9`` -> ``"1.4 GiB"``."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{n:.0f} B"
        n /= 1024
    return f"{n:.3g} PiB"  # pragma: no cover


def available_memory() -> int | None:
    """Bytes of memory available to new allocations (MemAvailable of /proc/meminfo, else physical pages from
    ``os.sysconf``), or None when neither is known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


#: The environment variable that caps the memory raywave may plan to use (bytes, or with a unit: ``8G``, ``512MiB``);
#: ``raywave --memory-limit SIZE`` sets it for one command. Unset: the memory available on the device.
MEMORY_LIMIT_ENV = "RAYWAVE_MEMORY_LIMIT"

_UNITS = {"": 1, "b": 1, "k": 1024, "kb": 1000, "kib": 1024, "m": 1024**2, "mb": 1000**2, "mib": 1024**2,
          "g": 1024**3, "gb": 1000**3, "gib": 1024**3, "t": 1024**4, "tb": 1000**4, "tib": 1024**4}


def parse_bytes(text) -> int:
    """``"8G"``, ``"512MiB"``, ``"1.5e9"`` -> bytes (K/M/G/T and KiB/MiB/GiB/TiB: powers of 1024; KB/MB/GB/TB:
    powers of 1000); a ValueError for anything else or a size <= 0."""
    import re

    m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*([A-Za-z]*)\s*", str(text))
    unit = m.group(2).lower() if m else None
    try:
        value = float(m.group(1)) if m else float("nan")
    except ValueError:
        value = float("nan")
    if unit not in _UNITS or not (value > 0 and value != float("inf")):
        raise ValueError(f"{text!r} is not a memory size (give bytes or a number with K, M, G or T, e.g. 8G)")
    return int(value * _UNITS[unit])


def memory_limit() -> int | None:
    """The configured memory limit (bytes) from :data:`MEMORY_LIMIT_ENV`, or None when unset."""
    text = os.environ.get(MEMORY_LIMIT_ENV, "").strip()
    if not text:
        return None
    try:
        return parse_bytes(text)
    except ValueError as e:
        raise ValueError(f"{MEMORY_LIMIT_ENV}: {e}") from None


def check_allocation(nbytes: float, what: str, knob: str, device=None, fraction: float = 0.8) -> None:
    """Raise :class:`MemoryLimitError` when ``nbytes`` (an estimate, bytes) exceeds ``fraction`` of the memory
    available on ``device`` (CPU: :func:`available_memory`; CUDA: the device's free memory), or the limit set by
    :data:`MEMORY_LIMIT_ENV` (``raywave --memory-limit``) when that is smaller. The one memory estimate every
    allocation that scales with user input goes through, before the work starts.

    Args: ``what`` names the array (e.g. "the 1e6×1e6 DOE simulation grid"), ``knob`` the setting that shrinks it
    (e.g. "raise the DOE pitch or lower oversample")."""
    avail = None
    dev = str(device) if device is not None else "cpu"
    if dev.startswith("cuda"):
        try:
            import torch

            avail = int(torch.cuda.mem_get_info(device)[0])
        except Exception:  # noqa: BLE001 - no CUDA: fall back to host memory
            avail = None
    if avail is None:
        avail = available_memory()
    if avail is None:
        avail = 1 << 50  # unknown: only refuse what no machine has (1 PiB)
    budget, where = fraction * avail, f"is available{' on ' + dev if dev != 'cpu' else ''}"
    limit = memory_limit()
    if limit is not None and limit < budget:
        budget, avail, where = limit, limit, f"is allowed ({MEMORY_LIMIT_ENV} / raywave --memory-limit)"
    if not nbytes <= budget:
        raise MemoryLimitError(f"{what} needs about {format_bytes(nbytes)} of memory, but only {format_bytes(avail)} "
                               f"{where}: {knob}")
