"""Ray fans: transverse ray aberrations along the pupil's y (tangential) and x (sagittal) diameters, and the OPD
along the same fans.

As OpticStudio's and optiland's ray fans: ``ey(py)`` is the image-plane y of the tangential fan's ray (px = 0)
and ``ex(px)`` the x of the sagittal fan's ray (py = 0), both relative to the chief ray of the *primary*
wavelength (so the other wavelengths' fans show lateral colour). Pupil coordinates normalised to the stop (fully
aimed rays, the rim rule of :mod:`raywave.rays.pupil`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from raywave.lens.analysis import field_pairs as _fields, wavefront_opd
from raywave.lens.sources import VignettingWarning, chief_ray, point_source_rays
from raywave.rays.pupil import inset_rim


@dataclass
class RayFan:
    """Ray fans of fields (F) × wavelengths (W) over ``pupil`` (P,) = linspace(-1, 1, P).

    Attributes:
        pupil: (P,) normalised pupil coordinate along the fan.
        ey: (F, W, P) mm, tangential fan (px = 0) image-plane y minus the primary chief ray's; NaN where vignetted.
        ex: (F, W, P) mm, sagittal fan (py = 0) image-plane x minus the primary chief ray's; NaN where vignetted.
        fields: (F, 2) in the lens's field type; ``wavelengths`` (W,) µm.
    """

    pupil: torch.Tensor
    ey: torch.Tensor
    ex: torch.Tensor
    fields: torch.Tensor
    wavelengths: list



def ray_fan(lens, fields=None, wavelengths=None, n: int = 21) -> RayFan:
    """Tangential and sagittal ray fans (:class:`RayFan`) of ``fields`` ((x, y) pairs or y values in the lens's field
    type; default its fields) at ``wavelengths`` µm (default the lens's), ``n`` rays per fan (odd keeps the chief
    ray on the fan). No autograd."""
    if n < 2:
        raise ValueError(f"a ray fan needs n >= 2 rays, got {n}")
    lens.require_unfolded("ray_fan")
    f = _fields(lens, fields)
    wls = list(lens.wavelengths if wavelengths is None else [float(w) for w in wavelengths])
    t = torch.linspace(-1.0, 1.0, n, dtype=torch.float64, device=lens.device)
    z = torch.zeros_like(t)
    px, py = inset_rim(torch.cat([z, t]), torch.cat([t, z]))  # tangential fan, then sagittal; the rim rule
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)  # vignetted rays: NaN in the fans
        out = lens.image_coordinates(lens.trace_to_image(point_source_rays(lens, f, wls, pupil=(px, py))))
        chief = lens.image_coordinates(lens.trace_to_image(chief_ray(lens, f, [lens.primary_wavelength])))
    ref = chief.o[:, 0, 0, :2]  # (F, 2)
    ok = out.valid & torch.isfinite(out.o).all(-1)
    nan = torch.full_like(out.o[..., 0], math.nan)
    dx = torch.where(ok, out.o[..., 0] - ref[:, None, None, 0], nan)
    dy = torch.where(ok, out.o[..., 1] - ref[:, None, None, 1], nan)
    if not bool(chief.valid[:, 0, 0].all()):  # no primary chief ray: no reference
        bad = ~chief.valid[:, 0, 0]
        dx[bad], dy[bad] = math.nan, math.nan
    return RayFan(t, dy[..., :n], dx[..., n:], f, wls)


@dataclass
class OPDFan:
    """OPD (waves) along the tangential (``w_t``, px = 0) and sagittal (``w_s``, py = 0) fans: (F, W, P), NaN where
    vignetted; ``pupil`` (P,)."""

    pupil: torch.Tensor
    w_t: torch.Tensor
    w_s: torch.Tensor
    fields: torch.Tensor
    wavelengths: list


def opd_fan(lens, fields=None, wavelengths=None, n: int = 21) -> OPDFan:
    """OPD fans (:func:`raywave.lens.analysis.wavefront_opd`: chief-ray reference sphere at the exit pupil) of
    ``fields`` at ``wavelengths`` µm, ``n`` samples per fan. No autograd."""
    f = _fields(lens, fields)
    wls = list(lens.wavelengths if wavelengths is None else [float(w) for w in wavelengths])
    t = torch.linspace(-1.0, 1.0, n, dtype=torch.float64, device=lens.device)
    z = torch.zeros_like(t)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        opd, _, _, v = wavefront_opd(lens, f, wls, pupil=inset_rim(torch.cat([z, t]), torch.cat([t, z])))
    opd = torch.where(v & torch.isfinite(opd), opd, torch.full_like(opd, math.nan))
    return OPDFan(t, opd[..., :n], opd[..., n:], f, wls)
