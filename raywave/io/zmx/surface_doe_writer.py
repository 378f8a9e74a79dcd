"""The diffractive .zmx surfaces that a spec's DOEs become (the writer's side of
:mod:`raywave.io.zmx.diffractive`): a ``binary_2`` phase model → ``BINARY_2`` (PARM 0 = order M, XDAT 1 = N,
XDAT 2 = normalisation radius R in mm, XDAT 3.. = A_i in rad on (r/R)^(2i)), a ``grating`` at ±90° (or a blank DOE)
→ ``DGRATING`` (PARM 1 = T lines per µm, PARM 2 = order ±1: the inverse of
:func:`raywave.io.zmx.diffractive._grating_phase`).

A DOE inside the lens (a surface's ``"doe"``, issue 46) is written where :func:`raywave.io.zmx.reader.read_zmx` reads
it back (:func:`raywave.io.zmx.diffractive.doe_inside`): on the surface itself when the reader gives back the same
DOE there (a plane STANDARD surface with the DOE 0 mm after it, whose clear aperture, else semi-diameter, is the
DOE's size; or a conformal DOE on a STANDARD surface: its curvature and conic), else on a plane of its own
(``GLAS`` the medium after the surface, ``DISZ`` the rest of the gap) ``distance`` mm after the surface: the
read-back lens has one more (plane) surface there, the same lens. What a .zmx cannot hold is listed for the
writer's :class:`~raywave.io.errors.LensFileWarning` (:func:`surface_doe_plan`)."""

from __future__ import annotations

import math

from raywave.io.errors import LensFileError
from raywave.io.spec import curvature_of
from raywave.io.surface_doe import is_conformal, surface_does
from raywave.io.zmx.diffractive import _surface_aperture_size
from raywave.io.zmx.tables import MAX_BINARY2_TERMS

#: DOE keys a .zmx surface does not store (the grid's pixels and the fabrication data), as the writer names them.
UNSTORED_DOE_KEYS = ("pitch", "shape", "design_wavelength", "material", "levels", "wrap")


def _num(x) -> str:
    return repr(float(x))


def doe_extras(doe: dict) -> list[str]:
    """The keys of ``doe`` that a .zmx diffractive surface does not store (:data:`UNSTORED_DOE_KEYS`, and an
    ``oversample`` other than 1)."""
    extra = [k for k in UNSTORED_DOE_KEYS if doe.get(k)]
    if doe.get("oversample", 1) != 1:
        extra.append("oversample")
    return extra


def zemax_type(doe: dict) -> tuple[str | None, str | None]:
    """``(Zemax type, None)`` of the diffractive surface that holds ``doe``'s phase (BINARY_2 for a ``binary_2``
    model; DGRATING for a ``grating`` at ±90° or a blank DOE), or ``(None, why not)``."""
    model = doe.get("phase_model")
    if doe.get("phase") is not None:
        return None, "a phase map: only binary_2 and grating phase models are written"
    if model is None:
        return "DGRATING", None  # a blank DOE: a grating of 0 lines per µm (read back as a blank DOE)
    if model["type"] == "binary_2":
        return "BINARY_2", None
    if model["type"] == "grating":
        angle = float(model.get("angle", 0.0))
        if angle % 360.0 not in (90.0, 270.0):
            return None, (f"a grating at {angle:g}°: a DGRATING's rulings run along its x axis, so it diffracts "
                          "along y only (90° or -90°)")
        return "DGRATING", None
    return None, f"a {model['type']} phase model: only binary_2 (BINARY_2) and grating (DGRATING) ones are written"


def grating_lines_per_um(period: float) -> float:
    """The DGRATING line density T (lines per µm, PARM 1) that :func:`raywave.io.zmx.diffractive._grating_phase`
    reads back (with order ±1) as ``period`` mm, ``1 / |T · 1e3|``: exactly where a float T does (always for a
    period read from a .zmx file), else the T whose period is nearest (within an ulp)."""
    t0 = 1e-3 / period
    cands, up, down = [t0], t0, t0
    for _ in range(4):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, 0.0)
        cands += [up, down]
    return min(cands, key=lambda t: abs(1.0 / (t * 1e3) - period))


def phase_lines(w, doe: dict, where: str, source) -> None:
    """The PARM / XDAT lines of ``doe``'s diffractive surface (its type: :func:`zemax_type`) through ``w``."""
    model = doe.get("phase_model")
    if model is not None and model["type"] == "binary_2":
        coeffs = [float(c) for c in model["coefficients"]]
        if len(coeffs) > MAX_BINARY2_TERMS:
            raise LensFileError(f"{where}.phase_model: a .zmx BINARY_2 surface holds at most {MAX_BINARY2_TERMS} "
                                f"terms, got {len(coeffs)}", source)
        w(f"  PARM 0 {_num(model.get('order', 1.0))}")
        for j in range(1, 9):
            w(f"  PARM {j} 0.0")
        for j, v in enumerate([float(len(coeffs)), float(model["norm_radius"])] + coeffs, start=1):
            w(f'  XDAT {j} {_num(v)} 0 0 1 0 0 ""')
        return
    if model is None:  # blank
        w("  PARM 1 0.0")
        w("  PARM 2 1.0")
        return
    # φ = 2π y sinθ / period, θ = ±90°: M T = ±1e-3 / period lines per µm (the reader's angle: the sign of M T)
    w(f"  PARM 1 {_num(grating_lines_per_um(float(model['period'])))}")
    w(f"  PARM 2 {_num(1.0 if math.sin(math.radians(float(model.get('angle', 0.0)))) > 0 else -1.0)}")


def doe_aperture_lines(w, doe: dict) -> bool:
    """``CLAP 0 r`` (a circle in a square grid) or ``SQAP hx hy`` (a square aperture) from ``doe``'s size, which
    the reader reads back as that aperture and size; False (nothing written) for a circle in a rectangular grid
    and for a DOE without a size."""
    size = doe.get("size")
    if size is None:
        return doe.get("aperture", "square") == "square"
    if doe.get("aperture", "square") == "circle":
        if float(size[0]) != float(size[1]):
            return False
        w(f"  CLAP 0 {_num(0.5 * float(size[0]))} 0")
    else:
        w(f"  SQAP {_num(0.5 * float(size[0]))} {_num(0.5 * float(size[1]))}")
    return True


def read_back_grid(s: dict, resized: bool) -> dict:
    """``aperture`` (and ``size``) that the reader gives a DOE on the written surface ``s`` (the surface's clear
    aperture, none where the writer leaves a resized stop's out, else its semi-diameter as a circle)."""
    grid = _surface_aperture_size({"aperture": None if resized else s.get("aperture")})
    diam = s.get("semi_diameter")
    if "size" not in grid and diam is not None and float(diam) > 0:
        grid = {"aperture": "circle", "size": [2.0 * float(diam), 2.0 * float(diam)]}
    return grid


def _same_grid(doe: dict, grid: dict) -> bool:
    size = doe.get("size")
    return (doe.get("aperture", "square") == grid["aperture"]
            and (None if size is None else [float(v) for v in size]) == grid.get("size"))


def surface_doe_plan(surfaces: list, resized: int | None, last_doe: float | None, source):
    """``(plan, lost)``: where each written DOE inside the lens goes, and what is left out.

    ``plan``: spec surface index → ``(own, planes)``: ``own`` the DOE written on the surface itself (None), and
    ``planes`` ``[(distance mm, doe)]`` the DOE planes written after it, in order. ``resized``: the index of the
    stop whose aperture the writer leaves out; ``last_doe``: the distance (mm, along z) of the DOE before the sensor
    when it is written after the last surface (the surface DOEs there must lie before it). ``lost``: phrases
    naming each DOE left out (its phase, where it sits) and each written DOE's keys that are not stored."""
    plan: dict[int, tuple] = {}
    lost: list[str] = []
    for i, s in enumerate(surfaces):
        does = surface_does(s)
        if not does:
            continue
        kind = s.get("type", "standard")
        mat = s.get("material", "air")
        mirror = isinstance(mat, str) and mat.lower() == "mirror"
        own, planes = None, []
        for j, doe in enumerate(does):
            where = f"surfaces[{i}].doe" + (f"[{j}]" if isinstance(s["doe"], list) else "")
            why = zemax_type(doe)[1]
            if why is None and (kind == "coordinate_break" or mirror):
                why = (f"on a {'mirror' if mirror else 'coordinate break'}: the reader takes a diffractive surface "
                       "inside the lens for a refracting one")
            if why is None and is_conformal(doe) and kind != "standard":
                why = (f"conformal on a {kind} surface: a BINARY_2 / DGRATING inside the lens is read as a "
                       "spherical / conic (STANDARD) surface")
            if why is None and is_conformal(doe) and own is not None:
                why = "a second DOE on the surface itself"
            if why is None and not is_conformal(doe) and last_doe is not None and i == len(surfaces) - 1 \
                    and not float(doe["distance"]) < last_doe:
                why = "at or after the DOE before the sensor"
            if why is not None:
                lost.append(f"{where} ({why})")
                continue
            if is_conformal(doe):
                own = (where, doe)
            else:
                planes.append((float(doe["distance"]), where, doe))
        planes.sort(key=lambda p: p[0])
        plane_surface = kind == "standard" and curvature_of(s) == 0.0
        grid = read_back_grid(s, resized == i)
        if own is None and planes and planes[0][0] == 0.0 and plane_surface and _same_grid(planes[0][2], grid):
            own = planes.pop(0)[1:]  # the plane surface itself is the DOE 0 mm after it
        if own is not None and is_conformal(own[1]) and not _same_grid(own[1], grid):
            lost.append(f"{own[0]}'s {'size and aperture' if own[1].get('size') else 'aperture'} (read back as the "
                        f"surface's: {grid['aperture']}{', ' + str(grid['size']) + ' mm' if 'size' in grid else ''})")
        if own is not None and plane_surface and not planes and not float(s["thickness"]) > 0 \
                and not (last_doe is not None and i == len(surfaces) - 1 and last_doe > 0):
            lost.append(f"{own[0]} (on a plane with thickness {s['thickness']!r}: a diffractive plane inside the "
                        "lens needs DISZ > 0)")
            own = None
        kept, prev = [], (0.0 if own is not None and plane_surface else None)
        for d, where, doe in planes:
            if prev is not None and not d > prev:  # a diffractive plane inside the lens needs DISZ > 0
                lost.append(f"{where} (at the same place as another DOE of the surface)")
                continue
            if not doe_aperture_lines(lambda line: None, doe):
                lost.append(f"{where}'s aperture ({doe.get('aperture')} without a square size: no CLAP / SQAP)")
            kept.append((d, where, doe))
            prev = d
        for where, doe in ([own] if own is not None else []) + [p[1:] for p in kept]:
            extra = doe_extras(doe)
            if extra:
                lost.append(f"{where}'s {', '.join(extra)}")
        plan[i] = (None if own is None else own[1], [(d, doe) for d, _, doe in kept])
    return plan, lost
