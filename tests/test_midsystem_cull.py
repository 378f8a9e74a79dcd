"""Leaving out the diffraction orders of a mid-system DOE that land far outside the PSF crop (issue 46,
:func:`raywave.hybrid.midsystem.cull_orders`): the far-field envelope against the Airy pattern (an independent
closed form), the bound against the change the engine shows when the orders are left out, and the orders that
land in the crop never left out."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.special import j1

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.midsystem as ms  # noqa: E402
from raywave.doe.params import FresnelDOE, GratingDOE  # noqa: E402
from raywave.hybrid.midsystem import MidSystemLens, Orders, tail_envelope  # noqa: E402

PITCH, PS, KS, WL = 1e-3, 2e-3, 32, 0.55


def _grating(field, period, tol, n=1000):
    doe = GratingDOE(period, n, PITCH)
    doe.fabricate(2)  # the 0/π binary grating: orders ±1 (40.5 %), ±3 (4.5 %), ±5 (1.6 %)
    sys_ = W.TwoLensSystem(field=field)
    return MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=n * PITCH,
                         final_pitch=PITCH, sensor_pitch=PS, orders=Orders(cull_tol=tol))


def _psf(ml, field):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ml.psf_result([field], WL, ks=KS)


def test_envelope_bounds_the_airy_pattern():
    """The Airy pattern of power P, ``P π NA²/λ² [2 J1(v)/v]²``, stays within 1.07 of :func:`tail_envelope` (1.069 at
    v = 2.17, in the central lobe; 1.012 on the first ring; the safety factor :data:`CULL_SAFETY` covers that),
    and approaches it on the rings' peaks."""
    na, lam = 0.056, WL * 1e-3
    rho = np.linspace(2e-3, 0.5, 20001)
    v = 2 * math.pi * na * rho / lam
    airy = math.pi * na ** 2 / lam ** 2 * (2 * j1(v) / v) ** 2
    env = tail_envelope(torch.tensor(rho), na, WL).numpy()
    assert (airy <= 1.07 * env).all()
    assert (airy[v > 4] <= 1.013 * env[v > 4]).all()
    assert (airy[v > 20] / env[v > 20]).max() > 0.99
    assert ms.CULL_SAFETY >= 1.07


def test_cull_off_by_default_and_with_zero():
    """``cull_tol=0`` (the default) keeps every order and records nothing."""
    assert Orders().cull_tol == 0.0
    ml = _grating((0.0, 0.0), 0.05, 0.0, n=400)
    assert _psf(ml, (0.0, 0.0)).culled == []
    with pytest.raises(ValueError, match="cull_tol"):
        Orders(cull_tol=-1e-3)
    short = MidSystemLens(ml.lens, ml.doe, 0, 3.0, final_distance=0.01, final_size=0.4, final_pitch=PITCH,
                          sensor_pitch=PS, cull_tol=0.1)  # the short keyword, as min_efficiency= / weak_edge=
    assert short.cull_tol == 0.1
    with pytest.raises(TypeError, match="cull_tol"):
        MidSystemLens(ml.lens, ml.doe, 0, 3.0, final_distance=0.01, final_size=0.4, final_pitch=PITCH,
                      orders=Orders(), cull_tol=0.1)


@pytest.mark.parametrize("field", [(0.0, 0.0), (0.0, 1.5)])
@pytest.mark.parametrize("tol", [1e-4, 0.1, 0.5])
def test_culled_psf_within_the_bound(field, tol):
    """The 50 µm grating (orders 110 µm apart on the sensor, the crop 64 µm wide, centred on order −1): the orders
    left out never include one landing in or next to the crop (−1, +1), the recorded bound is ≤ ``cull_tol``, and
    the PSF moves from the all-orders PSF by no more than the bound. At 1e-4 nothing is left out: the interference
    of order −5's tail with the kept light alone moves the PSF by 5e-4."""
    full = _psf(_grating(field, 0.05, 0.0), field).psf
    res = _psf(_grating(field, 0.05, tol), field)
    (rec,) = res.culled
    left = [s for s, _ in rec["orders"]]
    assert -1.0 not in left and 1.0 not in left
    assert rec["bound"] <= tol
    change = float(((res.psf - full).abs().sum() / full.abs().sum()).detach())
    assert change <= max(rec["bound"], 1e-15)
    if tol == 1e-4:
        assert left == [] and change == 0.0
    if tol == 0.5:
        assert set(left) >= {5.0, -5.0, 3.0}


def test_orders_in_the_crop_never_culled():
    """The 16-level Fresnel DOE with its weak orders (−15, +17: defocused, their footprints over the crop) and a
    100 µm grating (order +1 lands 55 µm from −1, the crop's centre; −3 at 55 µm too): with any tolerance (0.9), no
    order whose footprint reaches or nears the crop is left out."""
    doe = FresnelDOE(50.0, 1000, PITCH, wavelength=WL)
    doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=50.0, field=(0.0, 1.5))
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=1.0,
                       final_pitch=PITCH, sensor_pitch=PS, min_efficiency=1e-3, orders=None)
    ml.cull_tol = 0.9
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        orders = ml.source_orders((0.0, 1.5), WL, None, pms)
        assert len(orders) >= 3
        land = ml.order_landings((0.0, 1.5), WL, None, pms, orders)
        kept, rec = ml.cull((0.0, 1.5), WL, None, pms, orders, KS)
    assert all(ld is not None for ld in land)  # every order's footprint known: left in because it reaches the crop
    assert kept == orders and rec["orders"] == []
    ml = _grating((0.0, 0.0), 0.1, 0.9)
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        orders = ml.source_orders((0.0, 0.0), WL, None, pms)
        land = ml.order_landings((0.0, 0.0), WL, None, pms, orders)
        kept, rec = ml.cull((0.0, 0.0), WL, None, pms, orders, KS)
    near = [s for (s, _), ld in zip(orders, land) if abs(ld[2][0] - land[0][2][0]) < 0.07]
    assert {-1.0, 1.0} <= set(near)
    assert all(s not in [t for t, _ in rec["orders"]] for s in near)


def test_vignetted_order_not_culled():
    """An order whose probe rays an aperture cuts (here the DOE's grid, smaller than the beam) has no landing: its
    edge is not the stop's circle that the envelope bounds."""
    ml = _grating((0.0, 0.0), 0.05, 0.5, n=400)  # a 0.4 mm grid in a 0.56 mm beam
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    orders = ml.orders(WL)
    land = ml.order_landings((0.0, 0.0), WL, None, pms, orders)
    assert all(ld is None for ld in land)
    kept, rec = ml.cull((0.0, 0.0), WL, None, pms, orders, KS)
    assert kept == orders and rec["orders"] == []


def test_culled_psf_gradients_by_finite_differences():
    """With orders left out (the 50 µm grating at ``cull_tol=0.1``, a 16-pixel crop: ±1 kept), the PSF's gradient
    with respect to lens A's focal length against central differences: 5.5e-6 relative (the left-out orders carry
    no gradient; the choice does not change over the step). The grating's period is not checked here: its central
    differences are not converged with every order kept and nothing left out either (1.4e-2 / 1.6e-2 from the
    gradient at the steps 1e-6 / 1e-5, which differ from each other by 3 %)."""
    ml = _grating((0.0, 1.0), 0.05, 0.1)
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    kept = []

    def loss():
        res = _psf_ks(ml, (0.0, 1.0), 16)
        kept.append(tuple(s for s, _ in res.culled[0]["orders"]))
        return (res.psf[0, 0] * w).sum()

    M.assert_central_differences(loss, {"lens A focal length": ml.lens.surfaces[0].interaction.focal_length}, 1e-4)
    assert len(set(kept)) == 1 and len(kept[0]) >= 2 and 1.0 not in kept[0]


def _psf_ks(ml, field, ks):
    """``psf_result`` of one field (a pair) or several (a list of pairs), warnings silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ml.psf_result(field if isinstance(field, list) else [field], WL, ks=ks)


def test_crop_pitch_as_the_engine_resolves_it():
    """Without ``sensor_pitch`` the crop's pixels are the lens's sensor pixels, else the final plane's (as the
    engine's)."""
    ml = _grating((0.0, 0.0), 0.05, 0.1, n=400)
    assert ml.crop_pitch() == PS
    ml.sensor_pitch = None
    pms = [ms.DOEPhaseSurface(d).phase_map() for d in ml.does]
    hl = ml.order_lens(1.0, None, pms)
    assert ml.crop_pitch() == hl.sensor_pitch


def test_two_gratings_culled_within_the_bound():
    """Two crossed 50 µm binary gratings 1 mm apart (12 product orders of ≥ 1 %): with ``cull_tol=0.1`` the
    farthest product order is left out at both fields and the PSF moves by less than the bound (measured 7.6e-4
    against 5.8e-2)."""
    sys_ = W.TwoLensSystem(gap12=1.0, gap2=2.0)
    does = [GratingDOE(0.05, 1000, PITCH, angle=a) for a in (0.0, 90.0)]
    for d in does:
        d.fabricate(2)
    lens = M.two_lens(sys_)
    res = []
    for tol in (0.0, 0.1):
        # the cut (stop_edge="doe"): lens B is made for the axis, so at 1° the default "auto" takes the exact edge
        # for all 12 orders (~98 s here); culling does not depend on the edge
        ml = MidSystemLens(lens, does, [0, 0], [3.0, 4.0], final_distance=0.01, final_size=1.0, final_pitch=PITCH,
                           sensor_pitch=PS, orders=Orders(cull_tol=tol), stop_edge="doe")
        res.append(_psf_ks(ml, [(0.0, 0.0), (0.0, 1.0)], KS))
    assert res[0].culled == []
    for i, rec in enumerate(res[1].culled):
        assert rec["orders"] and all(abs(s[0]) + abs(s[1]) >= 4 for s, _ in rec["orders"])
        change = float((res[1].psf[i] - res[0].psf[i]).abs().sum().detach())
        assert 0 < change <= rec["bound"] <= 0.1
