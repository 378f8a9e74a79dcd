"""The exit-pupil (Huygens) reference PSF (raywave.models.exit_pupil) against the Debye focus and symmetry."""

import math
import warnings

import pytest
import torch

from raywave.lens import analysis
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.lens.lens import Lens
from raywave.lens.sources import marginal_rays
from raywave.materials import Air
from raywave.models import debye_psf, huygens_psf
from raywave.surfaces.aperture import CircularAperture
from raywave.surfaces.geometry import Plane
from raywave.surfaces.interaction import IdealLens
from raywave.surfaces.surface import Surface

LAM = 0.55
F, R = 10.0, 1.25  # F/4
NA = math.sin(math.atan(R / F))
KS, PITCH, OS = 21, 1.5e-3, 3  # first dark ring at 2.7 µm


def ideal_lens(f=F, r=R):
    surf = Surface(Plane(), Air(), thickness=f, aperture=CircularAperture(r), interaction=IdealLens(f), is_stop=True)
    return Lens([surf], wavelengths=(LAM,), primary=0)


def rel_l1(a, b):
    return float((a - b).abs().sum() / b.abs().sum())


@pytest.fixture(scope="module")
def debye_ref():
    return debye_psf(NA, LAM, KS, PITCH, oversample=OS, apodization="ideal_lens")


def test_ideal_lens_on_axis_matches_debye(debye_ref):
    # Measured L1 to the Debye PSF: 7.8e-4 (n_pupil 96), 4.2e-4 (128); ~ n_pupil^-2 (anti-aliased stop edge).
    # Energy fraction in the 31.5 µm crop: 0.97355 (Huygens, n_pupil 128) vs 0.97384 (Debye).
    lens = ideal_lens()
    res = {n: huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil=n, oversample=OS) for n in (96, 128)}
    h = res[128]
    assert h.psf.shape == (KS, KS) and h.psf.dtype == torch.float64
    assert float(h.psf.sum()) == pytest.approx(1.0, abs=1e-12)
    assert h.center == pytest.approx((0.0, 0.0), abs=1e-12)
    assert h.sensor_z == pytest.approx(F) and h.sphere_radius == pytest.approx(F)
    e96, e128 = rel_l1(res[96].psf, debye_ref.psf), rel_l1(h.psf, debye_ref.psf)
    print(f"ideal lens on axis: L1 to Debye {e96:.2e} (n_pupil 96), {e128:.2e} (128)")
    assert e128 < 1e-3
    assert 1.4 < e96 / e128 < 2.2  # second-order convergence in the pupil sampling
    assert h.energy_fraction == pytest.approx(debye_ref.energy_fraction, abs=1e-3)


def test_auto_n_pupil_converges_and_its_error_estimate_holds(debye_ref):
    """``n_pupil="auto"`` (issue 47), with the square grid (``quadrature="grid"``): levels ×1.5 from the wavefront's
    own need until the 1/n² estimate of the finest level's error is below ``tol``, then the Richardson extrapolation
    of the last two. Against the Debye focus (same midpoint pixel rule): the returned PSF is within its own estimate,
    and closer than the finest level alone. Measured (tol 2e-4): levels 128 / 192, estimate 1.85e-4, the
    extrapolation 1.5e-5 from Debye (the finest level 1.9e-4); with tol 1e-4: 128 / 192 / 288, 8.5e-5, 1.1e-5
    (8.8e-5)."""
    lens = ideal_lens()
    h = huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil="auto", oversample=OS, tol=2e-4,
                    quadrature="grid")
    finest = huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil=h.n_pupil, oversample=OS)
    err, err_finest = rel_l1(h.psf, debye_ref.psf), rel_l1(finest.psf, debye_ref.psf)
    print(f"auto: levels {h.levels}, estimate {h.error_estimate:.2e}, error {err:.2e} (finest level {err_finest:.2e})")
    assert [n for n, _ in h.levels][0] >= 128 and h.n_pupil == h.levels[-1][0]
    assert h.error_estimate <= 2e-4
    assert err <= h.error_estimate and err < 0.5 * err_finest
    assert err_finest <= 2 * h.error_estimate  # the estimate is the finest level's error, to a factor
    assert float(h.psf.sum()) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="n_pupil"):
        huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil="fine")
    with pytest.raises(ValueError, match="quadrature"):
        huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil=64, quadrature="hex")


def test_polar_quadrature_converges_spectrally_to_debye(debye_ref):
    """``quadrature="polar"`` (the default of ``n_pupil="auto"``, issue 47): Gauss–Legendre rings × the trapezoid
    rule in azimuth, the stop's edge exactly the outer ring. Its levels agree to ~1e-11 once the wavefront is
    resolved, where the square grid's cells converge as 1/n² (1.07e-3 from Debye at 64 cells a side). Measured:
    levels 64 / 80, estimate 2.6e-11, 1.6e-6 from the Debye focus (the Debye approximation's own error at this
    Fresnel number, with the same midpoint pixel rule)."""
    lens = ideal_lens()
    h = huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil="auto", oversample=OS, tol=2e-4)
    grid = huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil=h.n_pupil, oversample=OS)
    err, err_grid = rel_l1(h.psf, debye_ref.psf), rel_l1(grid.psf, debye_ref.psf)
    print(f"polar auto: levels {h.levels}, estimate {h.error_estimate:.2e}, error {err:.2e} (grid {err_grid:.2e})")
    assert len(h.levels) >= 2 and h.error_estimate < 1e-8
    assert err < 1e-5 and err < 0.05 * err_grid
    assert h.energy_fraction == pytest.approx(debye_ref.energy_fraction, abs=1e-4)


def test_polar_nodes_integrate_the_disc():
    """The polar nodes' weights integrate the unit disc's polynomials exactly (area π, ∫ρ⁴ = π/3, ∫x²y² = π/24),
    and the square rule the square's."""
    from raywave.models.exit_pupil import polar_nodes

    px, py, w = polar_nodes(40)
    assert float(w.sum()) == pytest.approx(math.pi, rel=1e-13)
    assert float((w * (px**2 + py**2) ** 2).sum()) == pytest.approx(math.pi / 3, rel=1e-13)
    assert float((w * px**2 * py**2).sum()) == pytest.approx(math.pi / 24, rel=1e-13)
    assert float(torch.hypot(px, py).max()) < 1.0
    sx, sy, sw = polar_nodes(10, square=True)
    assert float(sw.sum()) == pytest.approx(4.0, rel=1e-13)
    assert float((sw * sx**4 * sy**2).sum()) == pytest.approx(4 / 15, rel=1e-13)


def test_matrix_product_sum_equals_the_direct_sum():
    """raywave.models.huygens_sum (the sum as matrix products on tiles of the sensor grid, the distance split into
    separable parts and a mixed series) against the point-by-point sum: F/1.4-like cone (sin θ ≤ 0.34), R 8 mm,
    a 90 µm crop off the sphere's centre. Measured 9e-7 of the largest |U|."""
    from raywave.models.exit_pupil import _huygens_sum
    from raywave.models.huygens_sum import huygens_sum_grid

    g = torch.Generator().manual_seed(0)
    n, radius, k0 = 3000, 8.0, 2 * math.pi / 0.55e-3
    th = torch.rand(n, generator=g, dtype=torch.float64) * 0.35
    ph = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    q = radius * torch.stack([th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()], -1)
    opl, amp = torch.sin(5 * th) * 3e-3, torch.rand(n, generator=g, dtype=torch.float64)
    xs = torch.linspace(-0.04, 0.05, 60, dtype=torch.float64)
    ys = torch.linspace(-0.045, 0.05, 50, dtype=torch.float64)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    direct = _huygens_sum(torch.stack([gx.reshape(-1), gy.reshape(-1)], -1), q, opl, amp, radius, k0, 1.0, False)
    tiled = huygens_sum_grid(xs, ys, q, opl, amp, radius, k0, 1.0)
    assert tiled.shape == (50, 60)
    err = float((tiled.reshape(-1) - direct).abs().max() / direct.abs().max())
    print(f"matrix-product sum vs direct: {err:.2e}")
    assert err < 1e-5


def test_ideal_lens_defocus_matches_debye():
    # Measured L1 3.2e-3 (n_pupil 128): the Debye approximation itself is good to ~1/Fresnel number (1/284).
    lens = ideal_lens()
    dz = 0.02  # 0.6 λ/NA² ≈ 0.3 waves of defocus
    h = huygens_psf(lens, (0.0, 0.0), LAM, ks=KS, pitch=PITCH, n_pupil=96, oversample=OS, sensor_z=F + dz)
    d = debye_psf(NA, LAM, KS, PITCH, oversample=OS, defocus=dz)
    d0 = debye_psf(NA, LAM, KS, PITCH, oversample=OS)
    assert h.sensor_z == pytest.approx(F + dz)
    assert rel_l1(h.psf, d.psf) < 5e-3
    assert rel_l1(h.psf, d0.psf) > 0.05


def test_ideal_lens_off_axis_is_centred_on_the_chief_ray(debye_ref):
    # Measured: centroid offset 3e-5 px; L1 to the on-axis Debye shape 1.5e-2 (the oblique cone on a flat
    # sensor: NA and scale change by ~cos 5°, i.e. ~0.4 % per axis).
    lens = ideal_lens()
    h = huygens_psf(lens, (0.0, 5.0), LAM, ks=KS, pitch=PITCH, n_pupil=96, oversample=OS)
    y_chief = F * math.tan(math.radians(5.0))  # the ideal lens images the chief ray at f·tan θ
    assert h.center == pytest.approx((0.0, y_chief), abs=1e-9)
    assert h.sphere_radius == pytest.approx(F / math.cos(math.radians(5.0)), rel=1e-9)
    p = h.psf
    c = torch.arange(KS, dtype=torch.float64) - KS // 2
    cx, cy = float((p.sum(0) * c).sum()), float((p.sum(1) * c).sum())
    assert abs(cx) < 0.05 and abs(cy) < 0.05
    assert divmod(int(p.argmax()), KS) == (KS // 2, KS // 2)
    assert float((p - p.flip(1)).abs().max()) < 1e-8 * float(p.max())  # mirror symmetric in x
    err = rel_l1(p, debye_ref.psf)
    print(f"ideal lens at 5°: centroid ({cx:.1e}, {cy:.1e}) px, L1 to on-axis Debye {err:.2e}")
    assert err < 3e-2


def test_center_argument_shifts_the_crop():
    lens = ideal_lens()
    a = huygens_psf(lens, (0.0, 0.0), LAM, ks=11, pitch=PITCH, n_pupil=48, oversample=1)
    b = huygens_psf(lens, (0.0, 0.0), LAM, ks=11, pitch=PITCH, n_pupil=48, oversample=1, center=(2 * PITCH, -PITCH))
    pa, pb = a.psf * a.energy_fraction, b.psf * b.energy_fraction  # power fractions, comparable across crops
    assert b.center == pytest.approx((2 * PITCH, -PITCH))
    # b's pixel [iy, ix] sits where a's pixel [iy - 1, ix + 2] does.
    # (to the matrix-product sum's accuracy, raywave.models.huygens_sum: its tiles differ between the two crops)
    assert torch.allclose(pb[1:, :-2], pa[:-1, 2:], rtol=1e-5, atol=1e-9 * float(pa.max()))


@pytest.fixture(scope="module")
def asphere():
    return load_lens(bundled_lens_path("asphere_hk51"))


def test_asphere_on_axis_symmetric_and_plausible_strehl(asphere):
    h = huygens_psf(asphere, (0.0, 0.0), 0.53, ks=15, n_pupil=96, oversample=OS)
    assert h.pitch == pytest.approx(0.003) and h.sensor_z == pytest.approx(float(asphere.image_z().detach()))
    assert h.center == pytest.approx((0.0, 0.0), abs=1e-12)
    p, tol = h.psf, 1e-8 * float(h.psf.max())
    assert float((p - p.flip(1)).abs().max()) < tol
    assert float((p - p.flip(0)).abs().max()) < tol
    assert float((p - p.T).abs().max()) < tol
    # Strehl: on-axis irradiance / total power against a perfect focus of the same NA (one tiny pixel).
    with torch.no_grad():
        na = float(torch.linalg.vector_norm(asphere.trace(marginal_rays(asphere, (0, 0), 0.53)).d[0, 0, 0, :2]))
        rms = float(analysis.rms_wavefront_error(asphere, (0.0, 0.0), 0.53, n=65))
    peak = huygens_psf(asphere, (0.0, 0.0), 0.53, ks=1, pitch=1e-5, n_pupil=96, oversample=1).energy_fraction
    strehl = peak / debye_psf(na, 0.53, 1, 1e-5, oversample=1).energy_fraction
    marechal = math.exp(-((2 * math.pi * rms) ** 2))
    # Measured: NA 0.1262, Strehl 0.9248 (n_pupil 64..128 agree to 2e-4), RMS WFE 0.0452 λ, Maréchal 0.9224.
    print(f"asphere_hk51 on axis at 0.53 µm: NA {na:.4f}, Strehl {strehl:.4f}, Maréchal {marechal:.4f}")
    assert 0.85 < strehl < 0.97
    assert strehl == pytest.approx(marechal, abs=0.01)


def test_vignetted_rays_contribute_nothing_and_no_nan():
    clipped = load_lens(bundled_lens_path("asphere_hk51"))
    clipped.surfaces[2].aperture = CircularAperture(0.9)  # the 7° beam spans r = 0.16 .. 1.05 mm there
    full = huygens_psf(load_lens(bundled_lens_path("asphere_hk51")), (0.0, 7.0), 0.53, ks=15, n_pupil=48,
                       oversample=1)
    h = huygens_psf(clipped, (0.0, 7.0), 0.53, ks=15, n_pupil=48, oversample=1)
    assert 0 < h.n_rays < 0.9 * full.n_rays  # 1590 of 1884
    assert bool(torch.isfinite(h.psf).all()) and float(h.psf.sum()) == pytest.approx(1.0)
    assert math.isfinite(h.energy_fraction) and h.energy_fraction > 0
    assert h.center == pytest.approx(full.center)
    assert rel_l1(h.psf, full.psf) > 0.1


def test_undersampled_pupil_warns(asphere):
    with pytest.warns(RuntimeWarning, match="under-samples"):
        huygens_psf(asphere, (0.0, 17.5), 0.53, ks=5, n_pupil=32, oversample=1)
    with pytest.warns(RuntimeWarning, match="replicas"):
        huygens_psf(ideal_lens(), (0.0, 0.0), LAM, ks=40, pitch=2e-3, n_pupil=12, oversample=1)
    # the polar nodes: 32 for the 17.5° wavefront warn, the levels of n_pupil="auto" do not (their agreement checks)
    with pytest.warns(RuntimeWarning, match="polar pupil nodes under-sample"):
        huygens_psf(asphere, (0.0, 17.5), 0.53, ks=5, n_pupil=32, oversample=1, quadrature="polar")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        h = huygens_psf(asphere, (0.0, 7.0), 0.53, ks=8, n_pupil="auto", oversample=1)
    assert h.error_estimate < 1e-4
