"""The pupil aberration model: the refractive lens as a Zernike-fitted wavefront on a circular pupil at the DOE
plane (Wyant & Creath 1992; the paper's Sec. 1.4 uses OpticStudio's Zernike Standard coefficients, 37 terms).

Per field point and wavelength:

1. rays (a ``rays × rays`` grid over the stop, aimed exactly, apertures clipping) are traced in float64 to
   the DOE plane; their optical paths give the wavefront there, and its **aberration** relative to the
   reference sphere converging to the chief ray's sensor point C: ``W(X) = OPL(X) + n|C − X|`` (mm, piston
   removed);
2. the **pupil** is the circle around the lit footprint (centre: the middle of its bounding box, radius: the
   farthest ray), and W is fitted by least squares with Noll-normalised Zernike polynomials
   (:func:`raywave.doe.params.zernike_noll`, Noll order, ``n_terms`` = 37 by default) in the normalised
   pupil coordinates; the fit's RMS residual (waves) is reported in ``info["residual_rms_waves"]``;
3. the **pupil function** on the DOE grid is uniform in amplitude inside that circle (anti-aliased edge,
   DOE aperture applied) with the phase of the reference sphere plus the fitted W;
4. DOE and propagation as the engine (:meth:`raywave.hybrid.HybridLens.propagate`), crop centred on the
   chief ray (the same C as the ray-wave model).

What it misses: the real footprint's shape (vignetted, elliptical off-axis pupils become circles), the
real amplitude (uniform instead of the ray density) and whatever of W the truncated Zernike series cannot
hold; so it agrees with ray-wave on axis and departs off axis.
"""

from __future__ import annotations

import math
import warnings

import torch

from raywave.doe.params import zernike_noll
from raywave.hybrid.coherent import DOEField, FieldInfo, chief_rays
from raywave.lens.sources import VignettingWarning, point_source_rays
from raywave.models.base import ModelPSFResult, PSFModel, lit_window, propagate_fields, window_field, window_xy
from raywave.rays import pupil as pupil_patterns
from raywave.utils.phasor import polar

__all__ = ["PupilModel", "ZernikeFit", "fit_zernike", "zernike_basis"]


def zernike_basis(rho: torch.Tensor, theta: torch.Tensor, n_terms: int) -> torch.Tensor:
    """Noll Zernike polynomials Z_1..Z_n_terms at (ρ, θ) (any shape S): (S..., n_terms) float64."""
    return torch.stack([zernike_noll(j, rho, theta) for j in range(1, n_terms + 1)], -1)


class ZernikeFit:
    """A least-squares Zernike fit of a wavefront on a circular pupil.

    Attributes: ``coefficients`` (n_terms,) mm of OPL (Noll order, ``[0]`` piston), ``center`` (x, y) mm and
    ``radius`` mm of the pupil, ``residual_rms`` mm (RMS of data − fit over the samples), ``n_samples``."""

    def __init__(self, coefficients, center, radius, residual_rms, n_samples):
        self.coefficients, self.center, self.radius = coefficients, center, radius
        self.residual_rms, self.n_samples = residual_rms, n_samples

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The fitted wavefront (mm) at (x, y) mm (broadcast)."""
        u, v = (x - self.center[0]) / self.radius, (y - self.center[1]) / self.radius
        u, v = torch.broadcast_tensors(u, v)
        rho, theta = torch.sqrt(u * u + v * v), torch.atan2(v, u)
        out = torch.zeros_like(rho)
        for j, c in enumerate(self.coefficients.tolist(), start=1):
            out = out + c * zernike_noll(j, rho, theta)
        return out


def fit_zernike(x: torch.Tensor, y: torch.Tensor, w: torch.Tensor, n_terms: int = 37, center=None,
                radius=None) -> ZernikeFit:
    """Fit ``w`` (N,) sampled at (x, y) (N,) mm with ``n_terms`` Noll Zernikes on the circle ``center``,
    ``radius`` (default: around the samples' bounding box, through the farthest sample)."""
    if x.numel() < n_terms:
        raise ValueError(f"a {n_terms}-term Zernike fit needs at least {n_terms} samples, got {x.numel()}")
    if center is None:
        center = (0.5 * float(x.min() + x.max()), 0.5 * float(y.min() + y.max()))
    if radius is None:
        radius = float(torch.sqrt((x - center[0]) ** 2 + (y - center[1]) ** 2).max()) * (1 + 1e-9)
    if not radius > 0:
        raise ValueError("the pupil has zero radius (all samples at one point)")
    u, v = (x - center[0]) / radius, (y - center[1]) / radius
    a = zernike_basis(torch.sqrt(u * u + v * v), torch.atan2(v, u), n_terms)
    c = torch.linalg.lstsq(a, w[:, None]).solution[:, 0]
    res = w - a @ c
    return ZernikeFit(c, center, radius, float(torch.sqrt((res * res).mean())), int(x.numel()))


class PupilModel(PSFModel):
    """Zernike pupil aberration model on the hybrid lens's DOE and sensor (module docstring).

    Args:
        hybrid: the :class:`~raywave.hybrid.HybridLens`.
        n_terms: Zernike terms (Noll order; 37 = OpticStudio's Zernike Standard set).
        rays: pupil grid points per side for the wavefront samples (default 64).
    """

    name = "pupil"

    def __init__(self, hybrid, n_terms: int = 37, rays: int = 64):
        super().__init__(hybrid)
        if isinstance(n_terms, bool) or int(n_terms) != n_terms or int(n_terms) < 1:
            raise ValueError(f"n_terms must be a positive integer, got {n_terms!r}")
        if isinstance(rays, bool) or int(rays) != rays or int(rays) < 4:
            raise ValueError(f"rays must be an integer >= 4, got {rays!r}")
        self.n_terms, self.rays = int(n_terms), int(rays)

    def fit(self, field, wavelength: float, depth=None, chief=None):
        """Zernike fit of the DOE-plane wavefront aberration of one field point (2,) at ``wavelength``.

        Returns ``(fit, chief_doe, chief_sensor, n)``: :class:`ZernikeFit`, the chief ray's bundles at the DOE
        and the sensor, and the image-space index; ``fit`` is None when every ray is vignetted."""
        lens, hl = self.lens, self.hybrid
        z_doe, z_sen = hl.doe_z(), hl.sensor_z()
        with torch.no_grad():
            if chief is None:
                f1 = torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(1, 2)
                w1 = torch.tensor([float(wavelength)], dtype=torch.float64, device=lens.device)
                cd, cs, _ = chief_rays(lens, f1, w1, depth, z_doe, z_sen)
                chief = (cd[0, 0], cs[0, 0])
            cd, cs = chief
            px, py = pupil_patterns.grid(self.rays, "circle", device=lens.device)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", VignettingWarning)
                rays = point_source_rays(lens, field, wavelength, pupil=(px, py), aim="full", depth=depth)
            out = lens.trace(rays)
            n = float(lens.surfaces[-1].material.n(out.wavelength).reshape(-1)[0])
            at = out.propagate_to_z(z_doe, n)
            v = at.valid.reshape(-1)
            if int(v.sum()) < self.n_terms:
                return None, cd, cs, n
            xy = at.o.reshape(-1, 3)[v]
            c3 = cs.o.reshape(3)
            w = at.opl.reshape(-1)[v] + n * torch.linalg.vector_norm(xy - c3, dim=-1)
            w = w - w.mean()
            return fit_zernike(xy[:, 0], xy[:, 1], w, self.n_terms), cd, cs, n

    def doe_field(self, fit: ZernikeFit | None, chief_doe, chief_sensor, n: float, wavelength: float) -> DOEField:
        """The pupil function on the DOE grid (DOE phase not applied) as a :class:`~raywave.hybrid.DOEField`."""
        hl, doe = self.hybrid, self.doe
        q = hl.oversample
        p = doe.pitch / q
        dev = doe.device
        alpha, beta = (float(v) for v in chief_doe.d.reshape(3)[:2])
        cx, cy = (float(v) for v in chief_doe.o.reshape(3)[:2])
        c3 = chief_sensor.o.reshape(3).detach()
        center = (c3[0], c3[1])
        z = hl.sensor_z() - hl.doe_z()
        win = None
        if fit is not None:
            (ox, oy), r = fit.center, fit.radius
            win, origin = lit_window(doe, q, (ox - r, ox + r, oy - r, oy + r), 2 * p)
        if win is None:
            env = torch.zeros((1, 1), dtype=torch.complex128, device=dev)
            return window_field(env, None, doe.sim_grid(q), (float(wavelength), n, (alpha, beta)), z, center,
                                FieldInfo(0, "pupil"))
        x, y = window_xy(win, origin, p, dev)
        k = 2 * math.pi / (wavelength * 1e-3)
        zc = hl.doe_z() - float(c3[2])
        sphere = torch.sqrt((x - c3[0]) ** 2 + (y - c3[1]) ** 2 + zc * zc)
        s_c = math.sqrt((cx - float(c3[0])) ** 2 + (cy - float(c3[1])) ** 2 + zc * zc)
        phase = k * (-n * (sphere - s_c) + fit(x, y)) - k * n * (alpha * (x - cx) + beta * (y - cy))
        rho = torch.sqrt((x - fit.center[0]) ** 2 + (y - fit.center[1]) ** 2)
        cover = (0.5 + (fit.radius - rho) / p).clamp(0.0, 1.0) * doe.coverage(win, q, device=dev)
        return window_field(polar(cover, phase), win, doe.sim_grid(q), (float(wavelength), n, (alpha, beta)), z,
                            center, FieldInfo(int(fit.n_samples), "pupil"))

    def psf_result(self, fields=(0.0, 0.0), wavelengths=None, ks: int = 64, depth=None) -> ModelPSFResult:
        ks = self._check_ks(ks)
        hl = self.hybrid
        f = self._fields(fields)
        wls = self._wavelengths(wavelengths)
        with torch.no_grad():
            cd, cs, _ = chief_rays(self.lens, f, torch.tensor(wls, dtype=torch.float64, device=self.lens.device), depth,
                                   hl.doe_z(),
                                   hl.sensor_z())
        fds, coef, resid, pupils = [], [], [], []
        for i in range(f.shape[0]):
            row, crow, rrow, prow = [], [], [], []
            for j, wl in enumerate(wls):
                fit, a, b, n = self.fit(f[i], wl, depth, chief=(cd[i, j], cs[i, j]))
                row.append(self.doe_field(fit, a, b, n, wl))
                lam_mm = wl * 1e-3
                if fit is None:
                    crow.append([0.0] * self.n_terms), rrow.append(math.nan), prow.append([math.nan] * 3)
                else:
                    crow.append([c / lam_mm for c in fit.coefficients.tolist()])
                    rrow.append(fit.residual_rms / lam_mm), prow.append([*fit.center, fit.radius])
            fds.append(row), coef.append(crow), resid.append(rrow), pupils.append(prow)
        info = {"zernike_waves": torch.tensor(coef, dtype=torch.float64, device="cpu"),
                "residual_rms_waves": torch.tensor(resid, dtype=torch.float64, device="cpu"),
                "pupil": torch.tensor(pupils, dtype=torch.float64, device="cpu"), "n_terms": self.n_terms}
        return propagate_fields(hl, fds, ks, self.name, info)
