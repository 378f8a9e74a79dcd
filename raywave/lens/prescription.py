"""The lens prescription: one row per surface (radius, thickness, glass, semi-diameter, conic, aspheric terms, the
stop marked), as OpticStudio's Lens Data Editor or optiland's ``lens.info()``; and the paraxial power of a
BINARY_2 DOE (a lens file's ``doe.phase_model``) with the EFL of the lens and DOE together.

``Lens.table()`` and ``repr(lens)`` print :func:`format_table`; ``raywave info`` prints it under the paraxial table.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch

#: pupil rim samples per source for the computed semi-diameters
_RIM_SAMPLES = 36


@dataclass
class SurfaceRow:
    """One surface of the prescription (lengths mm; ``radius`` inf for a plane; ``semi_diameter`` the clear
    aperture when the surface has one (``fixed``), else the largest ray height of the lens's fields and wavelengths
    through the full pupil (None when it could not be traced); ``terms``: aspheric / toroidal / paraxial / coordinate
    break parameters by name)."""

    index: int
    kind: str
    radius: float
    thickness: float
    glass: str
    semi_diameter: float | None
    fixed: bool
    conic: float
    stop: bool
    terms: dict = field(default_factory=dict)
    comment: str = ""


def _f(t) -> float:
    return float(t.detach()) if isinstance(t, torch.Tensor) else float(t)


def _terms(surface) -> dict:
    """The surface's parameters beyond radius and conic, by name (only the non-zero ones)."""
    g, inter, kind = surface.geometry, surface.interaction, surface.kind
    out = {}
    if kind == "paraxial":
        out["focal_length"] = _f(inter.focal_length)
    elif kind == "coordinate_break":
        for k in ("decenter_x", "decenter_y", "tilt_x", "tilt_y", "tilt_z"):
            if getattr(inter, k) != 0.0:
                out[k] = float(getattr(inter, k))
    if kind == "toroidal":
        c_r = _f(g.rotation_curvature)
        out["radius_x"] = math.inf if c_r == 0 else 1.0 / c_r
    coeffs = getattr(g, "coefficients", None)
    if coeffs is not None:
        c = coeffs.detach().reshape(-1).tolist()
        powers = [i + 1 for i in range(len(c))] if kind == "odd_asphere" else [2 * i + 2 for i in range(len(c))]
        prefix = "b" if kind == "odd_asphere" else "a"
        out.update({f"{prefix}{p}": v for p, v in zip(powers, c) if v != 0.0})
    if inter.kind == "diffraction":
        out["diffraction_order"] = float(inter.order)
    return out


def rays_beyond_semi_diameters(lens, tol: float = 1e-3) -> list[tuple[int, float, float]]:
    """The surfaces whose semi-diameter (without an aperture of their own: it does not clip) the lens's own fields'
    rim rays pass beyond by more than ``tol`` of it: ``[(surface index, largest ray height mm, semi-diameter mm)]``
    (:func:`ray_heights`, the primary wavelength; empty where none does or the trace fails)."""
    heights = ray_heights(lens, lens.primary_wavelength)
    if heights is None:
        return []
    out = []
    for i, (s, h) in enumerate(zip(lens.surfaces, heights)):
        sd = s.semi_diameter
        if s.aperture is None and sd is not None and math.isfinite(sd) and sd > 0 and h > sd * (1 + tol):
            out.append((i, float(h), float(sd)))
    return out


def ray_heights(lens, wavelength=None, fields=None) -> list[float] | None:
    """Largest ray height (mm, in each surface's own frame) per surface of the lens's fields (along y, and on
    axis; ``fields``: these y fields instead) at every wavelength through the full pupil rim (aimed rays, without
    autograd); None when the trace fails (e.g. a lens whose field cannot be aimed) and for a folded lens (its
    record is in global coordinates)."""
    if lens.is_folded:
        return None
    from raywave.lens.sources import VignettingWarning, point_source_rays

    t = torch.linspace(0, 2 * math.pi, _RIM_SAMPLES + 1, dtype=torch.float64, device=lens.device)[:-1]
    px, py = torch.cat([t.new_zeros(1), torch.cos(t)]), torch.cat([t.new_zeros(1), torch.sin(t)])
    fields = sorted({0.0, *(float(f) for f in lens.fields)} if fields is None else {float(f) for f in fields})
    pts = torch.tensor([[0.0, f] for f in fields], dtype=torch.float64, device=lens.device)
    wls = lens.wavelengths if wavelength is None else [float(wavelength)]
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # vignetted sources: their rays are left out (valid mask)
            rays = point_source_rays(lens, pts, wls, pupil=(px, py), aim="full")
            _, rec = lens.trace(rays, record=True)
    except (ValueError, RuntimeError, NotImplementedError):
        return None
    heights = []
    for i in range(len(lens.surfaces)):
        x, y, _ = rec.points[i + 1]  # points[0]: where the rays start
        v = rec.valid[i + 1] & torch.isfinite(x) & torch.isfinite(y)
        r = torch.sqrt(x * x + y * y)
        heights.append(float(r[v].max()) if bool(v.any()) else math.nan)
    return heights


def surface_table(lens, wavelength: float | None = None, semi_diameters: bool = True) -> list[SurfaceRow]:
    """The prescription of ``lens``: one :class:`SurfaceRow` per surface. ``semi_diameters``: compute the
    semi-diameters of surfaces without a clear aperture from a trace (:func:`ray_heights`; else None)."""
    heights = ray_heights(lens, wavelength) if semi_diameters else None
    rows = []
    for i, s in enumerate(lens.surfaces):
        c = _f(s.geometry.curvature) if hasattr(s.geometry, "curvature") else 0.0
        clear = s.clear_radius()
        sd = clear if clear is not None else (heights[i] if heights is not None else None)
        if sd is not None and not math.isfinite(sd):
            sd = None
        glass = "MIRROR" if s.interaction.kind == "reflection" else s.material.name
        rows.append(SurfaceRow(i, s.kind, math.inf if c == 0 else 1.0 / c, _f(s.thickness), glass,
                               None if sd is None else float(sd), clear is not None,
                               _f(getattr(s.geometry, "conic", 0.0)), bool(s.is_stop), _terms(s), s.comment))
    return rows


def _num(v: float, width: int, prec: int = 6) -> str:
    if v is None:
        return f"{'-':>{width}s}"
    if math.isinf(v):
        return f"{'inf' if v > 0 else '-inf':>{width}s}"
    return f"{v:>{width}.{prec}g}"


def format_table(lens, rows: list[SurfaceRow]) -> str:
    """The prescription as text: a header line, one line per surface (``STO`` marks the stop, ``*`` a semi-diameter
    fixed by a clear aperture, the others are the ray heights), then the aspheric and other terms."""
    obj = "infinity" if math.isinf(lens.object_distance) else f"{lens.object_distance:g} mm"
    lines = [f"{lens.name or 'lens'}: {len(rows)} surfaces, object at {obj}, stop surface {lens.stop_index} "
             f"(lengths mm; semi-diameter: * clear aperture, else the traced beam)",
             f"  {'surf':>4s} {'type':<16s} {'radius':>12s} {'thickness':>12s} {'glass':<14s} {'semi-diam':>11s} "
             f"{'conic':>10s}"]
    for r in rows:
        tag = "STO" if r.stop else f"{r.index:>4d}"
        sd = _num(r.semi_diameter, 10, 5) + ("*" if r.fixed else " ")
        lines.append(f"  {tag:>4s} {r.kind:<16s} {_num(r.radius, 12, 7)} {_num(r.thickness, 12, 7)} "
                     f"{r.glass[:14]:<14s} {sd} {_num(r.conic, 10, 5)}")
    lines.append(f"  {'IMA':>4s} {'(image plane)':<16s} {'inf':>12s}")
    extra = [r for r in rows if r.terms]
    for r in extra:
        lines.append(f"  surface {r.index} ({r.kind}): " + ", ".join(f"{k} = {v:.6g}" for k, v in r.terms.items()))
    return "\n".join(lines)


def table(lens, wavelength: float | None = None) -> str:
    """:func:`format_table` of :func:`surface_table`."""
    return format_table(lens, surface_table(lens, wavelength))


# ---------------------------------------------------------------------------- DOE power
@dataclass
class DOEPower:
    """The paraxial power of a lens file's BINARY_2 DOE at one wavelength: ``power`` (1/mm, positive converges),
    the DOE's own ``focal_length`` (mm, inf for no power), and ``efl`` (mm) of the refractive lens and the DOE
    together (paraxial, the DOE ``distance`` mm after the last surface in the image-space medium)."""

    wavelength: float
    power: float
    focal_length: float
    efl: float
    distance: float


def binary2_power(phase_model: dict, wavelength: float) -> float:
    """Paraxial power (1/mm) at ``wavelength`` (µm) of a BINARY_2 phase φ = M Σ A_i (r/R)^(2i) (rad; OpticStudio's
    convention, M the diffraction order, R the normalisation radius mm): φ ≈ M A_1 r²/R² = −π r²/(λ f), so the power
    1/f = −M A_1 λ / (π R²) (λ in mm; a negative A_1 converges)."""
    coeffs = phase_model.get("coefficients") or [0.0]
    m, norm = float(phase_model.get("order", 1.0)), float(phase_model["norm_radius"])
    return -m * float(coeffs[0]) * wavelength * 1e-3 / (math.pi * norm * norm)


def doe_power(lens, doe_spec: dict, wavelength: float | None = None) -> DOEPower | None:
    """The paraxial power of the ``doe_spec`` (a lens spec's ``"doe"`` section) of ``lens`` and the EFL of both
    together, at ``wavelength`` µm (default the primary); None when the DOE has no BINARY_2 ``phase_model`` (a
    phase map: no paraxial power is defined), the DOE a thin element ``distance`` mm after the last vertex."""
    model = doe_spec.get("phase_model")
    if not model or model.get("type") != "binary_2":
        return None
    wl = lens.primary_wavelength if wavelength is None else float(wavelength)
    p = lens.paraxial(wl)
    power = binary2_power(model, wl)
    d = float(doe_spec.get("distance", 0.0))
    n = float(lens.surfaces[-1].material.n(torch.tensor([wl], dtype=torch.float64))[0])
    # a ray from infinity at height 1 leaves with reduced slope nu = −1/EFL and meets the DOE plane (d mm after the
    # last vertex, the focus BFL mm after it, in the medium n) at y = (BFL − d)/(n EFL); the DOE adds −y·power to nu
    efl, bfl = float(p.efl), float(p.bfl)
    y_doe = (bfl - d) / (n * efl) if math.isfinite(efl) else 1.0
    nu = (-1.0 / efl if math.isfinite(efl) else 0.0) - y_doe * power
    efl_total = math.inf if nu == 0 else -1.0 / nu
    return DOEPower(wl, power, math.inf if power == 0 else 1.0 / power, efl_total, d)
