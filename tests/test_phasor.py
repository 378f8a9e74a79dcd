"""raywave.utils.phasor: ``polar`` and ``unit_phasor`` against torch.polar (values and derivatives), and the same
values bit for bit with and without autograd (the memory-saving replay compares the two passes)."""

import torch

from raywave.utils.phasor import polar, unit_phasor


def test_polar_matches_torch_polar_to_rounding():
    a = torch.rand(64, 48, dtype=torch.float64)
    t = torch.randn(64, 48, dtype=torch.float64) * 50
    ref = torch.polar(a, t)
    assert float((polar(a, t) - ref).abs().max()) <= 4e-16


def test_unit_phasor_is_polar_with_unit_modulus_bit_for_bit():
    t = torch.randn(33, 21, dtype=torch.float64) * 1e3
    want = polar(torch.ones_like(t), t)
    assert torch.equal(unit_phasor(t), want)
    tg = t.clone().requires_grad_()
    assert torch.equal(unit_phasor(tg).detach(), want)  # the autograd path gives the same values


def test_unit_phasor_gradient_equals_polars_and_passes_gradcheck():
    g = torch.randn(17, 9, dtype=torch.complex128)
    t = torch.randn(17, 9, dtype=torch.float64, requires_grad=True)
    (got,) = torch.autograd.grad(unit_phasor(t), t, g)
    s = t.detach().clone().requires_grad_()
    (ref,) = torch.autograd.grad(polar(torch.ones_like(s), s), s, g)
    assert torch.equal(got, ref)
    assert torch.autograd.gradcheck(unit_phasor, (torch.randn(6, dtype=torch.float64, requires_grad=True),))
