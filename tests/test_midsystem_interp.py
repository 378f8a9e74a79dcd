"""The mid-system DOE's fast paths give the values (and gradients) of the straightforward autograd code, bit for bit
(issue 46's cost work: the PSFs must not move)."""

import torch

from raywave.hybrid.midsystem import _PlacedSum, _cubic_autograd, cubic_phase


def test_interpolation_without_autograd_is_the_autograd_paths_values_bit_for_bit():
    g = torch.Generator().manual_seed(3)
    pm = torch.randn(44, 36, dtype=torch.float64, generator=g) * 300.0  # a padded 40 × 32 map
    n = 4000  # inside, on the edge cells and off the grid (the clamped cells' extrapolation)
    u = torch.rand(n, dtype=torch.float64, generator=g) * 44.0 - 4.0
    v = torch.rand(n, dtype=torch.float64, generator=g) * 52.0 - 4.0
    with torch.no_grad():
        fast = cubic_phase(pm, u, v)
    ref = _cubic_autograd(pm.clone().requires_grad_(), u.clone().requires_grad_(), v)
    for a, b in zip(fast, ref):
        assert torch.equal(a, b.detach())


def test_interpolation_with_autograd_matches_finite_differences():
    g = torch.Generator().manual_seed(4)
    pm = torch.randn(14, 16, dtype=torch.float64, generator=g, requires_grad=True)
    u = (torch.rand(6, dtype=torch.float64, generator=g) * 9 + 2).requires_grad_()
    v = (torch.rand(6, dtype=torch.float64, generator=g) * 7 + 2).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, a, b: cubic_phase(p, a, b), (pm, u, v))
    phi, gu, gv = cubic_phase(pm, u, v)  # the returned derivatives are the interpolant's own
    du, = torch.autograd.grad(phi.sum(), u, retain_graph=True)
    dv, = torch.autograd.grad(phi.sum(), v)
    assert torch.allclose(du, gu, rtol=0, atol=1e-12) and torch.allclose(dv, gv, rtol=0, atol=1e-12)


def test_placed_sum_is_the_in_place_slice_sum_with_its_gradients_bit_for_bit():
    g = torch.Generator().manual_seed(5)
    shapes = [(30, 40), (28, 40), (30, 37)]
    offs = [(0, 0), (2, 0), (0, 3)]
    parts = [torch.randn(s, dtype=torch.complex128, generator=g).requires_grad_() for s in shapes]
    windows = [(slice(r, r + s[0]), slice(c, c + s[1])) for (r, c), s in zip(offs, shapes)]
    ref = torch.zeros((30, 40), dtype=torch.complex128)
    for w, p in zip(windows, parts):
        ref[w] += p
    out = _PlacedSum.apply((30, 40), windows, *parts)
    assert torch.equal(out, ref)
    weight = torch.randn((30, 40), dtype=torch.complex128, generator=g)
    ga = torch.autograd.grad((ref * weight).abs().sum(), parts)
    gb = torch.autograd.grad((out * weight).abs().sum(), parts)
    assert all(torch.equal(a, b) for a, b in zip(ga, gb))
