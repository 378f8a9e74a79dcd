"""Multi-Wiener deconvolution (raywave.imaging.deconv): the exact inverse of the renderer where the blur is
invertible, the same partition of unity, the warp undone, differentiable w.r.t. the PSFs and the regularisation."""

import math

import pytest
import torch

from raywave.imaging.deconv import WienerDeconv, laplacian_power, wiener_deconvolve
from raywave.imaging.render import render


def _image(seed=0, shape=(2, 3, 40, 48)):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    return torch.nn.functional.avg_pool2d(x, 3, 1, 1)  # some spatial correlation


def _kernel(shift=(0, 0), k=9):
    """A well-conditioned asymmetric kernel (|K̂| >= 0.2 everywhere), its centre at [k//2, k//2]."""
    w = torch.zeros(k, k, dtype=torch.float64)
    c = k // 2
    w[c, c] = 0.6
    w[c + shift[0], c + 2 + shift[1]] += 0.2
    w[c - 3, c] += 0.2
    return w


def test_uniform_blur_is_inverted_exactly():
    """Zero padding on both sides: blur then deconvolve with λ → 0 gives the image back away from the frame
    (light blurred out of the frame is lost near it); an asymmetric kernel catches a flipped or shifted kernel."""
    x = _image()
    k = _kernel()
    inner = (slice(None), slice(None), slice(10, -10), slice(10, -10))
    for orientation in ("picture", "sensor"):
        y = render(x, k, padding="zero", orientation=orientation)
        rec = wiener_deconvolve(y, k, 1e-12, padding="zero", orientation=orientation)
        assert torch.allclose(rec[inner], x[inner], atol=1e-4)  # the error decays away from the frame
        assert (rec - x).abs().max() < 2e-3 and (y - x).abs().max() > 0.1


def test_map_of_equal_kernels_equals_one_kernel():
    """The node results are blended with a partition of unity: a map of equal kernels is one deconvolution."""
    x = _image(1)
    k = _kernel()
    y = render(x, k, padding="zero")
    a = wiener_deconvolve(y, k, 1e-3)
    b = wiener_deconvolve(y, k.expand(3, 3, 9, 9), 1e-3)
    assert torch.allclose(a, b, atol=1e-12)


def test_spatially_varying_map_restores_its_blur():
    """A 2×2 map of different kernels: the multi-Wiener result is far closer to the sharp image than the blurred
    image is (the blend is exact only where one node's weight is 1, so not to round-off)."""
    x = _image(2, (1, 3, 64, 64))
    ks = torch.stack([_kernel((0, 0)), _kernel((1, 0)), _kernel((0, 1)), _kernel((2, 1))]).reshape(2, 2, 9, 9)
    y = render(x, ks, padding="zero")
    rec = wiener_deconvolve(y, ks, 1e-6, padding="zero")
    err_in = (y - x).square().mean().sqrt()
    err_out = (rec - x).square().mean().sqrt()
    assert err_out < 0.3 * err_in  # measured 0.2: the kernels differ by whole-pixel satellites


def test_warp_of_the_renderer_is_undone():
    """With a delta PSF the renderer only warps (distortion of the map's centres); the deconvolution undoes it
    (interior pixels; bilinear resampling twice)."""
    yy, xx = torch.meshgrid(torch.arange(48.0), torch.arange(48.0), indexing="ij")
    x = torch.stack([0.5 + 0.3 * torch.sin(xx / (4 + c) + yy / 7) for c in range(3)])[None].double()  # smooth:
    # bilinear resampling is accurate on it
    delta = torch.ones(2, 2, 1, 1, dtype=torch.float64)  # a 2×2 map of delta PSFs
    pos = torch.stack(torch.meshgrid(torch.tensor([-0.5, 0.5]), torch.tensor([-0.5, 0.5]), indexing="xy"), -1).double()
    sensor = (2.0, 2.0)
    centers = pos * 1.0 + torch.tensor([[[0.01, -0.02], [0.015, 0.0]], [[0.0, 0.01], [-0.01, 0.02]]]).double()
    centers = centers[None].expand(3, 2, 2, 2)
    kw = dict(positions=pos, centers=centers, sensor_size=sensor, extent=(-0.5, 0.5, -0.5, 0.5))
    y = render(x, delta, **kw)
    assert (y - x).abs().max() > 0.01  # it did move
    rec = wiener_deconvolve(y, delta, 1e-12, **kw)
    inner = (slice(None), slice(None), slice(4, -4), slice(4, -4))
    assert (rec - x)[inner].abs().mean() < 0.2 * (y - x)[inner].abs().mean()  # 0.13: bilinear resampling twice


def test_gradients_wrt_psf_and_regularisation_match_finite_differences():
    x = _image(4, (1, 3, 16, 16))
    k = _kernel(k=5).expand(3, 5, 5).clone().requires_grad_(True)
    y = render(x, k.detach(), padding="zero")
    lam = torch.tensor([1e-2, 2e-2, 3e-2], dtype=torch.float64, requires_grad=True)
    mu = torch.tensor([1e-2, 1e-3, 0.0], dtype=torch.float64)

    def f(kk, ll):
        return wiener_deconvolve(y, kk, (ll, mu)).sin().sum()

    assert torch.autograd.gradcheck(f, (k, lam), eps=1e-6, atol=1e-5)


def test_module_learns_positive_regularisation_and_rejects_bad_input():
    m = WienerDeconv(3, init_lambda=1e-3, init_mu=1e-2)
    reg = m.regularisation()
    assert reg.shape == (2, 3) and torch.allclose(reg[0], torch.full((3,), 1e-3))
    x = _image(5, (1, 3, 20, 20)).float()
    out = m(x, _kernel().float())
    out.mean().backward()
    assert m.log_lambda.grad is not None and torch.isfinite(m.log_lambda.grad).all()
    with pytest.raises(ValueError, match="regularisation"):
        wiener_deconvolve(x, _kernel().float(), -1.0)
    with pytest.raises(ValueError, match="init_lambda"):
        WienerDeconv(3, init_lambda=0.0)


def test_laplacian_power_is_normalised():
    lp = laplacian_power(16, 16)
    assert lp.shape == (16, 9) and float(lp[0, 0]) == 0.0 and math.isclose(float(lp.max()), 1.0)


def test_a_set_of_one_map_or_of_equal_maps_is_the_plain_filter():
    x = _image(3)
    k = _kernel()
    y = render(x, k, padding="zero")
    a = wiener_deconvolve(y, k, 1e-3)
    kk = k.expand(3, 1, 1, 9, 9)
    assert torch.allclose(wiener_deconvolve(y, kk[None], 1e-3), a, atol=1e-12)
    assert torch.allclose(wiener_deconvolve(y, torch.stack([kk, kk]), 1e-3), a, atol=1e-12)


def _box(n, k=9):
    w = torch.zeros(k, k, dtype=torch.float64)
    c = k // 2
    w[c - n:c + n + 1, c - n:c + n + 1] = 1.0
    return w / w.sum()


def test_unknown_depth_filter_has_less_expected_error_than_the_mean_psf():
    """Two depths: one in focus (a near-delta kernel), one defocused (a 7×7 box). Deconvolving with the depth-
    averaged PSF boosts frequencies that neither depth has and over-sharpens the in-focus image; the
    expected-error filter ``mean conj(K) / (mean |K|² + λ)`` has the smaller error averaged over the depths
    (it is the per-frequency minimiser of that error), and its gradient reaches both maps."""
    x = _image(4, (2, 3, 64, 64))
    maps = torch.stack([_kernel(), _box(3)])  # (S, ks, ks)
    g = torch.Generator().manual_seed(0)
    sims = [render(x, m, padding="zero") for m in maps]
    sims = [s + 1e-3 * torch.randn(s.shape, generator=g, dtype=s.dtype) for s in sims]
    lam = 1e-3
    inner = (slice(None), slice(None), slice(12, -12), slice(12, -12))

    def err(rec):
        return float((rec - x)[inner].square().mean())

    mean_psf = sum(err(wiener_deconvolve(s, maps.mean(0), lam, padding="zero")) for s in sims) / 2
    mset = maps[:, None, None, None].expand(2, 3, 1, 1, 9, 9).clone().requires_grad_(True)
    robust = [wiener_deconvolve(s, mset, lam, padding="zero") for s in sims]
    expected = sum(err(r.detach()) for r in robust) / 2
    assert expected < 0.8 * mean_psf
    sum(r.square().sum() for r in robust).backward()
    assert bool(mset.grad[0].abs().sum() > 0) and bool(mset.grad[1].abs().sum() > 0)


# ------------------------------------------------------------------ the colour prior (chroma = ρ)
def _rgb_maps(seed=3):
    """A 2×2 map of three different kernels per channel (C, N, M, 9, 9), each summing to 1."""
    g = torch.Generator().manual_seed(seed)
    k = torch.rand((3, 2, 2, 9, 9), generator=g, dtype=torch.float64) ** 4
    return k / k.sum((-2, -1), keepdim=True)


def test_colour_prior_of_rho_one_is_the_per_channel_filter():
    """ρ = 1: the regularisation matrix is diagonal, the 3×3 solve is the per-channel division (to rounding),
    for one map and for the expected-error filter of a set of maps."""
    x, k = _image(), _rgb_maps()
    y = render(x, k)
    for psf in (k, torch.stack([k, _rgb_maps(4)])):
        a = wiener_deconvolve(y, psf, (1e-3, 1e-2))
        b = wiener_deconvolve(y, psf, (1e-3, 1e-2), chroma=1.0)
        assert (a - b).abs().max() < 1e-12


def test_colour_prior_restores_grey_as_before_and_damps_chroma_by_rho():
    """The analytic limits of the colour prior with one kernel for the three channels: the luminance direction
    (1, 1, 1) is an eigenvector of the prior (eigenvalue 1), so a grey image is restored exactly as by the
    per-channel filter; a pure chroma image (zero mean over the channels) sees the regularisation R/ρ, i.e. the
    per-channel filter with λ/ρ and μ/ρ."""
    k1 = _rgb_maps()[0]
    k = k1.expand(3, *k1.shape)
    grey = _image(shape=(1, 1, 40, 48)).expand(1, 3, 40, 48)
    yg = render(grey, k)
    assert (wiener_deconvolve(yg, k, (1e-3, 1e-2), chroma=0.1) - wiener_deconvolve(yg, k, (1e-3, 1e-2))).abs().max() < 1e-12
    c = _image(seed=5, shape=(1, 3, 40, 48))
    c = c - c.mean(1, keepdim=True)
    yc = render(c, k)
    got = wiener_deconvolve(yc, k, (1e-3, 1e-2), chroma=0.1)
    want = wiener_deconvolve(yc, k, (1e-2, 1e-1))
    assert (got - want).abs().max() < 1e-12


def test_colour_prior_reduces_colour_noise_of_a_noisy_grey_image():
    """Independent noise in R, G, B of a blurred grey scene: the per-channel filter boosts it into colour
    speckle, the colour prior (ρ = 0.1) keeps the restored image's chroma less than half as large, at a smaller
    total error."""
    k = _rgb_maps()
    grey = _image(shape=(1, 1, 40, 48)).expand(1, 3, 40, 48)
    y = render(grey, k) + 0.01 * torch.randn((1, 3, 40, 48), generator=torch.Generator().manual_seed(1),
                                             dtype=torch.float64)

    def chroma_rms(r):
        return float((r - r.mean(1, keepdim=True)).square().mean().sqrt())

    per_channel = wiener_deconvolve(y, k, (1e-3, 1e-2))
    prior = wiener_deconvolve(y, k, (1e-3, 1e-2), chroma=0.1)
    assert chroma_rms(prior) < 0.5 * chroma_rms(per_channel)  # measured 0.39×
    assert (prior - grey).square().mean() < (per_channel - grey).square().mean()


def test_colour_prior_is_learned_and_checked():
    """WienerDeconv(init_chroma=ρ): a parameter that receives a gradient through the 3×3 solve (matching
    central differences); ρ outside (0, 1] or an image without 3 channels is an error that says so."""
    x, k = _image(shape=(1, 3, 24, 28)), _rgb_maps()
    y = render(x, k)
    m = WienerDeconv(3, init_chroma=0.2)
    assert m.log_chroma is not None and abs(float(m.chroma()) - 0.2) < 1e-7  # a float32 parameter
    m = m.double()
    loss = (m(y, k) - x).square().sum()
    loss.backward()
    g = float(m.log_chroma.grad)
    h = 1e-6
    with torch.no_grad():
        m.log_chroma += h
        lp = float((m(y, k) - x).square().sum())
        m.log_chroma -= 2 * h
        lm = float((m(y, k) - x).square().sum())
    assert g == pytest.approx((lp - lm) / (2 * h), rel=1e-5)
    assert WienerDeconv(3).log_chroma is None
    with pytest.raises(ValueError, match="chroma.*\\(0, 1\\]"):
        WienerDeconv(3, init_chroma=1.5)
    with pytest.raises(ValueError, match="3 channels"):
        wiener_deconvolve(y[:, :1], k[:1], 1e-3, chroma=0.5)


def test_chroma_ratio_is_zero_for_grey_one_for_independent_channels():
    from raywave.imaging.deconv import chroma_ratio

    g = torch.Generator().manual_seed(0)
    grey = torch.rand((4, 1, 32, 32), generator=g, dtype=torch.float64).expand(4, 3, 32, 32)
    assert chroma_ratio(grey) == pytest.approx(0.0, abs=1e-12)
    assert chroma_ratio(torch.rand((8, 3, 64, 64), generator=g, dtype=torch.float64)) == pytest.approx(1.0, abs=0.03)
    with pytest.raises(ValueError, match="3, H, W"):
        chroma_ratio(grey[:, :2])
