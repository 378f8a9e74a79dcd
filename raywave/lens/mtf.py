"""Modulation transfer functions of a lens: diffraction MTF (the pupil's autocorrelation by FFT, as OpticStudio's
and optiland's "FFT MTF") and geometric MTF (the Fourier transform of the ray spot), tangential (along image y)
and sagittal (along x), monochromatic or weighted over wavelengths; and the MTF of any sampled PSF
(:func:`psf_mtf`, e.g. the ray-wave PSF of a hybrid lens, which ``raywave mtf`` uses for lenses with a DOE).

**Diffraction MTF.** The pupil function P = A·exp(2πi·OPD) on an ``n`` × ``n`` grid over the normalised pupil
(``linspace(-1, 1, n)``: samples on the rim, the rim rule of :mod:`raywave.rays.pupil`; A = 1 for rays that reach the
image, 0 for vignetted ones), OPD from :func:`raywave.lens.analysis.wavefront_opd` (chief-ray reference sphere).
The OTF at a pupil shift of k samples is the autocorrelation of P (zero-padded FFT, no wrap-around), normalised to
1 at 0. One sample of shift along the pupil's y (x) diameter is the frequency n'·Δ/((n − 1)·λ) along image y (x),
Δ the length of the difference of the unit direction vectors of the two marginal rays at py = ±1 (px = ±1) after
the lens (projected on the image plane), n' the image-space index: optiland's calibration, exact where the map from
the pupil to the image-space direction cosines is affine. Frequencies between shifts are interpolated linearly.

**Geometric MTF.** |Σ_i exp(−2πi ν y_i)| / N over the N valid rays' image-plane y (x for sagittal) of a uniform
pupil grid (the spot's characteristic function: exact for the ray PSF), optionally multiplied by the
diffraction-limited MTF of the lens's F-number (``scale``, OpticStudio's and optiland's default).

Frequencies in cycles/mm; all results float64 tensors without autograd.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from raywave.lens.analysis import field_pairs as _fields, wavefront_opd
from raywave.lens.opd import square_pupil_grid
from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.rays.pupil import inset_rim


@dataclass
class MTFResult:
    """MTFs of fields (F) at ``frequencies`` (K,) cycles/mm: ``tangential`` and ``sagittal`` (F, K) in [0, 1], NaN
    for a field whose every ray is vignetted. ``kind``: "diffraction", "geometric" or "psf"; ``wavelengths`` µm
    (weights ``weights``, summing to 1); ``cutoff``: the incoherent cutoff 1/(λ·N) of the primary wavelength (on-axis
    paraxial F-number N), cycles/mm."""

    frequencies: torch.Tensor
    tangential: torch.Tensor
    sagittal: torch.Tensor
    fields: torch.Tensor
    wavelengths: list
    weights: list
    kind: str
    cutoff: float



def _wavelengths(lens, wavelengths, weights):
    wls = [float(lens.primary_wavelength)] if wavelengths is None else [float(w) for w in
                                                                          torch.as_tensor(wavelengths).reshape(-1)]
    w = [1.0] * len(wls) if weights is None else [float(v) for v in weights]
    if len(w) != len(wls) or any(not (v >= 0) for v in w) or sum(w) <= 0:
        raise ValueError(f"MTF wavelength weights {w} must be >= 0, not all 0, one per wavelength ({len(wls)})")
    s = sum(w)
    return wls, [v / s for v in w]


def cutoff_frequency(lens, wavelength: float | None = None) -> float:
    """The incoherent cutoff 1/(λ·N) (cycles/mm) of the lens's on-axis paraxial F-number N at ``wavelength`` µm."""
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    p = lens.paraxial(wl)
    return 1.0 / (wl * 1e-3 * float(p.working_fnum if math.isfinite(float(p.working_fnum)) else p.fnum))


def diffraction_limited_mtf(nu: torch.Tensor, cutoff: float) -> torch.Tensor:
    """The MTF of an aberration-free circular pupil: (2/π)(φ − cos φ sin φ), φ = arccos(ν/ν_c), 0 beyond ν_c."""
    x = (nu / cutoff).clamp(0.0, 1.0)
    phi = torch.arccos(x)
    return 2.0 / math.pi * (phi - torch.cos(phi) * torch.sin(phi))


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of ``fp`` (..., M) given at increasing ``xp`` (M,) to ``x`` (K,); 0 beyond ``xp[-1]``."""
    i = torch.searchsorted(xp, x.clamp(max=float(xp[-1])), right=True).clamp(1, xp.numel() - 1)
    x0, x1 = xp[i - 1], xp[i]
    w = ((x - x0) / (x1 - x0)).clamp(0.0, 1.0)
    out = fp[..., i - 1] * (1 - w) + fp[..., i] * w
    return torch.where(x > xp[-1], torch.zeros_like(out), out)


def _frequency_steps(lens, fields, wl, n) -> torch.Tensor:
    """Cycles/mm per pupil sample of shift, (F, 2) = (along y, along x), from the marginal rays' directions."""
    px = torch.tensor([0.0, 0.0, 1.0, -1.0], dtype=torch.float64, device=lens.device)
    py = torch.tensor([1.0, -1.0, 0.0, 0.0], dtype=torch.float64, device=lens.device)
    out = lens.image_coordinates(lens.trace_to_image(point_source_rays(lens, fields, [wl], pupil=inset_rim(px, py))))
    d = out.d[:, 0]  # (F, 4, 3), in the image plane's frame: its normal is z
    n_img = float(lens.surfaces[-1].material.n(torch.tensor([wl], dtype=torch.float64))[0])
    dt = torch.linalg.vector_norm(d[:, 0, :2] - d[:, 1, :2], dim=-1)
    ds = torch.linalg.vector_norm(d[:, 2, :2] - d[:, 3, :2], dim=-1)
    return torch.stack([dt, ds], -1) * abs(n_img) / ((n - 1) * wl * 1e-3)


def _pupil_autocorrelation(pupil: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """|OTF| along y and x of the (F, n, n) complex pupils at shifts 0..n−1 samples: (F, n) each, 1 at 0."""
    n = pupil.shape[-1]
    size = 2 * n
    spec = torch.fft.fft2(pupil, s=(size, size))
    otf = torch.fft.ifft2(spec.real ** 2 + spec.imag ** 2)  # autocorrelation, lag (0, 0) at [0, 0]
    dc = otf[..., 0, 0].real.clamp_min(1e-300)[..., None]
    return otf[..., :n, 0].abs() / dc, otf[..., 0, :n].abs() / dc


def diffraction_mtf(lens, fields=None, frequencies=None, wavelengths=None, weights=None, n: int = 64) -> MTFResult:
    """Diffraction (FFT) MTF of ``fields`` ((x, y) pairs or y values; default the lens's) at ``frequencies``
    cycles/mm (default 0 … cutoff in 64 steps), over an ``n`` × ``n`` pupil grid; ``wavelengths`` µm (default the
    primary) weighted by ``weights`` (default equal): the MTFs' weighted sum on the common frequency axis (the
    polychromatic OTF modulus of OpticStudio is a sum of complex OTFs; for the rotationally symmetric on-axis case
    they agree). See the module docstring."""
    lens.require_unfolded("diffraction_mtf")
    if n < 8:
        raise ValueError(f"the MTF's pupil grid needs n >= 8 samples across, got {n}")
    f = _fields(lens, fields)
    wls, wts = _wavelengths(lens, wavelengths, weights)
    cut = cutoff_frequency(lens)
    nu = (torch.linspace(0, cut, 65, dtype=torch.float64) if frequencies is None
          else torch.as_tensor(frequencies, dtype=torch.float64).reshape(-1))
    nu = nu.to(lens.device)
    px, py = square_pupil_grid(n, lens.device)
    inside = px * px + py * py <= 1.0
    tan = torch.zeros((f.shape[0], nu.numel()), dtype=torch.float64, device=lens.device)
    sag = torch.zeros_like(tan)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        for wl, wt in zip(wls, wts):
            opd, _, _, v = wavefront_opd(lens, f, [wl], pupil=inset_rim(px[inside], py[inside]))
            ok = v[:, 0] & torch.isfinite(opd[:, 0])
            field = torch.zeros((f.shape[0], n * n), dtype=torch.complex128, device=lens.device)
            phase = torch.where(ok, 2 * math.pi * opd[:, 0], torch.zeros_like(opd[:, 0]))
            field[:, inside] = torch.where(ok, torch.polar(torch.ones_like(phase), phase),
                                           torch.zeros_like(phase, dtype=torch.complex128))
            mt, ms = _pupil_autocorrelation(field.reshape(-1, n, n))
            steps = _frequency_steps(lens, f, wl, n)  # (F, 2)
            lags = torch.arange(n, dtype=torch.float64, device=lens.device)
            for i in range(f.shape[0]):
                dead = not bool(ok[i].any())
                tan[i] += wt * (math.nan if dead else _interp(nu, lags * steps[i, 0], mt[i]))
                sag[i] += wt * (math.nan if dead else _interp(nu, lags * steps[i, 1], ms[i]))
    return MTFResult(nu, tan, sag, f, wls, wts, "diffraction", cut)


def geometric_mtf(lens, fields=None, frequencies=None, wavelengths=None, weights=None, pupil=("grid", 64),
                  scale: bool = True) -> MTFResult:
    """Geometric MTF of ``fields`` at ``frequencies`` cycles/mm (default 0 … cutoff) from the rays of ``pupil``
    (``(pattern, n)`` or explicit ``(px, py)``; default a 64 × 64 grid in the disk), ``wavelengths`` weighted as in
    :func:`diffraction_mtf` (the weighted rays' characteristic function), times the diffraction limit when ``scale``.
    See the module docstring."""
    f = _fields(lens, fields)
    wls, wts = _wavelengths(lens, wavelengths, weights)
    cut = cutoff_frequency(lens)
    nu = (torch.linspace(0, cut, 65, dtype=torch.float64) if frequencies is None
          else torch.as_tensor(frequencies, dtype=torch.float64).reshape(-1)).to(lens.device)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        if not isinstance(pupil[0], str):  # explicit samples: the rim rule (named patterns have it already)
            pupil = inset_rim(*(torch.as_tensor(p, dtype=torch.float64, device=lens.device).reshape(-1)
                                for p in pupil))
        out = lens.image_coordinates(lens.trace_to_image(point_source_rays(lens, f, wls, pupil=pupil)))
    ok = out.valid & torch.isfinite(out.o).all(-1)  # (F, W, N)
    w = ok.to(torch.float64) * torch.tensor(wts, dtype=torch.float64, device=lens.device)[None, :, None]
    total = w.sum((-1, -2))  # (F,)

    def char(coord):
        c = torch.where(ok, coord, torch.zeros_like(coord))
        arg = 2 * math.pi * nu[None, None, None, :] * c[..., None]  # (F, W, N, K)
        re = (torch.cos(arg) * w[..., None]).sum((1, 2))
        im = (torch.sin(arg) * w[..., None]).sum((1, 2))
        m = torch.sqrt(re * re + im * im) / total.clamp_min(1e-300)[:, None]
        return torch.where(total[:, None] > 0, m, torch.full_like(m, math.nan))

    tan, sag = char(out.o[..., 1]), char(out.o[..., 0])
    if scale:
        dl = diffraction_limited_mtf(nu, cut)
        tan, sag = tan * dl, sag * dl
    return MTFResult(nu, tan, sag, f, wls, wts, "geometric", cut)


def psf_mtf(psf: torch.Tensor, pitch: float, frequencies: torch.Tensor,
            pixel_divided: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangential (along y, the PSF's rows) and sagittal (along x) MTF of sampled PSFs ``psf`` (..., ks, ks) on
    pixels of ``pitch`` mm at ``frequencies`` (K,) cycles/mm: |DFT of the PSF| along each axis through the origin,
    evaluated directly at each frequency (no grid rounding), normalised to 1 at 0. ``pixel_divided``: divide out the
    square pixel's own MTF |sinc(ν·pitch)| (the PSF's pixels integrate the light), so the result is the optics' MTF;
    frequencies beyond the pixels' Nyquist limit 1/(2·pitch) are NaN (not sampled)."""
    ks = psf.shape[-1]
    nu = torch.as_tensor(frequencies, dtype=torch.float64, device=psf.device).reshape(-1)
    pos = (torch.arange(ks, dtype=torch.float64, device=psf.device) - ks // 2) * pitch
    kern = torch.exp(-2j * math.pi * nu[:, None] * pos[None, :])  # (K, ks)
    p = psf.to(torch.float64)
    rows, cols = p.sum(-1), p.sum(-2)  # line spread functions: along y (rows) and along x (columns)
    total = p.sum((-1, -2)).clamp_min(1e-300)[..., None]
    tan = (rows.to(torch.complex128) @ kern.T).abs() / total
    sag = (cols.to(torch.complex128) @ kern.T).abs() / total
    if pixel_divided:
        s = torch.sinc(nu * pitch).abs().clamp_min(1e-12)
        tan, sag = tan / s, sag / s
    beyond = nu > 0.5 / pitch + 1e-12
    nan = torch.full_like(tan, math.nan)
    return torch.where(beyond, nan, tan), torch.where(beyond, nan, sag)
