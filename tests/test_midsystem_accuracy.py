"""A DOE inside the lens (issue 46) against the independent wave-optics reference of tests/wave_truth_doe.py:
point source at infinity, ideal lens A (the stop), 3 mm, the DOE, 3 mm, lens B perfect for the beam it receives,
the sensor; and the reference itself against the Rayleigh–Sommerfeld integral (the non-paraxial Airy pattern).
Gradients of the mid-system PSF by finite differences."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.base import BlankDOE  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import DOEClipWarning, MidSystemLens  # noqa: E402

N, PITCH, PS, KS = 1000, 1e-3, 2e-3, 32  # the DOE: 1 mm of 1 µm pixels; 2 µm sensor pixels


def _doe(kind, f=50.0, n=N, wavelength=0.55):
    if kind == "blank":
        return BlankDOE(n, PITCH), math.inf
    doe = FresnelDOE(f, n, PITCH, wavelength=wavelength)
    if kind == "16-level":
        doe.fabricate(16)
    return doe, f


def _compare(kind, field, system=None, f=50.0, n=N, center_atol=2e-5, **edge):
    """Relative L1 of the mid-system PSF against the reference; ``system``: :class:`W.TwoLensSystem`'s fields other
    than the test system's (lengths mm, ``wavelength`` µm: the DOE designed there); ``f`` the Fresnel DOE's focal
    length (mm), ``n`` its 1 µm pixels a side (the engine's plane as wide); ``center_atol`` (mm): how near the chief
    ray's point must lie to B's paraxial image point (the reference's sensor point: the paraxial image of A's focus,
    which a strong DOE or a wide field moves by its aberrations)."""
    system = dict(system or {})
    wl = system.get("wavelength", 0.55)
    doe, f_doe = _doe(kind, f, n, wl)
    sys_ = W.TwoLensSystem(f_doe=f_doe, field=field, **system)
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=n * PITCH,
                       final_pitch=1e-3, sensor_pitch=PS, **edge)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the 16-level DOE's high orders: under-sampled, left out (tested elsewhere)
        res = ml.psf_result([field], wl, ks=KS)
    center = res.center[0, 0].detach().numpy()
    np.testing.assert_allclose(center, sys_.image()[:2], atol=center_atol)  # the chief ray meets B's image point
    phase = None if kind == "blank" else doe.phase(wl).detach().numpy()
    ref = W.sensor_psf(sys_, n, PITCH, phase, center, PS, KS)
    return W.rel_l1(res.psf[0, 0].detach().numpy(), ref)


def _diagonal(theta):
    """The field (θx, θy) deg whose direction is at ``theta`` deg from the axis along (1, 1)/√2 (tan θx = tan θy =
    tan θ / √2)."""
    t = math.degrees(math.atan(math.tan(math.radians(theta)) / math.sqrt(2)))
    return (t, t)


def test_reference_is_the_airy_pattern():
    """Lens A alone (F/12.5), its focus by the reference's angular spectrum vs the RS integral by quadrature."""
    s = W.TwoLensSystem()
    n, p = 2000, 1e-3
    x = W.coords(n, p)
    u = W.circle_coverage(x, x, s.radius_a, p) * np.exp(1j * (W._sphere(x, x, s.focus_a(), 1.0, s.k) + s.k * s.f_a))
    dx = -x[0] / p
    sh = (dx - math.floor(dx)) * p
    u = W.asm(u, p, s.f_a, s.wavelength, shift=(sh, sh))
    irr = W.pixel_integrate(np.abs(u) ** 2, p, PS)
    idx = int(math.floor(dx)) + (np.arange(KS) - KS // 2) * 2
    crop = irr[np.ix_(idx, idx)]
    ref = W.airy_reference(s, PS, KS)
    assert W.rel_l1(crop / crop.sum(), ref) < 3e-5  # measured 1.26e-5 (1.7e-4 against the unconverged quadrature)


@pytest.mark.parametrize("kind,bar", [("blank", 4e-4), ("fresnel", 1e-3)])
def test_midsystem_doe_on_axis(kind, bar):
    """Measured: blank 2.0e-4, Fresnel-lens DOE (f = 50 mm) 8.9e-4."""
    assert _compare(kind, (0.0, 0.0)) < bar


@pytest.mark.slow
@pytest.mark.parametrize("kind,field,bar", [("blank", (0.0, 1.5), 4e-4), ("fresnel", (0.0, 1.5), 1e-3),
                                            ("16-level", (0.0, 0.0), 1.6e-3), ("16-level", (0.0, 1.5), 4e-3)])
def test_midsystem_doe_matrix(kind, field, bar):
    """The default edge (the sharp cut on the engine's plane). Measured: blank 2.2e-4 at 1.5°; Fresnel 9.0e-4;
    16 levels 1.35e-3 on axis, 3.3e-3 at 1.5°: over the issue's 1e-3 (the exact edge below, and docs/ray-wave.md,
    "A DOE inside the lens", for the cause)."""
    assert _compare(kind, field) < bar


ASM = dict(stop_edge="exit_pupil", edge_step="asm")


@pytest.mark.slow
@pytest.mark.parametrize("kind,field,bar", [("fresnel", (0.0, 0.0), 4e-4), ("fresnel", (0.0, 1.5), 4e-4),
                                            ("16-level", (0.0, 0.0), 1e-3), ("16-level", (0.0, 1.5), 3.5e-3)])
def test_midsystem_doe_exact_edge(kind, field, bar):
    """The stop's edge formed at its rim's images and propagated by the angular spectrum (``stop_edge="exit_pupil",
    edge_step="asm"``), the order-1 field: measured Fresnel 2.6e-4 on axis and at 1.5° (the sharp cut on the
    engine's plane: 8.9e-4 / 9.0e-4); 16 levels with order 1 alone (the default ``min_efficiency``) 7.6e-4 on axis,
    3.1e-3 at 1.5°: the weak orders −15 / +17, left out, bring the reference's order-1 part 3.1e-3 from the
    fabricated map there (test_reference_orders_for_16_levels); with them, the test below."""
    assert _compare(kind, field, **ASM) < bar


@pytest.mark.slow
@pytest.mark.parametrize("field,bar", [((0.0, 0.0), 7e-4), ((0.0, 1.5), 8e-4)])
def test_midsystem_16_levels_with_weak_orders(field, bar):
    """The 16-level DOE with its weak orders (``min_efficiency=1e-3``: orders 1, −15, +17; −31 dropped as
    under-sampled) and the exact edge: measured 3.4e-4 on axis, 7.3e-4 at 1.5° (the issue's bar 1e-3; 5.0e-4 / 5.6e-4
    while order +17's stop edge was not formed on its step plane, before its rim images: 2026-11-30, h46d). Before
    (2026-11-29, h46) 1.10e-3 / 1.76e-3: each order's absolute phase was read at its chief ray's point, where order
    −15's edge waves converge (its Poisson spot: 4.4e-3 at 1.5° with the rim fix alone), and order −15's edge wave
    reached the crop 0.37 wave off (its stop rim imaged with aberrations; 6.3e-4 on axis with the phase fix alone,
    5.4e-4 at 1.5°, where its spot lies 117 µm from the crop's centre). tests/test_midsystem_edge_orders.py."""
    assert _compare("16-level", field, min_efficiency=1e-3, **ASM) < bar


@pytest.mark.parametrize("kind,field,system,f,n,bar", [
    ("fresnel", _diagonal(2.5), None, 50.0, N, 5e-4),
    ("fresnel", (0.0, 1.5), {"radius_a": 0.625}, 50.0, 1200, 9e-4),
    ("fresnel", (0.0, 1.5), {"f_a": 20.0, "radius_a": 0.8, "gap1": 6.0, "gap2": 6.0, "f_b": 20.0}, 50.0, 1600, 5e-4),
    ("fresnel", (0.0, 1.5), {"gap1": 1.0, "gap2": 5.0}, 50.0, N, 5e-4),
    ("fresnel", (0.0, 1.5), None, 20.0, N, 5e-4),
    ("fresnel", (0.0, 1.5), None, -30.0, N, 5e-4),
    ("fresnel", (0.0, 1.5), None, 10.0, N, 6e-4),
    ("16-level", (1.5, 0.0), None, 50.0, N, 9e-4),
    ("16-level", _diagonal(1.5), None, 50.0, N, 9e-4)],
    ids=["diag2.5deg", "F8", "fA20", "doe-near-A", "f20", "f-30", "f10", "16-level-x1.5deg", "16-level-diag1.5deg"])
def test_midsystem_exact_edge_other_systems(kind, field, system, f, n, bar):
    """Systems, fields and DOE powers away from the tests' one system (benchmarks/midsystem_sweep.py, issue 46's
    sweep): the exact edge (the 16-level DOE with ``min_efficiency=1e-3``, orders 1, −15, +17). Measured: the
    Fresnel DOE 2.8e-4 at 2.5° along (1, 1)/√2; at 1.5° F/8 6.1e-4, lens A f 20 mm (F/12.5, gaps 6 mm) 3.4e-4, the
    DOE 1 mm after A 2.6e-4, DOE focal lengths 20 / −30 / 10 mm 3.2e-4 / 2.1e-4 / 3.9e-4; the 16-level DOE at 1.5°
    along x 7.3e-4, along the diagonal 7.4e-4. The default cut on the engine's plane exceeds 1e-3 on five of these
    (1.9e-3 F/8, 2.1e-3 f 20 mm, 2.1e-3 near A, 3.1e-3 f 20 mm, 9.3e-3 f 10 mm): docs/ray-wave.md."""
    extra = {"min_efficiency": 1e-3} if kind == "16-level" else {}
    assert _compare(kind, field, system, f, n, center_atol=4e-5, **extra, **ASM) < bar  # measured ≤ 2.5e-5 mm


@pytest.mark.slow
@pytest.mark.parametrize("field,bar", [((0.0, 0.0), 8e-4), ((0.0, 1.5), 9e-4)])
def test_midsystem_16_levels_weak_orders_doe_edge(field, bar):
    """The same with ``weak_edge="doe"``: order 1 with the exact edge, the weak orders −15 / +17 with the DOE-plane
    edge as the sources of one engine call (~¼ of the cost, benchmarks/psf_midsystem.py): measured 6.7e-4 on
    axis, 7.7e-4 at 1.5° (the issue's bar 1e-3)."""
    assert _compare("16-level", field, min_efficiency=1e-3, weak_edge="doe", **ASM) < bar


@pytest.mark.slow
@pytest.mark.parametrize("field,o1,o3", [((0.0, 0.0), (7e-4, 1e-3), 3.5e-4), ((0.0, 1.5), (2.6e-3, 3.6e-3), 8e-4)])
def test_reference_orders_for_16_levels(field, o1, o3):
    """Where the 16-level DOE's error comes from, in the reference alone: it is converged (padding 400 → 800
    samples moves it by 3.8e-6 on axis, 1.6e-5 at 1.5°), and fed only order 1 of the staircase (c₁e^{iφ0}) it is
    8.6e-4 (0°) / 3.1e-3 (1.5°) from the fabricated map; with orders −15 and +17 too, 2.5e-4 / 6.3e-4. So the weak
    orders (0.44 % and 0.34 % of the light) carry that much into the crop, by their interference with order 1's
    PSF, and the fabricated DOE's PSF needs them."""
    from raywave.hybrid.midsystem import DOEPhaseSurface, order_coefficients

    doe, _ = _doe("16-level")
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    center = sys_.image()[:2]
    fab = W.sensor_psf(sys_, N, PITCH, doe.phase(0.55).detach().numpy(), center, PS, KS)
    padded = W.sensor_psf(sys_, N, PITCH, doe.phase(0.55).detach().numpy(), center, PS, KS, pad=800)
    assert W.rel_l1(padded, fab) < 5e-5
    phi0 = DOEPhaseSurface(doe).phase_map()[2:-2, 2:-2].detach().numpy()
    cs = order_coefficients(16, True, 1.0, [1, -15, 17])
    one = W.sensor_psf(sys_, N, PITCH, cs[1] * np.exp(1j * phi0), center, PS, KS)
    three = W.sensor_psf(sys_, N, PITCH, sum(c * np.exp(1j * m * phi0) for m, c in cs.items()), center, PS, KS)
    assert o1[0] < W.rel_l1(one, fab) < o1[1]
    assert W.rel_l1(three, fab) < o3


@pytest.mark.parametrize("field,seed,step", [((0.0, 0.0), 3, 1e-6), ((0.0, 1.0), 3, 1e-6),
                                             (_diagonal(1.0), 11, 1e-7)])
def test_midsystem_gradients_by_finite_differences(field, seed, step):
    """d(Σ w·PSF) with respect to the DOE (its focal length) and lens A's focal length, on axis and at 1°, against
    central differences: measured 6e-5 relative for both, both fields. (With a 0.6 mm DOE the 1° beam overruns the
    DOE's grid: that hard edge inside the lens is not differentiated, 1.3–1.5 % off; DOEClipWarning, test below.)
    At 1° along (1, 1)/√2 (weights seed 11) lens A's reads 2.1e-3 from central differences at the step 1e-6 (1e-5
    mm), 9.3e-3 at 1e-5, 1.6e-6 at 1e-7: the truncation of the differences across the cut's piecewise-linear
    coverage (a sample leaves the ramp every ~0.1 µm of edge motion, docs/ray-wave.md), not the gradient; that
    field is checked at 1e-7."""
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    doe = FresnelDOE(50.0, 800, PITCH, wavelength=0.55)
    lens = M.two_lens(sys_)
    ml = MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=0.8, final_pitch=1e-3,
                       sensor_pitch=PS)
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("error", DOEClipWarning)
            return (ml.psf([field], 0.55, ks=16)[0, 0] * w).sum()

    params = {"doe focal length": doe.focal_length, "lens A focal length": lens.surfaces[0].interaction.focal_length}
    M.assert_central_differences(loss, params, 1e-3, step)  # 1e-6: at 1e-5 the FD truncation is 2e-3 for lens A


def test_midsystem_doe_clipping_warns():
    """A DOE grid smaller than the beam it meets inside the lens is named (its edge's position is not
    differentiated)."""
    sys_ = W.TwoLensSystem(f_doe=50.0, field=(0.0, 1.0))
    ml = MidSystemLens(M.two_lens(sys_), FresnelDOE(50.0, 600, PITCH, wavelength=0.55), 0, sys_.gap1,
                       final_distance=0.01, final_size=0.6, final_pitch=1e-3, sensor_pitch=PS)
    assert 0.05 < ml.footprint((0.0, 1.0), 0.55)[1] < 0.2  # measured 9.9 % of the probe rays outside the grid
    with pytest.warns(DOEClipWarning, match="grid cuts the beam"):
        ml.source_field((0.0, 1.0), 0.55)


def test_midsystem_field_gradients_off_axis():
    """Off axis (1°), the field on the engine's plane near the sensor, differentiated with respect to lens A's
    focal length: the irradiance at two points and their phase difference against central differences (measured
    7e-7 and 3e-5 relative)."""
    sys_ = W.TwoLensSystem(f_doe=50.0, field=(0.0, 1.0))
    doe = FresnelDOE(50.0, 600, PITCH, wavelength=0.55)
    lens = M.two_lens(sys_)
    # the cut's field (stop_edge="doe"): on this clipped 0.6 mm grid the default "auto" takes the exact edge, whose
    # node mesh moves with the lens (central differences need it held: tests/test_midsystem_weak_edge.py)
    ml = MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=0.6, final_pitch=1e-3,
                       sensor_pitch=PS, stop_edge="doe")
    prm = lens.surfaces[0].interaction.focal_length
    k = 2 * math.pi / 0.55e-3

    def probe():
        fd = ml.source_field((0.0, 1.0), 0.55)[0]
        iy0, _, ix0, _ = fd.box
        x, y = fd.grid.coordinates()
        a, b = fd.carrier
        u = fd.envelope * torch.polar(torch.ones_like(fd.envelope.real), k * (a * x[None, :] + b * y[:, None]))
        v1, v2 = u[340 - iy0, 310 - ix0], u[400 - iy0, 240 - ix0]
        return v1.abs() ** 2, v2.abs() ** 2, torch.angle(v1 * v2.conj())

    vals = probe()
    grads = [torch.autograd.grad(v, prm, retain_graph=True)[0] for v in vals]
    h = 1e-5
    with torch.no_grad():
        prm += h
    plus = probe()
    with torch.no_grad():
        prm -= 2 * h
    minus = probe()
    with torch.no_grad():
        prm += h
    for g, p_, m_ in zip(grads, plus, minus):
        fd = float((p_ - m_).detach()) / (2 * h)
        assert abs(float(g) - fd) <= 1e-4 * abs(fd), (float(g), fd)
