"""Glass codes: a glass given by its d-line index and Abbe number written as digits.

* ``NNNVVV`` (the international six-digit code, MIL-G-174): nd = 1.NNN, vd = VV.V (``517642``: 1.517, 64.2);
* ``NNNVVV.DDD`` (SCHOTT's nine-digit code, DDD the density): the same nd and vd, the density ignored;
* ``NNNNNN.VVVVVV`` (CODE V's fine code, six digits after the point): nd = 1.NNNNNN, vd = VV.VVVV
  (``517000.520000``: nd 1.517000, vd 52.0000).

A code never gives vd = 0: a code whose Abbe digits are all zero is an error naming it.
"""

from __future__ import annotations

import re

_SIX = re.compile(r"(\d{3})(\d{3})")
_NINE = re.compile(r"(\d{3})(\d{3})\.(\d{3})")
_FINE = re.compile(r"(\d{6})\.(\d{4,})")


def parse_glass_code(text: str) -> tuple[float, float] | None:
    """``(nd, vd)`` of a glass code (see the module docstring), or None when ``text`` is not one.

    Raises ValueError for a code with vd = 0 (all Abbe digits zero)."""
    t = str(text).strip().strip("'\"")
    m = _SIX.fullmatch(t) or _NINE.fullmatch(t)
    if m:
        nd, vd = 1.0 + int(m.group(1)) / 1000.0, int(m.group(2)) / 10.0
    else:
        m = _FINE.fullmatch(t)
        if not m:
            return None
        nd, vd = 1.0 + int(m.group(1)) / 1e6, float("0." + m.group(2)) * 100.0
    if not vd > 0:
        raise ValueError(f"glass code {t!r}: Abbe number vd = 0 (its Abbe digits are zero): not a glass code "
                         "raywave can read (NNNVVV, NNNVVV.DDD or CODE V's NNNNNN.VVVVVV)")
    return nd, vd
