"""Helpers shared by the lens-file formats: the canonical form of a spec, radius <-> curvature."""

from __future__ import annotations

import math

from raywave.io.doe import doe_canonical
from raywave.io.json_format import FORMAT_NAME, FORMAT_VERSION, UNITS

#: Wavelengths (µm) used when a spec gives none: F, d, C lines, primary d (as raywave.lens.build).
DEFAULT_WAVELENGTHS = {"values": [0.4861327, 0.5875618, 0.6562725], "primary": 1}


def radius_from_curvature(c: float):
    """The radius to write for curvature ``c``: "inf" for 0, else the float ``r`` with ``1/r == c``
    exactly and the shortest decimal form (so 1/22.01359 gives back 22.01359); None if no float
    within a few ulps of ``1/c`` inverts exactly to ``c`` (then keep the curvature)."""
    c = float(c)
    if c == 0.0:
        return "inf"
    r = 1.0 / c
    cands = [r]
    lo = hi = r
    for _ in range(4):
        lo = math.nextafter(lo, -math.inf)
        hi = math.nextafter(hi, math.inf)
        cands += [lo, hi]
    good = [x for x in cands if math.isfinite(x) and 1.0 / x == c]
    if not good:
        return None
    return min(good, key=lambda x: (len(repr(x)), abs(x - r)))


def curvature_of(s: dict) -> float:
    """Curvature (1/mm) of a standard / even-asphere surface spec."""
    if "curvature" in s:
        return float(s["curvature"])
    r = s.get("radius", "inf")
    if r == "inf":
        return 0.0
    return 1.0 / float(r)


def shape_entry(c: float) -> dict:
    """``{"radius": r}`` when a radius stores ``c`` exactly, else ``{"curvature": c}``."""
    r = radius_from_curvature(c)
    return {"curvature": float(c)} if r is None else {"radius": r}


def aspheric_canonical(asph: dict | None, powers=range(2, 21, 2)) -> dict:
    """a2..a_max (``powers``: a1..a8 for odd aspheres) with missing lower terms as 0.0 and trailing zero terms
    dropped ({} if all zero)."""
    asph = asph or {}
    powers = list(powers)
    vals = [float(asph.get(f"a{p}", 0.0)) for p in powers]
    while vals and vals[-1] == 0.0:
        vals.pop()
    return {f"a{p}": v for p, v in zip(powers, vals)}


#: Powers of the "aspheric" terms of each surface type.
ASPHERIC_POWERS = {"even_asphere": range(2, 481, 2), "odd_asphere": range(1, 241), "toroidal": range(2, 15, 2)}


def rotation_radius_canonical(r):
    """A toroid's radius of rotation: "inf" (also for None or 0, as OpticStudio reads 0), else a float."""
    if r is None or r == "inf" or r == 0 or (isinstance(r, float) and math.isinf(r)):
        return "inf"
    return float(r)


def system_aperture_canonical(ap):
    """``{kind: float}``, or None for no system aperture / float by stop size (the two are the same lens)."""
    if not ap or ap.get("float_by_stop_size"):
        return None
    (kind, value), = ap.items()
    return {kind: float(value)}


def material_canonical(m):
    if m is None:
        return "air"
    if isinstance(m, str):
        if m.strip().lower() == "mirror":
            return "mirror"
        return "air" if m.strip().lower() == "air" else m
    if "index" in m:
        return {"index": float(m["index"])}
    if "model" in m:
        return {"model": {"nd": float(m["model"]["nd"]), "vd": float(m["model"]["vd"])}}
    return dict(m)


def aperture_canonical(a):
    if a is None:
        return None
    if a["shape"] == "circle":
        out = {"shape": "circle", "radius": float(a["radius"])}
        if a.get("fixed"):
            out["fixed"] = True
        return out
    return {"shape": "square", "half_width": float(a["half_width"])}


def resized_stop_aperture(surfaces: list) -> int | None:
    """The index of the stop surface (marked, else the first that is not a coordinate break) when its aperture is a
    plain circle (no ``fixed``, decentre or obscuration) that a system aperture resizes entirely (the same lens as no
    aperture there), else None."""
    stops = [i for i, s in enumerate(surfaces) if s.get("stop")]
    i = stops[0] if stops else next((j for j, s in enumerate(surfaces) if s.get("type") != "coordinate_break"), None)
    a = surfaces[i].get("aperture") if i is not None else None
    plain = isinstance(a, dict) and a.get("shape") == "circle" and not (a.get("fixed") or a.get("obscuration")
                                                                          or any(a.get("decenter") or []))
    return i if plain else None


def surface_canonical(s: dict) -> dict:
    kind = s.get("type", "standard")
    out: dict = {"type": kind}
    if kind == "coordinate_break":
        out["decenter"] = [float(v) for v in s.get("decenter", [0.0, 0.0])]
        out["tilt"] = [float(v) for v in s.get("tilt", [0.0, 0.0, 0.0])]
        out["order"] = int(s.get("order", 0))
        out["thickness"] = float(s["thickness"])
        if s.get("comment"):
            out["comment"] = s["comment"]
        return out
    if kind == "paraxial":
        out["focal_length"] = float(s["focal_length"])
    else:
        out.update(shape_entry(curvature_of(s)))
        out["conic"] = float(s.get("conic", 0.0))
        if kind == "toroidal":
            out["radius_of_rotation"] = rotation_radius_canonical(s.get("radius_of_rotation"))
        if kind in ASPHERIC_POWERS:
            out["aspheric"] = aspheric_canonical(s.get("aspheric"), ASPHERIC_POWERS[kind])
    out["thickness"] = float(s["thickness"])
    out["material"] = material_canonical(s.get("material", "air"))
    out["aperture"] = aperture_canonical(s.get("aperture"))
    if s.get("semi_diameter") is not None:
        out["semi_diameter"] = float(s["semi_diameter"])
    out["stop"] = bool(s.get("stop", False))
    if s.get("comment"):
        out["comment"] = s["comment"]
    return out


def canonical_spec(spec: dict) -> dict:
    """The spec with every default written out, in the form the importers (.zmx, DeepLens) produce.

    Numbers become floats (except sensor resolution and the primary index), radii are written as the
    shortest float that inverts exactly to the curvature, aspheric terms are a2..a_max without trailing
    zeros, "air" materials are the string "air". ``canonical_spec(s)`` builds the same lens as ``s``.
    """
    out: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    for k in ("name", "description"):
        if spec.get(k):
            out[k] = spec[k]
    if spec.get("catalogs"):
        out["catalogs"] = list(spec["catalogs"])
    d = (spec.get("object") or {}).get("distance", "inf")
    out["object"] = {"distance": "inf" if d == "inf" else float(d)}
    obj = spec.get("object") or {}
    if material_canonical(obj.get("material")) != "air":
        out["object"]["material"] = material_canonical(obj["material"])
    if obj.get("curvature"):
        out["object"]["curvature"] = float(obj["curvature"])
    if (spec.get("image") or {}).get("curvature"):
        out["image"] = {"curvature": float(spec["image"]["curvature"])}
    ap = system_aperture_canonical(spec.get("system_aperture"))
    if ap is not None:
        out["system_aperture"] = ap
    f = spec.get("fields") or {"type": "angle", "values": [0.0]}
    out["fields"] = {"type": f.get("type", "angle"), "values": [float(v) for v in f["values"]]}
    w = spec.get("wavelengths") or DEFAULT_WAVELENGTHS
    out["wavelengths"] = {"values": [float(v) for v in w["values"]], "primary": int(w.get("primary", 0))}
    if spec.get("sensor"):
        s = spec["sensor"]
        out["sensor"] = {"size": [float(v) for v in s["size"]]}
        if s.get("resolution") is not None:
            out["sensor"]["resolution"] = [int(v) for v in s["resolution"]]
    out["surfaces"] = [surface_canonical(s) for s in spec["surfaces"]]
    if ap is not None:
        i = resized_stop_aperture(spec["surfaces"])
        if i is not None:  # the system aperture sizes it: the same lens as no aperture there
            out["surfaces"][i]["aperture"] = None
    if spec.get("doe") is not None:
        out["doe"] = doe_canonical(spec["doe"])
    return out
