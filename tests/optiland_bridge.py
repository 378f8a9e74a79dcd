"""Test helper: the same lens in optiland (an independent ray tracer), built from a raywave ``Lens`` of standard
surfaces at one wavelength (each medium as optiland's ``IdealMaterial`` with raywave's index at that wavelength, so
both tools see the same media). Import only after ``pytest.importorskip("optiland")``."""

import math
import warnings

import numpy as np
import torch

warnings.filterwarnings("ignore", module="optiland")
from optiland.materials import IdealMaterial  # noqa: E402
from optiland.optic import Optic  # noqa: E402


def optiland_lens(lens, wavelength: float, fields_deg, aiming: str = "robust") -> Optic:
    """optiland ``Optic`` of ``lens`` (standard / conic surfaces only, distant object, EPD aperture) at ``wavelength``
    µm, with angle fields ``fields_deg`` (along y) and full ray aiming at the stop (as raywave's ``aim="full"``)."""
    o = Optic()
    o.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
    wl = torch.tensor([wavelength], dtype=torch.float64)
    for i, s in enumerate(lens.surfaces):
        c = float(s.geometry.curvature)
        n = float(s.material.n(wl)[0])
        mat = "air" if abs(n - 1.0) < 1e-15 else IdealMaterial(n)
        o.surfaces.add(index=i + 1, radius=math.inf if c == 0 else 1.0 / c, thickness=float(s.thickness),
                       material=mat, is_stop=i == lens.stop_index, conic=float(getattr(s.geometry, "conic", 0.0)))
    o.surfaces.add(index=len(lens.surfaces) + 1)
    # raywave (as OpticStudio with ray aiming) fills the stop whose radius the paraxial EPD gives; optiland with an
    # "EPD" aperture puts pupil 1 at the real ray through the EPD rim instead (its stop hit ~2% larger on the Cooke
    # triplet): the same stop radius makes the pupil coordinates the same
    r_stop = float(lens.stop_radius())
    o.set_aperture("float_by_stop_size", 2.0 * r_stop)
    o.surfaces[lens.stop_index + 1].semi_aperture = r_stop  # the stop's size, without a clipping aperture
    o.fields.set_type("angle")
    for f in fields_deg:
        o.fields.add(y=float(f))
    o.wavelengths.add(wavelength, is_primary=True)
    o.ray_tracer.set_aiming(aiming, max_iter=50, tol=1e-12)
    return o
