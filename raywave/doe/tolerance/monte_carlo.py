"""The Monte Carlo of the fabrication tolerance's diffraction efficiency (:func:`tolerance_monte_carlo`), its
per-sample results (:class:`ToleranceResult`) and their statistics (:func:`summary_stats`); the PSF part is
:func:`raywave.assembly.tolerance.tolerance_monte_carlo`, an observer of this loop."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from raywave.doe.base import DOE
from raywave.doe.efficiency import staircase_efficiency
from raywave.doe.fabrication import mask_bits
from raywave.doe.tolerance.errors import FabricationErrors, _count, _orders, sample_errors
from raywave.doe.tolerance.gratings import grating_efficiency
from raywave.doe.tolerance.overlap import design_maps, doe_efficiency
from raywave.doe.tolerance.profile import PerturbedDOE
from raywave.utils.checks import wavelength_um

_TWO_PI = 2.0 * math.pi


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
    k, L, n, ords = _run_inputs(lens, levels, n_samples, orders)
    grating = not isinstance(doe, DOE)
    probe, lam0 = _nominal_element(doe, L, material, wavelength0, periodic)
    wls = _wavelengths(wavelengths, lam0)
    alphas = [probe.alpha(w) for w in wls]
    errs = _error_draws(errors, k, depth_error, misalignment, n, seed, generator, distribution)
    theory = np.array([[staircase_efficiency(m, L, a) for m in ords] for a in alphas])
    eff = _efficiency_of(doe, probe, L, lam0, wls, alphas, ords, oversample)
    nominal_eta, _ = eff(FabricationErrors.nominal(k))
    _start_observer(observer, grating, probe, wls)
    etas, rel = _run_samples(eff, errs, probe, (len(wls), len(ords)), grating, progress, observer)
    res = ToleranceResult(
        levels=L, masks=k, depth_error=float(depth_error), misalignment=float(misalignment),
        distribution=distribution, seed=None if generator is not None else (0 if seed is None else int(seed)),
        **_result_data(probe, lam0, wls, ords, alphas, errs, etas, rel, nominal_eta, theory, grating, oversample))
    if observer is not None:
        observer.finish(res)
    return res


def _run_inputs(lens, levels: int, n_samples: int, orders) -> tuple:
    """``(k, L, n, orders)``: the masks and levels of ``levels`` = L = 2^k, the number of samples and the orders,
    checked; a TypeError for a ``lens`` (the PSF part is :func:`raywave.assembly.tolerance.tolerance_monte_carlo`)."""
    if lens is not None:
        raise TypeError("raywave.doe.tolerance.tolerance_monte_carlo computes efficiencies only; the PSF change "
                        "through a HybridLens (lens=...) is raywave.assembly.tolerance.tolerance_monte_carlo "
                        "(the same arguments)")
    k = mask_bits(levels)
    L = int(levels)
    n = _count(n_samples, "the number of samples")
    return k, L, n, _orders(orders)


def _start_observer(observer, grating: bool, probe: PerturbedDOE, wls: list) -> None:
    """Tell ``observer`` (if any) the nominal element ``probe`` and the wavelengths (µm); a grating period has no
    PSF (ValueError)."""
    if observer is not None:
        if grating:
            raise ValueError("a PSF (lens=...) needs a DOE, not a grating period")
        observer.start(probe, wls)


def _result_data(probe, lam0, wls, ords, alphas, errs, etas, rel, nominal_eta, theory, grating, oversample) -> dict:
    """The :class:`ToleranceResult` fields of a run other than its tolerance inputs: wavelengths (µm), material,
    orders, detunings, the draws' depth errors (S, k) and shifts (S, k, 2 px), efficiencies (S, W, M), kind."""
    return dict(wavelengths=wls, wavelength0=lam0, material=str(probe.material_name), orders=ords, alpha=alphas,
                depth=np.stack([e.depth for e in errs]), shift=np.stack([e.shift for e in errs]), efficiency=etas,
                nominal_efficiency=nominal_eta, theory_efficiency=theory, kind="grating" if grating else "doe",
                relative=rel, info={"oversample": None if grating else int(oversample)})


def _nominal_element(doe, L: int, material, wavelength0, periodic: bool):
    """``(probe, λ0)``: the nominal fabricated element (a :class:`PerturbedDOE` without errors) and its λ0 (µm).

    A DOE keeps its material and design wavelength unless given; one grating period (a 1-D array of levels) becomes
    a 1-row :class:`_LevelsDOE` in FUSED_SILICA (default) at λ0 = 0.55 µm (default)."""
    if not isinstance(doe, DOE):
        period = np.asarray(doe)
        if period.ndim != 1:
            raise ValueError("doe must be a DOE or one grating period (a 1-D array of levels)")
        lam0 = 0.55 if wavelength0 is None else float(wavelength0)
        probe = PerturbedDOE(_LevelsDOE(period[None, :], L, lam0), L,
                             material="FUSED_SILICA" if material is None else material, wavelength0=lam0)
    else:
        probe = PerturbedDOE(doe, L, material=material, wavelength0=wavelength0, periodic=periodic)
        lam0 = probe.design_wavelength
    return probe, lam0


def _wavelengths(wavelengths, lam0: float) -> list:
    """The wavelengths (µm, a list of floats; default ``[λ0]``), each checked by :func:`wavelength_um`."""
    wls = [lam0] if wavelengths is None else [float(w) for w in np.atleast_1d(np.asarray(wavelengths, float))]
    for w in wls:
        wavelength_um(w, "wavelengths")
    return wls


def _error_draws(errors, k: int, depth_error, misalignment, n: int, seed, generator, distribution) -> list:
    """The S :class:`FabricationErrors` of the run: ``errors`` as given (checked: k masks each), else ``n`` random
    draws of :func:`sample_errors` (depth error in percent, misalignment in DOE pixels)."""
    if errors is None:
        return sample_errors(k, depth_error, misalignment, n, seed, generator, distribution)
    errs = list(errors)
    if not errs or not all(isinstance(e, FabricationErrors) and e.masks == k for e in errs):
        raise ValueError(f"errors must be a non-empty list of FabricationErrors for {k} masks")
    return errs


def _efficiency_of(doe, probe: PerturbedDOE, L: int, lam0: float, wls: list, alphas: list, ords: list,
                   oversample: int):
    """A function ``errors -> (eta (W, M), relative (W,) or None)``: the exact periodic efficiencies of a grating
    period (:func:`grating_efficiency` at every detuning α), or a DOE's efficiencies relative to its design
    (:func:`doe_efficiency` against the nominal ``probe``; the design maps are computed here, once)."""
    if not isinstance(doe, DOE):
        period = np.asarray(doe)

        def eff(e):
            return np.stack([grating_efficiency(period, L, e, a, ords) for a in alphas]), None
    else:
        design = design_maps(doe, lam0)

        def eff(e):
            return doe_efficiency(probe.with_errors(e), wls, ords, oversample, design, nominal=probe)
    return eff


def _run_samples(eff, errs: list, probe: PerturbedDOE, shape: tuple, grating: bool, progress: bool, observer):
    """Evaluate every draw: ``(etas (S, W, M), relative (S, W) or None for a grating)``, telling ``observer`` about
    each perturbed element after its efficiency; ``shape`` = (W, M)."""
    from tqdm.auto import tqdm

    n = len(errs)
    etas = np.zeros((n,) + tuple(shape))
    rel = None if grating else np.zeros((n, shape[0]))
    for s in tqdm(range(n), disable=not progress, desc="tolerance Monte Carlo", unit="sample"):
        e, r = eff(errs[s])
        etas[s] = e
        if rel is not None:
            rel[s] = r
        if observer is not None:
            observer.sample(s, probe.with_errors(errs[s]))
    return etas, rel


class _LevelsDOE(DOE):
    """A DOE whose design phase is a given level map (phase 2πℓ/L at λ0): one grating period as a 1-row DOE."""

    def __init__(self, level_map, levels: int, wavelength0: float):
        lv = np.asarray(level_map, dtype=np.int64)
        super().__init__(tuple(lv.shape), 1e-3, design_wavelength=wavelength0)
        self.register_buffer("phase_map", torch.as_tensor(lv * (_TWO_PI / levels), dtype=torch.float64))

    def design_phase_pixels(self, rows, cols):
        return self.phase_map[rows, cols]
