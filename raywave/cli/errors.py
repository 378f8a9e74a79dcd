"""The CLI's user-facing error and argument parsing helpers."""

import math
import sys


class CommandError(Exception):
    """An error to report to the user as one line, without a traceback."""


def report_warnings(caught) -> None:
    """Print recorded warnings (``warnings.catch_warnings(record=True)``) to stderr as ``raywave: warning: …``
    lines, each message once (whitespace folded), DeprecationWarnings left out. Commands call it after they
    succeed: an error exit is one line."""
    seen = set()
    for w in caught:
        msg = " ".join(str(w.message).split())
        if msg not in seen and not issubclass(w.category, DeprecationWarning):
            seen.add(msg)
            print(f"raywave: warning: {msg}", file=sys.stderr)


def number_arg(text: str, flag: str, positive: bool = False, nonneg: bool = False, allow_inf: bool = False) -> float:
    """A command-line number, or a one-line :class:`CommandError` naming the flag."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise CommandError(f"{flag}: {text!r} is not a number") from None
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise CommandError(f"{flag}: {text!r} is not a finite number")
    if positive and not v > 0:
        raise CommandError(f"{flag}: must be > 0, got {text}")
    if nonneg and v < 0:
        raise CommandError(f"{flag}: must be >= 0, got {text}")
    return v


def wavelength_arg(text: str, flag: str = "--wavelength") -> float:
    """A wavelength option (µm), checked by :func:`raywave.utils.checks.wavelength_um`, the one wavelength check of
    every entry point (a number above 100 is named as nanometres); a one-line :class:`CommandError` otherwise."""
    from raywave.utils.checks import wavelength_um

    w = number_arg(text, flag, positive=True)
    try:
        return wavelength_um(w, flag)
    except ValueError as e:
        raise CommandError(str(e)) from None


def pitch_arg(text: str, flag: str) -> float:
    """A pixel-pitch option (mm), checked by :func:`raywave.utils.checks.pitch_mm` (a pitch above 0.1 mm is named
    as µm given as mm); a one-line :class:`CommandError` otherwise."""
    from raywave.utils.checks import pitch_mm

    v = number_arg(text, flag, positive=True)
    try:
        return pitch_mm(v, flag)
    except ValueError as e:
        raise CommandError(str(e)) from None


def integer_arg(text: str, flag: str, minimum: int = 1) -> int:
    """A command-line integer ≥ ``minimum``, or a one-line :class:`CommandError`."""
    try:
        v = int(text)
    except (TypeError, ValueError):
        raise CommandError(f"{flag}: {text!r} is not an integer") from None
    if v < minimum:
        raise CommandError(f"{flag}: must be >= {minimum}, got {v}")
    return v


DEVICE_HELP = ("torch device to compute on: cpu (default), cuda, cuda:N; the PSFs are the same to ~1e-10 "
               "(docs/architecture.md, Devices)")


def device_arg(text: str, flag: str = "--device") -> str:
    """A torch device name (``cpu``, ``cuda``, ``cuda:1``) that this machine has, or a :class:`CommandError`."""
    import torch

    try:
        dev = torch.device(text)
    except (RuntimeError, TypeError, ValueError):
        raise CommandError(f"{flag}: {text!r} is not a torch device (give cpu, cuda or cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise CommandError(f"{flag}: {text!r}: this torch ({torch.__version__}) has no CUDA device; install a CUDA "
                               "build of torch (README, 'Set-up'; torch is pinned to the CPU build) or use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise CommandError(f"{flag}: {text!r}: there are {torch.cuda.device_count()} CUDA devices")
    elif dev.type != "cpu":
        raise CommandError(f"{flag}: {text!r}: raywave runs on cpu and cuda devices")
    return str(dev)


def finite_json(obj, where: str = "output"):
    """``obj`` with every infinite float written as the string ``"inf"`` / ``"-inf"`` (as the lens format does);
    a NaN anywhere is a :class:`CommandError` naming its key (JSON has no NaN or Infinity)."""
    if isinstance(obj, float) or (hasattr(obj, "dtype") and getattr(obj, "ndim", 1) == 0 and hasattr(obj, "item")):
        v = obj.item() if hasattr(obj, "item") else obj
        if isinstance(v, float):
            if math.isnan(v):
                raise CommandError(f"{where} is NaN (not a number): the computation failed for these inputs")
            if math.isinf(v):
                return "inf" if v > 0 else "-inf"
        return v
    if isinstance(obj, dict):
        return {k: finite_json(v, f"{where}.{k}" if where != "output" else str(k)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    return obj


def json_dumps(obj, **kwargs) -> str:
    """``json.dumps`` for everything the CLI prints or writes: strict JSON (never NaN or Infinity, see
    :func:`finite_json`; ``allow_nan=False`` as the last guard)."""
    import json

    return json.dumps(finite_json(obj), allow_nan=False, **kwargs)
