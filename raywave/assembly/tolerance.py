"""The fabrication-tolerance Monte Carlo with the PSF change through a hybrid lens (assembly layer).

:mod:`raywave.doe.tolerance` draws the fabrication errors and computes the diffraction efficiencies (the DOE
alone); this module adds, for a :class:`~raywave.hybrid.HybridLens`, every sample's ray-wave PSF compared with the
nominal element's (the **PSF** paragraph of :mod:`raywave.doe.tolerance`'s docstring): the field arriving at the
DOE depends on the lens only and is computed once; each perturbed element enters as its sample-averaged
transmittance on the lens's simulation grid. It sits above :mod:`raywave.hybrid` (docs/architecture.md), which is
why it is not in :mod:`raywave.doe`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from raywave.doe.base import DOE
from raywave.doe.tolerance import PSF_METRICS, PerturbedDOE, ToleranceResult
from raywave.doe.tolerance import tolerance_monte_carlo as _efficiency_monte_carlo
from raywave.hybrid.hybrid_lens import HybridLens
from raywave.hybrid.metrics import psf_metrics

__all__ = ["PSFTolerance", "tolerance_monte_carlo"]


def _psf_numbers(psf: torch.Tensor, pitch_um: float):
    m = psf_metrics(psf, pitch_um, fractions=(0.8,))
    return m["peak"], m["rms_radius"], m["r80"]


def _perturbed_psf(work: HybridLens, pdoe: PerturbedDOE, fds, ks: int) -> torch.Tensor:
    """PSFs (W, ks, ks) of the first field of ``fds`` with ``pdoe`` in ``work``, as **fractions of the power
    incident on the DOE** (not normalised to 1: light diffracted out of the crop is lost): the DOE's phase, and the
    amplitude of its sample-averaged transmittance applied to the incident field."""
    work.doe = pdoe
    row, ratio = [], []
    for fd in fds[0]:
        amp = pdoe.transmittance(fd.wavelength, fd.grid, work.oversample).abs()
        env = fd.envelope * amp
        p_in = float(fd.envelope.detach().abs().square().sum())
        ratio.append(float(env.detach().abs().square().sum()) / p_in if p_in > 0 else 0.0)
        row.append(fd.with_envelope(env))
    res = work.psf_result(cache=[row], ks=ks)
    keep = (1.0 - res.energy_outside[0]).detach().cpu() * torch.tensor(ratio, dtype=torch.float64)
    return res.psf[0].detach().cpu() * keep[:, None, None]


class PSFTolerance:
    """The PSF part of the Monte Carlo, an ``observer`` of :func:`raywave.doe.tolerance.tolerance_monte_carlo`:
    ``start`` computes the DOE-plane fields (once) and the nominal PSF, ``sample`` every draw's PSF metrics,
    ``finish`` stores them in the :class:`~raywave.doe.tolerance.ToleranceResult`.

    Args:
        lens: the :class:`HybridLens` (its lens, DOE distance, sensor pitch, oversample; the DOE is replaced).
        fields: one field point (lens's field type); ks: PSF crop (sensor pixels); rays: traced nodes.
    """

    def __init__(self, lens: HybridLens, fields=(0.0, 0.0), ks: int = 64, rays: int | None = None):
        self.lens, self.fields, self.ks, self.rays = lens, fields, ks, rays

    def start(self, probe: PerturbedDOE, wavelengths) -> None:
        lens = self.lens
        self.work = lens.with_doe(probe)
        with torch.no_grad():
            fds = self.work.doe_fields(self.fields, wavelengths, rays=self.rays,
                                       crop_reach=self.work.crop_reach(self.ks))
            if len(fds) != 1:
                raise ValueError(f"the PSF tolerance takes one field point, got {len(fds)}")
            for row in fds:
                for fd in row:
                    fd.field = fd.field.with_envelope(fd.envelope.detach())
            self.fds = fds
            self.nominal_psf = _perturbed_psf(self.work, probe, fds, self.ks)
        self.n_wl = len(wavelengths)
        self.pitch_um = self.work.sensor_pitch * 1e3
        self.nominal = [_psf_numbers(self.nominal_psf[i], self.pitch_um) for i in range(self.n_wl)]
        self.values: dict = {name: [] for name in PSF_METRICS}
        self.worst_val, self.worst_i, self.worst_psf = math.inf, None, None

    def sample(self, s: int, pdoe: PerturbedDOE) -> None:
        with torch.no_grad():
            p = _perturbed_psf(self.work, pdoe, self.fds, self.ks)
        row = {name: np.zeros(self.n_wl) for name in PSF_METRICS}
        for i in range(self.n_wl):
            peak, rms, r80 = _psf_numbers(p[i], self.pitch_um)
            row["peak_ratio"][i] = peak / self.nominal[i][0]
            row["l1"][i] = float((p[i] - self.nominal_psf[i]).abs().sum() / self.nominal_psf[i].sum())
            row["rms_radius_um"][i] = rms
            row["r80_um"][i] = r80
            row["crop_energy"][i] = float(p[i].sum())
        for name in PSF_METRICS:
            self.values[name].append(row[name])
        v = float(row["peak_ratio"].mean())
        if v < self.worst_val:
            self.worst_val, self.worst_i, self.worst_psf = v, s, p.cpu().numpy()

    def finish(self, res: ToleranceResult) -> None:
        nw = self.n_wl
        res.psf = {name: np.array(self.values[name]).reshape(-1, nw) for name in PSF_METRICS}
        res.nominal_psf_metrics = {"peak_ratio": np.ones(nw), "l1": np.zeros(nw),
                                   "rms_radius_um": np.array([v[1] for v in self.nominal]),
                                   "r80_um": np.array([v[2] for v in self.nominal]),
                                   "crop_energy": np.array([float(self.nominal_psf[i].sum()) for i in range(nw)])}
        res.nominal_psf = self.nominal_psf.cpu().numpy()
        res.worst_psf = self.worst_psf
        res.worst_sample = self.worst_i
        res.psf_pitch_um = self.pitch_um


def tolerance_monte_carlo(doe, levels: int = 16, depth_error: float = 5.0, misalignment: float = 0.1,
                          n_samples: int = 100, seed: int | None = 0, generator: torch.Generator | None = None,
                          wavelengths=None, orders=(1,), material=None, wavelength0: float | None = None,
                          distribution: str = "normal", oversample: int = 1, lens=None, fields=(0.0, 0.0),
                          ks: int = 64, rays: int | None = None, errors=None, periodic: bool = False,
                          progress: bool = False) -> ToleranceResult:
    """Monte Carlo of the fabrication tolerance: the efficiencies of
    :func:`raywave.doe.tolerance.tolerance_monte_carlo` (see it for the arguments) and, with ``lens`` (a
    :class:`~raywave.hybrid.HybridLens`: its lens, DOE distance, sensor pitch and oversample; ``doe`` replaces its
    DOE), every sample's PSF change (:class:`PSFTolerance`). ``fields``, ``ks``, ``rays``: the PSF's source (one
    field point, in the lens's field type), crop (sensor pixels) and node count.

    Returns a :class:`~raywave.doe.tolerance.ToleranceResult`; its PSFs are fractions of the power incident on the
    DOE (the light a fabrication error diffracts out of the ``ks × ks`` crop is lost), the metrics are defined in
    its docstring."""
    observer = None
    if lens is not None:
        if not isinstance(doe, DOE):
            raise ValueError("a PSF (lens=...) needs a DOE, not a grating period")
        observer = PSFTolerance(lens, fields, ks, rays)
    return _efficiency_monte_carlo(doe, levels, depth_error, misalignment, n_samples, seed, generator, wavelengths,
                                   orders, material, wavelength0, distribution, oversample, errors=errors,
                                   periodic=periodic, progress=progress, observer=observer)
