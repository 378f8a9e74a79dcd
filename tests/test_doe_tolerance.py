"""Fabrication tolerance (raywave.doe.tolerance) against results it does not compute itself: the Fourier series of
staircase and binary gratings in closed form, the detuned-wavelength formula, the exact piecewise-constant
Fourier series vs an FFT and vs the general overlap, whole-period invariance, the DOE's own fabricated phase,
seeded statistics, and the PSF peak against the first-order efficiency."""

import math

import numpy as np
import pytest
import torch

from raywave.doe import BlankDOE, GratingDOE, PixelDOE, detuning, staircase_efficiency
from raywave.doe.tolerance import (FabricationErrors, PerturbedDOE, blazed_grating_levels, design_maps,
                                   doe_efficiency, grating_efficiency, grating_efficiency_fft, level_height,
                                   sample_errors, summary_stats, tolerance_monte_carlo, transmittance)


def ramp_doe(L=16, period=16, ny=4, periods=4, lam=0.55):
    """A PixelDOE holding a linear ramp of ``period`` pixels, ``periods`` whole periods wide, offset so that its
    levels are those of :func:`blazed_grating_levels` (pixel i at level floor(iL/period), no rounding ties)."""
    i = np.arange(period * periods)
    ph = 2 * np.pi * (i + 0.5 - period / (2 * L)) / period
    return PixelDOE(np.tile(ph, (ny, 1)), 1e-3, design_wavelength=lam, trainable=False)


def closed_form_common(L, eps, m=1):
    """η_m of an L-level staircase whose steps are all (1 + ε) too deep, derived directly: the phase of step ℓ is
    2πℓ(1+ε)/L, c_m = sinc(m/L) (1/L) Σ_ℓ exp(i2πℓ(1+ε−m)/L)."""
    d = 1 + eps - m
    geo = 1.0 if abs(d) < 1e-15 else (math.sin(math.pi * d) / (L * math.sin(math.pi * d / L))) ** 2
    return np.sinc(m / L) ** 2 * geo


RANDOM = FabricationErrors(np.array([0.012, -0.02, 0.031, -0.004]),
                           np.array([[0.0, 0.0], [0.23, 0.1], [-0.51, -0.07], [0.13, 0.3]]))


# ------------------------------------------------------------------ nominal element
@pytest.mark.parametrize("L", [2, 4, 8, 16])
def test_nominal_staircase_efficiency_is_sinc_squared(L):
    per = blazed_grating_levels(L, 2 * L)
    orders = (1, 0, 2, 1 - L, 1 + L)
    want = [np.sinc(m / L) ** 2 if (m - 1) % L == 0 else 0.0 for m in orders]  # only m ≡ 1 (mod L) survive
    for eta in (grating_efficiency(per, L, orders=orders), grating_efficiency_fft(per, L, orders=orders, oversample=3)):
        assert eta == pytest.approx(want, abs=1e-12)
    doe = ramp_doe(L, period=2 * L)    # 2 pixels per level: the design phase changes by π/L per pixel
    eta, rel = doe_efficiency(PerturbedDOE(doe, L), 0.55, orders=(1, 0), design=design_maps(doe))
    assert eta[0] == pytest.approx([np.sinc(1 / L) ** 2, 0.0], abs=1e-12)
    assert rel[0] == pytest.approx(1.0, abs=1e-14)


def test_overlap_efficiency_of_a_grating_doe_equals_the_grating_efficiency():
    """The overlap with the design wave exp(i m φ_u) of a linear grating is its order-m efficiency: a GratingDOE
    (not whole periods wide) at λ0, sinc²(1/L); whole periods at other wavelengths, the detuned formula η_m(α)."""
    doe = GratingDOE(16e-3, (3, 65), 1e-3, design_wavelength=0.55)   # pixel centres on whole µm: exact levels
    eta, _ = doe_efficiency(PerturbedDOE(doe, 16), 0.55, orders=(1, -15), design=design_maps(doe))
    assert eta[0] == pytest.approx([np.sinc(1 / 16) ** 2, np.sinc(15 / 16) ** 2], abs=1e-12)
    doe = ramp_doe(16, 32, ny=2, periods=2)
    wls = [0.45, 0.55, 0.65]
    eta, _ = doe_efficiency(PerturbedDOE(doe, 16), wls, orders=(1, 0, 2), design=design_maps(doe))
    for i, w in enumerate(wls):
        a = detuning("FUSED_SILICA", w, 0.55)
        assert eta[i] == pytest.approx([staircase_efficiency(m, 16, a) for m in (1, 0, 2)], abs=1e-12)


def test_zero_errors_reproduce_the_doe_fabricated_in_its_material():
    """PerturbedDOE without errors is DOE.fabricate(L, material): the same exp(iφ) at λ0 and at another
    wavelength (the DOE's own dispersion), on the DOE grid and on an oversampled one."""
    rng = np.random.default_rng(1)
    ph = np.cumsum(np.cumsum(rng.normal(0, 0.3, (12, 14)), 0), 1)
    doe = PixelDOE(ph, 2e-3, design_wavelength=0.55, trainable=False)
    fab = PixelDOE(ph, 2e-3, design_wavelength=0.55, trainable=False, material="FUSED_SILICA").fabricate(8)
    pd = PerturbedDOE(doe, 8)
    for w in (0.55, 0.48):
        for q in (1, 3):
            t = pd.transmittance(w, oversample=q)
            ref = torch.polar(torch.ones_like(t.real), fab.phase(w, oversample=q).detach())
            assert float((t - ref).abs().max()) < 1e-12
    assert torch.equal(level_height(pd.masks, pd.errors), pd.level_map.to(torch.float64))


# ------------------------------------------------------------------ etch-depth errors
@pytest.mark.parametrize("L,eps", [(16, 0.05), (16, -0.1), (4, 0.2), (8, 0.02)])
def test_common_depth_error_equals_the_detuned_formula_and_the_closed_form(L, eps):
    per = blazed_grating_levels(L)
    k = int(math.log2(L))
    e = FabricationErrors.common_depth(k, eps)
    eta = grating_efficiency(per, L, e, orders=(1, 0))
    assert eta[0] == pytest.approx(staircase_efficiency(1, L, 1 + eps), abs=1e-12)
    assert eta[0] == pytest.approx(closed_form_common(L, eps), abs=1e-12)
    assert eta[1] == pytest.approx(closed_form_common(L, eps, 0), abs=1e-12)
    # a depth error and a wavelength detuning α multiply: α(1 + ε)
    a = detuning("FUSED_SILICA", 0.5, 0.55)
    assert grating_efficiency(per, L, e, alpha=a)[0] == pytest.approx(staircase_efficiency(1, L, a * (1 + eps)),
                                                                      abs=1e-12)


@pytest.mark.parametrize("eps", [0.0, 0.1, -0.15, 0.3])
def test_binary_grating_depth_error(eps):
    """L = 2, 50 % duty: phase depth φ = π(1+ε), η±1 = (2/π)² sin²(φ/2), η0 = cos²(φ/2)."""
    per = blazed_grating_levels(2, 8)
    e = FabricationErrors(np.array([eps]), np.zeros((1, 2)))
    phi = math.pi * (1 + eps)
    eta = grating_efficiency(per, 2, e, orders=(1, -1, 0))
    assert eta == pytest.approx([(2 / math.pi) ** 2 * math.sin(phi / 2) ** 2] * 2 + [math.cos(phi / 2) ** 2],
                                abs=1e-12)
    assert grating_efficiency_fft(per, 2, e, orders=(1, -1, 0), oversample=2) == pytest.approx(eta, abs=1e-12)


@pytest.mark.parametrize("x", [2.0, 5.0])
def test_mean_loss_of_independent_depth_errors(x):
    """Independent step errors ε_j ~ N(0, σ²), σ = x/2 %: the phase error of level ℓ is Σ_j b_j(ℓ) (2π/2^j) ε_j with
    bits b_j equally often 0 and 1, so its variance over the levels is Σ_j (2π/2^j)² ε_j²/4 and, to second
    order, E[η₁] = η₁⁰ (1 − π²σ² (1 − 4^−k)/3)."""
    per = blazed_grating_levels(16)
    r = tolerance_monte_carlo(per, 16, x, 0.0, 3000, seed=11)
    sigma = x / 200
    want = np.sinc(1 / 16) ** 2 * (1 - math.pi ** 2 * sigma ** 2 * (1 - 4.0 ** -4) / 3)
    loss, want_loss = r.nominal_efficiency[0, 0] - r.efficiency[:, 0, 0].mean(), r.nominal_efficiency[0, 0] - want
    assert loss == pytest.approx(want_loss, rel=0.08)   # Monte Carlo noise (3000 samples) and 4th-order terms


# ------------------------------------------------------------------ misalignment
def test_misalignment_by_whole_periods_changes_nothing():
    L, P = 16, 32
    per = blazed_grating_levels(L, P)
    base = grating_efficiency(per, L, orders=(1, 0, 2))
    e = FabricationErrors(np.zeros(4), np.array([[0, 0], [P, 0.0], [-2 * P, 0.0], [3 * P, 0.0]]))
    assert grating_efficiency(per, L, e, orders=(1, 0, 2)) == pytest.approx(base, abs=1e-13)
    doe = ramp_doe(L, P, ny=3, periods=2)
    pd = PerturbedDOE(doe, L, e, periodic=True)
    eta, rel = doe_efficiency(pd, 0.55, orders=(1, 0, 2), design=design_maps(doe))
    assert eta[0] == pytest.approx(base, abs=1e-12) and rel[0] == pytest.approx(1.0, abs=1e-12)


def test_whole_pixel_misalignment_equals_the_permuted_staircase():
    """Shifting the finest mask (1-pixel lines in a 16-pixel period) by one pixel swaps levels 2i and 2i+1: the
    period becomes 1, 0, 3, 2, ..., whose efficiency raywave.doe.period_efficiency gives (× the pixel sinc²)."""
    from raywave.doe import period_efficiency

    per = blazed_grating_levels(16)
    e = FabricationErrors(np.zeros(4), np.array([[0, 0], [0, 0], [0, 0], [1.0, 0]]))
    swapped = per ^ 1
    for m in (1, 0, 2, 9):
        want = period_efficiency(2 * np.pi * swapped / 16, m) * np.sinc(m / 16) ** 2
        assert grating_efficiency(per, 16, e, orders=(m,))[0] == pytest.approx(want, abs=1e-12)


def test_grating_misalignment_three_ways_agree():
    """The exact piecewise-constant Fourier series (1-D segments) = the general DOE overlap (2-D sub-rectangles,
    periodic) for any shifts; = the FFT of the oversampled period when the shifts are whole samples (1/8 px),
    and the FFT converges to it otherwise."""
    L = 16
    per = blazed_grating_levels(L)
    exact = grating_efficiency(per, L, RANDOM, orders=(1, 0, 2, -1))
    assert exact[0] < 0.9  # a sizeable effect
    doe = ramp_doe(L, L, ny=2, periods=3)
    eta, _ = doe_efficiency(PerturbedDOE(doe, L, RANDOM, periodic=True), 0.55, orders=(1, 0, 2, -1),
                            design=design_maps(doe))
    assert eta[0] == pytest.approx(exact, abs=1e-12)
    on_grid = FabricationErrors(RANDOM.depth, np.round(RANDOM.shift * 8) / 8)
    assert grating_efficiency_fft(per, L, on_grid, orders=(1, 0, 2), oversample=8) == pytest.approx(
        grating_efficiency(per, L, on_grid, orders=(1, 0, 2)), abs=1e-12)
    err = [abs(grating_efficiency_fft(per, L, RANDOM, oversample=q)[0] - exact[0]) for q in (2, 8, 32)]
    assert err[2] < err[0] and err[2] < 2e-4


def test_subpixel_edge_transmittance_is_the_area_average():
    """One mask (L = 2) shifted by 0.3 px: the pixel that the edge crosses transmits 0.7·e^{iφa} + 0.3·e^{iφb}."""
    lv = np.array([[1, 1, 0, 0]])
    doe = PixelDOE(lv * np.pi, 1e-3, design_wavelength=0.55, trainable=False)
    e = FabricationErrors(np.array([0.0]), np.array([[0.3, 0.0]]))
    pd = PerturbedDOE(doe, 2, e)
    t = pd.transmittance(0.55)[0]
    # level 1 (unetched, φ = π) at pixels 0-1, level 0 (etched, φ = 0) at 2-3; the etched area moves 0.3 px right
    want = torch.tensor([-1, -1, 0.3 * -1 + 0.7 * 1, 1], dtype=torch.complex128)
    assert torch.allclose(t, want, atol=1e-14)
    # on a 10× grid the edge falls on a sample boundary: a clean step, |t| = 1 everywhere
    t10 = transmittance(pd.masks, e, 2, 1.0, 10)[0]
    assert torch.allclose(t10.abs(), torch.ones(40, dtype=torch.float64), atol=1e-14)
    assert torch.allclose(t10[20:23].real, torch.tensor([-1.0, -1.0, -1.0], dtype=torch.float64))
    assert torch.allclose(t10[23:].real, torch.ones(17, dtype=torch.float64))


# ------------------------------------------------------------------ statistics
def test_sample_errors_distributions_and_seed():
    a = sample_errors(4, 5.0, 0.2, 4000, seed=3)
    d = np.stack([e.depth for e in a])
    s = np.stack([e.shift for e in a])
    assert np.all(s[:, 0] == 0)                                    # mask 1 is the reference
    assert d.std() == pytest.approx(0.025, rel=0.03)               # ±5 % = ±2σ
    assert s[:, 1:].std() == pytest.approx(0.1, rel=0.03)
    b = sample_errors(4, 5.0, 0.2, 4000, seed=3, distribution="uniform")
    du = np.stack([e.depth for e in b])
    assert du.max() <= 0.05 and du.min() >= -0.05 and du.std() == pytest.approx(0.05 / math.sqrt(3), rel=0.03)
    again = sample_errors(4, 5.0, 0.2, 4000, seed=3)
    assert all(np.array_equal(x.depth, y.depth) and np.array_equal(x.shift, y.shift) for x, y in zip(a, again))
    g = torch.Generator().manual_seed(3)
    assert np.array_equal(sample_errors(4, 5.0, 0.2, 1, generator=g)[0].depth, a[0].depth)


def test_monte_carlo_is_reproducible_and_its_statistics_are_right():
    per = blazed_grating_levels(16)
    kw = dict(levels=16, depth_error=5.0, misalignment=0.1, n_samples=40, wavelengths=[0.55, 0.45], orders=(1, 0))
    r1 = tolerance_monte_carlo(per, seed=7, **kw)
    r2 = tolerance_monte_carlo(per, seed=7, **kw)
    r3 = tolerance_monte_carlo(per, seed=8, **kw)
    assert np.array_equal(r1.efficiency, r2.efficiency) and not np.array_equal(r1.efficiency, r3.efficiency)
    assert r1.efficiency.shape == (40, 2, 2)
    assert r1.nominal_efficiency[0, 0] == pytest.approx(np.sinc(1 / 16) ** 2, abs=1e-12)
    assert np.all(r1.efficiency[:, 0, 0] <= r1.nominal_efficiency[0, 0] + 1e-12)   # errors only lose light at λ0
    # every sample is the exact grating efficiency of its own errors
    e = FabricationErrors(r1.depth[5], r1.shift[5])
    assert r1.efficiency[5, 1] == pytest.approx(
        grating_efficiency(per, 16, e, detuning("FUSED_SILICA", 0.45, 0.55), (1, 0)), abs=1e-14)
    s = r1.summary()
    first = [x for x in s["efficiency"] if x["order"] == 1 and x["wavelength_um"] == 0.55][0]
    assert first["mean"] == pytest.approx(r1.efficiency[:, 0, 0].mean())
    assert first["std"] == pytest.approx(r1.efficiency[:, 0, 0].std(ddof=1))
    assert first["theory"] == pytest.approx(np.sinc(1 / 16) ** 2)
    st = summary_stats([1.0, 2.0, 3.0])
    assert st["mean"] == 2.0 and st["std"] == 1.0 and st["p50"] == 2.0


def test_undersampled_design_phase_warns():
    from raywave.doe.tolerance import ToleranceWarning

    with pytest.warns(ToleranceWarning, match="undersampled"):
        design_maps(ramp_doe(2, 2))


def test_bad_inputs_are_clear_errors():
    per = blazed_grating_levels(16)
    with pytest.raises(ValueError, match="etch-depth error"):
        tolerance_monte_carlo(per, 16, depth_error=-1)
    with pytest.raises(ValueError, match="misalignment"):
        tolerance_monte_carlo(per, 16, misalignment=float("nan"))
    with pytest.raises(ValueError, match="number of samples"):
        tolerance_monte_carlo(per, 16, n_samples=0)
    with pytest.raises(ValueError, match="power of two"):
        tolerance_monte_carlo(blazed_grating_levels(12), 12)
    with pytest.raises(ValueError, match="distribution"):
        sample_errors(4, 5, 0.1, distribution="cauchy")
    with pytest.raises(ValueError, match="4 masks"):
        grating_efficiency(per, 16, FabricationErrors.common_depth(3, 0.1))
    with pytest.raises(ValueError, match="not a small error"):
        sample_errors(4, 80, 0.1)
    with pytest.raises(ValueError, match="multiple of the number of levels"):
        blazed_grating_levels(16, 24)


# ------------------------------------------------------------------ PSF
def test_psf_peak_follows_the_first_order_efficiency():
    """A 4-level diffractive lens (f_DOE = 10 mm) after an ideal lens, sensor at the combined focus: the other
    orders are far out of focus, so the in-focus PSF peak (a fraction of the incident power) scales with η₁ for a
    common depth error; the nominal sample equals the DOE fabricated in its material."""
    from raywave.assembly.tolerance import tolerance_monte_carlo  # the PSF part sits above raywave.hybrid
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens

    lam, f_doe, n, p = 0.55, 10.0, 480, 1e-3
    lens = ideal_lens(5.0, f_number=10.0, wavelengths=(lam,), sensor_distance=1 + 1 / (1 / 4 + 1 / f_doe))
    x = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * p
    doe = PixelDOE(-math.pi * (x[None, :] ** 2 + x[:, None] ** 2) / (lam * 1e-3 * f_doe), p, design_wavelength=lam,
                   trainable=False)
    # the DOE-plane edge: the beam's edge stays inside the 0.48 mm DOE. With the exit-pupil edge its Fresnel ripples
    # reach the DOE's hard aperture, and the defocused 0th order's axial value (which interferes with the in-focus
    # peak) changes with that edge: the peak then follows η₁ to ~4 % only (0.992 / 0.835 vs 0.973 / 0.872)
    hl = HybridLens(lens, BlankDOE(n, p), 1.0, sensor_pitch=1e-3, stop_edge="doe")
    errs = [FabricationErrors.common_depth(2, e) for e in (0.0, 0.1, -0.2)]
    r = tolerance_monte_carlo(doe, 4, lens=hl, errors=errs, ks=24, rays=24, orders=(1,))
    eta_ratio = r.efficiency[:, 0, 0] / r.nominal_efficiency[0, 0]
    assert eta_ratio[1:] == pytest.approx([closed_form_common(4, e) / closed_form_common(4, 0) for e in (0.1, -0.2)],
                                          abs=0.01)  # pixelation of the zones shifts it slightly
    assert r.psf["peak_ratio"][:, 0] == pytest.approx(eta_ratio, abs=0.015)
    assert r.psf["l1"][0, 0] == 0.0 and r.psf["l1"][2, 0] > 0.05
    fab = PixelDOE(doe.phase_map.detach(), p, design_wavelength=lam, trainable=False, material="FUSED_SILICA")
    ref = hl.with_doe(fab.fabricate(4)).psf_result((0, 0), lam, ks=24, rays=24)
    ref_abs = ref.psf[0, 0].detach() * (1 - float(ref.energy_outside[0, 0].detach()))
    assert np.abs(r.nominal_psf[0] - ref_abs.numpy()).max() < 1e-12
    assert r.worst_sample == 2


def test_subpixel_misalignment_psf_converges_on_the_coarse_grid():
    """Masks shifted by half pixels, PSF on the DOE grid itself (oversample 1, edges inside samples, carried by
    the exact mean transmittance) vs a 4× grid (every edge on a sample boundary: the sharp staircase): the same
    peak to < 1 % and the same PSF to ~1 % (L1), below the nominal PSF's own difference between the two grids.
    (Averaging the height instead would give a peak ~13 % too high here.)"""
    from raywave.assembly.tolerance import tolerance_monte_carlo  # the PSF part sits above raywave.hybrid
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens

    lam, f_doe, n, p = 0.55, 10.0, 240, 2e-3
    lens = ideal_lens(5.0, f_number=10.0, wavelengths=(lam,), sensor_distance=1 + 1 / (1 / 4 + 1 / f_doe))
    x = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * p
    doe = PixelDOE(-math.pi * (x[None, :] ** 2 + x[:, None] ** 2) / (lam * 1e-3 * f_doe), p, design_wavelength=lam,
                   trainable=False)
    e = FabricationErrors(np.zeros(3), np.array([[0, 0], [0.5, 0.25], [-0.5, 0.5]]))
    out = {}
    for q in (1, 4):
        hl = HybridLens(lens, BlankDOE(n, p), 1.0, sensor_pitch=1e-3, oversample=q, stop_edge="doe")  # see above
        r = tolerance_monte_carlo(doe, 8, lens=hl, errors=[FabricationErrors.nominal(3), e], ks=24, rays=24)
        out[q] = r
    r1, r4 = out[1], out[4]
    assert r1.psf["peak_ratio"][1, 0] == pytest.approx(r4.psf["peak_ratio"][1, 0], abs=0.01)
    assert r4.psf["peak_ratio"][1, 0] < 0.8                      # a sizeable effect
    worst1, worst4 = r1.worst_psf[0], r4.worst_psf[0]
    l1 = np.abs(worst1 - worst4).sum() / worst4.sum()
    l1_nominal = np.abs(r1.nominal_psf[0] - r4.nominal_psf[0]).sum() / r4.nominal_psf[0].sum()
    assert l1 < 0.012 and l1 < l1_nominal


def test_the_doe_layer_computes_no_psf():
    """The PSF change needs a hybrid lens, so it lives in the assembly layer (raywave.assembly.tolerance); the DOE
    layer's Monte Carlo says where it went instead of importing raywave.hybrid."""
    with pytest.raises(TypeError, match="raywave.assembly.tolerance"):
        tolerance_monte_carlo(PixelDOE(torch.zeros(4, 4), 1e-3), 4, lens=object(), n_samples=1)
