"""The CLI's user-facing error and argument parsing helpers."""

import math


class CommandError(Exception):
    """An error to report to the user as one line, without a traceback."""


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


def integer_arg(text: str, flag: str, minimum: int = 1) -> int:
    """A command-line integer ≥ ``minimum``, or a one-line :class:`CommandError`."""
    try:
        v = int(text)
    except (TypeError, ValueError):
        raise CommandError(f"{flag}: {text!r} is not an integer") from None
    if v < minimum:
        raise CommandError(f"{flag}: must be >= {minimum}, got {v}")
    return v
