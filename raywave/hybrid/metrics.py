"""Figures of merit of a sampled PSF: centroid, RMS radius, encircled energy, peak.

The PSF is a pixel-integrated array ``[iy, ix]`` (each value = the energy falling on that sensor pixel, both
indices increasing with the coordinate), pixel ``[ks//2, ks//2]`` centred on the reference point (the chief
ray for :class:`~raywave.hybrid.HybridLens`). Lengths are returned in the unit of ``pitch``.

* **centroid**: energy-weighted mean of the pixel centres, relative to the centre of pixel ``[ks//2, ks//2]``.
* **RMS radius**: ``sqrt(Σ E (r − centroid)²)`` over pixel centres. For a PSF sampled by pixels this is the
  RMS radius of the *pixel-integrated* PSF: ``sqrt(σx² + σy² + pitch²/6)`` for a smooth intensity of
  variances σx², σy² (each pixel adds its box variance pitch²/12 per axis).
* **encircled energy** ``EE(r)``: the energy inside a circle of radius r about the centroid, each pixel's
  energy spread uniformly over its square (the sensor cannot tell where in the pixel it fell), evaluated on
  ``sub × sub`` sub-pixels; ``r_p`` (e.g. r50, r80, r90) is where the EE curve, linearly interpolated between
  sub-pixel radii, reaches the fraction p of the PSF's total.
* **peak**: the largest pixel value (the fraction of the energy on the brightest pixel when the PSF sums to 1).
"""

from __future__ import annotations

import math

import torch

__all__ = ["centroid", "ee_curve", "ee_radius", "psf_metrics", "rms_radius"]

_MAX_SUBPIXELS = 4_000_000  # sub-pixel samples of the EE curve (caps memory for large PSFs)


def _as_psf(psf) -> torch.Tensor:
    p = torch.as_tensor(psf).detach().to(torch.float64)
    if p.ndim != 2:
        raise ValueError(f"a PSF is a 2-D array [iy, ix], got shape {tuple(p.shape)}")
    if p.numel() == 0:
        raise ValueError("the PSF is empty (no pixels)")
    if not bool(torch.isfinite(p).all()):
        raise ValueError("the PSF contains NaN or inf values")
    if float(p.min()) < 0:
        raise ValueError("the PSF has negative values (an intensity is >= 0)")
    if not float(p.sum()) > 0:
        raise ValueError("the PSF is all zeros (no light reaches the sensor)")
    return p


def _coords(p: torch.Tensor, pitch: float):
    ny, nx = p.shape
    x = (torch.arange(nx, dtype=torch.float64, device=p.device) - nx // 2) * pitch
    y = (torch.arange(ny, dtype=torch.float64, device=p.device) - ny // 2) * pitch
    return x, y


def centroid(psf, pitch: float = 1.0) -> tuple[float, float]:
    """(x, y) energy centroid relative to the centre of pixel ``[ny//2, nx//2]`` (unit of ``pitch``)."""
    p = _as_psf(psf)
    x, y = _coords(p, pitch)
    total = p.sum()
    return float((p.sum(0) * x).sum() / total), float((p.sum(1) * y).sum() / total)


def rms_radius(psf, pitch: float = 1.0) -> float:
    """RMS radius about the centroid (unit of ``pitch``), over pixel centres (see the module docstring)."""
    p = _as_psf(psf)
    x, y = _coords(p, pitch)
    total = p.sum()
    cx, cy = centroid(p, pitch)
    var = ((p.sum(0) * (x - cx) ** 2).sum() + (p.sum(1) * (y - cy) ** 2).sum()) / total
    return float(torch.sqrt(var))


def ee_curve(psf, pitch: float = 1.0, center=None, sub: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The encircled-energy curve ``(r, EE)`` about ``center`` (default: the centroid), EE normalised to 1.

    Each pixel's energy is spread uniformly over ``sub × sub`` sub-pixels (default: as many as fit
    :data:`_MAX_SUBPIXELS`, at most 8); ``r`` are the sorted sub-pixel radii and ``EE`` the energy within
    each, counting every sub-pixel half at its own radius (so linear interpolation is centred)."""
    p = _as_psf(psf)
    ny, nx = p.shape
    if sub is None:
        sub = int(max(1, min(8, math.floor(math.sqrt(_MAX_SUBPIXELS / (ny * nx))))))
    cx, cy = centroid(p, pitch) if center is None else (float(center[0]), float(center[1]))
    x, y = _coords(p, pitch)
    off = ((torch.arange(sub, dtype=torch.float64, device=p.device) + 0.5) / sub - 0.5) * pitch
    xs = (x[:, None] + off[None, :]).reshape(-1) - cx  # (nx·sub,)
    ys = (y[:, None] + off[None, :]).reshape(-1) - cy
    r = torch.sqrt(ys[:, None] ** 2 + xs[None, :] ** 2).reshape(-1)
    w = (p / (sub * sub)).repeat_interleave(sub, 0).repeat_interleave(sub, 1).reshape(-1)
    r, order = torch.sort(r)
    w = w[order]
    ee = (torch.cumsum(w, 0) - 0.5 * w) / w.sum()
    return r, ee


def ee_radius(psf, pitch: float = 1.0, fraction=0.8, center=None) -> float | list[float]:
    """Radius (unit of ``pitch``) about the centroid that encircles ``fraction`` of the energy (one value or a
    list of them); the EE curve of :func:`ee_curve` is interpolated linearly between sub-pixel radii."""
    r, ee = ee_curve(psf, pitch, center)
    fr = [fraction] if isinstance(fraction, (int, float)) else list(fraction)
    out = []
    for f in fr:
        if not 0 < f < 1:
            raise ValueError(f"an encircled-energy fraction lies in (0, 1), got {f!r}")
        i = int(torch.searchsorted(ee, torch.tensor(float(f), dtype=torch.float64, device=ee.device)))
        if i == 0:
            out.append(float(r[0]))
        elif i >= ee.numel():
            out.append(float(r[-1]))
        else:
            e0, e1 = float(ee[i - 1]), float(ee[i])
            t = 0.0 if e1 == e0 else (f - e0) / (e1 - e0)
            out.append(float(r[i - 1] + t * (r[i] - r[i - 1])))
    return out[0] if isinstance(fraction, (int, float)) else out


def psf_metrics(psf, pitch: float = 1.0, fractions=(0.5, 0.8, 0.9)) -> dict:
    """Figures of merit of a pixel-integrated PSF ``[iy, ix]`` (see the module docstring).

    Returns a dict, lengths in the unit of ``pitch``:
    ``centroid`` (x, y) relative to the centre of pixel ``[ny//2, nx//2]``, ``centroid_distance``,
    ``rms_radius`` (about the centroid), ``r50`` / ``r80`` / ``r90`` (one ``r{100·p}`` per fraction, about
    the centroid), ``peak`` (largest pixel value), ``total`` (sum of the PSF), ``peak_pixel`` [iy, ix].
    """
    p = _as_psf(psf)
    if not (isinstance(pitch, (int, float)) and math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"the PSF pixel pitch must be > 0, got {pitch!r}")
    cx, cy = centroid(p, pitch)
    radii = ee_radius(p, pitch, list(fractions), center=(cx, cy))
    k = int(torch.argmax(p))
    out = {
        "centroid": [cx, cy],
        "centroid_distance": math.hypot(cx, cy),
        "rms_radius": rms_radius(p, pitch),
    }
    for f, r in zip(fractions, radii):
        out[f"r{round(100 * f):d}"] = r
    out.update(peak=float(p.max()), total=float(p.sum()), peak_pixel=[k // p.shape[1], k % p.shape[1]])
    return out
