"""raywave against Optiland 0.6.3 on one real .zmx file (issue 44): EFL, BFL, F/#, entrance and exit pupil (z and
diameter) and the real chief ray's image intercept at the largest field, as relative differences.

Optiland reads the file with its own .zmx reader. It reads it *faithfully* when it models the same prescription:
the same surfaces and thicknesses (raywave reads configuration 1 of a zoom; Optiland the thicknesses as written)
and a system aperture it reads as OpticStudio does. Both tools then see the same media: Optiland's glasses are
replaced by constant indices equal to raywave's at the primary wavelength (catalog editions differ, and Optiland
models a ``___BLANK`` model glass with another dispersion formula); its asphere Newton iterations are tightened to
1e-15 (default 1e-10). Corrections where Optiland 0.6.3 reads a file unlike OpticStudio (as
tests/test_zmx_corpus.py): FLOA (float by stop size) and a file with no aperture line take the stop's DIAM as the
stop *diameter* (OpticStudio: semi-diameter), so Optiland gets 2·DIAM.

The chief ray is raywave's (aimed at the centre of the stop at the primary wavelength; for an image-height field,
the one solved to land at that height): its object-space start and direction are traced through Optiland's
surfaces and the image intercepts compared. A lens with an even asphere's r² term (a2 ≠ 0) has only its chief
ray compared: raywave's paraxial model includes that term's power, Optiland's leaves it out. Optiland's own chief ray for an image-height field is aimed at the
paraxial entrance pupil instead (no ray aiming), a different ray.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

QUANTITIES = ("efl", "bfl", "fnum", "ep_z", "epd", "xp_z", "xpd", "chief_y")


class NotFaithful(Exception):
    """Optiland does not read the file (or not as raywave and OpticStudio do): not compared, with the reason."""


def _s(x) -> float:
    return float(np.asarray(x).ravel()[0])


def _rel(a: float, b: float, scale: float = 0.0) -> float:
    den = max(abs(a), abs(b), scale)
    return 0.0 if den == 0.0 else abs(a - b) / den


def optiland_model(path: str, lens):
    """Optiland's model of ``path`` with raywave's indices; raises :class:`NotFaithful` with the reason."""
    from optiland.fileio.zemax.reader.converter import ZemaxToOpticConverter
    from optiland.fileio.zemax.reader.parser import ZemaxDataParser
    from optiland.materials import IdealMaterial

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            data = ZemaxDataParser(str(path)).parse()
            o = ZemaxToOpticConverter(data).convert()
        except Exception as err:  # noqa: BLE001 - Optiland's refusal is a reason not to compare
            raise NotFaithful(f"Optiland refuses it: {type(err).__name__}: {str(err)[:120]}") from None
    inner = o.surfaces.surfaces[1:-1]
    if len(inner) != len(lens.surfaces):
        raise NotFaithful(f"Optiland has {len(inner)} surfaces, raywave {len(lens.surfaces)}")
    for k, (a, b) in enumerate(zip(lens.surfaces, inner)):
        if (a.interaction.kind == "reflection") != bool(getattr(b.interaction_model, "is_reflective", False)):
            raise NotFaithful("a mirror in one and a refraction in the other (raywave reads a model glass of index -1, "
                              "an old file's way of writing a reflection, as a mirror)")
    ours = [float(s.thickness.detach()) for s in lens.surfaces]
    theirs = [_s(o.surfaces.surfaces[k + 2].geometry.cs.z) - _s(o.surfaces.surfaces[k + 1].geometry.cs.z)
              for k in range(len(inner))]
    if any(abs(a - b) > 1e-9 * max(1.0, abs(a)) for a, b in zip(ours, theirs)):
        raise NotFaithful("thicknesses differ (raywave reads configuration 1 of a multi-configuration file)")
    wl = lens.primary_wavelength
    n = [float(m.detach()) for m in lens.indices(torch.tensor(wl, dtype=torch.float64))]
    if abs(n[0] - 1.0) > 0 and not lens.object_material.is_air:
        raise NotFaithful("object space in a medium")
    for k, surf in enumerate(inner):
        surf.material_post = IdealMaterial(n[k + 1])
        g = surf.geometry
        if hasattr(g, "tol"):
            g.tol, g.max_iter = 1e-15, 200
    o.wavelengths.wavelengths = []
    o.wavelengths.add(wl, is_primary=True)
    ap = getattr(data, "aperture", None) or {}
    if lens.system_aperture is None or ap.get("floating_stop"):  # Optiland: DIAM read as the stop diameter
        o.set_aperture("float_by_stop_size", 2.0 * lens.stop_radius())
    elif "paraxialImageFNO" in ap:  # Optiland: the image-space F/#; OpticStudio: the paraxial working F/#
        raise NotFaithful("FNUM v 1 (paraxial working F/#) read by Optiland as the image-space F/#")
    return o


def _where_optiland_leaves(o, lens, rec) -> str:
    """Where Optiland's real trace (its last one, of raywave's chief ray) leaves raywave's (``rec``, raywave's
    TraceRecord of the same ray), and why, in words (surfaces numbered as in the file: the object is 0)."""
    ol = np.asarray(o.surfaces.y, dtype=float).ravel()  # the ray's height after each lens surface, then the image
    rw = [float(p[1].reshape(-1)[0]) for p in rec.points[1:]]
    k = next((i for i, (a, b) in enumerate(zip(rw, ol)) if not abs(a - b) <= 1e-6 * max(1.0, abs(a))), None)
    if k is None or k >= len(lens.surfaces):
        return "NaN"
    here = f"at surface {k + 1} Optiland's ray lands at y = {ol[k]:.6g} mm, raywave's at {rw[k]:.6g} mm"
    surf, prev = lens.surfaces[k], lens.surfaces[k - 1] if k > 0 else None
    same = (prev is not None and float(prev.thickness.detach()) == 0.0 and surf.kind == prev.kind == "standard"
            and float(surf.geometry.curvature.detach()) == float(prev.geometry.curvature.detach()))
    if same:
        return (f"{here}: surface {k + 1} coincides with surface {k} (zero thickness, the same curvature: one "
                "interface written twice) and Optiland's sphere intersection takes the far crossing for a ray that "
                "starts on it (raywave: the crossing where the ray stands, t = 0); NaN after")
    conic = float(getattr(surf.geometry, "conic", torch.zeros(())).detach().reshape(-1)[0])
    if surf.kind == "even_asphere" and conic == -1.0:
        gap = float(prev.thickness.detach()) if prev is not None else math.nan
        return (f"{here}: an even asphere on a paraboloid (conic -1), {gap:g} mm behind surface {k} (a hybrid "
                "aspheric layer); Optiland's asphere intersection converges to another crossing of it, a jump the "
                "ray's direction cannot make in that gap; NaN after")
    return f"{here}; NaN after"


def compare(path: str, lens) -> dict:
    """{quantity: relative difference} of raywave's ``lens`` (read from ``path``) against Optiland's model."""
    from optiland.rays import RealRays

    from raywave.lens.sources import chief_ray

    o = optiland_model(path, lens)
    p = lens.paraxial()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f2, F2 = _s(o.paraxial.f2()), _s(o.paraxial.F2())
        epd, epl = _s(o.paraxial.EPD()), _s(o.paraxial.EPL())
        xpl, xpd = _s(o.paraxial.XPL()), abs(_s(o.paraxial.XPD()))
    theirs = {"f2 (EFL)": f2, "F2 (BFL)": F2, "EPD": epd, "EPL (entrance pupil z)": epl, "XPL (exit pupil z)": xpl,
              "XPD": xpd}
    bad = [k for k, v in theirs.items() if not math.isfinite(v)]
    if bad:
        raise NotFaithful(f"a non-finite value from Optiland's paraxial trace ({', '.join(bad)})")
    last_t = float(lens.surfaces[-1].thickness.detach())
    total = lens.total_track()
    scale = max(1.0, abs(total))  # positions along z: relative to the lens's length
    out = {"efl": _rel(p.efl, f2), "bfl": _rel(p.bfl, F2 + last_t, scale), "fnum": _rel(p.fnum, abs(f2) / epd),
           "ep_z": _rel(p.ep_z, epl, scale), "epd": _rel(p.epd, epd), "xp_z": _rel(p.xp_z, total + xpl, scale),
           "xpd": _rel(p.xpd, xpd)}
    if any(float(getattr(s.geometry, "coefficients", torch.zeros(1))[0].detach()) != 0.0 and s.kind == "even_asphere"
           for s in lens.surfaces):
        # an even asphere's r² term (a2): raywave's paraxial model includes its power (c + 2 a2), Optiland's uses
        # the base radius only, so the paraxial quantities differ by definition; the real chief ray is compared
        out = {}
    fmax = max(lens.fields, key=abs)
    wl = lens.primary_wavelength
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cr = chief_ray(lens, (0.0, fmax), [wl])
        img, rec = lens.trace_to_image(cr, record=True)
    if not bool(img.valid.all()):
        raise NotFaithful(f"raywave's chief ray at field {fmax:g} is vignetted")
    oo, dd = cr.o[0, 0, 0].numpy(), cr.d[0, 0, 0].numpy()
    rays = RealRays(*(np.array([v]) for v in (*oo, *dd)), np.ones(1), np.full(1, wl))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o.surfaces.trace(rays, skip=1)
    y_ol = _s(rays.y)
    y_rw = float(img.o[0, 0, 0, 1])
    out["chief_y"] = _rel(y_rw, y_ol, 1e-3 * max(1.0, p.epd))
    if not math.isfinite(y_ol):
        kind = ("beyond 90°, from behind the first vertex" if lens.field_type == "angle" and abs(fmax) >= 90.0
                else "below 90°")
        raise NotFaithful(f"a non-finite value from Optiland's real trace of raywave's chief ray ({kind}; raywave "
                          f"traces it to the image): {_where_optiland_leaves(o, lens, rec)}")
    if not all(math.isfinite(v) for v in out.values()):
        bad = ", ".join(k for k, v in out.items() if not math.isfinite(v))
        raise NotFaithful(f"a non-finite value from raywave ({bad})")
    return out
