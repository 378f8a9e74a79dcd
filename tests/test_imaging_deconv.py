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
