"""The aperture entries of a .zmx ``SURF`` block -> the spec's ``"aperture"`` (mm).

OpticStudio's aperture types, as written in a .zmx file (one per surface; ``OBDC dx dy`` decentres it):

* ``CLAP rmin rmax``: circular aperture; rmin > 0 is an annulus (a circle with a central circular obscuration, a
  spider-free central obscuration);
* ``FLAP rmin rmax``: floating aperture: a circle at the semi-diameter (DIAM), rmin > 0 as for CLAP;
* ``SQAP hx hy``: rectangular aperture of half widths hx, hy (a square when they are equal);
* ``OBSC rmin rmax``: circular obscuration: blocks rmin <= r <= rmax (rmin = 0: a central disc; rmin > 0: an
  annular obscuration, a ring with light inside and outside it);
* ``OBSQ hx hy``: rectangular obscuration;
* ``OBDC dx dy``: the aperture's decentre: it moves the clear region and any obscuration together (an obscuration
  alone, OBSC / OBSQ: the obscuration).
"""

from __future__ import annotations

from raywave.io.errors import LensFileError
from raywave.io.zmx.tokens import _float

APERTURE_KEYS = ("CLAP", "FLAP", "SQAP", "OBDC", "OBSC", "OBSQ")


def _values(toks: list, key: str, where: str, path, ln: int) -> list[float]:
    return [_float(t, path, ln, f"{where}: {key}") for t in toks[:2]]


def _pair(vals: list[float]) -> tuple[float, float]:
    """(min, max) of a CLAP / FLAP / OBSC entry: one value is the max (min 0)."""
    if not vals:
        return 0.0, 0.0
    return (0.0, vals[0]) if len(vals) == 1 else (vals[0], vals[1])


def _half_widths(vals: list[float], key: str, where: str, path, ln: int) -> tuple[float, float]:
    if not vals:
        raise LensFileError(f"{where}: {key} needs half widths", path, ln)
    hx = vals[0]
    hy = vals[1] if len(vals) > 1 else hx
    return hx, hy


def surface_aperture(p: dict, where: str, ln: int, key: str, rest: str, path, scale: float) -> None:
    """Read one aperture entry (line ``ln``: ``key rest``) of a SURF block into the parsed surface ``p`` (radii and
    half widths scaled to mm by ``scale``). A FLAP is kept as ``("FLAP", line, rmin mm)`` until the block's DIAM is
    known (:func:`finish_aperture`); an OBDC as ``p["ap_decenter"]``."""
    toks = rest.split()
    vals = _values(toks, key, where, path, ln)
    if key in ("CLAP", "FLAP"):
        rmin, rmax = _pair(vals)
        if key == "FLAP" and rmax == 0.0:
            if not rmin >= 0.0:
                raise LensFileError(f"{where}: FLAP minimum radius {rmin} must be >= 0", path, ln)
            p["aperture"] = ("FLAP", ln, rmin * scale)  # resolved from DIAM by finish_aperture
            return
        if not rmax > 0:
            raise LensFileError(f"{where}: empty aperture ({key} radius {rmax})", path, ln)
        if not 0.0 <= rmin < rmax:
            raise LensFileError(f"{where}: {key} minimum radius {rmin} must be >= 0 and < the maximum radius "
                                f"{rmax}", path, ln)
        p["aperture"] = {"shape": "circle", "radius": rmax * scale}
        if rmin > 0.0:  # an annular clear aperture: a central circular obscuration of radius rmin
            p["aperture"]["obscuration"] = {"shape": "circle", "radius": rmin * scale}
    elif key == "OBSC":
        rmin, rmax = _pair(vals)
        if not rmax > 0:
            raise LensFileError(f"{where}: empty obscuration (OBSC radius {rmax})", path, ln)
        if not 0.0 <= rmin < rmax:
            raise LensFileError(f"{where}: OBSC minimum radius {rmin} must be >= 0 and < the maximum radius {rmax}",
                                path, ln)
        obs = {"shape": "circle", "radius": rmax * scale} if rmin == 0.0 else \
            {"shape": "annulus", "inner_radius": rmin * scale, "radius": rmax * scale}
        p["aperture"] = {"shape": "none", "obscuration": obs}
    elif key == "OBSQ":
        hx, hy = _half_widths(vals, key, where, path, ln)
        if not (hx > 0 and hy > 0):
            raise LensFileError(f"{where}: empty obscuration (OBSQ half widths {hx} x {hy})", path, ln)
        p["aperture"] = {"shape": "none", "obscuration": {"shape": "rectangle", "half_width_x": hx * scale,
                                                          "half_width_y": hy * scale}}
    elif key == "SQAP":
        hx, hy = _half_widths(vals, key, where, path, ln)
        if not (hx > 0 and hy > 0):
            raise LensFileError(f"{where}: empty aperture (SQAP half widths {hx} x {hy})", path, ln)
        p["aperture"] = {"shape": "square", "half_width": hx * scale} if hx == hy else \
            {"shape": "rectangle", "half_width_x": hx * scale, "half_width_y": hy * scale}
    elif key == "OBDC":  # applied once the whole block is read (the aperture may come after it)
        if any(v != 0.0 for v in vals):
            p["ap_decenter"] = ([v * scale for v in vals] + [0.0])[:2], rest.strip(), ln
    else:
        raise ValueError(f"not an aperture key: {key}")


def finish_aperture(p: dict, where: str, path) -> None:
    """Once a SURF block is read: a FLAP becomes a circle at the semi-diameter (DIAM), and the OBDC decentre is
    applied (to the aperture; to its obscuration when the aperture is an obscuration alone)."""
    ap = p["aperture"]
    if isinstance(ap, tuple):  # FLAP: floating aperture at the semi-diameter
        _, ln, rmin = ap
        if p["diam"] is None:
            raise LensFileError(f"{where}: floating aperture without a semi-diameter (DIAM)", path, ln)
        ap = p["aperture"] = {"shape": "circle", "radius": p["diam"]}
        p["floating_aperture"] = True  # follows the semi-diameter (a configuration's SDIA)
        if rmin > 0.0:
            if not rmin < p["diam"]:
                raise LensFileError(f"{where}: FLAP minimum radius {rmin} mm is not inside the semi-diameter "
                                    f"{p['diam']} mm", path, ln)
            ap["obscuration"] = {"shape": "circle", "radius": rmin}
    if "ap_decenter" not in p:
        return
    d, rest, ln = p.pop("ap_decenter")
    if not isinstance(ap, dict):
        # OBDC with no aperture: OpticStudio keeps it for when an aperture is given; nothing to move
        return
    if ap["shape"] == "none":
        ap["obscuration"]["decenter"] = d
    else:
        ap["decenter"] = d
