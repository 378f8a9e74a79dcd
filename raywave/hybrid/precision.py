"""Why the coherent trace runs in float64: the phase error that lower precision leaves at the DOE plane.

Optical paths through a lens are millimetres long, i.e. ~10⁴ wavelengths; float32 keeps ~7 significant
digits, so an optical path of 10 mm carries an error of ~1e-6 mm ≈ 2e-3 waves per operation, accumulated
over the hundreds of operations of a trace into a sizeable fraction of a wave, and it is *different for
neighbouring rays* (round-off is not smooth): the field's phase becomes discontinuous (the paper's Fig. S2).
Float64 leaves ~1e-10 waves. Propagating a field whose phase was formed in float64 is, in contrast, safe
in complex64 (the phase is then bounded to [−π, π] and the error is relative: ~1e-7).
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.lens.sources import VignettingWarning, point_source_rays

__all__ = ["ray_phase_error"]


def ray_phase_error(lens, z_doe: float, field=(0.0, 0.0), wavelength=None, n: int = 129, dtype=torch.float32,
                    depth=None) -> dict:
    """Trace the same regular pupil grid (n × n over the stop) in ``dtype`` and in float64 to the plane
    ``z = z_doe`` and compare the phase ``k·OPL`` of every ray.

    Returns a dict: ``error`` (N,) float64 phase error of ``dtype`` relative to float64 (rad), ``rms``,
    ``max`` (rad), ``xy`` (N, 2) positions (mm) on the plane, ``phase64`` (N,) the float64 phase relative to
    the chief ray (rad), ``opl64`` and ``opl`` (N,) the optical paths (mm) traced in float64 and in ``dtype``. The reference's constant is removed (only phase differences across the beam matter).
    """
    wl = lens.primary_wavelength if wavelength is None else float(wavelength)
    g = torch.linspace(-1, 1, n, dtype=torch.float64, device=lens.device)
    px, py = torch.meshgrid(g, g, indexing="xy")
    keep = (px**2 + py**2) <= 1
    px, py = px[keep], py[keep]
    out = {}
    for dt in (torch.float64, dtype):
        with warnings.catch_warnings():
            # the square pupil grid's corners are cut by the stop on purpose (``keep``/``valid`` drop them); any
            # other warning (a wavelength outside a glass's range, ...) reaches the user
            warnings.simplefilter("ignore", VignettingWarning)
            rays = point_source_rays(lens, field, wl, pupil=(px, py), aim="chief", depth=depth, dtype=dt)
            res = lens.trace(rays)
            nn_ = lens.surfaces[-1].material.n(res.wavelength).to(dt)
            at = res.propagate_to_z(torch.tensor(z_doe, dtype=dt, device=lens.device), nn_)
        out[dt] = (at.o[0, 0, :, :2].detach().to(torch.float64), at.opl[0, 0].detach(), at.valid[0, 0])
    xy, opl64, v64 = out[torch.float64]
    _, opl_lo, v_lo = out[dtype]
    k = 2 * math.pi / (wl * 1e-3)
    valid = v64 & v_lo
    # the phase each precision *forms*: k·OPL computed in that precision (then compared in float64)
    ph64 = k * opl64
    ph_lo = (torch.tensor(k, dtype=dtype, device=opl_lo.device) * opl_lo).to(torch.float64)
    err = (ph_lo - ph64)[valid]
    err = err - err.mean()
    c = int(torch.argmin((px[valid] ** 2 + py[valid] ** 2)))
    return {
        "error": err,
        "rms": float(err.pow(2).mean().sqrt()),
        "max": float(err.abs().max()),
        "xy": xy[valid],
        "phase64": (ph64[valid] - ph64[valid][c]),
        "opl64": opl64[valid],
        "opl": opl_lo[valid].to(torch.float64),
    }
