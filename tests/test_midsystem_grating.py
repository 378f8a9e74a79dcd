"""A DOE inside a real lens (issue 46): a grating between two elements of the bundled Cooke triplet; the order
amplitudes of a staircase; the DOE's phase surface; placement and sampling checks."""

import math
import warnings

import numpy as np
import pytest
import torch

import raywave
from raywave.doe.base import BlankDOE, PixelDOE
from raywave.doe.efficiency import detuning, period_efficiency, staircase_efficiency
from raywave.doe.params import FresnelDOE, GratingDOE
from raywave.hybrid.coherent.record import SamplingWarning
from raywave.hybrid.midsystem import (DOEPhaseSurface, MidSystemLens, doe_orders, insert_doe, order_coefficients,
                                      sampling_report)
from raywave.lens.sources import point_source_rays

AFTER, DIST = 1, 3.0  # the air gap between the Cooke triplet's first and second elements


def test_order_coefficients_match_staircase_and_dft():
    """|c_m|² is the scalar staircase formula (and a DFT of one finely sampled period of the rounded staircase)."""
    for L, alpha in ((2, 1.0), (2, 1.237), (4, 0.9), (16, 1.0), (16, 1.237)):
        cs = order_coefficients(L, True, alpha, range(-20, 21))
        for m, c in cs.items():
            assert abs(abs(c) ** 2 - staircase_efficiency(m, L, alpha)) < 1e-12
        phi = (np.arange(L * 4096) + 0.5) * 2 * math.pi / (L * 4096)  # one period of φ0
        q = np.remainder(np.round(phi * L / (2 * math.pi)), L) * 2 * math.pi / L
        u = np.exp(1j * alpha * q)
        for m in (-1, 0, 1, 2):
            c_dft = np.mean(u * np.exp(-1j * m * phi))
            assert abs(c_dft - cs[m]) < 2e-3  # the DFT's own sampling of the steps
        assert abs(period_efficiency(alpha * q, 1) - abs(cs[1]) ** 2) < 2e-3
    kin = order_coefficients(None, True, 1.1, range(-3, 4))
    assert abs(sum(abs(c) ** 2 for c in kin.values()) - 1) < 0.02 and abs(abs(kin[1]) ** 2 - np.sinc(0.1) ** 2) < 1e-12


def test_phase_surface_unwraps_and_interpolates_exactly():
    """A wrapped pixel map reads as its smooth phase; cubic convolution is exact for a quadratic, with its gradient."""
    n, p = 64, 2e-3
    x = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * p
    a, b, c = 900.0, -40.0, 25.0
    phase = a * (x[None, :] ** 2 + 0.5 * x[:, None] ** 2) + b * x[None, :] + c * x[:, None]
    surf = DOEPhaseSurface(PixelDOE(torch.remainder(phase, 2 * math.pi), p))
    xs = (torch.tensor([0.0013, -0.02, 0.031], dtype=torch.float64),
          torch.tensor([-0.007, 0.011, 0.029], dtype=torch.float64))
    phi, gx, gy = surf(*xs, torch.tensor(0.55))
    exact = a * (xs[0] ** 2 + 0.5 * xs[1] ** 2) + b * xs[0] + c * xs[1]
    off = phase[0, 0] - torch.remainder(phase, 2 * math.pi)[0, 0]  # the unwrapped map starts at the wrapped value
    torch.testing.assert_close(phi + off, exact, atol=1e-9, rtol=0)
    torch.testing.assert_close(gx, 2 * a * xs[0] + b, atol=1e-8, rtol=0)
    torch.testing.assert_close(gy, a * xs[1] + c, atol=1e-8, rtol=0)


def test_placement_and_sampling_are_checked():
    lens = raywave.load_lens("cooke_triplet")
    doe = BlankDOE(100, 0.01)
    with pytest.raises(ValueError, match="inside the gap"):
        insert_doe(lens, AFTER, 7.0, DOEPhaseSurface(doe), doe=doe)
    with pytest.raises(ValueError, match="not a surface index"):
        insert_doe(lens, 9, 1.0, DOEPhaseSurface(doe), doe=doe)
    coarse = FresnelDOE(2.0, 200, 0.01, wavelength=0.55)  # ~8 rad per pixel at its edge
    with pytest.raises(ValueError, match="under-sampled"):
        sampling_report(coarse, doe_orders(coarse, 0.55))
    fine = FresnelDOE(200.0, 200, 0.005, wavelength=0.55)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep = sampling_report(fine, doe_orders(fine, 0.55))
    assert rep["max_step"] < 0.5 and rep["pixel_amplitude"] > 0.99
    fine.fabricate(16)
    with pytest.warns(SamplingWarning, match="not sampled, left out"):
        rep = sampling_report(fine, doe_orders(fine, 0.55, min_efficiency=1e-3))
    assert [round(s) for s, _ in rep["kept"]][0] == 1


#: the gratings: (wavelength µm, period mm, pixels a side, pitch mm, the engine's plane's distance after the last
#: vertex and size, mm). The test's 100 µm binary grating at 0.45 µm (12 µm pixels, 8.3 a period); a 50 µm one at
#: 0.65 µm (5 µm pixels, 10 a period; 2.9× the deflection), its engine's plane 2.4 mm before the sensor (at 0.88 mm,
#: the 100 µm grating's place, its orders' power reads 1.3e-3 off: docs/ray-wave.md, benchmarks/midsystem_sweep.py)
GRATINGS = {"100um": (0.45, 0.1, 1000, 0.012, 41.5, 0.8), "50um": (0.65, 0.05, 2400, 0.005, 40.0, 2.0)}


def _grating_system(wavelength, period=0.1, n=1000, pitch=0.012, final_distance=41.5, final_size=0.8):
    lens = raywave.load_lens("cooke_triplet")
    doe = GratingDOE(period, n, pitch, material="FUSED_SILICA")  # default: 100 µm period, 12 mm square
    doe.fabricate(2)  # the 0/π binary grating at 0.55 µm
    ml = MidSystemLens(lens, doe, AFTER, DIST, final_distance=final_distance, final_size=final_size,
                       final_pitch=1e-3, sensor_pitch=2e-3, min_efficiency=0.05)
    return lens, doe, ml


@pytest.mark.parametrize("grating", list(GRATINGS))
@pytest.mark.parametrize("field", [(0.0, 0.0), (3.0, 5.0)])
def test_grating_orders_follow_the_grating_equation(field, grating):
    """Orders −1, 0, +1 of a grating between two elements of the Cooke triplet, just after the grating (before the
    next surface): n sin θ2 − n sin θ1 = mλ/Λ along the grating vector, the other component unchanged (measured
    ≤ 4e-16 rad for 100 µm at 0.45 µm, ≤ 2.3e-15 rad for 50 µm at 0.65 µm)."""
    wl, period, *grid = GRATINGS[grating]
    lens, doe, ml = _grating_system(wl, period, *grid)
    orders = ml.orders(wl)
    assert sorted(round(s) for s, _ in orders) == [-1, 0, 1]
    lam_mm = wl * 1e-3
    for scale, _ in orders:
        lm = insert_doe(lens, AFTER, DIST, DOEPhaseSurface(doe, scale), 1.0, doe)
        rays = point_source_rays(lm, torch.tensor([field], dtype=torch.float64), [wl], pupil=(
            torch.tensor([0.0, 0.5, -0.3, 0.0]), torch.tensor([0.0, 0.2, 0.6, -0.8])), aim="full")
        before = lm.trace(rays, stop=AFTER + 1)
        after = lm.trace(rays, stop=AFTER + 2)
        assert bool(after.valid.all())
        n = float(lm.surfaces[AFTER].material.n(torch.tensor(wl, dtype=torch.float64)))
        d1, d2 = before.d[0, 0], after.d[0, 0]
        theta1 = torch.asin(d1[:, 0])
        theta2 = torch.asin(d2[:, 0])
        expected = torch.asin((n * torch.sin(theta1) + scale * lam_mm / period) / n)
        assert float((theta2 - expected).abs().max().detach()) < 1e-9
        assert float((d2[:, 1] - d1[:, 1]).abs().max().detach()) < 1e-12


@pytest.mark.parametrize("grating", list(GRATINGS))
def test_grating_order_efficiencies_through_the_lens(grating):
    """The power each order brings to the plane near the sensor, over a blank DOE's, is the staircase formula
    (binary gratings, detuned: orders 0 and ±1; measured 7e-5 for 100 µm at 0.45 µm, 2.7e-5 for 50 µm at 0.65
    µm)."""
    wl, period, n, pitch, dist, size = GRATINGS[grating]
    lens, doe, ml = _grating_system(wl, period, n, pitch, dist, size)
    alpha = detuning("FUSED_SILICA", wl, 0.55)
    # the blank's field through the orders' edge: the cut on the engine's plane (order_lens's), not the default
    # "auto", which takes the exit-pupil edge on the triplet (docs/ray-wave.md: the efficiencies near the focus)
    blank = MidSystemLens(lens, BlankDOE(n, pitch), AFTER, DIST, dist, size, 1e-3, sensor_pitch=2e-3, stop_edge="doe")
    fd_b = blank.source_field((0.0, 0.0), wl)[0]
    p_blank = float((fd_b.envelope.abs() ** 2).sum())
    for scale, c in ml.orders(wl):
        hl = ml.order_lens(scale, False)
        fd = hl.doe_fields([(0.0, 0.0)], [wl])[0][0]
        eta = abs(c) ** 2 * float((fd.envelope.abs() ** 2).sum()) / p_blank
        assert abs(eta - staircase_efficiency(int(round(scale)), 2, alpha)) < 1e-3, (scale, eta)


def test_continuous_doe_disperses_per_ray():
    """A continuous DOE is one order whose phase scales with α(λ) of its dispersion model, evaluated at every
    ray's wavelength (a tensor)."""
    lens = raywave.load_lens("cooke_triplet")
    wl = torch.tensor([0.45, 0.55, 0.65], dtype=torch.float64)
    for kw, expect in (({}, torch.ones(3, dtype=torch.float64)), ({"dispersion": "air"}, 0.55 / wl),
                       ({"material": "FUSED_SILICA"}, None)):
        doe = FresnelDOE(100.0, 200, 0.05, **kw)
        ml = MidSystemLens(lens, doe, AFTER, DIST, 41.5, 0.8, 1e-3)
        got = torch.as_tensor(ml._dispersion_scale(wl), dtype=torch.float64) * torch.ones(3, dtype=torch.float64)
        if expect is None:
            expect = torch.stack([torch.as_tensor(doe.dispersion_ratio(float(w)), dtype=torch.float64) for w in wl])
        torch.testing.assert_close(got, expect, rtol=1e-14, atol=0)
        assert doe_orders(doe, 0.45) == [(pytest.approx(float(expect[0])), 1.0 + 0j)]
