"""Issue 47: the Fresnel edge step reads the stop rim's images (points and optical paths, k azimuths) at every node's
azimuth. They are smooth periodic functions of the azimuth, so trigonometric interpolation
(raywave.hybrid.coherent.stop_edge._rim_fourier) is exact for their first harmonics, where the periodic cubic
(_rim_cubic) cuts the chords of a large rim: on the f/3 double Gauss (a 21.4 mm rim image, 64 points) that moved the
edge's path difference by ~0.005 waves and its on-axis PSF by 1.07e-2 rel L1 (1.07e-3 from the converged Huygens
PSF with the trigonometric interpolation; benchmarks/results/stop_edge_references_2026-11-29_k47.json)."""

import math

import torch

from raywave.hybrid.coherent.stop_edge import RIM_POINTS, _rim_cubic, _rim_fourier


def _rim(k: int, radius: float = 21.4):
    """A rim image off centre with a tilted, astigmatic optical path: (k, 4) values x, y, z, opl at k azimuths."""
    th = torch.arange(k, dtype=torch.float64) * (2 * math.pi / k)
    x = 0.3 + radius * torch.cos(th)
    y = -1.2 + 0.97 * radius * torch.sin(th)
    z = 20.0 + 0.4 * torch.cos(2 * th)
    opl = 150.0 + 4.0 * torch.sin(th) + 0.02 * torch.cos(3 * th)
    return torch.stack([x, y, z, opl], -1)


def _exact(az: torch.Tensor, radius: float = 21.4) -> torch.Tensor:
    return torch.stack([0.3 + radius * torch.cos(az), -1.2 + 0.97 * radius * torch.sin(az),
                        20.0 + 0.4 * torch.cos(2 * az), 150.0 + 4.0 * torch.sin(az) + 0.02 * torch.cos(3 * az)], -1)


def test_trigonometric_rim_interpolation_is_exact_for_smooth_rims_where_the_cubic_is_not():
    g = torch.Generator().manual_seed(3)
    az = torch.rand(500, generator=g, dtype=torch.float64) * 2 * math.pi - math.pi
    r = 1.0 + torch.rand(500, generator=g, dtype=torch.float64)  # stop points in and outside the rim
    xs, ys = r * torch.cos(az), r * torch.sin(az)
    want = _exact(az)
    vals = _rim(RIM_POINTS)
    four = _rim_fourier(vals, xs, ys)
    assert float((four - want).abs().max()) < 1e-10  # mm
    cubic = _rim_cubic(vals, xs, ys)
    # the cubic's error on this 21 mm rim: ~1e-5 mm in position and optical path (0.02 waves at 0.55 µm)
    assert float((cubic - want).abs().max()) > 1e-6


def test_trigonometric_rim_interpolation_is_differentiable_in_values_and_stop_points():
    vals = _rim(8, radius=1.0).requires_grad_(True)
    xs = torch.tensor([0.3, -0.8, 0.1], dtype=torch.float64, requires_grad=True)
    ys = torch.tensor([0.9, 0.2, -1.1], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(_rim_fourier, (vals, xs, ys))
