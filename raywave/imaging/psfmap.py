"""PSF maps: the PSFs of a lens model on a grid of sensor positions, at several depths and wavelengths.

**PSF models.** Anything with ``psf_result(fields, wavelengths=None, ks=64, depth=None, **kw) ->
raywave.hybrid.PSFResult`` (``psf`` (F, W, ks, ks) each summing to 1, ``center`` (F, W, 2) mm = pixel
``[ks//2, ks//2]``, ``energy_outside``, ``pitch``): :class:`raywave.hybrid.HybridLens` and the comparison models
of :mod:`raywave.models`. Field points are angles in degrees, (θx, θy), OpticStudio signs (+θy images at +y).

**Grid definition** (:func:`normalised_grid`, :func:`field_grid`). An N×M map samples the sensor at the
*centres of an N×M tiling* of the normalised sensor square [-1, 1]²:

    u_j = (2j + 1)/M − 1   (j = 0 … M−1, along x),    v_i = (2i + 1)/N − 1   (i = 0 … N−1, along y),

``positions[i, j] = (u_j, v_i)``; row i runs along sensor +y, column j along +x (the ``[iy, ix]`` order of PSFs).
A normalised position (u, v) is the sensor point (x, y) = (u·w/2, v·h/2) mm of a w × h mm sensor
(``lens.sensor_size`` unless ``sensor_size`` is given; a lens without a sensor: the square in its image circle).
Its field angle is found through the lens:

* ``mapping="chief_ray"`` (default): the field whose **real chief ray** (through the refractive lens, aimed at
  the stop centre, at ``wavelength``, default the lens's primary, and at the first depth of the map) lands at
  (x, y) on the sensor. The lens is rotationally symmetric, so this is a 1-D Newton solve of the real image
  height ρ(θ) = √(x² + y²) (to 1e-10 mm) along the azimuth φ of (x, y); tan θx = tan θ cos φ,
  tan θy = tan θ sin φ.
  So the map's centres at the reference wavelength and depth sit on the nodes; distortion shows up as the
  non-uniform spacing of the field angles, lateral colour and depth as centres off the nodes.
* ``mapping="paraxial"``: the rectilinear (pinhole) field, tan θ = ρ / s with s the paraxial image-height scale
  (dρ/d tanθ at θ → 0 of the real chief ray, = EFL for a distant object). The centres then sit where the
  real lens puts these fields: off the nodes by the **distortion**, which :func:`raywave.imaging.render` applies
  as a warp.

The centres always come from the model (its chief ray), and the render uses ``centers − node position`` to
shift each region (distortion, lateral colour, depth-dependent image height).

**Batching and caching.** The model is called for ``batch`` field points at a time, all wavelengths together
(a :class:`~raywave.hybrid.HybridLens` holds the DOE-plane fields of one call in memory: ~7–9 MB each for the
bundled hybrid lens, so the default ``batch`` keeps ≲ 24 fields per call). A :class:`DOEFieldCache` keeps the
detached DOE-plane fields of a **frozen refractive lens** across calls (the paper's DOE-training step): only the
DOE modulation and the propagation are recomputed. :func:`psf_map` runs without autograd by default (the
paper's non-differentiable first pass); :func:`psf_map_points` recomputes any subset of a map's PSFs with
autograd (the replay of the memory-saving training loop).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import torch

from raywave.imaging.map_checkpoint import MapCheckpoint, map_key
from raywave.utils import devices

__all__ = ["DOEFieldCache", "PSFCropWarning", "PSFMap", "field_grid", "field_signature", "fields_at", "node_values",
           "normalised_grid", "psf_map", "psf_map_points", "sensor_size_of"]

class PSFCropWarning(UserWarning):
    """Some PSFs of a map lose much of their light outside the ks×ks crop (crop too small, or a beam clipped by
    the DOE aperture that diffracts widely)."""


#: A map warns when a PSF's energy outside its crop exceeds this fraction.
CROP_WARNING_FRACTION = 0.25
#: DOE-plane fields per model call that :func:`psf_map` aims at when ``batch`` is not given.
DEFAULT_FIELDS_PER_CALL = 24
_AUTO_PROGRESS_PSFS = 100  # progress=None shows a bar from this many PSFs on (on a terminal)
_NEWTON_TOL = 1e-10  # mm of real image height
_NEWTON_ITERS = 30


# ---------------------------------------------------------------------------- grid and fields
def _grid_shape(grid) -> tuple[int, int]:
    g = (grid, grid) if isinstance(grid, int) else tuple(int(v) for v in grid)
    if len(g) != 2 or min(g) < 1:
        raise ValueError(f"grid: give (N, M) positive integers (rows along y, columns along x), got {grid!r}")
    return g


def normalised_grid(grid=(10, 10), dtype=torch.float64, device=None) -> torch.Tensor:
    """``(N, M, 2)`` normalised sensor positions (u, v) ∈ (−1, 1)² of the cell centres of an N×M tiling.

    ``[i, j] = ((2j + 1)/M − 1, (2i + 1)/N − 1)``: row i along +y, column j along +x."""
    n, m = _grid_shape(grid)
    v = (2 * torch.arange(n, dtype=dtype, device=device) + 1) / n - 1
    u = (2 * torch.arange(m, dtype=dtype, device=device) + 1) / m - 1
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), -1)


def _lens_of(model):
    from raywave.lens.lens import Lens

    if isinstance(model, Lens):
        return model
    lens = getattr(model, "lens", None)
    if isinstance(lens, Lens):
        return lens
    raise TypeError(f"{type(model).__name__} has no refractive lens (a raywave Lens or an object with a .lens); "
                    "give the field angles explicitly (fields=)")


def sensor_size_of(model, sensor_size=None) -> tuple[float, float]:
    """(w, h) mm: ``sensor_size`` when given, else the model's lens's sensor size, else (a lens file without a
    sensor, e.g. most .zmx files) the square inscribed in the lens's image circle
    (:func:`raywave.lens.analysis.default_sensor_size`: its corners see the lens's largest field)."""
    if sensor_size is not None:
        s = tuple(float(v) for v in (sensor_size if hasattr(sensor_size, "__len__") else (sensor_size,)))
        if len(s) == 1:
            s = (s[0], s[0])
        if len(s) != 2 or not all(math.isfinite(v) and v > 0 for v in s):
            raise ValueError(f"sensor_size: give (width, height) in mm, both > 0, got {sensor_size!r}")
        return s
    lens = _lens_of(model)
    size = getattr(lens, "sensor_size", None)
    if size is None:
        from raywave.lens.analysis import default_sensor_size

        try:
            return default_sensor_size(lens)
        except ValueError as err:
            raise ValueError(f"the lens has no sensor size and {err}: give one (lens file 'sensor': {{'size': "
                             "[w, h]}, or sensor_size=(w, h) mm)") from None
    return float(size[0]), float(size[1])


def _chief_heights(lens, theta_deg: torch.Tensor, wavelength: float, depth) -> torch.Tensor:
    """Real chief-ray image height (mm) at the sensor for fields (0, θ) (θ in degrees, (P,)), no autograd."""
    from raywave.lens.frames import image_space
    from raywave.lens.sources import VignettingWarning, chief_ray

    if image_space(lens) is not lens:  # sensor heights along one straight axis: give the fields instead
        raise ValueError("the chief-ray mapping of sensor points to fields assumes one straight optical axis, but "
                         "this lens has coordinate breaks or mirrors: pass the field angles explicitly (fields=)")
    f = torch.stack([torch.zeros_like(theta_deg), theta_deg], -1)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", VignettingWarning)
        rays = chief_ray(lens, f, [wavelength], field_type="angle", depth=depth)
        out = lens.trace_to_image(rays)
    h = out.o[:, 0, 0, 1].to(torch.float64)
    return torch.where(out.valid[:, 0, 0], h, torch.full_like(h, float("nan"))).cpu()


def fields_at(model_or_lens, points_mm, wavelength: float | None = None, depth=None,
              mapping: str = "chief_ray") -> torch.Tensor:
    """Field angles (degrees, ``(..., 2)`` = (θx, θy)) of sensor points ``points_mm`` ``(..., 2)`` (x, y) mm.

    See the module docstring for ``mapping`` ("chief_ray": the real chief ray at ``wavelength`` and ``depth``
    lands on the point; "paraxial": the rectilinear field tan θ = ρ / s)."""
    if mapping not in ("chief_ray", "paraxial"):
        raise ValueError(f"mapping must be 'chief_ray' or 'paraxial', got {mapping!r}")
    lens = _lens_of(model_or_lens)
    wl = float(lens.primary_wavelength if wavelength is None else wavelength)
    pts = torch.as_tensor(points_mm, dtype=torch.float64, device="cpu").detach()
    shape = pts.shape[:-1]
    flat = pts.reshape(-1, 2)
    rho = torch.linalg.vector_norm(flat, dim=-1)
    # paraxial scale s = dρ/d(tan θ) at the axis: ρ/tan θ = s (1 + O(θ²)) at two small angles, extrapolated
    # (Richardson)
    t0 = 0.02
    h = _chief_heights(lens, torch.tensor([t0, 0.5 * t0], dtype=torch.float64, device="cpu"), wl, depth)
    s1, s2 = float(h[0]) / math.tan(math.radians(t0)), float(h[1]) / math.tan(math.radians(0.5 * t0))
    s = (4 * s2 - s1) / 3
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"the lens gives no upright real image at {wl:g} µm (paraxial image-height scale "
                         f"{s:g} mm): cannot map sensor positions to field angles")
    theta = torch.rad2deg(torch.atan(rho / s))
    if mapping == "chief_ray":
        theta = _solve_heights(lens, rho, theta, wl, depth)
    tt = torch.tan(torch.deg2rad(theta))
    safe = torch.where(rho > 0, rho, torch.ones_like(rho))
    cos_phi, sin_phi = flat[:, 0] / safe, flat[:, 1] / safe  # exact zeros on the axes
    out = torch.stack([torch.rad2deg(torch.atan(tt * cos_phi)), torch.rad2deg(torch.atan(tt * sin_phi))], -1)
    return out.reshape(shape + (2,))


def _solve_heights(lens, rho: torch.Tensor, theta: torch.Tensor, wl: float, depth) -> torch.Tensor:
    """θ (deg) with real chief-ray height ρ(θ) = ``rho`` (mm), Newton from ``theta``, batched over all points."""
    d = 1e-5  # deg, finite-difference step
    theta = theta.clone()
    for _ in range(_NEWTON_ITERS):
        h = _chief_heights(lens, torch.cat([theta, theta + d]), wl, depth)
        h0, h1 = h[: theta.numel()], h[theta.numel():]
        err = h0 - rho
        if bool(torch.isnan(err).any()):
            k = int(torch.isnan(err).nonzero()[0])
            raise ValueError(f"no chief ray reaches the sensor for the field of image height {float(rho[k]):.4g} mm "
                             f"(field {float(theta[k]):.4g} deg, {wl:g} µm): the sensor corner lies outside what the "
                             "lens images; give a smaller sensor_size")
        if float(err.abs().max()) <= _NEWTON_TOL:
            return theta
        slope = (h1 - h0) / d
        if bool((slope <= 0).any()):
            k = int((slope <= 0).nonzero()[0])
            raise ValueError(f"the real image height stops growing with the field angle at {float(theta[k]):.4g} deg "
                             f"({wl:g} µm): image height {float(rho[k]):.4g} mm cannot be reached")
        theta = theta - err / slope
    raise ValueError(f"field angles for the image heights did not converge to {_NEWTON_TOL:g} mm "
                     f"(residual {float(err.abs().max()):.3g} mm)")


def field_grid(model_or_lens, grid=(10, 10), sensor_size=None, wavelength: float | None = None, depth=None,
               mapping: str = "chief_ray") -> torch.Tensor:
    """``(N, M, 2)`` field angles (deg, (θx, θy)) of the :func:`normalised_grid` nodes of the sensor.

    Args:
        model_or_lens: a :class:`~raywave.lens.Lens` or a model with a ``.lens`` (HybridLens, comparison models).
        grid: (N, M) rows (along y) × columns (along x), or one integer for N = M.
        sensor_size: (w, h) mm (default the lens's sensor size).
        wavelength: µm of the reference chief ray (default the lens's primary).
        depth: object distance (mm, ``inf``; default the lens's).
        mapping: "chief_ray" (real image height, default) or "paraxial" (rectilinear); see the module docstring.
    """
    w, h = sensor_size_of(model_or_lens, sensor_size)
    pos = normalised_grid(grid, device="cpu")  # host-side: field angles are CPU tensors
    pts = pos * torch.tensor([0.5 * w, 0.5 * h], dtype=torch.float64, device="cpu")
    return fields_at(model_or_lens, pts, wavelength, depth, mapping)


# ---------------------------------------------------------------------------- the map
@dataclass
class PSFMap:
    """PSFs on an N×M grid of sensor positions, for D depths and W wavelengths (or colour channels).

    Attributes:
        psf: float64 ``(D, W, N, M, ks, ks)``, each PSF summing to 1 (``[iy, ix]``, pixel ``[ks//2, ks//2]`` on the
            chief ray).
        centers: ``(D, W, N, M, 2)`` mm: the sensor position of each PSF's pixel ``[ks//2, ks//2]``.
        fields: ``(N, M, 2)`` field angles (deg) of the nodes.
        positions: ``(N, M, 2)`` normalised sensor positions (u, v) of the nodes.
        depths: ``(D,)`` mm (``inf`` for a distant object).
        wavelengths: ``(W,)`` µm (for a channel-averaged map: the channels' weighted mean wavelengths).
        pitch: PSF pixel pitch (mm).
        sensor_size: (w, h) mm that the normalised positions refer to (None if unknown).
        energy_outside: ``(D, W, N, M)`` fraction of the power outside each PSF's crop.
    """

    psf: torch.Tensor
    centers: torch.Tensor
    fields: torch.Tensor
    positions: torch.Tensor
    depths: torch.Tensor
    wavelengths: torch.Tensor
    pitch: float
    sensor_size: tuple
    energy_outside: torch.Tensor | None = None
    info: dict = field(default_factory=dict)

    @property
    def grid(self) -> tuple[int, int]:
        return int(self.psf.shape[2]), int(self.psf.shape[3])

    @property
    def ks(self) -> int:
        return int(self.psf.shape[-1])

    def node_positions_mm(self) -> torch.Tensor:
        """``(N, M, 2)`` sensor positions (mm) of the nodes."""
        if self.sensor_size is None:
            raise ValueError("this PSF map has no sensor size (made from explicit fields for a model without one)")
        w, h = self.sensor_size
        return self.positions * torch.tensor([0.5 * w, 0.5 * h], dtype=self.positions.dtype,
                                             device=self.positions.device)

    def flat_fields(self) -> torch.Tensor:
        """``(N·M, 2)`` node fields in row-major order (node k = (k // M, k % M)), for :func:`psf_map_points`."""
        return self.fields.reshape(-1, 2)

    def channel_average(self, color) -> "PSFMap":
        """The evaluation map: the wavelengths of ``color`` (:class:`~raywave.imaging.color.ColorSpec`, this map
        made with ``wavelengths=color.all_wavelengths()``) averaged per channel with its sensor-response weights,
        each PSF first shifted onto the channel's mean centre. Returns a map with W = C channels."""
        want = color.all_wavelengths()
        if self.wavelengths.numel() != want.numel() or not torch.allclose(self.wavelengths.cpu(), want, atol=1e-9):
            raise ValueError(f"channel_average: the map's wavelengths {self.wavelengths.tolist()} are not the "
                             f"colour spec's {want.tolist()} (make the map with wavelengths=color.all_wavelengths())")
        psf, cen = color.average(self.psf, self.centers, self.pitch, dim=1)
        eo = None
        if self.energy_outside is not None:
            eo, _ = color.average(self.energy_outside[..., None, None], None, None, dim=1)
            eo = eo[..., 0, 0]
        return replace(self, psf=psf, centers=cen, wavelengths=color.centers().to(self.wavelengths.device),
                       energy_outside=eo, info={**self.info, "channels": list(color.names)})

    def detach(self) -> "PSFMap":
        return replace(self, psf=self.psf.detach(), centers=self.centers.detach())

    def to_numpy_dict(self) -> dict:
        """Plain numpy arrays (for ``numpy.savez``)."""
        import numpy as np

        out = {
            "psf": self.psf.detach().cpu().numpy(),
            "centers": self.centers.detach().cpu().numpy(),
            "fields": self.fields.detach().cpu().numpy(),
            "positions": self.positions.detach().cpu().numpy(),
            "depths": self.depths.detach().cpu().numpy(),
            "wavelengths": self.wavelengths.detach().cpu().numpy(),
            "pitch": np.float64(self.pitch),
        }
        if self.sensor_size is not None:
            out["sensor_size"] = np.array(self.sensor_size, dtype=np.float64)
        if self.energy_outside is not None:
            out["energy_outside"] = self.energy_outside.detach().cpu().numpy()
        return out

    def save(self, path) -> None:
        """Write the map as a .npz (arrays of :meth:`to_numpy_dict`)."""
        import numpy as np

        np.savez(path, **self.to_numpy_dict())

    @classmethod
    def load(cls, path) -> "PSFMap":
        """Read a map written by :meth:`save`."""
        import numpy as np

        with np.load(path) as z:
            t = {k: torch.from_numpy(z[k]) for k in z.files}
        return cls(psf=t["psf"], centers=t["centers"], fields=t["fields"], positions=t["positions"], depths=t["depths"],
                   wavelengths=t["wavelengths"], pitch=float(t["pitch"]),
                   sensor_size=tuple(float(v) for v in t["sensor_size"]) if "sensor_size" in t else None,
                   energy_outside=t.get("energy_outside"))


def field_signature(model) -> tuple:
    """What a model's DOE-plane fields depend on besides their sources: ``model.field_signature()`` for a
    :class:`~raywave.hybrid.HybridLens` (lens, DOE grid and aperture, settings; not the DOE's phase); for any other
    object only the object itself. Two models with equal signatures build equal fields (:class:`DOEFieldCache`)."""
    own = getattr(model, "field_signature", None)
    return own() if callable(own) else (type(model).__name__, id(model))


class DOEFieldCache:
    """Detached DOE-plane fields of a **frozen** refractive lens, reused across :func:`psf_map` calls.

    Keys: (depth, θx, θy, wavelength, mode, rays) (a faithful-mode field keeps its first random draw). Least
    recently used fields are dropped beyond ``max_bytes``
    (default 4 GB; the bundled hybrid lens's fields are ~7–9 MB each). The cache remembers the optics that
    filled it (:func:`field_signature`: the refractive lens's exact parameters and structure, the DOE's grid
    and aperture, the hybrid's distances and settings, not the DOE's phase) and empties itself when asked by
    different optics, so two hybrids of one frozen lens (a design and its baseline DOE) can share it; a lens
    changed in place changes the signature too.
    """

    def __init__(self, max_bytes: float | None = 4e9):
        self.max_bytes = max_bytes
        self._store: OrderedDict = OrderedDict()
        self._signature: tuple | None = None
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(depth, field, wavelength, mode="accurate", rays=None) -> tuple:
        d = math.inf if depth is None else float(depth)
        return (round(d, 9) if math.isfinite(d) else d, round(float(field[0]), 10), round(float(field[1]), 10),
                round(float(wavelength), 10), mode, rays)

    @staticmethod
    def _nbytes(fd) -> int:
        return int(fd.envelope.numel() * fd.envelope.element_size())

    @property
    def nbytes(self) -> int:
        return sum(self._nbytes(v) for v in self._store.values())

    def __len__(self) -> int:
        return len(self._store)

    def clear(self) -> None:
        self._store.clear()

    def fields(self, model, fields: torch.Tensor, wavelengths, depth, mode: str = "accurate", rays=None,
               **field_kw) -> list:
        """Nested list ``[F][W]`` of detached DOE fields for these sources, tracing only the missing ones."""
        if not hasattr(model, "doe_fields"):
            raise TypeError(f"{type(model).__name__} has no doe_fields(): a DOE-field cache needs a HybridLens")
        sig = field_signature(model)
        if sig != self._signature:
            self.clear()
            self._signature = sig
        wls = [float(w) for w in torch.as_tensor(wavelengths, dtype=torch.float64, device="cpu").reshape(-1)]
        f = fields.detach().cpu().reshape(-1, 2)
        reach = round(float(field_kw.get("crop_reach", 0.0)), 12)  # the exact edge's lattice follows the crop's reach
        keys = [[self.key(depth, f[i], wl, mode, rays) + (reach,) for wl in wls] for i in range(f.shape[0])]
        missing_rows = [i for i in range(f.shape[0]) if any(k not in self._store for k in keys[i])]
        if missing_rows:
            self.misses += len(missing_rows)
            with torch.no_grad():  # a frozen lens: no graph to keep
                new = model.doe_fields(f[missing_rows], wls, depth, mode, rays, **field_kw)
            for r, row in zip(missing_rows, new):
                for k, fd in zip(keys[r], row):
                    self._store[k] = fd.detach()
        self.hits += f.shape[0] - len(missing_rows)
        out = []
        for row in keys:
            out.append([self._store[k] for k in row])
            for k in row:
                self._store.move_to_end(k)
        self._evict(protect={k for row in keys for k in row})
        return out

    def _evict(self, protect) -> None:
        if self.max_bytes is None:
            return
        total = self.nbytes
        for k in list(self._store):
            if total <= self.max_bytes:
                break
            if k in protect:
                continue
            total -= self._nbytes(self._store.pop(k))


def _as_depths(depths) -> list[float]:
    if depths is None:
        return [math.inf]
    ds = [float(d) for d in (depths if hasattr(depths, "__len__") else [depths])]
    if not ds:
        raise ValueError("depths: give at least one object distance (mm, or inf)")
    for d in ds:
        if not d > 0:
            raise ValueError(f"depths: object distances must be > 0 mm (or inf), got {d!r}")
    return ds


def _wavelength_list(wavelengths) -> list[float]:
    if wavelengths is None:
        from raywave.imaging.color import ColorSpec

        return [float(w) for w in ColorSpec().centers()]
    wl = [float(w) for w in torch.as_tensor(wavelengths, dtype=torch.float64, device="cpu").reshape(-1)]
    if not wl or not all(math.isfinite(w) and 0 < w <= 100 for w in wl):
        raise ValueError(f"wavelengths: give µm values > 0, got {wl!r}")
    return wl


def psf_map_points(model, fields, wavelengths=None, depth=None, ks: int = 64, cache: DOEFieldCache | None = None,
                   **psf_kw):
    """PSFs of a subset of field points, **with autograd** (the training replay recomputes chunks of a map).

    Args:
        model: a PSF model (``psf_result``).
        fields: ``(P, 2)`` field angles (deg), e.g. ``psf_map.flat_fields()[chunk]``.
        wavelengths: ``(W,)`` µm (default the R, G, B channel centres 0.66, 0.53, 0.47).
        depth: object distance (mm; ``inf``/None distant as the model defines).
        ks: PSF size (pixels).
        cache: a :class:`DOEFieldCache` (frozen lens: only the DOE and the propagation are differentiated).
        psf_kw: passed to ``model.psf_result`` (``mode``, ``rays``, ``propagation_dtype``, ...).

    Returns:
        the model's :class:`~raywave.hybrid.PSFResult` for the P points: ``psf`` ``(P, W, ks, ks)``, ``center``
        ``(P, W, 2)`` mm, ...
    """
    f = torch.as_tensor(fields, dtype=torch.float64)
    if f.ndim == 1:
        f = f[None]
    if f.ndim != 2 or f.shape[-1] != 2:
        raise ValueError(f"fields: give (P, 2) field angles in degrees, got shape {tuple(f.shape)}")
    wls = _wavelength_list(wavelengths)
    if cache is not None:
        field_keys, prop_keys = ("full_grid", "generator", "check", "trace_dtype"), ("propagation_dtype",)
        unknown = sorted(set(psf_kw) - set(field_keys) - set(prop_keys) - {"mode", "rays"})
        if unknown:
            raise ValueError(f"psf_map_points: {unknown} cannot be used with a DOE-field cache")
        rays = psf_kw.get("rays", getattr(model, "rays", None))
        model = _cache_target(model)
        reach = {"crop_reach": model.crop_reach(ks)} if hasattr(model, "crop_reach") else {}
        fds = cache.fields(model, f, wls, depth, psf_kw.get("mode", "accurate"), rays,
                           **{k: v for k, v in psf_kw.items() if k in field_keys}, **reach)
        kw = {k: v for k, v in psf_kw.items() if k in prop_keys}
        return model.psf_result(f, wls, ks=ks, depth=depth, cache=fds, **kw)
    return model.psf_result(f, wls, ks=ks, depth=depth, **psf_kw)


def _warn_crop(eo: torch.Tensor, fields: torch.Tensor, ds, wls, ks: int) -> None:
    """One :class:`PSFCropWarning` naming the worst PSF when any loses more than CROP_WARNING_FRACTION."""
    bad = eo > CROP_WARNING_FRACTION
    if not bool(bad.any()):
        return
    d, w, i, j = (int(v) for v in torch.nonzero(eo == eo.max())[0])
    f = [round(float(v), 4) for v in fields[i, j]]
    warnings.warn(f"{int(bad.sum())} of {eo.numel()} PSFs lose more than {CROP_WARNING_FRACTION:.0%} of their light "
                  f"outside the {ks}×{ks} crop; worst {float(eo.max()):.0%} at node ({i}, {j}) (field {f} deg, depth "
                  f"{ds[d]:g} mm, {wls[w]:g} µm): increase ks, or the beam is clipped by the DOE aperture",
                  PSFCropWarning, stacklevel=3)


def _cache_target(model):
    """The HybridLens whose DOE fields a cache holds: the model itself, or the engine a PSF model names as the
    source of its DOE-plane fields (``doe_field_source``, e.g. ``raywave.models.RayWaveModel``'s)."""
    if hasattr(model, "doe_fields"):
        return model
    hybrid = getattr(model, "doe_field_source", None)
    if hasattr(hybrid, "doe_fields"):
        return hybrid
    raise TypeError(f"{type(model).__name__} has no DOE-plane fields to cache (cache= needs a HybridLens or the "
                    "ray-wave model)")


def node_values(x: torch.Tensor, nodes) -> torch.Tensor:
    """Values of map-shaped ``x`` ``(W, N, M, ...)`` (e.g. ``psf_map.psf[d]``, its ``.grad`` or its centres) at
    flat node indices ``nodes`` (k = i·M + j, as :meth:`PSFMap.flat_fields`), in :func:`psf_map_points`'s layout
    ``(P, W, ...)``: the replay calls ``torch.autograd.backward(points.psf, node_values(psf.grad, chunk))``."""
    W, N, M = x.shape[:3]
    idx = torch.as_tensor(nodes, dtype=torch.long, device=x.device).reshape(-1)
    return x.reshape(W, N * M, *x.shape[3:]).index_select(1, idx).transpose(0, 1)


def default_batch(n_wavelengths: int) -> int:
    """Field points per model call so that ≲ :data:`DEFAULT_FIELDS_PER_CALL` DOE fields are held at once."""
    return max(1, DEFAULT_FIELDS_PER_CALL // max(1, n_wavelengths))


def _on_accelerator(model) -> bool:
    """Whether the model's parameters or buffers live on an accelerator (not the CPU)."""
    if not isinstance(model, torch.nn.Module):
        return False
    t = next(iter(model.parameters()), None)
    t = next(iter(model.buffers()), None) if t is None else t
    return t is not None and devices.accelerator(t)


def map_call_size(model, grad: bool, cache) -> int | None:
    """Sources (field points × wavelengths) per model call of a map without a field cache: the model's
    ``map_sources_per_call`` (a model that builds its fields in memory-bounded groups within a call and traces what
    its sources share once per call: :class:`~raywave.hybrid.HybridLens`, issue 43) without autograd, and with
    autograd on an accelerator (the map keeps every call's graph anyway, and each call is a few hundred kernel
    launches whatever its size: a 10×10×3 map's forward + backward on an H200 took 22.5 s in calls of 8 field points,
    5.4 s in calls of 100); else None (the fixed :func:`default_batch`; on a CPU a call's size changes no time, with a
    cache every field is kept)."""
    if cache is not None or (grad and not _on_accelerator(model)):
        return None
    return getattr(model, "map_sources_per_call", None)


def _map_fields(model, grid, fields, sensor_size, mapping, reference_wavelength, depth):
    """The map's node field angles ``(N, M, 2)`` (deg, float64) and sensor size ((w, h) mm, or None if unknown):
    ``fields`` when given, else :func:`field_grid` of ``grid`` at ``depth`` (mm, the map's first)."""
    size = sensor_size_of(model, sensor_size) if (sensor_size is not None or fields is None) else None
    if fields is None:
        return field_grid(model, grid, size, reference_wavelength, depth, mapping), size
    f_nm = torch.as_tensor(fields, dtype=torch.float64)
    if f_nm.ndim != 3 or f_nm.shape[-1] != 2:
        raise ValueError(f"fields: give (N, M, 2) field angles in degrees, got shape {tuple(f_nm.shape)}")
    if size is None:
        try:
            size = sensor_size_of(model)
        except (TypeError, ValueError):
            size = None  # unknown: the map's centres cannot be placed on a sensor (render without centres)
    return f_nm, size


def _pair_order(n: int, m: int) -> torch.Tensor:
    """The map's N×M nodes (row-major flat indices) in the order they are computed: from the outside in, the four
    mirror images ``(r, c), (r, M−1−c), (N−1−r, c), (N−1−r, M−1−c)`` side by side (fewer on the middle row or
    column), so that a chunk holds them together (one model call builds them from one DOE-plane field on a
    mirror-symmetric lens: :mod:`raywave.hybrid.mirror`)."""
    order = []
    for r in range((n + 1) // 2):
        for c in range((m + 1) // 2):
            for rr, cc in dict.fromkeys(((r, c), (r, m - 1 - c), (n - 1 - r, c), (n - 1 - r, m - 1 - c))):
                order.append(rr * m + cc)
    return torch.tensor(order, dtype=torch.long, device="cpu")  # host-side, like the field angles


def _map_chunks(n_points: int, n_wavelengths: int, batch: int | None,
                per_call: int | None = None) -> list[tuple[int, int]]:
    """[start, end) ranges of the ``n_points`` flat field points, ``batch`` per model call; default: ``per_call``
    sources (field points × wavelengths) when the model says how many one call takes (a model that bounds its own
    memory: :attr:`raywave.hybrid.HybridLens.map_sources_per_call`), else :func:`default_batch`."""
    if batch is None and per_call is not None:
        batch = max(1, int(per_call) // max(1, n_wavelengths))
    b = default_batch(n_wavelengths) if batch is None else int(batch)
    if b < 1:
        raise ValueError(f"batch must be >= 1 field point, got {batch}")
    return [(s, min(s + b, n_points)) for s in range(0, n_points, b)]


def _progress_disable(progress: bool | None, n_psfs: int):
    """tqdm's ``disable`` for a map of ``n_psfs`` PSFs (D·W·N·M): None (a bar only on a terminal) from
    _AUTO_PROGRESS_PSFS on when ``progress`` is None."""
    if progress is None:  # tqdm's disable=None: only on a terminal
        return None if n_psfs >= _AUTO_PROGRESS_PSFS else True
    return not progress


@contextlib.contextmanager
def _one_aperture_warning():
    """Merge the :class:`~raywave.hybrid.DOEApertureWarning` and :class:`~raywave.hybrid.VignettingEdgeWarning` of
    each model call inside (one per chunk and depth) into one a kind for the whole map, issued at the caller of
    :func:`psf_map`. Every other warning meets the caller's filters as it happens (an "error" filter still stops the
    map at once) and is shown as usual."""
    from raywave.hybrid.coherent.record import VignettingEdgeWarning
    from raywave.hybrid.hybrid_lens import DOEApertureWarning

    merged = (DOEApertureWarning, VignettingEdgeWarning)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DOEApertureWarning)  # collected here, filtered once merged
        warnings.simplefilter("always", VignettingEdgeWarning)
        yield

    def mergeable(w):
        return isinstance(w.message, merged) and w.message.entries

    for w in caught:  # the others passed the caller's filters already: show them as they were
        if not mergeable(w):
            warnings.showwarning(w.message, w.category, w.filename, w.lineno, w.file, w.line)
    aperture = [w.message for w in caught if mergeable(w) and isinstance(w.message, DOEApertureWarning)]
    for kind in ("beam", "band"):  # one warning per kind: the beam's clipping, the edge ripples'
        same = [w for w in aperture if getattr(w, "kind", "beam") == kind]
        if same:
            # stacklevel: this generator → contextlib's __exit__ → psf_map → psf_map's caller
            warnings.warn(DOEApertureWarning.merged(same, "map"), stacklevel=4)
    vignetted = [w.message for w in caught if mergeable(w) and isinstance(w.message, VignettingEdgeWarning)]
    if vignetted:  # the sources whose vignetting edge is cut without its waves: one warning for the map
        warnings.warn(VignettingEdgeWarning.merged(vignetted, "map"), stacklevel=4)


def _model_device(model) -> torch.device:
    """The device of a model's parameters (the CPU for a model without any)."""
    params = model.parameters() if isinstance(model, torch.nn.Module) else iter(())
    return next(params, torch.empty(0)).device


def _map_depths(model, flat, chunks, ds, wls, ks, cache, bar, psf_kw, store=None):
    """Per depth of ``ds`` (mm), the chunks' PSFs ``(F, W, ks, ks)``, centres ``(F, W, 2)`` mm (float64) and
    energies outside ``(F, W)``, each concatenated over the ``flat`` ``(F, 2)`` field points (deg); and the PSF
    pitch (mm). Runs in the caller's autograd mode; the ``bar`` counts PSFs (a chunk's field points × wavelengths).
    ``store``: a :class:`~raywave.imaging.map_checkpoint.MapCheckpoint`: its finished chunks are loaded, the others
    computed and written to it as they finish."""
    psfs, cens, outs = [], [], []
    pitch = None
    dev = _model_device(model)
    for di, d in enumerate(ds):
        dp, dc, do = [], [], []
        for s, e in chunks:
            got = store.load(di, (s, e)) if store is not None else None
            if got is not None:
                psf, cen, eo, pitch = got
                psf, cen, eo = psf.to(dev), cen.to(dev), eo.to(dev)
            else:
                res = psf_map_points(model, flat[s:e], wls, d, ks, cache, **psf_kw)
                psf, cen, eo, pitch = res.psf, res.center.to(torch.float64), res.energy_outside, float(res.pitch)
                if store is not None:
                    store.save(di, (s, e), psf, cen, eo, pitch)
            dp.append(psf), dc.append(cen), do.append(eo)
            bar.update((e - s) * len(wls))
        psfs.append(torch.cat(dp)), cens.append(torch.cat(dc)), outs.append(torch.cat(do))
    return psfs, cens, outs, pitch


def psf_map(model, grid=(10, 10), depths=(math.inf,), wavelengths=None, ks: int = 64, batch: int | None = None,
            progress: bool | None = None, cache: DOEFieldCache | None = None, fields=None, sensor_size=None,
            mapping: str = "chief_ray", reference_wavelength: float | None = None, grad: bool = False,
            checkpoint=None, **psf_kw) -> PSFMap:
    """The PSF map of ``model``: ``(D, W, N, M, ks, ks)`` PSFs on the N×M grid of :func:`field_grid`.

    Args:
        model: a PSF model (``psf_result``; a ``.lens`` for the field grid unless ``fields`` is given).
        grid: (N, M) nodes (rows along y, columns along x) or one integer.
        depths: object distances (mm, ``inf`` = distant); the field angles are those of the first depth.
        wavelengths: ``(W,)`` µm (default the channel centres R, G, B = 0.66, 0.53, 0.47; for training one
            :meth:`ColorSpec.sample` draw, for evaluation ``ColorSpec.all_wavelengths()`` then
            :meth:`PSFMap.channel_average`).
        ks: PSF size in sensor pixels.
        batch: field points per model call (all wavelengths together); default :func:`map_call_size` (without
            a cache, and without autograd or on a GPU, a HybridLens takes up to 512 sources a call) or
            :func:`default_batch`.
        progress: show a tqdm bar counting PSFs (depths × wavelengths × nodes, a chunk's worth at a time): True,
            False, or None (default): for maps of ≥ 100 PSFs when stderr is a terminal.
        cache: :class:`DOEFieldCache` of a frozen refractive lens (HybridLens only).
        fields: ``(N, M, 2)`` field angles (deg) instead of :func:`field_grid` (``positions`` are then those of
            ``grid``).
        sensor_size, mapping, reference_wavelength: see :func:`field_grid`.
        grad: keep autograd (default False: the map is computed without a graph).
        checkpoint: a folder (path) that makes the map resumable: each finished chunk is written there, and a
            map run again with the same folder after an interruption loads them and computes only the rest
            (:mod:`raywave.imaging.map_checkpoint`; a folder of another map is refused). Not with ``grad``.
        psf_kw: passed to ``model.psf_result`` (``mode``, ``rays``, ...).
    """
    from tqdm.auto import tqdm

    ds = _as_depths(depths)
    wls = _wavelength_list(wavelengths)
    if int(ks) < 1:
        raise ValueError(f"ks must be >= 1, got {ks}")
    f_nm, size = _map_fields(model, grid, fields, sensor_size, mapping, reference_wavelength, ds[0])
    n, m = f_nm.shape[:2]
    positions = normalised_grid((n, m), device="cpu")  # host-side, like the field angles
    order = _pair_order(n, m)  # mirror-image nodes side by side: a chunk holds both (built once, mirrored)
    flat = f_nm.reshape(-1, 2)[order]
    chunks = _map_chunks(flat.shape[0], len(wls), batch, map_call_size(model, grad, cache))
    store = None
    if checkpoint is not None:
        if grad:
            raise ValueError("psf_map: checkpoint= keeps finished PSFs on disk, without their autograd graph: it "
                             "cannot be used with grad=True")
        store = MapCheckpoint(checkpoint, map_key(model, flat, ds, wls, ks, chunks, psf_kw))
    disable = _progress_disable(progress, len(ds) * len(wls) * flat.shape[0])
    bar = tqdm(total=len(ds) * len(wls) * flat.shape[0], desc=f"PSF map {n}×{m}×{len(wls)}λ×{len(ds)} depth",
               unit="PSF", disable=disable, leave=False)
    ctx = torch.enable_grad() if grad else torch.no_grad()
    with ctx, _one_aperture_warning():
        psfs, cens, outs, pitch = _map_depths(model, flat, chunks, ds, wls, ks, cache, bar, psf_kw, store)
    bar.close()
    back = torch.argsort(order)  # the chunks' order back to row-major
    psfs, cens, outs = ([t[back] for t in ts] for ts in (psfs, cens, [torch.as_tensor(o) for o in outs]))
    # (D, F, W, ...) -> (D, W, N, M, ...)
    psf = torch.stack(psfs).transpose(1, 2).reshape(len(ds), len(wls), n, m, ks, ks)
    cen = torch.stack(cens).transpose(1, 2).reshape(len(ds), len(wls), n, m, 2)
    eo = torch.stack([torch.as_tensor(o) for o in outs]).transpose(1, 2).reshape(len(ds), len(wls), n, m)
    _warn_crop(eo.detach(), f_nm, ds, wls, ks)
    return PSFMap(psf=psf, centers=cen, fields=f_nm, positions=positions.to(f_nm.device),
                  depths=torch.tensor(ds, dtype=torch.float64, device="cpu"),
                  wavelengths=torch.tensor(wls, dtype=torch.float64, device="cpu"),
                  pitch=pitch, sensor_size=None if size is None else tuple(size), energy_outside=eo,
                  info={"mapping": mapping if fields is None else "given"})
