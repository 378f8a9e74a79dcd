"""The image sensor: pixel grid, Poisson–Gaussian noise, saturation, bit depth, and a display (sRGB) path.

**Signal.** Images are linear, normalised so that 1 is the saturation level at the set gain. A pixel of mean
signal x collects ``x/a`` photo-electrons, a Poisson count (shot noise), plus Gaussian read noise; in
normalised units

    y = a·Poisson(x / a) + σ·n,    n ~ N(0, 1)      →   E[y] = x,   Var[y] = a·x + σ²

then clipped to [0, 1] (full well / ADC range) and quantised to ``2^bits − 1`` levels (adds Δ²/12,
Δ = 1/(2^bits − 1), to the variance away from the clip). In electrons (:meth:`Sensor.from_electrons`): full well
``FW`` e⁻, read noise ``r`` e⁻ rms and analog gain ``g`` (ISO-like: g times fewer electrons for the same output) give
``a = g/FW`` and ``σ = g·r/FW``. :meth:`Sensor.normalised` takes ``a`` and ``σ`` directly.

**Gradients.** ``noise="poisson"`` draws the exact Poisson–Gaussian noise and passes the gradient straight
through (∂y/∂x = 1); ``noise="gaussian"`` uses the differentiable approximation ``x + √(a·x + σ²)·n``;
``noise="none"`` keeps the clip and quantisation only. Rounding uses a straight-through gradient as well.
Randomness comes only from the ``generator`` passed to :meth:`Sensor.forward`.

**Display.** :func:`linear_to_srgb` / :func:`srgb_to_linear` (IEC 61966-2-1) and :func:`apply_gamma`: for PNGs,
not for the physics.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["Sensor", "apply_gamma", "linear_to_srgb", "srgb_to_linear"]


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1] (clipped), for display."""
    x = x.clamp(0, 1)
    lo = 12.92 * x
    hi = 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055
    return torch.where(x <= 0.0031308, lo, hi)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`linear_to_srgb` (sRGB-encoded values in [0, 1] → linear), e.g. for 8-bit photos."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def apply_gamma(x: torch.Tensor, gamma: float = 2.2) -> torch.Tensor:
    """Simple display gamma: ``x^(1/gamma)`` of linear values clipped to [0, 1]."""
    if not gamma > 0:
        raise ValueError(f"gamma must be > 0, got {gamma!r}")
    return x.clamp(0, 1) ** (1.0 / gamma)


def _straight_through(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Value of y, gradient of x."""
    return x + (y - x).detach()


class Sensor(nn.Module):
    """Pixel grid + Poisson–Gaussian noise + saturation + quantisation (see the module docstring).

    Args:
        shot: a, normalised shot-noise scale (variance a·x; 1/a electrons at saturation). 0: no shot noise.
        read: σ, normalised read-noise standard deviation. 0: none.
        bit_depth: ADC bits (None: no quantisation).
        pitch: pixel pitch (mm), optional.
        resolution: (nx, ny) pixels, optional.
        noise: "poisson" (exact, straight-through gradient), "gaussian" (differentiable approximation) or "none".
        clip: clip to [0, 1] (saturation; the lower end: no negative digital numbers).
    """

    def __init__(self, shot: float = 1e-4, read: float = 2e-4, bit_depth: int | None = 10, pitch: float | None = None,
                 resolution=None, noise: str = "poisson", clip: bool = True):
        super().__init__()
        for name, v in (("shot", shot), ("read", read)):
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"Sensor: {name} noise must be a finite number >= 0, got {v!r}")
        if bit_depth is not None and not (1 <= int(bit_depth) <= 32):
            raise ValueError(f"Sensor: bit_depth must be 1 … 32 bits (or None), got {bit_depth!r}")
        if noise not in ("poisson", "gaussian", "none"):
            raise ValueError(f"Sensor: noise must be 'poisson', 'gaussian' or 'none', got {noise!r}")
        if pitch is not None and not float(pitch) > 0:
            raise ValueError(f"Sensor: pixel pitch must be > 0 mm, got {pitch!r}")
        if resolution is not None:
            resolution = tuple(int(v) for v in resolution)
            if len(resolution) != 2 or min(resolution) < 1:
                raise ValueError(f"Sensor: resolution is (nx, ny) pixels, got {resolution!r}")
        self.shot = float(shot)
        self.read = float(read)
        self.bit_depth = None if bit_depth is None else int(bit_depth)
        self.pitch = None if pitch is None else float(pitch)
        self.resolution = resolution
        self.noise = noise
        self.clip = bool(clip)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_electrons(cls, full_well: float = 10_000.0, read_noise: float = 2.0, gain: float = 1.0, **kw) -> "Sensor":
        """Sensor from physical units: full well (e⁻), read noise (e⁻ rms), analog gain (≥ 0, 1 = base ISO)."""
        if not (full_well > 0 and gain > 0 and read_noise >= 0):
            raise ValueError(f"Sensor.from_electrons: full_well and gain must be > 0 and read_noise >= 0, got "
                             f"{full_well!r}, {gain!r}, {read_noise!r}")
        return cls(shot=gain / full_well, read=gain * read_noise / full_well, **kw)

    @classmethod
    def normalised(cls, shot: float, read: float, **kw) -> "Sensor":
        """Sensor from the normalised noise model Var[y] = shot·x + read²."""
        return cls(shot=shot, read=read, **kw)

    @classmethod
    def from_lens(cls, lens, **kw) -> "Sensor":
        """Pitch and resolution of a lens's sensor (``lens.sensor_size`` / ``sensor_resolution``)."""
        res = getattr(lens, "sensor_resolution", None)
        return cls(pitch=getattr(lens, "pixel_pitch", None), resolution=res, **kw)

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[float, float] | None:
        """(w, h) mm, when pitch and resolution are known."""
        if self.pitch is None or self.resolution is None:
            return None
        return self.pitch * self.resolution[0], self.pitch * self.resolution[1]

    @property
    def step(self) -> float | None:
        """Quantisation step Δ = 1/(2^bits − 1) (None without quantisation)."""
        return None if self.bit_depth is None else 1.0 / (2 ** self.bit_depth - 1)

    def variance(self, x: torch.Tensor) -> torch.Tensor:
        """The model's noise variance a·x + σ² (before clip and quantisation)."""
        return self.shot * x.clamp_min(0) + self.read**2

    # ------------------------------------------------------------------ the forward model
    def add_noise(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Poisson–Gaussian noise per ``noise`` (no clip, no quantisation)."""
        if self.noise == "none" or (self.shot == 0 and self.read == 0):
            return x
        # the draws are made on the generator's device (a CPU generator with a CUDA image: the same noise as on
        # the CPU, so a seeded run does not depend on where it runs) and then moved to the image's device
        dev = generator.device if generator is not None else x.device
        if self.noise == "gaussian":
            n = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=dev).to(x.device)
            return x + torch.sqrt(self.variance(x)) * n
        xd = x.detach().clamp_min(0)
        y = xd
        if self.shot > 0:
            y = self.shot * torch.poisson((xd / self.shot).to(dev), generator=generator).to(x.device)
        if self.read > 0:
            y = y + self.read * torch.randn(x.shape, generator=generator, dtype=x.dtype, device=dev).to(x.device)
        return _straight_through(x, y)

    def quantise(self, y: torch.Tensor) -> torch.Tensor:
        """Round to the ADC's levels (straight-through gradient)."""
        if self.bit_depth is None:
            return y
        levels = 2 ** self.bit_depth - 1
        return _straight_through(y, torch.round(y * levels) / levels)

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Raw normalised image: noise, clip to [0, 1], quantisation. ``x`` linear, any shape."""
        if not x.is_floating_point():
            raise TypeError("Sensor: give a float image (linear, 1 = saturation)")
        y = self.add_noise(x, generator)
        if self.clip:
            y = y.clamp(0, 1)
        return self.quantise(y)

    @staticmethod
    def display(raw: torch.Tensor, transfer: str | float = "srgb") -> torch.Tensor:
        """Display-encoded image: ``"srgb"`` (default), ``"linear"`` or a gamma value (e.g. 2.2)."""
        if transfer == "srgb":
            return linear_to_srgb(raw)
        if transfer == "linear":
            return raw.clamp(0, 1)
        return apply_gamma(raw, float(transfer))

    def extra_repr(self) -> str:
        s = f"shot={self.shot:g}, read={self.read:g}, bit_depth={self.bit_depth}, noise={self.noise!r}"
        if self.pitch is not None:
            s += f", pitch={self.pitch * 1e3:g} µm"
        if self.resolution is not None:
            s += f", resolution={self.resolution}"
        return s
