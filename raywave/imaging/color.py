"""Colour: the wavelengths that stand for each colour channel and how they combine (paper §2.2).

Every colour channel is represented by three wavelengths (µm), by default

========  ====================
channel   wavelengths (µm)
========  ====================
R         0.62, 0.66, 0.70
G         0.50, 0.53, 0.56
B         0.45, 0.47, 0.49
========  ====================

* **Training** (:meth:`ColorSpec.sample`): one wavelength drawn at random per channel (uniformly, through an
  explicit ``torch.Generator``); the same draw for every field of a PSF map, so one map = one RGB PSF per field.
* **Evaluation** (:meth:`ColorSpec.average`): the PSFs of all three wavelengths of a channel averaged with the
  sensor-response weights. **Default weights: equal (1/3 each)**: the paper weights the three wavelengths the
  same because the real broadband response of its CMOS sensor (OmniVision OV2710) is unknown. Give
  ``weights`` (one row of three non-negative numbers per channel; normalised to sum 1) for a measured response.

Averaging PSFs of different wavelengths first brings them into one frame: each PSF is centred on its own chief
ray (lateral colour moves it), so it is shifted by ``(center_w − center_avg) / pitch`` pixels (bilinear,
energy-conserving) before the weighted sum; the channel's centre is the weighted mean of the centres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["DEFAULT_CHANNEL_WAVELENGTHS", "ColorSpec", "shift_psf"]

#: The paper's wavelengths (µm) per channel, in R, G, B order.
DEFAULT_CHANNEL_WAVELENGTHS = ((0.62, 0.66, 0.70), (0.50, 0.53, 0.56), (0.45, 0.47, 0.49))


def _default_wavelengths():
    return [list(w) for w in DEFAULT_CHANNEL_WAVELENGTHS]


@dataclass
class ColorSpec:
    """Wavelengths (µm) per colour channel and their sensor-response weights.

    Attributes:
        wavelengths: ``C`` rows of ``K`` wavelengths (µm); default R, G, B of the paper (C = K = 3).
        weights: ``C`` rows of ``K`` non-negative weights (normalised per row to sum 1); None: equal weights.
        names: channel names (default "R", "G", "B" for three channels, else "C0", "C1", ...).
    """

    wavelengths: list = field(default_factory=_default_wavelengths)
    weights: list | None = None
    names: tuple | None = None

    def __post_init__(self):
        wl = torch.as_tensor(self.wavelengths, dtype=torch.float64, device="cpu")
        if wl.ndim != 2 or wl.numel() == 0:
            raise ValueError(f"ColorSpec.wavelengths: give one row of wavelengths (µm) per channel, got shape "
                             f"{tuple(wl.shape)}")
        if not bool(torch.isfinite(wl).all()) or bool((wl <= 0).any()) or bool((wl > 100).any()):
            raise ValueError(f"ColorSpec.wavelengths: wavelengths must be finite, > 0 and in µm, got {wl.tolist()}")
        self.wavelengths = [[float(v) for v in row] for row in wl]
        if self.weights is None:
            w = torch.full_like(wl, 1.0 / wl.shape[1])
        else:
            w = torch.as_tensor(self.weights, dtype=torch.float64, device="cpu")
            if w.shape != wl.shape:
                raise ValueError(f"ColorSpec.weights: shape {tuple(w.shape)} must match the wavelengths' "
                                 f"{tuple(wl.shape)} (one weight per wavelength)")
            if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or bool((w.sum(1) <= 0).any()):
                raise ValueError(f"ColorSpec.weights: weights must be finite, >= 0, with a positive sum per channel, "
                                 f"got {w.tolist()}")
            w = w / w.sum(1, keepdim=True)
        self.weights = [[float(v) for v in row] for row in w]
        if self.names is None:
            self.names = ("R", "G", "B") if wl.shape[0] == 3 else tuple(f"C{i}" for i in range(wl.shape[0]))
        if len(self.names) != wl.shape[0]:
            raise ValueError(f"ColorSpec.names: {len(self.names)} names for {wl.shape[0]} channels")

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return len(self.wavelengths)

    def wavelength_table(self) -> torch.Tensor:
        """``(C, K)`` float64 wavelengths (µm), a CPU tensor (host-side metadata, like every wavelength list)."""
        return torch.tensor(self.wavelengths, dtype=torch.float64, device="cpu")

    def weight_table(self) -> torch.Tensor:
        """``(C, K)`` float64 weights, each row summing to 1 (a CPU tensor)."""
        return torch.tensor(self.weights, dtype=torch.float64, device="cpu")

    def all_wavelengths(self) -> torch.Tensor:
        """``(C·K,)`` float64: every wavelength, channel after channel (the order :meth:`average` expects)."""
        return self.wavelength_table().reshape(-1)

    def centers(self) -> torch.Tensor:
        """``(C,)`` the weighted mean wavelength of each channel (µm)."""
        return torch.round((self.wavelength_table() * self.weight_table()).sum(1) * 1e12) / 1e12

    def sample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """``(C,)`` float64: one wavelength per channel drawn uniformly from its K (training)."""
        wl = self.wavelength_table()
        idx = torch.randint(0, wl.shape[1], (wl.shape[0],), generator=generator, device="cpu")
        return wl[torch.arange(wl.shape[0], device="cpu"), idx]

    def average(self, psf: torch.Tensor, centers: torch.Tensor | None = None, pitch: float | None = None,
                dim: int = 1):
        """Weighted average of the PSFs of each channel's wavelengths (evaluation).

        Args:
            psf: ``(..., C·K, ..., ks, ks)``: the wavelengths of :meth:`all_wavelengths` along ``dim``.
            centers: ``(..., C·K, ..., 2)`` mm (the PSFs' leading shape, last axis (x, y)); when given with ``pitch``
                the PSFs are first shifted onto the channel's weighted-mean centre.
            pitch: PSF pixel pitch (mm).
            dim: the wavelength axis of ``psf`` (and of ``centers``).

        Returns:
            ``psf`` with that axis reduced to C (each PSF still summing to 1 up to what a shift moves out of
            the crop), and the channel centres (or None).
        """
        C, K = len(self.wavelengths), len(self.wavelengths[0])
        d = dim % psf.ndim
        if psf.shape[d] != C * K:
            raise ValueError(f"ColorSpec.average: axis {dim} of the PSFs has {psf.shape[d]} wavelengths, expected "
                             f"{C}×{K} = {C * K}")
        w = self.weight_table().to(device=psf.device, dtype=psf.dtype)
        shape = psf.shape[:d] + (C, K) + psf.shape[d + 1:]
        p = psf.reshape(shape)
        wb = w.reshape((1,) * d + (C, K) + (1,) * (psf.ndim - d - 1))
        if centers is None:
            return (p * wb).sum(d + 1), None
        if pitch is None:
            raise ValueError("ColorSpec.average: give the PSF pitch (mm) with the centres")
        if tuple(centers.shape) != tuple(psf.shape[:-2]) + (2,):
            raise ValueError(f"ColorSpec.average: centres of shape {tuple(centers.shape)} do not match the PSFs' "
                             f"{tuple(psf.shape[:-2])} + (2,)")
        c = centers.reshape(centers.shape[:d] + (C, K) + centers.shape[d + 1:])
        wc = w.to(c.dtype).reshape((1,) * d + (C, K) + (1,) * (c.ndim - d - 2))
        cmean = (c * wc).sum(d + 1, keepdim=True)
        off = (cmean - c) / pitch  # pixels: move each PSF onto the mean centre
        shifted = shift_psf(p, off)
        return (shifted * wb).sum(d + 1), cmean.squeeze(d + 1)


def shift_psf(psf: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Move PSFs by a sub-pixel or pixel ``shift`` (bilinear; energy-conserving away from the crop's edge).

    Args:
        psf: ``(..., ks, ks)`` indexed ``[iy, ix]``.
        shift: ``(..., 2)`` pixels (dx, dy), same leading shape: the content moves toward +x, +y by it.
    Returns:
        ``(..., ks, ks)``: out[iy, ix] = psf at (ix − dx, iy − dy), bilinearly interpolated, zero outside.
    """
    ks_y, ks_x = psf.shape[-2:]
    shift = shift.to(psf.dtype)
    lead = psf.shape[:-2]
    p = psf.reshape(-1, ks_y, ks_x)
    s = shift.reshape(-1, 2)
    out = p
    for axis, comp in ((-1, 0), (-2, 1)):
        n = p.shape[axis]
        d = s[:, comp]
        di = torch.floor(d.detach())
        frac = (d - di)  # differentiable in the shift
        idx = torch.arange(n, device=psf.device)
        # out[i] = (1 − f) in[i − di] + f in[i − di − 1]
        src0 = idx[None, :] - di.long()[:, None]
        src1 = src0 - 1
        def take(src):
            ok = (src >= 0) & (src < n)
            srcc = src.clamp(0, n - 1)
            if axis == -1:
                g = torch.gather(out, 2, srcc[:, None, :].expand(-1, out.shape[1], -1))
                return g * ok[:, None, :]
            g = torch.gather(out, 1, srcc[:, :, None].expand(-1, -1, out.shape[2]))
            return g * ok[:, :, None]
        f = frac[:, None, None]
        out = (1 - f) * take(src0) + f * take(src1)
    return out.reshape(lead + (ks_y, ks_x))
