"""A DOE placed at a surface of a raywave JSON lens (issue 46): the surface's ``"doe"`` key.

``"doe"`` on a surface (or a list of them) is a DOE plane ``distance`` mm after that surface's vertex, inside the
gap to the next surface (``0 <= distance < thickness``), with the keys of the top-level ``"doe"`` section
(``pitch``, ``size`` / ``shape``, ``aperture``, ``phase`` / ``phase_model``, ``design_wavelength``, ``material``,
``levels``, ``wrap``; docs/lens-format.md). ``"conformal": true`` (and no ``distance``) puts the DOE on the
surface itself instead: its phase on the surface's sag, refracting in the same step (a DOE on a curved substrate;
the surface must refract). The top-level ``"doe"`` stays the DOE before the sensor. Built by
:func:`raywave.assembly.midsystem.midsystem_from_spec`.
"""

from __future__ import annotations

from raywave.io.doe import validate_doe


class _AtSurface:
    """The schema validator, with the key paths of :func:`raywave.io.doe.validate_doe` (``("doe", ...)``) moved
    under the surface's ``("surfaces", i, "doe"[, j])``."""

    def __init__(self, v, prefix: tuple):
        self._v, self._prefix = v, prefix

    def __getattr__(self, name):
        f = getattr(self._v, name)
        if not callable(f):
            return f

        def call(*args, **kw):
            args = tuple(self._prefix + a[1:] if isinstance(a, tuple) and a[:1] == ("doe",) else a for a in args)
            return f(*args, **kw)

        return call


def is_conformal(doe: dict) -> bool:
    """Whether a surface DOE object sits on the surface itself (``"conformal": true``)."""
    return isinstance(doe, dict) and doe.get("conformal") is True


def without_conformal(doe: dict) -> dict:
    """A conformal surface DOE object as the top-level section's keys (``conformal`` dropped, ``distance`` 0):
    what :func:`raywave.io.doe.validate_doe` and :func:`raywave.io.doe.resolve_doe` read."""
    out = {k: v for k, v in doe.items() if k != "conformal"}
    out.setdefault("distance", 0.0)
    return out


def surface_does(s: dict) -> list:
    """The DOE objects of a surface spec's ``"doe"`` (none, one object or a list), as a list."""
    d = s.get("doe")
    if d is None:
        return []
    return list(d) if isinstance(d, list) else [d]


def validate_surface_doe(v, s: dict, path: tuple) -> None:
    """Check the ``"doe"`` of the surface ``s`` at key path ``path`` with the validator ``v`` (every DOE's keys as
    the top-level section's; its ``distance`` inside the gap after the surface)."""
    d = s.get("doe")
    if d is None:
        return
    items = [(d, path + ("doe",))] if not isinstance(d, list) else [(x, path + ("doe", j)) for j, x in enumerate(d)]
    if isinstance(d, list) and not d:
        v.err(path + ("doe",), "an empty list: give a DOE object, a list of them, or leave the key out")
    gap = {"surfaces": [{"thickness": s.get("thickness")}]}  # the distance's limit: this surface's thickness
    for doe, p in items:
        if isinstance(doe, dict) and "conformal" in doe:
            if not isinstance(doe["conformal"], bool):
                v.err(p + ("conformal",), f"must be true or false, got {doe['conformal']!r}")
            elif doe["conformal"]:
                if "distance" in doe:
                    v.err(p + ("distance",), "a conformal DOE sits on the surface itself: leave 'distance' out")
                doe = without_conformal(doe)
            else:
                doe = {k: x for k, x in doe.items() if k != "conformal"}
        validate_doe(_AtSurface(v, p), doe, gap)
