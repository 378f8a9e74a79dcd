"""Spatially-varying image simulation from a PSF map (paper §2.3), differentiable w.r.t. image and PSFs.

**Model.** A source pixel at sensor position s spreads its energy with the PSF of its own field,
``out(x) = Σ_s I(s)·K_s(x − s)``. The PSFs are known on an N×M grid of nodes; between nodes ``K_s`` is the
**bilinear interpolation** of the four surrounding node PSFs (constant beyond the outermost nodes). Because
bilinear weights ``w_n(s)`` form a partition of unity, ``out = Σ_n (w_n·I) ⊛ K_n``: the input is split into
overlapping smooth "tent" pieces, each convolved (FFT, batched over nodes, channels and images) with its node's
PSF, and the pieces are added back (overlap-add). This is *exactly* the per-pixel model with interpolated PSFs
(tested against a direct per-pixel sum, :func:`render_reference`), so

* there are no seams: the result is continuous across patch borders (``blend="none"`` gives the paper's /
  DeepLens's hard patches for comparison, whose seams are measured in the tests and docs/imaging.md);
* energy is conserved (each piece keeps its energy, PSFs sum to 1; only light crossing the frame is lost);
* a spatially uniform map is one FFT convolution, a delta PSF the identity.

Each piece is convolved on its support window only (about 2 cells + the kernel), so the cost is ~4 image-sized
FFT convolutions whatever N×M.

**Orientation.** ``orientation="picture"`` (default): images are *upright pictures*, as image files store them
and as a camera outputs them: row 0 is the top of the scene, column 0 its left. A real lens inverts the image
(the top of the scene lands at sensor −y, its left at sensor +x: field angle +θy images at +y) and the camera
reads the sensor out rotated by 180°, so picture pixel (row r, column c) of an H×W picture is the sensor point

    x = u·w/2, y = v·h/2,   u = u1 − (c + ½)/W·(u1 − u0),   v = v0 + (r + ½)/H·(v1 − v0)

for the normalised ``extent = (u0, u1, v0, v1)`` the picture covers (default the whole sensor, (−1, 1, −1, 1)).
As an array the picture is the sensor's ``[iy, ix]`` array with the x axis reversed (rows already run along +y
because row 0 is the top of the scene = sensor −y). The output has the same orientation as the input (the
simulated photograph of the input scene). ``orientation="sensor"``: arrays are ``[iy, ix]`` as PSFs are
(``u = u0 + (c + ½)/W·(u1 − u0)``).

**Pixels.** The input is the ideal image on the sensor at the image's own pixel pitch
(``(u1 − u0)·w/2/W`` × ``(v1 − v0)·h/2/H`` mm). When ``pitch`` (the PSFs' pixel pitch) and ``sensor_size`` are
given and differ from it, the PSFs are resampled to the image pitch by exact pixel-area overlap (energy kept);
without them the image pixels are taken to be PSF pixels.

**Distortion, lateral colour, depth.** With ``centers`` (the map's chief-ray positions, mm) the image is first
warped by the displacement ``centers − node positions`` (interpolated bilinearly between nodes, per channel;
bilinear resampling), then blurred with the PSFs (which are centred on their chief rays).

**Depth.** :func:`render` simulates one object plane; :func:`render_rgbd` an RGB-D scene by depth layers:
per-pixel weights from linear interpolation in inverse depth (1/z; ``inf`` → 0) between the two nearest
layers of the map, clamped outside, each layer rendered with its own PSFs and the layers added. Occlusion at
depth edges is not modelled (layers add, as in the common layered approximation).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["depth_layer_weights", "pixel_positions", "render", "render_map", "render_reference", "render_rgbd",
           "resample_psf"]

_PADDING = {"reflect": "reflect", "zero": "constant", "replicate": "replicate"}
_GRID_PADDING = {"reflect": "reflection", "zero": "zeros", "replicate": "border"}


# ---------------------------------------------------------------------------- helpers
def _fast(n: int) -> int:
    from raywave.wave.propagation import fast_fft_size

    return fast_fft_size(n)


def _hat_weights(nodes: torch.Tensor, coords: torch.Tensor, blend: str) -> torch.Tensor:
    """``(n, L)`` weights of ``n`` ascending node coordinates at pixel coordinates ``coords`` (L,).

    ``bilinear``: tent functions, constant beyond the end nodes (a partition of unity).
    ``none``: 1 for the nearest node (hard patches)."""
    n = nodes.numel()
    if n == 1:
        return torch.ones((1, coords.numel()), dtype=coords.dtype, device=coords.device)
    if blend == "none":
        idx = (coords[None, :] - nodes[:, None]).abs().argmin(0)
        return F.one_hot(idx, n).T.to(coords.dtype)
    t = coords.clamp(float(nodes[0]), float(nodes[-1]))
    k = torch.searchsorted(nodes, t, right=True).clamp(1, n - 1)  # t in [nodes[k-1], nodes[k]]
    a, b = nodes[k - 1], nodes[k]
    f = (t - a) / (b - a)
    w = torch.zeros((n, coords.numel()), dtype=coords.dtype, device=coords.device)
    cols = torch.arange(coords.numel(), device=coords.device)
    w[k - 1, cols] += 1 - f
    w[k, cols] += f
    return w


def _windows(weights: torch.Tensor):
    """For (n, L) weights: ``lo`` (n,) window starts, common window length, and which nodes have support."""
    nz = weights != 0
    has = nz.any(1)
    L = weights.shape[1]
    idx = torch.arange(L, device=weights.device)
    first = torch.where(nz, idx, L).amin(1)
    last = torch.where(nz, idx, -1).amax(1)
    length = int((last - first + 1)[has].max()) if bool(has.any()) else 1
    lo = torch.minimum(first.clamp(max=L - 1), torch.tensor(L - length, device=weights.device))
    return lo.clamp(min=0), length, has


def _node_coords(positions: torch.Tensor, extent, shape, orientation: str):
    """Node pixel coordinates along rows (N,) and columns (M,) in *sensor orientation* arrays."""
    u0, u1, v0, v1 = extent
    H, W = shape
    u = positions[0, :, 0].to(torch.float64)
    v = positions[:, 0, 1].to(torch.float64)
    if not (torch.allclose(positions[..., 0], u[None, :].expand_as(positions[..., 0]).to(positions.dtype))
            and torch.allclose(positions[..., 1], v[:, None].expand_as(positions[..., 1]).to(positions.dtype))):
        raise ValueError("positions: the nodes must form a grid (positions[i, j] = (u_j, v_i))")
    if bool((u[1:] <= u[:-1]).any()) or bool((v[1:] <= v[:-1]).any()):
        raise ValueError("positions: node coordinates must increase along columns (u) and rows (v)")
    cx = (u - u0) / (u1 - u0) * W - 0.5
    cy = (v - v0) / (v1 - v0) * H - 0.5
    return cy, cx


def resample_psf(psf: torch.Tensor, pitch_in: float, pitch_out) -> torch.Tensor:
    """PSFs ``(..., ks, ks)`` of pixel pitch ``pitch_in`` (mm) on pixels of ``pitch_out`` (mm, or (px, py)).

    Exact pixel-area overlap (the energy of every input pixel is shared among the output pixels it overlaps, so
    sums are kept); the centre of pixel ``[ks//2, ks//2]`` stays at the centre of output pixel ``[ky//2, kx//2]``.
    Returns ``(..., ky, kx)`` (odd sizes covering the input)."""
    from raywave.wave.propagation import pixel_integrate

    qx, qy = (float(pitch_out), float(pitch_out)) if not hasattr(pitch_out, "__len__") else map(float, pitch_out)
    ky_in, kx_in = psf.shape[-2:]
    p = float(pitch_in)

    def size(k_in, q):
        reach = max(k_in // 2 + 0.5, k_in - 1 - k_in // 2 + 0.5) * p  # mm from the centre to the far edge
        return 2 * max(0, math.ceil(reach / q - 0.5)) + 1

    ky, kx = size(ky_in, qy), size(kx_in, qx)
    return pixel_integrate(psf, p, (qx, qy), (-(kx_in // 2) * p, -(ky_in // 2) * p),
                           (-(kx // 2) * qx, -(ky // 2) * qy), (ky, kx), mode="sum", kernel="box")


def _check_image(image: torch.Tensor) -> torch.Tensor:
    if not torch.is_tensor(image) or not image.is_floating_point():
        raise TypeError("image: give a float tensor (B, C, H, W) or (C, H, W) (convert uint8 images to float first)")
    if image.ndim not in (3, 4):
        raise ValueError(f"image: expected (B, C, H, W) or (C, H, W), got shape {tuple(image.shape)}")
    if not bool(torch.isfinite(image).all()):
        raise ValueError("image: contains NaN or inf")
    return image if image.ndim == 4 else image[None]


def _check_psf(psf: torch.Tensor, channels: int) -> torch.Tensor:
    """→ (C, N, M, ky, kx)."""
    if not torch.is_tensor(psf):
        psf = torch.as_tensor(psf)
    if psf.ndim == 2:
        psf = psf[None, None, None]
    elif psf.ndim == 3:
        psf = psf[:, None, None]
    elif psf.ndim == 4:
        psf = psf[None]
    if psf.ndim != 5:
        raise ValueError(f"psf: expected (C, N, M, ks, ks) (or (N, M, ks, ks), (C, ks, ks), (ks, ks)), got shape "
                         f"{tuple(psf.shape)}")
    if psf.shape[0] == 1 and channels > 1:
        psf = psf.expand(channels, *psf.shape[1:])
    if psf.shape[0] != channels:
        raise ValueError(f"psf: {psf.shape[0]} PSF channels for an image of {channels} channels")
    if not bool(torch.isfinite(psf.detach()).all()):
        raise ValueError("psf: contains NaN or inf")
    return psf


def _image_pitch(extent, sensor_size, shape):
    u0, u1, v0, v1 = extent
    w, h = sensor_size
    H, W = shape
    return (u1 - u0) * 0.5 * w / W, (v1 - v0) * 0.5 * h / H


def pixel_positions(shape, extent=(-1.0, 1.0, -1.0, 1.0), orientation: str = "picture", dtype=torch.float64,
                    device=None) -> torch.Tensor:
    """``(H, W, 2)`` normalised sensor positions (u, v) of the pixel centres of an H×W image covering ``extent``
    (see the module docstring; multiply by (w/2, h/2) for mm). ``orientation="picture"``: column 0 is sensor +x
    (the scene's left), row 0 sensor −y (the scene's top)."""
    H, W = (int(v) for v in shape)
    u0, u1, v0, v1 = (float(v) for v in extent)
    c = (torch.arange(W, dtype=dtype, device=device) + 0.5) / W
    r = (torch.arange(H, dtype=dtype, device=device) + 0.5) / H
    if orientation == "picture":
        u = u1 - c * (u1 - u0)
    elif orientation == "sensor":
        u = u0 + c * (u1 - u0)
    else:
        raise ValueError(f"orientation must be 'picture' or 'sensor', got {orientation!r}")
    v = v0 + r * (v1 - v0)
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), -1)


# ---------------------------------------------------------------------------- the renderer
def render(image: torch.Tensor, psf: torch.Tensor, *, positions: torch.Tensor | None = None,
           centers: torch.Tensor | None = None, sensor_size=None, pitch: float | None = None,
           extent=(-1.0, 1.0, -1.0, 1.0), orientation: str = "picture", padding: str = "reflect",
           blend: str = "bilinear") -> torch.Tensor:
    """Blur ``image`` with the spatially-varying PSFs of a map (one object plane).

    Args:
        image: ``(B, C, H, W)`` or ``(C, H, W)`` float (linear irradiance); orientation per ``orientation``.
        psf: ``(C, N, M, ks, ks)`` node PSFs (``[iy, ix]``, centre pixel ``[ks//2, ks//2]``, e.g.
            ``psf_map.psf[d]`` with one wavelength per channel); ``(N, M, ks, ks)`` shared by all channels,
            ``(C, ks, ks)`` or ``(ks, ks)`` for a uniform PSF.
        positions: ``(N, M, 2)`` normalised node positions (default :func:`~raywave.imaging.psfmap.normalised_grid`).
        centers: ``(C, N, M, 2)`` mm chief-ray positions of the node PSFs (distortion / lateral colour warp; needs
            ``sensor_size``).
        sensor_size: (w, h) mm that the normalised positions refer to.
        pitch: the PSFs' pixel pitch (mm): with ``sensor_size``, PSFs are resampled to the image's pixel pitch.
        extent: ``(u0, u1, v0, v1)`` normalised sensor region the image covers.
        orientation: "picture" (upright photo, default) or "sensor" (``[iy, ix]``); see the module docstring.
        padding: the scene beyond the frame: "reflect" (default), "replicate" or "zero" (energy test).
        blend: "bilinear" (default; seam-free) or "none" (hard patches, for comparison).

    Returns:
        the blurred image, same shape, dtype and orientation as ``image``; differentiable w.r.t. the image, the
        PSFs and the centres.
    """
    if blend not in ("bilinear", "none"):
        raise ValueError(f"blend must be 'bilinear' or 'none', got {blend!r}")
    squeeze = image.ndim == 3
    x, k, positions, sensor_size, extent, cy, cx = prepare_map_arguments(
        image, psf, positions, sensor_size, pitch, extent, orientation, padding)
    flip = orientation == "picture"
    if centers is not None:
        if sensor_size is None:
            raise ValueError("centers: give sensor_size (mm) to convert the PSF centres to pixels")
        x = _warp(x, centers, positions, sensor_size, extent, cy, cx, padding)
    out = _blur(x, k, cy, cx, padding, blend)
    if flip:
        out = out.flip(-1)
    return out[0] if squeeze else out


def prepare_map_arguments(image, psf, positions, sensor_size, pitch, extent, orientation, padding):
    """Validate and normalise the arguments shared by :func:`render` and
    :func:`~raywave.imaging.deconv.wiener_deconvolve`.

    Returns ``(x, k, positions, sensor_size, extent, cy, cx)``: the image as ``(B, C, H, W)`` in **sensor**
    orientation (flipped from "picture"), the node kernels ``(C, N, M, ks, ks)`` resampled to the image's pixel
    pitch (when ``pitch`` and ``sensor_size`` are given), the ``(N, M, 2)`` node positions, the sensor size (w, h)
    mm or None, the extent as a 4-tuple and the node pixel coordinates ``cy (N,)``, ``cx (M,)``."""
    x = _check_image(image)
    B, C, H, W = x.shape
    k = _check_psf(psf, C).to(x.dtype)
    N, M = k.shape[1:3]
    if orientation not in ("picture", "sensor"):
        raise ValueError(f"orientation must be 'picture' or 'sensor', got {orientation!r}")
    if padding not in _PADDING:
        raise ValueError(f"padding must be one of {sorted(_PADDING)}, got {padding!r}")
    extent = tuple(float(v) for v in extent)
    if len(extent) != 4 or not (extent[1] > extent[0] and extent[3] > extent[2]):
        raise ValueError(f"extent: give (u0, u1, v0, v1) with u1 > u0 and v1 > v0, got {extent!r}")
    if positions is None:
        from raywave.imaging.psfmap import normalised_grid

        positions = normalised_grid((N, M), device=x.device)
    positions = torch.as_tensor(positions).detach().to(device=x.device)
    if tuple(positions.shape) != (N, M, 2):
        raise ValueError(f"positions: expected ({N}, {M}, 2) for {N}×{M} node PSFs, got {tuple(positions.shape)}")
    if sensor_size is not None:
        sensor_size = tuple(float(v) for v in sensor_size)
    if pitch is not None and sensor_size is not None:
        qx, qy = _image_pitch(extent, sensor_size, (H, W))
        if abs(qx / pitch - 1) > 1e-9 or abs(qy / pitch - 1) > 1e-9:
            k = resample_psf(k, pitch, (qx, qy))
    if orientation == "picture":
        x = x.flip(-1)  # picture → sensor orientation [iy, ix]
    cy, cx = _node_coords(positions, extent, (H, W), orientation)
    return x, k, positions, sensor_size, extent, cy.to(x.dtype), cx.to(x.dtype)


_WARP_ITERATIONS = 4


def _node_grid(nodes: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates ``t`` → grid_sample coordinates (align_corners=True) of the node array: the fractional
    node index (piecewise linear between the ascending ``nodes``, clamped), scaled to [−1, 1]."""
    n = nodes.numel()
    if n == 1:
        return torch.zeros_like(t)
    tc = t.clamp(float(nodes[0]), float(nodes[-1]))
    k = torch.searchsorted(nodes, tc.detach().contiguous(), right=True).clamp(1, n - 1)
    a, b = nodes[k - 1], nodes[k]
    frac = (k - 1).to(t.dtype) + (tc - a) / (b - a)
    return 2 * frac / (n - 1) - 1


def _node_offsets(x, centers, positions, sensor_size, extent):
    """The displacement ``centers − node positions`` (C, N, M, 2) in image pixels for the image ``x`` (B, C, H, W)
    (``centers`` (N, M, 2) or (C, N, M, 2) mm, ``positions`` (N, M, 2) normalised node positions, ``sensor_size``
    (w, h) mm), or None where every node's PSF sits on its node (nothing to move)."""
    _, C, H, W = x.shape
    cen = torch.as_tensor(centers).to(device=x.device, dtype=x.dtype)
    if cen.ndim == 3:
        cen = cen[None].expand(C, *cen.shape)
    if cen.shape != (C,) + tuple(positions.shape):
        raise ValueError(f"centers: expected ({C}, {positions.shape[0]}, {positions.shape[1]}, 2) mm, got "
                         f"{tuple(cen.shape)}")
    w, h = sensor_size
    nodes_mm = positions.to(x.dtype) * torch.tensor([0.5 * w, 0.5 * h], dtype=x.dtype, device=x.device)
    qx, qy = _image_pitch(extent, sensor_size, (H, W))
    off = (cen - nodes_mm) / torch.tensor([qx, qy], dtype=x.dtype, device=x.device)  # (C, N, M, 2) pixels
    return off if bool(off.detach().abs().gt(1e-9).any()) else None


def _warp(x, centers, positions, sensor_size, extent, cy, cx, padding):
    """Move the image content by the displacement ``centers − node positions`` (sensor orientation)."""
    B, C, H, W = x.shape
    off = _node_offsets(x, centers, positions, sensor_size, extent)
    if off is None:
        return x
    # the source of output pixel p is s with s + D(s) = p (D interpolated bilinearly between the nodes):
    # fixed-point iterations s ← p − D(s) from s = p (error ~ |∇D|^k, |∇D| ≪ 1)
    off_img = off.permute(0, 3, 1, 2)  # (C, 2, N, M)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=x.dtype, device=x.device),
                            torch.arange(W, dtype=x.dtype, device=x.device), indexing="ij")
    sx, sy = xx.expand(C, H, W), yy.expand(C, H, W)
    for _ in range(_WARP_ITERATIONS):
        g = torch.stack([_node_grid(cx, sx), _node_grid(cy, sy)], -1)  # (C, H, W, 2) node-index coordinates
        disp = F.grid_sample(off_img, g, mode="bilinear", padding_mode="border", align_corners=True)  # (C, 2, H, W)
        sx, sy = xx - disp[:, 0], yy - disp[:, 1]
    grid = torch.stack([(2 * sx + 1) / W - 1, (2 * sy + 1) / H - 1], -1)  # (C, H, W, 2)
    grid = grid[None].expand(B, C, H, W, 2).reshape(B * C, H, W, 2)
    out = F.grid_sample(x.reshape(B * C, 1, H, W), grid, mode="bilinear", padding_mode=_GRID_PADDING[padding],
                        align_corners=False)
    return out.reshape(B, C, H, W)


def _blur(x, k, cy, cx, padding, blend):
    """Partition-of-unity overlap-add FFT convolution in sensor orientation. x (B, C, H, W), k (C, N, M, ky, kx)."""
    B, C, H, W = x.shape
    N, M, ky, kx = k.shape[1:]
    py0, py1 = ky // 2, ky - 1 - ky // 2
    px0, px1 = kx // 2, kx - 1 - kx // 2
    mode = _PADDING[padding]
    if mode == "reflect" and (max(py0, py1) >= H or max(px0, px1) >= W):
        mode = "replicate"  # the PSF is larger than the image: reflection is undefined
    xp = F.pad(x, (px0, px1, py0, py1), mode=mode) if (py0 or py1 or px0 or px1) else x
    Hp, Wp = xp.shape[-2:]
    dev, dt = x.device, x.dtype
    wy = _hat_weights(cy, torch.arange(Hp, dtype=dt, device=dev) - py0, blend)  # (N, Hp)
    wx = _hat_weights(cx, torch.arange(Wp, dtype=dt, device=dev) - px0, blend)  # (M, Wp)
    lo_y, Ly, has_y = _windows(wy)
    lo_x, Lx, has_x = _windows(wx)
    iy = torch.nonzero(has_y).reshape(-1)
    ix = torch.nonzero(has_x).reshape(-1)
    wy, lo_y, wx, lo_x = wy[iy], lo_y[iy], wx[ix], lo_x[ix]
    k = k[:, iy][:, :, ix]  # (C, n, m, ky, kx)
    ry = lo_y[:, None] + torch.arange(Ly, device=dev)  # (n, Ly) padded row indices
    rx = lo_x[:, None] + torch.arange(Lx, device=dev)  # (m, Lx)
    win = xp[:, :, ry[:, None, :, None], rx[None, :, None, :]]  # (B, C, n, m, Ly, Lx)
    wwy = torch.gather(wy, 1, ry)  # (n, Ly)
    wwx = torch.gather(wx, 1, rx)  # (m, Lx)
    win = win * (wwy[:, None, :, None] * wwx[None, :, None, :])
    Ay, Ax = Ly + ky - 1, Lx + kx - 1
    fy, fx = _fast(Ay), _fast(Ax)
    spec = torch.fft.rfft2(win, s=(fy, fx)) * torch.fft.rfft2(k, s=(fy, fx))
    full = torch.fft.irfft2(spec, s=(fy, fx))[..., :Ay, :Ax]  # (B, C, n, m, Ay, Ax)
    Hc, Wc = Hp + ky - 1, Wp + kx - 1
    oy = lo_y[:, None] + torch.arange(Ay, device=dev)  # canvas rows (n, Ay)
    ox = lo_x[:, None] + torch.arange(Ax, device=dev)
    idx = (oy[:, None, :, None] * Wc + ox[None, :, None, :]).reshape(-1)
    canvas = torch.zeros((B, C, Hc * Wc), dtype=dt, device=dev)
    canvas = canvas.index_add(2, idx, full.reshape(B, C, -1))
    canvas = canvas.reshape(B, C, Hc, Wc)
    # canvas index = padded source row + kernel row = output padded row + ky//2; output row r ↔ padded r + py0
    return canvas[..., py0 + ky // 2: py0 + ky // 2 + H, px0 + kx // 2: px0 + kx // 2 + W]


def render_map(image: torch.Tensor, psf_map, depth_index: int = 0, use_centers: bool = True, **kw) -> torch.Tensor:
    """:func:`render` with the PSFs of one depth of a :class:`~raywave.imaging.psfmap.PSFMap` (its W wavelengths
    or channels = the image's channels), its node positions, pitch, sensor size and (``use_centers``) centres."""
    d = int(depth_index)
    if use_centers and psf_map.sensor_size is None:
        raise ValueError("render_map: the PSF map has no sensor size, so its centres cannot be used "
                         "(use_centers=False)")
    return render(image, psf_map.psf[d], positions=psf_map.positions,
                  centers=psf_map.centers[d] if use_centers else None, sensor_size=psf_map.sensor_size,
                  pitch=psf_map.pitch, **kw)


# ---------------------------------------------------------------------------- depth
def depth_layer_weights(depth: torch.Tensor, layers) -> torch.Tensor:
    """Per-pixel weights ``(D, ...)`` of the depth layers ``layers`` (D,) mm for a depth map ``depth`` (...) mm.

    Linear interpolation in inverse depth 1/z (``inf`` → 0) between the two nearest layers, clamped outside
    their range; the weights are ≥ 0 and sum to 1 at every pixel."""
    z = torch.as_tensor(layers, dtype=torch.float64, device="cpu").reshape(-1)
    if z.numel() == 0 or bool((z <= 0).any()):
        raise ValueError(f"layers: give depths > 0 mm (or inf), got {z.tolist()}")
    dm = torch.as_tensor(depth)
    if not bool((dm > 0).all()):
        raise ValueError("depth map: depths must be > 0 mm (or inf)")
    inv = (1.0 / z).to(device=dm.device, dtype=dm.dtype if dm.is_floating_point() else torch.float64)
    order = torch.argsort(inv)
    inv_s = inv[order]
    t = (1.0 / dm.to(inv.dtype)).clamp(float(inv_s[0]), float(inv_s[-1]))
    w_sorted = _hat_weights(inv_s, t.reshape(-1), "bilinear")  # (D, P)
    w = torch.empty_like(w_sorted)
    w[order] = w_sorted
    return w.reshape((z.numel(),) + tuple(dm.shape))


def render_rgbd(image: torch.Tensor, depth: torch.Tensor, psf: torch.Tensor, layers, *, centers=None,
                **kw) -> torch.Tensor:
    """Render an RGB-D scene by depth layers.

    Args:
        image: ``(B, C, H, W)`` (or (C, H, W)).
        depth: ``(B, 1, H, W)``, ``(B, H, W)`` or ``(H, W)`` object distance per pixel (mm; ``inf`` allowed),
            in the image's orientation.
        psf: ``(D, C, N, M, ks, ks)`` PSFs of the D layers (e.g. ``psf_map.psf``).
        layers: ``(D,)`` mm, the layers' depths (e.g. ``psf_map.depths``).
        centers: ``(D, C, N, M, 2)`` mm or None.
        kw: as :func:`render` (positions, sensor_size, pitch, extent, orientation, padding, blend).
    """
    squeeze = image.ndim == 3
    x = _check_image(image)
    B, C, H, W = x.shape
    dm = torch.as_tensor(depth, device=x.device)
    if dm.ndim == 2:
        dm = dm[None, None].expand(B, 1, H, W)
    elif dm.ndim == 3:
        dm = dm[:, None]
    if dm.shape[-2:] != (H, W) or dm.shape[1] != 1:
        raise ValueError(f"depth: expected (B, 1, {H}, {W}) / (B, {H}, {W}) / ({H}, {W}), got {tuple(depth.shape)}")
    z = torch.as_tensor(layers, dtype=torch.float64).reshape(-1)
    if psf.ndim != 6 or psf.shape[0] != z.numel():
        raise ValueError(f"psf: expected (D, C, N, M, ks, ks) with D = {z.numel()} layers, got {tuple(psf.shape)}")
    wts = depth_layer_weights(dm.to(torch.float64), z).to(x.dtype)  # (D, B, 1, H, W)
    out = 0
    for d in range(z.numel()):
        if not bool(wts[d].any()):
            continue
        out = out + render(x * wts[d], psf[d], centers=None if centers is None else centers[d], **kw)
    if not torch.is_tensor(out):
        out = torch.zeros_like(x)
    return out[0] if squeeze else out


# ---------------------------------------------------------------------------- per-pixel reference
def render_reference(image: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """Direct per-pixel spatially-varying blur (slow; the ground truth for tests), sensor orientation, zero
    padding: ``out[y, x] = Σ_s image[s]·kernels[s][y − s + ks//2]``.

    Args:
        image: ``(B, C, H, W)``.
        kernels: ``(C, H, W, ky, kx)``: the PSF of every *source* pixel.
    """
    B, C, H, W = image.shape
    ky, kx = kernels.shape[-2:]
    out = torch.zeros((B, C, H + ky - 1, W + kx - 1), dtype=image.dtype, device=image.device)
    for a in range(ky):
        for b in range(kx):
            out[:, :, a:a + H, b:b + W] += image * kernels[None, :, :, :, a, b]
    return out[:, :, ky // 2: ky // 2 + H, kx // 2: kx // 2 + W]
