"""Reconstruction networks: shapes for any H, W, gradients reach every parameter, parameter counts, the
building blocks against their definitions."""

import pytest
import torch

from raywave.training.networks import (NAFNet, LayerNorm2d, SimpleGate, UNet, build_network, count_parameters)

NETS = [("unet", {}), ("nafnet", {}), ("unet", {"width": 8, "depth": 2}), ("nafnet", {"width": 8, "enc_blocks": (1, 2)})]


@pytest.mark.parametrize("kind,kw", NETS)
@pytest.mark.parametrize("hw", [(32, 32), (37, 50), (9, 13)])
def test_shapes_any_size(kind, kw, hw):
    torch.manual_seed(0)
    net = build_network(kind, **kw)
    x = torch.rand(2, 3, *hw)
    y = net(x)
    assert y.shape == x.shape and torch.isfinite(y).all()


@pytest.mark.parametrize("kind,kw", NETS)
def test_gradients_reach_every_parameter(kind, kw):
    torch.manual_seed(0)
    net = build_network(kind, **kw)
    # NAFNet's β, γ start at 0, which blocks the gradient of everything inside the blocks: perturb them
    # and the last convolution starts at zero (identity network): perturb it too
    with torch.no_grad():
        for name, p in net.named_parameters():
            if name.endswith("beta") or name.endswith("gamma"):
                p.fill_(0.1)
            if name.startswith(("out.", "ending.")):
                p.normal_(0, 0.1)
    x = torch.rand(1, 3, 24, 24, requires_grad=True)
    net(x).square().mean().backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or float(p.grad.abs().sum()) == 0]
    assert not missing
    assert float(x.grad.abs().sum()) > 0


def test_parameter_counts_reported_and_small_by_default():
    counts = {k: count_parameters(build_network(k)) for k in ("unet", "nafnet")}
    print("parameter counts (default widths):", counts)
    assert counts == {"unet": count_parameters(UNet()), "nafnet": count_parameters(NAFNet())}
    assert all(10_000 < c < 1_000_000 for c in counts.values()), counts
    assert count_parameters(UNet(width=32)) > 3 * counts["unet"]


@pytest.mark.parametrize("kind", ["unet", "nafnet"])
def test_untrained_networks_are_the_identity(kind):
    """The last convolution starts at zero (and NAFNet's β = γ = 0): the untrained network returns its input."""
    torch.manual_seed(0)
    net = build_network(kind, width=8)
    x = torch.rand(1, 3, 17, 16)
    assert torch.equal(net(x), x)


def test_layernorm2d_and_simplegate_definitions():
    x = torch.randn(2, 6, 5, 7, dtype=torch.float64)
    ln = LayerNorm2d(6).double()
    ref = torch.nn.functional.layer_norm(x.permute(0, 2, 3, 1), (6,), eps=1e-6).permute(0, 3, 1, 2)
    assert torch.allclose(ln(x), ref, atol=1e-12)
    assert torch.equal(SimpleGate()(x), x[:, :3] * x[:, 3:])


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown network 'resnet'"):
        build_network("resnet")
    with pytest.raises(ValueError, match="dec_blocks"):
        NAFNet(enc_blocks=(1, 1), dec_blocks=(1,))
