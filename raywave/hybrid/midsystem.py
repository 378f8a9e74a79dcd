"""A DOE inside the lens (issue 46): a thin DOE plane between two surfaces of the sequential lens.

Method (docs/ray-wave.md, "A DOE inside the lens"). The fabricated DOE's transmission at λ is
``exp(i α Q(φ0))``: ``φ0`` its unwrapped design phase at λ0, ``Q`` the wrap to [0, 2π) and the L-level staircase
(identity for a continuous DOE), ``α = φ(λ)/φ(λ0)`` its dispersion. Being periodic in ``φ0``, it is a sum of
diffraction orders, ``exp(i α Q(φ0)) = Σ_m c_m exp(i m φ0)``, with the staircase's Fourier coefficients ``c_m``
(:func:`order_coefficients`; ``|c_m|²`` is :func:`raywave.doe.staircase_efficiency`). Every order is a smooth
phase ``m φ0``; it enters the lens as a thin phase surface (:class:`~raywave.surfaces.Diffraction`, the local
grating: exact for a thin phase screen in the ray limit) and the engine's accurate mode carries it through the
surfaces after it to a blank DOE plane near the sensor (:class:`~raywave.hybrid.HybridLens` unchanged, ray → field
→ band-limited angular spectrum → sensor). The orders' fields meet there coherently: each one's absolute phase is
fixed by its chief ray's optical path (:func:`_absolute_phase`; with the exact edge, whose fields carry the stop's
edge waves inside the beam, by its rays' paths over the pupil: :func:`_pupil_phase`), their envelopes are put on
the reference order's carrier and summed with ``c_m`` before the one propagation to the sensor. With the exact edge
the weaker orders' stop edges are formed for the PSF crop's centre (:class:`_CropRims`).

A continuous DOE is one order with the phase ``α φ0`` and ``c = 1``. The DOE's phase map is read from its pixels
(the design phase × ``phase_scale``), unwrapped by phasor differences (so a wrapped pixel map is read as its
smooth phase) and interpolated by cubic convolution (C¹, exact for quadratics) for the rays
(:class:`DOEPhaseSurface`). What it leaves out: the DOE pixels' flat steps (a sample-and-hold multiplies the
order's amplitude by ``sinc(p ∂φ/∂x / 2π) sinc(p ∂φ/∂y / 2π)``; :func:`sampling_report` gives its worst value
and warns past 1 %), and orders below ``min_efficiency``. Differentiable in the DOE's parameters and the lens's
(the split thickness included).
"""

from __future__ import annotations

import cmath
import copy
import math
import warnings
from collections import OrderedDict
from dataclasses import dataclass

import torch
from torch import nn

from raywave.rays.pupil import rim_and_grid
from raywave.doe.base import DOE, BlankDOE
from raywave.hybrid.coherent.exit_pupil import (MAX_XP_SAMPLES, SPHERE_TOL, _beam_fits, _edge_method,
                                                defocus_mismatch, edge_focus_many)
from raywave.hybrid.coherent.record import CausticWarning, DOEField, SamplingWarning
from raywave.hybrid.coherent.stop_edge import RimImages
from raywave.hybrid.coherent.tracing import per_source
from raywave.hybrid.hybrid_lens import HybridLens, PSFResult
from raywave.lens.lens import Lens
from raywave.lens.sources import VignettingWarning, chief_ray, point_source_rays, rays_through
from raywave.rays.bundle import RayBundle
from raywave.surfaces.aperture import CircularAperture, SquareAperture
from raywave.surfaces.geometry import Plane
from raywave.surfaces.interaction import Diffraction
from raywave.surfaces.surface import Surface
from raywave.wave.grid import Field

__all__ = ["DOEClipWarning", "DOEPhaseSurface", "MidSystemLens", "MidSystemPSFResult", "cull_orders",
           "order_coefficients", "sampling_report", "insert_doe", "tail_envelope"]

_TWO_PI = 2.0 * math.pi

#: a DOE-pixel step of the order's phase beyond this (rad) is refused: the map no longer tells its gradient
MAX_STEP = 0.5 * math.pi
#: the pixels' flat steps (sample-and-hold) may cost this much of an order's amplitude before a warning
PIXEL_LOSS_WARN = 0.01
#: ``MidSystemLens(stop_edge=...)``: "auto" (the default) chooses per source between the sharp cut on the engine's
#: plane ("doe") and the exit-pupil edge ("exit_pupil") by :meth:`MidSystemLens.cut_estimates`
MID_STOP_EDGES = ("auto", "doe", "exit_pupil")
#: ``stop_edge="auto"``: the cut on the engine's plane is kept while the wave near the stop's edge is a sphere to
#: this many waves (:func:`~raywave.hybrid.coherent.exit_pupil.edge_aberration`; 2× the engine's
#: :data:`~raywave.hybrid.coherent.exit_pupil.SPHERE_TOL`: a guard against an aberrated wave whose edge rays' focus
#: happens to lie on the sensor, e.g. the Cooke triplet on axis, 0.56 waves, its cut 1.8e-2 off); the sweep's cases
#: that hold reach 0.0103 waves (the Fresnel DOE at 3°: the cut 9.4e-4 / 9.7e-4, the exact edge 1.5e-3 along y) ...
CUT_SPHERE_TOL = 2 * SPHERE_TOL
#: ... and its edge rays' focus lies on the sensor to within this Fresnel-scaling mismatch (waves,
#: :func:`~raywave.hybrid.coherent.exit_pupil.defocus_mismatch` of the edge rays' focus, the sensor and the engine's
#: plane: how much a sharp cut's focal field depends on the plane where it cuts). Calibrated on issue 46's sweep
#: (benchmarks/midsystem_sweep.py, 32 × 32 crops of 2 µm, the cut against the wave reference): every Fresnel / blank
#: case up to 3.17e-6 is within 9.7e-4 (the test system 2.59e-6, 9.0e-4), from 3.59e-6 on 1.05e-3 … 9.3e-3 (the exact
#: edge 2.1e-4 … 6.1e-4 there)
CUT_MISMATCH_TOL = 3.0e-6
#: ``stop_edge="auto"``, where the cut fails: the exit-pupil edge's Fresnel step (cheaper than the exact one for a
#: wide beam) is taken where the engine's error estimate (:func:`~raywave.hybrid.coherent.exit_pupil.
#: fresnel_step_estimates`) holds with the edge's Fresnel zone at most this fraction of the rim curve's radius of
#: curvature on the engine's plane (the engine's own bar is 0.3), else the exact step. The bundled asphere with a
#: DOE at its stop, 0.09–0.096 (0°–9°): the Fresnel step 0.9e-4 – 1.4e-4 from the exact one at 1/7 of its time; the
#: two-lens sweep's failing cases 0.15 – 0.31, where the Fresnel step reads 6.8e-4 (F/8, 0.15), 5.3e-4 (f 20 mm,
#: 0.26) but 1.26e-3 (the DOE near A, 0.26) and costs up to 16× the exact step (f 20 mm)
MID_FRESNEL_CURVATURE = 0.12


def dispersion_alpha(doe: DOE, wavelength: float) -> float:
    """``α = φ(λ)/φ(λ0)`` of ``doe``'s dispersion model at ``wavelength`` µm (1 for ``"none"``)."""
    r = doe.dispersion_ratio(wavelength)
    return 1.0 if r is None else float(r.detach()) if isinstance(r, torch.Tensor) else float(r)


def order_coefficients(levels: int | None, wrapped: bool, alpha: float, orders) -> dict:
    """Complex amplitude ``c_m`` of diffraction order ``m`` of ``exp(i α Q(φ0)) = Σ c_m exp(i m φ0)``.

    ``Q``: the wrap to [0, 2π) (``wrapped``) and, with ``levels`` L, rounding to the nearest of the levels 2πk/L
    (:func:`raywave.doe.phase_levels`: level k covers φ0 ∈ [2π(k − ½)/L, 2π(k + ½)/L)), so
    ``c_m = sinc(m/L) (1/L) Σ_k exp(i2πk(α − m)/L)``; a kinoform (no levels): ``c_m = e^{iπ(α−m)} sinc(α − m)``.
    ``orders``: iterable of integers. Returns ``{m: complex}``."""
    out = {}
    for m in orders:
        m = int(m)
        if levels is not None:
            L = int(levels)
            s = sum(cmath.exp(1j * _TWO_PI * k * (alpha - m) / L) for k in range(L)) / L
            out[m] = complex(_sinc(m / L) * s)
        elif wrapped:
            out[m] = complex(cmath.exp(1j * math.pi * (alpha - m)) * _sinc(alpha - m))
        else:
            raise ValueError("order_coefficients: a continuous (unwrapped) DOE has one order (its phase α·φ0)")
    return out


def _sinc(x: float) -> float:
    return 1.0 if x == 0 else math.sin(math.pi * x) / (math.pi * x)


def doe_orders(doe: DOE, wavelength: float, min_efficiency: float = 1e-3, max_order: int = 64) -> list:
    """The orders of ``doe`` at ``wavelength`` µm as ``[(scale, c)]``: the phase surface carries ``scale·φ0``
    and the order's field is multiplied by the complex ``c``; a continuous DOE gives ``[(α, 1)]``, a fabricated one
    every order ``|m| ≤ max_order`` with ``|c_m|² ≥ min_efficiency``, strongest first."""
    alpha = dispersion_alpha(doe, wavelength)
    if not doe.wrap and doe.quant_levels is None:
        return [(alpha, 1.0 + 0j)]
    cs = order_coefficients(doe.quant_levels, doe.wrap, alpha, range(-max_order, max_order + 1))
    keep = [(float(m), c) for m, c in cs.items() if abs(c) ** 2 >= min_efficiency]
    if not keep:
        raise ValueError(f"no diffraction order of the DOE carries {min_efficiency:g} of the light at {wavelength:g} "
                         "µm: lower min_efficiency")
    return sorted(keep, key=lambda t: -abs(t[1]))


def _unwrapped(phase: torch.Tensor) -> torch.Tensor:
    """``phase`` (ny, nx) rad unwrapped by phasor differences (each step taken in (−π, π]): along the first column,
    then along every row; ``phase`` itself where no step passes ±π (a DOE's design phase, unwrapped already: no
    cumulative sum's rounding, and a fifth of the cost). Differentiable (the steps' gradient is the identity's)."""
    dc, dr = phase[1:, :1] - phase[:-1, :1], phase[:, 1:] - phase[:, :-1]
    kc, kr = torch.round(dc.detach() / _TWO_PI), torch.round(dr.detach() / _TWO_PI)
    if not (bool(kc.any()) or bool(kr.any())):  # no step of 2π (a design phase, already unwrapped): as it is
        return phase
    col = torch.cat([phase[:1, :1], phase[:1, :1] + torch.cumsum(dc - _TWO_PI * kc, 0)], 0)
    rows = torch.cumsum(dr - _TWO_PI * kr, 1)
    return torch.cat([col, col + rows], 1)


def _keys_rows(t: torch.Tensor) -> torch.Tensor:
    """:func:`_keys` as one (..., 2, 4) tensor: the weights of the taps −1 … 2 at fractions ``t`` (...) (row 0) and
    their derivatives (row 1), by the same expressions (the same values, bit for bit)."""
    t2, t3 = t * t, t * t * t
    return torch.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2, (t3 - t2) / 2,
                        (-3 * t2 + 4 * t - 1) / 2, (9 * t2 - 10 * t) / 2, (-9 * t2 + 8 * t + 1) / 2,
                        (3 * t2 - 2 * t) / 2], -1).reshape(t.shape + (2, 4))


def _cubic_taps(pm: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """The 4×4 taps of the padded map ``pm`` (ny + 4, nx + 4) around the index points ``u``, ``v`` (N,) (columns,
    rows; detached) and the points' cells: ``(vals (N, 4, 4) [rows, columns], iu (N,), iv (N,))``."""
    ny, nx = pm.shape[0] - 4, pm.shape[1] - 4
    iu = torch.floor(u).clamp(1, nx + 1)  # the 4 taps iu−1 … iu+2 stay inside the padded map
    iv = torch.floor(v).clamp(1, ny + 1)
    w = nx + 4
    off = (torch.arange(-1, 3, device=u.device)[:, None] * w + torch.arange(-1, 3, device=u.device)).reshape(-1)
    at = iv.long() * w + iu.long()
    return pm.reshape(-1).take(at[:, None] + off).reshape(-1, 4, 4), iu, iv


def _cubic_eval(pm: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``out`` (N, 2, 2), ``out[n, a, b] = ∂^a_v ∂^b_u φ`` (a, b ≤ 1, index units) of the Keys interpolant of ``pm``
    at ``u``, ``v`` (N,) (no autograd), as two batched products ``(rows · vals) · cols`` (rows (N, 2, 4): the row
    weights and their derivatives; cols (N, 4, 2): the columns'): the order in which :func:`_cubic_autograd`'s
    ``einsum("nij,ni,nj->n")`` contracts, so its values bit for bit, the three from one gather and one pair of
    products."""
    vals, iu, iv = _cubic_taps(pm, u, v)
    k = _keys_rows(torch.stack([u - iu, v - iv]))
    return torch.bmm(torch.bmm(k[1], vals), k[0].transpose(1, 2))


def _keys(t: torch.Tensor):
    """Keys cubic-convolution weights (a = −½) for offsets −1, 0, 1, 2 at fractions ``t`` and their derivatives."""
    t2, t3 = t * t, t * t * t
    w = torch.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2, (t3 - t2) / 2], -1)
    dw = torch.stack([(-3 * t2 + 4 * t - 1) / 2, (9 * t2 - 10 * t) / 2, (-9 * t2 + 8 * t + 1) / 2, (3 * t2 - 2 * t) / 2],
                     -1)
    return w, dw


def _cubic_autograd(pm: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """:func:`cubic_phase` with autograd through the weights, the gather and three contractions (the values of
    :func:`_cubic_eval`, bit for bit; kept as it is so that the gradients are too)."""
    vals, iu, iv = _cubic_taps(pm, u.detach(), v.detach())
    wu, dwu = _keys(u - iu)
    wv, dwv = _keys(v - iv)
    return (torch.einsum("nij,ni,nj->n", vals, wv, wu), torch.einsum("nij,ni,nj->n", vals, wv, dwu),
            torch.einsum("nij,ni,nj->n", vals, dwv, wu))


def cubic_phase(pm: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """``(φ, ∂φ/∂u, ∂φ/∂v)`` (N,) of the padded phase map ``pm`` (ny + 4, nx + 4) at the index points ``u``
    (columns), ``v`` (rows) (N,) (Keys cubic convolution, C¹, exact for quadratics): :func:`_cubic_autograd` when
    autograd needs it (differentiable in ``pm`` and the points), else :func:`_cubic_eval` (the same values)."""
    if torch.is_grad_enabled() and (pm.requires_grad or u.requires_grad or v.requires_grad):
        return _cubic_autograd(pm, u, v)
    out = _cubic_eval(pm, u, v)
    return out[:, 0, 0], out[:, 0, 1], out[:, 1, 0]


class DOEPhaseSurface(nn.Module):
    """The smooth phase of a DOE's diffraction order as a :class:`~raywave.surfaces.Diffraction` phase callable.

    ``φ(x, y) = scale · φ0(x, y)``: ``φ0`` the DOE's design phase × ``phase_scale`` (rad at λ0, unwrapped by phasor
    differences) at its pixel centres, interpolated by cubic convolution (C¹; exact for quadratics), with its exact
    gradient (rad/mm). ``scale``: a number, or a callable ``wavelength (µm) -> number`` (a continuous DOE's
    dispersion α(λ)). Points off the grid take the edge pixels' linear extrapolation (the DOE's aperture, a surface
    aperture, blocks them). ``phase_map``: the map of :meth:`phase_map` when already built (shared by the
    orders and traces of one PSF call); else it is built at the first call (make a new instance after changing
    the DOE). Traces without autograd read it detached.

    ``source_index``: the surface takes its scale per source (issue 46: the orders of a PSF call traced as the
    sources of one engine call): while :func:`raywave.hybrid.coherent.tracing.per_source` is open, each traced row
    (the bundles' first axis) takes ``value[source_index]`` of its source's value (a tuple of every DOE's scale; a
    None value: ``scale``); traced outside one, ``scale`` (None: an error)."""

    def __init__(self, doe: DOE, scale=1.0, phase_map: torch.Tensor | None = None, source_index: int | None = None):
        super().__init__()
        self.doe = doe
        self.scale = scale
        self._map = phase_map
        self.source_index = source_index
        self._rows = None

    def source_rows(self, orders, index=None) -> None:
        """Set (``orders``: the per-source values, ``index`` (R,) long: each row's source, None: row r is source r)
        or clear (``orders`` None) the per-row scales of :func:`raywave.hybrid.coherent.tracing.per_source`: (R, 1,
        1) float64, or a 0-d tensor for one source (it broadcasts with any bundle shape)."""
        if orders is None or self.source_index is None:
            self._rows = None
            return
        k = self.source_index
        if any(o is None for o in orders) and not isinstance(self.scale, (int, float)):
            raise ValueError("mid-system DOE: a source without its order traced through a per-source phase surface")
        vals = [float(self.scale) if o is None else float(o[k]) for o in orders]
        t = torch.tensor(vals, dtype=torch.float64, device=self.doe.device)
        if index is not None:
            self._rows = t.to(index.device)[index].reshape(-1, 1, 1)
        elif len(vals) == 1:
            self._rows = t.reshape(())
        else:
            self._rows = t.reshape(-1, 1, 1)

    def phase_map(self) -> torch.Tensor:
        """``φ0`` on the DOE pixels (ny, nx), unwrapped, with two pixels of linear extrapolation on every side."""
        p = self.doe.design_phase_pixels(slice(None), slice(None))
        if self.doe.phase_scale != 1.0:
            p = p * self.doe.phase_scale
        p = _unwrapped(p) if min(p.shape) > 1 else p
        for dim in (0, 1):  # linear extrapolation: two samples before and after
            n = p.shape[dim]
            if n >= 4:  # the two edge samples of each side from one narrow (one full-size gradient in the backward)
                head, tail = p.narrow(dim, 0, 2), p.narrow(dim, n - 2, 2)
                a, b = head.narrow(dim, 0, 1), head.narrow(dim, 1, 1)
                c, d = tail.narrow(dim, 1, 1), tail.narrow(dim, 0, 1)
            else:
                a, b = p.narrow(dim, 0, 1), p.narrow(dim, min(1, n - 1), 1)
                c, d = p.narrow(dim, n - 1, 1), p.narrow(dim, max(n - 2, 0), 1)
            p = torch.cat([a + 2 * (a - b), a + (a - b), p, c + (c - d), c + 2 * (c - d)], dim)
        return p

    def forward(self, x, y, wavelength):
        doe = self.doe
        if self._map is None:
            self._map = self.phase_map()
        pm = self._map if torch.is_grad_enabled() else self._map.detach()
        ny, nx = doe.shape
        pitch = doe.pitch
        u = x / pitch + (nx - 1) / 2 + 2.0  # index in the padded map
        v = y / pitch + (ny - 1) / 2 + 2.0
        shape = u.shape
        phi, gx, gy = cubic_phase(pm, u.reshape(-1), v.reshape(-1))
        gx, gy = gx / pitch, gy / pitch
        s = self._row_scale(shape) if self._rows is not None or self.scale is None else (
            self.scale(wavelength) if callable(self.scale) else self.scale)
        return tuple(s * t.reshape(shape) for t in (phi, gx, gy))

    def _row_scale(self, shape):
        """The per-row scales for traced points of ``shape`` (R, W, N); a RuntimeError when their rows are not the
        sources' (a bundle flattened or cut, or traced outside :func:`~raywave.hybrid.coherent.tracing.
        per_source`)."""
        r = self._rows
        if r is None:
            raise RuntimeError("mid-system DOE: a per-source phase surface traced without its sources' orders "
                               "(raywave.hybrid.coherent.tracing.per_source)")
        if r.ndim == 0:
            return r
        if len(shape) != 3 or shape[0] != r.shape[0]:
            raise RuntimeError(f"mid-system DOE: a bundle of shape {tuple(shape)} traced with {r.shape[0]} per-source "
                               "orders: its rows are not the sources")
        return r


def _doe_aperture(doe: DOE):
    """The DOE's clear aperture as a surface aperture (the inscribed circle, or the square grid)."""
    w, h = doe.size
    if doe.aperture == "circle":
        return CircularAperture(0.5 * min(w, h))
    if abs(w - h) > 1e-12 * max(w, h):
        raise ValueError(f"a mid-system DOE needs a square grid (or aperture='circle'); got {w:g}×{h:g} mm")
    return SquareAperture(0.5 * w)


def insert_doe(lens: Lens, after: int, distance: float | None, phase, order: float = 1.0,
               doe: DOE | None = None) -> Lens:
    """A new :class:`~raywave.lens.Lens` sharing ``lens``'s surfaces, with a thin phase plane ``distance`` mm after
    the vertex of surface ``after`` (in the medium after it): a :class:`~raywave.surfaces.Diffraction` with
    ``phase`` and ``order`` and ``doe``'s aperture. The split gap is differentiable: the plane's own thickness is
    ``thickness[after] − distance`` (a tensor expression of the original parameter).

    ``distance=None``: a conformal DOE, the phase on surface ``after`` itself (its sag, its refraction: the surface
    is rebuilt with a :class:`~raywave.surfaces.Diffraction` interaction, which bends by the phase's gradient
    projected on the tangent plane and refracts in one step; its aperture: the surface's, else the DOE's)."""
    n_s = len(lens.surfaces)
    if not 0 <= int(after) < n_s:
        raise ValueError(f"insert_doe: after={after!r} is not a surface index of a {n_s}-surface lens")
    s = lens.surfaces[after]
    if distance is None:
        return _conformal(lens, int(after), phase, order, doe)
    t = s.thickness
    if not (0.0 <= float(distance) < float(t.detach())):
        raise ValueError(f"insert_doe: the DOE must lie inside the gap after surface {after} (0 ≤ distance < "
                         f"{float(t.detach()):g} mm), got {distance!r}")
    if s.interaction.kind in ("coordinate_break", "reflection") or lens.is_folded or lens.has_mirrors:
        raise ValueError("insert_doe: mid-system DOEs are supported in unfolded lenses without coordinate breaks "
                         "or mirrors")
    head = Surface(s.geometry, s.material, float(distance), s.aperture, s.interaction, s.is_stop, s.semi_diameter,
                   s.comment)
    del head.thickness
    head.thickness = torch.tensor(float(distance), dtype=torch.float64, device=t.device)
    plane = Surface(Plane(), s.material, 0.0, _doe_aperture(doe) if doe is not None else None,
                    Diffraction(phase, order), comment="DOE (mid-system)")
    del plane.thickness
    plane.thickness = t - float(distance)
    return _with_surfaces(lens, list(lens.surfaces[:after]) + [head, plane] + list(lens.surfaces[after + 1:]))


def _conformal(lens: Lens, after: int, phase, order: float, doe: DOE | None) -> Lens:
    """:func:`insert_doe` with ``distance=None``: surface ``after`` carries the phase (a refracting surface)."""
    s = lens.surfaces[after]
    if s.interaction.kind != "refraction" or lens.is_folded or lens.has_mirrors:
        raise ValueError(f"insert_doe: a conformal DOE needs a refracting surface in an unfolded lens without "
                         f"mirrors; surface {after} is a {s.interaction.kind!r} surface")
    # the surface's own aperture where it has one (the footprint check warns when light leaves the DOE's grid)
    ap = s.aperture if s.aperture is not None or doe is None else _doe_aperture(doe)
    new_s = Surface(s.geometry, s.material, 0.0, ap, Diffraction(phase, order), s.is_stop, s.semi_diameter,
                    s.comment + " + DOE (conformal)")
    del new_s.thickness
    new_s.thickness = s.thickness
    return _with_surfaces(lens, list(lens.surfaces[:after]) + [new_s] + list(lens.surfaces[after + 1:]))


def _with_surfaces(lens: Lens, surfaces) -> Lens:
    """A new :class:`~raywave.lens.Lens` with ``surfaces`` and ``lens``'s settings."""
    new = Lens.__new__(Lens)
    nn.Module.__init__(new)
    new.surfaces = nn.ModuleList(surfaces)
    internal = set(nn.Module().__dict__)
    for k, v in lens.__dict__.items():  # the lens's settings (object, fields, wavelengths, sensor, pupil)
        if k not in internal:
            new.__dict__[k] = v
    new.object_material = lens.object_material
    new.training = lens.training
    return new


def sampling_report(doe: DOE, orders, max_step: float = MAX_STEP, box=None, phase_map=None) -> dict:
    """How well the DOE's pixels carry the phases ``scale·φ0`` of its orders (``orders``: ``[(scale, c)]``,
    strongest first, as :func:`doe_orders`).

    Returns ``{"step": rad per pixel of φ0 (x, y), "max_step": of the kept orders, "pixel_amplitude": worst sinc
    factor, "kept": the kept orders, "dropped": [(scale, |c|²)]}``: the largest phase step between neighbouring
    DOE pixels (after unwrapping), and the smallest amplitude factor ``sinc(Δφx/2π) sinc(Δφy/2π)`` that the
    pixels' flat steps leave on a kept order (1: no loss; the method does not model it). An order whose step exceeds
    ``max_step`` is not sampled by the DOE's pixels (its gradient is not known): it is dropped with a
    :class:`~raywave.hybrid.SamplingWarning` naming the power it carries, and when it is the strongest order the
    DOE is refused (ValueError: refine the DOE pitch). Warns too when the amplitude falls below
    ``1 − PIXEL_LOSS_WARN``. ``box``: the lit ``(xmin, xmax, ymin, ymax)`` mm on the DOE (default: all of it)."""
    with torch.no_grad():
        p = (DOEPhaseSurface(doe).phase_map() if phase_map is None else phase_map.detach())[2:-2, 2:-2]
        if box is not None:
            ny, nx = doe.shape
            cx, cy = (nx - 1) / 2, (ny - 1) / 2
            c0 = max(int(math.floor(box[0] / doe.pitch + cx)) - 2, 0)
            c1 = min(int(math.ceil(box[1] / doe.pitch + cx)) + 3, nx)
            r0 = max(int(math.floor(box[2] / doe.pitch + cy)) - 2, 0)
            r1 = min(int(math.ceil(box[3] / doe.pitch + cy)) + 3, ny)
            if c1 - c0 >= 2 and r1 - r0 >= 2:
                p = p[r0:r1, c0:c1]
        dx = (p[:, 1:] - p[:, :-1]).abs()
        dy = (p[1:, :] - p[:-1, :]).abs()
        gx = float(dx.max()) if dx.numel() else 0.0
        gy = float(dy.max()) if dy.numel() else 0.0
    kept, dropped = [], []
    for scale, c in orders:
        (kept if abs(float(scale)) * max(gx, gy) <= max_step else dropped).append((scale, c))
    if not kept or (dropped and dropped[0] is orders[0]):
        s0 = abs(float(orders[0][0]))
        raise ValueError(f"mid-system DOE under-sampled: its strongest order's phase ({s0:g}·φ0) changes by "
                         f"{s0 * max(gx, gy):.3g} rad between neighbouring {doe.pitch * 1e3:g} µm pixels (limit "
                         f"{max_step:.3g} rad): refine the DOE pitch")
    worst = max(abs(float(s)) for s, _ in kept)
    amp = _sinc(worst * gx / _TWO_PI) * _sinc(worst * gy / _TWO_PI)
    rep = {"step": (gx, gy), "max_step": worst * max(gx, gy), "pixel_amplitude": amp, "kept": kept,
           "dropped": [(s, abs(c) ** 2) for s, c in dropped]}
    if dropped:
        lost = sum(abs(c) ** 2 for _, c in dropped)
        warnings.warn(SamplingWarning(
            f"mid-system DOE: orders {', '.join(f'{s:g}' for s, _ in dropped)} ({100 * lost:.2g} % of the light) "
            f"change by more than {max_step:.3g} rad between neighbouring {doe.pitch * 1e3:g} µm pixels: not "
            "sampled, left out"), stacklevel=3)
    if amp < 1.0 - PIXEL_LOSS_WARN:
        warnings.warn(SamplingWarning(
            f"mid-system DOE: the {doe.pitch * 1e3:g} µm pixels' flat steps cost up to {100 * (1 - amp):.2g} % of the "
            f"order-{worst:g} amplitude (steps of {rep['max_step']:.3g} rad), which the local-grating model does not "
            "include"), stacklevel=3)
    return rep


#: :func:`cull_orders`: the safety factor on :func:`tail_envelope` (the engine's far tail of a grating order reaches
#: 0.83 of it: benchmarks/midsystem_cull.py), the crop's cells per side for its integral, the pupil probe of an
#: order's footprint (rim points, grid side: :func:`~raywave.rays.pupil.rim_and_grid`)
CULL_SAFETY = 4.0
CULL_CELLS = 16
CULL_PROBE = (32, 5)


def tail_envelope(rho, na: float, wavelength: float):
    """Upper envelope (1/mm², per unit power of the beam) of the intensity ``ρ`` mm (a float or tensor) outside the
    geometric footprint of a beam cut by a sharp circular stop: the Airy pattern's ``8 NA²/(λ² v³)``, ``v = 2π NA
    ρ/λ`` (``= λ/(π³ NA ρ³)``). Airy: ``I = P π NA²/λ² [2 J1(v)/v]²``, ``v J1(v)² → (2/π)(1 + 3/(8v²))``: it
    reaches 1.069 of the envelope (at v = 2.17, in the central lobe), 1.012 on the first ring. A defocused or
    aberrated beam: beyond its footprint (geometric rays reach no point there) the field is the stop's edge wave
    from the rim's stationary points, whose amplitudes go as ``1/ρ`` and ``1/(ρ + 2R)`` (``R``: the footprint's
    half-width) where the focused beam's go as ``2/ρ``: below the envelope at the same gap ``ρ`` from the
    footprint. ``na``: n·sin of the beam's half-angle (the smallest
    over its rim: the envelope falls with NA); ``wavelength`` µm. Not for other edges (a vignetting edge, a
    square aperture fall as ρ⁻²): :meth:`MidSystemLens.order_landings` marks such beams as not to be culled."""
    return wavelength * 1e-3 / (math.pi ** 3 * na * rho ** 3)


def crop_tail(box, crop, na: float, wavelength: float, cells: int = CULL_CELLS) -> float:
    """Upper bound on the fraction of a beam's power on the crop ``(x0, x1, y0, y1)`` mm from its footprint ``box``
    ``(x0, x1, y0, y1)`` mm on the sensor: :data:`CULL_SAFETY` × Σ over ``cells``² cells of the cell's area ×
    :func:`tail_envelope` at the gap between the footprint and the cell's nearest point; ``inf`` where the
    footprint reaches the crop."""
    t = torch.arange(cells, dtype=torch.float64) / cells
    w, h = (crop[1] - crop[0]) / cells, (crop[3] - crop[2]) / cells
    lo_x, lo_y = crop[0] + t * (crop[1] - crop[0]), crop[2] + t * (crop[3] - crop[2])
    gx = torch.clamp(torch.maximum(lo_x - box[1], box[0] - (lo_x + w)), min=0.0)
    gy = torch.clamp(torch.maximum(lo_y - box[3], box[2] - (lo_y + h)), min=0.0)
    rho = torch.sqrt(gx[None, :] ** 2 + gy[:, None] ** 2)
    if bool((rho <= 0).any()):
        return math.inf
    return CULL_SAFETY * float((tail_envelope(rho, na, wavelength) * (w * h)).sum())


def inside_fraction(box, crop, na: float, wavelength: float) -> float:
    """Lower bound on the fraction of a beam's power on the crop when its footprint ``box`` lies inside it (0
    otherwise): ``1 −`` :data:`CULL_SAFETY` × :func:`tail_envelope` integrated over every point farther than ``ρ``
    (the footprint's smallest gap to the crop's border) from the box (perimeter ``L``): ``λ/(π³ NA) (L/(2ρ²) +
    2π/ρ)``."""
    rho = min(box[0] - crop[0], crop[1] - box[1], box[2] - crop[2], crop[3] - box[3])
    if rho <= 0:
        return 0.0
    perim = 2.0 * ((box[1] - box[0]) + (box[3] - box[2]))
    out = CULL_SAFETY * wavelength * 1e-3 / (math.pi ** 3 * na) * (perim / (2 * rho ** 2) + _TWO_PI / rho)
    return max(0.0, 1.0 - out)


def cull_orders(orders, landings, crop, wavelength: float, tol: float):
    """Which of a source's ``orders`` (``[(scale, c)]``, strongest first) to leave out: ``(kept indices, [(scale,
    bound on its power on the crop)], bound)``.

    ``landings``: each order's ``(footprint box, NA, …)`` on the sensor (:meth:`MidSystemLens.order_landings`; None:
    unknown, or its beam cut by an edge other than the stop: never culled); ``crop``: ``(x0, x1, y0, y1)`` mm around
    the strongest order's chief ray. With ``ε_j`` (:func:`crop_tail`, × |c_j|²) the power of order ``j`` on the
    crop, the kept light's ``S ≥ (√(|c_0|² f_0) − Σ_{j>0} √(|c_j|² min(ε_j, 1)))²`` (``f_0``:
    :func:`inside_fraction`; Minkowski), and leaving out a set ``C`` changes the crop's intensity by ``|U_k + U_C|² −
    |U_k|²``, of L1 norm ``≤ 2√S b + b²`` (Cauchy–Schwarz; ``b ≤ Σ_C √ε_j``): the normalised PSF moves by at most
    ``4β + 2β²``, ``β = b/√S``, in relative L1 (the interference with the kept light is what counts: order +5 of a
    50 µm binary grating brings 6e-7 of the crop's light and moves the PSF by 2.7e-4). Orders are left out
    weakest-on-the-crop first while that bound stays ``≤ tol``; the strongest order (the crop's centre) never."""
    m = len(orders)
    if tol <= 0 or m < 2 or landings[0] is None:
        return list(range(m)), [], 0.0
    eff = [abs(c) ** 2 for _, c in orders]
    box0, na0 = landings[0][:2]
    f0 = inside_fraction(box0, crop, na0, wavelength)
    eps = [math.inf] + [math.inf if landings[j] is None else eff[j] * crop_tail(landings[j][0], crop, landings[j][1],
                                                                                wavelength) for j in range(1, m)]
    root_s = math.sqrt(eff[0] * f0) - sum(math.sqrt(min(eps[j], eff[j])) for j in range(1, m))
    if root_s <= 0:
        return list(range(m)), [], 0.0
    culled, b, bound = [], 0.0, 0.0
    for j in sorted(range(1, m), key=lambda i: eps[i]):
        if not math.isfinite(eps[j]):
            break
        beta = (b + math.sqrt(eps[j])) / root_s
        if 4 * beta + 2 * beta * beta > tol:
            break
        b += math.sqrt(eps[j])
        bound = 4 * beta + 2 * beta * beta
        culled.append(j)
    kept = [j for j in range(m) if j not in culled]
    return kept, [(orders[j][0], eps[j]) for j in culled], bound


@dataclass
class MidSystemPSFResult(PSFResult):
    """A :class:`~raywave.hybrid.PSFResult` of :class:`MidSystemLens` plus ``culled``: per source with several
    orders, ``{"field", "wavelength", "orders": [(scale, bound on its power on the crop)] left out, "bound": the
    bound on the normalised PSF's relative L1 change}`` (:func:`cull_orders`)."""

    culled: list = None


class DOEClipWarning(UserWarning):
    """A mid-system DOE's grid (its aperture) cuts the beam that the stop lets through: the cut is a hard edge
    inside the lens, formed geometrically on the engine's plane, whose position is not differentiated."""


def _as_list(v, n: int, name: str) -> list:
    """``v`` as a list of ``n`` items (a scalar repeated, or a sequence of length ``n``)."""
    if isinstance(v, (list, tuple)):
        if len(v) != n:
            raise ValueError(f"MidSystemLens: {name} has {len(v)} entries for {n} DOEs")
        return list(v)
    return [v] * n


@dataclass(frozen=True)
class FinalPlane:
    """The blank plane behind the lens where a :class:`MidSystemLens` builds the engine's field: ``distance`` mm
    after the last vertex (see :class:`~raywave.hybrid.HybridLens` ``doe_distance``), its square grid ``size`` mm
    a side at ``pitch`` mm (also its simulation pitch)."""

    distance: float
    size: float
    pitch: float


@dataclass(frozen=True)
class Orders:
    """Which diffraction orders a :class:`MidSystemLens` traces, and how the weak ones' stop edge is formed.

    Args:
        keep: the orders to keep (integers); with several DOEs, one such set (or None) per DOE. None: every order
            that ``min_efficiency`` keeps.
        min_efficiency: the orders (products of the DOEs' orders) with ``|c|²`` below it are left out.
        weak_edge: the stop edge of the orders after the strongest when ``stop_edge="exit_pupil"``. None: the same
            as the strongest order's (one engine call per order); ``"doe"``: the sharp cut on the final plane, all
            of them the sources of ONE engine call (:meth:`MidSystemLens.orders_engine`), the strongest order alone
            with the exact edge: the 16-level DOE with ``min_efficiency=1e-3`` and ``edge_step="asm"`` within
            6.7e-4 / 7.7e-4 of the reference at 0° / 1.5° (5.0e-4 / 5.6e-4 with every order's exact edge) at ~¼ of
            the cost (benchmarks/psf_midsystem.py, docs/ray-wave.md "A DOE inside the lens").
        cull_tol: an order whose light lands outside the PSF crop is left out of a source when a bound on the
            relative L1 change of its normalised PSF stays below ``cull_tol`` (:func:`cull_orders`: the orders'
            geometric footprints on the sensor, a sharp circular stop's far-field envelope, and the coherent cross
            term with the kept light); 0 (the default) keeps every order. The orders left out and the bound are in
            the result's ``culled`` (:class:`MidSystemPSFResult`). Off by default: an order's tail interferes with
            the kept light, so the PSF moves by about the square root of the power the tail puts on the crop
            (order −5 of a 50 µm binary grating, 220 µm from a 64 µm crop: 5e-4 relative L1); at 1e-4 the bound
            leaves out nothing that lands on a sensor of a few mm, and its probe trace costs ~10 ms a source
            (docs/ray-wave.md, "A DOE inside the lens").
    """

    keep: object = None
    min_efficiency: float = 0.01
    weak_edge: str | None = None
    cull_tol: float = 0.0

    def __post_init__(self):
        if self.weak_edge not in (None, "doe"):
            raise ValueError(f"MidSystemLens: weak_edge must be None or 'doe', got {self.weak_edge!r}")
        if not (self.min_efficiency >= 0.0):
            raise ValueError(f"MidSystemLens: min_efficiency must be ≥ 0, got {self.min_efficiency!r}")
        if not (0.0 <= self.cull_tol < 1.0):
            raise ValueError(f"MidSystemLens: cull_tol must be in [0, 1), got {self.cull_tol!r}")


#: :class:`MidSystemLens`'s arguments after ``distance`` before the final plane became a value type, in their order
_LEGACY_ARGS = ("final_distance", "final_size", "final_pitch", "sensor_pitch", "stop_edge", "min_efficiency", "orders")
#: the short keywords of :class:`Orders`' fields that :class:`MidSystemLens` still takes
_ORDER_KEYWORDS = ("min_efficiency", "weak_edge", "cull_tol")


def _final_plane(final: tuple, legacy: dict, options: dict) -> FinalPlane:
    """The :class:`FinalPlane` of :class:`MidSystemLens`'s ``*final`` (one :class:`FinalPlane`, or the pre-value-type
    positional ``final_distance, final_size, final_pitch[, sensor_pitch, stop_edge, min_efficiency, orders]``,
    the options among them written into ``options``) and ``legacy`` keywords (``final_distance=``, ``final_size=``,
    ``final_pitch=``); TypeError naming what is missing or unknown."""
    unknown = set(legacy) - set(_LEGACY_ARGS[:3])
    if unknown:
        raise TypeError(f"MidSystemLens: unexpected keyword argument(s) {sorted(unknown)}")
    if len(final) == 1 and isinstance(final[0], FinalPlane) and not legacy:
        return final[0]
    if len(final) > len(_LEGACY_ARGS):
        raise TypeError(f"MidSystemLens takes at most {4 + len(_LEGACY_ARGS)} positional arguments")
    given = dict(zip(_LEGACY_ARGS, final))
    for k, v in legacy.items():
        if k in given:
            raise TypeError(f"MidSystemLens: {k} given twice")
        given[k] = v
    for k in _LEGACY_ARGS[3:]:
        if k in given:
            options[k] = given[k]
    missing = [k for k in _LEGACY_ARGS[:3] if k not in given]
    if missing:
        raise TypeError(f"MidSystemLens: give the final plane as final=FinalPlane(distance, size, pitch) (or "
                        f"final_distance=, final_size=, final_pitch=); missing {', '.join(missing)}")
    return FinalPlane(float(given["final_distance"]), float(given["final_size"]), float(given["final_pitch"]))


def _orders(orders, min_efficiency, weak_edge, cull_tol=None) -> Orders:
    """:class:`MidSystemLens`'s :class:`Orders` from its ``orders`` argument (an :class:`Orders`, or the orders to keep)
    and the short keywords ``min_efficiency`` / ``weak_edge`` / ``cull_tol`` (None: not given); TypeError where both
    forms are given."""
    if isinstance(orders, Orders):
        if min_efficiency is not None or weak_edge is not None or cull_tol is not None:
            raise TypeError("MidSystemLens: give min_efficiency / weak_edge / cull_tol inside orders=Orders(...), not "
                            "beside it")
        return orders
    return Orders(orders, 0.01 if min_efficiency is None else float(min_efficiency), weak_edge,
                  Orders.cull_tol if cull_tol is None else float(cull_tol))


class MidSystemLens(nn.Module):
    """A lens with thin DOEs inside it (planes in its gaps, or conformal on its surfaces), and the sensor.

    Args:
        lens: the refractive lens (its last thickness reaches the sensor).
        doe: the DOE (square grid, or ``aperture="circle"``), centred on the axis; or a list of DOEs (one behind
            the other: their orders' products are traced).
        after, distance: where each DOE sits: ``distance`` mm after the vertex of surface ``after`` (inside the
            gap after it); ``distance=None``: on surface ``after`` itself (conformal: the phase on its sag). With
            several DOEs, lists (or one value for all).
        final: the blank plane where the engine's field is built (:class:`FinalPlane`: its distance mm after the
            last vertex, see :class:`~raywave.hybrid.HybridLens` ``doe_distance``, and its square grid's size and
            pitch, mm; the pitch is its simulation pitch). The earlier form ``final_distance, final_size,
            final_pitch`` (positional or keywords) is still accepted.
        sensor_pitch: as :class:`~raywave.hybrid.HybridLens`.
        stop_edge, edge_step: where the stop's edge is formed. "auto" (the default; None means it too): per source,
            the sharp cut on the engine's plane where :meth:`cut_estimates` says it holds (the wave near the stop's
            edge a sphere focused on the sensor), else the exit-pupil edge with ``edge_step`` (default: the Fresnel
            step where its error estimate holds with a margin, else "asm", the exact construction, where the beam
            fits its lattice, else the engine's "adaptive" step); :meth:`edges` gives each source's choice. "doe": the sharp cut on the engine's plane
            for every source (before 2026-12-01 the default). "exit_pupil" (``edge_step`` as
            :class:`~raywave.hybrid.HybridLens`; "asm": the stop's edge formed at each rim point's image and
            propagated by the angular spectrum, 3× closer to the reference for the strong order at ~10-20× the
            cost; with it the weak orders' edge waves reach the crop with their traced paths: a 16-level DOE within
            1e-3 of the reference with ``min_efficiency=1e-3``); see docs/ray-wave.md, "A DOE inside the lens".
        orders: which diffraction orders are traced and how the weak ones' edge is formed (:class:`Orders`); the
            short forms: the orders to keep themselves (``orders=[1, -1]``: :class:`Orders` ``keep``), and the
            keywords ``min_efficiency=`` and ``weak_edge=`` (:class:`Orders`' fields).
    """

    def __init__(self, lens: Lens, doe, after, distance, *final, sensor_pitch: float | None = None,
                 stop_edge: str | None = "auto", edge_step: str | None = None, orders=None, **legacy):
        short = {k: legacy.pop(k) for k in _ORDER_KEYWORDS if k in legacy}
        opts = {"sensor_pitch": sensor_pitch, "stop_edge": stop_edge, "min_efficiency": short.get("min_efficiency"),
                "orders": orders}
        plane = _final_plane(final, legacy, opts)
        sensor_pitch, stop_edge = opts["sensor_pitch"], "auto" if opts["stop_edge"] is None else opts["stop_edge"]
        if stop_edge not in MID_STOP_EDGES:
            raise ValueError(f"MidSystemLens: stop_edge must be one of {MID_STOP_EDGES}, got {stop_edge!r}")
        choice = _orders(opts["orders"], opts["min_efficiency"], short.get("weak_edge"), short.get("cull_tol"))
        super().__init__()
        does = list(doe) if isinstance(doe, (list, tuple)) else [doe]
        n = len(does)
        if n == 0:
            raise ValueError("MidSystemLens: no DOE given")
        afters = [int(a) for a in _as_list(after, n, "after")]
        dists = [None if d is None else float(d) for d in _as_list(distance, n, "distance")]
        keep = choice.keep
        only = keep if n > 1 and isinstance(keep, (list, tuple)) and len(keep) == n and \
            all(o is None or isinstance(o, (list, tuple, set, range)) for o in keep) else [keep] * n
        self.only = [None if o is None else {int(m) for m in o} for o in only]
        self.lens = lens
        self.does = nn.ModuleList(does)
        self.doe = does[0]
        self.placements = list(zip(afters, dists))
        self.after, self.distance = afters[0], dists[0]
        keys = [(a, -1.0 if d is None else d) for a, d in self.placements]
        if len(set(keys)) != n:
            raise ValueError(f"MidSystemLens: two DOEs at the same place {self.placements}")
        grid = int(math.ceil(plane.size / plane.pitch))
        self.final = BlankDOE(grid, plane.pitch)
        self.final_distance = float(plane.distance)
        self.sensor_pitch, self.stop_edge = sensor_pitch, stop_edge
        self.edge_step = edge_step
        self.weak_edge = choice.weak_edge
        self.min_efficiency = float(choice.min_efficiency)
        self.cull_tol = float(choice.cull_tol)
        self._transfer_cache = OrderedDict()
        self._edge_transfers = OrderedDict()  # the exact edge step's (exit_pupil.edge_transfer), shared likewise
        self.build_lens([1.0] * n)  # checks the placements now

    def _engine_edge(self) -> str:
        """The engine's ``stop_edge`` for this lens's own engines: "doe" where it is "auto" (the per-source choice is
        made by a view, :meth:`with_edge`)."""
        return "doe" if self.stop_edge == "auto" else self.stop_edge

    def with_edge(self, stop_edge: str, edge_step: str | None = None) -> "MidSystemLens":
        """A view of this lens (the same lens, DOEs, parameters and transfer memos; a shallow copy) whose stop edge
        is ``stop_edge`` ("doe" or "exit_pupil") with ``edge_step``: how "auto" builds a source's field."""
        if stop_edge not in ("doe", "exit_pupil"):
            raise ValueError(f"MidSystemLens.with_edge: stop_edge must be 'doe' or 'exit_pupil', got {stop_edge!r}")
        view = copy.copy(self)
        view.stop_edge, view.edge_step = stop_edge, edge_step
        return view

    def cut_estimates(self, fields, wavelength: float, depth=None, phase_maps=None) -> list:
        """Whether the sharp cut on the engine's plane (``stop_edge="doe"``) holds for each source of ``fields`` (F,
        2) at ``wavelength`` µm (issue 46, ``stop_edge="auto"``): ``[{"waves", "mismatch", "holds"}]``. On the lens
        with every DOE's strongest order, from one trace of the sources' edge rays (48 each: the rings 0.9 / 1.0 /
        1.1 of the stop; :func:`~raywave.hybrid.coherent.exit_pupil.edge_focus_many`, host floats): ``waves`` how far
        the wave near the stop's edge is from a sphere (its edge rays' spread about their common focus over the
        focus's diffraction scale), ``mismatch`` how much a sharp cut's focal field depends on where it cuts, for a
        sphere on that focus (:func:`~raywave.hybrid.coherent.exit_pupil.defocus_mismatch`: the edge's defocus on
        the sensor in waves × that defocus over the engine's plane's distance to the focus). For a sphere focused
        on the sensor both are 0 and the cut is exact (the Fresnel scaling theorem); a DOE that aberrates the
        converging beam moves the edge rays' focus off the sensor. ``holds``: ``waves`` ≤ :data:`CUT_SPHERE_TOL`
        and ``mismatch`` ≤ :data:`CUT_MISMATCH_TOL` (False where an edge ray cannot be traced)."""
        hl = self.with_edge("doe").order_lens(self._strongest_scales(wavelength), None, phase_maps)
        f = torch.as_tensor(fields, dtype=torch.float64).reshape(-1, 2)
        z_doe, z_sensor = hl.doe_z(), hl.sensor_z()
        out = []
        for waves, z_focus, na, n_med in (row[0] for row in edge_focus_many(hl.lens, f, [float(wavelength)], depth)):
            if z_focus is None:
                out.append({"waves": math.inf, "mismatch": math.inf, "holds": False})
                continue
            mis = defocus_mismatch(z_focus, na, n_med, float(wavelength), z_doe, z_sensor)
            out.append({"waves": waves, "mismatch": mis, "holds": waves <= CUT_SPHERE_TOL and mis <= CUT_MISMATCH_TOL})
        return out

    def edges(self, fields, wavelength: float, depth=None, phase_maps=None, ks: int | None = None) -> list:
        """Each source's ``(stop_edge, edge_step)`` (``fields`` (F, 2), ``wavelength`` µm, the PSF crop ``ks``
        pixels, None: unknown): this lens's own unless it is "auto"; then ``("doe", None)`` where
        :meth:`cut_estimates` says the cut holds, else ``("exit_pupil", edge_step)``: the ``edge_step`` given, else
        "fresnel" where the engine's Fresnel-step estimate holds with the curvature ratio at most
        :data:`MID_FRESNEL_CURVATURE` (:meth:`fresnel_estimates`), else "asm" where the beam on the exit-pupil plane
        fits the exact construction (at most :data:`~raywave.hybrid.coherent.exit_pupil.MAX_XP_SAMPLES` of the
        engine plane's pitch a side, and its window in memory: the exact step's own limits), else "adaptive" (the
        engine's default step: the Fresnel step, with its error estimate's warning where that does not hold)."""
        f = torch.as_tensor(fields, dtype=torch.float64).reshape(-1, 2).tolist()
        if self.stop_edge != "auto":
            return [(self.stop_edge, self.edge_step)] * len(f)
        est = self.cut_estimates(f, wavelength, depth, phase_maps)
        fail = [i for i, e in enumerate(est) if not e["holds"]]
        out = [("doe", None)] * len(f)
        if not fail:
            return out
        if self.edge_step is not None:
            return [("exit_pupil", self.edge_step) if i in fail else o for i, o in enumerate(out)]
        hl = self._strongest_exit_pupil_lens(wavelength, phase_maps)
        fres = _fresnel_estimates_on(hl, [f[i] for i in fail], float(wavelength), depth, ks)
        for i, fe in zip(fail, fres):
            if fe is not None and fe[0] <= fe[1] and fe[2] <= MID_FRESNEL_CURVATURE:
                out[i] = ("exit_pupil", "fresnel")
            else:
                out[i] = ("exit_pupil", self._exact_step(hl, f[i], float(wavelength), depth))
        return out

    def fresnel_estimates(self, fields, wavelength: float, depth=None, phase_maps=None, ks: int | None = None) -> list:
        """The engine's Fresnel-step error estimate (:func:`~raywave.hybrid.coherent.exit_pupil.
        fresnel_step_estimates`: ``(zones, zones_max, curvature)`` or None) of each source of ``fields`` (F, 2) at
        ``wavelength`` µm on the lens with the strongest orders, for a ``ks``-pixel crop (None: the crop unknown,
        its reach 0), from one trace of the sources' stop-rim images."""
        return _fresnel_estimates_on(self._strongest_exit_pupil_lens(wavelength, phase_maps), fields,
                                     float(wavelength), depth, ks)

    def _strongest_exit_pupil_lens(self, wavelength: float, phase_maps=None) -> HybridLens:
        """The engine on the lens with every DOE's strongest order at ``wavelength`` µm, with the exit-pupil edge:
        what :meth:`edges` estimates the Fresnel and exact steps on (built once a call)."""
        return self.with_edge("exit_pupil").order_lens(self._strongest_scales(wavelength), None, phase_maps)

    def _strongest_scales(self, wavelength: float) -> tuple:
        """Each DOE's strongest order's scale at ``wavelength`` µm among the orders it keeps
        (:meth:`doe_order_list`; all its orders where it keeps none): the orders' product with the most light."""
        out = []
        for j in range(len(self.does)):
            kept = self.doe_order_list(j, float(wavelength)) or doe_orders(self.does[j], float(wavelength),
                                                                             self.min_efficiency)
            out.append(kept[0][0])
        return tuple(out)

    def _exact_step(self, hl: HybridLens, field, wavelength: float, depth) -> str:
        """"asm" where the source's beam fits the exact construction on ``hl``'s exit-pupil plane
        (:data:`~raywave.hybrid.coherent.exit_pupil.MAX_XP_SAMPLES` samples a side and its window in memory), else
        "adaptive"; "adaptive" too where the exit pupil is undefined (the engine then cuts on its plane, with its
        warning)."""
        try:
            z_xp = hl.exit_pupil_z(wavelength)
        except ValueError:
            return "adaptive"
        p_sim = self.final.pitch
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", VignettingWarning)  # a footprint probe; the PSF warns
            _, xb = _edge_method(hl.lens, field, wavelength, depth, z_xp, p_sim, "asm")
        return "asm" if _beam_fits(hl.lens, xb, p_sim, MAX_XP_SAMPLES) else "adaptive"

    def build_lens(self, scales, phase_maps=None, dispersive=None, per_source: bool = False):
        """``(lens, indices)``: the lens with every DOE's order phase (``scales[i]·φ0`` of DOE ``i``; a callable
        scale: α(λ)) and the index of each DOE's surface in it. ``per_source``: the non-dispersive DOEs take their
        scale per source (:class:`DOEPhaseSurface` ``source_index``; ``scales`` unused for them): one lens for
        every order of a call."""
        n = len(self.does)
        pms = phase_maps if phase_maps is not None else [None] * n
        lens_m = self.lens
        # the deepest first: earlier indices stay valid; in one gap, the farther plane first
        todo = sorted(range(n), key=lambda i: (self.placements[i][0], -1.0 if self.placements[i][1] is None
                                               else self.placements[i][1]), reverse=True)
        for i in todo:
            a, d = self.placements[i]
            disp = dispersive is not None and dispersive[i]
            if per_source and not disp:
                surf = DOEPhaseSurface(self.does[i], None, pms[i], source_index=i)
            else:
                surf = DOEPhaseSurface(self.does[i], self._scale_fn(i) if disp else float(scales[i]), pms[i])
            lens_m = insert_doe(lens_m, a, d, surf, 1.0, self.does[i])
        return lens_m, self.doe_surface_indices()

    def doe_surface_indices(self) -> list:
        """The index of each DOE's surface in the lenses of :meth:`build_lens` (the placements alone decide it)."""
        n = len(self.does)
        idx = []
        for i in range(n):
            a, d = self.placements[i]
            before = sum(1 for j in range(n) if self.placements[j][1] is not None and
                         (self.placements[j][0] < a or (self.placements[j][0] == a and d is not None and
                                                        self.placements[j][1] < d)))
            idx.append(a + before + (0 if d is None else 1))
        return idx

    def _continuous(self, i: int) -> bool:
        d = self.does[i]
        return not d.wrap and d.quant_levels is None

    def order_lens(self, scale, dispersive=None, phase_map=None) -> HybridLens:
        """The engine for one order: the lens with the order's phase planes, the blank final plane, the sensor.
        ``scale``: the order's scale (a number, or a tuple with one per DOE); ``phase_map``: the DOEs'
        :meth:`DOEPhaseSurface.phase_map` (one, or a list), when already built; ``dispersive``: whether the DOEs
        are continuous (their scale α(λ)); default: read from the DOEs. With ``stop_edge="auto"`` the engine of
        the cut (``"doe"``): the choice is per source (:meth:`edges`), made by :meth:`psf` / :meth:`source_field`."""
        n = len(self.does)
        scales = list(scale) if isinstance(scale, (tuple, list)) else [scale] * n
        pms = phase_map if isinstance(phase_map, (list, tuple)) else [phase_map] * n
        disp = [self._continuous(i) for i in range(n)] if dispersive is None else _as_list(dispersive, n, "dispersive")
        lens_m, _ = self.build_lens(scales, pms, disp)
        edge = {} if self.edge_step is None or self.stop_edge != "exit_pupil" else {"edge_step": self.edge_step}
        hl = HybridLens(lens_m, self.final, self.final_distance, sensor_pitch=self.sensor_pitch,
                        stop_edge=self._engine_edge(), **edge)
        # one memo of window transfer functions (and of the exact edge step's) for every order
        return hl.use_transfer_cache(self._transfer_cache, self._edge_transfers)

    def caustics(self, hl: HybridLens, field, wavelength: float, depth=None) -> int:
        """How many line foci (caustics) an order's beam crosses between the first DOE and the engine's plane
        (0, 1 or 2: a point focus is 2): from the chief ray's neighbourhood, the 2×2 map ``M`` of small pupil
        offsets from the first DOE's surface to the plane (``det M < 0``: one; ``det M > 0`` and ``tr M < 0``:
        two). Each one delays the order's field by π/2 (the Gouy phase), which the rays' optical paths do not
        hold (:meth:`source_field` applies it relative to the strongest order)."""
        lens_m = hl.lens
        e = 1e-3
        px = torch.tensor([0.0, e, 0.0], dtype=torch.float64)
        py = torch.tensor([0.0, 0.0, e], dtype=torch.float64)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # 3 probe rays near the chief ray, apertures off; the PSF itself warns
            rays = point_source_rays(lens_m, torch.tensor([list(field)], dtype=torch.float64), [wavelength],
                                     pupil=(px, py), aim="full", depth=depth)
            at_doe = lens_m.trace(rays, stop=self.doe_surface_indices()[0] + 1, apertures=False)
            out = lens_m.trace(rays, apertures=False)
            nmed = lens_m.surfaces[-1].material.n(out.wavelength).to(out.dtype)
            out = out.propagate_to_z(float(lens_m.vertex_z()[-1].detach()) + hl.doe_distance, nmed)
        a, b = at_doe.o.reshape(-1, 3)[:3, :2], out.o.reshape(-1, 3)[:3, :2]
        j0 = torch.stack([a[1] - a[0], a[2] - a[0]], 1)
        j1 = torch.stack([b[1] - b[0], b[2] - b[0]], 1)
        m = j1 @ torch.linalg.inv(j0)
        det, tr = float(torch.linalg.det(m)), float(torch.trace(m))
        if not (math.isfinite(det) and math.isfinite(tr)):
            return 0
        return 1 if det < 0 else 2 if tr < 0 else 0

    def _dispersion_scale(self, wavelength, i: int = 0):
        """α(λ) of continuous DOE ``i`` at the rays' wavelengths (a tensor, µm)."""
        doe = self.does[i]
        if doe.dispersion == "none":
            return 1.0
        if doe.dispersion == "air":
            return doe.design_wavelength / wavelength
        return doe.dispersion_ratio(wavelength)

    def _scale_fn(self, i: int):
        """:meth:`_dispersion_scale` of DOE ``i`` as a callable of the wavelength."""
        return lambda wavelength: self._dispersion_scale(wavelength, i)

    def footprint(self, field, wavelength: float, depth=None, phase_maps=None, i: int = 0):
        """``(box, clipped)`` on DOE ``i``: the lit ``(xmin, xmax, ymin, ymax)`` mm (None when nothing reaches it)
        and the fraction of the probe rays (the pupil's rim and a grid inside, aimed through the stop of the lens
        with every DOE's strongest order) that reach its surface but fall outside the DOE's aperture."""
        n = len(self.does)
        scales = [doe_orders(self.does[j], wavelength, self.min_efficiency)[0][0] for j in range(n)]
        pms = phase_maps if phase_maps is not None else [None] * n
        lens_m, idx = self.build_lens(scales, pms)
        px, py = rim_and_grid(72, 9)
        k = idx[i]
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the footprint's probe rays: vignetted ones drop out by `ok`; the PSF warns
            rays = point_source_rays(lens_m, torch.tensor([list(field)], dtype=torch.float64), [wavelength],
                                     pupil=(px, py), aim="full", depth=depth)
            before = lens_m.trace(rays, stop=k)
            out = lens_m.trace(before, start=k, stop=k + 1, apertures=False)
        ok = out.valid
        if not bool(ok.any()):
            return None, 0.0
        x, y = out.o[..., 0][ok], out.o[..., 1][ok]
        inside = _doe_aperture(self.does[i]).contains(x, y)
        clipped = 1.0 - float(inside.double().mean())
        if not bool(inside.any()):
            return None, clipped
        x, y = x[inside], y[inside]
        return (float(x.min()), float(x.max()), float(y.min()), float(y.max())), clipped

    def lit_box(self, field, wavelength: float, depth=None, phase_map: torch.Tensor | None = None, i: int = 0):
        """The lit ``(xmin, xmax, ymin, ymax)`` mm on DOE ``i`` (:meth:`footprint`), or None."""
        pms = phase_map if isinstance(phase_map, (list, tuple)) or phase_map is None else [phase_map] + [None] * (
            len(self.does) - 1)
        return self.footprint(field, wavelength, depth, pms, i)[0]

    def doe_order_list(self, i: int, wavelength: float) -> list:
        """``[(scale, c)]`` of DOE ``i`` (:func:`doe_orders`, restricted to the requested ``orders``)."""
        out = doe_orders(self.does[i], wavelength, self.min_efficiency)
        if self.only[i] is not None and not self._continuous(i):
            out = [(s, c) for s, c in out if int(round(s)) in self.only[i]]
        return out

    def orders(self, wavelength: float, per_doe=None) -> list:
        """``[(scale, c)]`` of :func:`doe_orders` at ``wavelength`` (one DOE); with several, ``[(scales, c)]``:
        the products of the DOEs' orders (``per_doe``: each DOE's list, default :meth:`doe_order_list`) with
        ``|c|² ≥ min_efficiency``, strongest first."""
        n = len(self.does)
        lists = per_doe if per_doe is not None else [self.doe_order_list(i, wavelength) for i in range(n)]
        if n == 1:
            return list(lists[0])
        combos = [((), 1.0 + 0j)]
        for lst in lists:
            combos = [(sc + (s,), c * cm) for sc, c in combos for s, cm in lst]
        keep = sorted([t for t in combos if abs(t[1]) ** 2 >= self.min_efficiency], key=lambda t: -abs(t[1]))
        if not keep:
            raise ValueError(f"no product of the DOEs' orders carries {self.min_efficiency:g} of the light at "
                             f"{wavelength:g} µm: lower min_efficiency")
        return keep

    def source_field(self, field, wavelength: float, depth=None, report: bool = True, phase_maps=None,
                     orders=None, ks: int | None = None):
        """The combined field on the final plane for one source: ``(DOEField, HybridLens of the strongest
        order, orders)``. ``phase_maps``: the DOEs' :meth:`DOEPhaseSurface.phase_map` when the caller built them
        (once for all its sources); else built here. ``orders``: the source's :meth:`source_orders` when the
        caller has them. ``ks``: the PSF crop the field is for (the exact edge's lattice keeps the edge waves that
        land in it: :meth:`HybridLens.doe_fields` ``crop_reach``); None: the geometric spot only."""
        pms = phase_maps if phase_maps is not None else [DOEPhaseSurface(d).phase_map() for d in self.does]
        if self.stop_edge == "auto":
            view = self.with_edge(*self.edges([tuple(field)], wavelength, depth, pms, ks)[0])
            return view.source_field(field, wavelength, depth, report, pms, orders, ks)
        if orders is None:
            orders = self.source_orders(field, wavelength, depth, pms, report)
        if len(orders) > 1 and self.stop_edge == "doe":
            return self._orders_field(field, wavelength, depth, pms, orders)
        if len(orders) > 1 and self.stop_edge == "exit_pupil" and self.weak_edge == "doe":
            return self._split_field(field, wavelength, depth, pms, orders, ks)
        return self._orders_loop(field, wavelength, depth, pms, orders, ks)

    def source_orders(self, field, wavelength: float, depth=None, pms=None, report: bool = True) -> list:
        """The orders ``[(scale, c)]`` (:meth:`orders`) of the source ``field`` at ``wavelength`` µm; with ``report``,
        those that its lit footprint on each DOE samples (:func:`sampling_report`, warning of the orders left
        out), and a :class:`DOEClipWarning` where a DOE's grid cuts its beam. ``pms``: the DOEs' phase maps."""
        n = len(self.does)
        pms = pms if pms is not None else [DOEPhaseSurface(d).phase_map() for d in self.does]
        per = [self.doe_order_list(i, wavelength) for i in range(n)]
        if report:
            for i in range(n):
                box, clipped = self.footprint(field, wavelength, depth, pms, i)
                if clipped > 0:
                    warnings.warn(DOEClipWarning(
                        f"mid-system DOE {i} (after surface {self.placements[i][0]}): its {self.does[i].size[0]:g} mm "
                        f"grid cuts the beam of field {list(field)} at {wavelength:g} µm ({100 * clipped:.2g} % of "
                        "the probe rays): a hard edge inside the lens whose position is not differentiated; make "
                        "the DOE larger than its footprint"), stacklevel=3)
                per[i] = sampling_report(self.does[i], per[i], box=box, phase_map=pms[i])["kept"]
        return self.orders(wavelength, per)

    def _orders_loop(self, field, wavelength: float, depth, pms, orders, ks: int | None = None):
        """:meth:`source_field` with one engine call per order (one order; or the exit-pupil edge for every order)."""
        parts = []
        for j, (scale, c) in enumerate(orders):
            hl = self.order_lens(scale, None, pms)
            if j > 0 and parts and self.stop_edge == "exit_pupil":  # the crop's centre: the strongest order's
                hl.use_rim_images(_CropRims(parts[0][1].center, hl.sensor_z()))
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                fd = hl.doe_fields([tuple(field)], [wavelength], depth, crop_reach=_reach(hl, ks))[0][0]
            caustic = any(issubclass(w.category, CausticWarning) for w in caught)
            if caustic and j > 0:  # a weak order that folds before the engine's plane: its field is not built
                warnings.warn(SamplingWarning(
                    f"mid-system DOE: order {scale} ({100 * abs(c) ** 2:.2g} % of the light) "
                    f"folds (a caustic) before the plane {self.final_distance:g} mm after the last surface: left out"),
                    stacklevel=3)
                continue
            for w in caught:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            if len(orders) > 1:  # the Gouy phase of the foci the order crosses, relative to the strongest order
                nc = self.caustics(hl, field, wavelength, depth)
                nc0 = nc if j == 0 else nc0
                c = c * cmath.exp(-0.5j * math.pi * (nc - nc0))
            parts.append((hl, fd, c))
        if len(parts) == 1:
            hl, fd, c = parts[0]
            return fd, hl, orders
        return _combine(parts, self.final, field, wavelength, depth), parts[0][0], orders

    def orders_engine(self, phase_map=None, stop_edge: str | None = None) -> HybridLens:
        """The engine for every order of a call at once (issue 46): the lens whose non-dispersive DOEs take their
        scale per source (:meth:`build_lens` ``per_source``), the blank final plane, the sensor, no mirroring (the
        orders of one source are sources at the same field point). ``phase_map``: as :meth:`order_lens`;
        ``stop_edge``: the engine's edge (default :attr:`stop_edge`)."""
        n = len(self.does)
        pms = phase_map if isinstance(phase_map, (list, tuple)) else [phase_map] * n
        disp = [self._continuous(i) for i in range(n)]
        lens_m, _ = self.build_lens([None] * n, pms, disp, per_source=True)
        edge = {} if self.edge_step is None else {"edge_step": self.edge_step}
        edge_at = self._engine_edge() if stop_edge is None else stop_edge
        if edge_at != "exit_pupil":
            edge = {}
        hl = HybridLens(lens_m, self.final, self.final_distance, sensor_pitch=self.sensor_pitch,
                        stop_edge=edge_at, mirror=False, **edge)
        return hl.use_transfer_cache(self._transfer_cache, self._edge_transfers)

    def _orders_field(self, field, wavelength: float, depth, pms, orders):
        """:meth:`source_field` of ``orders`` (``[(scale, c)]``, strongest first, more than one) with the DOE-plane
        edge: the orders are the sources of ONE engine call (:meth:`orders_engine`; their traces, geometry, chief
        rays and Gouy probes batched across orders: :func:`~raywave.hybrid.coherent.tracing.per_source`), each
        order's field the one its own engine builds (to the batched aiming's rounding)."""
        hl, geo, fds, keep, values = self._batched_orders(field, wavelength, depth, pms, orders, first=0)
        if len(keep) == 1:
            return fds[0][0], hl, orders
        nc = self._caustic_counts(hl, geo, values)
        nc = [nc[j] for j in keep]
        cd = geo.chief[0]
        parts = []
        for k, j in enumerate(keep):  # the Gouy phase of the foci each order crosses, relative to the strongest
            c = orders[j][1] * cmath.exp(-0.5j * math.pi * (nc[k] - nc[0]))
            fd = fds[j][0]
            parts.append((fd, c, _phase_at(cd[j, 0], fd, float(wavelength))))
        return _sum_orders(parts, self.final, float(wavelength)), hl, orders

    def _batched_orders(self, field, wavelength: float, depth, pms, orders, first: int | None,
                        stop_edge: str | None = None):
        """The fields of ``orders`` (``[(scale, c)]``) on the final plane as the sources of ONE engine call
        (:meth:`orders_engine` with ``stop_edge``): ``(hl, geo, fds [M][1], keep, values)``. An order that folds
        before the engine's plane (a caustic) is left out with a :class:`~raywave.hybrid.SamplingWarning`, unless
        it is order ``first`` (the strongest: its caustic is warned as the engine does); ``keep``: the indices of
        the kept orders; ``values``: their per-source scales."""
        hl = self.orders_engine(pms, stop_edge)
        lens_m = hl.lens
        values = [tuple(sc) if isinstance(sc, (tuple, list)) else (sc,) for sc, _ in orders]
        f = hl._engine_fields([tuple(field)] * len(orders))
        wls = [float(wavelength)]
        pending = ([], [])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with per_source(lens_m, values):
                geo = hl._accurate_geometry(f, wls, depth)
            geo.orders = values
            fds = hl._finish_fields(hl._accurate_group(geo, list(range(len(orders))), 64, True), geo, pending)
        keep = []
        for j, (scale, c) in enumerate(orders):
            if j != first and geo.clips[j][0][2] > 0:  # a weak order that folds before the engine's plane: left out
                warnings.warn(SamplingWarning(
                    f"mid-system DOE: order {scale} ({100 * abs(c) ** 2:.2g} % of the light) "
                    f"folds (a caustic) before the plane {self.final_distance:g} mm after the last surface: left out"),
                    stacklevel=5)
                continue
            keep.append(j)
        for w in caught:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        kept_fds = [fds[j][0] for j in keep]
        hl._warn_clipped([e for e in pending[0] if any(e[0] is fd for fd in kept_fds)])
        if first is not None and geo.clips[first][0][2] > 0:
            hl._warn_caustic([(geo.clips[first][0][2], list(field), float(wavelength))])
        return hl, geo, fds, keep, values

    def _split_field(self, field, wavelength: float, depth, pms, orders, ks: int | None = None):
        """:meth:`source_field` of ``orders`` (more than one) with ``weak_edge="doe"``: the strongest order with the
        exact edge (its own engine, :meth:`order_lens`; its absolute phase over the pupil, :func:`_pupil_phase`),
        the weaker ones with the DOE-plane edge as the sources of ONE engine call (:meth:`_batched_orders`; each
        one's phase at its chief ray, :func:`_phase_at`: no edge waves inside their beams), summed coherently
        with their Gouy phases relative to the strongest."""
        scale0, c0 = orders[0]
        hl0 = self.order_lens(scale0, None, pms)
        fd0 = hl0.doe_fields([tuple(field)], [wavelength], depth, crop_reach=_reach(hl0, ks))[0][0]
        hl, geo, fds, keep, values = self._batched_orders(field, wavelength, depth, pms, orders[1:], None, "doe")
        if not keep:
            return fd0, hl0, orders
        nc0 = self.caustics(hl0, field, wavelength, depth)
        nc = self._caustic_counts(hl, geo, values)
        cd = geo.chief[0]
        parts = [(fd0, c0, _pupil_phase(hl0, fd0, field, float(wavelength), depth))]
        for j in keep:
            c = orders[j + 1][1] * cmath.exp(-0.5j * math.pi * (nc[j] - nc0))
            fd = fds[j][0]
            parts.append((fd, c, _phase_at(cd[j, 0], fd, float(wavelength))))
        return _sum_orders(parts, self.final, float(wavelength)), hl0, orders

    def _caustic_counts(self, hl: HybridLens, geo, values) -> list:
        """:meth:`caustics` of the orders ``values`` (their per-source scales; the call's first sources) of ``hl``
        (:meth:`orders_engine`) whose call shared ``geo`` (its chief rays' entrance-plane points and entrance
        pupil), from one batched trace: 3 rays a source, its chief ray and two offset by 1e-3 of the entrance pupil's
        radius on the entrance plane (the map ``M`` from the DOE to the plane does not depend on how the probe is
        parametrised)."""
        lens_m = hl.lens
        m = len(values)
        ep_z, r_ep = geo.entrance
        e = 1e-3 * max(r_ep, 1e-3)
        uv = geo.chief[2][:m, :1, None, :].detach() + torch.tensor([[0.0, 0.0], [e, 0.0], [0.0, e]],
                                                                   dtype=torch.float64, device=lens_m.device)
        wl = torch.tensor(geo.wls, dtype=torch.float64, device=lens_m.device)
        with torch.no_grad(), per_source(lens_m, values):
            rays = rays_through(lens_m, uv, geo.f[:m], lens_m.field_type, wl, depth=geo.depth, ep_z=ep_z)
            out, rec = lens_m.trace(rays, apertures=False, record=True)
            nmed = lens_m.surfaces[-1].material.n(out.wavelength).to(out.dtype)
            out = out.propagate_to_z(float(lens_m.vertex_z()[-1].detach()) + hl.doe_distance, nmed)
        pts = rec.points[self.doe_surface_indices()[0] + 1]
        a = torch.stack([pts[0][:, 0], pts[1][:, 0]], -1)  # (M, 3, 2) on the first DOE
        b = out.o[:, 0, :, :2]
        j0 = torch.stack([a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]], -1)
        j1 = torch.stack([b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]], -1)
        mm = j1 @ torch.linalg.inv(j0)
        counts = []
        for det, tr in zip(torch.linalg.det(mm).tolist(), mm.diagonal(dim1=-2, dim2=-1).sum(-1).tolist()):
            counts.append(0 if not (math.isfinite(det) and math.isfinite(tr)) else 1 if det < 0 else 2 if tr < 0 else 0)
        return counts

    def order_landings(self, field, wavelength: float, depth, pms, orders) -> list:
        """Each order's geometric footprint on the sensor, ``[(box (x0, x1, y0, y1) mm, NA, chief ray's landing (x,
        y) mm) or None]``, from ONE
        trace of the orders as sources (:func:`~raywave.hybrid.coherent.tracing.per_source`): the chief ray, a rim
        and a grid over the stop (:data:`CULL_PROBE`), apertures on. The box holds the landings, widened by one
        sensor pixel; NA: ``n`` × the smallest sine between a rim ray and the chief ray. None for an order whose
        probe rays an aperture cuts (a vignetting edge, the DOE's grid: not the stop's circular edge that
        :func:`tail_envelope` bounds) or whose rays do not reach the sensor."""
        n = len(self.does)
        lens_m, _ = self.build_lens([None] * n, pms, [self._continuous(i) for i in range(n)], per_source=True)
        values = [tuple(sc) if isinstance(sc, (tuple, list)) else (sc,) for sc, _ in orders]
        rx, ry = rim_and_grid(*CULL_PROBE)
        zero = torch.zeros(1, dtype=torch.float64)
        px, py = torch.cat([zero, rx]).to(lens_m.device), torch.cat([zero, ry]).to(lens_m.device)
        f = torch.tensor([list(field)] * len(orders), dtype=torch.float64)
        wl = torch.tensor([wavelength], dtype=torch.float64, device=lens_m.device)
        with torch.no_grad(), warnings.catch_warnings(), per_source(lens_m, values):
            warnings.simplefilter("ignore", VignettingWarning)  # a vignetted probe marks its order as kept
            rays = point_source_rays(lens_m, f, wl, pupil=(px, py), aim="full", depth=depth)
            out = lens_m.trace(rays)
        nmed = lens_m.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(float(lens_m.image_z().detach()), nmed)
        ps = self.crop_pitch()
        res = []
        for j in range(len(orders)):
            o, d, ok = at.o[j, 0], at.d[j, 0], at.valid[j, 0]
            if not bool(ok.all()) or not bool(torch.isfinite(o).all()):
                res.append(None)
                continue
            x, y = o[:, 0], o[:, 1]
            box = (float(x.min()) - ps, float(x.max()) + ps, float(y.min()) - ps, float(y.max()) + ps)
            sin = torch.linalg.vector_norm(torch.cross(d[1:CULL_PROBE[0] + 1], d[:1].expand(CULL_PROBE[0], 3), dim=-1),
                                           dim=-1)
            na = float(nmed.reshape(-1)[0]) * float(sin.min())
            res.append((box, na, (float(x[0]), float(y[0]))) if na > 0 else None)
        return res

    def crop_pitch(self) -> float:
        """The PSF's pixel pitch (mm): ``sensor_pitch``, else the lens's sensor pixel pitch, else the final plane's
        pitch (as :class:`~raywave.hybrid.HybridLens` resolves it)."""
        pitch = self.sensor_pitch if self.sensor_pitch is not None else self.lens.pixel_pitch
        return float(pitch if pitch is not None else self.final.pitch)

    def cull(self, field, wavelength: float, depth, pms, orders, ks: int):
        """``(orders kept, record)``: :func:`cull_orders` of the source ``field`` at ``wavelength`` for the ``ks`` ×
        ``ks`` crop (one sensor pixel of margin around it) centred on the strongest order's chief ray;
        ``record``: ``{"field", "wavelength", "orders": [(scale, bound on its power on the crop)], "bound"}``."""
        rec = {"field": list(field), "wavelength": float(wavelength), "orders": [], "bound": 0.0}
        if self.cull_tol <= 0 or len(orders) < 2:
            return orders, rec
        land = self.order_landings(field, wavelength, depth, pms, orders)
        if land[0] is None:
            return orders, rec
        ps = self.crop_pitch()
        cx, cy = land[0][2]
        h = (0.5 * ks + 1) * ps
        kept, culled, bound = cull_orders(orders, land, (cx - h, cx + h, cy - h, cy + h), float(wavelength),
                                          self.cull_tol)
        rec["orders"], rec["bound"] = culled, bound
        return [orders[j] for j in kept], rec

    def psf_result(self, fields=(0.0, 0.0), wavelengths=0.55, ks: int = 64, depth=None) -> "MidSystemPSFResult":
        """PSFs ``(F, W, ks, ks)`` (sum 1, centred on the strongest order's chief ray) as :class:`MidSystemPSFResult`
        (its ``culled``: the orders left out of each source by :meth:`cull`, and the bound)."""
        fields = torch.as_tensor(fields, dtype=torch.float64).reshape(-1, 2).tolist()
        wls = [float(w) for w in torch.as_tensor(wavelengths, dtype=torch.float64).reshape(-1)]
        psfs, centers, outs, rays = [], [], [], []
        pms = [DOEPhaseSurface(d).phase_map() for d in self.does]  # once per call (with autograd if on)
        built, culled = {}, []
        for j, wl in enumerate(wls):
            for i, (fd, hl, orders) in enumerate(self._wavelength_fields(fields, wl, depth, pms, ks, culled)):
                built[i, j] = (fd, hl, orders)
        for i in range(len(fields)):
            pr, cr, orow, rr = [], [], [], []
            for j in range(len(wls)):
                fd, hl, orders = built[i, j]
                psf, c, o = hl.propagate(fd, ks)
                pr.append(psf), cr.append(c), orow.append(o), rr.append(fd.rays * len(orders))
            psfs.append(torch.stack(pr)), centers.append(torch.stack(cr)), outs.append(torch.stack(orow))
            rays.append(rr)
        return MidSystemPSFResult(torch.stack(psfs), torch.stack(centers), torch.stack(outs), hl.sensor_pitch,
                                  torch.tensor(rays), culled=culled)

    def _wavelength_fields(self, fields: list, wavelength: float, depth, pms, ks: int | None = None,
                           culled: list | None = None) -> list:
        """:meth:`source_field` of every source ``fields`` ([F] of (2,)) at ``wavelength``: ``[(DOEField, HybridLens,
        orders)]``. Where every source has one order, the same (a continuous DOE; a fabricated one whose strongest
        order alone is kept), they are the sources of ONE engine call (its traces batched across them; each field
        the one its own call builds, to the batched aiming's rounding); else one :meth:`source_field` per source.
        ``ks``: the crop for which a source's orders far outside it are left out (:meth:`cull`; their records
        appended to ``culled``); None: none is. With ``stop_edge="auto"`` the sources are grouped by their edge
        (:meth:`edges`) and each group built as above with its edge."""
        if self.stop_edge == "auto":
            groups = {}
            for i, key in enumerate(self.edges(fields, wavelength, depth, pms, ks)):
                groups.setdefault(key, []).append(i)
            out = [None] * len(fields)
            for key, idx in groups.items():
                part = self.with_edge(*key)._wavelength_fields([fields[i] for i in idx], wavelength, depth, pms, ks,
                                                               culled)
                for i, r in zip(idx, part):
                    out[i] = r
            return out
        orders = [self.source_orders(f, wavelength, depth, pms) for f in fields]
        if ks is not None and self.cull_tol > 0:
            for i, f in enumerate(fields):
                if len(orders[i]) > 1:
                    orders[i], rec = self.cull(f, wavelength, depth, pms, orders[i], ks)
                    if culled is not None:
                        culled.append(rec)
        one = [o[0][0] for o in orders if len(o) == 1]
        if len(fields) > 1 and len(one) == len(fields) and all(s == one[0] for s in one):
            hl = self.order_lens(one[0], None, pms)
            hl.mirror = False  # a DOE inside the lens may break the lens's mirror symmetry
            fds = hl.doe_fields([tuple(f) for f in fields], [wavelength], depth, crop_reach=_reach(hl, ks))
            return [(fds[i][0], hl, orders[i]) for i in range(len(fields))]
        return [self.source_field(f, wavelength, depth, phase_maps=pms, orders=o, ks=ks)
                for f, o in zip(fields, orders)]

    def psf(self, fields=(0.0, 0.0), wavelengths=0.55, ks: int = 64, depth=None) -> torch.Tensor:
        return self.psf_result(fields, wavelengths, ks, depth).psf


def _absolute_phase(hl: HybridLens, fd: DOEField, field, wavelength: float, depth) -> torch.Tensor:
    """``K`` (mm of optical path) with ``true field = envelope·carrier·exp(i k K)`` up to one constant common to
    every order: the chief ray's optical path at its point ``X`` on the final plane less the phase of the carrier
    and of the envelope there (bilinear interpolation of the envelope's phasor; the carrier is the chief ray's
    direction, so the envelope's phase is stationary at ``X``)."""
    lens = hl.lens
    z = float(lens.vertex_z()[-1].detach()) + hl.doe_distance
    wl = torch.tensor([wavelength], dtype=torch.float64, device=lens.device)
    cr = chief_ray(lens, torch.tensor([list(field)], dtype=torch.float64), wl, depth=depth)
    out = lens.trace(cr, apertures=False)
    nmed = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z, nmed)
    return _phase_at(at[0, 0, 0], fd, wavelength)


def _phase_at(chief, fd: DOEField, wavelength: float) -> torch.Tensor:
    """:func:`_absolute_phase` from the order's chief ray on the final plane (a scalar-batch bundle: its point and
    optical path)."""
    x, y, opl = chief.o[0], chief.o[1], chief.opl
    g = fd.grid
    (x0, y0), p = g.origin, fd.pitch
    fx, fy = (float(x.detach()) - x0) / p, (float(y.detach()) - y0) / p
    ix, iy = int(math.floor(fx)), int(math.floor(fy))
    ny, nx = fd.envelope.shape[-2:]
    if not (0 <= ix < nx - 1 and 0 <= iy < ny - 1):
        raise ValueError("mid-system DOE: an order's chief ray misses its own field window on the final plane")
    tx, ty = fx - ix, fy - iy
    e = fd.envelope
    val = ((1 - ty) * ((1 - tx) * e[iy, ix] + tx * e[iy, ix + 1]) + ty * ((1 - tx) * e[iy + 1, ix] + tx * e[iy + 1, ix + 1]))
    k = _TWO_PI / (wavelength * 1e-3)
    a, b = fd.carrier
    return opl - fd.n * (a * x + b * y) - torch.angle(val) / k


def _fresnel_estimates_on(hl: HybridLens, fields, wavelength: float, depth, ks: int | None) -> list:
    """:meth:`MidSystemLens.fresnel_estimates` on the engine ``hl`` (one trace of the sources' stop-rim images, as
    the engine traces them)."""
    f = torch.as_tensor(fields, dtype=torch.float64, device=hl.optics.device).reshape(-1, 2)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # a probe; the PSF warns
        rims = hl.edge_rim_images(f, [wavelength], depth)[0]
    return hl.edge_step_estimates(rims, wavelength, _reach(hl, ks))


def _reach(hl: HybridLens, ks: int | None) -> float:
    """The ``ks``-pixel PSF crop's reach (mm) on ``hl``'s sensor (:meth:`HybridLens.crop_reach`), 0 without a crop."""
    return 0.0 if ks is None else hl.crop_reach(ks)


def _combine(parts, final: DOE, field, wavelength: float, depth) -> DOEField:
    """The orders' fields ``[(hl, fd, c)]`` (the exit-pupil edge: one engine call per order) summed coherently on
    the union of their windows, on the first (strongest) order's carrier; its sensor point, distance and diagnostics
    (:func:`_sum_orders`, each order's absolute phase from its geometric wave over the pupil: :func:`_pupil_phase`)."""
    return _sum_orders([(fd, c, _pupil_phase(hl, fd, field, wavelength, depth)) for hl, fd, c in parts], final,
                       wavelength)


#: :func:`_pupil_phase`: the pupil points (a sunflower of this many over this fraction of the stop's radius) whose
#: geometric phases fix an order's absolute phase when its field carries the stop's edge waves
PHASE_POINTS = 64
PHASE_RADIUS = 0.7


def _pupil_phase(hl: HybridLens, fd: DOEField, field, wavelength: float, depth) -> torch.Tensor:
    """:func:`_absolute_phase` read over the pupil instead of at the chief ray's point: ``K`` (mm) from the
    envelope's samples nearest :data:`PHASE_POINTS` rays spread over the stop (inside :data:`PHASE_RADIUS` of its
    radius), each sample's geometric phase from its ray's optical path (Malus–Dupin from the ray's point to the
    sample), ``K = −arg Σ envelope·exp(−ik(Φ − n c·x))/k``. With the exact edge an order's field carries the stop's
    edge waves inside its beam, as the wave does; for an order whose beam is wide on the engine's plane they
    converge on its axis, where the chief ray is (on a round stop the envelope there is the geometric wave plus an
    edge wave as strong, in any phase: the Poisson spot), so one sample does not tell the geometric wave's phase;
    over many samples their phases differ and their sum averages them out. Differentiable (the envelope and the
    rays' paths)."""
    lens = hl.lens
    z = hl.doe_z()
    i = torch.arange(PHASE_POINTS, dtype=torch.float64) + 0.5
    r = PHASE_RADIUS * torch.sqrt(i / PHASE_POINTS)
    a = i * (math.pi * (3.0 - math.sqrt(5.0)))  # the golden angle
    wl = torch.tensor([wavelength], dtype=torch.float64, device=lens.device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # the vignetted points drop out by `valid`
        rays = point_source_rays(lens, torch.tensor([list(field)], dtype=torch.float64), wl,
                                 pupil=((r * torch.cos(a)).to(lens.device), (r * torch.sin(a)).to(lens.device)),
                                 aim="full", depth=depth)
        out = lens.trace(rays)
    nmed = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z, nmed)
    g = fd.grid
    (x0, y0), p = g.origin, fd.pitch
    ny, nx = fd.envelope.shape[-2:]
    x, y, opl, d = at.o[0, 0, :, 0], at.o[0, 0, :, 1], at.opl[0, 0], at.d[0, 0]
    ix = torch.round((x.detach() - x0) / p).long()
    iy = torch.round((y.detach() - y0) / p).long()
    ok = at.valid[0, 0] & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & torch.isfinite(opl.detach())
    if int(ok.sum()) < PHASE_POINTS // 4:  # too few of the beam's rays on the window: the chief ray's point
        return _absolute_phase(hl, fd, field, wavelength, depth)
    ix, iy, x, y, opl, d = ix[ok], iy[ok], x[ok], y[ok], opl[ok], d[ok]
    sx, sy = x0 + ix.to(x.dtype) * p, y0 + iy.to(y.dtype) * p
    k = _TWO_PI / (wavelength * 1e-3)
    ca, cb = fd.carrier
    geo = opl + fd.n * (d[:, 0] * (sx - x) + d[:, 1] * (sy - y)) - fd.n * (ca * sx + cb * sy)
    v = (fd.envelope[iy, ix] * torch.polar(torch.ones_like(geo), -k * geo)).sum()
    return -torch.angle(v) / k


#: :class:`_CropRims`: Newton rounds aiming a rim point's diffracted ray at the crop's centre, the largest miss (mm)
#: accepted, the direction-cosine step of the finite-difference Jacobian and the largest step of a round
CHORD_ROUNDS = 16
CHORD_TOL = 1e-7
CHORD_FD = 1e-7
CHORD_MAX_STEP = 0.05


class _CropRims:
    """Stop-rim images for an order whose edge wave reaches the PSF crop far from the rim rays (issue 46: a weak
    diffraction order of a mid-system DOE, wide on the sensor where the strongest order focuses): the hook of
    :meth:`~raywave.hybrid.HybridLens.use_rim_images`.

    The exact edge (``stop_edge="exit_pupil"``) forms the stop's edge at each rim point's image ``E`` on the rim
    ray (where the rim point's rays nudged across the edge cross it: the tangential focus) and lets its wave
    leave ``E`` on straight lines; it reaches a sensor point ``Q`` with the path ``Φ_E + n|Q − E|``. The wave the
    rim point diffracts reaches ``Q`` along its own ray, which leaves the rim point at another angle, and when the
    stop's rim is imaged with aberrations for that order (a strong DOE order: pupil aberrations of a strong lens)
    the two paths differ: by 0.37 wave at the crop's centre for order −15 of the 16-level Fresnel DOE of
    tests/test_midsystem_accuracy.py, which reverses its edge wave's rings there. Here ``E`` moves along the rim ray
    to where the straight path ``Φ_E + n|Q − E|`` equals the traced one, ``Φ(rim point) + [rim point → Q]`` (that
    ray aimed at ``Q`` from the rim point by Newton rounds over its direction after the stop, its path at ``Q`` by
    Malus–Dupin from where it meets the sensor plane); ``Φ_E`` stays the rim ray's own path to ``E``, so the edge
    is where geometric optics puts it. Exact at ``Q`` (the crop's centre), and near it over a crop much smaller than
    the order's blur. A source whose rays cannot all be aimed at ``Q`` (e.g. ``Q`` outside the rim points' reach)
    keeps its traced rim images. Differentiable to first order (the aiming's solution detached: the path between
    two fixed points is stationary)."""

    def __init__(self, center, z_sensor: float):
        self.q = tuple(float(torch.as_tensor(v).detach()) for v in (center[0], center[1], z_sensor))

    def __call__(self, optics, fields, wls, depth, rims):
        return [[None if r is None else self.one(optics, fields[i], float(wls[j]), depth, r)
                 for i, r in enumerate(row)] for j, row in enumerate(rims)]

    def one(self, optics, field, wavelength: float, depth, rim):
        """The rim images ``rim`` (:class:`RimImages`) of the source ``field`` (2,) moved to the crop's centre's
        chords (the class docstring), or ``rim`` when that cannot be done."""
        theta = rim[0]
        dev = optics.device
        wl = torch.tensor([wavelength], dtype=torch.float64, device=dev)
        si = optics.stop_index
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", VignettingWarning)  # the rim rays, apertures off (as stop_rim_images)
            rays = point_source_rays(optics, field.reshape(1, 2), wl, pupil=(torch.cos(theta), torch.sin(theta)),
                                     aim="full", depth=depth)
        at = optics.trace(rays, stop=si + 1, apertures=False)  # on the stop, after it: the rim points
        geo = optics.trace(at, start=si + 1, apertures=False)  # the rim rays, image side
        if not bool(at.valid.all()) or not bool(geo.valid.all()):
            return rim
        n = optics.surfaces[-1].material.n(wl).to(torch.float64)[0]
        q = torch.tensor(self.q, dtype=torch.float64, device=dev)
        d = self._aim(optics, at, q, wl, n)
        if d is None:
            return rim
        # the diffracted ray (its direction detached), with autograd through the rim point and the lens
        out = optics.trace(RayBundle.create(at.o, d, at.wavelength, opl=at.opl), start=si + 1, apertures=False)
        hit = out.propagate_to_z(q[2], n)
        path_q = hit.opl + n * (hit.d[..., 0] * (q[0] - hit.o[..., 0]) + hit.d[..., 1] * (q[1] - hit.o[..., 1]))
        o0, d0, p0 = geo.o, geo.d, geo.opl
        t = ((rim[1].detach() - o0[..., 2].detach()) / d0[..., 2].detach())
        with torch.no_grad():
            for _ in range(CHORD_ROUNDS):
                t = t - self._chord_f(o0, d0, p0, path_q, q, n, t) / self._chord_df(o0, d0, q, n, t)
            ok = bool(torch.isfinite(t).all()) and bool((self._chord_f(o0, d0, p0, path_q, q, n, t).abs()
                                                         < CHORD_TOL).all())
            ok = ok and bool((self._chord_df(o0, d0, q, n, t) > 1e-9).all())
        if not ok:
            return rim
        t = t - self._chord_f(o0, d0, p0, path_q, q, n, t) / self._chord_df(o0, d0, q, n, t).detach()
        e = (o0 + t[..., None] * d0).reshape(-1, 3)
        return RimImages(theta, e[:, 2], e, (p0 + n * t).reshape(-1))

    @staticmethod
    def _chord_f(o0, d0, p0, path_q, q, n, t):
        x = o0 + t[..., None] * d0
        return p0 + n * t + n * torch.linalg.vector_norm(q - x, dim=-1) - path_q

    @staticmethod
    def _chord_df(o0, d0, q, n, t):
        x = o0 + t[..., None] * d0
        r = q - x
        return n * (1.0 - (d0 * r).sum(-1) / torch.linalg.vector_norm(r, dim=-1))

    @staticmethod
    def _aim(optics, at, q, wl, n):
        """The directions (…, 3) after the stop, at the rim points ``at.o``, of the rays that meet the sensor
        plane at ``q`` (Newton rounds over the x, y direction cosines, finite-difference Jacobian), detached; None
        when the rounds do not converge."""
        si = optics.stop_index
        o = at.o.detach()
        d = at.d.detach().clone()
        sz = torch.sign(d[..., 2:])
        e = CHORD_FD
        with torch.no_grad():
            for _ in range(CHORD_ROUNDS):
                dx = torch.stack([d[..., :2], d[..., :2] + torch.tensor([e, 0.0], dtype=d.dtype, device=d.device),
                                  d[..., :2] + torch.tensor([0.0, e], dtype=d.dtype, device=d.device)], 0)
                dz = sz * torch.sqrt((1.0 - (dx * dx).sum(-1, keepdim=True)).clamp_min(1e-12))
                trial = RayBundle.create(o.expand(3, *o.shape), torch.cat([dx, dz], -1), at.wavelength)
                h = optics.trace(trial, start=si + 1, apertures=False).propagate_to_z(q[2], n)
                if not bool(h.valid.all()):
                    return None
                pts = h.o[..., :2]
                miss = pts[0] - q[:2]
                if float(miss.abs().max()) < CHORD_TOL:
                    return d
                jac = torch.stack([(pts[1] - pts[0]) / e, (pts[2] - pts[0]) / e], -1)  # (…, 2 out, 2 in)
                step = (torch.linalg.pinv(jac) @ miss[..., None])[..., 0].clamp(-CHORD_MAX_STEP, CHORD_MAX_STEP)
                xy = d[..., :2] - step
                d = torch.cat([xy, sz * torch.sqrt((1.0 - (xy * xy).sum(-1, keepdim=True)).clamp_min(1e-12))], -1)
                if not bool(torch.isfinite(d).all()):
                    return None
        return None


class _PlacedSum(torch.autograd.Function):
    """``Σ_j`` of the complex ``parts`` (each its own shape) placed in a zero array of ``shape`` at the
    ``windows`` (a (rows, columns) slice pair each), added in order in place; the backward hands each part its
    window of the gradient (what autograd gives through the in-place slice additions, without cloning the whole
    array once per part)."""

    @staticmethod
    def forward(ctx, shape, windows, *parts):
        env = torch.zeros(shape, dtype=torch.complex128, device=parts[0].device)
        for w, part in zip(windows, parts):
            env[w] += part
        ctx.windows = windows
        return env

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        return (None, None, *[grad[w] for w in ctx.windows])


def _sum_orders(parts, final: DOE, wavelength: float) -> DOEField:
    """The orders' fields ``[(fd, c, K)]`` (``K``: :func:`_absolute_phase`) summed coherently on the union of their
    windows, on the first (strongest) order's carrier; its sensor point, distance and diagnostics."""
    fd0 = parts[0][0]
    k = _TWO_PI / (wavelength * 1e-3)
    boxes = [fd.box for fd, _, _ in parts]
    iy0, iy1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
    ix0, ix1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
    grid = final.sim_grid(1).window(iy0, iy1, ix0, ix1)
    placed = []
    K0 = None
    a0, b0 = fd0.carrier
    for fd, c, K in parts:
        K0 = K.detach() if K0 is None else K0
        a, b = fd.carrier
        gx, gy = fd.grid.coordinates(device=fd0.envelope.device)
        # the carrier change and the absolute phase as a separable phasor: exp(i rx(x)) exp(i ry(y))
        rx = k * fd.n * (a - a0) * gx + k * (K - K0)
        ry = k * fd.n * (b - b0) * gy
        ex, ey = torch.polar(torch.ones_like(rx), rx), torch.polar(torch.ones_like(ry), ry)
        part = (c * ex)[None, :] * fd.envelope * ey[:, None]
        by0, by1, bx0, bx1 = fd.box
        placed.append(((slice(by0 - iy0, by1 - iy0), slice(bx0 - ix0, bx1 - ix0)), part))
    env = _PlacedSum.apply((iy1 - iy0, ix1 - ix0), [w for w, _ in placed], *[q for _, q in placed])
    return DOEField(Field(env, grid, wavelength, fd0.n, fd0.carrier), (iy0, iy1, ix0, ix1), fd0.z, fd0.center,
                    fd0.info, fd0.chief_tan)

