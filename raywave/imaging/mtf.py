"""The MTF of a hybrid lens through its ray-wave PSFs (:class:`raywave.hybrid.HybridLens`): the DOE's phase and
aperture, the stop's edge and the lens's aberrations all in it, where the pupil FFT of
:func:`raywave.lens.mtf.diffraction_mtf` sees the refractive lens alone.

The PSFs are computed on a fine sensor grid (default pitch λN/4 at the primary wavelength, N the on-axis working
F-number: twice the sampling the incoherent cutoff 1/(λN) needs), summed over the wavelengths with their weights,
and transformed by :func:`raywave.lens.mtf.psf_mtf` with the pixels' own sinc divided out. The light that falls
outside the ks × ks crop (``PSFResult.energy_outside``) is taken to carry no modulation at the frequencies shown (it
spreads wider than the crop): the MTF above 0 is scaled by the power inside the crop.
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens.mtf import MTFResult, cutoff_frequency, psf_mtf


class MTFCropWarning(UserWarning):
    """Much of a PSF's light falls outside the crop the MTF is computed on."""


def raywave_mtf(hl, fields=None, frequencies=None, wavelengths=None, weights=None, pitch: float | None = None,
                ks: int = 128, outside_limit: float = 0.05) -> tuple[MTFResult, torch.Tensor]:
    """MTF (tangential: along sensor y; sagittal: along x) of the hybrid lens ``hl`` at ``fields`` ((x, y) pairs or
    y values in degrees / the lens's field type; default the lens's along y) and ``frequencies`` (cycles/mm, default
    0 … min(cutoff, Nyquist of ``pitch``) in 64 steps), ``wavelengths`` µm (default the primary) weighted by
    ``weights``, PSFs of ``ks`` × ``ks`` pixels of ``pitch`` mm. Returns the :class:`MTFResult` (kind "raywave")
    and the energy outside the crop per field (F,) (a :class:`MTFCropWarning` above ``outside_limit``)."""
    lens = hl.lens
    if fields is None:
        fields = [(0.0, float(f)) for f in lens.fields]
    f = torch.as_tensor(fields, dtype=torch.float64)
    f = torch.stack([torch.zeros_like(f), f], -1) if f.ndim == 1 else f.reshape(-1, 2)
    wls = [float(lens.primary_wavelength)] if wavelengths is None else [float(w) for w in wavelengths]
    wts = torch.tensor([1.0] * len(wls) if weights is None else [float(w) for w in weights], dtype=torch.float64)
    if wts.numel() != len(wls) or bool((wts < 0).any()) or float(wts.sum()) <= 0:
        raise ValueError(f"MTF wavelength weights {wts.tolist()} must be >= 0, not all 0, one per wavelength")
    wts = wts / wts.sum()
    cut = cutoff_frequency(lens)
    if pitch is None:
        pitch = 0.25 / cut  # λN/4
    if frequencies is None:
        frequencies = torch.linspace(0.0, min(cut, 0.5 / pitch), 65, dtype=torch.float64)
    nu = torch.as_tensor(frequencies, dtype=torch.float64).reshape(-1)
    fine = hl.with_doe(hl.doe, sensor_pitch=float(pitch))
    with torch.no_grad():
        res = fine.psf_result([tuple(float(v) for v in row) for row in f], wls, ks=int(ks))
    psf = (res.psf.cpu() * wts[None, :, None, None]).sum(1)  # (F, ks, ks)
    outside = (res.energy_outside.cpu() * wts[None]).sum(1)  # (F,)
    tan, sag = psf_mtf(psf, float(res.pitch), nu)
    inside = (1.0 - outside)[:, None]
    scale = torch.where(nu[None] > 0, inside, torch.ones_like(inside))
    dead = psf.sum((-1, -2)) <= 0
    tan = torch.where(dead[:, None], torch.full_like(tan, math.nan), tan * scale)
    sag = torch.where(dead[:, None], torch.full_like(sag, math.nan), sag * scale)
    for i in range(f.shape[0]):
        if float(outside[i]) > outside_limit:
            warnings.warn(f"field {f[i].tolist()}: {100 * float(outside[i]):.1f} % of the PSF's light falls outside its "
                          f"{ks}×{ks} crop of {pitch * 1e3:.3g} µm pixels; the MTF's low frequencies are uncertain by "
                          "about that much: raise ks", MTFCropWarning, stacklevel=2)
    return MTFResult(nu, tan, sag, f, wls, wts.tolist(), "raywave", cut), outside
