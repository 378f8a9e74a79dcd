"""Depth from the image's own evidence (``network.deconv: wiener_select``, issue 15's EDoF reconstruction):
the power-spectrum prior against white noise, the Gaussian evidence picking the true depth of images drawn from
the model itself, the reconstruction = the evidence-weighted blend of each depth's Wiener filter (checked
against :func:`raywave.imaging.deconv.wiener_deconvolve` called directly), gradients and clear errors."""

import math
import warnings

import pytest
import torch

from raywave.imaging.deconv import WienerDeconv, wiener_deconvolve
from raywave.imaging.depth import depth_evidence, depth_weights, power_spectrum_prior, prior_on_grid
from raywave.imaging.render import render
from raywave.training.networks import NAFNet, DepthSelect, PSFAwareNet

SHOT, READ = 1e-4, 2e-4


def _gaussian_maps(widths, C=3, n=2, ks=15):
    """(S, C, n, n, ks, ks) normalised Gaussian PSF maps, one width (pixels) per 'depth'."""
    yy, xx = torch.meshgrid(torch.arange(ks) - ks // 2, torch.arange(ks) - ks // 2, indexing="ij")
    maps = []
    for w in widths:
        k = torch.exp(-(yy ** 2 + xx ** 2).double() / (2 * w ** 2))
        maps.append((k / k.sum()).expand(C, n, n, ks, ks).clone())
    return torch.stack(maps)


def _prior_field(B=2, C=3, size=96, seed=0, alpha=2.5):
    """Gaussian random images with the power spectrum ∝ 1/(f² + f0²)^(α/2) (natural-image-like), mean 0.4."""
    g = torch.Generator().manual_seed(seed)
    f = torch.fft.fftfreq(size, dtype=torch.float64)
    fr2 = f[:, None] ** 2 + f[None, :] ** 2
    amp = (fr2 + 0.01 ** 2) ** (-alpha / 4)
    noise = torch.randn(B, C, size, size, generator=g, dtype=torch.float64)
    x = torch.fft.ifft2(torch.fft.fft2(noise) * amp).real
    x = 0.08 * x / x.std()
    return (x + 0.4).clamp(0.0, 1.0)


def test_prior_of_white_noise_is_flat_at_its_variance():
    """White noise of variance σ² has the spectral density σ² at every frequency (per-pixel normalisation)."""
    g = torch.Generator().manual_seed(1)
    x = 0.05 * torch.randn(16, 3, 64, 64, generator=g, dtype=torch.float64)
    p = power_spectrum_prior(x)
    assert p.shape == (3, 48)
    ring = p[:, 3:40] / 0.05 ** 2  # the outermost rings (corners) hold few frequencies
    assert torch.allclose(ring.mean(1), torch.ones(3, dtype=p.dtype), rtol=0.05)
    assert float((ring - 1).abs().max()) < 0.3
    grid = prior_on_grid(p, 32, 40)
    assert grid.shape == (3, 32, 40) and torch.allclose(grid[:, 5, 7], p[:, 20:30].mean(1), rtol=0.15)


@pytest.mark.parametrize("true", [0, 1, 2])
def test_evidence_picks_the_depth_that_blurred_the_image(true):
    """Images drawn from the Gaussian model (prior spectrum, one of three blurs, sensor noise): the evidence is
    lowest for the blur that made them, and the depth weights concentrate on it."""
    maps = _gaussian_maps([1.0, 2.2, 3.6])
    x = _prior_field(seed=true)
    prior = power_spectrum_prior(_prior_field(B=8, seed=10))
    g = torch.Generator().manual_seed(2)
    y = render(x, maps[true])
    y = y + (SHOT * y.clamp(min=0) + READ ** 2).sqrt() * torch.randn(y.shape, generator=g, dtype=y.dtype)
    E, cy, cx = depth_evidence(y, maps, prior, SHOT, READ)
    assert E.shape == (2, 3, 2, 2) and cy.shape == (2,) and cx.shape == (2,)
    assert bool((E.argmin(1) == true).all())
    w = depth_weights(y, maps, prior, SHOT, READ)
    assert w.shape == (2, 3, 96, 96) and torch.allclose(w.sum(1), torch.ones(2, 96, 96, dtype=w.dtype))
    assert float(w[:, true].mean()) > 0.95


def _select_net(prior):
    net = NAFNet(3, width=4, enc_blocks=(1,), middle_blocks=1).double()
    return PSFAwareNet(net, WienerDeconv(3, init_lambda=1e-3, init_mu=1e-2, init_chroma=0.1).double(),
                       select=DepthSelect(prior, SHOT, READ))


def test_select_reconstruction_is_the_weighted_blend_of_each_depths_filter():
    maps, y = _gaussian_maps([1.0, 2.2, 3.6]), render(_prior_field(seed=3), _gaussian_maps([2.2])[0])
    prior = power_spectrum_prior(_prior_field(B=8, seed=11))
    pan = _select_net(prior)
    reg, rho = pan.deconv.regularisation(), pan.deconv.chroma()
    w = depth_weights(y, maps, prior, SHOT, READ)
    ref = sum(w[:, s:s + 1] * wiener_deconvolve(y, maps[s], reg, chroma=rho) for s in range(3))
    got = pan.deconvolve(y, maps)
    assert torch.allclose(got, ref, atol=1e-12)
    assert torch.allclose(pan(y, maps), got, atol=1e-12)  # an untrained network (zero residual) is the identity
    # one map (or no select): the plain deconvolution
    assert torch.allclose(pan.deconvolve(y, maps[1]), wiener_deconvolve(y, maps[1], reg, chroma=rho), atol=1e-12)


def test_select_gradients_reach_every_depths_map():
    maps = _gaussian_maps([1.0, 2.2, 3.6]).requires_grad_(True)
    y = render(_prior_field(seed=4), _gaussian_maps([2.2])[0]).detach()
    pan = _select_net(power_spectrum_prior(_prior_field(B=8, seed=12)))
    pan.select.temperature = 1e4  # soft weights: every depth contributes
    pan(y, maps).square().mean().backward()
    g = maps.grad
    assert torch.isfinite(g).all() and all(g[s].abs().max() > 0 for s in range(3))


def test_float32_gradients_stay_finite_where_nodes_miss_the_image():
    """Training runs in float32 on patches that see only some map nodes: the evidence's gradients w.r.t. the maps
    and the image stay finite (found by the EDoF demo: a NaN DOE after the first stage-1 step)."""
    maps = _gaussian_maps([1.0, 2.2, 3.6], n=5).float().requires_grad_(True)
    y = render(_prior_field(seed=5), _gaussian_maps([2.2])[0]).float().requires_grad_(True)
    prior = power_spectrum_prior(_prior_field(B=8, seed=13)).float()
    for extent in ((-1.0, -0.2, -1.0, -0.2), (0.3, 0.9, -0.4, 0.2)):  # a corner: most nodes have no weight here
        w = depth_weights(y, maps, prior, SHOT, READ, extent=extent, temperature=10.0)
        assert w.dtype == torch.float32 and torch.isfinite(w).all()
        (w * torch.linspace(0, 1, 3)[None, :, None, None]).sum().backward()
        assert torch.isfinite(maps.grad).all() and torch.isfinite(y.grad).all()
        assert maps.grad.abs().max() > 0


def test_select_errors_are_clear():
    maps, y = _gaussian_maps([1.0, 2.0]), _prior_field()
    prior = power_spectrum_prior(y)
    with pytest.raises(ValueError, match="S >= 2 depths"):
        depth_evidence(y, maps[:1], prior, SHOT, READ)
    with pytest.raises(ValueError, match="temperature must be > 0"):
        depth_weights(y, maps, prior, SHOT, READ, temperature=0.0)
    with pytest.raises(ValueError, match="prior has 1 channels"):
        depth_evidence(y, maps, prior[:1], SHOT, READ)
    with pytest.raises(ValueError, match="at least 8×8"):
        power_spectrum_prior(y[..., :4, :4])


def test_trainer_builds_the_depth_select(tiny_lens_file, tmp_path):
    """``network.deconv: wiener_select``: the prior measured on the training patches travels in the state dict,
    a training step runs, and one depth is refused clearly."""
    from test_training_e2e import CFG

    from raywave.training.config import apply_overrides, load_config
    from raywave.training.trainer import Trainer

    p = tmp_path / "cfg.yaml"
    p.write_text(CFG.format(lens=tiny_lens_file, deconv="wiener_select", ablation="false"))
    cfg = apply_overrides(load_config(p), ["optics.depths=[300.0,3000.0]"])
    tr = Trainer(cfg, tmp_path / "r", progress=False)
    assert isinstance(tr.net.select, DepthSelect) and "select.prior" in tr.net.state_dict()
    assert math.isclose(tr.net.select.read, cfg.stage2.read_noise / cfg.stage2.full_well)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr.run(stop_after=2)
    cfg1 = apply_overrides(load_config(p), ["optics.depths=[300.0]"])
    with pytest.raises(ValueError, match="two or more optics.depths"):
        Trainer(cfg1, tmp_path / "r1", progress=False)


def test_a_non_finite_gradient_is_refused_before_it_reaches_the_parameters(tiny_lens_file, tmp_path):
    """A NaN in a gradient stops the step by name instead of turning the DOE into NaN (the PSF would then fail
    far from the cause)."""
    from test_training_e2e import CFG

    from raywave.training.config import load_config
    from raywave.training.trainer import Trainer

    p = tmp_path / "cfg.yaml"
    p.write_text(CFG.format(lens=tiny_lens_file, deconv="wiener", ablation="false"))
    tr = Trainer(load_config(p), tmp_path / "r", progress=False)
    opt, _ = tr._optimizer("stage1")
    before = tr.hl.doe.phase_map.detach().clone()
    tr.hl.doe.phase_map.grad = torch.full_like(before, float("nan"))
    with pytest.raises(FloatingPointError, match="gradient of hybrid.doe.phase_map .* is not finite"):
        tr._optimizer_step(opt, None)
    assert torch.equal(tr.hl.doe.phase_map.detach(), before)

