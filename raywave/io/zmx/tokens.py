"""Bytes -> text -> the lines of a .zmx file: decoding, number tokens, the split into system entries and
``SURF`` blocks, and the line being interpreted (per thread, for errors from malformed values)."""

from __future__ import annotations

import math
import re
import threading

from raywave.io.errors import LensFileError
from raywave.io.zmx.tables import IGNORED_SURFACE_KEYS


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


#: A number written with a decimal comma (``1,5168``), as some locales write them; OpticStudio reads it.
_DECIMAL_COMMA = re.compile(r"^[-+]?\d*,\d+(?:[eE][-+]?\d+)?$")


def _float(tok: str, path, line, what) -> float:
    """A number token: INFINITY / INF, a decimal point or a decimal comma (``1,5168``, recorded in
    ``_state.decimal_commas`` for one warning per file); anything else is a line-numbered :class:`LensFileError`."""
    try:
        if tok.upper() in ("INFINITY", "INF"):
            return math.inf
        if tok.upper() in ("-INFINITY", "-INF"):
            return -math.inf
        return float(tok)
    except ValueError:
        if _DECIMAL_COMMA.match(tok):
            _state.decimal_commas.append(line)
            return float(tok.replace(",", "."))
        raise LensFileError(f"{what}: {tok!r} is not a number", path, line) from None


def _int(tok: str, path, line, what, lo: int | None = None, hi: int | None = None) -> int:
    """An integer token (``3`` or ``3.0``) in ``lo..hi``, or a :class:`LensFileError` naming ``what``."""
    v = _float(tok, path, line, what)
    if not (math.isfinite(v) and v == int(v)):
        raise LensFileError(f"{what}: {tok!r} is not an integer", path, line)
    v = int(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"{lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
        raise LensFileError(f"{what}: {v} is out of range {rng}", path, line)
    return v


class _Surf:
    def __init__(self, number: int, line: int, suffix: str = ""):
        self.number = number
        self.line = line
        self.suffix = suffix  # "AS" of "SURF 5AS" (read as surface 5)
        self.entries: list[tuple[int, str, str]] = []


#: ``SURF 5AS``: a surface number with a suffix (OpticStudio reads the number).
_SURF_NUMBER = re.compile(r"^(\d+)([A-Za-z_]*)$")


def _parse_lines(text: str):
    """-> (system entries [(line, key, rest)], surfaces [_Surf]). After ``MNUM`` (the multi-configuration table
    that OpticStudio writes after the surfaces) every unindented line is a system entry."""
    system: list[tuple[int, str, str]] = []
    surfaces: list[_Surf] = []
    in_mce = False
    for ln, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip().lstrip("\ufeff")
        if not s:
            continue
        key, _, rest = s.partition(" ")
        key = key.upper()
        rest = rest.strip()
        if key == "SURF" and not in_mce:
            m = _SURF_NUMBER.match(rest.split()[0]) if rest.split() else None
            if m is None:
                raise LensFileError(f"SURF needs a surface number, got {rest!r}", None, ln)
            surfaces.append(_Surf(int(m.group(1)), ln, m.group(2)))
        elif key == "MNUM" or in_mce:
            in_mce = in_mce or key == "MNUM"
            system.append((ln, key, rest))
        elif surfaces and raw[:1] in (" ", "\t"):
            surfaces[-1].entries.append((ln, key, rest))
        elif surfaces and key in _SURFACE_KEYS:
            # unindented surface key after the surfaces started (hand-written files): still a surface key
            surfaces[-1].entries.append((ln, key, rest))
        else:
            system.append((ln, key, rest))
    return system, surfaces


#: The keys of a SURF block: an unindented one after the surfaces started still belongs to the last surface
#: (hand-written files); any other unindented key there is a system entry (tolerances, merit function rows, ...).
_SURFACE_KEYS = {"TYPE", "CURV", "DISZ", "CONI", "DIAM", "STOP", "COMM", "PARM", "GLAS", "CLAP", "FLAP", "SQAP",
                 "OBDC", "OBSC", "OBSQ", "XDAT", "ELAP", "ELOB", "UDAP", "USAP", "SPID"} | set(IGNORED_SURFACE_KEYS)

class _LineState(threading.local):
    """The line being interpreted, per thread (for errors from malformed values)."""

    def __init__(self):
        self.line = None
        self.decimal_commas: list = []  # lines where a number had a decimal comma


_state = _LineState()
