"""Diffractive optical elements: a thin phase element on a regular pixel grid in a plane z = const.

A DOE is a grid of ``shape = (ny, nx)`` square pixels of ``pitch`` (mm), centred on the optical axis:
pixel ``[iy, ix]`` is centred at ``((ix - (nx-1)/2)·pitch, (iy - (ny-1)/2)·pitch)`` (indices increase with
the coordinate). Its aperture is the grid itself ("square") or the circle inscribed in it ("circle");
light outside the aperture is blocked, so the DOE's edge diffracts.

The ray-wave model samples the field on a *simulation grid* that may subdivide every DOE pixel into
``oversample × oversample`` samples (a DOE pixel is a flat-topped step; resolving it captures its high
diffraction orders). Every method that returns maps takes a ``window = (iy0, ix0, ny, nx)`` in
simulation-grid indices, or the sub-:class:`~raywave.wave.Grid` of :meth:`DOE.sim_grid` that the window is
(a field's grid: :class:`raywave.hybrid.DOEField`), so that only the lit part of a large DOE is ever materialised.
The DOE pitch is the *fabrication* pitch (one level per DOE pixel); the simulation pitch is ``pitch / oversample``.

**Phase, height and wavelength** (docs/ray-wave.md, "DOEs"). Every DOE describes a *design phase* p (rad,
float64) at its ``design_wavelength`` λ0 (µm, default 0.55): subclasses implement
:meth:`DOE.design_phase_pixels` (one value per DOE pixel). The base class turns it into

* the **fabricated profile** (:meth:`DOE.profile_pixels`): ``phase_scale · p``, optionally wrapped to
  [0, 2π) (a kinoform) and quantised to ``L`` levels (nearest level, level L folded to 0) with a
  straight-through gradient (forward: the quantised profile; backward: the identity), see :meth:`fabricate`;
* the **phase at any wavelength** (:meth:`DOE.phase_pixels`), by the DOE's ``dispersion`` model:

  - ``"none"``: the same phase (rad) at every wavelength (Zemax's diffractive-surface model, the ideal
    first-order element; the default without a material);
  - ``"air"``: a fixed optical path, ``φ(λ) = φ(λ0)·λ0/λ`` (``PixelDOE(..., design_wavelength=λ0)``);
  - ``"material"``: a surface-relief **height map** h in a material (default FUSED_SILICA) in a medium of
    index ``n_medium`` (1: air), ``φ(λ) = 2π (n(λ) − n_medium) h / λ``, so
    ``φ(λ) = φ(λ0) · λ0 (n(λ) − n_medium) / (λ (n(λ0) − n_medium))``;

* the **height map** (:meth:`DOE.height_pixels`, µm): ``h = φ(λ0) λ0 / (2π (n(λ0) − n_medium))`` of the
  fabricated profile (in the DOE's material, FUSED_SILICA if it has none);
* the **level map** (:meth:`DOE.levels`): the integer level (0..L−1, torch.long) of every DOE pixel, what a
  fabrication process etches.

All phases are differentiable with respect to the DOE's parameters (``nn.Parameter``).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from raywave.utils.checks import wavelength_um
from raywave.utils.phasor import unit_phasor
from raywave.wave.grid import Field, Grid

__all__ = ["DEFAULT_DESIGN_WAVELENGTH", "DEFAULT_LEVELS", "DEFAULT_MATERIAL", "DISPERSIONS", "DOE", "BlankDOE",
           "has_zero_phase", "PixelDOE", "SumDOE", "Window", "check_levels", "phase_levels", "quantize_phase"]

Window = tuple  # (iy0, ix0, ny, nx) in simulation-grid indices, or a sub-Grid of DOE.sim_grid

#: Design wavelength (µm) of a DOE that does not name one.
DEFAULT_DESIGN_WAVELENGTH = 0.55
#: Material of a DOE's height map when none is named.
DEFAULT_MATERIAL = "FUSED_SILICA"
#: Default number of fabrication levels (4 binary masks).
DEFAULT_LEVELS = 16
#: Dispersion models: how the phase at the design wavelength becomes the phase at another wavelength.
DISPERSIONS = ("none", "air", "material")
_TWO_PI = 2.0 * math.pi


def check_levels(levels, name: str = "levels") -> int:
    """``levels`` as an int >= 2, else a ValueError saying why."""
    if hasattr(levels, "item") and getattr(levels, "ndim", None) == 0:  # numpy / torch scalar
        levels = levels.item()
    if isinstance(levels, bool) or not isinstance(levels, (int, float)) or (
            isinstance(levels, float) and not (math.isfinite(levels) and levels == int(levels))):
        raise ValueError(f"{name} must be an integer number of phase levels (>= 2), got {levels!r}")
    if levels < 2:
        raise ValueError(f"{name} must be an integer number of phase levels >= 2, got {levels!r}")
    return int(levels)


def _check_wavelength(w, name: str) -> float:
    return wavelength_um(w, name)


def phase_levels(phase: torch.Tensor, levels: int) -> torch.Tensor:
    """The one phase quantiser: the level index (torch.long, 0..L−1) of every value of ``phase`` (rad): the phase
    wrapped to [0, 2π) and rounded to the nearest of the L levels ``2πk/L`` (round half to even), level L folded
    to 0. No gradient (an index). :func:`quantize_phase`, :meth:`DOE.levels` and
    :func:`raywave.doe.fabrication.quantise_phase` are this function."""
    L = check_levels(levels)
    w = torch.remainder(phase.detach(), _TWO_PI)
    return torch.remainder(torch.round(w * (L / _TWO_PI)), L).to(torch.long)


def quantize_phase(phase: torch.Tensor, levels: int | None = None, wrap: bool = True) -> torch.Tensor:
    """Wrap ``phase`` (rad) to [0, 2π) and, with ``levels`` = L, round it to the nearest of the L levels
    ``2πk/L`` (level L folds to 0; :func:`phase_levels`), with a straight-through gradient: the forward value is
    the wrapped / quantised phase exactly, the gradient is that of ``phase`` (identity)."""
    if levels is None and not wrap:
        return phase
    if levels is None:
        q = torch.remainder(phase.detach(), _TWO_PI)
    else:
        L = check_levels(levels)
        q = phase_levels(phase, L).to(phase.dtype) * (_TWO_PI / L)
    return q + (phase - phase.detach())


class DOE(nn.Module):
    """Base class: grid geometry, aperture, the windowed phase map, dispersion and fabrication.

    Args:
        shape: ``(ny, nx)`` number of DOE pixels (or an int for a square grid).
        pitch: DOE pixel pitch in mm.
        aperture: ``"square"`` (the whole grid transmits) or ``"circle"`` (the inscribed circle).
        design_wavelength: λ0 (µm) at which :meth:`design_phase_pixels` gives the phase (default 0.55).
        material: the height map's material (a glass name, e.g. "FUSED_SILICA", or a Material); giving one
            makes the DOE dispersive (``dispersion="material"``). Unknown names raise GlassNotFoundError.
        dispersion: "none", "air" or "material" (see the module docstring); default "material" with a
            material, else "none".
        n_medium: refractive index of the medium around the relief (1: air).
    """

    #: the ``type`` of :meth:`to_spec` (None: the class cannot be described by a spec)
    spec_type: str | None = None

    def __init__(self, shape, pitch: float, aperture: str = "square", design_wavelength: float | None = None,
                 material=None, dispersion: str | None = None, n_medium: float = 1.0):
        super().__init__()
        if isinstance(shape, int):
            shape = (shape, shape)
        ny, nx = (int(s) for s in shape)
        if ny < 1 or nx < 1:
            raise ValueError(f"DOE shape must be positive, got {shape}")
        if not (isinstance(pitch, (int, float)) and pitch > 0 and math.isfinite(pitch)):
            raise ValueError(f"DOE pitch must be > 0 mm, got {pitch!r}")
        if not math.isfinite(float(pitch) * max(ny, nx)):
            raise ValueError(f"DOE size must be finite: {nx}×{ny} pixels of {pitch:g} mm overflow")
        if aperture not in ("square", "circle"):
            raise ValueError(f"DOE aperture must be 'square' or 'circle', got {aperture!r}")
        self.shape = (ny, nx)
        self.pitch = float(pitch)
        self.aperture = aperture
        # follows .to(device): tells parameter-free DOEs where to build their maps
        self.register_buffer("_anchor", torch.zeros((), dtype=torch.float64), persistent=False)
        self.design_wavelength = (DEFAULT_DESIGN_WAVELENGTH if design_wavelength is None
                                  else _check_wavelength(design_wavelength, "design_wavelength"))
        if not (math.isfinite(float(n_medium)) and float(n_medium) >= 1.0):
            raise ValueError(f"n_medium must be a refractive index >= 1, got {n_medium!r}")
        self.n_medium = float(n_medium)
        self.material = None
        self.dispersion = "none"
        self._set_dispersion(dispersion if dispersion is not None else ("material" if material is not None
                                                                        else "none"), material)
        #: multiplies the subclass's design phase (kept 1 unless :meth:`fabricate` moved the design wavelength)
        self.phase_scale = 1.0
        #: fabrication: wrap the profile to [0, 2π) at λ0, and quantise it to this many levels (None: continuous)
        self.wrap = False
        self.quant_levels: int | None = None

    # ------------------------------------------------------------------ optics settings
    def _set_dispersion(self, dispersion: str, material=None) -> None:
        if dispersion not in DISPERSIONS:
            raise ValueError(f"dispersion must be one of {', '.join(map(repr, DISPERSIONS))}, got {dispersion!r}")
        if dispersion == "material" or material is not None:
            from raywave.materials import get_material

            m = get_material(DEFAULT_MATERIAL if material is None else material)  # GlassNotFoundError
            if m.is_air:
                raise ValueError("a DOE's material cannot be air")
            wl0 = torch.tensor(self.design_wavelength, dtype=torch.float64, device="cpu")
            dn = float(m.n(wl0).detach()) - self.n_medium
            if not dn > 0:
                raise ValueError(f"the DOE material {m.name} (n = {dn + self.n_medium:.6g} at "
                                 f"{self.design_wavelength:g} µm) must be denser than the medium "
                                 f"(n = {self.n_medium:g})")
            self.material = m.to(self.device)
        self.dispersion = dispersion

    @property
    def material_name(self) -> str | None:
        return None if self.material is None else str(self.material.name)

    def _height_material(self):
        if self.material is not None:
            return self.material
        from raywave.materials import get_material

        return get_material(DEFAULT_MATERIAL)

    def _delta_n(self, wavelength, material=None) -> torch.Tensor:
        m = material if material is not None else self._height_material()
        wl = torch.as_tensor(wavelength, dtype=torch.float64, device=self.device)
        return m.to(self.device).n(wl) - self.n_medium

    def dispersion_ratio(self, wavelength):
        """``φ(λ) / φ(λ0)`` of the dispersion model (None for "none": the phase is the same at every λ)."""
        if self.dispersion == "none":
            return None
        lam0 = self.design_wavelength
        if self.dispersion == "air":
            return lam0 / float(wavelength)
        return (lam0 / torch.as_tensor(wavelength, dtype=torch.float64, device=self.device)) * (
            self._delta_n(wavelength, self.material) / self._delta_n(lam0, self.material))

    def fabricate(self, levels: int | None = DEFAULT_LEVELS, wavelength: float | None = None, material=None,
                  wrap: bool = True) -> "DOE":
        """Make this DOE the fabricated element: its phase at ``wavelength`` λ0 (µm; default the design
        wavelength) wrapped to [0, 2π) and quantised to ``levels`` (None: continuous kinoform) there, with a
        straight-through gradient; with ``material`` (a glass name) it becomes a dispersive height map in it.
        The phase at λ0 is kept: when λ0 differs from the design wavelength, the design phase is rescaled by
        the DOE's (old) dispersion model first. Returns ``self``."""
        lam0 = self.design_wavelength if wavelength is None else _check_wavelength(wavelength, "wavelength")
        L = None if levels is None else check_levels(levels)
        if lam0 != self.design_wavelength:
            r = self.dispersion_ratio(lam0)
            if r is not None:
                self.phase_scale *= float(r.detach()) if isinstance(r, torch.Tensor) else float(r)
            self.design_wavelength = lam0
        if material is not None:
            self._set_dispersion("material", material)
        elif self.dispersion == "material":
            self._set_dispersion("material", self.material)  # re-check at the new λ0
        self.quant_levels = L
        self.wrap = bool(wrap) or L is not None
        return self

    # ------------------------------------------------------------------ geometry
    @property
    def device(self) -> torch.device:
        return self._anchor.device

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

    def sim_grid(self, oversample: int = 1) -> Grid:
        """The simulation grid as a :class:`~raywave.wave.Grid` (pitch ``pitch / oversample``, centred on the
        axis); a field's window on it is ``sim_grid(q).locate(field_grid)``."""
        return Grid(self.sim_origin(oversample), self.pitch / oversample, self.sim_shape(oversample))

    def sim_window(self, window, oversample: int = 1) -> tuple[int, int, int, int]:
        """``window`` (``(iy0, ix0, ny, nx)`` simulation-grid indices, a sub-:class:`~raywave.wave.Grid` of
        :meth:`sim_grid`, or None: the whole grid) as ``(iy0, ix0, ny, nx)``, checked to lie inside the grid."""
        q = int(oversample)
        sy, sx = self.sim_shape(q)
        if window is None:
            return 0, 0, sy, sx
        if isinstance(window, Grid):
            iy0, iy1, ix0, ix1 = self.sim_grid(q).locate(window)
            return iy0, ix0, iy1 - iy0, ix1 - ix0
        iy0, ix0, ny, nx = (int(v) for v in window)
        if iy0 < 0 or ix0 < 0 or ny < 1 or nx < 1 or iy0 + ny > sy or ix0 + nx > sx:
            raise ValueError(f"window {tuple(window)} lies outside the DOE simulation grid {sy}×{sx}")
        return iy0, ix0, ny, nx

    def pixel_xy(self, rows: slice = slice(None), cols: slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor]:
        """Centres (mm, float64) of the DOE pixels ``[rows, cols]``: ``x`` (nx,), ``y`` (ny,)."""
        iy = torch.arange(*rows.indices(self.shape[0]), dtype=torch.float64, device=self.device)
        ix = torch.arange(*cols.indices(self.shape[1]), dtype=torch.float64, device=self.device)
        return (ix - (self.shape[1] - 1) / 2) * self.pitch, (iy - (self.shape[0] - 1) / 2) * self.pitch

    def _count(self, rows: slice, cols: slice) -> tuple[int, int]:
        return len(range(*rows.indices(self.shape[0]))), len(range(*cols.indices(self.shape[1])))

    def coverage(self, window: Window, oversample: int = 1, device=None) -> torch.Tensor:
        """Fraction (0..1) of every simulation pixel of ``window`` inside the DOE aperture, (ny, nx) float64.

        Square: 1 on the grid. Circle: an anti-aliased edge, ``clamp(0.5 + (R - r)/p, 0, 1)``, which places
        the edge with sub-pixel accuracy. ``window``: as :meth:`sim_window`."""
        iy0, ix0, ny, nx = self.sim_window(window, oversample)
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
    def design_phase_pixels(self, rows: slice, cols: slice) -> torch.Tensor:
        """Design phase (rad, float64, unwrapped) of the DOE pixels ``[rows, cols]`` at the design wavelength
        (before ``phase_scale``, wrapping and quantisation). Subclasses implement this."""
        raise NotImplementedError

    def profile_pixels(self, rows: slice = slice(None), cols: slice = slice(None)) -> torch.Tensor:
        """The fabricated profile: phase (rad) at the design wavelength of the DOE pixels ``[rows, cols]``,
        wrapped / quantised when the DOE is fabricated (straight-through gradient)."""
        p = self.design_phase_pixels(rows, cols)
        if self.phase_scale != 1.0:
            p = p * self.phase_scale
        return quantize_phase(p, self.quant_levels, self.wrap)

    def phase_pixels(self, wavelength: float, rows: slice, cols: slice) -> torch.Tensor:
        """Phase (rad, float64) of the DOE pixels ``[rows, cols]`` at ``wavelength`` (µm)."""
        p = self.profile_pixels(rows, cols)
        r = self.dispersion_ratio(wavelength)
        return p if r is None else p * r

    def height_pixels(self, rows: slice = slice(None), cols: slice = slice(None)) -> torch.Tensor:
        """Surface-relief height (µm, float64) of the DOE pixels ``[rows, cols]``:
        ``h = φ(λ0) λ0 / (2π (n(λ0) − n_medium))`` of the fabricated profile, in the DOE's material (FUSED_SILICA
        when it has none)."""
        lam0 = self.design_wavelength
        return self.profile_pixels(rows, cols) * (lam0 / _TWO_PI) / self._delta_n(lam0)

    def height_2pi(self, wavelength: float | None = None) -> float:
        """The height (µm) of a 2π phase step at ``wavelength`` (default λ0): ``λ0 / (n(λ0) − n_medium)``."""
        lam0 = self.design_wavelength if wavelength is None else _check_wavelength(wavelength, "wavelength")
        return lam0 / float(self._delta_n(lam0).detach())

    def levels(self, L: int = DEFAULT_LEVELS, wavelength0: float | None = None, window=None) -> torch.Tensor:
        """Integer level map (torch.long, values 0..L−1) of the DOE pixels: the (continuous, unquantised) phase at
        ``wavelength0`` (µm; default the design wavelength) wrapped to [0, 2π) and rounded to the nearest of
        the L levels 2πk/L, level L folded to 0. ``window = (iy0, ix0, ny, nx)`` in DOE-pixel indices (default:
        the whole DOE, (ny, nx)). Level k is a phase of 2πk/L at λ0, a height of k·h_2π/L."""
        L = check_levels(L, "L")
        lam0 = self.design_wavelength if wavelength0 is None else _check_wavelength(wavelength0, "wavelength0")
        if window is None:
            rows, cols = slice(None), slice(None)
        else:
            iy0, ix0, ny, nx = (int(v) for v in window)
            if iy0 < 0 or ix0 < 0 or ny < 1 or nx < 1 or iy0 + ny > self.shape[0] or ix0 + nx > self.shape[1]:
                raise ValueError(f"window {tuple(window)} lies outside the DOE grid {self.shape[0]}×{self.shape[1]}")
            rows, cols = slice(iy0, iy0 + ny), slice(ix0, ix0 + nx)
        with torch.no_grad():
            p = self.design_phase_pixels(rows, cols) * self.phase_scale
            if lam0 != self.design_wavelength:
                r = self.dispersion_ratio(lam0)
                if r is not None:
                    p = p * r
            return phase_levels(p, L)

    def phase(self, wavelength: float, window: Window | None = None, oversample: int = 1) -> torch.Tensor:
        """Phase map (rad, float64) on the simulation pixels of ``window`` (default: the whole grid; as
        :meth:`sim_window`: ``(iy0, ix0, ny, nx)`` or a sub-Grid of :meth:`sim_grid`).

        Every DOE pixel is held constant over its ``oversample²`` simulation pixels."""
        q = int(oversample)
        iy0, ix0, ny, nx = self.sim_window(window, q)
        r0, r1 = iy0 // q, (iy0 + ny - 1) // q + 1
        c0, c1 = ix0 // q, (ix0 + nx - 1) // q + 1
        ph = self.phase_pixels(wavelength, slice(r0, r1), slice(c0, c1))
        if q > 1:
            ph = ph.repeat_interleave(q, 0).repeat_interleave(q, 1)
            ph = ph[iy0 - r0 * q: iy0 - r0 * q + ny, ix0 - c0 * q: ix0 - c0 * q + nx]
        return ph

    def modulate(self, field: Field, oversample: int = 1) -> Field:
        """The field just after the DOE: ``field``'s envelope (any leading batch dims, on a window of
        :meth:`sim_grid`) times ``exp(iφ)`` of this DOE at the field's wavelength (the envelope's dtype kept)."""
        if has_zero_phase(self):  # exp(i·0) = 1: the field as it is (no phase map, no product)
            return field
        phase = self.phase(field.wavelength, field.grid, oversample)
        return field.with_envelope(field.envelope * unit_phasor(phase).to(field.envelope.dtype))

    def window_phasors(self, wavelength: float, corners, shape, oversample: int = 1) -> torch.Tensor:
        """``exp(iφ)`` at ``wavelength`` (µm) on B windows of one ``shape`` ``(ny, nx)`` whose sample (0, 0) lies at
        the simulation-grid indices ``corners`` (B pairs ``(iy0, ix0)``, host ints), complex128 ``(B, ny, nx)``:
        the batched form of :meth:`modulate`'s factor (one :meth:`phase` evaluation over the windows' union on the
        grid, one gather). Samples beyond the grid repeat its edge (a padded window's envelope is 0 there)."""
        q = int(oversample)
        ny, nx = (int(v) for v in shape)
        sy, sx = self.sim_shape(q)
        iy0s, ix0s = [int(c[0]) for c in corners], [int(c[1]) for c in corners]
        lo_y, hi_y = max(0, min(iy0s)), min(sy, max(iy0s) + ny)
        lo_x, hi_x = max(0, min(ix0s)), min(sx, max(ix0s) + nx)
        if hi_y <= lo_y or hi_x <= lo_x:  # no window meets the grid
            return torch.ones((len(iy0s), ny, nx), dtype=torch.complex128, device=self.device)
        inside = all(0 <= y and y + ny <= sy for y in iy0s) and all(0 <= x and x + nx <= sx for x in ix0s)
        if inside and len(iy0s) * ny * nx < (hi_y - lo_y) * (hi_x - lo_x):
            # windows far apart (a map's mirror images): each window's own phase, not their union's (the same
            # pixels, fewer of them)
            return unit_phasor(torch.stack([self.phase(wavelength, (y, x, ny, nx), q) for y, x in zip(iy0s, ix0s)]))
        # the phase of the windows' union through phase() (a subclass's own phase map, e.g. a PerturbedDOE's, holds)
        ph = self.phase(wavelength, (lo_y, lo_x, hi_y - lo_y, hi_x - lo_x), q)
        if inside:  # slices of the union (a copy each instead of an indexed gather)
            return unit_phasor(torch.stack([ph[y - lo_y:y - lo_y + ny, x - lo_x:x - lo_x + nx]
                                            for y, x in zip(iy0s, ix0s)]))
        dev = ph.device
        start = torch.tensor([iy0s, ix0s], dtype=torch.long, device=dev)  # (2, B)
        iy = (start[0][:, None] + torch.arange(ny, device=dev)).clamp(lo_y, hi_y - 1) - lo_y
        ix = (start[1][:, None] + torch.arange(nx, device=dev)).clamp(lo_x, hi_x - 1) - lo_x
        return unit_phasor(ph[iy[:, :, None], ix[:, None, :]])

    # ------------------------------------------------------------------ specs
    def model_spec(self) -> dict:
        """The parameters of this DOE's phase model as a plain dict (``{"type": ..., ...}``)."""
        raise NotImplementedError(f"{type(self).__name__} has no phase-model spec")

    def to_spec(self) -> dict:
        """The whole DOE as a plain dict (grid, phase model, dispersion, fabrication); parameters that do not fit
        a small dict (pixel maps) are zeros here and live in the ``state_dict`` (see :func:`raywave.doe.save_doe`)."""
        out = {"shape": list(self.shape), "pitch": self.pitch, "aperture": self.aperture,
               "model": self.model_spec(), "design_wavelength": self.design_wavelength,
               "dispersion": self.dispersion, "material": self.material_name, "n_medium": self.n_medium,
               "phase_scale": self.phase_scale, "wrap": self.wrap, "levels": self.quant_levels}
        return out

    def _load_optics(self, spec: dict) -> "DOE":
        """Apply the dispersion / fabrication keys of a :meth:`to_spec` dict."""
        self.phase_scale = float(spec.get("phase_scale", 1.0))
        self.wrap = bool(spec.get("wrap", False))
        lv = spec.get("levels")
        self.quant_levels = None if lv is None else check_levels(lv)
        return self

    def __add__(self, other: "DOE") -> "DOE":
        return SumDOE(self, other)

    def extra_repr(self) -> str:
        s = f"shape={self.shape}, pitch={self.pitch:g} mm, aperture={self.aperture!r}"
        if self.dispersion != "none":
            s += f", design_wavelength={self.design_wavelength:g} µm, dispersion={self.dispersion!r}"
            if self.material is not None:
                s += f", material={self.material_name!r}"
        if self.wrap or self.quant_levels:
            s += f", levels={self.quant_levels}, wrap={self.wrap}"
        return s


class BlankDOE(DOE):
    """A DOE with zero phase: only its aperture (a clear window of the given size)."""

    spec_type = "blank"

    def design_phase_pixels(self, rows, cols):
        return torch.zeros(self._count(rows, cols), dtype=torch.float64, device=self.device)

    def model_spec(self) -> dict:
        return {"type": "blank"}


def has_zero_phase(doe) -> bool:
    """Whether ``doe``'s phase is exactly 0 at every pixel and wavelength by construction: a :class:`BlankDOE` that
    computes its phase through the base class (a subclass that overrides any step of it is not assumed blank).
    Then ``exp(iφ) = 1`` and the engine skips the phase map and its product (the same PSFs)."""
    cls = type(doe)
    return (isinstance(doe, BlankDOE) and cls.phase is DOE.phase and cls.phase_pixels is DOE.phase_pixels
            and cls.profile_pixels is DOE.profile_pixels and cls.design_phase_pixels is BlankDOE.design_phase_pixels)


class PixelDOE(DOE):
    """A free pixel phase map: one trainable phase value (rad) per DOE pixel (the most general DOE).

    The DOE pitch is the fabrication pitch: the map is held constant over the ``oversample²`` simulation
    samples of each pixel, so a coarse fabrication grid is simulated on a finer one at no extra parameters.

    Args:
        phase: ``(ny, nx)`` phase in radians at ``design_wavelength`` (a tensor or array).
        pitch: pixel pitch (mm).
        design_wavelength: µm. ``None``: the same phase at every wavelength (``dispersion="none"``; λ0 = 0.55 µm
            for fabrication). Otherwise, without a material, the DOE is a fixed optical-path profile in air,
            ``φ(λ) = φ · λ_d / λ`` (``dispersion="air"``); with ``material`` a height map in it.
        aperture: "square" or "circle".
        trainable: register the map as an ``nn.Parameter`` (default) or a buffer.
        material, dispersion, n_medium: see :class:`DOE`.
    """

    spec_type = "pixel"

    def __init__(self, phase, pitch: float, design_wavelength: float | None = None, aperture: str = "square",
                 trainable: bool = True, material=None, dispersion: str | None = None, n_medium: float = 1.0):
        ph = torch.as_tensor(phase, dtype=torch.float64)
        if ph.ndim != 2:
            raise ValueError(f"a DOE phase map must be 2-D (ny, nx), got shape {tuple(ph.shape)}")
        if not bool(torch.isfinite(ph).all()):
            raise ValueError("the DOE phase map contains NaN or inf values")
        if dispersion is None and material is None and design_wavelength is not None:
            dispersion = "air"
        super().__init__(tuple(ph.shape), pitch, aperture, design_wavelength, material, dispersion, n_medium)
        if trainable:
            self.phase_map = nn.Parameter(ph.clone())
        else:
            self.register_buffer("phase_map", ph.clone())
        self.trainable = bool(trainable)

    @classmethod
    def from_height(cls, height_um, pitch: float, material=DEFAULT_MATERIAL,
                    design_wavelength: float = DEFAULT_DESIGN_WAVELENGTH, **kw) -> "PixelDOE":
        """A dispersive DOE from a height map (µm) in ``material``: ``φ(λ0) = 2π (n(λ0) − n_medium) h / λ0``."""
        h = torch.as_tensor(height_um, dtype=torch.float64)
        probe = BlankDOE(1, 1.0, design_wavelength=design_wavelength, material=material,
                         n_medium=kw.get("n_medium", 1.0))
        dn = float(probe._delta_n(probe.design_wavelength).detach())
        return cls(h * (_TWO_PI * dn / probe.design_wavelength), pitch, design_wavelength=design_wavelength,
                   material=material, **kw)

    def design_phase_pixels(self, rows, cols):
        return self.phase_map[rows, cols]

    def model_spec(self) -> dict:
        return {"type": "pixel", "trainable": self.trainable}


class SumDOE(DOE):
    """The sum of DOEs on the same grid (shape and pitch): their phases add at every wavelength (and so do their
    heights when they share a material). The sum's design phase is the terms' phases at its design wavelength
    (default the first term's, fixed at construction); its dispersion model is the terms' common one (pass
    ``dispersion`` / ``material`` when they differ). The sum can itself be fabricated (quantising the total).
    ``doe_a + doe_b`` builds one."""

    spec_type = "sum"

    def __init__(self, *terms: DOE, aperture: str | None = None, design_wavelength: float | None = None,
                 material=None, dispersion: str | None = None, n_medium: float | None = None):
        if len(terms) == 1 and isinstance(terms[0], (list, tuple)):
            terms = tuple(terms[0])
        if not terms or not all(isinstance(t, DOE) for t in terms):
            raise ValueError("SumDOE needs one or more DOEs")
        first = terms[0]
        for t in terms[1:]:
            if t.shape != first.shape or abs(t.pitch - first.pitch) > 1e-12 * first.pitch:
                raise ValueError(f"DOEs summed must share the grid: {first.shape} of {first.pitch:g} mm vs "
                                 f"{t.shape} of {t.pitch:g} mm")
        if dispersion is None and material is None:
            models = {(t.dispersion, t.material_name, t.design_wavelength if t.dispersion != "none" else None)
                      for t in terms}
            if len(models) > 1:
                raise ValueError("the summed DOEs have different dispersion models "
                                 f"({sorted(map(str, models))}): give the sum's dispersion / material")
            dispersion, mat = first.dispersion, first.material
            material = mat
        super().__init__(first.shape, first.pitch, aperture or first.aperture,
                         first.design_wavelength if design_wavelength is None else design_wavelength,
                         material, dispersion, first.n_medium if n_medium is None else n_medium)
        self.terms = nn.ModuleList(terms)
        self._term_wavelength = self.design_wavelength

    def design_phase_pixels(self, rows, cols):
        out = None
        for t in self.terms:
            p = t.phase_pixels(self._term_wavelength, rows, cols)
            out = p if out is None else out + p
        return out

    def model_spec(self):
        return {"type": "sum", "terms": [t.to_spec() for t in self.terms], "term_wavelength": self._term_wavelength}
