"""Diffractive optical elements: a thin phase element on a regular pixel grid in a plane z = const.

A DOE is a grid of ``shape = (ny, nx)`` square pixels of ``pitch`` (mm), centred on the optical axis:
pixel ``[iy, ix]`` is centred at ``((ix - (nx-1)/2)·pitch, (iy - (ny-1)/2)·pitch)`` (indices increase with
the coordinate). Its aperture is the grid itself ("square") or the circle inscribed in it ("circle");
light outside the aperture is blocked, so the DOE's edge diffracts.

The ray-wave model samples the field on a *simulation grid* that may subdivide every DOE pixel into
``oversample × oversample`` samples (a DOE pixel is a flat-topped step; resolving it captures its high
diffraction orders). Every method that returns maps takes a ``window = (iy0, ix0, ny, nx)`` in
simulation-grid indices so that only the lit part of a large DOE is ever materialised.

Phases are float64 radians; ``phase(wavelength, ...)`` is differentiable with respect to the DOE's
parameters. Subclasses implement :meth:`DOE.phase_pixels` (one value per DOE pixel); parametrised DOEs
(Fresnel lens, Zernike, binary-2, ...) are added in the same way.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["DOE", "BlankDOE", "PixelDOE", "Window"]

Window = tuple  # (iy0, ix0, ny, nx) in simulation-grid indices


class DOE(nn.Module):
    """Base class: grid geometry, aperture and the windowed phase map.

    Args:
        shape: ``(ny, nx)`` number of DOE pixels (or an int for a square grid).
        pitch: DOE pixel pitch in mm.
        aperture: ``"square"`` (the whole grid transmits) or ``"circle"`` (the inscribed circle).
    """

    def __init__(self, shape, pitch: float, aperture: str = "square"):
        super().__init__()
        if isinstance(shape, int):
            shape = (shape, shape)
        ny, nx = (int(s) for s in shape)
        if ny < 1 or nx < 1:
            raise ValueError(f"DOE shape must be positive, got {shape}")
        if not (pitch > 0 and math.isfinite(pitch)):
            raise ValueError(f"DOE pitch must be > 0 mm, got {pitch!r}")
        if aperture not in ("square", "circle"):
            raise ValueError(f"DOE aperture must be 'square' or 'circle', got {aperture!r}")
        self.shape = (ny, nx)
        self.pitch = float(pitch)
        self.aperture = aperture
        # follows .to(device): tells parameter-free DOEs where to build their maps
        self.register_buffer("_anchor", torch.zeros((), dtype=torch.float64), persistent=False)

    @property
    def device(self) -> torch.device:
        return self._anchor.device

    # ------------------------------------------------------------------ geometry
    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the grid in mm."""
        return self.shape[1] * self.pitch, self.shape[0] * self.pitch

    def sim_shape(self, oversample: int = 1) -> tuple[int, int]:
        """Simulation-grid shape ``(ny·q, nx·q)``."""
        return self.shape[0] * oversample, self.shape[1] * oversample

    def sim_origin(self, oversample: int = 1) -> tuple[float, float]:
        """(x, y) mm of the centre of simulation pixel (0, 0)."""
        p = self.pitch / oversample
        ny, nx = self.sim_shape(oversample)
        return -(nx - 1) / 2 * p, -(ny - 1) / 2 * p

    def coverage(self, window: Window, oversample: int = 1, device=None) -> torch.Tensor:
        """Fraction (0..1) of every simulation pixel of ``window`` inside the DOE aperture, (ny, nx) float64.

        Square: 1 on the grid. Circle: an anti-aliased edge, ``clamp(0.5 + (R - r)/p, 0, 1)``, which places
        the edge with sub-pixel accuracy."""
        iy0, ix0, ny, nx = window
        p = self.pitch / oversample
        if self.aperture == "square":
            return torch.ones((ny, nx), dtype=torch.float64, device=device)
        x0, y0 = self.sim_origin(oversample)
        x = x0 + (ix0 + torch.arange(nx, dtype=torch.float64, device=device)) * p
        y = y0 + (iy0 + torch.arange(ny, dtype=torch.float64, device=device)) * p
        r = torch.sqrt(x[None, :] ** 2 + y[:, None] ** 2)
        radius = 0.5 * min(self.size)
        return (0.5 + (radius - r) / p).clamp(0.0, 1.0)

    # ------------------------------------------------------------------ phase
    def phase_pixels(self, wavelength: float, rows: slice, cols: slice) -> torch.Tensor:
        """Phase (rad, float64) of the DOE pixels ``[rows, cols]`` at ``wavelength`` (µm)."""
        raise NotImplementedError

    def phase(self, wavelength: float, window: Window | None = None, oversample: int = 1) -> torch.Tensor:
        """Phase map (rad, float64) on the simulation pixels of ``window`` (default: the whole grid).

        Every DOE pixel is held constant over its ``oversample²`` simulation pixels."""
        q = int(oversample)
        if window is None:
            window = (0, 0) + self.sim_shape(q)
        iy0, ix0, ny, nx = window
        sy, sx = self.sim_shape(q)
        if iy0 < 0 or ix0 < 0 or iy0 + ny > sy or ix0 + nx > sx:
            raise ValueError(f"window {window} lies outside the DOE simulation grid {sy}×{sx}")
        r0, r1 = iy0 // q, (iy0 + ny - 1) // q + 1
        c0, c1 = ix0 // q, (ix0 + nx - 1) // q + 1
        ph = self.phase_pixels(wavelength, slice(r0, r1), slice(c0, c1))
        if q > 1:
            ph = ph.repeat_interleave(q, 0).repeat_interleave(q, 1)
            ph = ph[iy0 - r0 * q: iy0 - r0 * q + ny, ix0 - c0 * q: ix0 - c0 * q + nx]
        return ph

    def extra_repr(self) -> str:
        return f"shape={self.shape}, pitch={self.pitch:g} mm, aperture={self.aperture!r}"


class BlankDOE(DOE):
    """A DOE with zero phase: only its aperture (a clear window of the given size)."""

    def phase_pixels(self, wavelength, rows, cols):
        ny = len(range(*rows.indices(self.shape[0])))
        nx = len(range(*cols.indices(self.shape[1])))
        return torch.zeros((ny, nx), dtype=torch.float64, device=self.device)


class PixelDOE(DOE):
    """A free pixel phase map: one trainable phase value (rad) per DOE pixel.

    Args:
        phase: ``(ny, nx)`` phase in radians at ``design_wavelength`` (a tensor or array).
        pitch: pixel pitch (mm).
        design_wavelength: µm. ``None``: the same phase at every wavelength. Otherwise the DOE is a fixed
            optical-path profile in air, ``φ(λ) = φ · λ_d / λ`` (the material dispersion of a real surface
            relief is added by the DOE issue's models).
        aperture: "square" or "circle".
        trainable: register the map as an ``nn.Parameter`` (default) or a buffer.
    """

    def __init__(self, phase, pitch: float, design_wavelength: float | None = None, aperture: str = "square",
                 trainable: bool = True):
        ph = torch.as_tensor(phase, dtype=torch.float64)
        if ph.ndim != 2:
            raise ValueError(f"a DOE phase map must be 2-D (ny, nx), got shape {tuple(ph.shape)}")
        if not bool(torch.isfinite(ph).all()):
            raise ValueError("the DOE phase map contains NaN or inf values")
        super().__init__(tuple(ph.shape), pitch, aperture)
        if trainable:
            self.phase_map = nn.Parameter(ph.clone())
        else:
            self.register_buffer("phase_map", ph.clone())
        self.design_wavelength = None if design_wavelength is None else float(design_wavelength)

    def phase_pixels(self, wavelength, rows, cols):
        ph = self.phase_map[rows, cols]
        if self.design_wavelength is not None:
            ph = ph * (self.design_wavelength / float(wavelength))
        return ph

    def extra_repr(self) -> str:
        dw = "" if self.design_wavelength is None else f", design_wavelength={self.design_wavelength:g} µm"
        return super().extra_repr() + dw
