"""raywave.wave.field.cubic_matrix (Keys cubic convolution, quadratic extrapolation beyond the ends): each row sums
to 1 and the interpolant reproduces any quadratic exactly, up to and at the boundary nodes (the ghost nodes folded
onto the first and last three nodes)."""

import torch

from raywave.wave.field import cubic_matrix, upsample_nodes, upsample_nodes_window


def test_cubic_matrix_reproduces_quadratics_to_the_boundary():
    g = torch.Generator().manual_seed(3)
    for n_nodes in (3, 4, 9, 41):
        pos = torch.cat([torch.rand(200, generator=g, dtype=torch.float64) * (n_nodes - 1),
                         torch.tensor([0.0, 0.5, n_nodes - 1.5, n_nodes - 1.0], dtype=torch.float64)])
        m = cubic_matrix(pos, n_nodes)
        assert m.shape == (pos.numel(), n_nodes)
        assert torch.allclose(m.sum(1), torch.ones_like(pos), rtol=0, atol=1e-14)
        x = torch.arange(n_nodes, dtype=torch.float64)
        for f in (lambda t: 2.0 + 0 * t, lambda t: 0.7 * t - 1.0, lambda t: 0.3 * t * t - 2.0 * t + 5.0):
            assert torch.allclose(m @ f(x), f(pos), rtol=0, atol=1e-11)
        # at a node the interpolant is the node's value
        on = cubic_matrix(x, n_nodes)
        assert torch.allclose(on, torch.eye(n_nodes, dtype=torch.float64), rtol=0, atol=1e-15)


def test_banded_upsample_equals_the_dense_products():
    """upsample_nodes on the CPU (block products over the nodes each block of fine samples touches, issue 47) equals
    the dense ``my @ values @ mx.T`` to rounding, and its gradient too; with and without autograd bit for bit (a
    replay compares the two). Blocks of several rows and a last partial block (5 × 37 nodes → 301 × 290 samples)."""
    g = torch.Generator().manual_seed(5)
    values = torch.randn((3, 37, 41), generator=g, dtype=torch.float64)
    pos_y = torch.linspace(0.0, 36.0, 301, dtype=torch.float64)
    pos_x = torch.linspace(0.3, 39.1, 290, dtype=torch.float64)
    my, mx = cubic_matrix(pos_y, 37), cubic_matrix(pos_x, 41)
    dense = my @ values @ mx.T
    with torch.no_grad():
        got = upsample_nodes(values, pos_y=pos_y, pos_x=pos_x)
    assert got.shape == dense.shape
    assert float((got - dense).abs().max()) < 1e-13
    v = values.clone().requires_grad_()
    out = upsample_nodes(v, pos_y=pos_y, pos_x=pos_x)
    assert torch.equal(out.detach(), got)
    w = torch.randn(out.shape, generator=g, dtype=torch.float64)
    (out * w).sum().backward()
    assert torch.allclose(v.grad, my.T @ w @ mx, rtol=0, atol=1e-12)
    # the stride form and one channel without a leading axis
    with torch.no_grad():
        one = upsample_nodes(values[0], stride=4)
    fine = torch.arange(36 * 4 + 1, dtype=torch.float64) / 4
    ref = cubic_matrix(fine, 37) @ values[0] @ cubic_matrix(torch.arange(40 * 4 + 1, dtype=torch.float64) / 4, 41).T
    assert one.shape == ref.shape and float((one - ref).abs().max()) < 1e-13


def _random_stack(seed: int, shape: tuple, y: tuple, x: tuple):
    """``(generator, values, pos_y, pos_x)``: a generator seeded ``seed``, random float64 node values ``shape`` drawn
    from it, and the fine positions ``linspace(*y)`` (rows) and ``linspace(*x)`` (columns), in node units."""
    g = torch.Generator().manual_seed(seed)
    values = torch.randn(shape, generator=g, dtype=torch.float64)
    return g, values, torch.linspace(*y, dtype=torch.float64), torch.linspace(*x, dtype=torch.float64)


def test_upsample_window_is_the_slice_of_the_upsampling():
    """upsample_nodes_window (issue 46: the fine field's crop): the values (and the window's) are upsample_nodes'
    bit for bit, and the window's gradient (its banded transpose) equals autograd's through the slice of the whole
    upsampling to rounding; without autograd the window is a plain slice."""
    g, values, pos_y, pos_x = _random_stack(7, (4, 40, 37), (0.3, 38.6, 301), (0.0, 36.0, 290))
    box = (17, 260, 5, 281)
    v = values.clone().requires_grad_()
    full = upsample_nodes(v, pos_y=pos_y, pos_x=pos_x)
    ref = full[:, box[0]:box[1], box[2]:box[3]]
    fine, window = upsample_nodes_window(v, pos_y, pos_x)
    assert not fine.requires_grad and torch.equal(fine, full.detach())
    got = window(box)
    assert got.requires_grad and torch.equal(got.detach(), ref.detach())
    w = torch.randn(ref.shape, generator=g, dtype=torch.float64)
    g_ref, = torch.autograd.grad(ref, v, w)
    g_got, = torch.autograd.grad(got, v, w)
    assert float((g_got - g_ref).abs().max()) <= 1e-13 * float(g_ref.abs().max())
    with torch.no_grad():
        plain, win = upsample_nodes_window(values, pos_y, pos_x)
        assert torch.equal(win(box), plain[:, box[0]:box[1], box[2]:box[3]]) and torch.equal(plain, fine)


def test_upsample_window_of_one_channel():
    """upsample_nodes_window of a single (Ky, Kx) map: the window and its gradient as for a stack."""
    g = torch.Generator().manual_seed(9)
    v = torch.randn((12, 15), generator=g, dtype=torch.float64, requires_grad=True)
    pos_y, pos_x = torch.linspace(0.0, 11.0, 50, dtype=torch.float64), torch.linspace(0.2, 14.0, 61, dtype=torch.float64)
    ref = upsample_nodes(v, pos_y=pos_y, pos_x=pos_x)[3:40, 2:55]
    got = upsample_nodes_window(v, pos_y, pos_x)[1]((3, 40, 2, 55))
    assert torch.equal(got.detach(), ref.detach())
    w = torch.randn(ref.shape, generator=g, dtype=torch.float64)
    assert torch.allclose(torch.autograd.grad(got, v, w)[0], torch.autograd.grad(ref, v, w)[0], rtol=0, atol=1e-13)


def test_upsample_window_split_is_the_unbind_of_the_window():
    """upsample_nodes_window's window split into its channels (``split=True``; :class:`_BandedChannels`, issue 43:
    each channel's gradient taken where it is, no stack): the channels of the window bit for bit, the gradient that
    of the unbound window bit for bit (a channel left out of the loss included), and without autograd the plain
    slice's channels."""
    g, values, pos_y, pos_x = _random_stack(11, (5, 23, 19), (0.2, 21.7, 131), (0.0, 18.0, 117))
    box = (9, 120, 3, 101)
    v = values.clone().requires_grad_()
    fine, window = upsample_nodes_window(v, pos_y, pos_x)
    ref = window(box).unbind(0)
    got = window(box, split=True)
    assert len(got) == 5 and all(torch.equal(a.detach(), b.detach()) for a, b in zip(got, ref))
    w = torch.randn((5, *ref[0].shape), generator=g, dtype=torch.float64)
    used = (0, 2, 3)  # channels 1 and 4 get no gradient (None in the backward)
    g_ref, = torch.autograd.grad(sum((ref[i] * w[i]).sum() for i in used), v)
    g_got, = torch.autograd.grad(sum((got[i] * w[i]).sum() for i in used), v)
    assert torch.equal(g_got, g_ref)
    with torch.no_grad():
        plain, win = upsample_nodes_window(values, pos_y, pos_x)
        assert all(torch.equal(a, b) for a, b in zip(win(box, split=True), plain[:, box[0]:box[1], box[2]:box[3]]))


def test_banded_channels_gradcheck():
    """torch.autograd.gradcheck of :class:`_BandedChannels` (every channel an output) on a small window."""
    from raywave.wave.field import _BandedChannels, _banded_upsample

    g = torch.Generator().manual_seed(5)
    v = torch.randn((3, 6, 5), generator=g, dtype=torch.float64, requires_grad=True)
    my = cubic_matrix(torch.linspace(0.3, 4.6, 11, dtype=torch.float64), 6)[2:9]
    mx = cubic_matrix(torch.linspace(0.0, 3.9, 9, dtype=torch.float64), 5)[1:8]

    def f(x):
        with torch.no_grad():
            out = _banded_upsample(x, my, mx)
        return _BandedChannels.apply(x, my, mx, out)

    assert torch.autograd.gradcheck(f, (v,), check_undefined_grad=False)
