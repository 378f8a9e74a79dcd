"""Reconstruction networks in plain torch: a small UNet and a NAFNet-style network (Chen et al. 2022,
"Simple Baselines for Image Restoration": LayerNorm2d, SimpleGate, simplified channel attention).

Both map a blurred image ``(B, C, H, W)`` to a restored one of the same shape and any H, W: the input is
padded (replicate) to a multiple of ``2**depth`` internally and the output cropped back. Both predict a
residual, ``out = x + f(x)``, with the last convolution initialised to zero, so that an untrained network is
exactly the identity (training starts from "no reconstruction" rather than from random output).
The defaults are small enough to train on a CPU; the paper-size settings are in the docstrings.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["UNet", "NAFNet", "LayerNorm2d", "SimpleGate", "NAFBlock", "PSFAwareNet", "DepthSelect", "build_network",
           "count_parameters"]


def count_parameters(module: nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) scalar parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def _pad_to_multiple(x: torch.Tensor, m: int) -> tuple[torch.Tensor, int, int]:
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, h, w


def _zero(conv: nn.Conv2d) -> None:
    nn.init.zeros_(conv.weight)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)


# ------------------------------------------------------------------ UNet
class _DoubleConv(nn.Sequential):
    def __init__(self, cin: int, cout: int):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.2, inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.2, inplace=True))


class UNet(nn.Module):
    """A small UNet: ``depth`` down-sampling levels, ``width·2^level`` channels, skip connections by
    concatenation, bilinear up-sampling; residual output.

    Args:
        channels: image channels in and out (3).
        width: channels at full resolution (default 16; 32–64 for paper-size training).
        depth: number of 2× down-samplings (default 3).
    """

    def __init__(self, channels: int = 3, width: int = 16, depth: int = 3):
        super().__init__()
        if width < 1 or depth < 0:
            raise ValueError(f"UNet needs width >= 1 and depth >= 0, got width={width}, depth={depth}")
        self.depth = depth
        ch = [width * 2 ** i for i in range(depth + 1)]
        self.inc = _DoubleConv(channels, ch[0])
        self.down = nn.ModuleList(_DoubleConv(ch[i], ch[i + 1]) for i in range(depth))
        self.up = nn.ModuleList(_DoubleConv(ch[i + 1] + ch[i], ch[i]) for i in reversed(range(depth)))
        self.out = nn.Conv2d(ch[0], channels, 1)
        _zero(self.out)  # the untrained network is the identity (residual output)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xp, h, w = _pad_to_multiple(x, 2 ** self.depth)
        skips = [self.inc(xp)]
        for d in self.down:
            skips.append(d(F.max_pool2d(skips[-1], 2)))
        y = skips.pop()
        for u in self.up:
            s = skips.pop()
            y = u(torch.cat([F.interpolate(y, size=s.shape[-2:], mode="bilinear", align_corners=False), s], 1))
        return x + self.out(y)[..., :h, :w]


# ------------------------------------------------------------------ NAFNet
class LayerNorm2d(nn.Module):
    """Layer normalisation over the channel dimension of ``(B, C, H, W)`` at every pixel, with per-channel
    affine weight and bias."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mu = x.mean(1, keepdim=True)
        var = (x - mu).pow(2).mean(1, keepdim=True)
        y = (x - mu) / torch.sqrt(var + self.eps)
        return self.weight[:, None, None] * y + self.bias[:, None, None]


class SimpleGate(nn.Module):
    """Split the channels in two halves and multiply them (NAFNet's non-linearity)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, b = x.chunk(2, dim=1)
        return a * b


class NAFBlock(nn.Module):
    """NAFNet block: LN → 1×1 → depthwise 3×3 → SimpleGate → simplified channel attention → 1×1 (+β-scaled
    residual), then LN → 1×1 → SimpleGate → 1×1 (+γ-scaled residual). β, γ start at 0 (identity block)."""

    def __init__(self, c: int, dw_expand: int = 2, ffn_expand: int = 2):
        super().__init__()
        dw = c * dw_expand
        self.norm1 = LayerNorm2d(c)
        self.conv1 = nn.Conv2d(c, dw, 1)
        self.conv2 = nn.Conv2d(dw, dw, 3, padding=1, groups=dw)
        self.sg = SimpleGate()
        self.sca = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(dw // 2, dw // 2, 1))
        self.conv3 = nn.Conv2d(dw // 2, c, 1)
        ffn = c * ffn_expand
        self.norm2 = LayerNorm2d(c)
        self.conv4 = nn.Conv2d(c, ffn, 1)
        self.conv5 = nn.Conv2d(ffn // 2, c, 1)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.sg(self.conv2(self.conv1(self.norm1(x))))
        y = self.conv3(y * self.sca(y))
        x = x + self.beta * y
        y = self.conv5(self.sg(self.conv4(self.norm2(x))))
        return x + self.gamma * y


class NAFNet(nn.Module):
    """NAFNet-style encoder–decoder: strided-conv down-sampling (channels ×2), pixel-shuffle up-sampling,
    additive skips, NAF blocks at every level; residual output.

    Args:
        channels: image channels (3).
        width: channels at full resolution (default 16; the NAFNet paper uses 32–64).
        enc_blocks: NAF blocks per encoder level (its length is the depth; default (1, 1, 1)).
        middle_blocks: blocks at the lowest resolution (default 1).
        dec_blocks: blocks per decoder level (default: same as ``enc_blocks``).
    """

    def __init__(self, channels: int = 3, width: int = 16, enc_blocks=(1, 1, 1), middle_blocks: int = 1,
                 dec_blocks=None):
        super().__init__()
        enc_blocks = tuple(int(b) for b in enc_blocks)
        dec_blocks = enc_blocks if dec_blocks is None else tuple(int(b) for b in dec_blocks)
        if len(dec_blocks) != len(enc_blocks):
            raise ValueError(f"dec_blocks {dec_blocks} must have as many levels as enc_blocks {enc_blocks}")
        if width < 1:
            raise ValueError(f"NAFNet width must be >= 1, got {width}")
        self.depth = len(enc_blocks)
        self.intro = nn.Conv2d(channels, width, 3, padding=1)
        self.ending = nn.Conv2d(width, channels, 3, padding=1)
        _zero(self.ending)  # the untrained network is the identity (residual output)
        self.encoders, self.downs = nn.ModuleList(), nn.ModuleList()
        self.decoders, self.ups = nn.ModuleList(), nn.ModuleList()
        c = width
        for n in enc_blocks:
            self.encoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))
            self.downs.append(nn.Conv2d(c, 2 * c, 2, stride=2))
            c *= 2
        self.middle = nn.Sequential(*[NAFBlock(c) for _ in range(int(middle_blocks))])
        for n in reversed(dec_blocks):
            self.ups.append(nn.Sequential(nn.Conv2d(c, 2 * c, 1, bias=False), nn.PixelShuffle(2)))
            c //= 2
            self.decoders.append(nn.Sequential(*[NAFBlock(c) for _ in range(n)]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xp, h, w = _pad_to_multiple(x, 2 ** self.depth)
        y = self.intro(xp)
        skips = []
        for enc, down in zip(self.encoders, self.downs):
            y = enc(y)
            skips.append(y)
            y = down(y)
        y = self.middle(y)
        for dec, up, s in zip(self.decoders, self.ups, reversed(skips)):
            y = dec(up(y) + s)
        return x + self.ending(y)[..., :h, :w]


def build_network(kind: str, **kw) -> nn.Module:
    """A network by name: ``"unet"`` or ``"nafnet"`` with its keyword arguments."""
    kinds = {"unet": UNet, "nafnet": NAFNet}
    if kind not in kinds:
        raise ValueError(f"unknown network {kind!r}; known: {', '.join(kinds)}")
    return kinds[kind](**kw)


class PSFAwareNet(nn.Module):
    """PSF-aware reconstruction: ``net(deconv(image, psf map))``, a multi-Wiener deconvolution with the current
    PSF map (:class:`~raywave.imaging.deconv.WienerDeconv`, learned regularisation) refined by a network.

    The deconvolution is differentiable w.r.t. the PSFs: in end-to-end training ∂loss/∂PSF flows through it
    as well as through the rendering (so the optics learn to be restorable, not only small).

    With S candidate maps (one per object depth; the camera does not know which blurred the image):
    without ``select`` one filter serves every depth, the expected-error filter over the S maps; with
    ``select`` (a :class:`DepthSelect`) the image is deconvolved with each depth's map alone and the results
    are blended per pixel with the depth weights the image's own evidence gives
    (:mod:`raywave.imaging.depth`).

    Args:
        net: the refinement network (``(B, C, H, W) → (B, C, H, W)``, residual).
        deconv: the deconvolution module.
        select: a :class:`DepthSelect`, or None.
    """

    def __init__(self, net: nn.Module, deconv: nn.Module, select: nn.Module | None = None):
        super().__init__()
        self.net, self.deconv, self.select = net, deconv, select

    def forward(self, image: torch.Tensor, psf: torch.Tensor | None = None, extents=None, depth_centers=None,
                **kw) -> torch.Tensor:
        """``image (B, C, H, W)`` blurred; ``psf (C, N, M, ks, ks)`` the map it was blurred with (or
        ``(S, C, N, M, ks, ks)``: the candidate maps, e.g. one per depth); ``extents``:
        one normalised sensor extent per image (or one for all); ``kw``: positions, centers, sensor_size, pitch
        (:func:`~raywave.imaging.deconv.wiener_deconvolve`); ``depth_centers (S, C, N, M, 2)`` mm: each map's
        PSF centres, for the per-depth deconvolutions of ``select`` (default: ``centers``)."""
        if psf is None:
            raise ValueError("PSFAwareNet needs the PSF map the image was blurred with (psf=...)")
        return self.net(self.deconvolve(image, psf, extents, depth_centers=depth_centers, **kw))

    def deconvolve(self, image, psf, extents=None, depth_centers=None, **kw) -> torch.Tensor:
        """The deconvolution stage alone (the network's input)."""
        if self.select is None or psf.dim() != 6 or psf.shape[0] < 2:
            return self._per_image(self.deconv, image, psf, extents, **kw)
        S = psf.shape[0]
        outs = []
        for s in range(S):
            kws = dict(kw, centers=depth_centers[s]) if depth_centers is not None else kw
            outs.append(self._per_image(self.deconv, image, psf[s:s + 1], extents, **kws))
        kws = {k: v for k, v in kw.items() if k != "centers"}
        w = self._per_image(self.select, image, psf, extents, **kws)  # (B, S, H, W)
        return sum(w[:, s:s + 1] * outs[s] for s in range(S))

    @staticmethod
    def _per_image(fn, image, psf, extents, **kw) -> torch.Tensor:
        """``fn(image, psf, extent=…, **kw)`` with one extent for all images or one per image."""
        if extents is None or (len(extents) == 4 and not hasattr(extents[0], "__len__")):
            return fn(image, psf, **({"extent": tuple(extents)} if extents is not None else {}), **kw)
        if len(extents) != image.shape[0]:
            raise ValueError(f"extents: one per image ({image.shape[0]}), got {len(extents)}")
        return torch.cat([fn(image[i:i + 1], psf, extent=tuple(e), **kw) for i, e in enumerate(extents)])


class DepthSelect(nn.Module):
    """Per-pixel weights of the S depths' maps from the image's own evidence
    (:func:`raywave.imaging.depth.depth_weights`): the image prior (a radial power-spectrum table, a buffer:
    it travels with ``state_dict``), the sensor's noise (``shot``, ``read`` as fractions of full scale) and
    the softmax temperature.

    Args:
        prior: ``(C, bins)`` from :func:`~raywave.imaging.depth.power_spectrum_prior` of training images.
        shot, read: the sensor noise (:class:`~raywave.imaging.sensor.Sensor`).
        temperature: 1 is the Gaussian model's posterior.
    """

    def __init__(self, prior: torch.Tensor, shot: float, read: float, temperature: float = 1.0):
        super().__init__()
        self.register_buffer("prior", torch.as_tensor(prior, dtype=torch.float64).clone())
        self.shot, self.read, self.temperature = float(shot), float(read), float(temperature)

    def forward(self, image: torch.Tensor, psf: torch.Tensor, **kw) -> torch.Tensor:
        """``(B, S, H, W)`` depth weights of ``image (B, C, H, W)`` for the maps ``psf (S, C, N, M, ks, ks)``;
        ``kw``: positions, sensor_size, pitch, extent, orientation."""
        from raywave.imaging.depth import depth_weights

        w = depth_weights(image, psf, self.prior.to(image.dtype), self.shot, self.read,
                          temperature=self.temperature, **kw)
        return w.to(image.dtype)

    def extra_repr(self) -> str:
        return f"shot={self.shot:g}, read={self.read:g}, temperature={self.temperature:g}"
