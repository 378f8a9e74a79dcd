"""raywave.utils.fused: one compiled loop per elementwise chain, the eager function as reference and fallback."""

import math
import warnings

import pytest
import torch

from raywave.utils.fused import FusedFallbackWarning, fused


def _chain(x, y, z: float):
    """A float64 chain like the engine's (phase, sin/cos, products), complex result stacked (..., 2)."""
    ph = z * torch.sqrt(1.0 + x * x) - y
    return torch.stack([torch.cos(ph) * y, torch.sin(ph) * y], -1)


_fused_chain = fused(_chain)


def _inputs(n=4099, requires_grad=False):
    g = torch.Generator().manual_seed(3)
    x = torch.rand(n, dtype=torch.float64, generator=g).requires_grad_(requires_grad)
    y = torch.rand(n, dtype=torch.float64, generator=g).requires_grad_(requires_grad)
    return x, y


def test_fused_matches_the_eager_chain_to_rounding():
    x, y = _inputs()
    for z in (3.0, 1234.5):  # a large phase: the compiled sin/cos still within a few ulp of the argument's size
        got, want = _fused_chain(x, y, z), _chain(x, y, z)
        assert got.dtype == torch.float64 and got.shape == (x.numel(), 2)
        assert (got - want).abs().max() <= 64 * torch.finfo(torch.float64).eps * max(1.0, z)


def test_fused_values_do_not_depend_on_the_position_in_the_array():
    """A sub-array gives the same bits as the same samples inside a longer array (vector loop vs its tail)."""
    x, y = _inputs()
    whole = _fused_chain(x, y, 7.0)
    part = _fused_chain(x[5:1030], y[5:1030], 7.0)
    assert torch.equal(whole[5:1030], part)


def test_fused_gradients_match_eager_and_forward_equals_no_grad():
    x, y = _inputs(requires_grad=True)
    got = _fused_chain(x, y, 2.5)
    gx, gy = torch.autograd.grad(got.square().sum(), (x, y))
    x2, y2 = _inputs(requires_grad=True)
    want = _chain(x2, y2, 2.5)
    wx, wy = torch.autograd.grad(want.square().sum(), (x2, y2))
    assert torch.allclose(gx, wx, rtol=0, atol=1e-13) and torch.allclose(gy, wy, rtol=0, atol=1e-13)
    with torch.no_grad():
        assert torch.equal(_fused_chain(x, y, 2.5), got.detach())


def test_raywave_compile_0_keeps_the_eager_function(monkeypatch):
    monkeypatch.setenv("RAYWAVE_COMPILE", "0")
    x, y = _inputs(513)
    assert torch.equal(_fused_chain(x, y, 3.0), _chain(x, y, 3.0))


def test_a_function_that_cannot_compile_falls_back_with_one_warning():
    def data_dependent(x):
        return x * 2.0 if float(x.sum()) > 0 else x  # a host read: no single graph

    f = fused(data_dependent)
    x = torch.ones(8, dtype=torch.float64)
    with pytest.warns(FusedFallbackWarning, match="data_dependent"):
        assert torch.equal(f(x), x * 2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(f(x), x * 2.0)  # eager from now on, no second warning


def test_bad_input_raises_its_own_error_not_a_compiler_warning():
    x, y = _inputs(16)
    with pytest.raises(RuntimeError, match="size"):
        _fused_chain(x, y[:5], 1.0)
    assert math.isfinite(float(_fused_chain(x, y, 1.0).sum()))  # still compiled afterwards


def test_the_raised_recompile_limit_is_scoped_to_the_fused_call():
    import torch._dynamo

    before = torch._dynamo.config.cache_size_limit
    x, y = _inputs(64)
    _fused_chain(x, y, 1.5)
    assert torch._dynamo.config.cache_size_limit == before


def _window_chain(a, b, k: float):
    """A 2-D window chain (the knife edge's kind: two crops of one array in, two arrays out)."""
    return torch.cos(k * b) * a, torch.sin(k * b) * a


_fused_window = fused(_window_chain)


def test_a_square_window_first_does_not_cost_a_rectangular_one_its_own_graph():
    """Duck sizing off: a square first call (an on-axis PSF's window) does not specialise its two sizes as equal, so
    rectangular windows later (off-axis PSFs) run the same compiled graph (each extra graph ~1–15 s)."""
    from torch._dynamo.utils import counters
    g = torch.Generator().manual_seed(5)
    base = torch.rand(2, 90, 120, dtype=torch.float64, generator=g)
    before = counters["stats"]["unique_graphs"]
    for (r0, r1, c0, c1) in ((3, 67, 5, 69), (2, 50, 7, 101), (4, 81, 3, 40)):  # square, then wide and tall
        a, b = base[0, r0:r1, c0:c1], base[1, r0:r1, c0:c1]
        got = _fused_window(a, b, 2.0)
        want = _window_chain(a, b, 2.0)
        assert all((x - y).abs().max() <= 1e-14 for x, y in zip(got, want))
    assert counters["stats"]["unique_graphs"] - before == 1
