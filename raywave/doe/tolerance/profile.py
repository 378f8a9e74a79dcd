"""The perturbed profile of a fabricated DOE on the simulation grid, exactly (sub-pixel mask shifts split every
sample into constant sub-rectangles), and :class:`PerturbedDOE`, the fabricated element as a DOE
(:mod:`raywave.doe.tolerance`, "Sub-pixel shifts, exactly")."""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.doe.base import DOE
from raywave.doe.fabrication import mask_bits, masks_from_levels
from raywave.doe.tolerance.errors import FabricationErrors

_TWO_PI = 2.0 * math.pi


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

    def transmittance(self, wavelength: float, window=None, oversample: int = 1) -> torch.Tensor:
        """Complex transmittance (complex128) of the perturbed element at ``wavelength`` on the simulation samples
        of ``window`` (default: the whole grid): the exact mean of ``exp(iφ)`` over each sample
        (:func:`transmittance`), ``|t| < 1`` where a shifted mask edge crosses a sample."""
        q = int(oversample)
        window = self.sim_window(window, q)
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
