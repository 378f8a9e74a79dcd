"""The Debye reference PSF (raywave.models.debye) against the Airy pattern and its own invariants."""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import brentq
from scipy.special import j0, j1, roots_legendre

from raywave.models import debye_field, debye_psf, debye_total_power

LAM = 0.55  # µm
V_ZERO = 3.8317059702075125  # first zero of J1


def k_mm(lam=LAM):
    return 2 * math.pi / (lam * 1e-3)


def airy(na, ks, pitch, lam=LAM):
    """Paraxial Airy pattern [2 J1(v)/v]², v = k·NA·ρ, point-sampled at the pixel centres, summing to 1."""
    c = (np.arange(ks) - ks // 2) * pitch
    v = k_mm(lam) * na * np.hypot(c[None, :], c[:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(v == 0, 1.0, (2 * j1(v) / v) ** 2)
    return torch.from_numpy(a / a.sum())


def rel_l1(a, b):
    return float((a - b).abs().sum() / b.abs().sum())


def first_zero_pitch(na, lam=LAM):
    return V_ZERO / (k_mm(lam) * na)  # = 0.6098 λ/NA (mm)


@pytest.mark.parametrize("apodization", ["ideal_lens", "aplanatic", "uniform"])
def test_paraxial_limit_is_airy(apodization):
    # Measured: 3.5e-5 (ideal_lens), 7.0e-6 (aplanatic), 1.4e-5 (uniform).
    na, ks = 0.01, 65
    pitch = first_zero_pitch(na) / 8
    d = debye_psf(na, LAM, ks, pitch, oversample=1, apodization=apodization)
    assert d.psf.dtype == torch.float64 and d.psf.shape == (ks, ks)
    assert float(d.psf.sum()) == pytest.approx(1.0, abs=1e-12)
    assert rel_l1(d.psf, airy(na, ks, pitch)) < 1e-4


def test_paraxial_first_dark_ring_at_0_61_lambda_over_na():
    na = 0.01
    r0 = first_zero_pitch(na)
    # The field is real in the focal plane; its first zero is the first dark ring.
    zero = brentq(lambda r: float(debye_field(np.array([r]), na, LAM).real[0]), 0.5 * r0, 1.5 * r0, xtol=1e-15)
    assert zero == pytest.approx(r0, rel=1e-4)  # measured 1.7e-5
    assert zero / (LAM * 1e-3 / na) == pytest.approx(0.61, abs=1e-3)


def test_nonparaxial_deviation_from_airy_at_na_0125():
    # Measured L1 vs the paraxial Airy formula (v = k·sin α·ρ) at NA 0.125 / 0.25:
    #   ideal_lens 5.55e-3 / 2.30e-2, aplanatic 1.11e-3 / 4.54e-3, uniform 2.22e-3 / 9.10e-3: of order 1e-3 and
    #   growing as NA². (An apodisation a ∝ cos θ would give the Airy pattern exactly in v.)
    ks = 65
    errs = {}
    for na in (0.125, 0.25):
        pitch = first_zero_pitch(na) / 8
        for apo in ("ideal_lens", "aplanatic", "uniform"):
            psf = debye_psf(na, LAM, ks, pitch, oversample=1, apodization=apo).psf
            errs[na, apo] = rel_l1(psf, airy(na, ks, pitch))
    assert 4e-3 < errs[0.125, "ideal_lens"] < 7e-3
    assert 0.8e-3 < errs[0.125, "aplanatic"] < 1.5e-3
    assert 1.5e-3 < errs[0.125, "uniform"] < 3e-3
    for apo in ("ideal_lens", "aplanatic", "uniform"):
        assert errs[0.25, apo] / errs[0.125, apo] == pytest.approx(4.0, rel=0.1)


def test_encircled_energy_in_first_dark_ring():
    # Radial quadrature of |U|² against the Parseval total: Airy gives 1 − J0² − J1² = 0.8378 at v = 3.8317.
    na = 0.01
    x, w = roots_legendre(400)
    expected = 1 - j0(V_ZERO) ** 2
    assert expected == pytest.approx(0.838, abs=5e-4)
    for rmax, v in ((first_zero_pitch(na), V_ZERO), (20 * first_zero_pitch(na), 20 * V_ZERO)):
        rho = 0.5 * rmax * (x + 1)
        u2 = debye_field(rho, na, LAM).abs().numpy() ** 2
        ee = np.sum(0.5 * rmax * w * u2 * 2 * math.pi * rho) / debye_total_power(na)
        assert ee == pytest.approx(1 - j0(v) ** 2 - j1(v) ** 2, abs=1e-4)  # measured 2e-5


def test_crop_energy_fraction_between_inscribed_and_circumscribed_circles():
    na, ks = 0.01, 33
    pitch = first_zero_pitch(na) / 4
    d = debye_psf(na, LAM, ks, pitch, oversample=5)
    half = ks / 2 * pitch
    ee = lambda r: 1 - j0(k_mm() * na * r) ** 2 - j1(k_mm() * na * r) ** 2  # noqa: E731
    assert ee(half) < d.energy_fraction < ee(half * math.sqrt(2))  # 0.9626 < 0.9639 < 0.9735


def test_symmetry_and_centre():
    na, ks = 0.125, 31
    d = debye_psf(na, LAM, ks, 0.7e-3, oversample=3, center=(0.2, -0.1), defocus=0.01)
    p = d.psf
    tol = 1e-12 * float(p.max())
    assert float((p - p.flip(1)).abs().max()) < tol
    assert float((p - p.flip(0)).abs().max()) < tol
    assert float((p - p.T).abs().max()) < tol
    assert divmod(int(p.argmax()), ks) == (ks // 2, ks // 2)
    assert d.center == (0.2, -0.1)
    # Even crops: pixel ks//2 is the centre, the row/column 0 has no mirror partner.
    q = debye_psf(na, LAM, 16, 0.7e-3, oversample=3).psf[1:, 1:]
    assert float((q - q.flip(0)).abs().max()) < 1e-12 * float(q.max())
    assert float((q - q.flip(1).T).abs().max()) < 1e-12 * float(q.max())
    # A Debye focus is symmetric in defocus: U(ρ, −z) = conj U(ρ, z).
    m = debye_psf(na, LAM, ks, 0.7e-3, oversample=3, defocus=-0.01).psf
    assert float((m - p).abs().max()) < tol


def test_quadrature_and_pixel_integration_converge():
    na = 0.125
    for dz in (0.0, 0.05):
        a = debye_psf(na, LAM, 33, 1e-3, oversample=2, defocus=dz).psf
        b = debye_psf(na, LAM, 33, 1e-3, oversample=2, defocus=dz, n_theta=1500).psf
        assert float((a - b).abs().max()) < 1e-10 * float(b.max())
    # Midpoint rule over 3 µm pixels (first dark ring at 2.7 µm): second order in the sub-sample size.
    p = {os_: debye_psf(na, LAM, 9, 3e-3, oversample=os_).psf for os_ in (5, 15, 45)}
    e5, e15 = rel_l1(p[5], p[45]), rel_l1(p[15], p[45])  # measured 2.35e-2, 2.31e-3
    assert e15 < 3e-3 and 8 < e5 / e15 < 12


def test_bad_input():
    with pytest.raises(ValueError, match="apodization"):
        debye_psf(0.1, LAM, 8, 1e-3, apodization="gauss")
    with pytest.raises(ValueError, match="numerical aperture"):
        debye_psf(1.2, LAM, 8, 1e-3)
    with pytest.raises(ValueError):
        debye_psf(0.1, LAM, 8, 0.0)
