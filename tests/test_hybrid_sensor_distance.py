"""The PSF is differentiable with respect to the DOE → sensor distance (the lens's last thickness: focus).

Checked against central finite differences of the whole discrete model: the windowed propagation's ``dz``
(``propagate_window``) alone, then the HybridLens PSF on and off axis (ideal lens with a small PixelDOE, the
bundled asphere, the faithful full-grid path), and the direction of the gradient against the thin-lens focus."""

import math
import warnings
import sys
from pathlib import Path

import pytest
import torch

from raywave.doe import PixelDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, ideal_lens, load_lens

sys.path.insert(0, str(Path(__file__).parent))
from window_calls import transfer as _wt, window as _pw  # noqa: E402

LAM = 0.55
F, FNUM, DIST = 5.0, 8.0, 1.0  # ideal lens f = 5 mm at F/8, DOE 1 mm behind it (0.5 mm beam on the DOE)
KS = 24


def smooth_phase(n: int, amp: float, seed: int, sigma_px: float = 20.0) -> torch.Tensor:
    """Gaussian-filtered random phase (n, n), RMS ``amp`` rad (a DOE that visibly changes the PSF)."""
    r = torch.randn(n, n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    f = torch.fft.fftfreq(n, dtype=torch.float64)
    g = torch.exp(-0.5 * (f[:, None] ** 2 + f[None, :] ** 2) * (2 * math.pi * sigma_px) ** 2)
    p = torch.fft.ifft2(torch.fft.fft2(r) * g).real
    return amp * p / p.std()


def weights(ks: int = KS, seed: int = 1) -> torch.Tensor:
    return torch.randn(ks, ks, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def thickness_fd(hl, loss, rel=1e-6):
    """(autograd, central difference) of ``loss()`` w.r.t. the lens's last thickness."""
    t = hl.lens.surfaces[-1].thickness
    hl.zero_grad()
    loss().backward()
    g = float(t.grad)
    eps = rel * float(t.detach())
    with torch.no_grad():
        t += eps
        lp = float(loss())
        t -= 2 * eps
        lm = float(loss())
        t += eps
    return g, (lp - lm) / (2 * eps)


# ------------------------------------------------------------------ _pw(dz=)
def _beam(n=200, p=1e-3, sigma=0.06, z0=2.0):
    """A Gaussian beam (σ = 60 µm, cut by the 200 µm window: edge diffraction reaches the band's roll-off)
    converging to a focus z0 mm away, as an envelope (carrier removed)."""
    x = (torch.arange(n, dtype=torch.float64) - n / 2) * p
    xx, yy = torch.meshgrid(x, x, indexing="xy")
    k = 2 * math.pi / (LAM * 1e-3)
    return torch.exp(-(xx**2 + yy**2) / (2 * sigma**2)) * torch.exp(-1j * k * (xx**2 + yy**2) / (2 * z0)), float(x[0])


@pytest.mark.parametrize("carrier", [(0.0, 0.0), (0.05, -0.03)])
def test_window_dz_matches_a_finite_difference_in_z(carrier):
    u, x0 = _beam()
    z0, p = 2.0, 1e-3
    out_origin = (-0.02 + carrier[0] * z0, -0.02 + carrier[1] * z0)
    w = weights(41, 3)

    def loss(z, dz=None):
        out = _pw(u, p, LAM, z, (x0, x0), out_origin, (41, 41), carrier=carrier, dz=dz)
        return (out.abs() ** 2 * w).sum()

    dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
    value = loss(z0, dz)
    assert float(value.detach()) == float(loss(z0))  # a zero-valued dz changes nothing
    value.backward()
    eps = 1e-6
    fd = (float(loss(z0 + eps)) - float(loss(z0 - eps))) / (2 * eps)
    assert float(dz.grad) == pytest.approx(fd, rel=1e-6)


def test_window_dz_of_the_complex_field_is_the_axial_frequency_times_2pi_i():
    """A plane wave exp(i2π(f·x + w z)) gains exactly i2πw per mm of distance (w from the true frequency)."""
    p, n, edge = 1e-3, 256, 64
    carrier = (0.04, 0.0)
    kx = 12 / (n * p)  # envelope frequency (cycles/mm): a plane wave tilted beyond the carrier
    x = torch.arange(n, dtype=torch.float64) * p
    ramp = torch.ones(n, dtype=torch.float64)  # raised-cosine edges: no edge diffraction reaches the centre
    ramp[:edge] = 0.5 - 0.5 * torch.cos(math.pi * (torch.arange(edge, dtype=torch.float64) + 0.5) / edge)
    ramp[-edge:] = ramp[:edge].flip(0)
    u = torch.exp(2j * math.pi * kx * x)[None, :] * (ramp[:, None] * ramp[None, :])
    dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
    out = _pw(u, p, LAM, 0.2, (0.0, 0.0), (124 * p, 124 * p), (8, 8), carrier=carrier, dz=dz)
    ratio_re = torch.autograd.grad(out.real[4, 4], dz, retain_graph=True)[0]
    ratio_im = torch.autograd.grad(out.imag[4, 4], dz)[0]
    d = complex(float(ratio_re), float(ratio_im)) / complex(out[4, 4].detach())
    k = 1.0 / (LAM * 1e-3)
    w = math.sqrt(k * k - (kx + k * carrier[0]) ** 2)
    assert d.imag == pytest.approx(2 * math.pi * w, rel=1e-6)  # (w without the carrier: 8e-4 off)
    assert abs(d.real) < 1e-6 * 2 * math.pi * w


def test_window_shift_derivative_includes_the_band_following_the_window():
    u, x0 = _beam()
    w = weights(41, 4)
    base = (-0.02, -0.02)

    def loss(ox, shift=None):
        out = _pw(u, 1e-3, LAM, 2.0, (x0, x0), (ox, base[1]), (41, 41), shift=shift)
        return (out.abs() ** 2 * w).sum()

    s = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    loss(base[0], s).backward()
    eps = 1e-7
    fd = (float(loss(base[0] + eps)) - float(loss(base[0] - eps))) / (2 * eps)
    assert float(s.grad[0]) == pytest.approx(fd, rel=1e-5)


def test_a_cached_two_tuple_transfer_is_rebuilt_with_its_weight_derivative():
    u, x0 = _beam(n=64, sigma=0.02)
    args = (u.shape, (21, 21), 1e-3, LAM, 1.5, (x0, x0), (-0.01, -0.01))
    t2, t3 = _wt(*args), _wt(*args, weight_derivative=True)
    assert len(t2) == 2 and len(t3) == 3 and torch.equal(t2[0], t3[0]) and t3[2].shape == (3, *t3[0].shape)
    grads = []
    for t in (t2, t3):
        dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
        out = _pw(u, 1e-3, LAM, 1.5, (x0, x0), (-0.01, -0.01), (21, 21), dz=dz, transfer=t)
        (out.abs() ** 2).sum().backward()
        grads.append(float(dz.grad))
    assert grads[0] == grads[1]


@pytest.mark.parametrize("with_weights", [True, False])
def test_the_hand_written_backward_of_the_perturbed_transfer_passes_gradcheck(with_weights):
    """At non-zero shift and dz too (the phase factor and the weight factor a ≠ 1), and for the input h."""
    from raywave.wave.propagation import _Perturbed

    g = torch.Generator().manual_seed(0)
    h = torch.randn(6, 5, dtype=torch.complex128, generator=g).requires_grad_(True)
    fx, fy = torch.fft.fftfreq(5, d=1e-3, dtype=torch.float64), torch.fft.fftfreq(6, d=1e-3, dtype=torch.float64)
    axial = (0.5, 1.2, (0.01, -0.02))  # λ µm, n, carrier: the axial frequency w is recomputed from them
    rel = torch.randn(3, 6, 5, dtype=torch.float64, generator=g) if with_weights else None
    args = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (1e-4, -2e-4, 3e-3)]
    assert torch.autograd.gradcheck(lambda h, sx, sy, dz: _Perturbed.apply(h, sx, sy, dz, fx, fy, axial, rel),
                                    (h, *args))


def test_dz_must_be_a_scalar_tensor():
    u, x0 = _beam(n=32, sigma=0.01)
    with pytest.raises(TypeError, match="dz"):
        _pw(u, 1e-3, LAM, 1.0, (x0, x0), (0.0, 0.0), (8, 8), dz=0.0)
    with pytest.raises(ValueError, match="dz must be a scalar"):
        _pw(u, 1e-3, LAM, 1.0, (x0, x0), (0.0, 0.0), (8, 8), dz=torch.zeros(2))


# ------------------------------------------------------------------ HybridLens PSF
def ideal_hybrid(sensor_distance=None, n=600):
    lens = ideal_lens(F, f_number=FNUM, wavelengths=(LAM,), sensor_distance=sensor_distance)
    return HybridLens(lens, PixelDOE(smooth_phase(n, 2.0, 0), 1e-3), DIST, sensor_pitch=1e-3)


@pytest.mark.parametrize("sensor_distance", [F, F + 0.03])
@pytest.mark.parametrize("fld", [(0.0, 0.0), (0.0, 3.0), (2.0, -1.5)])
def test_ideal_lens_psf_gradient_wrt_the_sensor_distance(sensor_distance, fld):
    hl = ideal_hybrid(sensor_distance)
    w = weights()
    g, fd = thickness_fd(hl, lambda: (hl.psf(fld, LAM, ks=KS, rays=32)[0, 0] * w).sum())
    assert g != 0.0
    assert g == pytest.approx(fd, rel=1e-5, abs=1e-7)


@pytest.mark.parametrize("fld", [(0.0, 0.0), (0.0, 3.0)])
def test_ideal_lens_psf_peak_gradient_points_to_the_focus(fld):
    """Behind the focus the peak grows when the sensor moves toward the lens, in front of it the other way."""
    for sd, sign in ((F + 0.04, -1.0), (F - 0.04, 1.0)):
        hl = ideal_hybrid(sd)
        hl.doe.phase_map.data.zero_()
        g, fd = thickness_fd(hl, lambda: hl.psf(fld, LAM, ks=KS, rays=32)[0, 0, KS // 2, KS // 2])
        assert g == pytest.approx(fd, rel=1e-5)
        assert sign * g > 0


def test_the_crop_centre_follows_the_chief_ray_with_the_sensor():
    hl = ideal_hybrid()
    res = hl.psf_result((0.0, 3.0), LAM, ks=KS, rays=32)
    t = hl.lens.surfaces[-1].thickness
    (dcy,) = torch.autograd.grad(res.center[0, 0, 1], t)
    assert float(dcy) == pytest.approx(math.tan(math.radians(3.0)), rel=1e-9)


def test_asphere_psf_gradient_wrt_the_sensor_distance():
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    phase = 0.3 * torch.randn(1500, 1500, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    hl = HybridLens(lens, PixelDOE(phase, 1e-3), 0.7)
    w = weights()
    for fld in ((0.0, 0.0), (0.0, 4.0)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            g, fd = thickness_fd(hl, lambda: (hl.psf(fld, 0.53, ks=KS, rays=32)[0, 0] * w).sum())
        assert g == pytest.approx(fd, rel=1e-5), (fld, g, fd)


def test_faithful_full_grid_psf_gradient_wrt_the_sensor_distance():
    lens = ideal_lens(F, f_number=16.0, wavelengths=(LAM,), sensor_distance=F + 0.05)
    hl = HybridLens(lens, PixelDOE(smooth_phase(400, 1.0, 2), 2e-3), DIST, sensor_pitch=2e-3)
    w = weights(16)

    def loss():
        psf = hl.psf((0.0, 1.0), LAM, ks=16, mode="faithful", rays=20_000, full_grid=True,
                     generator=torch.Generator().manual_seed(7))
        return (psf[0, 0] * w).sum()

    g, fd = thickness_fd(hl, loss)
    assert g == pytest.approx(fd, rel=1e-5)


def test_frozen_lens_or_cached_fields_give_the_same_psf_and_no_lens_gradient():
    hl = ideal_hybrid(F + 0.03)
    live = hl.psf((0.0, 3.0), LAM, ks=KS, rays=32)
    cache = [[fd.detach() for fd in row] for row in hl.doe_fields((0.0, 3.0), LAM, rays=32)]
    cached = hl.psf(ks=KS, cache=cache)
    hl.lens.requires_grad_(False)
    frozen = hl.psf((0.0, 3.0), LAM, ks=KS, rays=32)
    hl.lens.requires_grad_(True)
    assert torch.equal(live.detach(), frozen) or torch.allclose(live.detach(), frozen, rtol=0, atol=1e-15)
    assert torch.allclose(live.detach(), cached.detach(), rtol=0, atol=1e-15)
    hl.zero_grad()
    cached[0, 0, KS // 2, KS // 2].backward()
    assert all(p.grad is None for p in hl.lens.parameters())
    assert hl.doe.phase_map.grad is not None
