"""Cross-check against optiland (an independent ray tracer, test-only dependency).

Three classic lenses with constant indices (so that both tools see the same media): EFL, BFL, pupils to
1e-9 relative, and image-plane intercepts and optical path lengths of explicit named rays to 1e-9 mm.
Skipped cleanly when optiland is not installed.
"""

import math
import warnings

import numpy as np
import pytest
import torch

from conftest import std
from raywave.lens.lens import Lens
from raywave.rays.bundle import RayBundle
from raywave.surfaces.geometry import EvenAsphere
from raywave.surfaces.surface import Surface
from raywave.materials.base import ConstantIndex

optiland = pytest.importorskip("optiland")
warnings.filterwarnings("ignore", module="optiland")
from optiland.materials import IdealMaterial  # noqa: E402
from optiland.optic import Optic  # noqa: E402
from optiland.rays import RealRays  # noqa: E402

# (radius, thickness, n, is_stop, conic, aspheric coefficients [a4, a6, ...] or None)
COOKE = [
    (22.01359, 3.25896, 1.6204, False, 0.0, None),
    (-435.7604, 6.007551, 1.0, False, 0.0, None),
    (-22.21328, 0.9994, 1.6034, True, 0.0, None),
    (20.29192, 4.750409, 1.0, False, 0.0, None),
    (79.68364, 2.952076, 1.6204, False, 0.0, None),
    (-18.3783, 42.20778, 1.0, False, 0.0, None),
]
DOUBLE_GAUSS = [
    (54.153246, 8.746658, 1.6074, False, 0.0, None),
    (152.52192, 0.5, 1.0, False, 0.0, None),
    (35.950624, 14.0, 1.6204, False, 0.0, None),
    (math.inf, 3.776966, 1.6034, False, 0.0, None),
    (22.269925, 14.253059, 1.0, False, 0.0, None),
    (math.inf, 12.428, 1.0, True, 0.0, None),
    (-25.685033, 3.776966, 1.6034, False, 0.0, None),
    (math.inf, 10.833929, 1.6204, False, 0.0, None),
    (-36.980221, 0.5, 1.0, False, 0.0, None),
    (196.41751, 6.858175, 1.6204, False, 0.0, None),
    (-67.14755, 57.314085, 1.0, False, 0.0, None),
]
ASPHERE = [
    (math.inf, 0.1, 1.0, True, 0.0, None),
    (4.7531, 7.5, 1.5168, False, -1.2051, [5.33e-4, 1.12e-5, -3.75e-7, -7.63e-9, 1.36e-10]),
    (-15.65, 5.5, 1.0, False, 0.0, None),
]
LENSES = {"cooke": (COOKE, 10.0), "double_gauss": (DOUBLE_GAUSS, 33.3333), "asphere": (ASPHERE, 2.0)}


def _raywave(rows, epd):
    surfaces = []
    for r, t, n, stop, k, asph in rows:
        if asph is None:
            surfaces.append(std(r, t, n, stop=stop, conic=k))
        else:
            surfaces.append(Surface(EvenAsphere(1.0 / r, k, [0.0] + asph), ConstantIndex(n), t, is_stop=stop))
    return Lens(surfaces, epd=epd)


def _optiland(rows, epd):
    o = Optic()
    o.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
    for i, (r, t, n, stop, k, asph) in enumerate(rows):
        mat = "air" if n == 1.0 else IdealMaterial(n)
        if asph is None:
            o.surfaces.add(index=i + 1, radius=r, thickness=t, material=mat, is_stop=stop, conic=k)
        else:
            o.surfaces.add(index=i + 1, surface_type="even_asphere", radius=r, thickness=t, material=mat,
                          is_stop=stop, conic=k, coefficients=[0.0] + asph, tol=1e-15, max_iter=200)
            # optiland: coefficients[0] is the r² term; its default Newton tolerance (1e-10) leaves ~1e-8 mm
    o.surfaces.add(index=len(rows) + 1)
    o.set_aperture("EPD", epd)
    o.fields.set_type("angle")
    o.fields.add(y=0.0)
    o.wavelengths.add(0.5876, is_primary=True)
    return o


@pytest.mark.parametrize("name", list(LENSES))
def test_first_order_matches_optiland(name):
    rows, epd = LENSES[name]
    ours = _raywave(rows, epd).paraxial(0.5876)
    o = _optiland(rows, epd)
    total = sum(r[1] for r in rows)
    assert ours.efl == pytest.approx(float(o.paraxial.f2()), rel=1e-9)
    # optiland's F2 is the back focal point measured from the image plane.
    assert ours.bfl == pytest.approx(float(o.paraxial.F2()) + rows[-1][1], rel=1e-9)
    assert ours.ep_z == pytest.approx(float(o.paraxial.EPL()), rel=1e-9, abs=1e-12)
    assert ours.xp_z == pytest.approx(total + float(o.paraxial.XPL()), rel=1e-9)
    assert ours.xpd == pytest.approx(float(o.paraxial.XPD()), rel=1e-9)


def _named_rays(epd):
    """Named rays starting 5 mm in front of the first vertex (x, y, z, L, M): axial-ish, skew, field."""
    h = 0.35 * epd
    x = np.array([0.0, 0.3 * h, 0.0, -0.5 * h, 0.2 * h])
    y = np.array([0.0, 0.6 * h, h, 0.4 * h, -0.7 * h])
    L = np.array([0.0, 0.01, 0.0, 0.03, -0.02])
    M = np.array([0.0, 0.02, -0.05, -0.04, 0.06])
    return x, y, np.full(5, -5.0), L, M, np.sqrt(1 - L**2 - M**2)


@pytest.mark.parametrize("name", list(LENSES))
def test_named_rays_match_optiland(name):
    rows, epd = LENSES[name]
    x, y, z, L, M, N = _named_rays(epd)
    o = _optiland(rows, epd)
    rays = RealRays(x.copy(), y.copy(), z.copy(), L.copy(), M.copy(), N.copy(), np.ones(5), np.full(5, 0.5876))
    o.surfaces.trace(rays, skip=1)
    lens = _raywave(rows, epd)
    with torch.no_grad():
        out = lens.trace_to_image(RayBundle.create(np.stack([x, y, z], -1), np.stack([L, M, N], -1), 0.5876))
    assert bool(out.valid.all()), "the named rays must pass the stop"
    np.testing.assert_allclose(out.o[:, 0].numpy(), np.asarray(rays.x), atol=1e-9, rtol=0)
    np.testing.assert_allclose(out.o[:, 1].numpy(), np.asarray(rays.y), atol=1e-9, rtol=0)
    np.testing.assert_allclose(out.d[:, 0].numpy(), np.asarray(rays.L), atol=1e-12, rtol=0)
    np.testing.assert_allclose(out.d[:, 1].numpy(), np.asarray(rays.M), atol=1e-12, rtol=0)
    np.testing.assert_allclose(out.opl.numpy(), np.asarray(rays.opd), atol=1e-9, rtol=0)
