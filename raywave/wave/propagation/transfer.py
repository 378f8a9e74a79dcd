"""The transfer function of the shifted band-limited angular spectrum between two windows (Matsushima 2010),
with a smooth roll-off of the band limit (see :func:`window_transfer`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from raywave.utils.phasor import polar
from raywave.wave.grid import Field, Grid
from raywave.wave.propagation.band import index_runs
from raywave.wave.propagation.kernels import band_values, transfer_params
from raywave.wave.propagation._common import (_TWO_PI, _UM_TO_MM, _pair, _positive, _sqrt_kz, _xy, _z_value,
                                              check_single_field, fast_fft_size, legacy_call)


#: the FFT size of every window pair (:func:`window_transfer`, the batched engine) multiplied by this factor per axis
#: and rounded up to a fast size: 1 (the default) leaves the smallest size that keeps the circular convolution linear,
#: bit for bit. A convergence hook, not a setting (benchmarks/fft_size_convergence.py): on fields the grid resolves, a
#: larger size moves a PSF by ≤ 6.4e-9 relative L1 (the rolled-off kernel's tails, which wrap at the own size),
#: ≤ 1.5e-7 where the DOE's edge clips the beam (issue 43)
FFT_SIZE_SCALE = 1.0


class _Geometry(NamedTuple):
    """The checked scalars of one window pair: FFT size, the band of the lateral shift Δ per axis."""

    k: float  # n/λ, cycles/mm in the medium
    zf: float  # z (mm) as a float, for every discrete choice
    zt: object  # z for the phase (a float64 tensor when z was one)
    size: tuple[int, int]  # (My, Mx)
    shift: tuple[float, float]  # (dx, dy) = out_origin − in_origin, mm
    carrier: tuple[float, float]  # (α, β)
    pitch: tuple[float, float]  # (px, py)
    bx: tuple[float, float, float]  # (lo, hi, roll-off width) of Δx, mm
    by: tuple[float, float, float]


@dataclass(frozen=True)
class WindowSource:
    """The geometry of one window-to-window propagation (host values): the input window (``in_shape`` ``(ny, nx)``
    samples, sample (0, 0) at ``in_origin`` ``(x, y)`` mm), the output window's origin ``out_origin`` (mm), the
    vacuum ``wavelength`` (µm), the distance ``z`` (mm; a float, or a 0-d tensor whose value is used for the
    discrete choices and which the phase follows), the medium index ``n`` and the carrier ``(α, β)`` (direction
    cosines) removed from both windows (see :func:`~raywave.wave.propagation.propagate_window`). One source of a
    :class:`~raywave.wave.propagation.batch.WindowBatch`."""

    in_shape: tuple[int, int]
    in_origin: tuple[float, float]
    out_origin: tuple[float, float]
    wavelength: float
    z: object
    n: float = 1.0
    carrier: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        # host values normalised, so that two descriptions of one geometry compare (and hash) equal
        object.__setattr__(self, "in_shape", tuple(int(v) for v in self.in_shape))
        object.__setattr__(self, "in_origin", tuple(float(v) for v in self.in_origin))
        object.__setattr__(self, "out_origin", tuple(float(v) for v in self.out_origin))
        object.__setattr__(self, "wavelength", float(self.wavelength))
        if not isinstance(self.z, torch.Tensor):
            object.__setattr__(self, "z", float(self.z))
        object.__setattr__(self, "n", float(self.n))
        object.__setattr__(self, "carrier", tuple(float(v) for v in self.carrier))

    @classmethod
    def between(cls, field, out, z) -> "WindowSource":
        """The geometry of propagating the single :class:`~raywave.wave.grid.Field` ``field`` (shared wavelength,
        index and carrier) by ``z`` mm onto the :class:`~raywave.wave.grid.Grid` ``out``."""
        g = field.grid
        return cls(g.shape, g.origin, out.origin, field.wavelength, z, field.n, field.carrier)


def _geometry(src: WindowSource, out_shape, pitch, margin, guard) -> _Geometry:
    """Check the geometry ``src`` (:class:`WindowSource`) of a propagation onto a window of ``out_shape`` samples of
    ``pitch`` mm with the band limit's ``margin`` (pixels) and ``guard`` (Fresnel zones), and derive the FFT size
    and the bands of Δ (:func:`window_transfer`)."""
    in_shape, wavelength, z, n, carrier = src.in_shape, src.wavelength, src.z, src.n, src.carrier
    in_origin, out_origin = src.in_origin, src.out_origin
    px, py = _pair(pitch, "pitch")
    _positive(px, "pitch"), _positive(py, "pitch")
    lam = _positive(wavelength, "wavelength") * _UM_TO_MM
    n = _positive(n, "n")
    zf, zt = _z_value(z)
    (niy, nix), (noy, nox) = (int(s) for s in in_shape), (int(s) for s in out_shape)
    if min(niy, nix, noy, nox) < 1:
        raise ValueError(f"window shapes must be positive, got {tuple(in_shape)} and {tuple(out_shape)}")
    xi0, yi0 = _xy(in_origin, "in_origin")
    xo0, yo0 = _xy(out_origin, "out_origin")
    ax, ay = _xy(carrier, "carrier")
    margin, guard = float(margin), float(guard)
    if not (margin >= 0 and guard >= 0 and math.isfinite(margin) and math.isfinite(guard)):
        raise ValueError("margin and guard must be finite and >= 0")

    cos2 = max(1.0 - ax * ax - ay * ay, 0.1)  # clamp: grazing/invalid carriers do not blow the guard up
    fresnel = math.sqrt(lam / n * abs(zf) / cos2**1.5)
    # roll-off widths (mm) per axis: dΔx/dfx = z (k² − fy²)/w³ → the x zone narrows by sqrt(1 − β²)
    tx = guard * fresnel * math.sqrt(max(1.0 - ay * ay, 0.1))
    ty = guard * fresnel * math.sqrt(max(1.0 - ax * ax, 0.1))
    ex = int(math.ceil(margin + tx / px - 1e-9))
    ey = int(math.ceil(margin + ty / py - 1e-9))
    mx, my = fast_fft_size(nix + nox - 1 + 2 * ex), fast_fft_size(niy + noy - 1 + 2 * ey)
    if FFT_SIZE_SCALE != 1.0:
        mx, my = fast_fft_size(math.ceil(FFT_SIZE_SCALE * mx)), fast_fft_size(math.ceil(FFT_SIZE_SCALE * my))

    dx, dy = xo0 - xi0, yo0 - yi0
    bx = (dx - (nix - 1 + margin) * px, dx + (nox - 1 + margin) * px, tx)  # (lo, hi, roll-off) of Δx
    by = (dy - (niy - 1 + margin) * py, dy + (noy - 1 + margin) * py, ty)
    return _Geometry(n / lam, zf, zt, (my, mx), (dx, dy), (ax, ay), (px, py), bx, by)


def window_fft_shape(src: WindowSource, out_shape, pitch, margin: float = 0.5, guard: float = 2.0) -> tuple:
    """``(My, Mx)``: the FFT grid that propagating the geometry ``src`` (:class:`WindowSource`) onto a window of
    ``out_shape`` = (ny, nx) samples of ``pitch`` mm uses, with the band limit's ``margin`` (pixels) and ``guard``
    (Fresnel zones) as in :func:`window_transfer`: host numbers, nothing allocated (a memory plan's input)."""
    return tuple(int(v) for v in _geometry(src, out_shape, pitch, margin, guard).size)


def _candidates(g: torch.Tensor, k: float, zf: float, lo: float, hi: float, taper: float) -> torch.Tensor:
    """Indices of the spatial frequencies ``g`` (1-D, cycles/mm) whose column (row) can be non-zero:
    |Δx| = |z gx|/w ≥ |z gx|/sqrt(k² − gx²) whatever gy is."""
    q = k * k - g * g
    s1 = zf * g / torch.sqrt(q.clamp_min(1e-300))
    at_zero = torch.full_like(s1, lo - taper <= 0.0 <= hi + taper, dtype=torch.bool)
    ok = torch.where(s1 > 0, s1 <= hi + taper, torch.where(s1 < 0, s1 >= lo - taper, at_zero))
    return torch.nonzero((q > 0) & ok).squeeze(1)


def _roll_off(shift: torch.Tensor, band, zf: float, weight: torch.Tensor, weight_derivative: bool):
    """Multiply ``weight`` in place by the roll-off of one axis, whose lateral shift Δ is ``shift`` (consumed);
    returns (∂ log W/∂z, ∂ log W/∂s) of this axis with ``weight_derivative``, else None."""
    lo, hi, taper = band
    if weight_derivative:
        # Δ ∝ z and T ∝ sqrt|z|: ∂dist/∂z = sign(Δ − mid)·Δ/z and ∂T/∂z = T/(2z) where dist > 0
        sgn = torch.sign(shift - 0.5 * (lo + hi))
        dshift = sgn * shift / zf if zf != 0 else torch.zeros_like(shift)
    # how far Δ lies outside [lo, hi] (0 inside)
    dist = shift.sub_(0.5 * (lo + hi)).abs_().sub_(0.5 * (hi - lo)).clamp_(min=0.0)
    if taper <= 0:
        weight.mul_(dist <= 0)
        return (torch.zeros_like(dist), torch.zeros_like(dist)) if weight_derivative else None
    factor = None
    if weight_derivative:
        ramp = (dist > 0) & (dist < taper)
        dt_z = torch.where(ramp, (dshift - dist / (2.0 * zf)) / taper, torch.zeros_like(dist))
        dt_s = torch.where(ramp, -sgn / taper, torch.zeros_like(dist))  # the band moves with the window
    t = dist.div_(taper).clamp_(max=1.0)
    if weight_derivative:
        # d(log(1 − S))/dt, S' = 30 t²(1 − t)², 1 − S = (1 − t)³(1 + 3t + 6t²): finite up to t = 1
        dlog = torch.where(t < 1, -30.0 * t * t / ((1.0 - t) * (1.0 + t * (3.0 + 6.0 * t))).clamp_min(1e-300),
                           torch.zeros_like(t))
        factor = (dlog * dt_z, dlog * dt_s)
    # the quintic smoothstep roll-off S(t) = t³(10 + t(6t − 15)), W ← W − W·S, evaluated only where it
    # changes W (0 < t: S(0) = 0; at t = 1, S = 1 exactly): most of the band lies inside (t = 0)
    ramp_idx = (t > 0).nonzero(as_tuple=True)
    if ramp_idx[0].numel():
        tr = t[ramp_idx]
        s = tr * tr * tr * (10.0 + tr * (6.0 * tr - 15.0))
        wr = weight[ramp_idx]
        weight.index_put_(ramp_idx, wr - wr * s)
    return factor


def _ramp_lines(g: torch.Tensor, g_other: torch.Tensor, k: float, zf: float, band) -> torch.Tensor:
    """Indices of the band's lines (columns for the x axis: ``g`` its spatial frequencies, cycles/mm; ``g_other``
    the band's frequencies along the other axis) where the lateral shift Δ = z·g/sqrt(k² − g² − g_o²) may leave
    ``[lo, hi]`` of ``band`` (the roll-off or an evanescent entry): along a line |Δ| grows with |g_o|, so its
    range is that of the line's two extreme |g_o|. The other lines lie inside by a margin far above rounding, so
    their roll-off factor is exactly 1 (skipping them gives the same values)."""
    lo, hi, _ = band
    a, b = (g_other * g_other).aminmax()
    q_near, q_far = k * k - g * g - a, k * k - g * g - b
    ok = q_far > 0
    s_near = zf * g / torch.sqrt(torch.where(ok, q_near, 1.0))
    s_far = zf * g / torch.sqrt(torch.where(ok, q_far, 1.0))
    tol = 1e-9 * max(abs(lo), abs(hi), 1e-9)
    inside = ok & (torch.minimum(s_near, s_far) >= lo + tol) & (torch.maximum(s_near, s_far) <= hi - tol)
    return torch.nonzero(~inside).squeeze(1)


def _roll_off_lines(g, g_other, k: float, zf: float, inv_w, band, weight, weight_derivative: bool, dim: int):
    """:func:`_roll_off` of one axis (``dim`` 1: x, the band's columns; 0: y, its rows; ``g`` (L,) that axis's
    frequencies, ``g_other`` the other's, ``inv_w`` (R, C) 1/w), evaluated on the lines that can roll off alone
    (:func:`_ramp_lines`; the same values: elsewhere the factor is 1 and its derivatives 0), a contiguous run of
    lines at a time (views: no gathers)."""
    lines = _ramp_lines(g, g_other, k, zf, band)
    if lines.numel() == g.numel():  # every line: the whole band at once
        shift = (zf * g)[None, :] * inv_w if dim == 1 else (zf * g)[:, None] * inv_w
        return _roll_off(shift, band, zf, weight, weight_derivative)
    facs = (torch.zeros_like(weight), torch.zeros_like(weight)) if weight_derivative else None
    for a, b in index_runs(lines):
        gl = (zf * g)[a:b]
        iw = inv_w.narrow(dim, a, b - a)
        shift = gl[None, :] * iw if dim == 1 else gl[:, None] * iw
        fac = _roll_off(shift, band, zf, weight.narrow(dim, a, b - a), weight_derivative)  # in place on the view
        if weight_derivative:
            for full, part in zip(facs, fac):
                full.narrow(dim, a, b - a).copy_(part.expand_as(shift))
    return facs


def _band_values(geo: _Geometry, fx, fy, rows, cols, weight_derivative: bool):
    """The transfer function on the band rectangle ``rows × cols``: (G, relative weight derivatives or None). With a
    roll-off on both axes and a distance that carries no derivative, ``G`` is the compiled loop's
    (:func:`~raywave.wave.propagation.kernels.transfer_values`: the batched engine's values, ~10× faster than this
    eager chain); the eager chain otherwise (and for the weights' derivatives)."""
    compiled = geo.bx[2] > 0 and geo.by[2] > 0 and not (isinstance(geo.zt, torch.Tensor) and geo.zt.requires_grad
                                                        and torch.is_grad_enabled())
    if compiled:
        p = torch.tensor(transfer_params(geo), dtype=torch.float64, device=fx.device)
        g = band_values(fx[cols], fy[rows], p)
        if not weight_derivative:
            return g, None
        _, rel = _eager_band_values(geo, fx, fy, (rows, cols), weight_derivative)
        return g, rel
    return _eager_band_values(geo, fx, fy, (rows, cols), weight_derivative)


def _eager_band_values(geo: _Geometry, fx, fy, band, weight_derivative: bool):
    """:func:`_band_values` as a chain of tensor operations (the sharp band limit, a distance that carries a
    derivative, the weights' derivatives); ``band`` = ``(rows, cols)``."""
    rows, cols = band
    k, zf = geo.k, geo.zf
    (ax, ay), (dx, dy) = geo.carrier, geo.shift
    gxs, gys = fx[cols] + k * ax, fy[rows] + k * ay  # physical spatial frequencies (cycles/mm)
    # band-sized float64 arrays are released as soon as they are used (the peak memory of a PSF with a wide band:
    # the exit-pupil edge's 1175×1473 band held ~9 of them at once)
    arg = k * k - gxs[None, :] ** 2 - gys[:, None] ** 2
    prop = arg > 0
    w = _sqrt_kz(arg, prop)  # (n/λ)·cosθ; 1 on evanescent entries
    del arg
    weight = prop.to(torch.float64)  # evanescent: exactly 0
    del prop
    inv_w = 1.0 / w
    fac_x = _roll_off_lines(gxs, gys, k, zf, inv_w, geo.bx, weight, weight_derivative, dim=1)
    fac_y = _roll_off_lines(gys, gxs, k, zf, inv_w, geo.by, weight, weight_derivative, dim=0)
    del inv_w
    phase = _TWO_PI * geo.zt * w
    del w
    phase += _TWO_PI * ((fx[cols] * dx)[None, :] + (fy[rows] * dy)[:, None])
    g = polar(weight, phase)
    del phase
    if not weight_derivative:
        return g, None
    (rz_x, rs_x), (rz_y, rs_y) = fac_x, fac_y
    live = weight > 0
    zero = torch.zeros((), dtype=torch.float64, device=weight.device)
    rel = [torch.where(live, r, zero) for r in (rz_x + rz_y, rs_x.expand_as(weight), rs_y.expand_as(weight))]
    return g, rel


class WindowTransfer(Sequence):
    """The result of :func:`window_transfer`: the tuple ``(G, (My, Mx))`` (``(G, (My, Mx), R)`` with
    ``weight_derivative``) it always was — index it, unpack it, take ``len`` — stored compactly as its band.

    ``G`` and ``R`` are zero outside the rectangle ``rows × cols`` of the FFT grid (the 1-D pre-selection), so
    only that rectangle is kept: ``band`` complex128 ``(R, C)`` and ``band_rel`` float64 ``(3, R, C)`` (or None),
    with ``rows`` ``(R,)`` and ``cols`` ``(C,)`` int64 indices into the ``fftfreq`` grid of size ``size``. The
    full-size ``G`` and ``R`` are built on first access (and kept); :func:`propagate_window` uses the band alone
    and never builds them (and skips the FFT work on the columns that the band leaves at zero)."""

    __slots__ = ("size", "rows", "cols", "band", "band_rel", "weight_derivative", "_full")

    def __init__(self, size, rows, cols, band, band_rel=None, weight_derivative: bool = False):
        self.size = (int(size[0]), int(size[1]))
        self.rows, self.cols, self.band, self.band_rel = rows, cols, band, band_rel
        self.weight_derivative = bool(weight_derivative)
        self._full = None

    def _items(self) -> tuple:
        if self._full is None:
            my, mx = self.size
            dev = self.band.device
            idx = (self.rows[:, None], self.cols[None, :])
            g = torch.zeros((my, mx), dtype=torch.complex128, device=dev)
            if self.band.numel():
                g.index_put_(idx, self.band)
            if not self.weight_derivative:
                self._full = (g, self.size)
            else:
                r = torch.zeros((3, my, mx), dtype=torch.float64, device=dev)
                if self.band.numel():
                    for i in range(3):
                        r[i].index_put_(idx, self.band_rel[i])
                self._full = (g, self.size, r)
        return self._full

    def __len__(self) -> int:
        return 3 if self.weight_derivative else 2

    def __getitem__(self, i):
        if isinstance(i, int) and i in (1, -2 if self.weight_derivative else -1):
            return self.size  # the FFT size needs no full-size array
        return self._items()[i]

    def __iter__(self):
        return iter(self._items())

    def __repr__(self) -> str:
        return (f"WindowTransfer(size={self.size}, band={tuple(self.band.shape)}, "
                f"weight_derivative={self.weight_derivative})")


def window_transfer(field: Field, out: Grid, z=None, *legacy, margin: float = 0.5, guard: float = 2.0,
                    weight_derivative: bool = False, **legacy_kw) -> WindowTransfer:
    """Transfer function used by :func:`propagate_window` (float64-accurate, complex128) for propagating ``field``
    (a :class:`~raywave.wave.grid.Field`: its grid, wavelength, index and carrier; the envelope's values are not
    used, its device is) by ``z`` mm (float or 0-d tensor) onto the window ``out`` (a
    :class:`~raywave.wave.grid.Grid` of the same pitch, any origin and shape). ``margin`` and ``guard``: as
    :func:`propagate_window`. The geometry alone (no tensor): :func:`_window_transfer` of a :class:`WindowSource`.

    Returns ``(G, (My, Mx))`` (a :class:`WindowTransfer`, which holds only the band where ``G`` can be non-zero) with, on the ``fftfreq`` grid of the FFT size ``(My, Mx)``,
    ``G = W(f) · H(f + f_c) · exp(i2π f·(out_origin − in_origin))`` with
    ``H(f) = exp(i2π z sqrt((n/λ)² − |f|²))`` and ``f_c = n·carrier/λ``. The band-limit weight ``W`` is a
    function of the geometric lateral shift per axis, ``Δ = z (f + f_c)/sqrt((n/λ)² − |f + f_c|²)``
    (= z·tanθ in x resp. y):

    * ``W = 1`` where Δ lies in ``[out_min − in_max − margin·p, out_max − in_min + margin·p]`` in both axes
      (exactly the directions that carry light from the input window into the output window; pixel centres);
    * beyond, ``W`` rolls off smoothly (quintic smoothstep, C²) to 0 over ``T = guard·F`` with the Fresnel-zone
      width ``F = sqrt(λ/n · |z| / cos³θ_c)`` (``θ_c`` the carrier angle); ``guard = 0`` gives the sharp
      band limit of Matsushima (2010);
    * ``W = 0`` for evanescent components.

    The FFT size is the smallest fast size ≥ ``N_in + N_out − 1 + 2·ceil(margin + T/p)`` per axis, so the
    circular convolution equals the linear one for the whole (rolled-off) kernel. Only the rows/columns that
    can be non-zero are evaluated (a 1-D pre-selection), so building ``G`` costs little beyond the FFTs.
    Exposed so that a caller propagating many fields between the same windows can reuse ``G``.

    ``weight_derivative=True`` returns ``(G, (My, Mx), R)`` with ``R`` float64 ``(3, My, Mx)`` (1/mm), the
    relative first-order changes ``(∂W/∂z, ∂W/∂s_x, ∂W/∂s_y) / W`` of the roll-off weights (0 where ``W = 0``,
    where the derivatives vanish too) with the distance (Δ ∝ z, T ∝ sqrt|z|) and with a translation ``s`` of
    the output window (the band follows it): :func:`propagate_window` adds ``(dz·R_z + s·R_s)·G`` for its
    ``dz`` and ``shift`` so that their derivatives are those of the whole discrete model.
    """
    if legacy or legacy_kw or not isinstance(field, Field):
        legacy_call("window_transfer", "window_transfer(field, out, z, *, margin=0.5, guard=2.0, "
                    "weight_derivative=False)")
    check_single_field(field, out, z, "window_transfer")
    return _window_transfer(WindowSource.between(field, out, z), out.shape, field.grid.pitch, (margin, guard),
                            field.envelope.device, weight_derivative)


def _window_transfer(src: WindowSource, out_shape, pitch, band_limit, device, weight_derivative: bool) -> WindowTransfer:
    """:func:`window_transfer` of the geometry ``src`` onto ``out_shape`` samples of ``pitch`` mm; ``band_limit`` =
    ``(margin, guard)``; the tensors on ``device``."""
    geo = _geometry(src, out_shape, pitch, *band_limit)
    (my, mx), (px, py), k = geo.size, geo.pitch, geo.k
    fx = torch.fft.fftfreq(mx, d=px, dtype=torch.float64, device=device)
    fy = torch.fft.fftfreq(my, d=py, dtype=torch.float64, device=device)
    cols = _candidates(fx + k * geo.carrier[0], k, geo.zf, *geo.bx)
    rows = _candidates(fy + k * geo.carrier[1], k, geo.zf, *geo.by)
    if cols.numel() == 0 or rows.numel() == 0:
        empty = torch.zeros((rows.numel(), cols.numel()), dtype=torch.complex128, device=device)
        rel = torch.zeros((3, *empty.shape), dtype=torch.float64, device=device) if weight_derivative else None
        return WindowTransfer((my, mx), rows, cols, empty, rel, weight_derivative)
    g, rel = _band_values(geo, fx, fy, rows, cols, weight_derivative)
    return WindowTransfer((my, mx), rows, cols, g, None if rel is None else torch.stack(rel), weight_derivative)
