"""The stop's edge diffracting from the exit pupil: the knife-edge Fresnel step to the DOE plane
(:func:`stop_edge_factor`) and the images of the stop's rim (:func:`stop_rim_images`)."""

from __future__ import annotations

import functools
import math
import warnings

import numpy as np
import torch

from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.utils import devices
from raywave.utils.fresnel import fresnel as fresnel_torch
from raywave.utils.fused import compile_enabled, fused
from raywave.utils.phasor import polar


#: default width (Fresnel zones of the exit pupil → DOE distance) of the band around the geometric footprint
#: on the DOE plane that keeps the stop edge's diffraction ripples (see
#: :func:`raywave.hybrid.coherent.exit_pupil.exit_pupil_field`). Off axis the rim rays land far from the chief
#: ray's image (astigmatism: up to 134 µm at 17.5° on the bundled asphere), and edge waves several zones out come
#: back into the PSF crop: 4 zones (the default before 2026-11-28) left 1.5e-3 L1 there, 5 zones 8.8e-4
RIPPLE_ZONES = 5.0

#: the most Fresnel zones :func:`ripple_band` widens the band to (the double Gauss at full field needs ~11: its
#: band converges at 12, 12 vs 16 zones 6e-5 of its PSF; issue 47)
MAX_RIPPLE_ZONES = 16.0

#: :func:`ripple_band`: the band reaches this many Fresnel zones beyond the edge waves' reach at the crop's centre.
#: The fixed 5-zone band holds every measured case whose reach is at most 5.1 (the bundled asphere at 17.5°, 2.8, and
#: its 6×6×3 map's corners up to 3.9; the F/1.3 asphere at 0.7 / 1.0 field, 3.9 / 5.1: 8.2e-4 / 2.5e-4 / 4.5e-4 rel
#: L1 from converged references), so the band is the reach itself where that is wider (those cases keep 5 zones bit
#: for bit, the F/1.3 asphere at full field 5.09). 1 zone more took the double Gauss at full field from 6.8e-4 to
#: 6.0e-4 but the F/1.3 asphere at full field to a 12.6 GiB DOE-plane window (6.1 zones; 2.0e-4 there)
REACH_MARGIN = 0.0

#: :func:`edge_reach_many` where the PSF crop lies inside the stop rim rays' ring on the sensor (a sensor far from
#: their focus: every rim ray lands beyond the crop's reach, and the ring winds round the crop's centre; class J of
#: docs/ray-wave.md): the band reaches this many Fresnel zones beyond the edge waves' reach, and at least
#: :data:`DEFOCUS_BAND_ZONES`. There every rim point's edge wave reaches the crop (an axial caustic of the edge
#: waves: on axis they carry as much light as the geometric wave), and so does the band's own roll-off, which the
#: in-focus rule (the reach itself) leaves as an error of the crop's order. Measured (session xxxi, rel L1 from
#: converged references; benchmarks/defocused_sensor.py): the doublet of tests/test_midsystem_zmx.py 5.5 mm past
#: its focus (~100 waves), its DOE plane 5 / 10 / 20 mm after the lens (reach 2.2 / 2.8 / 4.3 zones): the reach's
#: band (5 zones) 3.3e-4 / 2.6e-3 / 1.38e-1, 3 zones beyond it 3.0e-4 / 3.5e-4 / 3.5e-3, 4 zones 7.7e-5 / 1.9e-4 /
#: 1.44e-3 (the Fresnel step's own limit there: 5 zones 1.42e-3), and the exact construction's rim step (reach
#: 0.75) 6.4e-3 with its 4 zones, 3.4e-3 with 4.75, 7.5e-4 with 5.75, 1.9e-4 with 8
DEFOCUS_TAIL_ZONES = 4.0
#: the narrowest band (Fresnel zones) :func:`edge_reach_many` allows a crop inside the rim rays' ring
#: (:data:`DEFOCUS_TAIL_ZONES`)
DEFOCUS_BAND_ZONES = 8.0

#: :func:`ripple_band` where the edge waves' reach at the crop's centre is short (issue 47's cost): the band is the
#: reach plus :data:`REACH_TAIL_ZONES`, at least this many zones and at most :data:`RIPPLE_ZONES`. The 5-zone band
#: was set by the bundled asphere at 17.5° (reach 2.81: 4 zones 2.6e-3, 5 zones 8.2e-4 rel L1 from the converged
#: Huygens reference); nearer the axis the reach is shorter and 4 zones hold as 5 do (2026-12-01, h47c: the bundled
#: asphere at 0 / 7 / 10°, reach 0.06 / 0.51 / 0.98: 7.7e-5 / 1.5e-4 / 1.7e-4 against 5.5e-5 / 1.4e-4 / 1.6e-4 with
#: 5 zones; 3.5 zones 1.4e-4 / 2.1e-4 / 2.4e-4). Equal to :data:`RIPPLE_ZONES`: the fixed band of before
RIPPLE_MIN_ZONES = 4.0

#: :func:`ripple_band`: Fresnel zones kept beyond the edge waves' reach where the band is narrower than
#: :data:`RIPPLE_ZONES`. The reach is taken at the crop's centre only, and the crop's other pixels receive edge waves
#: from farther out: the 50 mm singlet at 0.7 field (reach 1.86, the sensor at the DOE's pitch) needs ~4.5 zones
#: (4.06 / 4.25 / 4.5 / 4.75 / 5: 1.26e-3 / 9.4e-4 / 7.4e-4 / 6.3e-4 / 5.7e-4), the bundled asphere at 17.5° (reach
#: 2.81) 5 (4 zones 2.6e-3); 2.2 zones beyond the reach (the roll-off's :data:`ROLL_ZONES` and a little more) were too
#: few for the singlet, 3 hold both (h47c, 2026-12-01)
REACH_TAIL_ZONES = 3.0

#: Fresnel zones over which the ripple band rolls off to 0 at its outer end (its shape hardly matters, its
#: extent does: at 17.5° full weight out to 3 zones and a roll-off over 1 / 1.5 / 2 zones: 1.5e-3 / 1.1e-3 /
#: 8.8e-4 L1 from the Huygens PSF)
ROLL_ZONES = 2.0

#: below this many values :func:`_fresnel_threads` evaluates in the calling thread
_FRESNEL_CHUNK = 65536

#: band samples per chunk of the knife-edge factor's forward arithmetic (its temporaries' size)
_BAND_CHUNK = 1 << 17


def _fresnel_threads(x):
    """scipy's Fresnel integrals ``(C, S)`` of a float64 numpy array, split over torch's intra-op thread count (the
    ufunc releases the GIL: on 2 threads it halves the Fresnel step's largest single cost); the values are those of
    one call."""
    from concurrent.futures import ThreadPoolExecutor

    from scipy.special import fresnel

    c_, s_ = np.empty_like(x), np.empty_like(x)
    parts = min(torch.get_num_threads(), x.size // _FRESNEL_CHUNK)
    if parts <= 1:
        fresnel(x, out=(s_, c_))
        return c_, s_
    bounds = np.linspace(0, x.size, parts + 1).astype(int)

    def run(i):
        sl = slice(bounds[i], bounds[i + 1])
        fresnel(x[sl], out=(s_[sl], c_[sl]))

    with ThreadPoolExecutor(parts) as pool:
        list(pool.map(run, range(parts)))
    return c_, s_


#: where the knife-edge factor's Fresnel integrals are evaluated on the CPU: "table" (:func:`_fresnel_table_values`:
#: quintic Hermite interpolation of scipy's values and their first two derivatives on a fine grid, ~1.5–3× faster than
#: scipy, within 5e-16 of it on |x| ≤ 8 and 3.5e-14 on |x| ≤ 22.7, the widest band's), "scipy"
#: (:func:`_fresnel_threads`, cephes on the host) or "torch" (:func:`raywave.utils.fresnel.fresnel`, ~70 whole-array
#: torch operations; on an accelerator always, with no device → host → device round trip). Measured A/B in one
#: process (benchmarks/fresnel_ab.py, issue 47, 2026-11-30) on a 10×10×3 map's band values: torch 0.88× scipy's time
#: on 1 thread, but on 2 threads of a loaded machine 13–200× (each of its operations on ~80 k values is an OpenMP
#: region that waits for the second thread to be scheduled; scipy's runs such arrays on one thread); PSFs ≤ 3.6e-16
#: rel L1 apart. The table since issue 47's twelfth session (h47g; scipy's own cost is mostly its libm sin/cos)
FRESNEL_CPU = "table"

#: :func:`_fresnel_table`'s grid step: the quintic Hermite interpolation's error is ~h⁶/46080·max|f⁽⁶⁾|,
#: |f⁽⁶⁾| ≈ (π|x|)⁵: ~1e-16 at |x| = 8, ~4e-14 at 22.7 (the band's largest |ν|, √2·:data:`MAX_RIPPLE_ZONES`); a
#: cubic table as accurate needs 2⁻¹³ (8× the rows: it falls out of the cache between the envelope's blocks)
FRESNEL_TABLE_STEP = 2.0**-10  # a power of two (:func:`_fresnel_table_values`' exact positions)
#: :func:`_fresnel_table`'s smallest half-range (it doubles up to :data:`FRESNEL_TABLE_MAX`, beyond which
#: :func:`_fresnel_table_values` takes scipy's values): 8 covers the default 5-zone band (|ν| ≤ 7.1)
FRESNEL_TABLE_HALF = 8.0
FRESNEL_TABLE_MAX = 32.0


@functools.lru_cache(maxsize=4)
def _fresnel_table(half: float) -> torch.Tensor:
    """The quintic (Hermite) polynomials of ``(C, S)`` on each interval of the grid ``x_i = −half + i·h`` (h =
    :data:`FRESNEL_TABLE_STEP`): float64 ``(12, n − 1)``, column i ``(c0 … c5, s0 … s5)`` with ``C(x_i + t·h) = Σ
    c_j t^j`` for t in [0, 1], matching scipy's ``C``, ``S`` at both nodes and their exact first and second derivatives
    (``C' = cos u``, ``S' = sin u``, ``C'' = −πx sin u``, ``S'' = πx cos u``, ``u = πx²/2``). A memo of a pure
    function: built once per range (1.5 MB for ``half`` 8)."""
    from scipy.special import fresnel

    step = FRESNEL_TABLE_STEP
    x = -half + step * np.arange(int(round(2 * half / step)) + 1)
    s_, c_ = fresnel(x)
    ph = 0.5 * np.pi * (x * x)  # x² exact on this grid
    cos_, sin_ = np.cos(ph), np.sin(ph)
    rows = []
    for f, d1, d2 in ((c_, cos_, -np.pi * x * sin_), (s_, sin_, np.pi * x * cos_)):
        f0, f1 = f[:-1], f[1:]
        m0, m1 = step * d1[:-1], step * d1[1:]
        q0, q1 = step * step * d2[:-1], step * step * d2[1:]
        df = f1 - f0
        rows += [f0, m0, 0.5 * q0,
                 10.0 * df - 6.0 * m0 - 4.0 * m1 - 1.5 * q0 + 0.5 * q1,
                 -15.0 * df + 8.0 * m0 + 7.0 * m1 + 1.5 * q0 - q1,
                 6.0 * df - 3.0 * m0 - 3.0 * m1 - 0.5 * q0 + 0.5 * q1]
    return torch.from_numpy(np.stack(rows, 0))


def _fresnel_table_values(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Fresnel integrals ``(C, S)`` of ``v`` (float64, CPU, 1-D) from :func:`_fresnel_table` (one gather of each
    value's interval's coefficients and two quintics: ~30 whole-array operations), or scipy's beyond |x| ≥
    :data:`FRESNEL_TABLE_MAX`."""
    if v.numel() == 0:
        return v.clone(), v.clone()
    lo, hi = (float(e) for e in v.aminmax())  # (one pass, no |v| array)
    top = max(-lo, hi)
    if not (top < FRESNEL_TABLE_MAX and lo == lo and hi == hi):  # (NaN too)
        return tuple(torch.from_numpy(a) for a in _fresnel_threads(v.numpy()))
    half = FRESNEL_TABLE_HALF
    while top >= half:
        half *= 2.0
    tab = _fresnel_table(half)
    # the position in steps, v/h, and its fraction t are exact (h a power of two): the same t, and so the same values
    # bit for bit, whichever half-range's table a call uses (a batch of windows and each window alone)
    pos = v * (1.0 / FRESNEL_TABLE_STEP)
    i = pos.floor()
    t = pos.sub_(i)
    # in 0 … 2·half/h − 1 = the table's last interval: −half ≤ v < half (|v| ≤ top < half)
    idx = i.long().add_(round(half / FRESNEL_TABLE_STEP))
    out = []
    for k in (0, 6):  # Horner, each coefficient gathered into a contiguous array (~2× faster than one gather of rows)
        f = tab[k + 5].index_select(0, idx).mul_(t)
        for j in (4, 3, 2, 1):
            f.add_(tab[k + j].index_select(0, idx)).mul_(t)
        out.append(f.add_(tab[k].index_select(0, idx)))
    return out[0], out[1]


def _fresnel_integrals(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Fresnel integrals ``(C, S)`` of ``v`` (detached; ``v``'s dtype and device): torch's
    (:func:`raywave.utils.fresnel.fresnel`) on an accelerator, on the CPU the backend :data:`FRESNEL_CPU`."""
    v = v.detach()
    if devices.accelerator(v) or FRESNEL_CPU == "torch":
        return tuple(t.to(v.dtype) for t in fresnel_torch(v))
    if FRESNEL_CPU == "table":
        return tuple(t.to(v.dtype).reshape(v.shape) for t in _fresnel_table_values(v.to(torch.float64).reshape(-1)))
    if FRESNEL_CPU != "scipy":
        raise ValueError(f"FRESNEL_CPU must be 'table', 'scipy' or 'torch', got {FRESNEL_CPU!r}")
    return tuple(torch.from_numpy(a).to(v.dtype) for a in _fresnel_threads(v.numpy()))


def _smoothstep(t: torch.Tensor) -> torch.Tensor:
    t = t.clamp(0.0, 1.0)
    return t * t * t * (10.0 + t * (6.0 * t - 15.0))


def _smoothstep_(t: torch.Tensor) -> torch.Tensor:
    """:func:`_smoothstep` of ``t`` (overwritten: clamped), the same values bit for bit, in a new tensor."""
    t.clamp_(0.0, 1.0)
    q = t * 6.0
    q.sub_(15.0).mul_(t).add_(10.0)
    p = t * t
    return p.mul_(t).mul_(q)


#: the edge wave's tail inside the beam is kept up to this many times the outer band's Fresnel parameter (4√2 with
#: 5 ripple zones: further in moves the bundled asphere's L1 from the Huygens PSF by < 3e-6)
INNER_TAIL = 0.8


def _nu_inner(ripple_zones: float) -> float:
    """Fresnel parameter inside the beam beyond which the edge wave's tail is dropped."""
    return INNER_TAIL * math.sqrt(2.0) * ripple_zones


#: :func:`_zone_estimate`'s floor of 0.1 on the convergence holds over at most this distance (mm) from the edge: beyond
#: (an edge at :data:`EXIT_PUPIL_FAR`, a telecentric lens's) the floor would make the 10 m edge a 1 m one, whose zone is
#: ~3× the beam's own (``d·r/(d + r) → r``) and whose node grid the memory refused (the Sigma 8-16 mm DC file on axis,
#: 8.4 GiB of nearest-node fill); every edge within it keeps its estimate
ZONE_FLOOR_DISTANCE = 1e3


def _zone_estimate(wavelength: float, n: float, dz: float, dz_focus: float, alpha: float, beta: float) -> float:
    """Upper estimate (mm) of the stop edge's Fresnel zone on the DOE plane ``sqrt(λ/n·|L|)`` (see
    :func:`_fresnel_scale`) from the chief ray: ``L = dz·M/cos³θ`` with the convergence ``M`` towards a focus
    ``dz_focus`` beyond the edge's plane (at least 0.1 (0.1·:data:`ZONE_FLOOR_DISTANCE`/|dz| for an edge farther
    than it), at most 1), 30 % wider for the marginal rays' tilt."""
    floor = 0.1 * min(1.0, ZONE_FLOOR_DISTANCE / max(abs(dz), 1e-12))
    m = min(max(abs(dz_focus - dz) / max(abs(dz_focus), 1e-12), floor), 1.0)
    cos2 = max(1.0 - alpha * alpha - beta * beta, 0.1)
    return 1.3 * math.sqrt(wavelength * 1e-3 / n * abs(dz) * m / cos2**1.5)


def _fresnel_scale(slopes, nx, ny, h_node: float, dz: float, lam_m: float, pitch: float) -> torch.Tensor:
    """Fresnel scale ``g = sqrt(2 / (λ_m L))`` (1/mm) of the stop's edge at the DOE-plane nodes (ky, kx), so that
    ``ν = g · s`` (s: signed DOE-plane distance to the edge's geometric shadow) is the knife-edge's Fresnel
    parameter.

    The edge is sharp on a plane ``dz`` mm before the DOE plane (the exit pupil); the wave runs along the local
    ray (direction cosines ``t``, ``γ``; straight lines in the image medium of wavelength ``λ_m = λ/n``). In the
    DOE-plane coordinates along the edge's normal ``n̂`` the knife-edge diffracts over the effective length

        ``L = dz · q · M``,  ``q = (1 − (n̂ × t)²) / γ³``,  ``M = |K⁻ᵀ n̂|``,  ``K = ∂x_edge/∂x_doe = I − dz ∇(t/γ)``:

    ``q`` the tilted plane wave's Fresnel length in plane coordinates (the angular spectrum's second order about
    the ray: ``1/γ³`` across the tilt, ``1/γ`` along it), ``M`` the local magnification of the edge's normal
    distance from the edge's plane to the DOE plane (a converging wave: the Fresnel scaling theorem,
    ``L = d (R − d)/R`` for a sphere of radius R). ``L`` is kept ≥ ``(1.5 p)²/λ_m`` so that the edge is never
    sharper than 1.5 pixels (anti-aliasing when the DOE sits at the exit pupil). Args: ``slopes`` (4, ky, kx):
    ``t_x/γ, t_y/γ, t_x, t_y`` at the nodes; ``nx, ny`` (ky, kx) the edge normal (or (M, ky, kx): M directions at
    once, e.g. across and along the edge); ``h_node`` node spacing (mm). Differentiable with respect to the ray
    directions."""
    _, _, tx, ty = slopes
    grads = torch.gradient(slopes[:2], spacing=h_node, dim=(1, 2))
    return _fresnel_scale_at(grads, (tx, ty), (nx, ny), dz, lam_m, (1.5 * pitch) ** 2 / lam_m)


def _fresnel_scale_at(grads, t: tuple, normal: tuple, dz, lam_m, min_length) -> torch.Tensor:
    """:func:`_fresnel_scale` from the node-grid differences of the slopes ``grads`` = ``((da/dy, db/dy), (da/dx,
    db/dx))`` (``a, b = t_x/γ, t_y/γ``), the direction cosines ``t`` = ``(t_x, t_y)``, the edge normal ``normal`` =
    ``(nx, ny)``, ``dz`` (mm, a float or a map), ``lam_m`` (mm) and the shortest length ``min_length`` mm (``(1.5
    p)²/λ_m``): floats, or tensors that broadcast (many constructions at once, each with its own; the same
    arithmetic)."""
    (da_dy, db_dy), (da_dx, db_dx) = grads
    tx, ty = t
    nx, ny = normal
    k00, k01, k10, k11 = 1 - dz * da_dx, -dz * da_dy, -dz * db_dx, 1 - dz * db_dy
    det = k00 * k11 - k01 * k10
    det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    mx = (k11 * nx - k10 * ny) / det
    my = (-k01 * nx + k00 * ny) / det
    m_n = torch.sqrt(mx * mx + my * my + 1e-300)
    g2 = (1 - tx * tx - ty * ty).clamp_min(1e-6)
    q = (1 - (nx * ty - ny * tx) ** 2) / (g2 * torch.sqrt(g2))
    length = (abs(dz) * q * m_n).clamp_min(min_length)
    return torch.sqrt(2.0 / (lam_m * length))


def stop_edge_factor(nu: torch.Tensor, dz: float, ripple_zones: float, g: torch.Tensor, pitch: float,
                     kappa: torch.Tensor | None = None) -> torch.Tensor:
    """The knife-edge Fresnel diffraction factor (complex128, same shape as ``nu``) that multiplies the
    geometric-optics field near the stop edge's shadow on the DOE plane.

    ``D(ν) = ((1 − i)/2)·[(C(ν) + ½) + i(S(ν) + ½)]`` (Fresnel integrals; ``exp(−iωt)``: the kernel
    ``exp(+iπν²/2)``): 1 deep in the beam, ½ on the geometric edge (¼ of the intensity), → 0 in the shadow;
    its complex conjugate when the DOE plane lies before the edge's plane (``dz < 0``). Kept: the band
    ``ν ≥ −ν_max``, ``ν_max = ripple_zones·√2`` (ripple_zones Fresnel zones outside the shadow's edge, rolled off
    over the last :data:`ROLL_ZONES`), and the edge wave's tail inside the beam up to ``ν_b = min(INNER_TAIL·ν_max,
    0.6/(g p))`` (beyond, its fringes near the grid's Nyquist frequency and it leaves the PSF crop), blended
    smoothly to 1 from ``ν_b/2``. ``kappa``: the edge's curvature in Fresnel units, ``κ/g`` (``κ = −∇·n̂`` (1/mm)
    the curvature of the edge's level lines, > 0 for a convex aperture, ``g`` (1/mm) the Fresnel scale across the
    edge; ``κ·g/g_t²`` where the scale along the edge ``g_t`` differs); a curved edge's factor to first order in
    ``ε = kappa/2``: the edge wave ``D − step`` converges (inside) or spreads (outside) like a cylindrical wave,
    amplitude ``sqrt(1 + ν·kappa)``, plus the term :func:`curved_edge_term` that is left on and near the shadow's
    edge, where that factor is 1. Evaluated on the band only (1 inside, 0 outside). Differentiable with respect
    to ``ν`` and ``kappa`` (exactly)."""
    inside, idx, nb, nu_max = _edge_band(nu, ripple_zones, g, pitch)
    out = inside.to(torch.complex128)
    if idx[0].numel() == 0:
        return out
    kap = None if kappa is None else kappa[idx]
    re, im = _EdgeBand.apply(nu[idx], kap, nb, nu_max, dz >= 0)
    return out.index_put_(idx, torch.complex(re, im))  # in place: ``out`` is new and carries no graph


def _band_masks(nu: torch.Tensor, ripple_zones: float, g, pitch: float):
    """``(inside, band, ν_b, ν_max)`` of the knife-edge factor on ``ν`` (detached): ``inside`` (bool) where the factor
    is 1 (ν ≥ ν_b, ν_b from the local scale ``g`` (1/mm, a tensor or one value) and ``pitch`` mm: the band the grid
    resolves), ``band`` (bool) where it is evaluated (−ν_max < ν < ν_b; ν_max = √2 · ``ripple_zones``).
    ``ripple_zones`` a tensor: per-row constants of a batch of windows stacked by rows (issue 43, the batched field
    stage): ``ripple_zones`` and ``g`` (R, 1) float64, one value per row of ``nu`` (R, N); ν_b and ν_max are then
    (R, 1), each row's the values its own window's floats give (true divisions, as on the host)."""
    nu_b, nu_max = _band_limits(ripple_zones, g, pitch)
    nu = nu.detach()
    inside = nu >= nu_b
    outer = nu > -nu_max
    if isinstance(ripple_zones, torch.Tensor) or ripple_zones < 0:
        return inside, outer & ~inside, nu_b, nu_max
    # inside lies within ν > −ν_max (ν_b ≥ 2 > 0 ≥ −ν_max): the band is the one without the other, an exclusive or
    return inside, outer.logical_xor_(inside), nu_b, nu_max


def _band_limits(ripple_zones, g, pitch: float):
    """``(ν_b, ν_max)`` of :func:`_band_masks` (floats, or tensors for tensor constants)."""
    nu_max = math.sqrt(2.0) * ripple_zones
    if isinstance(ripple_zones, torch.Tensor):  # per-row constants: the host formula below, row by row
        nu_b = torch.maximum(torch.minimum(torch.full_like(g, 0.6) / (g * pitch), _nu_inner(ripple_zones)),
                             torch.full_like(g, 2.0))
    elif isinstance(g, torch.Tensor):
        nu_b = torch.clamp(0.6 / (g.detach() * pitch), max=_nu_inner(ripple_zones)).clamp_min(2.0)
    else:  # one value for the whole window
        nu_b = max(min(0.6 / (float(g) * pitch), _nu_inner(ripple_zones)), 2.0)
    return nu_b, nu_max


def _edge_band(nu: torch.Tensor, ripple_zones: float, g, pitch: float):
    """Where :func:`stop_edge_factor` is 1 and where it is evaluated: ``(inside (bool, nu's shape), idx (the band
    samples' indices, a tuple of int64 tensors), nb (the band's ν_b, float64 (B,)), ν_max)`` (from ``ν`` detached:
    no graph)."""
    inside, band, nu_b, nu_max = _band_masks(nu, ripple_zones, g, pitch)
    nu = nu.detach()
    idx = band.nonzero(as_tuple=True)
    nb = nu_b.expand(nu.shape)[idx] if isinstance(nu_b, torch.Tensor) else torch.full(
        idx[0].shape, nu_b, dtype=nu.dtype, device=nu.device)
    if isinstance(nu_max, torch.Tensor):  # per-row constants (:func:`_band_masks`): each band sample's own
        nu_max = nu_max.expand(nu.shape)[idx]
    return inside, idx, nb, nu_max


def edge_envelope(amp: torch.Tensor, angle: torch.Tensor, nu: torch.Tensor, dz: float, ripple_zones: float, g,
                  pitch: float, kappa: torch.Tensor | None = None, scale: tuple | None = None) -> torch.Tensor:
    """``polar(amp, angle) · stop_edge_factor(nu, dz, ripple_zones, g, pitch, kappa)`` (complex128, the shape of
    ``amp``): the geometric envelope times the knife edge, the same values, with a hand-written backward when
    autograd records it (a trainable lens). Autograd would keep ~14 window-sized arrays (the phasor, the factor,
    both factors of their product, the band's indices and terms); this keeps the four inputs and the band's
    Fresnel integrals, and recomputes the rest (no Fresnel integral: their derivatives are ``cos``, ``sin``).
    ``ripple_zones`` and ``g`` may be (R, 1) tensors for the inputs (R, N): the windows of a batch stacked by rows,
    each row with its own window's constants (:func:`_band_masks`; the batched field stage, issue 43). On the CPU
    forward and backward each run as one compiled loop over the window (:func:`_envelope_dense`, issue 47: a single
    PSF's envelope 43 → 24 ms), with ``RAYWAVE_COMPILE=0`` as the eager band arithmetic below (the same values to
    ~2e-16 relative).

    ``scale`` ``(cov, k)``: ``amp`` and ``angle`` are then the amplitude before a coverage ``cov`` (``amp``'s shape, or
    None: 1) and the phase φ (mm) with ``k`` (1/mm, a float): the envelope of ``amp·cov`` and ``k·φ``, the same
    values bit for bit (two exact products). Without a graph and in the compiled loop (:func:`_dense_plan`) the two
    products are taken inside it, on strided crops as they come (issue 47: no window-sized product or contiguous copy
    before the loop); otherwise formed here first."""
    graph = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (amp, angle, nu, kappa)
                                            + (() if scale is None or scale[0] is None else (scale[0],)))
    consts = (dz >= 0, ripple_zones, g, pitch)
    if scale is not None:
        cov, k = scale
        plan = None if graph else _dense_plan(nu, consts)
        if plan is not None:
            return _dense_values_scaled((amp, cov, angle, k), nu, kappa, plan)
        amp, angle = (amp if cov is None else amp * cov), k * angle
    if not graph:  # the same blocks as with a graph: the same values bit for bit (a replay compares the two)
        return _EdgeEnvelope.values(amp, angle, nu, kappa, consts, False)[0]
    return _EdgeEnvelope.apply(amp, angle, nu, kappa, dz >= 0, ripple_zones, g, pitch)


#: rows per block of :class:`_EdgeEnvelope` (its window-sized temporaries exist a block at a time): at least this
#: many, and as many as :data:`ENVELOPE_BLOCK_SAMPLES` allows
ENVELOPE_BLOCK_ROWS = 64
#: samples per block of :class:`_EdgeEnvelope` (~15 temporaries of 8–16 bytes each: ~25 MB): a window of up to
#: this many samples is one block (issue 43: each block costs ~25 dispatched ops). 2¹⁷ since issue 47 (2¹⁹ before): the
#: bundled asphere's single PSF (845 × 1040 samples) in 7 blocks instead of 2, a fifth of the page faults (30 k → 6 k
#: per PSF, 42 → 24 ms of system time), the same values
ENVELOPE_BLOCK_SAMPLES = 2**17
#: :data:`ENVELOPE_BLOCK_SAMPLES` on an accelerator (CUDA: every op a kernel launch, memory aplenty; ~200 bytes of
#: temporaries a sample, ~6 GB): a batch of the field stage's windows (:func:`~raywave.hybrid.coherent.accurate.
#: _fine_field_batch`) in a few blocks (each ~170 dispatched ops); on a CUDA device at most a 2048th of its memory in
#: samples (:func:`_block_rows`: ~10 % of it; 2²³ on 16 GB, today's size there)
ENVELOPE_BLOCK_SAMPLES_ACCELERATOR = 2**25


def _block_rows(nu: torch.Tensor) -> int:
    """Rows per block of :class:`_EdgeEnvelope` for the window ``nu`` ((ny, nx) or 1-D): at least
    :data:`ENVELOPE_BLOCK_ROWS`, as many as the device's block size (:data:`ENVELOPE_BLOCK_SAMPLES` on the CPU,
    :data:`ENVELOPE_BLOCK_SAMPLES_ACCELERATOR` elsewhere) allows. The values do not depend on it (elementwise)."""
    samples = ENVELOPE_BLOCK_SAMPLES_ACCELERATOR if devices.accelerator(nu) else ENVELOPE_BLOCK_SAMPLES
    if nu.device.type == "cuda":
        samples = max(ENVELOPE_BLOCK_SAMPLES, min(samples, torch.cuda.get_device_properties(nu.device).total_memory
                                                  // 2048))
    return max(ENVELOPE_BLOCK_ROWS, samples // max(nu.shape[-1] if nu.ndim > 1 else 1, 1))


class _EdgeEnvelope(torch.autograd.Function):
    """:func:`edge_envelope` with autograd: ``z = a·e^{iθ}·D(ν, κ/g)``; ``∂z/∂a = e^{iθ}D``, ``∂z/∂θ = i z``, and
    ``∂/∂ν``, ``∂/∂(κ/g)`` of ``D`` on the band (:meth:`_EdgeBand.grads`). Forward and backward run in blocks of
    :data:`ENVELOPE_BLOCK_ROWS` rows or more (:data:`ENVELOPE_BLOCK_SAMPLES`; elementwise: the same values); the band's Fresnel integrals are computed once,
    in the forward, and kept (in the band's row-major order, so a block's are a contiguous slice)."""

    @staticmethod
    def values(amp, angle, nu, kap, consts, keep_fresnel: bool = True):
        """``(z (complex128, nu's shape), the band's Fresnel integrals (C, S) or None without ``keep_fresnel``)``
        (no graph), block by block (:meth:`_block_values`; the backward walks the same blocks); or, where
        :func:`_dense_plan` allows, the whole window as one compiled loop (:func:`_envelope_dense`; the Fresnel
        integrals then ``None``: the backward recomputes them in its own loop)."""
        plan = _dense_plan(nu, consts)
        if plan is not None:
            return _dense_values(amp, angle, nu, kap, plan), None
        out = torch.empty(nu.shape, dtype=torch.complex128, device=nu.device)
        g = consts[2]
        step = _block_rows(nu)
        parts = []
        for r in range(0, nu.shape[0], step):
            rows = slice(r, r + step)
            fr = _EdgeEnvelope._block_values(amp[rows] if amp.ndim else amp, angle[rows], nu[rows],
                                             None if kap is None else kap[rows],
                                             (consts[0], _rows(consts[1], rows), _rows(g, rows), consts[3]),
                                             out[rows])
            if keep_fresnel and fr is not None:
                parts.append(fr)
        if not keep_fresnel:
            return out, None
        if not parts:
            empty = torch.empty(0, dtype=torch.float64, device=nu.device)
            return out, (empty, empty)
        return out, tuple(torch.cat(t) for t in zip(*parts))

    @staticmethod
    def _block_values(amp, angle, nu, kap, consts, out):
        """``polar(amp, angle)·D`` of one block of rows written into ``out`` (complex128, the block's shape; the values
        of :meth:`_block`'s factor times :func:`polar`, bit for bit): the band selected with one mask, the factor's
        real and imaginary parts scattered into two real arrays and the complex product taken in real arithmetic
        (torch's own: ``(x·Re D − y·Im D) + i(y·Re D + x·Im D)``). Returns the block band's Fresnel integrals
        ``(C, S)`` (None where it has none)."""
        forward_edge, ripple_zones, g, pitch = consts
        inside, band, nu_b, nu_max = _band_masks(nu, ripple_zones, g, pitch)  # _edge_band's, as masks
        nu = nu.detach()
        x, y = torch.cos(angle), torch.sin(angle)
        x.mul_(amp)  # polar's parts: cos·amp, sin·amp
        y.mul_(amp)
        re_out, im_out = torch.view_as_real(out).unbind(-1)
        d_re = inside.to(x.dtype).contiguous()  # (written through a flat view below)
        # the band's samples by their flat indices (row-major: masked_select's order), gathered and scattered back
        # with index_select / index_copy_: the same values, ~half masked_select's and masked_scatter_'s time
        idx = band.reshape(-1).nonzero().squeeze(1)
        if idx.numel() == 0:
            torch.mul(x, d_re, out=re_out)
            torch.mul(y, d_re, out=im_out)
            return None

        take = _BandTake(nu, idx, nu_b)
        v = take(nu)
        nb = take(nu_b) if isinstance(nu_b, torch.Tensor) else nu_b
        if isinstance(nu_max, torch.Tensor):  # per-row constants (:func:`_band_masks`)
            nu_max = take(nu_max)
        fresnel = _fresnel_integrals(v)
        re, im = _EdgeBand._values(v, None if kap is None else take(kap.detach()), nb, *fresnel, nu_max, forward_edge)
        d_re.view(-1).index_copy_(0, idx, re)
        d_im = torch.zeros(x.shape, dtype=x.dtype, device=x.device)
        d_im.view(-1).index_copy_(0, idx, im)
        torch.mul(x, d_re, out=re_out)
        re_out.sub_(y * d_im)
        torch.mul(y, d_re, out=im_out)
        im_out.add_(x.mul_(d_im))
        return fresnel

    @staticmethod
    def forward(ctx, amp, angle, nu, kap, forward_edge: bool, ripple_zones: float, g, pitch: float):
        ctx.consts = (forward_edge, ripple_zones, g, pitch)
        out, fresnel = _EdgeEnvelope.values(amp, angle, nu, kap, ctx.consts)
        ctx.dense = fresnel is None  # the compiled loop's forward: its backward the compiled loop's too
        # a view of a larger tensor (the accurate construction's interpolated channels: ν and κ/g are two of four,
        # before the crop to the lit window) would keep all of it: keep compact copies instead
        ctx.save_for_backward(amp, angle, *(_compact(t) for t in (nu, kap)), *(fresnel or ()))
        return out

    @staticmethod
    def backward(ctx, grad):
        amp, angle, nu, kap, *fresnel = ctx.saved_tensors
        forward_edge, ripple_zones, g, pitch = ctx.consts
        need = ctx.needs_input_grad
        if ctx.dense:
            return _dense_backward(grad, (amp, angle, nu, kap), ctx.consts, need)
        g_amp = torch.empty_like(amp) if need[0] else None
        g_angle = torch.empty_like(angle) if need[1] else None
        g_nu = torch.zeros_like(nu) if need[2] else None
        g_kap = torch.zeros_like(kap) if need[3] and kap is not None else None
        start, step = 0, _block_rows(nu)
        for r in range(0, nu.shape[0], step):
            rows = slice(r, r + step)
            consts = (forward_edge, _rows(ripple_zones, rows), _rows(g, rows), pitch)
            k = _EdgeEnvelope._block_grads(grad[rows], (amp[rows] if amp.ndim else amp, angle[rows], nu[rows],
                                                        None if kap is None else kap[rows]),
                                           (fresnel, start), consts,
                                           tuple(None if t is None else t[rows] for t in (g_amp, g_angle, g_nu, g_kap)))
            start += k
        return g_amp, g_angle, g_nu, g_kap, None, None, None, None

    @staticmethod
    def _block_grads(grad, inputs: tuple, fresnel: tuple, consts, outs: tuple) -> int:
        """One block of rows of the backward, written into ``outs`` = ``(∂L/∂a, ∂L/∂θ, ∂L/∂ν, ∂L/∂(κ/g))`` (views of
        the block's rows, or None; ``∂L/∂ν`` and ``∂L/∂(κ/g)`` zero-filled: written on the band) from the output's
        gradient ``grad`` (complex128) and ``inputs`` = ``(a, θ, ν, κ/g or None)`` of the block. ``fresnel`` =
        ``((C, S) of the whole window's band, the block's first band sample)``. With ``q = conj(G)·e^{iθ}`` (real
        arithmetic, one window-sized pass): ``∂L/∂a = Re(q·D)``, ``∂L/∂θ = −a·Im(q·D)`` (``Re(conj(G)·i·z)``) and on
        the band ``∂L/∂D = conj(q)·a`` (:meth:`_EdgeBand.grads`); ``D`` is 1 / 0 off the band. The band's samples by
        flat row-major indices, as :meth:`_block_values`. Returns the block's number of band samples."""
        forward_edge, ripple_zones, g, pitch = consts
        amp, angle, nu, kap = inputs
        g_amp, g_angle, g_nu, g_kap = outs
        inside, band, nu_b, nu_max = _band_masks(nu, ripple_zones, g, pitch)
        idx = band.reshape(-1).nonzero().squeeze(1)
        cos_, sin_ = torch.cos(angle), torch.sin(angle)
        gr = torch.view_as_real(grad)
        g_re, g_im = gr[..., 0], gr[..., 1]
        q_re = g_re * cos_
        q_re.addcmul_(g_im, sin_)  # Re(conj(G)·e^{iθ}) = G_r cos θ + G_i sin θ
        q_im = sin_.mul_(g_re)
        q_im.sub_(cos_.mul_(g_im))  # Im(conj(G)·e^{iθ}) = G_r sin θ − G_i cos θ
        del cos_, sin_
        d_re = inside.to(torch.float64)
        k = idx.numel()
        if k == 0:  # D real: Re(q·D) = q_re·D, Im(q·D) = q_im·D
            if g_amp is not None:
                torch.mul(q_re, d_re, out=g_amp)
            if g_angle is not None:
                torch.mul(q_im, d_re, out=g_angle).mul_(amp).neg_()
            return 0
        fr, start = fresnel
        take = _BandTake(nu, idx, nu_b)
        v = take(nu.detach())
        nb = take(nu_b) if isinstance(nu_b, torch.Tensor) else nu_b
        if isinstance(nu_max, torch.Tensor):
            nu_max = take(nu_max)
        cv = None if kap is None else take(kap.detach())
        c_, s_ = fr[0][start:start + k], fr[1][start:start + k]
        if g_amp is not None or g_angle is not None:
            re, im = _EdgeBand._values(v, cv, nb, c_, s_, nu_max, forward_edge)
            d_re.view(-1).index_copy_(0, idx, re)
            d_im = torch.zeros_like(d_re)
            d_im.view(-1).index_copy_(0, idx, im)
            del re, im
            if g_amp is not None:  # Re(q·D) = q_re·D_re − q_im·D_im
                torch.mul(q_re, d_re, out=g_amp).sub_(q_im * d_im)
            if g_angle is not None:  # −a·Im(q·D) = −a·(q_re·D_im + q_im·D_re)
                torch.mul(q_re, d_im, out=g_angle).addcmul_(q_im, d_re).mul_(amp).neg_()
            del d_im
        if g_nu is None and g_kap is None:
            return k
        a_b = take(amp.detach()) if amp.ndim else amp.detach()
        gd_re = take(q_re).mul_(a_b)  # ∂L/∂D = conj(q)·a on the band
        gd_im = take(q_im).mul_(a_b).neg_()
        gv, gc = _EdgeBand.grads(v, cv, nb, c_, s_, nu_max, forward_edge, gd_re, gd_im, g_kap is not None)
        if g_nu is not None:
            g_nu.view(-1).index_copy_(0, idx, gv)
        if g_kap is not None:
            g_kap.view(-1).index_copy_(0, idx, gc)
        return k


class _BandTake:
    """The band samples of a block's arrays by their flat row-major indices ``idx`` (:meth:`_EdgeEnvelope.
    _block_values`): ``take(t)`` for ``t`` of the block's shape ``nu.shape`` (or broadcast to it), or a per-row
    constant ``(R, 1)`` gathered by each band sample's row (not expanded to the block's size first: two block-sized
    copies less at the peak), the same values."""

    def __init__(self, nu: torch.Tensor, idx: torch.Tensor, nu_b):
        self.shape, self.idx = nu.shape, idx
        self.row = None
        if nu.ndim == 2 and isinstance(nu_b, torch.Tensor) and tuple(nu_b.shape) == (nu.shape[0], 1):
            self.row = torch.div(idx, nu.shape[1], rounding_mode="floor")

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        if self.row is not None and t.shape[-1] == 1:
            return t.reshape(-1).index_select(0, self.row)
        return t.expand(self.shape).reshape(-1).index_select(0, self.idx)


def _rows(c, rows: slice):
    """A constant of :class:`_EdgeEnvelope` for a block of ``rows``: a tensor's rows (per-row or per-sample values),
    a float as it is."""
    return c[rows] if isinstance(c, torch.Tensor) else c


def _compact(t: torch.Tensor | None) -> torch.Tensor | None:
    """``t``, or a copy of it when it is a view into a larger storage (so that saving it does not keep that alive)."""
    if t is None or t._base is None or t._base.numel() == t.numel():
        return t
    return t.clone(memory_format=torch.contiguous_format)


def _smoothstep_slope(t: torch.Tensor) -> torch.Tensor:
    """d/dt of :func:`_smoothstep`: ``30 t²(1 − t)²`` on (0, 1), 0 outside."""
    inside = (t > 0) & (t < 1)
    return torch.where(inside, 30.0 * t * t * (1.0 - t) ** 2, torch.zeros_like(t))


#: largest |κ/g| in a curved edge's first-order term (:func:`curved_edge_term`); beyond (a small obscuration or
#: stop) the step is approximate anyway: :data:`raywave.hybrid.coherent.accurate.EDGE_CURVATURE_LIMIT` warns
KAPPA_MAX = 0.5


def curved_edge_term(v: torch.Tensor, d_re, d_im, forward_edge: bool, cos_sin=None):
    """``(Re, Im)`` of the bracket ``B = ν(D − H) + ((1 + i)/2π)·e^{iπν²/2}`` (its conjugate for ``forward_edge``
    False) of a curved edge's first-order term ``c = −(κ/2g)·B`` at ``ν`` = ``v``, from the knife edge ``D`` =
    ``(d_re, d_im)`` and the step ``H = [ν > 0]``.

    Why: near a circle of radius ``a = 1/κ`` the lit region is ``x > −ν + ε y²`` in Fresnel units (``ε = κ/2g``);
    the first order in ``ε`` of the Fresnel integral over it is ``−ε·((1 + i)/2π)·e^{iπν²/2}`` at every ``ν``.
    The spreading factor ``sqrt(1 + sκ)`` on ``D − H`` (:class:`_EdgeBand`) holds its far part; ``c`` is the rest:
    ``O(ε/ν²)`` away from the edge, ``−ε(1 + i)/2π`` on it (0.5 % of the field on the bundled asphere's edge).
    ``∂B/∂ν = D − H`` (the chirps' derivatives cancel). ``cos_sin``: ``(cos, sin)`` of ``πν²/2`` when the caller
    has them."""
    if cos_sin is None:
        ph = 0.5 * math.pi * v * v
        cos_sin = (torch.cos(ph), torch.sin(ph))
    cos_, sin_ = cos_sin
    b_re = v * torch.where(v > 0, d_re - 1.0, d_re) + (cos_ - sin_) / (2.0 * math.pi)
    b_im = v * d_im + (cos_ + sin_) / (2.0 * math.pi) * (1.0 if forward_edge else -1.0)
    return b_re, b_im


class _EdgeBand(torch.autograd.Function):
    """The knife-edge factor on the band samples, ``(Re, Im)`` of ``(D·f + c)·w_out`` in the shadow (``ν ≤ 0``)
    and of ``(1 + ((D − 1)·f + c)·w_in)·w_out`` inside, with ``D`` the Fresnel knife edge (its mirror for
    ``forward_edge`` False), ``f = sqrt(1 + clamp(ν κ/g))`` the curvature's spreading, ``c = −(κ/2g)·B`` the curved
    edge's first-order term (:func:`curved_edge_term`; ``κ/g`` clamped to ±:data:`KAPPA_MAX`), ``w_out``/``w_in``
    the band's smooth roll-offs (see :func:`stop_edge_factor`). A hand-written backward that recomputes the few
    band-sized terms it needs from ``ν`` and ``κ/g``: autograd would keep ~20 of them per PSF (the largest share of
    the Fresnel step's extra memory in a lens-trained backward), this keeps two."""

    @staticmethod
    def _terms(v, kap, nb, nu_max: float):
        t_out = (v + nu_max) / (ROLL_ZONES * math.sqrt(2.0))
        t_in = (v - 0.5 * nb) / (0.5 * nb)
        w_out, w_in = _smoothstep(t_out), 1.0 - _smoothstep(t_in)  # w_in = 1 in the shadow (v ≤ 0)
        if kap is None:
            return t_out, t_in, w_out, w_in, None, None
        sk = v * kap  # s·κ
        ok = (sk >= -0.9) & (sk <= 3.0)  # the clamp passes the gradient on its closed range
        return t_out, t_in, w_out, w_in, torch.sqrt(1.0 + sk.clamp(-0.9, 3.0)), ok

    @staticmethod
    def _knife(c_, s_, forward_edge: bool):
        """``(Re D, Im D)`` from the Fresnel integrals: ``D = (1 − i)/2·(a + ib)`` (``forward_edge``) or its mirror
        ``(1 + i)/2·(a − ib)``, ``a = C + ½``, ``b = S + ½``."""
        a, b = c_ + 0.5, s_ + 0.5
        return 0.5 * a + 0.5 * b, (0.5 * b - 0.5 * a if forward_edge else 0.5 * a - 0.5 * b)

    @staticmethod
    def _values(v, kap, nb, c_, s_, nu_max: float, forward_edge: bool):
        """``(Re, Im)`` of the factor on band samples (the forward's arithmetic): the terms of :meth:`_knife`,
        :meth:`_terms` and :func:`curved_edge_term` in their order, written in place (the same values bit for bit,
        at ~60 % of the time: no band-sized array is allocated per operation). ``nb``: a tensor, or one float for
        the whole band."""
        pos = v > 0
        ha = c_ + 0.5
        ha.mul_(0.5)
        hb = s_ + 0.5
        hb.mul_(0.5)
        d_re = ha + hb  # Re D = ½a + ½b
        d_im = hb.sub_(ha) if forward_edge else ha.sub_(hb)  # Im D = ±(½b − ½a)
        t = v + nu_max
        w_out = _smoothstep_(t.div_(ROLL_ZONES * math.sqrt(2.0)))
        h = 0.5 * nb
        t = v - h
        w = _smoothstep_(t.div_(h))
        w.neg_().add_(1.0)  # w_in = 1 − smoothstep
        w.mul_(w_out)  # w = w_out·w_in
        if kap is None:
            m = w
        else:  # m = w·sqrt(1 + clamp(ν κ/g))
            m = v * kap
            m.clamp_(-0.9, 3.0).add_(1.0).sqrt_().mul_(w)
        step = pos.to(d_re.dtype)  # H = [ν > 0]: 1 or 0 (one conversion; a product with a bool array is ~4× slower)
        e_re = torch.sub(d_re, step)  # the edge wave D − H
        re = e_re * m
        re.add_(w_out.mul_(step))  # w_out + (D − 1)·m inside, D·m in the shadow
        im = d_im * m
        if kap is None:
            return re, im
        ph = v * (0.5 * math.pi)
        ph.mul_(v)
        cos_, sin_ = torch.cos(ph), ph.sin_()
        b_re = v * e_re  # curved_edge_term's bracket
        b_re.add_(torch.sub(cos_, sin_).div_(2.0 * math.pi))
        cos_.add_(sin_).div_(2.0 * math.pi)
        b_im = v * d_im
        b_im.add_(cos_ if forward_edge else cos_.neg_())
        e = kap.clamp(-KAPPA_MAX, KAPPA_MAX)
        e.mul_(-0.5).mul_(w)
        re.add_(b_re.mul_(e))
        im.add_(b_im.mul_(e))
        return re, im

    @staticmethod
    def forward(ctx, v, kap, nb, nu_max: float, forward_edge: bool):
        c_, s_ = _fresnel_integrals(v)
        re, im = torch.empty_like(v), torch.empty_like(v)
        # in chunks: the ~15 band-sized temporaries of the arithmetic stay small (elementwise: the same values)
        for a in range(0, v.numel(), _BAND_CHUNK):
            sl = slice(a, a + _BAND_CHUNK)
            re[sl], im[sl] = _EdgeBand._values(v[sl], None if kap is None else kap[sl], nb[sl], c_[sl], s_[sl],
                                               nu_max, forward_edge)
        ctx.save_for_backward(v, kap, nb, c_, s_)
        ctx.nu_max, ctx.forward_edge = nu_max, forward_edge
        return re, im

    @staticmethod
    def backward(ctx, g_re, g_im):
        v, kap, nb, c_, s_ = ctx.saved_tensors
        g_v, g_k = _EdgeBand.grads(v, kap, nb, c_, s_, ctx.nu_max, ctx.forward_edge, g_re, g_im,
                                   ctx.needs_input_grad[1])
        return g_v, g_k, None, None, None

    @staticmethod
    def grads(v, kap, nb, c_, s_, nu_max: float, forward_edge: bool, g_re, g_im, need_kap: bool):
        """The gradients ``(∂L/∂ν, ∂L/∂(κ/g) or None)`` on the band samples from those of ``(Re, Im)`` of the
        factor (``c_``, ``s_`` the Fresnel integrals at ``v``)."""
        # the compiled loop's arithmetic with the edge's direction as a sign (the same bits as the branches)
        g_v, g_k = _band_grads(v, kap, nb, (c_, s_), nu_max, 1.0 if forward_edge else -1.0, (g_re, g_im))
        return g_v, (g_k if need_kap else None)


@functools.lru_cache(maxsize=4)
def _fresnel_table_rows(half: float) -> torch.Tensor:
    """:func:`_fresnel_table` by rows, ``(n − 1, 12)`` contiguous: an interval's 12 coefficients side by side (the
    compiled loop's indexed loads of a sample's coefficients then hit one or two cache lines, not twelve: 5.3 vs 8.3
    ms for 880 k values)."""
    return _fresnel_table(half).t().contiguous()


def _fresnel_table_cs(v, rows, offset):
    """``(C, S)`` of ``v`` from the table ``rows`` (:func:`_fresnel_table_rows`; ``offset`` = its half-range in steps)
    for ``|v|`` below its half-range: :func:`_fresnel_table_values`' arithmetic (exact positions, Horner in the same
    order) as whole-array operations, for :func:`_envelope_dense`'s compiled loop (the gathers are indexed loads
    there)."""
    pos = v * (1.0 / FRESNEL_TABLE_STEP)
    i = pos.floor()
    t = pos - i
    idx = i.long() + offset
    out = []
    for k in (0, 6):
        f = rows[idx, k + 5] * t
        for j in (4, 3, 2, 1):
            f = (f + rows[idx, k + j]) * t
        out.append(f + rows[idx, k])
    return out[0], out[1]


def _factor_terms(v, kap, nb, nu_max, fresnel, sign: float):
    """``(Re, Im)`` of the knife-edge factor at band values ``v``: :meth:`_EdgeBand._values`' arithmetic in its
    order, without its in-place writes (for a compiled loop); ``fresnel`` = ``(C, S)`` at ``v``, ``sign`` 1.0 for
    ``forward_edge``, else −1.0 (a product: exactly the mirrored difference; one compiled graph for both)."""
    c_, s_ = fresnel
    ha = (c_ + 0.5) * 0.5
    hb = (s_ + 0.5) * 0.5
    d_re = ha + hb
    d_im = (hb - ha) * sign
    w_out = _smoothstep((v + nu_max) / (ROLL_ZONES * math.sqrt(2.0)))
    h = 0.5 * nb
    w = (1.0 - _smoothstep((v - h) / h)) * w_out
    m = w if kap is None else torch.sqrt((v * kap).clamp(-0.9, 3.0) + 1.0) * w
    step = (v > 0).to(v.dtype)
    e_re = d_re - step
    re = e_re * m + w_out * step
    im = d_im * m
    if kap is None:
        return re, im
    ph = (v * (0.5 * math.pi)) * v
    cos_, sin_ = torch.cos(ph), torch.sin(ph)
    b_re = v * e_re + (cos_ - sin_) / (2.0 * math.pi)
    b_im = v * d_im + (cos_ + sin_) / (2.0 * math.pi) * sign
    e = kap.clamp(-KAPPA_MAX, KAPPA_MAX) * -0.5 * w
    return re + b_re * e, im + b_im * e


def _dense_band(nu, kap, nb, nu_max, tab, offset, sign: float):
    """``(band, Re D, Im D, (C, S))`` of the knife-edge factor ``D`` on a whole window (:func:`_envelope_dense`):
    ``band`` where it is evaluated (−ν_max < ν < ν_b), ``D`` 1 inside (ν ≥ ν_b) and 0 beyond; the Fresnel
    integrals and the factor's terms are computed everywhere (one loop: cheaper than gathering the band) and kept on
    the band (ν is 0 off it: every table index in range, no NaN)."""
    inside = nu >= nb
    band = (nu > -nu_max) & ~inside
    v = torch.where(band, nu, 0.0)
    fresnel = _fresnel_table_cs(v, tab, offset)
    re, im = _factor_terms(v, kap, nb, nu_max, fresnel, sign)
    return band, v, torch.where(band, re, inside.to(nu.dtype)), torch.where(band, im, 0.0), fresnel


@fused
def _envelope_dense(amp, angle, nu, kap, nb, nu_max, tab, offset: int, sign: float):
    """``polar(amp, angle)·D(ν, κ/g)`` (:func:`edge_envelope`) of a whole window as one compiled loop: its real and
    imaginary parts (float64, ``nu``'s shape): ``nb`` (ν_b) and ``nu_max`` tensors broadcasting to ``nu`` (per
    window, per row or per sample), ``tab`` the Fresnel table (:func:`_fresnel_table_rows`) covering the band,
    ``offset`` its half-range in table steps, ``sign`` 1.0 for a forward edge (``dz ≥ 0``), else −1.0. The values of
    :meth:`_EdgeEnvelope._block_values` to rounding (the compiled loop's sin/cos)."""
    _, _, d_re, d_im, _ = _dense_band(nu, kap, nb, nu_max, tab, offset, sign)
    x = torch.cos(angle) * amp
    y = torch.sin(angle) * amp
    # two outputs, not one stacked (..., 2): an interleaved store keeps the loop from vectorising (8× slower)
    return x * d_re - y * d_im, y * d_re + x * d_im


@fused
def _envelope_dense_scaled(fine: tuple, nu, kap, nb, nu_max, tab, offset: int, sign: float):
    """:func:`_envelope_dense` of ``amp·cov`` and ``k·φ`` from ``fine`` = ``(amp, cov or None, φ, k (a 0-dim
    tensor))``: the two products inside the loop (the same values: exact products), the inputs strided as they
    come (:func:`edge_envelope`'s ``scale``)."""
    amp, cov, phi, k = fine
    a = amp if cov is None else amp * cov
    angle = k * phi
    _, _, d_re, d_im, _ = _dense_band(nu, kap, nb, nu_max, tab, offset, sign)
    x = torch.cos(angle) * a
    y = torch.sin(angle) * a
    return x * d_re - y * d_im, y * d_re + x * d_im


@fused
def _envelope_dense_grads(grad: tuple, amp, angle, nu, kap, nb, nu_max, tab, offset: int, sign: float):
    """The backward of :func:`_envelope_dense` as one compiled loop: ``(∂L/∂a, ∂L/∂θ, ∂L/∂ν, ∂L/∂(κ/g) or None)``
    from the output's gradient ``grad`` = ``(g_re, g_im)``: :meth:`_EdgeEnvelope._block_grads`' arithmetic (``q =
    conj(G)·e^{iθ}``, ``∂L/∂a = Re(q·D)``, ``∂L/∂θ = −a·Im(q·D)``, on the band :meth:`_EdgeBand.grads`' of
    ``∂L/∂D = conj(q)·a``), the band's Fresnel integrals recomputed from the table. All four always (one graph)."""
    g_re, g_im = grad
    cos_, sin_ = torch.cos(angle), torch.sin(angle)
    q_re = g_re * cos_ + g_im * sin_
    q_im = sin_ * g_re - cos_ * g_im
    band, v, d_re, d_im, fresnel = _dense_band(nu, kap, nb, nu_max, tab, offset, sign)
    g_amp = q_re * d_re - q_im * d_im
    g_angle = -((q_re * d_im + q_im * d_re) * amp)
    gv, gk = _band_grads(v, kap, nb, fresnel, nu_max, sign, (q_re * amp, -(q_im * amp)))
    return g_amp, g_angle, torch.where(band, gv, 0.0), None if gk is None else torch.where(band, gk, 0.0)


def _band_grads(v, kap, nb, fresnel, nu_max, sign: float, grads: tuple):
    """:meth:`_EdgeBand.grads` (both gradients, ``∂L/∂(κ/g)`` None without ``kap``) with the edge's direction as
    ``sign`` (1.0 / −1.0: products, the same values as its branches) for :func:`_envelope_dense_grads`."""
    g_re, g_im = grads
    c_, s_ = fresnel
    t_out, t_in, w_out, w_in, f, ok = _EdgeBand._terms(v, kap, nb, nu_max)
    a, b = c_ + 0.5, s_ + 0.5
    d_re, d_im = 0.5 * a + 0.5 * b, (0.5 * b - 0.5 * a) * sign
    ph = 0.5 * math.pi * v * v  # C' = cos, S' = sin
    cos_, sin_ = torch.cos(ph), torch.sin(ph)
    dd_re, dd_im = 0.5 * (cos_ + sin_), sign * 0.5 * (sin_ - cos_)
    dw_out = _smoothstep_slope(t_out) / (ROLL_ZONES * math.sqrt(2.0))
    dw_in = -_smoothstep_slope(t_in) / (0.5 * nb)
    w = w_out * w_in
    dw = dw_out * w_in + w_out * dw_in
    lit = v > 0
    e_re = torch.where(lit, d_re - 1.0, d_re)  # the edge wave D − H
    if kap is None:
        m, dm = w, dw
    else:
        m, dm = w * f, dw * f + w * torch.where(ok, 0.5 * kap / f, torch.zeros_like(f))
    dre = torch.where(lit, dw_out, torch.zeros_like(dw_out)) + dd_re * m + e_re * dm
    dim = dd_im * m + d_im * dm
    if kap is None:
        return g_re * dre + g_im * dim, None
    # curved_edge_term's bracket B; d(c·w)/dν = ∂c/∂ν·w + c·dw/dν, c = e·B, ∂B/∂ν = D − H
    b_re = v * e_re + (cos_ - sin_) / (2.0 * math.pi)
    b_im = v * d_im + (cos_ + sin_) / (2.0 * math.pi) * sign
    e = -0.5 * kap.clamp(-KAPPA_MAX, KAPPA_MAX)
    dre = dre + e * (e_re * w + b_re * dw)
    dim = dim + e * (d_im * w + b_im * dw)
    df = torch.where(ok, 0.5 * v / f, torch.zeros_like(f)) * w  # ∂f/∂(κ/g)·w
    de = torch.where((kap >= -KAPPA_MAX) & (kap <= KAPPA_MAX), -0.5 * w, torch.zeros_like(w))  # ∂e/∂(κ/g)·w
    return g_re * dre + g_im * dim, g_re * (e_re * df + b_re * de) + g_im * (d_im * df + b_im * de)


def _dense_plan(nu: torch.Tensor, consts, compiled: bool = True):
    """Whether :class:`_EdgeEnvelope` runs as one compiled loop (:func:`_envelope_dense`): on the CPU, with the
    Fresnel table (:data:`FRESNEL_CPU`) covering the band (|ν| < max(ν_max, ν_b) ≤ :data:`FRESNEL_TABLE_MAX`: every
    band of :data:`MAX_RIPPLE_ZONES` or fewer), compiling switched on (``RAYWAVE_COMPILE``) and not failed. Returns
    ``(ν_b, ν_max (tensors broadcasting to ν), the table, its half-range in steps)`` or None (the blocks of
    :meth:`_EdgeEnvelope._block_values`: eager arithmetic on the band's samples alone, the faster one uncompiled).
    One host read of ν_b's and ν_max's largest value where they are per-row tensors. ``compiled`` False: without
    the compile switches (the backward of a compiled forward)."""
    if compiled and (nu.device.type != "cpu" or FRESNEL_CPU != "table" or nu.dtype != torch.float64
                     or not compile_enabled() or _envelope_dense._failed or nu.numel() == 0 or nu.ndim == 0):
        return None
    forward_edge, ripple_zones, g, pitch = consts
    nb, nm = (_per_row(c, nu) for c in _band_limits(ripple_zones, g, pitch))
    top = float(torch.maximum(nb.abs().max(), nm.abs().max()))
    if not top <= FRESNEL_TABLE_MAX:  # (NaN too)
        return None
    half = FRESNEL_TABLE_HALF
    while top > half:
        half *= 2.0
    return nb, nm, _fresnel_table_rows(half), round(half / FRESNEL_TABLE_STEP), 1.0 if forward_edge else -1.0


def _per_row(c, nu: torch.Tensor) -> torch.Tensor:
    """A constant of the knife-edge band (a float, or a tensor broadcasting to ``nu``) as a tensor for
    :func:`_envelope_dense`: a float or a 0-dim tensor as an ``(R, 1, …)`` column (``nu``'s rows), the same graph as
    a batch's per-row constants (issue 43) and so the same values bit for bit; a tensor otherwise as it is."""
    if isinstance(c, torch.Tensor) and c.ndim:
        return c.detach()
    return torch.full((nu.shape[0],) + (1,) * (nu.ndim - 1), float(c), dtype=torch.float64, device=nu.device)


def _dense_args(amp, angle, nu, kap, plan):
    """The detached inputs of :func:`_envelope_dense` (and its backward) from :class:`_EdgeEnvelope`'s and a
    :func:`_dense_plan`."""
    # contiguous (a copy only of a strided crop): fewer stride patterns, fewer compiled graphs (torch.compile's limit)
    return (amp.detach().contiguous(), angle.detach().contiguous(), nu.detach().contiguous(),
            None if kap is None else kap.detach().contiguous(), plan[0], plan[1])


#: samples per call of :func:`_envelope_dense` (its real and imaginary parts exist a block at a time before they
#: are written into the complex result: 2 × 32 MB, not 2 × 8 bytes a sample of a 64 M-sample window)
DENSE_BLOCK_SAMPLES = 1 << 22


def _dense_values(amp, angle, nu, kap, plan) -> torch.Tensor:
    """The envelope (complex128, ``nu``'s shape) from :func:`_envelope_dense` in blocks of rows
    (:func:`_in_row_blocks`); elementwise, the same values whatever the blocks."""
    amp, angle, nu, kap, nb, nm = _dense_args(amp, angle, nu, kap, plan)
    return _in_row_blocks(nu, lambda r: _envelope_dense(*(r(t) for t in (amp, angle, nu, kap, nb, nm)), *plan[2:]))


def _dense_values_scaled(fine: tuple, nu, kap, plan) -> torch.Tensor:
    """:func:`_dense_values` of :func:`_envelope_dense_scaled` (``fine`` = ``(amp, cov or None, φ, k float)``, the
    window-sized inputs as they come: no contiguous copy), in the same blocks of rows."""
    amp, cov, phi, k = fine
    kt = torch.tensor(float(k), dtype=torch.float64, device=nu.device)  # (a tensor: one graph for every wavelength)
    return _in_row_blocks(nu, lambda r: _envelope_dense_scaled((r(amp), r(cov), r(phi), kt),
                                                               *(r(t) for t in (nu, kap, plan[0], plan[1])),
                                                               *plan[2:]))


def _in_row_blocks(nu: torch.Tensor, loop) -> torch.Tensor:
    """The complex128 array (``nu``'s shape) whose real and imaginary parts ``loop(r)`` computes, without autograd,
    in blocks of rows of about :data:`DENSE_BLOCK_SAMPLES` (an even split: never a one-row block, which would compile
    a graph of its own). ``r(t)``: the block's rows of an input ``t`` of the window's rows (anything else, a 0-dim or
    None, as it is); one block: the inputs whole."""
    rows = nu.shape[0]
    n = max(1, min(rows // 2, -(-nu.numel() // DENSE_BLOCK_SAMPLES)))
    with torch.no_grad():  # (detached inputs; one graph whether or not autograd records the call)
        if n == 1:
            return torch.complex(*loop(lambda t: t))
        out = torch.empty(nu.shape, dtype=torch.complex128, device=nu.device)
        bounds = [round(i * rows / n) for i in range(n + 1)]
        for a, b in zip(bounds[:-1], bounds[1:]):
            def r(t, a=a, b=b):
                return t[a:b] if t is not None and t.ndim == nu.ndim and t.shape[0] == rows else t
            torch.complex(*loop(r), out=out[a:b])
    return out


def _dense_backward(grad, inputs: tuple, consts, need):
    """:meth:`_EdgeEnvelope.backward` of the compiled loop's forward (:func:`_envelope_dense_grads`)."""
    amp, angle, nu, kap = inputs
    plan = _dense_plan(nu, consts, compiled=False)  # (the same loop's arithmetic, eager if compiling is off now)
    with torch.no_grad():
        # the gradient's real and imaginary planes as two fresh contiguous arrays: the incoming gradient is often a
        # strided view (of a crop, a stack's slice) whose row stride, storage offset and base's shape vary from
        # call to call, and each new pattern recompiled the loop (~1-3 s with inductor's disk cache, ~20 s without;
        # once or twice per model call of a map; issue 43, xxviii); two copies of the window, the same values
        gr = torch.view_as_real(grad.resolve_conj())
        g = _envelope_dense_grads((gr[..., 0].clone(memory_format=torch.contiguous_format),
                                   gr[..., 1].clone(memory_format=torch.contiguous_format)),
                                  *_dense_args(amp, angle, nu, kap, plan), *plan[2:])
    return (g[0].sum_to_size(amp.shape) if need[0] else None, g[1] if need[1] else None, g[2] if need[2] else None,
            g[3] if need[3] else None, None, None, None, None)


#: stop-rim points at which :func:`stop_rim_images` finds the edge's image
RIM_POINTS = 64
#: the engine's stop-edge images lie at most this far (mm) from the DOE plane: an exit pupil or a rim image farther
#: away on either side, or at infinity (an image-space telecentric lens: the rays through a rim point leave parallel),
#: is placed at this distance before the plane, along its ray. The edge's Fresnel length on the DOE plane, ``d·r/(d +
#: r)`` for an edge ``d`` mm before it and a focus ``r`` mm after it, has the same limit ``r`` from either side and is
#: then within ``r/d`` of it, and the construction's margins stay finite; near-parallel rays put a telecentric lens's
#: rim images at ±tens of metres at random, and left on their sides they made one rim of two far halves (the
#: Telecentric Tandem file: 1.03e-2 on axis that way, 7.7e-5 placed before the plane). Issue 47 class D (2026-12-01):
#: the two ideal lenses with B's focus on the stop and a Fresnel DOE, 1.8e-4 / 3.3e-4 from the wave truth at 0° / 2°
#: (tests/test_ideal_lens_truth.py; B 11.99 mm behind A, its pupil 14 m away: 2.1e-4 / 2.2e-4 placed here, 1.8e-4 where
#: it lies); the telecentric lens file of US 4,929,066 (pupil 3.4 m before the DOE) 2.30e-4 / 1.75e-4 at 0 / 0.7
#: field from the converged Huygens PSF. Until then a pupil over 1 m away made the default fall back to the DOE-plane
#: edge: 4.9e-2 / 3.82e-3 there
EXIT_PUPIL_FAR = 1e4
#: the source nudge of :func:`stop_rim_images`' central differences, relative to the lens's largest field: small
#: enough that the rim images do not depend on the field's units (an angle or an object height naming the same
#: source agree to ~1e-10 in the PSF), large enough for float64 rays
RIM_NUDGE = 1e-5


def stop_rim_images(lens, field, wavelength: float, depth, field_type: str | None = None, k: int = RIM_POINTS,
                    bound: tuple | None = None):
    """Where the stop's rim is sharp, seen by one source: z (mm) of the image of every rim point along the ray
    that the source sends through it, ``(theta (k,), z (k,))`` with ``theta`` the rim point's azimuth on the stop
    (``atan2(y, x)`` of the stop coordinates), a :class:`RimImages` that also holds the image points and the
    optical paths to them; None when the rays cannot be traced.

    The image of a stop point P is where the rays through P from neighbouring sources cross (straight lines in
    the image medium, usually extended backwards to a virtual point inside the lens): the exit pupil is the
    image of the stop's centre, but off axis and at the rim the pupil's own aberrations move it (pupil spherical
    aberration, astigmatism). The neighbouring source is displaced along the rim point's radial direction (the
    edge's normal, the direction its Fresnel diffraction runs), to first order from central differences;
    the crossing is the closest approach of the two rays. Differentiable with respect to the lens (the rays are
    traced with autograd when it is on). Many sources at once: :func:`stop_rim_images_many`. ``bound``: ``(z_plane,
    far)`` mm: images farther than ``far`` from the plane (or at infinity) placed that far before it along their rays
    (the engine's :data:`EXIT_PUPIL_FAR` from the DOE plane); None: where they lie."""
    f = torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(1, 2)
    return stop_rim_images_all(lens, f, [float(wavelength)], depth, field_type, k, bound)[0][0]


def stop_rim_images_many(lens, fields, wavelength: float, depth, field_type: str | None = None,
                         k: int = RIM_POINTS) -> list:
    """:func:`stop_rim_images` of the sources ``fields`` (F, 2) at one wavelength (µm), from one trace of all their
    rim rays (5·F sources × k rim points): a list of F results (``(theta, z)`` or None)."""
    return stop_rim_images_all(lens, fields, [float(wavelength)], depth, field_type, k)[0]


def stop_rim_images_all(lens, fields, wavelengths, depth, field_type: str | None = None,
                        k: int = RIM_POINTS, bound: tuple | None = None) -> list:
    """:func:`stop_rim_images` of the sources ``fields`` (F, 2) at every wavelength of ``wavelengths`` (W,) µm, from
    one trace of all their rim rays (5·F sources × W wavelengths × k rim points; issue 43: one trace per call instead
    of one per wavelength): ``[W][F]`` results (``(theta, z)`` or None); ``bound`` as :func:`stop_rim_images`."""
    field_type = field_type or lens.field_type
    f = torch.as_tensor(fields, dtype=torch.float64, device=lens.device).reshape(-1, 2)
    nf = f.shape[0]
    fmax = max([abs(float(v)) for v in getattr(lens, "fields", [])] + [0.0]) or 1.0
    eps = RIM_NUDGE * fmax
    ex = torch.tensor([eps, 0.0], dtype=f.dtype, device=f.device)
    ey = torch.tensor([0.0, eps], dtype=f.dtype, device=f.device)
    # (F, 5, 2) → (5F, 2): each source and its central-difference nudges, source-major
    srcs = torch.stack([f, f + ex, f + ey, f - ex, f - ey], 1).reshape(-1, 2)
    theta = torch.arange(k, dtype=torch.float64, device=lens.device) * (2 * math.pi / k)
    c, s = torch.cos(theta), torch.sin(theta)
    wl = torch.tensor([float(w) for w in wavelengths], dtype=torch.float64, device=lens.device)
    with warnings.catch_warnings():
        # a diagnostic trace of nudged sources through the rim, apertures off: the field construction of the
        # source itself reports its vignetting. Other warnings pass through.
        warnings.simplefilter("ignore", VignettingWarning)
        rays = point_source_rays(lens, srcs, wl, pupil=(c, s), aim="full", depth=depth, field_type=field_type)
        out, rec = lens.trace(rays, apertures=False, record=True)
    nw = wl.numel()
    o, d = out.o.reshape(nf, 5, nw, k, 3), out.d.reshape(nf, 5, nw, k, 3)
    opl = out.opl.reshape(nf, 5, nw, k)
    n_img = lens.surfaces[-1].material.n(wl).to(opl.dtype)  # the image medium's index (W,)
    v = out.valid.reshape(nf, 5, nw, k).all(-1).all(1).tolist()  # (F, W)
    stop = lens.stop_index
    if stop == 0:  # the rays' own directions reach the first surface
        dv = rays.d
    else:
        dv = torch.stack(rec.points[stop + 1], -1) - torch.stack(rec.points[stop], -1)
    dv = dv.reshape(nf, 5, nw, k, 3)
    # every source and wavelength at once: (F·W, 5, k, ...) rows, source-major
    rows = nf * nw
    # a source with an invalid ray is left out: its rows set to ones (through where, so that no NaN of theirs reaches
    # the gradients of the others; its nudges then do not turn the rays) and dropped as degenerate
    live = torch.tensor([v[i][j] for i in range(nf) for j in range(nw)], device=o.device)[:, None, None, None]
    o, d, dv = (torch.where(live, t_, torch.ones_like(t_)) for t_ in
                (t.transpose(1, 2).reshape(rows, 5, k, 3) for t in (o, d, dv)))
    z, points, paths, ok = _rim_crossings(o, d, dv, c, s, (opl[:, 0].reshape(rows, k), n_img.repeat(nf)[:, None]),
                                          bound)
    ok = ok.tolist()
    dirs = d[:, 0]  # (rows, k, 3): the source's own rim rays in the image medium
    # every row's views from one unbind per tensor (issue 43: not four selects a row)
    z, points, paths, dirs = (t.unbind(0) for t in (z, points, paths, dirs))
    return [[RimImages(theta, z[i * nw + j], points[i * nw + j], paths[i * nw + j], dirs[i * nw + j])
             if v[i][j] and ok[i * nw + j] else None for i in range(nf)] for j in range(nw)]


class RimImages(tuple):
    """What :func:`stop_rim_images` returns: the tuple ``(theta, z)`` (rim azimuths on the stop (k,), z (k,) mm of
    each rim point's image) with, as attributes, ``points`` (k, 3) mm (the image point on the source's own ray
    through the rim point), ``opl`` (k,) mm (that ray's optical path from the source to the point) and
    ``directions`` (k, 3) (that ray's unit direction in the image medium), or None."""

    def __new__(cls, theta, z, points=None, opl=None, directions=None):
        obj = super().__new__(cls, (theta, z))
        obj.points, obj.opl, obj.directions = points, opl, directions
        return obj


def _rim_crossings(o, d, dv, c, s, paths: tuple, bound: tuple | None = None):
    """The rim images of B sources at once from their rays (B, 5, k, 3) (each source and its four nudges) through the
    rim points at azimuths with cosines and sines ``c``, ``s`` (k,): ``(z (B, k) mm, image points (B, k, 3), optical
    paths to them (B, k) mm, ok (B,) bool)`` (``paths`` = ``(opl0, n_img)``: ``opl0`` (B, k) the source's rays' paths
    at ``o[:, 0]``, ``n_img`` (B, 1) the image medium's index); ``ok`` False for a degenerate source
    (:func:`_radial_nudge`) or a non-finite crossing. ``bound`` ``(z_plane, far)``: a crossing farther than ``far``
    mm from the plane, or none (parallel rays: a telecentric rim), placed ``far`` before the plane
    (:func:`_bounded_steps`)."""
    opl0, n_img = paths
    w, turns = _radial_nudge(dv, c, s)
    # (B, k, 3): the ray of the source nudged so that its ray through the rim point turns along the rim's normal
    do = w[..., :1] * (o[:, 1] - o[:, 3]) + w[..., 1:] * (o[:, 2] - o[:, 4])
    dd = w[..., :1] * (d[:, 1] - d[:, 3]) + w[..., 1:] * (d[:, 2] - d[:, 4])
    a = d[:, 0]

    def perp(v_):
        return v_ - (v_ * a).sum(-1, keepdim=True) * a

    po, pd = perp(do), perp(dd)
    t = -(po * pd).sum(-1) / (pd * pd).sum(-1).clamp_min(1e-300)
    if bound is not None:
        t = _bounded_steps(t, o[:, 0, :, 2], a[..., 2], (po, pd), bound)
    z = o[:, 0, :, 2] + t * a[..., 2]
    ok = turns & torch.isfinite(z.detach()).all(-1)
    return z, o[:, 0] + t[..., None] * a, opl0 + n_img * t, ok


def _bounded_steps(t: torch.Tensor, oz: torch.Tensor, az: torch.Tensor, turn: tuple, bound: tuple) -> torch.Tensor:
    """The steps ``t`` (B, k) mm along the rays (from ``oz`` (B, k) mm, direction z-cosines ``az``) to their rim
    images, an image farther than ``far`` mm from the plane ``z_plane`` (``bound``) on either side, or at infinity
    (the nudged rays do not turn: ``turn`` = ``(po, pd)`` (B, k, 3), their offset (mm) and turn across them; a turn
    under 1e-12 of the offset puts the image beyond 1e12 mm, and an exact 0 would put it at ``t = 0``), moved to
    ``far`` before the plane (:data:`EXIT_PUPIL_FAR`)."""
    z_plane, far = bound
    po, pd = turn
    before = (z_plane - far - oz) / az
    parallel = (pd * pd).sum(-1).detach() * 1e24 <= (po * po).sum(-1).detach()
    beyond = (oz + t.detach() * az - z_plane).abs() > far
    return torch.where(parallel | beyond, before, t)


def _radial_nudge(dv: torch.Tensor, c: torch.Tensor, s: torch.Tensor):
    """Weights (B, k, 2) of the x and y source nudges (central differences: sources 1, 3 and 2, 4 of the rays'
    directions ``dv`` (B, 5, k, 3) as they arrive at the stop) whose combination turns the ray through each rim
    point along the rim's normal ``(c, s)`` as it arrives at the stop: the edge's image for its normal diffraction,
    the same whatever units (angle, object height) the field takes; and (B,) bool: False where the nudges do not
    turn the rays (a degenerate source; its weights are then meaningless, but finite)."""
    slope = dv[..., :2] / dv[..., 2:3]  # (B, 5, k, 2): the incoming ray's slopes at the stop
    jac = torch.stack([slope[:, 1] - slope[:, 3], slope[:, 2] - slope[:, 4]], -1)  # (B, k, 2 slope, 2 nudge)
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    nonzero = det.detach().abs() > 1e-300
    det = torch.where(nonzero, det, torch.ones_like(det))  # (finite weights, and gradients, for a degenerate source)
    w0 = (jac[..., 1, 1] * c - jac[..., 0, 1] * s) / det
    w1 = (-jac[..., 1, 0] * c + jac[..., 0, 0] * s) / det
    turns = nonzero.all(-1)
    return torch.stack([w0, w1], -1), turns


def _rim_azimuth_index(k: int, xs: torch.Tensor, ys: torch.Tensor):
    """``(i0 (N,) long, w (N,))``: the rim interval ``[i0, i0 + 1]`` (of ``k`` equal azimuth steps) holding the
    azimuth of each stop point (xs, ys) and the fraction ``w`` along it (the stop's centre: azimuth 0)."""
    ok = (xs * xs + ys * ys).detach() > 0
    az = torch.atan2(torch.where(ok, ys, torch.zeros_like(ys)), torch.where(ok, xs, torch.ones_like(xs)))
    u = torch.remainder(az, 2 * math.pi) / (2 * math.pi / k)
    i0 = torch.floor(u.detach()).long().clamp(0, k - 1)
    return i0, u - i0


def _rim_cubic(values: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Per-rim-point ``values`` (k, ...) at the azimuths of stop points (xs, ys) (N,): periodic Catmull–Rom cubic
    interpolation (third order: 64 points on a 1.2 mm circle are interpolated to within 3 nm of it, where linear
    interpolation cuts the chords by 1.4 µm, a shift of the edge that the path difference would feel);
    differentiable. Returns (N, ...)."""
    k = values.shape[0]
    i0, w = _rim_azimuth_index(k, xs, ys)
    p0, p1, p2, p3 = (values[(i0 + j) % k] for j in (-1, 0, 1, 2))
    w = w.reshape(-1, *([1] * (values.ndim - 1)))
    return p1 + 0.5 * w * (p2 - p0 + w * (2 * p0 - 5 * p1 + 4 * p2 - p3 + w * (3 * (p1 - p2) + p3 - p0)))


def _rim_fourier(values: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Per-rim-point ``values`` (k, C) (k equal azimuth steps from 0) at the azimuths of stop points (xs, ys) (N,):
    trigonometric interpolation, (N, C). The rim's images and their optical paths are smooth periodic functions of
    the azimuth (a circle on axis, its first harmonics off axis), so this is exact to the rounding where
    :func:`_rim_cubic` is not (issue 47: 64 points on the double Gauss's 21 mm rim image; the cubic's chords moved
    the edge's path difference by ~0.005 waves, 1.07e-2 rel L1 of its PSF, against 1.06e-3 with 256 points);
    differentiable. The stop's centre gets the azimuth 0."""
    k = values.shape[0]
    ok = (xs * xs + ys * ys).detach() > 0
    az = torch.atan2(torch.where(ok, ys, torch.zeros_like(ys)), torch.where(ok, xs, torch.ones_like(xs)))
    c = torch.fft.rfft(values, dim=0) / k  # (k//2 + 1, C)
    w = torch.full((c.shape[0], 1), 2.0, dtype=values.dtype, device=values.device)
    w[0] = 1.0
    if k % 2 == 0:
        w[-1] = 1.0
    ph = az[:, None] * torch.arange(c.shape[0], dtype=values.dtype, device=values.device)[None, :]  # (N, M)
    return torch.cos(ph) @ (w * c.real) - torch.sin(ph) @ (w * c.imag)


#: :func:`_rim_fourier_rows` evaluates its (B, N, k/2 + 1) harmonics in blocks of rows of at most this many elements
#: (128 MB a float64 array: the cosines, the sines and their phases are the construction's largest node arrays)
RIM_FOURIER_BLOCK = 2**24


def _rim_fourier_rows(values: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """:func:`_rim_fourier` of B rims at once: ``values`` (B, k, C) at the azimuths of the stop points ``xs``, ``ys``
    (B, N) (row b on rim b), (B, N, C), the harmonics in blocks of rows (:data:`RIM_FOURIER_BLOCK`); the same
    arithmetic as each row's own call (up to the last-bit rounding of the vectorised cos, sin and atan2, which depends
    on an element's place in memory). Differentiable."""
    k = values.shape[1]
    ok = (xs * xs + ys * ys).detach() > 0
    az = torch.atan2(torch.where(ok, ys, torch.zeros_like(ys)), torch.where(ok, xs, torch.ones_like(xs)))
    c = torch.fft.rfft(values, dim=1) / k  # (B, k//2 + 1, C)
    m = c.shape[1]
    w = torch.full((m, 1), 2.0, dtype=values.dtype, device=values.device)
    w[0] = 1.0
    if k % 2 == 0:
        w[-1] = 1.0
    wc, ws = w * c.real, w * c.imag
    harmonics = torch.arange(m, dtype=values.dtype, device=values.device)
    rows = max(1, RIM_FOURIER_BLOCK // (xs.shape[1] * m))
    parts = []
    for i in range(0, xs.shape[0], rows):
        ph = az[i:i + rows, :, None] * harmonics  # (b, N, M)
        parts.append(torch.cos(ph) @ wc[i:i + rows] - torch.sin(ph) @ ws[i:i + rows])
    return parts[0] if len(parts) == 1 else torch.cat(parts)


def _rim_z_rows(z: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """:func:`_rim_z` of B rims at once: the rim images' z (B, k) mm at the azimuths of the stop points ``xs``,
    ``ys`` (B, N) (row b on rim b), (B, N); the same arithmetic as each row's own call."""
    k = z.shape[1]
    i0, w = _rim_azimuth_index(k, xs, ys)
    return z.gather(1, i0) * (1 - w) + z.gather(1, (i0 + 1) % k) * w


def _rim_z(rim, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """z of the stop rim's image (:func:`stop_rim_images`) at the azimuth of stop points (xs, ys), periodic linear
    interpolation (differentiable; the stop's centre, where the azimuth is undefined, gets the image of azimuth 0)."""
    theta, z = rim
    k = theta.numel()
    i0, w = _rim_azimuth_index(k, xs, ys)
    return z[i0] * (1 - w) + z[(i0 + 1) % k] * w


def edge_reach_zones(rim, z_doe: float, z_sensor: float, point, lam_m: float, half: float = 0.0,
                     crop_reach: float = 0.0):
    """How far outside (or inside) the geometric shadow on the DOE plane the stop edge's waves that reach a sensor
    point start, in DOE-plane Fresnel zones of the ripple band (:data:`RIPPLE_ZONES`'s unit: ``s / sqrt(λ_m L)``,
    ``L = d (R − d) / R`` with ``d``, ``R`` the rim image's distances to the DOE plane and to the sensor along its rim
    ray): the largest over the rim points whose edge wave is stationary at the point, the inner side divided by
    :data:`INNER_TAIL` (the band's inner tail is that fraction of its outer width); None where the rim images carry no
    ray directions (or a rim ray runs parallel to the planes).

    Edge waves leave each rim image ``E`` on straight lines (the image medium): the one leaving the DOE plane ``s``
    mm outside the shadow's edge ``S`` (along the shadow's outward normal ``n̂``) reaches the sensor at ``L + s·m·n̂``,
    ``L`` the rim ray's landing, ``m = (z_s − z_E) / (z_d − z_E)``. A sensor point ``P`` receives rim point ``j``'s
    edge wave (stationary phase along the rim) where the normal line ``L_j + t·n̂_j`` passes through it: the sign
    changes of ``(P − L_j)·t̂_j`` between consecutive rim points (``t̂`` the tangent), interpolated. ``point`` (2,)
    mm the sensor point (the crop's centre), ``half`` (mm) the crop's half-width (the reach grows by its projection
    on the normal), ``lam_m`` (mm) the wavelength in the image medium, ``crop_reach`` (mm) the crop's half-diagonal
    for a crop inside the rim rays' ring (:func:`edge_reach_many`). No autograd; one host read
    (:func:`edge_reach_many` of the one source)."""
    return edge_reach_many([rim], z_doe, z_sensor, torch.as_tensor(point).reshape(1, 2), [lam_m], half,
                           crop_reach)[0]


def _reach_rows(rims: list):
    """The rim images of ``rims`` that carry ray directions and image points, stacked: ``(rows (indices into rims),
    e (R, k, 3) image points, a (R, k, 3) directions)`` (detached float64), grouped by their rim point count k
    (a list of such triples)."""
    by_k: dict = {}
    for i, rim in enumerate(rims):
        if rim is None or getattr(rim, "directions", None) is None or getattr(rim, "points", None) is None:
            continue
        by_k.setdefault(int(rim.points.shape[0]), []).append(i)
    # stacked, then detached: two ops a group, not two a rim (issue 43)
    return [(rows, torch.stack([rims[i].points for i in rows]).detach().double(),
             torch.stack([rims[i].directions for i in rows]).detach().double()) for rows in by_k.values()]


def edge_reach_many(rims: list, z_doe: float, z_sensor: float, points: torch.Tensor, lam_ms: list,
                    half: float = 0.0, crop_reach: float = 0.0) -> list:
    """:func:`edge_reach_zones` of many sources at once: their rim images ``rims`` (S), sensor points ``points``
    (S, 2) mm and wavelengths in the image medium ``lam_ms`` (S,) mm, on the planes ``z_doe``, ``z_sensor`` (issue 43:
    one host read for a call's sources instead of a few per construction). Returns S values (zones, or None), each the
    arithmetic of the one-source rule on its row. ``crop_reach`` (mm, the PSF crop's half-diagonal; 0: unknown):
    where the crop lies inside the rim rays' ring on the sensor (:func:`crop_inside_ring`) the value is the reach the
    band must cover there, the reach + :data:`DEFOCUS_TAIL_ZONES` and at least :data:`DEFOCUS_BAND_ZONES`."""
    out: list = [None] * len(rims)
    for rows, e, a in _reach_rows(rims):
        idx = torch.tensor(rows, device=e.device)
        pt = points.detach().to(device=e.device, dtype=e.dtype)[idx]  # (R, 2)
        lam = torch.tensor([float(lam_ms[i]) for i in rows], dtype=e.dtype, device=e.device)[:, None]
        ok = (a[..., 2].abs() > 1e-9).all(1)  # (R,)
        az = torch.where(ok[:, None], a[..., 2], torch.ones_like(a[..., 2]))
        t_s = (z_doe - e[..., 2]) / az
        t_l = (z_sensor - e[..., 2]) / az
        ok = ok & (t_s.abs() > 1e-9).all(1) & (t_l.abs() > 1e-9).all(1)
        t_s = torch.where(ok[:, None], t_s, torch.ones_like(t_s))
        t_l = torch.where(ok[:, None], t_l, 2 * torch.ones_like(t_l))
        s_pt = e[..., :2] + t_s[..., None] * a[..., :2]  # (R, k, 2)
        l_pt = e[..., :2] + t_l[..., None] * a[..., :2]
        m = t_l / t_s
        tang = torch.roll(s_pt, -1, 1) - torch.roll(s_pt, 1, 1)
        tang = tang / tang.norm(dim=2, keepdim=True).clamp_min(1e-300)
        normal = torch.stack([tang[..., 1], -tang[..., 0]], 2)
        normal = normal * torch.sign(((s_pt - s_pt.mean(1, keepdim=True)) * normal).sum(2) + 1e-300)[..., None]
        zone = torch.sqrt(lam * (t_s * (t_l - t_s) / t_l).abs()).clamp_min(1e-300)
        rel = pt[:, None, :] - l_pt
        scale = (m.abs() * zone)
        zones = (rel * normal).sum(2) / scale  # signed: > 0 outside the shadow
        crop = half * (normal.abs().sum(2)) / scale
        t = (rel * tang).sum(2)
        t1, z1, c1 = torch.roll(t, -1, 1), torch.roll(zones, -1, 1), torch.roll(crop, -1, 1)
        hit = (t * t1 <= 0) & ((t - t1).abs() > 0)
        w = t / (t - t1).where(hit, torch.ones_like(t))
        z = zones + w * (z1 - zones)
        c = crop + w * (c1 - crop)
        near = t.abs() <= half * tang.abs().sum(2)  # the normal line crosses the crop away from its centre

        def reach(z_, c_, mask):
            outer = (z_ + c_).clamp_min(0.0)
            inner = (c_ - z_).clamp_min(0.0) / INNER_TAIL
            return torch.where(mask, torch.maximum(outer, inner), -math.inf).amax(1)

        best = torch.maximum(reach(z, c, hit), reach(zones, crop, near))
        best = torch.where(torch.isneginf(best), torch.zeros_like(best), best)  # no stationary rim point: 0
        if crop_reach > 0:  # a crop inside the rim rays' ring: every rim point's edge wave reaches it
            wide = torch.clamp_min(best + DEFOCUS_TAIL_ZONES, DEFOCUS_BAND_ZONES)
            best = torch.where(crop_inside_ring(l_pt, pt, crop_reach), wide, best)
        for i, v, good in zip(rows, best.tolist(), ok.tolist()):
            out[i] = float(v) if good else None
    return out


def crop_inside_ring(land: torch.Tensor, point: torch.Tensor, crop_reach: float) -> torch.Tensor:
    """Whether a PSF crop lies inside its stop rim rays' ring on the sensor, ``(S,)`` bool: the rim rays' landings
    ``land`` ``(S, k, 2)`` mm (in rim order) wind round the crop's centre ``point`` ``(S, 2)`` and every one lies
    farther from it than the crop's reach ``crop_reach`` mm (a sensor far from the rim rays' focus; at a focus,
    aberrated or not, some land within the crop, or the ring does not enclose it: a coma spot's cusp)."""
    rel = land - point[:, None, :]
    ang = torch.atan2(rel[..., 1], rel[..., 0])
    turn = torch.remainder(torch.roll(ang, -1, 1) - ang + math.pi, 2 * math.pi) - math.pi
    winds = turn.sum(1).abs() > math.pi  # the winding number is ±1 (0: outside)
    return winds & (rel.norm(dim=-1).amin(1) > crop_reach)


def ripple_band(rim, z_plane: float, z_sensor: float, point, lam_m: float, reach=...,
                crop_reach: float = 0.0) -> float:
    """The ripple band's width (Fresnel zones) for one source's field on the plane ``z_plane``: :data:`RIPPLE_ZONES`,
    widened where the stop edge's waves that reach the sensor point ``point`` (2,) mm (the PSF crop's centre, the
    chief ray's landing) start farther out: :func:`edge_reach_zones` + :data:`REACH_MARGIN`, at most
    :data:`MAX_RIPPLE_ZONES` (issue 47). Where the crop holds the geometric spot's light from near the rim (a
    diffraction-limited spot, most aberrated ones) the reach is a few zones and the band is at most
    :data:`RIPPLE_ZONES` (:func:`short_reach_band`: the reach + :data:`REACH_TAIL_ZONES`, at least
    :data:`RIPPLE_MIN_ZONES`);
    where only the inner pupil lights it (the cusp of a wide coma spot: the double Gauss at full field, 8.9 zones;
    at 0.7 field 6.5; the F/1.3 asphere at full field 5.1) the edge waves it receives start far out, and the band
    widens to them. ``lam_m`` (mm):
    the wavelength in the image medium. :data:`RIPPLE_ZONES` where the rim images carry no ray directions (a
    mid-system DOE's rim images). ``reach``: the caller's :func:`edge_reach_zones` of these arguments (e.g. from
    :func:`edge_reach_many` for all of a call's sources), else computed here (one host read), with the crop's reach
    ``crop_reach`` mm (0: unknown): a crop inside the rim rays' ring widens the band (:data:`DEFOCUS_TAIL_ZONES`)."""
    if reach is ...:
        reach = edge_reach_zones(rim, z_plane, z_sensor, point, lam_m, crop_reach=crop_reach)
    if reach is None:
        return RIPPLE_ZONES
    return max(short_reach_band(reach), min(reach + REACH_MARGIN, MAX_RIPPLE_ZONES))


def short_reach_band(reach: float) -> float:
    """The ripple band (Fresnel zones) that the edge waves reaching the crop from ``reach`` zones out need: ``reach +``
    :data:`REACH_TAIL_ZONES`, within [:data:`RIPPLE_MIN_ZONES`, :data:`RIPPLE_ZONES`] (:func:`ripple_band` widens it
    further to a reach beyond :data:`RIPPLE_ZONES`)."""
    return min(max(RIPPLE_MIN_ZONES, reach + REACH_TAIL_ZONES), RIPPLE_ZONES)
