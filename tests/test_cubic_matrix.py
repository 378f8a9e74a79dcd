"""raywave.wave.field.cubic_matrix (Keys cubic convolution, quadratic extrapolation beyond the ends): each row sums
to 1 and the interpolant reproduces any quadratic exactly, up to and at the boundary nodes (the ghost nodes folded
onto the first and last three nodes)."""

import torch

from raywave.wave.field import cubic_matrix


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
