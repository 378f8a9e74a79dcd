"""Errors and warnings of the lens-file readers and writers."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class LensFileError(ValueError):
    """A lens file (or spec dict) that raywave cannot read or write.

    The message always starts with where the problem is: ``path:line: message`` when the line is
    known, ``path: message`` otherwise (``path`` is ``"<spec>"`` for an in-memory spec). When a file has
    several problems they are all reported, one per line of the message; ``errors`` holds them as
    ``(line, message)`` pairs (``line`` may be None).

    Attributes:
        path: the file (str) or ``"<spec>"``.
        line: 1-based line of the first problem, or None.
        column: 1-based column of the first problem, or None.
        reason: the first problem's message without the location prefix.
        errors: every problem found, as ``(line, message)`` pairs.
    """

    def __init__(self, message: str, path=None, line: int | None = None, column: int | None = None,
                 errors: Iterable[tuple[int | None, str]] | None = None):
        self.path = "<spec>" if path is None else str(path)
        self.line = line
        self.column = column
        self.reason = message
        self.errors = list(errors) if errors is not None else [(line, message)]
        lines = [self._format(line, message, column)]
        for ln, msg in self.errors[1:]:
            lines.append(self._format(ln, msg))
        super().__init__("\n".join(lines))

    def _format(self, line, message, column=None) -> str:
        if line is None:
            return f"{self.path}: {message}"
        if column is not None:
            return f"{self.path}:{line}:{column}: {message}"
        return f"{self.path}:{line}: {message}"

    @classmethod
    def collect(cls, errors: list[tuple[int | None, str]], path) -> "LensFileError":
        """One error reporting every ``(line, message)`` of ``errors`` (first one first)."""
        line, message = errors[0]
        return cls(message, path, line, errors=errors)

    def __reduce__(self):  # picklable despite the keyword arguments
        return (type(self), (self.reason, self.path, self.line, self.column, self.errors))


class LensFileWarning(UserWarning):
    """Something in a lens file that raywave ignores, or information a format cannot store."""


def suggestion(word: str, choices: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``choices``, or ``""``."""
    choices = list(choices)
    close = difflib.get_close_matches(word, choices, n=1, cutoff=0.6)
    if not close:
        lowered = {c.lower(): c for c in choices}
        if word.lower() in lowered:
            close = [lowered[word.lower()]]
    return f" (did you mean {close[0]!r}?)" if close else ""


def with_location(err: Exception, path) -> Exception:
    """``err`` with its message prefixed by ``path: `` (unless it names the file already), same type: errors
    raised while building a lens from a file's spec (overlapping surfaces, an unknown glass) name the file."""
    where = str(path)
    if isinstance(err, LensFileError) or where in str(err) or not err.args or not isinstance(err.args[0], str):
        return err
    err.args = (f"{where}: {err.args[0]}",) + tuple(err.args[1:])
    return err
