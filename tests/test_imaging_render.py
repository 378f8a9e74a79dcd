"""Spatially-varying rendering against results it does not compute itself: scipy's FFT convolution, a direct
per-pixel sum, exact pixel shifts, energy sums, finite differences; the image-orientation convention."""

import math

import numpy as np
import pytest
import torch
from scipy.signal import fftconvolve

from raywave.imaging import (depth_layer_weights, normalised_grid, pixel_positions, render, render_reference,
                             render_rgbd, resample_psf)
from raywave.imaging.render import _hat_weights

D = torch.float64


def random_psfs(c, n, m, ks, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = torch.rand((c, n, m, ks, ks), generator=g, dtype=D) ** 4
    return k / k.sum((-1, -2), keepdim=True)


def image(b=2, c=3, h=40, w=52, seed=1):
    return torch.rand((b, c, h, w), generator=torch.Generator().manual_seed(seed), dtype=D)


def delta(c, n, m, ks, dx=0, dy=0):
    k = torch.zeros((c, n, m, ks, ks), dtype=D)
    k[..., ks // 2 + dy, ks // 2 + dx] = 1
    return k


def gaussian_kernel(sx, sy, ks, theta=0.0):
    """Normalised anisotropic Gaussian (ks, ks) [iy, ix] centred on pixel ks//2."""
    t = torch.arange(ks, dtype=D) - ks // 2
    y, x = torch.meshgrid(t, t, indexing="ij")
    c, s = math.cos(theta), math.sin(theta)
    xr, yr = c * x + s * y, -s * x + c * y
    g = torch.exp(-0.5 * ((xr / sx) ** 2 + (yr / sy) ** 2))
    return g / g.sum()


# ---------------------------------------------------------------------------- the must-shows
@pytest.mark.parametrize("orientation", ["picture", "sensor"])
@pytest.mark.parametrize("padding", ["reflect", "replicate", "zero"])
def test_a_delta_psf_leaves_the_image_unchanged(orientation, padding):
    img = image()
    out = render(img, delta(3, 4, 5, 9), orientation=orientation, padding=padding)
    assert float((out - img).abs().max()) < 1e-13


@pytest.mark.parametrize("ks", [9, 10])
def test_a_uniform_psf_map_is_one_fft_convolution(ks):
    """Every node carries the same PSF: the result is scipy's linear convolution (zero padding) to 1e-10, in
    sensor orientation directly and in picture orientation with the PSF mirrored in x (columns run along −x)."""
    img = image()
    k = random_psfs(3, 1, 1, ks)[:, 0, 0]
    kmap = k[:, None, None].expand(3, 4, 5, ks, ks)
    H, W = img.shape[-2:]
    ref = np.stack([[fftconvolve(img[b, c].numpy(), k[c].numpy(), mode="full")[ks // 2: ks // 2 + H,
                                                                              ks // 2: ks // 2 + W]
                     for c in range(3)] for b in range(2)])
    out = render(img, kmap, orientation="sensor", padding="zero")
    assert np.abs(out.numpy() - ref).max() < 1e-10
    x0 = ks - 1 - ks // 2  # the mirrored kernel's centre column
    refp = np.stack([[fftconvolve(img[b, c].numpy(), k[c].flip(-1).numpy(), mode="full")[ks // 2: ks // 2 + H,
                                                                                        x0: x0 + W]
                      for c in range(3)] for b in range(2)])
    outp = render(img, kmap, orientation="picture", padding="zero")
    assert np.abs(outp.numpy() - refp).max() < 1e-10


def test_energy_is_conserved():
    """A scene with a dark border wider than the PSFs keeps its total energy exactly (per image and channel)."""
    img = torch.zeros((2, 3, 48, 60), dtype=D)
    img[:, :, 12:36, 12:48] = image(2, 3, 24, 36)
    for blend in ("bilinear", "none"):
        out = render(img, random_psfs(3, 3, 4, 15), padding="zero", blend=blend)
        assert float((out.sum((-1, -2)) - img.sum((-1, -2))).abs().max()) < 1e-12
        assert float(out.min()) > -1e-12


def test_blending_is_exactly_the_per_pixel_model_with_interpolated_psfs():
    """Σ_n (w_n·I) ⊛ K_n equals the direct per-pixel sum with K(s) = Σ_n w_n(s) K_n (bilinear weights at the
    source pixel), computed independently by render_reference."""
    img = image()
    N, M, H, W = 4, 5, 40, 52
    k = random_psfs(3, N, M, 7)
    pos = normalised_grid((N, M))
    cx = (pos[0, :, 0] + 1) / 2 * W - 0.5
    cy = (pos[:, 0, 1] + 1) / 2 * H - 0.5
    wy = _hat_weights(cy, torch.arange(H, dtype=D), "bilinear")
    wx = _hat_weights(cx, torch.arange(W, dtype=D), "bilinear")
    assert torch.allclose(wy.sum(0), torch.ones(H, dtype=D)) and torch.allclose(wx.sum(0), torch.ones(W, dtype=D))
    kern = torch.einsum("nh,mw,cnmab->chwab", wy, wx, k)
    ref = render_reference(img, kern)
    out = render(img, k, orientation="sensor", padding="zero")
    assert float((out - ref).abs().max()) < 1e-13


def seam_case(n, blend, size=72, ks=15):
    """Smoothly varying anisotropic Gaussian PSF (σ 0.7 → 2.6 px, rotating): rendering from an n×n map vs the
    per-pixel ground truth with the exact PSF at every source pixel. Returns the error image (H, W)."""
    g = torch.Generator().manual_seed(3)
    img = torch.rand((1, 1, size, size), generator=g, dtype=D)

    def psf_at(u, v):
        r2 = 0.5 * (u * u + v * v)
        return gaussian_kernel(0.7 + 1.9 * r2, 0.7 + 0.9 * r2, ks, theta=math.atan2(v, u))

    pix = pixel_positions((size, size), orientation="sensor")
    kern = torch.stack([torch.stack([psf_at(float(pix[r, c, 0]), float(pix[r, c, 1])) for c in range(size)])
                        for r in range(size)])[None]
    ref = render_reference(img, kern)
    pos = normalised_grid((n, n))
    kmap = torch.stack([torch.stack([psf_at(float(pos[i, j, 0]), float(pos[i, j, 1])) for j in range(n)])
                        for i in range(n)])[None]
    out = render(img, kmap, orientation="sensor", padding="zero", blend=blend)
    return (out - ref)[0, 0]


def seam_metrics(e, n, m=8):
    """Max |error| and RMS inside the frame (margin m), and the seam ratio: the largest mean |step| of the error
    across a patch border (between columns / rows) over the median step inside the frame (1 = no seam)."""
    H, W = e.shape
    dc = (e[m:-m, 1:] - e[m:-m, :-1]).abs().mean(0)  # dc[c]: step between columns c and c + 1
    dr = (e[1:, m:-m] - e[:-1, m:-m]).abs().mean(1)
    bc = [round(k * W / n) - 1 for k in range(1, n)]
    br = [round(k * H / n) - 1 for k in range(1, n)]
    seam = max(float(dc[bc].max() / dc[m:W - m - 1].median()), float(dr[br].max() / dr[m:H - m - 1].median()))
    inner = e[m:-m, m:-m]
    return float(inner.abs().max()), float(inner.pow(2).mean().sqrt()), seam


def test_seam_error_against_a_per_pixel_reference():
    """Blended maps have no seams: the error against the exact per-pixel model is small, shrinks with the grid,
    and does not step across patch borders (seam ratio ≈ 1–2, like anywhere else); hard patches (the paper's /
    DeepLens's patch convolution) step there (ratio ≈ 7). Measured (72², σ 0.7–2.6 px, image in [0, 1]):
    max |error| blended 3×3 0.043, 5×5 0.020; hard 3×3 0.144, 5×5 0.147; seam ratio blended 1.35 / 1.73, hard
    7.7 / 7.3 (docs/imaging.md)."""
    out = {(n, b): seam_metrics(seam_case(n, b), n) for n in (3, 5) for b in ("bilinear", "none")}
    (b3, _, s3), (b5, _, s5) = out[3, "bilinear"], out[5, "bilinear"]
    (h3, _, t3), (h5, _, t5) = out[3, "none"], out[5, "none"]
    assert b3 < 0.05 and b5 < 0.025 and b5 < 0.6 * b3  # converges with the grid
    assert h3 > 2.5 * b3 and h5 > 5 * b5  # hard patches are much worse ...
    assert s3 < 2.2 and s5 < 2.2  # ... blended: no seam
    assert t3 > 5 and t5 > 5  # hard patches: seams


def test_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(5)
    img = torch.rand((1, 2, 12, 14), generator=g, dtype=D, requires_grad=True)
    k = random_psfs(2, 2, 3, 5).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: render(a, b, padding="reflect"), (img, k), eps=1e-6, atol=1e-7)


def test_gradient_wrt_the_psf_centres_matches_finite_differences():
    """The centres (chief rays: distortion, lateral colour) are differentiable through the warp."""
    g = torch.Generator().manual_seed(6)
    img = torch.rand((1, 1, 10, 12), generator=g, dtype=D)
    k = random_psfs(1, 2, 2, 3)
    nodes = normalised_grid((2, 2)) * torch.tensor([0.6, 0.5], dtype=D)
    cen = (nodes + 0.013 * torch.rand((2, 2, 2), generator=g, dtype=D))[None].requires_grad_(True)
    f = lambda c: render(img, k, centers=c, sensor_size=(1.2, 1.0), padding="replicate")  # noqa: E731
    assert torch.autograd.gradcheck(f, (cen,), eps=1e-7, atol=1e-6)


def test_float32_images_render_in_float32_with_float64_psfs():
    img = image().to(torch.float32)
    k = random_psfs(3, 2, 2, 9).requires_grad_(True)
    out = render(img, k)
    assert out.dtype == torch.float32
    out.sum().backward()
    assert k.grad is not None and k.grad.dtype == D and bool(torch.isfinite(k.grad).all())
    ref = render(img.to(D), k.detach())
    assert float((out.detach().to(D) - ref).abs().max()) < 1e-5


# ---------------------------------------------------------------------------- orientation
def test_picture_orientation_convention():
    """Picture pixel (row 0, column 0) is the scene's top left; the lens inverts, so it lies on the sensor at
    (+x, −y): a PSF that spreads toward sensor +x moves picture content to the left (lower columns) and one
    toward sensor +y moves it down (higher rows). Only nodes on the sensor's +x half carry the shifted PSF."""
    pix = pixel_positions((40, 60))
    assert float(pix[0, 0, 0]) > 0 and float(pix[0, 0, 1]) < 0  # top left of the picture = sensor (+x, −y)
    assert float(pix[-1, -1, 0]) < 0 and float(pix[-1, -1, 1]) > 0
    k = delta(1, 1, 2, 9)
    k[0, 0, 1] = 0
    k[0, 0, 1, 4 + 1, 4 + 3] = 1  # node at u = +0.5 (sensor +x): light moves 3 px toward +x and 1 px toward +y
    img = torch.zeros((1, 1, 40, 60), dtype=D)
    img[0, 0, 20, 8] = 1.0  # left of the picture = sensor +x half
    img[0, 0, 20, 50] = 2.0  # right of the picture = sensor −x half
    out = render(img, k, padding="zero")[0, 0]
    assert float(out[21, 5]) == pytest.approx(1.0) and float(out[20, 50]) == pytest.approx(2.0)
    # the same PSF map in sensor orientation: content at sensor +x (high columns) moves to higher columns
    img_s = img.flip(-1)
    out_s = render(img_s, k, padding="zero", orientation="sensor")[0, 0]
    assert float(out_s[21, 60 - 1 - 8 + 3]) == pytest.approx(1.0)
    assert torch.equal(out_s, out.flip(-1))


def test_distortion_warp_moves_content_to_the_psf_centres():
    """Centres off their nodes: a uniform offset of 2 px toward sensor +x shifts the picture 2 px to the left;
    a radial (barrel-like) offset field moves a point at a node onto that node's centre (to 0.03 px: the
    bilinear resampling of a single pixel under a varying Jacobian, measured 0.018 px)."""
    H, W = 27, 45  # 3×3 nodes on pixel centres
    sensor = (4.5, 2.7)  # 0.1 mm pixels
    half = torch.tensor([2.25, 1.35], dtype=D)
    pos = normalised_grid((3, 3))
    nodes = pos * half
    img = image(1, 1, H, W)
    cen = (nodes + torch.tensor([0.2, 0.0], dtype=D))[None]
    out = render(img, delta(1, 3, 3, 5), centers=cen, sensor_size=sensor, padding="zero")
    assert float((out[..., :, : W - 2] - img[..., :, 2:]).abs().max()) < 1e-12
    scale = 1 - 0.03 * (pos**2).sum(-1, keepdim=True)
    cen = (nodes * scale)[None]
    pix = pixel_positions((H, W)) * half
    for i, j in [(2, 2), (0, 1), (1, 0)]:
        img = torch.zeros((1, 1, H, W), dtype=D)
        r, c = (int(v) for v in torch.nonzero(((pix - nodes[i, j]).abs() < 1e-9).all(-1))[0])
        img[0, 0, r, c] = 1.0
        out = render(img, delta(1, 3, 3, 5), centers=cen, sensor_size=sensor, padding="zero")[0, 0]
        tot = float(out.sum())
        got = [float((out * pix[..., k]).sum()) / tot for k in (0, 1)]
        assert got == pytest.approx(cen[0, i, j].tolist(), abs=3e-3)  # 0.03 px


def test_psfs_are_resampled_to_the_image_pitch_with_their_energy():
    k = random_psfs(1, 1, 1, 16)[0, 0, 0]
    r = resample_psf(k, 3e-3, 7e-3)
    assert r.shape[-1] % 2 == 1 and float(r.sum()) == pytest.approx(1.0, abs=1e-12)
    # centroid kept to a small fraction of the output pixel (box overlaps assign energy to pixel centres)
    def cen(a, p):
        t = (torch.arange(a.shape[-1], dtype=D) - a.shape[-1] // 2) * p
        return float((a.sum(0) * t).sum()), float((a.sum(1) * t).sum())
    assert cen(r, 7e-3) == pytest.approx(cen(k, 3e-3), abs=0.02 * 7e-3)
    # a map at 3 µm PSF pixels on an image of 6 µm pixels: the PSFs are binned 2×2
    img = image(1, 1, 20, 30)
    kmap = random_psfs(1, 1, 1, 8)
    out = render(img, kmap, sensor_size=(0.18, 0.12), pitch=3e-3, padding="zero", orientation="sensor")
    binned = resample_psf(kmap[0, 0, 0], 3e-3, 6e-3)
    ref = render(img, binned, padding="zero", orientation="sensor")
    assert float((out - ref).abs().max()) < 1e-13


# ---------------------------------------------------------------------------- depth
def test_rgbd_layers_interpolate_in_inverse_depth():
    layers = torch.tensor([200.0, 300.0, math.inf], dtype=D)
    dm = torch.tensor([[150.0, 200.0, 240.0], [300.0, 1e4, math.inf]], dtype=D)
    w = depth_layer_weights(dm, layers)
    assert torch.allclose(w.sum(0), torch.ones_like(dm))
    assert torch.allclose(w[:, 0, 0], torch.tensor([1.0, 0, 0], dtype=D))  # nearer than the nearest layer
    t = (1 / 240 - 1 / 300) / (1 / 200 - 1 / 300)
    assert torch.allclose(w[:, 0, 2], torch.tensor([t, 1 - t, 0], dtype=D))
    assert torch.allclose(w[:, 1, 1], torch.tensor([0, 1e-4 / (1 / 300), 1 - 1e-4 * 300], dtype=D))
    img = image(1, 3, 24, 30)
    psf = torch.stack([random_psfs(3, 2, 2, 7, seed=s) for s in range(3)])
    a = render_rgbd(img, torch.full((24, 30), 300.0, dtype=D), psf, layers)
    assert float((a - render(img, psf[1])).abs().max()) < 1e-13
    dm = torch.full((1, 24, 30), 250.0, dtype=D)
    dm[..., 15:] = math.inf
    b = render_rgbd(img, dm, psf, layers, padding="zero")
    wl = depth_layer_weights(dm[:, None], layers)
    ref = sum(render(img * wl[d], psf[d], padding="zero") for d in range(3))
    assert float((b - ref).abs().max()) < 1e-13


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("psf,match", [
    (torch.zeros(2, 2, 2, 5, 5, dtype=D), "2 PSF channels"),
    (torch.full((3, 2, 2, 5, 5), float("nan"), dtype=D), "NaN"),
    (torch.zeros(5, dtype=D), "expected"),
])
def test_bad_psfs_are_errors(psf, match):
    with pytest.raises(ValueError, match=match):
        render(image(), psf)


def test_bad_images_and_options_are_errors():
    k = random_psfs(3, 2, 2, 5)
    with pytest.raises(TypeError, match="float"):
        render(torch.zeros(1, 3, 8, 8, dtype=torch.uint8), k)
    with pytest.raises(ValueError, match="orientation"):
        render(image(), k, orientation="upside")
    with pytest.raises(ValueError, match="sensor_size"):
        render(image(), k, centers=torch.zeros(3, 2, 2, 2, dtype=D))
    with pytest.raises(ValueError, match="extent"):
        render(image(), k, extent=(1, -1, -1, 1))
