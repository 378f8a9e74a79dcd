"""Bytes -> text -> the lines of a .zmx file: decoding, number tokens, the split into system entries and
``SURF`` blocks, and the line being interpreted (per thread, for errors from malformed values)."""

from __future__ import annotations

import math
import threading

from raywave.io.errors import LensFileError


def decode_zmx_bytes(raw: bytes) -> tuple[str, str]:
    """(text, encoding name) of a .zmx file: UTF-16 by BOM or NUL bytes, else UTF-8, else Latin-1."""
    if raw.startswith(b"\xff\xfe"):
        return raw[2:].decode("utf-16-le"), "utf-16-le"
    if raw.startswith(b"\xfe\xff"):
        return raw[2:].decode("utf-16-be"), "utf-16-be"
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8"), "utf-8"
    head = raw[:400]
    if b"\x00" in head:
        even_nuls = head[0::2].count(0)
        odd_nuls = head[1::2].count(0)
        enc = "utf-16-le" if odd_nuls >= even_nuls else "utf-16-be"
        return raw.decode(enc, errors="replace"), enc
    try:
        return raw.decode("utf-8"), "utf-8"
    except UnicodeDecodeError:
        return raw.decode("latin-1"), "latin-1"


def _float(tok: str, path, line, what) -> float:
    try:
        if tok.upper() in ("INFINITY", "INF"):
            return math.inf
        if tok.upper() in ("-INFINITY", "-INF"):
            return -math.inf
        return float(tok)
    except ValueError:
        raise LensFileError(f"{what}: {tok!r} is not a number", path, line) from None


def _int(tok: str, path, line, what, lo: int | None = None, hi: int | None = None) -> int:
    """An integer token (``3`` or ``3.0``) in ``lo..hi``, or a :class:`LensFileError` naming ``what``."""
    try:
        v = float(tok)
    except ValueError:
        raise LensFileError(f"{what}: {tok!r} is not a number", path, line) from None
    if not (math.isfinite(v) and v == int(v)):
        raise LensFileError(f"{what}: {tok!r} is not an integer", path, line)
    v = int(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"{lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
        raise LensFileError(f"{what}: {v} is out of range {rng}", path, line)
    return v


class _Surf:
    def __init__(self, number: int, line: int):
        self.number = number
        self.line = line
        self.entries: list[tuple[int, str, str]] = []


def _parse_lines(text: str):
    """-> (system entries [(line, key, rest)], surfaces [_Surf])."""
    system: list[tuple[int, str, str]] = []
    surfaces: list[_Surf] = []
    for ln, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip().lstrip("\ufeff")
        if not s:
            continue
        key, _, rest = s.partition(" ")
        key = key.upper()
        rest = rest.strip()
        if key == "SURF":
            try:
                n = int(rest.split()[0])
            except (ValueError, IndexError):
                raise LensFileError(f"SURF needs a surface number, got {rest!r}", None, ln) from None
            surfaces.append(_Surf(n, ln))
        elif surfaces and raw[:1] in (" ", "\t"):
            surfaces[-1].entries.append((ln, key, rest))
        elif surfaces and key not in _SYSTEM_KEYS_AFTER_SURFACES:
            # unindented key after the surfaces started (hand-written files): still a surface key
            surfaces[-1].entries.append((ln, key, rest))
        else:
            system.append((ln, key, rest))
    return system, surfaces


#: System keys that may appear after the SURF blocks (OpticStudio writes some there).
_SYSTEM_KEYS_AFTER_SURFACES = {"TOL", "TOLE", "MNUM", "MOFF", "BLNK", "CONF", "NSCD", "COFN", "VERS"}

class _LineState(threading.local):
    """The line being interpreted, per thread (for errors from malformed values)."""

    def __init__(self):
        self.line = None


_state = _LineState()
