"""Ray tracing with the local grating approximation (Zemax's diffractive surfaces; Zhu et al. 2023), and its
incoherent PSF by ray binning.

The model (per field point and wavelength):

1. rays sample the stop uniformly (an ``rays × rays`` grid over the unit disk, every ray aimed exactly at
   its stop point) and are traced through the refractive lens (apertures clip) to the DOE plane; each carries
   the source's power per unit entrance-pupil area (:func:`raywave.lens.sources.source_weight`; the change of
   cell area by pupil distortion is ignored);
2. rays outside the DOE aperture are blocked; the DOE is a :class:`raywave.surfaces.interaction.Diffraction`
   surface (one more interaction, the vector law ``n2 d2_t = n1 d1_t + (m λ/2π) ∇φ`` with its OPL
   ``m λ φ/2π``), whose ∇φ comes from the DOE's pixel phase map at that wavelength
   (:class:`PixelPhaseGradient`: central differences of the phase differences wrapped into (−π, π], so a
   2π-wrapped kinoform has its smooth gradient, bilinearly interpolated at the hit point);
3. rays go straight to the sensor and are binned (nearest pixel, their power) into the ks×ks crop centred
   on the chief ray traced through the refractive lens only (the engine's convention); the crop sums to 1 and
   ``energy_outside`` is the power reaching the DOE that falls outside it.

Where the phase has **no gradient** (a binary or quantised profile's steps, pixel-to-pixel jumps: the wrapped
first differences change by more than ``jump_tolerance`` rad from one pixel to the next) the finite
differences bend rays by a meaningless angle and a flat step bends none: the model is wrong there, and a
:class:`DiscontinuousPhaseWarning` says where (pixels, radii, ray fraction). It also has no diffraction at all
(no Airy pattern, no edge diffraction, no orders other than ``order``).
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.hybrid.coherent import chief_rays
from raywave.lens.sources import VignettingWarning, point_source_rays, source_weight
from raywave.models.base import ModelPSFResult, PSFModel
from raywave.rays import pupil as pupil_patterns
from raywave.surfaces.interaction import Diffraction

__all__ = ["DiscontinuousPhaseWarning", "LocalGratingModel", "PixelPhaseGradient", "bin_rays"]

_TWO_PI = 2 * math.pi


class DiscontinuousPhaseWarning(UserWarning):
    """The DOE phase jumps between pixels: the local grating approximation has no gradient there."""


def _wrap(d: torch.Tensor) -> torch.Tensor:
    return torch.remainder(d + math.pi, _TWO_PI) - math.pi


def _central(d: torch.Tensor, dim: int, pitch: float) -> torch.Tensor:
    """Gradient (rad/mm) along ``dim`` from the first differences ``d`` (one shorter along ``dim``): central
    inside, one-sided at the two ends."""
    first = d.narrow(dim, 0, 1)
    last = d.narrow(dim, d.shape[dim] - 1, 1)
    mid = 0.5 * (d.narrow(dim, 0, d.shape[dim] - 1) + d.narrow(dim, 1, d.shape[dim] - 1))
    return torch.cat([first, mid, last], dim) / pitch


def _jumps(d: torch.Tensor, dim: int, tol: float) -> torch.Tensor:
    """Pixels where the wrapped first differences ``d`` change by more than ``tol`` (a step, not a slope)."""
    n = d.shape[dim] + 1
    bad = torch.zeros(d.shape[:dim] + (n,) + d.shape[dim + 1:], dtype=torch.bool, device=d.device)
    if d.shape[dim] >= 2:
        dd = (d.narrow(dim, 1, d.shape[dim] - 1) - d.narrow(dim, 0, d.shape[dim] - 1)).abs() > tol
        bad.narrow(dim, 1, n - 2).copy_(dd)
        # the two pixels on either side of the jump both see it in their central difference
        bad.narrow(dim, 0, n - 2).logical_or_(dd)
        bad.narrow(dim, 2, n - 2).logical_or_(dd)
    return bad


class PixelPhaseGradient:
    """The phase of a window of DOE pixels at one wavelength as a :class:`Diffraction` phase callable.

    Args:
        doe: the DOE; ``wavelength`` µm; ``bbox = (xmin, xmax, ymin, ymax)`` mm of the hits (the window is the
            DOE pixels covering it plus 2); ``jump_tolerance``: rad (see the module docstring).

    Attributes: ``phase``, ``gx``, ``gy`` (ny, nx) rad and rad/mm on the pixel centres; ``jump`` (ny, nx) bool;
    ``origin`` (x, y) mm of pixel (0, 0) of the window; ``rows``, ``cols`` its DOE pixel ranges.
    """

    def __init__(self, doe, wavelength: float, bbox, jump_tolerance: float = 0.1):
        p = doe.pitch
        ny, nx = doe.shape
        xc0, yc0 = -(nx - 1) / 2 * p, -(ny - 1) / 2 * p
        c0 = max(int(math.floor((bbox[0] - xc0) / p)) - 2, 0)
        c1 = min(int(math.ceil((bbox[1] - xc0) / p)) + 3, nx)
        r0 = max(int(math.floor((bbox[2] - yc0) / p)) - 2, 0)
        r1 = min(int(math.ceil((bbox[3] - yc0) / p)) + 3, ny)
        c1, r1 = max(c1, c0 + 2), max(r1, r0 + 2)
        c0, r0 = min(c0, nx - 2), min(r0, ny - 2)
        self.rows, self.cols = (r0, r1), (c0, c1)
        self.pitch = p
        self.origin = (xc0 + c0 * p, yc0 + r0 * p)
        with torch.no_grad():
            phi = doe.phase_pixels(wavelength, slice(r0, r1), slice(c0, c1)).to(torch.float64)
        dx, dy = _wrap(phi[:, 1:] - phi[:, :-1]), _wrap(phi[1:, :] - phi[:-1, :])
        self.phase = phi
        self.gx, self.gy = _central(dx, 1, p), _central(dy, 0, p)
        self.jump = _jumps(dx, 1, jump_tolerance) | _jumps(dy, 0, jump_tolerance)

    def _stencil(self, x, y):
        ny, nx = self.phase.shape
        fx = ((x - self.origin[0]) / self.pitch).clamp(0, nx - 1)
        fy = ((y - self.origin[1]) / self.pitch).clamp(0, ny - 1)
        i0 = fx.floor().clamp(max=nx - 2).long()
        j0 = fy.floor().clamp(max=ny - 2).long()
        return i0, j0, fx - i0, fy - j0

    def _interp(self, m, i0, j0, wx, wy):
        return ((m[j0, i0] * (1 - wx) + m[j0, i0 + 1] * wx) * (1 - wy)
                + (m[j0 + 1, i0] * (1 - wx) + m[j0 + 1, i0 + 1] * wx) * wy)

    def __call__(self, x, y, wavelength=None):
        """(φ, ∂φ/∂x, ∂φ/∂y) at the points (x, y) mm, bilinear in the pixel centres (the wavelength is the
        one the map was built for)."""
        i0, j0, wx, wy = self._stencil(x, y)
        return tuple(self._interp(m, i0, j0, wx, wy) for m in (self.phase, self.gx, self.gy))

    def on_jump(self, x, y) -> torch.Tensor:
        """Whether a point's bilinear stencil touches a discontinuous pixel (bool, shape of x)."""
        i0, j0, _, _ = self._stencil(x, y)
        j = self.jump
        return j[j0, i0] | j[j0, i0 + 1] | j[j0 + 1, i0] | j[j0 + 1, i0 + 1]

    def report(self, lit: torch.Tensor | None = None) -> dict:
        """Where the jumps are: count, fraction of the window, radii (mm), the first one's pixel and position."""
        jump = self.jump if lit is None else self.jump & lit
        n = int(jump.sum())
        out = {"pixels": n, "fraction": n / max(int(jump.numel() if lit is None else lit.sum()), 1)}
        if n:
            iy, ix = torch.nonzero(jump, as_tuple=True)
            x = self.origin[0] + ix.to(torch.float64) * self.pitch
            y = self.origin[1] + iy.to(torch.float64) * self.pitch
            r = torch.sqrt(x * x + y * y)
            out.update(r_min=float(r.min()), r_max=float(r.max()),
                       first_pixel=[int(iy[0]) + self.rows[0], int(ix[0]) + self.cols[0]],
                       first_xy=[float(x[0]), float(y[0])])
        return out


def bin_rays(x, y, weight, center, pitch: float, ks: int) -> torch.Tensor:
    """Sum ray powers ``weight`` (N,) at sensor points (x, y) (N,) mm into the ks×ks pixel grid whose pixel
    ``[ks//2, ks//2]`` is centred at ``center`` (x, y) mm; rays outside are dropped. Returns (ks, ks) float64."""
    ix = torch.floor((x - center[0]) / pitch + 0.5).long() + ks // 2
    iy = torch.floor((y - center[1]) / pitch + 0.5).long() + ks // 2
    ok = (ix >= 0) & (ix < ks) & (iy >= 0) & (iy < ks)
    out = torch.zeros(ks * ks, dtype=torch.float64, device=x.device)
    out.index_add_(0, (iy * ks + ix)[ok], weight[ok].to(torch.float64))
    return out.reshape(ks, ks)


class LocalGratingModel(PSFModel):
    """Ray tracing through the DOE with the local grating approximation, PSF by binning (module docstring).

    Args:
        hybrid: the :class:`~raywave.hybrid.HybridLens`.
        rays: pupil grid points per side (about 0.785·rays² rays per PSF; default 401).
        order: the diffraction order m the DOE sends the rays into.
        jump_tolerance: rad; a change of the wrapped phase difference by more than this between neighbouring
            pixels is a discontinuity (0.1 rad flags staircases of up to ~60 levels, never a smooth phase).
    """

    name = "raytrace"

    def __init__(self, hybrid, rays: int = 401, order: float = 1.0, jump_tolerance: float = 0.1):
        super().__init__(hybrid)
        if isinstance(rays, bool) or int(rays) != rays or int(rays) < 3:
            raise ValueError(f"rays must be an integer >= 3 (pupil grid points per side), got {rays!r}")
        self.rays = int(rays)
        self.order = float(order)
        self.jump_tolerance = float(jump_tolerance)

    def _doe_inside(self, x, y):
        doe = self.doe
        w, h = doe.size
        if doe.aperture == "circle":
            return x * x + y * y <= (0.5 * min(w, h)) ** 2
        return (x.abs() <= 0.5 * w) & (y.abs() <= 0.5 * h)

    def trace(self, field, wavelength: float, depth=None):
        """Rays of one field point (2,) at ``wavelength`` through lens and DOE to the sensor.

        Returns ``(at_sensor, weight, valid, on_jump, sampler)``: the bundle (N,) on the sensor plane, ray
        powers (N,), valid (N,), whether each ray crossed a discontinuity (N,), the phase sampler (or None)."""
        lens, hl = self.lens, self.hybrid
        px, py = pupil_patterns.grid(self.rays, "circle", device=lens.device)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", VignettingWarning)  # reported per PSF by the caller
            rays = point_source_rays(lens, field, wavelength, pupil=(px, py), aim="full", depth=depth)
            weight = source_weight(lens, rays, depth).reshape(-1)
            out = lens.trace(rays)
            n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
            at = out.propagate_to_z(hl.doe_z(), n)
            x, y = at.o[..., 0].reshape(-1), at.o[..., 1].reshape(-1)
            valid = at.valid.reshape(-1) & self._doe_inside(x, y)
            jump = torch.zeros_like(valid)
            sampler = None
            if bool(valid.any()):
                xv, yv = x[valid], y[valid]
                bbox = (float(xv.min()), float(xv.max()), float(yv.min()), float(yv.max()))
                sampler = PixelPhaseGradient(self.doe, wavelength, bbox, self.jump_tolerance)
                jump = sampler.on_jump(x, y) & valid
            else:
                def sampler_fn(x, y, w):
                    z = torch.zeros_like(x)
                    return z, z, z
            surface = Diffraction(sampler if sampler is not None else sampler_fn, self.order)
            d = at.d.reshape(-1, 3)
            one, zero = torch.ones_like(x), torch.zeros_like(x)
            wl = torch.full_like(x, float(wavelength))
            nn_ = torch.full_like(x, float(n.reshape(-1)[0]))
            dx, dy, dz, extra, ok = surface(x, y, d[:, 0], d[:, 1], d[:, 2], zero, zero, one, nn_, nn_, wl)
            valid = valid & ok
            o = at.o.reshape(-1, 3)
            from raywave.rays.bundle import RayBundle

            after = RayBundle(o, torch.stack([dx, dy, torch.where(valid, dz, one)], -1), wl, valid,
                              at.opl.reshape(-1) + extra)
            at_s = after.propagate_to_z(hl.sensor_z(), float(n.reshape(-1)[0]))
        return at_s, weight, valid, jump, sampler

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> ModelPSFResult:
        ks = self._check_ks(ks)
        hl = self.hybrid
        f = self._fields(fields)
        wls = self._wavelengths(wavelengths)
        with torch.no_grad():
            _, cs, _ = chief_rays(self.lens, f, torch.tensor(wls, dtype=torch.float64, device=self.lens.device), depth,
                                  hl.doe_z(),
                                  hl.sensor_z())
        psfs, centers, outs, nr, reports = [], [], [], [], []
        for i in range(f.shape[0]):
            pr, cr, orow, rr, rep_row = [], [], [], [], []
            for j, wl in enumerate(wls):
                at_s, w, valid, jump, sampler = self.trace(f[i], wl, depth)
                c = cs.o[i, j, :2].detach()
                xs, ys = at_s.o[:, 0], at_s.o[:, 1]
                total = float(w[valid].sum())
                psf = bin_rays(xs[valid], ys[valid], w[valid], (float(c[0]), float(c[1])), hl.sensor_pitch, ks)
                inside = float(psf.sum())
                psf = psf / inside if inside > 0 else psf
                rep = {"rays": int(valid.sum()), "rays_on_discontinuity": int(jump.sum()),
                       "fraction_on_discontinuity": float(jump.sum()) / max(int(valid.sum()), 1)}
                if sampler is not None:
                    rep.update({"doe_" + k: v for k, v in sampler.report().items()})
                if rep["rays_on_discontinuity"]:
                    self._warn(f[i], wl, rep)
                if total == 0.0:
                    warnings.warn(f"raytrace model: field {f[i].tolist()} at {wl:g} µm: no ray reaches the sensor "
                                  "(vignetted or outside the DOE); its PSF is all zeros", VignettingWarning,
                                  stacklevel=2)
                pr.append(psf), cr.append(c), rr.append(int(valid.sum())), rep_row.append(rep)
                orow.append(torch.tensor(max(1.0 - inside / total, 0.0) if total > 0 else 1.0, dtype=torch.float64,
                                         device=psf.device))
            psfs.append(torch.stack(pr)), centers.append(torch.stack(cr)), outs.append(torch.stack(orow))
            nr.append(rr), reports.append(rep_row)
        return ModelPSFResult(torch.stack(psfs), torch.stack(centers), torch.stack(outs), hl.sensor_pitch,
                              torch.tensor(nr, device="cpu"), model=self.name, info={"discontinuity": reports})

    def _warn(self, field, wl: float, rep: dict) -> None:
        where = ""
        if "doe_r_min" in rep:
            where = (f" at radii {rep['doe_r_min']:.4g}–{rep['doe_r_max']:.4g} mm on the DOE (first at pixel "
                     f"[iy, ix] = {rep['doe_first_pixel']}, (x, y) = ({rep['doe_first_xy'][0]:.4g}, "
                     f"{rep['doe_first_xy'][1]:.4g}) mm)")
        warnings.warn(
            f"raytrace model (local grating approximation): the DOE phase is discontinuous — it steps by more than "
            f"{self.jump_tolerance:g} rad between neighbouring pixels (binary / quantised levels or pixel jumps) in "
            f"{rep.get('doe_pixels', 0)} pixels{where}; it has no gradient there, and "
            f"{100 * rep['fraction_on_discontinuity']:.1f} % of the rays of field {[float(v) for v in field]} at "
            f"{wl:g} µm cross such a step and are bent by meaningless finite differences (rays on flat steps are "
            "not bent at all): this PSF is not physical, use the ray-wave model",
            DiscontinuousPhaseWarning, stacklevel=3)
