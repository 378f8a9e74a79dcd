"""Fabrication tolerance of an L = 2^k level DOE: etch-depth errors and mask misalignment, by Monte Carlo.

**The fabricated profile.** An L-level DOE is made with k binary masks (:mod:`raywave.doe.fabrication`): step j
(j = 1..k) etches the areas open in mask j by ``d_j = h_2π/2^j``. A fabricated element deviates from the design
in two ways, modelled here per mask (= per lithography + etch step):

* **etch depth**: step j etches ``d_j (1 + ε_j)``: one relative error ε_j per step, the same over the whole
  element (an etch-rate / time error);
* **misalignment**: mask j lies shifted by ``(δx_j, δy_j)`` DOE pixels on the substrate (the pattern moves
  toward +x for δx > 0: ``m_j(x − δx_j, y − δy_j)``); mask 1 is the reference (δ_1 = 0), so only relative
  shifts count, as in a real layer-to-layer alignment.

The relief height above the deepest floor, in units of ``h_2π/L`` ("level units"), is then

    h(x, y) = Σ_j 2^(k−j) (1 + ε_j) (1 − m_j(x − δx_j, y − δy_j)),

which is the level map ℓ exactly when every ε_j and δ_j is zero (Σ_j 2^(k−j) = L − 1: level L − 1 is the
unetched top). The phase at any wavelength follows the DOE's material dispersion (:class:`~raywave.doe.DOE`
``dispersion="material"``): ``φ(λ) = 2π α(λ) h / L`` with ``α(λ) = λ0 (n(λ) − n_m) / (λ (n(λ0) − n_m))``.

**Sub-pixel shifts, exactly.** Misalignment is a fraction of a pixel. On a grid of q × q samples per DOE pixel
(the ray-wave simulation grid of a :class:`~raywave.hybrid.HybridLens` with ``oversample=q``; q = 1 is the DOE
grid), every sample is split at the fractional parts of the k masks' shifts into at most (k+1)² sub-rectangles on
each of which every shifted mask, hence the relief, is constant (:func:`profile_parts`). So the fabricated,
sharp-edged staircase is represented without approximation: its **mean transmittance** over each sample
(:func:`transmittance`, ``|t| < 1`` on samples that an edge crosses: the exact cell average of ``exp(iφ)``, what
diffraction into angles resolved by the grid sees) and its mean height (:func:`level_height`). Outside the DOE
grid nothing is etched: a shifted mask drags unetched field into the grid's edge (``periodic=True`` wraps
instead, for whole periods of a grating). Representing an edge inside a sample by the mean *height* instead
(a one-sample ramp) or rounding the shifts to whole samples would bias η₁ by ≈ 0.1/q or scatter it by ≈ 0.15/q
for ±0.25 px (measured on a 16-level grating), which is why neither is done.

**Efficiency.** Scalar, thin-element theory:

* a **grating** (one period of a 1-D blazed staircase, one level per pixel, periodic): the Fourier coefficient
  of order m of the perturbed period's transmittance ``exp(iφ)``, computed exactly from its piecewise-constant
  segments (:func:`grating_efficiency`, any shifts), or by an FFT of the period's sample-averaged transmittance on
  the q-times oversampled grid, ``η_m = |FFT_m/N|² sinc²(m/N)`` (:func:`grating_efficiency_fft`; the sinc is the
  exact integral of a constant sample, so the FFT is exact when the shifts are whole samples);
* a **general DOE**, relative to its design: the power fraction of the design's order-m wave
  ``exp(i m φ_u)`` (φ_u: the unwrapped, unquantised design phase at λ0; order m of a kinoform wrapped on φ_u is
  ``exp(i m φ_u)`` at every wavelength), the normalised overlap over the aperture A

      η_m = |∫_A exp(iφ_pert) exp(−i m φ_u) dA|² / A²     (:func:`doe_efficiency`),

  with φ_u linear inside each DOE pixel (its gradient from wrapped central differences) and the design wave
  integrated exactly over each sub-rectangle (``sinc(m g_x du/2πq) · sinc(m g_y dv/2πq)`` about its centre), so
  the overlap is exact for any shifts. For a linear grating over whole periods it *is* the grating's order-m
  efficiency (sinc²(1/L) for a nominal L-level staircase; the same digits as :func:`grating_efficiency` with
  errors): tested. For m ≡ 1 (mod L) at λ0 it holds pixel by pixel, so any width will do. ``relative`` is the
  overlap with the *nominal* fabricated element instead (1 without errors).

**Random errors** (:func:`sample_errors`): a tolerance ``±x`` is read as **±2σ of a normal distribution**
(``distribution="normal"``, the default: σ = x/2, 95 % of the samples inside ±x) or as the bounds of a
**uniform** one (``distribution="uniform"``). ``depth_error`` x is in percent of each step's depth (independent
per step); ``misalignment`` in DOE pixels, independent in x and y for every mask but the first. Random numbers
come from a CPU ``torch.Generator`` (``seed`` or ``generator``) in a fixed order, so a seed reproduces a run
exactly on any device.

**PSF** (:func:`raywave.assembly.tolerance.tolerance_monte_carlo`, in the assembly layer above
:mod:`raywave.hybrid`; this module's loop tells it about every draw through an ``observer``). With ``lens`` (a
:class:`~raywave.hybrid.HybridLens`) every sample's perturbed element replaces the DOE and
the ray-wave PSF is compared with the nominal element's (the field arriving at the DOE depends on the lens only
and is computed once). The element enters as its sample-averaged transmittance on the lens's simulation grid
(``oversample``): its phase through :meth:`PerturbedDOE.phase`, its amplitude (< 1 on samples that a shifted
edge crosses) multiplied into the incident field. PSFs are kept as **fractions of the power incident on the
DOE** (not renormalised to 1, so that light a fabrication error sends into other orders, out of the crop, counts):
``peak_ratio`` = peak / nominal peak (Strehl-like), ``l1`` = Σ|p − p0| / Σ p0, ``crop_energy`` = Σ p, and the
shape metrics ``rms_radius_um`` and ``r80_um`` of :func:`raywave.hybrid.metrics.psf_metrics`. Tested: the in-focus
peak of a diffractive lens follows η₁ (the other orders are out of focus).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from raywave.doe.base import DOE, check_levels
from raywave.doe.efficiency import staircase_efficiency
from raywave.doe.fabrication import mask_bits, masks_from_levels
from raywave.utils.checks import wavelength_um

__all__ = ["DISTRIBUTIONS", "PSF_METRICS", "FabricationErrors", "PerturbedDOE", "ToleranceResult", "ToleranceWarning",
           "blazed_grating_levels", "design_maps", "doe_efficiency", "grating_efficiency", "grating_efficiency_fft",
           "level_height", "profile_parts", "sample_errors", "summary_stats", "tolerance_monte_carlo",
           "transmittance"]

#: Distributions of :func:`sample_errors` for a tolerance ±x: normal with σ = x/2, or uniform in [−x, x].
DISTRIBUTIONS = ("normal", "uniform")
_TWO_PI = 2.0 * math.pi
_TILE_SAMPLES = 2_000_000   # simulation samples per tile of the efficiency overlap (bounds memory)


# ---------------------------------------------------------------------------- errors
@dataclass(frozen=True)
class FabricationErrors:
    """The errors of one fabricated element (k = number of masks).

    Attributes:
        depth: (k,) relative etch-depth errors ε_j (fractions: 0.02 = +2 %): step j etches ``d_j (1 + ε_j)``.
        shift: (k, 2) lateral shift (δx, δy) of mask j in DOE pixels (+x: the pattern moves toward +x).
    """

    depth: np.ndarray
    shift: np.ndarray

    def __post_init__(self):
        d = np.asarray(self.depth, dtype=np.float64).reshape(-1)
        s = np.asarray(self.shift, dtype=np.float64).reshape(-1, 2) if np.size(self.shift) else \
            np.zeros((d.size, 2))
        if s.shape[0] != d.size:
            raise ValueError(f"fabrication errors: {d.size} depth errors but {s.shape[0]} mask shifts")
        if not (np.isfinite(d).all() and np.isfinite(s).all()):
            raise ValueError("fabrication errors must be finite numbers")
        if (d <= -1).any():
            raise ValueError(f"a relative etch-depth error must be > −1 (−100 %), got {d.min():g}")
        object.__setattr__(self, "depth", d)
        object.__setattr__(self, "shift", s)

    @property
    def masks(self) -> int:
        return int(self.depth.size)

    @classmethod
    def nominal(cls, k: int) -> "FabricationErrors":
        """No errors for k masks."""
        return cls(np.zeros(k), np.zeros((k, 2)))

    @classmethod
    def common_depth(cls, k: int, eps: float) -> "FabricationErrors":
        """Every step etched ``(1 + eps)`` times too deep (a common etch-rate error), no misalignment."""
        return cls(np.full(k, float(eps)), np.zeros((k, 2)))


def _nonneg(x, name: str, unit: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number >= 0 ({unit}), got {x!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite number >= 0 ({unit}), got {x!r}")
    return v


def _count(n, name: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) and not (isinstance(n, float) and n.is_integer()):
        raise ValueError(f"{name} must be an integer >= 1, got {n!r}")
    if int(n) < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {n!r}")
    return int(n)


def _generator(seed, generator) -> torch.Generator:
    if generator is not None:
        if not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        return generator
    g = torch.Generator()
    g.manual_seed(0 if seed is None else int(seed))
    return g


def sample_errors(k: int, depth_error: float, misalignment: float, n_samples: int = 1, seed: int | None = 0,
                  generator: torch.Generator | None = None, distribution: str = "normal") -> list:
    """``n_samples`` random :class:`FabricationErrors` for k masks.

    Args:
        depth_error: tolerance ±x of every step's etch depth, in **percent** (≥ 0).
        misalignment: tolerance ±m of every mask's shift (mask 2..k; mask 1 is the reference), **DOE pixels**,
            independent in x and y.
        distribution: "normal" (±x = ±2σ) or "uniform" (in [−x, x]).
        seed / generator: a CPU ``torch.Generator`` (or its seed); per sample the k depth errors are drawn first,
            then the (k − 1, 2) shifts.
    """
    k = _count(k, "the number of masks")
    x = _nonneg(depth_error, "the etch-depth error", "percent") / 100.0
    m = _nonneg(misalignment, "the misalignment", "DOE pixels")
    n = _count(n_samples, "the number of samples")
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {', '.join(map(repr, DISTRIBUTIONS))}, got {distribution!r}")
    if x >= 1 and distribution == "uniform" or x >= 0.5 and distribution == "normal":
        raise ValueError(f"an etch-depth tolerance of ±{100 * x:g} % is not a small error (depths could become "
                         "negative): use < 100 % (uniform) or < 50 % (normal, ±2σ)")
    g = _generator(seed, generator)
    out = []
    for _ in range(n):
        if distribution == "normal":
            e = torch.randn(k, generator=g, dtype=torch.float64) * (x / 2)
            s = torch.randn((k - 1, 2), generator=g, dtype=torch.float64) * (m / 2)
        else:
            e = (torch.rand(k, generator=g, dtype=torch.float64) * 2 - 1) * x
            s = (torch.rand((k - 1, 2), generator=g, dtype=torch.float64) * 2 - 1) * m
        shift = np.concatenate([np.zeros((1, 2)), s.numpy()], axis=0)
        out.append(FabricationErrors(e.numpy(), shift))
    return out


# ---------------------------------------------------------------------------- the perturbed profile on a grid
def _axis_partition(shifts_samples) -> list:
    """Split a sample's extent [0, 1) along one axis at the fractional parts of the masks' shifts (in samples):
    ``[(u0, u1, offsets)]`` where on [u0, u1) mask j reads source sample ``a − offsets[j]`` (a shift of n + f
    samples: ``a − n − 1`` for u < f, ``a − n`` for u ≥ f)."""
    t = np.asarray(shifts_samples, dtype=np.float64)
    n = np.floor(t)
    f = t - n
    cuts = np.unique(np.concatenate([[0.0, 1.0], f]))
    out = []
    for u0, u1 in zip(cuts[:-1], cuts[1:]):
        if u1 - u0 <= 1e-12:
            continue
        mid = 0.5 * (u0 + u1)
        out.append((float(u0), float(u1), (n + (mid < f)).astype(np.int64)))
    return out


def _source_index(n_px: int, q: int, start: int, count: int, offset: int, periodic: bool, device):
    """Source pixel index (long) and validity (bool) of samples ``start..start+count`` shifted by ``offset``
    samples along an axis of ``n_px`` pixels (q samples each); outside the grid: invalid (unetched) or wrapped."""
    total = n_px * q
    src = torch.arange(start - offset, start - offset + count, device=device, dtype=torch.long)
    if periodic:
        src = torch.remainder(src, total)
        valid = None
    else:
        valid = (src >= 0) & (src < total)
        src = src.clamp(0, total - 1)
    return torch.div(src, q, rounding_mode="floor"), valid


def _check_grid_args(masks, errors, oversample, window):
    m = torch.as_tensor(masks)
    if m.ndim != 3:
        raise ValueError(f"masks must be a (k, ny, nx) array, got shape {tuple(m.shape)}")
    if errors.masks != m.shape[0]:
        raise ValueError(f"{m.shape[0]} masks need {m.shape[0]} depth errors and shifts, got {errors.masks}")
    q = int(oversample)
    if q < 1:
        raise ValueError(f"oversample must be an integer >= 1, got {oversample!r}")
    if window is None:
        window = (0, 0, m.shape[1] * q, m.shape[2] * q)
    return m, q, tuple(int(v) for v in window)


def profile_parts(masks, errors: FabricationErrors, oversample: int = 1, window=None, periodic: bool = False):
    """The perturbed profile on the simulation samples of ``window = (iy0, ix0, ny, nx)`` (default: the whole grid,
    ``oversample`` samples per DOE pixel), **exactly**: every sample is split at the fractional parts of the masks'
    shifts into sub-rectangles on which every shifted mask is constant.

    Yields ``(area, (cu, cv), (du, dv), h)``: the sub-rectangle's area fraction of the sample, its centre offset
    from the sample centre and its size (sample units, x then y), and the relief height in level units
    (``h_2π/L``) on it, an (ny, nx) float64 map (module docstring formula)."""
    m, q, window = _check_grid_args(masks, errors, oversample, window)
    iy0, ix0, ny, nx = window
    k, Ny, Nx = m.shape
    mf = m.to(torch.float64)
    dev = m.device
    weights = [2.0 ** (k - 1 - j) * (1.0 + float(errors.depth[j])) for j in range(k)]
    parts_x = _axis_partition(errors.shift[:, 0] * q)
    parts_y = _axis_partition(errors.shift[:, 1] * q)
    cache_x: dict = {}
    cache_y: dict = {}
    for v0, v1, oy in parts_y:
        for u0, u1, ox in parts_x:
            h = torch.zeros((ny, nx), dtype=torch.float64, device=dev)
            for j in range(k):
                ky, kx = int(oy[j]), int(ox[j])
                if ky not in cache_y:
                    cache_y[ky] = _source_index(Ny, q, iy0, ny, ky, periodic, dev)
                if kx not in cache_x:
                    cache_x[kx] = _source_index(Nx, q, ix0, nx, kx, periodic, dev)
                (py, vy), (px, vx) = cache_y[ky], cache_x[kx]
                etched = mf[j][py][:, px]
                if vy is not None:
                    etched = etched * vy[:, None] * vx[None, :]
                h += weights[j] * (1.0 - etched)
            yield ((u1 - u0) * (v1 - v0), (0.5 * (u0 + u1) - 0.5, 0.5 * (v0 + v1) - 0.5), (u1 - u0, v1 - v0), h)


def level_height(masks, errors: FabricationErrors, oversample: int = 1, window=None,
                 periodic: bool = False) -> torch.Tensor:
    """Mean relief height in level units (``h_2π/L``; float64) of every simulation sample of ``window`` (default:
    the whole grid of ``oversample`` samples per pixel) of the element made with ``masks`` ((k, ny, nx) bool, True
    = etched, :func:`~raywave.doe.fabrication.masks_from_levels`) with ``errors``. Without errors it is the level
    map, each level repeated over its q × q samples."""
    out = None
    for area, _, _, h in profile_parts(masks, errors, oversample, window, periodic):
        out = area * h if out is None else out + area * h
    return out


def transmittance(masks, errors: FabricationErrors, levels: int, alpha: float, oversample: int = 1, window=None,
                  periodic: bool = False) -> torch.Tensor:
    """The exact mean over every simulation sample of the perturbed element's transmittance
    ``exp(i 2π α h / L)`` (complex128 (ny, nx)): sharp mask edges inside a sample give ``|t| < 1`` there."""
    out = None
    c = _TWO_PI * float(alpha) / int(levels)
    for area, _, _, h in profile_parts(masks, errors, oversample, window, periodic):
        t = torch.polar(torch.full_like(h, area), h * c)
        out = t if out is None else out + t
    return out


class PerturbedDOE(DOE):
    """A fabricated L-level DOE with fabrication errors: the height map of the module docstring in ``material``
    (default: the DOE's, else fused silica), its phase at any wavelength by the material's dispersion.

    It has the grid, pitch and aperture of ``doe`` and can replace it in a :class:`~raywave.hybrid.HybridLens`:
    :meth:`transmittance` is the exact mean of ``exp(iφ)`` over every sample of the requested simulation grid
    (any sub-pixel shifts, :func:`profile_parts`), :meth:`phase` its phase (what the lens applies; the amplitude,
    < 1 only where an edge crosses a sample, is applied by :func:`tolerance_monte_carlo`).

    Args:
        doe: the design (its level map ``doe.levels(levels, wavelength0)`` is what is fabricated).
        levels: L, a power of two.
        errors: a :class:`FabricationErrors` (default: none, the nominal fabricated element).
        material: the substrate (a glass name); default the DOE's material, else FUSED_SILICA.
        wavelength0: λ0 (µm) of the levels and etch depths; default the DOE's design wavelength.
        periodic: shifted masks wrap around the grid (one period of a grating) instead of bringing in unetched
            field.
    """

    def __init__(self, doe: DOE, levels: int, errors: FabricationErrors | None = None, material=None,
                 wavelength0: float | None = None, periodic: bool = False):
        k = mask_bits(levels)
        lam0 = doe.design_wavelength if wavelength0 is None else wavelength0
        mat = material if material is not None else (doe.material if doe.material is not None else None)
        super().__init__(doe.shape, doe.pitch, doe.aperture, design_wavelength=lam0,
                         material=mat if mat is not None else "FUSED_SILICA", dispersion="material",
                         n_medium=doe.n_medium)
        self.to(doe.device)
        self.L = int(levels)
        level_map = doe.levels(self.L, lam0).to(doe.device)
        self.register_buffer("level_map", level_map, persistent=False)
        masks = torch.as_tensor(masks_from_levels(level_map.cpu().numpy(), self.L), device=doe.device)
        self.register_buffer("masks", masks, persistent=False)
        self.errors = FabricationErrors.nominal(k) if errors is None else errors
        if self.errors.masks != k:
            raise ValueError(f"{self.L} levels = {k} masks need {k} depth errors and shifts, got {self.errors.masks}")
        self.periodic = bool(periodic)
        self._memo: dict = {}

    def with_errors(self, errors: FabricationErrors) -> "PerturbedDOE":
        """A shallow copy with other errors (shares the level map and masks)."""
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new._modules = dict(self._modules)
        new._buffers = dict(self._buffers)
        new._parameters = dict(self._parameters)
        if errors.masks != self.errors.masks:
            raise ValueError(f"{self.errors.masks} masks need as many errors, got {errors.masks}")
        new.errors = errors
        new._memo = {}
        return new

    def height_levels(self, window=None, oversample: int = 1) -> torch.Tensor:
        """The mean relief height in level units on the simulation samples of ``window`` (:func:`level_height`)."""
        return level_height(self.masks, self.errors, oversample, window, self.periodic)

    def design_phase_pixels(self, rows, cols):
        """The phase at λ0 of the perturbed relief's mean height over every DOE pixel (for height maps and levels;
        :meth:`transmittance` is the optics)."""
        r = range(*rows.indices(self.shape[0]))
        c = range(*cols.indices(self.shape[1]))
        if r.step != 1 or c.step != 1:
            raise ValueError("PerturbedDOE: pixel slices must be contiguous")
        h = self.height_levels((r.start, c.start, len(r), len(c)), 1)
        return h * (_TWO_PI / self.L)

    def _window(self, window, q: int):
        if window is None:
            window = (0, 0) + self.sim_shape(q)
        iy0, ix0, ny, nx = window
        sy, sx = self.sim_shape(q)
        if iy0 < 0 or ix0 < 0 or iy0 + ny > sy or ix0 + nx > sx:
            raise ValueError(f"window {window} lies outside the DOE simulation grid {sy}×{sx}")
        return window

    def transmittance(self, wavelength: float, window=None, oversample: int = 1) -> torch.Tensor:
        """Complex transmittance (complex128) of the perturbed element at ``wavelength`` on the simulation samples
        of ``window`` (default: the whole grid): the exact mean of ``exp(iφ)`` over each sample
        (:func:`transmittance`), ``|t| < 1`` where a shifted mask edge crosses a sample."""
        q = int(oversample)
        window = self._window(window, q)
        key = (float(wavelength), window, q)
        hit = self._memo.get(key)
        if hit is None:  # the last few are kept: tolerance_monte_carlo asks for the amplitude and the phase
            hit = transmittance(self.masks, self.errors, self.L, self.alpha(wavelength), q, window, self.periodic)
            self._memo[key] = hit
            while len(self._memo) > 4:
                self._memo.pop(next(iter(self._memo)))
        return hit

    def phase(self, wavelength: float, window=None, oversample: int = 1) -> torch.Tensor:
        """Phase (rad, float64) of :meth:`transmittance`: what a :class:`~raywave.hybrid.HybridLens` applies. Its
        amplitude (< 1 only on samples crossed by a shifted mask edge) is left out there;
        :func:`tolerance_monte_carlo` applies it to the incident field as well."""
        return torch.angle(self.transmittance(wavelength, window, oversample))

    def alpha(self, wavelength: float) -> float:
        """Detuning α(λ) = φ(λ)/φ(λ0) of the material."""
        return float(self.dispersion_ratio(wavelength).detach())

    def extra_repr(self) -> str:
        return (super().extra_repr() + f", L={self.L}, depth errors={np.round(100 * self.errors.depth, 3).tolist()} %,"
                f" shifts={np.round(self.errors.shift, 4).tolist()} px")


# ---------------------------------------------------------------------------- gratings
def blazed_grating_levels(levels: int, period_px: int | None = None) -> np.ndarray:
    """One period of a blazed L-level staircase, one level per pixel: ``(period_px,)`` int64, pixel i at level
    ``floor(i·L/period_px)`` (default ``period_px = L``; it must be a multiple of L)."""
    L = check_levels(levels)
    P = L if period_px is None else _count(period_px, "the grating period (pixels)")
    if P % L:
        raise ValueError(f"the grating period ({P} pixels) must be a multiple of the number of levels ({L})")
    return (np.arange(P) * L) // P


def _grating_masks(level_period, levels: int) -> np.ndarray:
    lv = np.asarray(level_period)
    if lv.ndim != 1 or lv.size < 1:
        raise ValueError(f"a grating period is a 1-D array of levels, got shape {lv.shape}")
    return masks_from_levels(lv[None, :], levels)[:, 0, :]


def _orders(orders) -> list[int]:
    out = []
    for m in ([orders] if isinstance(orders, (int, np.integer)) else list(orders)):
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
            raise ValueError(f"diffraction orders are integers, got {m!r}")
        out.append(int(m))
    if not out:
        raise ValueError("give at least one diffraction order")
    return out


def grating_efficiency(level_period, levels: int, errors: FabricationErrors | None = None, alpha: float = 1.0,
                       orders=(1,)) -> np.ndarray:
    """η_m of one period of a perturbed 1-D grating (periodic; only the x-shifts matter), **exactly**: the
    period's transmittance is piecewise constant between the (shifted) mask edges, so
    ``c_m = (1/P) Σ_s exp(iφ_s) ∫_s exp(−2πimx/P) dx`` in closed form.

    Args:
        level_period: (P,) levels, one per pixel (e.g. :func:`blazed_grating_levels`).
        levels: L = 2^k.
        errors: :class:`FabricationErrors` (default none).
        alpha: detuning φ(λ)/φ(λ0) (:func:`raywave.doe.detuning`; 1 at λ0).
        orders: diffraction orders m.
    Returns (len(orders),) float64 efficiencies.
    """
    L = int(levels)
    masks = _grating_masks(level_period, L)
    k, P = masks.shape
    err = FabricationErrors.nominal(k) if errors is None else errors
    if err.masks != k:
        raise ValueError(f"{k} masks need {k} depth errors and shifts, got {err.masks}")
    dx = err.shift[:, 0]
    # breakpoints: every pixel edge of every shifted mask, folded into [0, P)
    edges = np.concatenate([np.mod(np.arange(P) + d, P) for d in dx] + [np.array([0.0, float(P)])])
    edges = np.unique(edges)
    a, b = edges[:-1], edges[1:]
    keep = b - a > 1e-12
    a, b = a[keep], b[keep]
    mid = 0.5 * (a + b)
    h = np.zeros_like(mid)
    for j in range(k):
        src = np.floor(np.mod(mid - dx[j], P)).astype(np.int64) % P
        h += 2.0 ** (k - 1 - j) * (1.0 + err.depth[j]) * (1.0 - masks[j, src])
    t = np.exp(1j * _TWO_PI * float(alpha) * h / L)
    out = []
    for m in _orders(orders):
        w = b - a
        c = np.sum(t * np.exp(-1j * _TWO_PI * m * mid / P) * w * np.sinc(m * w / P)) / P
        out.append(float(abs(c) ** 2))
    return np.array(out)


def grating_efficiency_fft(level_period, levels: int, errors: FabricationErrors | None = None, alpha: float = 1.0,
                           orders=(1,), oversample: int = 16) -> np.ndarray:
    """η_m of one period of a perturbed grating by an FFT of its sample-averaged transmittance
    (:func:`transmittance`, periodic) on the ``oversample``-times finer grid: ``|FFT_m/N|² sinc²(m/N)`` (N samples;
    the sinc integrates a constant sample exactly). Exact when every shift is a whole number of samples; otherwise
    the samples crossed by an edge are not constant, an error of order m/N there."""
    L = int(levels)
    masks = torch.as_tensor(_grating_masks(level_period, L))[:, None, :]
    k = masks.shape[0]
    err = FabricationErrors.nominal(k) if errors is None else errors
    t = transmittance(masks, err, L, alpha, oversample, (0, 0, 1, masks.shape[-1] * int(oversample)),
                      periodic=True)[0].numpy()
    N = t.size
    c = np.fft.fft(t) / N
    return np.array([float(abs(c[m % N]) ** 2 * np.sinc(m / N) ** 2) for m in _orders(orders)])


# ---------------------------------------------------------------------------- general DOE efficiency
def _design_phase(doe: DOE, wavelength0: float) -> torch.Tensor:
    """The unwrapped, unquantised design phase (rad) at λ0 of every DOE pixel, (ny, nx) float64."""
    with torch.no_grad():
        p = doe.design_phase_pixels(slice(None), slice(None)) * doe.phase_scale
        if wavelength0 != doe.design_wavelength:
            r = doe.dispersion_ratio(wavelength0)
            if r is not None:
                p = p * r
    return p.detach().to(torch.float64)


def _wrapped_gradient(p: torch.Tensor, dim: int) -> torch.Tensor:
    """Phase change per pixel along ``dim`` (rad), from wrapped central differences (one-sided at the edges)."""
    n = p.shape[dim]
    if n < 2:
        return torch.zeros_like(p)
    d = torch.diff(p, dim=dim)
    d = torch.atan2(torch.sin(d), torch.cos(d))
    first = d.narrow(dim, 0, 1)
    last = d.narrow(dim, n - 2, 1)
    if n == 2:
        return torch.cat([first, last], dim=dim)
    mid = 0.5 * (d.narrow(dim, 0, n - 2) + d.narrow(dim, 1, n - 2))
    return torch.cat([first, mid, last], dim=dim)


def _sample_maps(a: torch.Tensor, q: int, rows: slice) -> torch.Tensor:
    """A per-pixel map's rows ``rows`` repeated over q × q samples."""
    return a[rows].repeat_interleave(q, 0).repeat_interleave(q, 1)


def _sample_offsets(ny_px: int, nx_px: int, q: int, device):
    """Offsets (pixels) of every sample centre from its pixel centre: ``(ox (1, nx·q), oy (ny·q, 1))``."""
    off = (torch.arange(q, dtype=torch.float64, device=device) + 0.5) / q - 0.5
    return off.repeat(nx_px)[None, :], off.repeat(ny_px)[:, None]


class ToleranceWarning(UserWarning):
    """A tolerance analysis whose input makes a result unreliable (e.g. an undersampled design phase)."""


def design_maps(doe: DOE, wavelength0: float | None = None):
    """``(φ_u, gx, gy)``: the DOE's unwrapped design phase at λ0 (rad) on its pixels and its gradients (rad per
    pixel, from wrapped central differences: valid while the phase changes by < π per pixel; a
    :class:`ToleranceWarning` says when it comes close)."""
    import warnings

    lam0 = doe.design_wavelength if wavelength0 is None else float(wavelength0)
    p = _design_phase(doe, lam0)
    gx, gy = _wrapped_gradient(p, 1), _wrapped_gradient(p, 0)
    g = max(float(gx.abs().max()), float(gy.abs().max())) if p.numel() else 0.0
    if g > 0.9 * math.pi:
        warnings.warn(f"the DOE's design phase changes by up to {g:.3g} rad per pixel (Nyquist: π): the DOE is "
                      "(nearly) undersampled, so its local gradients and the design-order efficiencies are "
                      "unreliable", ToleranceWarning, stacklevel=2)
    return p, gx, gy


def doe_efficiency(pdoe: PerturbedDOE, wavelengths, orders=(1,), oversample: int = 1, design=None,
                   nominal: PerturbedDOE | None = None):
    """Efficiency of a perturbed DOE relative to its design, η_m (module docstring), and ``relative``, its overlap
    with the nominal fabricated element, computed in tiles of DOE rows.

    Exact for any shifts and a design phase linear inside each DOE pixel: the perturbed transmittance is constant
    on the sub-rectangles of :func:`profile_parts`, and the design wave's integral over each is
    ``area · exp(i m φ_u(centre)) · sinc(m gx du/2πq) · sinc(m gy dv/2πq)``. ``oversample`` (samples per pixel)
    only refines the aperture's edge (a circle); 1 suffices for a square aperture.

    Args:
        pdoe: the perturbed element (:class:`PerturbedDOE`).
        wavelengths: µm, scalar or list.
        orders: design orders m (the wave ``exp(i m φ_u)``).
        design: ``(φ_u, gx, gy)`` of :func:`design_maps` for the DOE that ``pdoe`` fabricates (required).
        nominal: the nominal element (default ``pdoe`` without errors), for ``relative``.
    Returns ``(eta (W, M), relative (W,))`` numpy float64.
    """
    wls = [float(w) for w in np.atleast_1d(np.asarray(wavelengths, dtype=np.float64))]
    ords = _orders(orders)
    q = int(oversample)
    if q < 1:
        raise ValueError(f"oversample must be an integer >= 1, got {oversample!r}")
    if design is None:
        raise ValueError("doe_efficiency needs the design maps (φ_u, gx, gy) of design_maps(doe)")
    phi_u, gx, gy = (torch.as_tensor(v, dtype=torch.float64, device=pdoe.device) for v in design)
    if tuple(phi_u.shape) != tuple(pdoe.shape):
        raise ValueError(f"the design maps ({tuple(phi_u.shape)}) and the DOE ({pdoe.shape}) differ in shape")
    nom = pdoe.with_errors(FabricationErrors.nominal(pdoe.errors.masks)) if nominal is None else nominal
    ny, nx = pdoe.shape
    dev = pdoe.device
    rows_per_tile = max(1, _TILE_SAMPLES // max(1, nx * q * q))
    cs = [_TWO_PI * pdoe.alpha(w) / pdoe.L for w in wls]
    acc = torch.zeros((len(wls), len(ords)), dtype=torch.complex128, device=dev)
    acc_rel = torch.zeros(len(wls), dtype=torch.complex128, device=dev)
    wsum = torch.zeros((), dtype=torch.float64, device=dev)
    for r0 in range(0, ny, rows_per_tile):
        r1 = min(ny, r0 + rows_per_tile)
        rows = slice(r0, r1)
        win = (r0 * q, 0, (r1 - r0) * q, nx * q)
        w = pdoe.coverage(win, q, device=dev)
        wsum = wsum + w.sum()
        h0 = nom.height_levels(win, q)
        p, ax, ay = _sample_maps(phi_u, q, rows), _sample_maps(gx, q, rows), _sample_maps(gy, q, rows)
        ox, oy = _sample_offsets(r1 - r0, nx, q, dev)
        p = p + ax * ox + ay * oy                     # φ_u at the sample centres
        t0c = [torch.polar(torch.ones_like(h0), -h0 * c).reshape(-1) for c in cs]   # conj of the nominal element
        for area, (cu, cv), (du, dv), h in profile_parts(pdoe.masks, pdoe.errors, q, win, pdoe.periodic):
            pc = p + (ax * cu + ay * cv) / q          # ... at the sub-rectangle's centre
            ds = [torch.polar(torch.sinc(m * ax * du / (_TWO_PI * q)) * torch.sinc(m * ay * dv / (_TWO_PI * q)),
                              -m * pc).reshape(-1) for m in ords]
            wa = w * area
            for i, c in enumerate(cs):
                t = torch.polar(wa, h * c).reshape(-1)
                for jm, d in enumerate(ds):
                    acc[i, jm] += torch.dot(t, d)
                acc_rel[i] += torch.dot(t, t0c[i])
    a2 = float(wsum) ** 2
    eta = (acc.abs() ** 2 / a2).cpu().numpy()
    rel = (acc_rel.abs() ** 2 / a2).cpu().numpy()
    return eta, rel


# ---------------------------------------------------------------------------- statistics, Monte Carlo
def summary_stats(values) -> dict:
    """mean, std (n − 1), min, max and the 5th / 50th / 95th percentiles of a 1-D sample (json-ready floats)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("no values")
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0, "min": float(v.min()),
            "max": float(v.max()), "p5": float(np.percentile(v, 5)), "p50": float(np.percentile(v, 50)),
            "p95": float(np.percentile(v, 95))}


PSF_METRICS = ("peak_ratio", "l1", "rms_radius_um", "r80_um", "crop_energy")


@dataclass
class ToleranceResult:
    """Per-sample results of :func:`tolerance_monte_carlo` (S samples, W wavelengths, M orders).

    Attributes:
        levels, masks: L and k. depth_error (percent), misalignment (DOE pixels), distribution, seed: the inputs.
        wavelengths: (W,) µm; wavelength0: λ0 µm; material: name; orders: (M,) ints; alpha: (W,) detunings.
        depth: (S, k) relative depth errors; shift: (S, k, 2) mask shifts (px).
        efficiency: (S, W, M) η_m of every sample; nominal_efficiency: (W, M) without errors;
        theory_efficiency: (W, M) the ideal L-level staircase at α(λ) (:func:`staircase_efficiency`).
        relative: (S, W) overlap with the nominal element (None for a grating).
        psf: per metric (:data:`PSF_METRICS`: peak_ratio, l1, rms_radius_um, r80_um, crop_energy; module
            docstring) an (S, W) array (None without a lens); nominal_psf_metrics: per metric (W,);
            nominal_psf, worst_psf: (W, ks, ks) fractions of the incident power; worst_sample: the sample with
            the lowest peak ratio (mean over the wavelengths); psf_pitch_um: their pixel pitch.
        kind: "grating" or "doe".
    """

    levels: int
    masks: int
    depth_error: float
    misalignment: float
    distribution: str
    seed: int | None
    wavelengths: list
    wavelength0: float
    material: str
    orders: list
    alpha: list
    depth: np.ndarray
    shift: np.ndarray
    efficiency: np.ndarray
    nominal_efficiency: np.ndarray
    theory_efficiency: np.ndarray
    kind: str = "doe"
    relative: np.ndarray | None = None
    psf: dict | None = None
    nominal_psf_metrics: dict | None = None
    nominal_psf: np.ndarray | None = None
    worst_psf: np.ndarray | None = None
    worst_sample: int | None = None
    psf_pitch_um: float | None = None
    info: dict = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return int(self.depth.shape[0])

    def summary(self) -> dict:
        """A json-ready dict: inputs, nominal / theory efficiencies per wavelength and order, and the statistics
        (:func:`summary_stats`) of every per-sample quantity."""
        eff = []
        for i, w in enumerate(self.wavelengths):
            for j, m in enumerate(self.orders):
                eff.append({"wavelength_um": w, "order": m, "alpha": self.alpha[i],
                            "theory": float(self.theory_efficiency[i, j]),
                            "nominal": float(self.nominal_efficiency[i, j]),
                            **summary_stats(self.efficiency[:, i, j])})
        out = {"kind": self.kind, "levels": self.levels, "masks": self.masks, "samples": self.n_samples,
               "depth_error_percent": self.depth_error, "misalignment_px": self.misalignment,
               "distribution": self.distribution,
               "tolerance_meaning": "±x = ±2σ of a normal distribution" if self.distribution == "normal"
               else "±x = bounds of a uniform distribution",
               "seed": self.seed, "wavelength0_um": self.wavelength0, "material": self.material,
               "wavelengths_um": list(self.wavelengths), "orders": list(self.orders), "efficiency": eff, **self.info}
        if self.relative is not None:
            out["relative"] = [{"wavelength_um": w, **summary_stats(self.relative[:, i])}
                               for i, w in enumerate(self.wavelengths)]
        if self.psf is not None:
            out["psf"] = [{"wavelength_um": w, "metric": name, "nominal": float(self.nominal_psf_metrics[name][i]),
                           **summary_stats(self.psf[name][:, i])}
                          for name in PSF_METRICS for i, w in enumerate(self.wavelengths)]
            out["worst_sample"] = self.worst_sample
            out["psf_pitch_um"] = self.psf_pitch_um
        return out


def tolerance_monte_carlo(doe, levels: int = 16, depth_error: float = 5.0, misalignment: float = 0.1,
                          n_samples: int = 100, seed: int | None = 0, generator: torch.Generator | None = None,
                          wavelengths=None, orders=(1,), material=None, wavelength0: float | None = None,
                          distribution: str = "normal", oversample: int = 1, lens=None, errors=None,
                          periodic: bool = False, progress: bool = False, observer=None) -> ToleranceResult:
    """Monte Carlo of the fabrication tolerance's diffraction efficiency (module docstring). The PSF change
    through a hybrid lens is :func:`raywave.assembly.tolerance.tolerance_monte_carlo` (same arguments plus
    ``lens``, ``fields``, ``ks``, ``rays``), which sits above :mod:`raywave.hybrid` and runs this loop with an
    ``observer``.

    Args:
        doe: a :class:`~raywave.doe.DOE` (general element, efficiency relative to its design), or one period of a
            grating as a 1-D array of levels (e.g. :func:`blazed_grating_levels`; exact periodic efficiencies).
        levels: L = 2^k.
        depth_error: ±x percent per etch step; misalignment: ±m DOE pixels per mask and axis (see
            :func:`sample_errors` and ``distribution``).
        n_samples, seed / generator: the random draws (deterministic for a seed).
        wavelengths: µm (default λ0). orders: diffraction orders m.
        material, wavelength0: the substrate (default the DOE's, else FUSED_SILICA; a grating: FUSED_SILICA) and λ0
            (default the DOE's design wavelength; a grating: 0.55 µm).
        oversample: samples per DOE pixel of the efficiency overlap (general DOE; exact at any value for a square
            aperture, finer only resolves a circular aperture's edge).
        lens: not taken here (a TypeError naming :func:`raywave.assembly.tolerance.tolerance_monte_carlo`, where
            the PSF part lives).
        errors: a list of :class:`FabricationErrors` to evaluate instead of random draws (then ``n_samples``,
            ``seed`` and the tolerances are only recorded).
        periodic: shifted masks wrap around the DOE grid (a DOE that is whole periods of a grating).
        progress: show a tqdm progress bar.
        observer: an object told about the run: ``observer.start(probe, wavelengths)`` (the nominal
            :class:`PerturbedDOE`, after the nominal efficiency), ``observer.sample(s, perturbed_doe)`` for every
            draw (after its efficiency), ``observer.finish(result)``; how the PSF part hooks in.
    Returns a :class:`ToleranceResult` (``psf`` fields None: no PSF here).
    """
    from tqdm.auto import tqdm

    if lens is not None:
        raise TypeError("raywave.doe.tolerance.tolerance_monte_carlo computes efficiencies only; the PSF change "
                        "through a HybridLens (lens=...) is raywave.assembly.tolerance.tolerance_monte_carlo "
                        "(the same arguments)")

    k = mask_bits(levels)
    L = int(levels)
    n = _count(n_samples, "the number of samples")
    ords = _orders(orders)
    grating = not isinstance(doe, DOE)
    if grating:
        period = np.asarray(doe)
        if period.ndim != 1:
            raise ValueError("doe must be a DOE or one grating period (a 1-D array of levels)")
        lam0 = 0.55 if wavelength0 is None else float(wavelength0)
        probe = PerturbedDOE(_LevelsDOE(period[None, :], L, lam0), L,
                             material="FUSED_SILICA" if material is None else material, wavelength0=lam0)
    else:
        probe = PerturbedDOE(doe, L, material=material, wavelength0=wavelength0, periodic=periodic)
        lam0 = probe.design_wavelength
    wls = [lam0] if wavelengths is None else [float(w) for w in np.atleast_1d(np.asarray(wavelengths, float))]
    for w in wls:
        wavelength_um(w, "wavelengths")
    alphas = [probe.alpha(w) for w in wls]
    if errors is None:
        errs = sample_errors(k, depth_error, misalignment, n, seed, generator, distribution)
    else:
        errs = list(errors)
        if not errs or not all(isinstance(e, FabricationErrors) and e.masks == k for e in errs):
            raise ValueError(f"errors must be a non-empty list of FabricationErrors for {k} masks")
        n = len(errs)
    theory = np.array([[staircase_efficiency(m, L, a) for m in ords] for a in alphas])

    if grating:
        def eff(e):
            return np.stack([grating_efficiency(period, L, e, a, ords) for a in alphas]), None
    else:
        design = design_maps(doe, lam0)

        def eff(e):
            return doe_efficiency(probe.with_errors(e), wls, ords, oversample, design, nominal=probe)

    nominal_eta, _ = eff(FabricationErrors.nominal(k))

    if observer is not None:
        if grating:
            raise ValueError("a PSF (lens=...) needs a DOE, not a grating period")
        observer.start(probe, wls)

    etas = np.zeros((n, len(wls), len(ords)))
    rel = None if grating else np.zeros((n, len(wls)))
    for s in tqdm(range(n), disable=not progress, desc="tolerance Monte Carlo", unit="sample"):
        e, r = eff(errs[s])
        etas[s] = e
        if rel is not None:
            rel[s] = r
        if observer is not None:
            observer.sample(s, probe.with_errors(errs[s]))

    res = ToleranceResult(
        levels=L, masks=k, depth_error=float(depth_error), misalignment=float(misalignment),
        distribution=distribution, seed=None if generator is not None else (0 if seed is None else int(seed)),
        wavelengths=wls, wavelength0=lam0, material=str(probe.material_name), orders=ords, alpha=alphas,
        depth=np.stack([e.depth for e in errs]), shift=np.stack([e.shift for e in errs]), efficiency=etas,
        nominal_efficiency=nominal_eta, theory_efficiency=theory, kind="grating" if grating else "doe",
        relative=rel, info={"oversample": None if grating else int(oversample)})
    if observer is not None:
        observer.finish(res)
    return res


class _LevelsDOE(DOE):
    """A DOE whose design phase is a given level map (phase 2πℓ/L at λ0): one grating period as a 1-row DOE."""

    def __init__(self, level_map, levels: int, wavelength0: float):
        lv = np.asarray(level_map, dtype=np.int64)
        super().__init__(tuple(lv.shape), 1e-3, design_wavelength=wavelength0)
        self.register_buffer("phase_map", torch.as_tensor(lv * (_TWO_PI / levels), dtype=torch.float64))

    def design_phase_pixels(self, rows, cols):
        return self.phase_map[rows, cols]
