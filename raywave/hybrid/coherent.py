"""Coherent ray tracing to the DOE plane and the complex field it carries there.

For one point source and one wavelength the refractive lens delivers, just before the DOE plane
``z = z_doe``, a wave whose optical path (OPL, mm), irradiance and edges follow from rays traced in float64.
Two constructions of the sampled field on the DOE simulation grid are provided:

``accurate`` (default)
    Trace *exactly aimed* rays to a coarse regular grid of nodes on the DOE plane (Newton on the entrance-pupil
    coordinates, every ray landing on its node to 1e-10 mm), and read off at every node the smooth real
    quantities of the wave there: the optical path Φ (corrected to the node by Malus–Dupin,
    ``Φ(x) = OPL + n d⊥·(x − X)``, which also gives the exact first-order derivative with respect to the lens
    parameters), the amplitude ``sqrt(irradiance / d_z)`` from the ray density (the Jacobian of the
    pupil → DOE map, by differences over the node grid), and the signed distance to every vignetting edge
    (each aperture's ``slack``, converted to DOE-plane mm by its gradient). These are interpolated to the
    fine grid with third-order cubic convolution, and only then is the phase formed, ``exp(i k Φ)``; edges
    are anti-aliased from the distance. Nothing is averaged as phasors, so the result does not alias when
    there are far fewer rays than pixels. Assumes the pupil → DOE map does not fold (no caustic between the
    lens and the DOE), which holds when the DOE is well away from focus; a fold is reported.

``faithful``
    The paper's method: rays sampled over the pupil, each ray's complex amplitude ``d_z · exp(i k OPL)``
    spread bilinearly into its four neighbouring pixels (:func:`raywave.wave.field.splat_bilinear`).

With the stop's edge at the exit pupil (``HybridLens(stop_edge="exit_pupil")``, :func:`exit_pupil_field`) the
accurate field either is built on the exit-pupil plane and propagated to the DOE plane by the angular spectrum
(``method="asm"``, exact), or carries on the DOE plane the knife-edge Fresnel factor of the edge diffracting
from the exit pupil (``method="fresnel"``, :func:`stop_edge_factor`: any beam size, the DOE grid only).

Both return :class:`DOEField` objects: the field's *envelope* on a window of the simulation grid (the
carrier ``exp(i k n (α x + β y))`` of the chief ray removed, so off-axis light stays far below Nyquist), with
the DOE aperture applied and the DOE phase not yet applied. Phases are formed from float64 optical paths.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch

from raywave.lens.sources import entrance_plane_z, point_source_rays, rays_through, source_weight
from raywave.utils.errors import check_allocation
from raywave.utils.safe import safe_sqrt
from raywave.wave.field import edge_coverage, splat_bilinear, upsample_nodes
from raywave.wave.propagation import propagate_window

__all__ = ["DOEField", "SamplingWarning", "accurate_field", "chief_rays", "doe_clipping", "doe_clippings",
           "exit_pupil_field", "footprints",
           "faithful_field"]

_NEWTON_TOL = 1e-10  # mm on the DOE plane
_NEWTON_ITERS = 25


class SamplingWarning(UserWarning):
    """A grid too coarse for the phase it must carry, or a ray map that cannot be interpolated."""


@dataclass
class DOEField:
    """The field arriving at the DOE plane for one point source and one wavelength.

    Attributes:
        envelope: complex128 ``(ny, nx)``: the field just before the DOE on the simulation-grid window,
            divided by the carrier ``exp(i k n (α x + β y))``; DOE aperture applied, DOE phase not.
        window: ``(iy0, ix0, ny, nx)`` in simulation-grid indices (for the DOE phase map).
        origin: ``(x, y)`` mm of the centre of window pixel (0, 0).
        pitch: simulation-grid pitch (mm).
        carrier: ``(α, β)`` direction cosines of the chief ray after the lens.
        n: refractive index between the DOE and the sensor.
        wavelength: µm.
        z: DOE → sensor distance (mm).
        center: ``(x, y)`` mm where the chief ray (through the refractive lens only) meets the sensor.
        rays: number of rays traced to build the field.
        mode: "accurate" or "faithful".
        full_grid: the envelope is the whole DOE grid with no carrier removed, for the paper's full 2×-padded
            angular-spectrum propagation.
        clipped: fraction of the beam's power (leaving the lens) that falls outside the DOE aperture and is
            blocked there (from traced rays; :func:`doe_clipping`).
        beam_half: largest |x| or |y| (mm) of the beam's geometric footprint on the DOE plane.
        stop_edge: where the field's geometric-optics edge was formed: "doe" (at the DOE plane) or
            "exit_pupil" (at the exit pupil, then propagated to the DOE plane by the angular spectrum).
        chief_tan: ``(d_x/d_z, d_y/d_z)`` of the chief ray between the DOE and the sensor (how far ``center``
            moves per mm of sensor displacement), set by ``HybridLens.doe_fields``; None (fields built elsewhere,
            or detached for a cache): the PSF is not differentiated with respect to the sensor distance.
    """

    envelope: torch.Tensor
    window: tuple
    origin: tuple
    pitch: float
    carrier: tuple
    n: float
    wavelength: float
    z: float
    center: tuple
    rays: int
    mode: str
    full_grid: bool = False
    clipped: float = 0.0
    beam_half: float = 0.0
    stop_edge: str = "doe"
    chief_tan: tuple | None = None

    @property
    def power(self) -> torch.Tensor:
        """∫|U|² dA over the DOE plane (relative power reaching the DOE through its aperture)."""
        return (self.envelope.abs() ** 2).sum() * self.pitch**2

    def detach(self) -> "DOEField":
        """A copy cut from the autograd graph (for caching with a frozen refractive lens): its PSF is not
        differentiated with respect to the lens, the sensor distance included (``chief_tan`` dropped)."""
        center = tuple(c.detach() if isinstance(c, torch.Tensor) else c for c in self.center)
        return replace(self, envelope=self.envelope.detach(), center=center, chief_tan=None)

    def to(self, dtype) -> "DOEField":
        """A copy with the envelope cast to ``dtype`` (e.g. complex64 for propagation only)."""
        return replace(self, envelope=self.envelope.to(dtype))


# ---------------------------------------------------------------------------------------------------------
# geometry shared by both modes
# ---------------------------------------------------------------------------------------------------------
def _medium_index(lens, wavelength: float) -> float:
    wl = torch.tensor(wavelength, dtype=torch.float64, device=lens.device)
    return float(lens.surfaces[-1].material.n(wl).detach())


def _check_beyond_last_surface(out, z_doe: float) -> None:
    z = out.o[..., 2].detach()
    z = z[out.valid] if bool(out.valid.any()) else z.new_zeros(1) - math.inf
    if z.numel() and float(z.max()) > z_doe + 1e-12:
        raise ValueError(f"the DOE plane (z = {z_doe:.6g} mm) cuts the last lens surface: a ray leaves it at "
                         f"z = {float(z.max()):.6g} mm; move the DOE further from the lens")


def chief_rays(lens, fields, wavelengths, depth, z_doe: float, z_sensor: float):
    """Chief rays (aimed at the stop centre, through the refractive lens only) at the DOE and the sensor.

    Returns ``(at_doe, at_sensor, uv)``: bundles of shape (F, W) and the chief rays' entrance-plane points
    (F, W, 2) mm (detached)."""
    cr = point_source_rays(lens, fields, wavelengths, pupil=(torch.zeros(1), torch.zeros(1)), aim="full", depth=depth)
    o, d = cr.o[:, :, 0].detach(), cr.d[:, :, 0].detach()
    uv = o[..., :2] + d[..., :2] * ((entrance_plane_z(lens) - o[..., 2:]) / d[..., 2:])
    out = lens.trace(cr, apertures=False)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at_doe = out.propagate_to_z(z_doe, n)
    at_sensor = out.propagate_to_z(z_sensor, n)
    return at_doe[:, :, 0], at_sensor[:, :, 0], uv


def _footprint(lens, field, wavelength, depth, z_doe: float, n_grid: int = 15, n_rim: int = 72, virtual: bool = False):
    """Lit bounding box ``(xmin, xmax, ymin, ymax)`` on the DOE plane (None if every ray is vignetted) of one
    field (2,) at one wavelength (1,) µm (:func:`footprints` of a 1×1 batch).

    ``virtual``: the plane may lie inside the lens (a virtual plane reached by extending the rays that leave
    the last surface backwards along straight lines, e.g. the exit pupil)."""
    return footprints(lens, torch.as_tensor(field).reshape(1, 2), wavelength, depth, z_doe, n_grid, n_rim,
                      virtual)[0][0]


def footprints(lens, fields, wavelengths, depth, z_doe: float, n_grid: int = 15, n_rim: int = 72,
               virtual: bool = False) -> list:
    """Lit bounding boxes ``(xmin, xmax, ymin, ymax)`` (mm) on the plane ``z_doe`` of fields (F, 2) at wavelengths
    (W,) µm, a nested list ``[F][W]`` (None where every ray is vignetted), from one trace of all F×W beams (~250
    rays each: the rim of the pupil and a grid inside, every ray aimed at its stop point). See :func:`_footprint`."""
    t = torch.linspace(0, 2 * math.pi, n_rim + 1, dtype=torch.float64)[:-1]
    g = torch.linspace(-1, 1, n_grid, dtype=torch.float64)
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    inside = gx**2 + gy**2 <= 1
    px = torch.cat([torch.cos(t), gx[inside]])
    py = torch.cat([torch.sin(t), gy[inside]])
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the caller reports vignetting once
        rays = point_source_rays(lens, fields, wavelengths, pupil=(px, py), aim="full", depth=depth)
        out = lens.trace(rays)
        if not virtual:
            _check_beyond_last_surface(out, z_doe)
        n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(z_doe, n)
        valid, x, y = at.valid, at.o[..., 0], at.o[..., 1]
        inf = torch.full_like(x, math.inf)
        box = torch.stack([torch.where(valid, x, inf).amin(-1), torch.where(valid, x, -inf).amax(-1),
                           torch.where(valid, y, inf).amin(-1), torch.where(valid, y, -inf).amax(-1)], -1).cpu()
        lit = valid.any(-1).cpu()
    return [[tuple(float(v) for v in box[i, j]) if bool(lit[i, j]) else None for j in range(box.shape[1])]
            for i in range(box.shape[0])]


def inside_doe(doe, xy: torch.Tensor) -> torch.Tensor:
    """Whether points ``xy`` (..., 2) mm on the DOE plane fall inside the DOE aperture (square grid or the
    inscribed circle), bool (...)."""
    w, h = doe.size
    if doe.aperture == "circle":
        return xy[..., 0] ** 2 + xy[..., 1] ** 2 <= (0.5 * min(w, h)) ** 2
    return (xy[..., 0].abs() <= 0.5 * w) & (xy[..., 1].abs() <= 0.5 * h)


def doe_clipping(lens, doe, field, wavelength, depth, z_doe: float, n_grid: int = 48) -> tuple[float, float]:
    """Fraction of the beam's power blocked by the DOE aperture, and the beam's half extent on the DOE plane.

    Rays on a regular ``n_grid``² grid over the stop (every ray aimed at its stop point, so each carries
    about the same power) are traced through the lens with its apertures (vignetted rays leave the beam
    before the DOE) to the plane ``z_doe``; each ray is weighted by :func:`source_weight`. Returns
    ``(blocked, half)``: the blocked power fraction (0..1) of the rays that leave the lens, and the largest
    |x| or |y| (mm) of their landing points (the half side of a centred square DOE that holds them all);
    ``(0, 0)`` if every ray is vignetted. Cheap (one batched trace of ~0.8·n_grid² rays); a diagnostic,
    not differentiable.

    Args: field (2,) in the lens's field type, wavelength (1,) µm tensor, depth (mm or None). Many fields and
    wavelengths at once: :func:`doe_clippings`."""
    return doe_clippings(lens, doe, torch.as_tensor(field).reshape(1, 2), wavelength, depth, z_doe, n_grid)[0][0]


def doe_clippings(lens, doe, fields, wavelengths, depth, z_doe: float, n_grid: int = 48) -> list:
    """:func:`doe_clipping` of fields (F, 2) at wavelengths (W,) µm from one trace of all F×W beams: a nested list
    ``[F][W]`` of ``(blocked, half)``. (The rays' aiming iterates over the whole batch, so the values can differ
    from single calls' in the last digits of the aim: ~1e-12 mm on the stop.)"""
    g = (torch.arange(n_grid, dtype=torch.float64) + 0.5) / n_grid * 2 - 1
    gx, gy = torch.meshgrid(g, g, indexing="xy")
    inside = gx**2 + gy**2 <= 1
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the caller reports vignetting once
        rays = point_source_rays(lens, fields, wavelengths, pupil=(gx[inside], gy[inside]), aim="full", depth=depth)
        out = lens.trace(rays)
        n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(z_doe, n)
        v = at.valid
        xy = at.o[..., :2]
        w = torch.where(v, source_weight(lens, rays, depth).expand_as(v), torch.zeros((), dtype=xy.dtype,
                                                                                        device=xy.device))
        blocked = (w * ~inside_doe(doe, xy)).sum(-1) / w.sum(-1).clamp_min(1e-300)
        half = torch.where(v[..., None], xy.abs(), torch.zeros((), dtype=xy.dtype, device=xy.device)).amax((-1, -2))
        lit = v.any(-1)
        blocked, half, lit = blocked.cpu(), half.cpu(), lit.cpu()
    return [[(float(blocked[i, j]), float(half[i, j])) if bool(lit[i, j]) else (0.0, 0.0)
             for j in range(v.shape[1])] for i in range(v.shape[0])]


def _sim_grid(doe, oversample: int):
    p = doe.pitch / oversample
    x0, y0 = doe.sim_origin(oversample)
    sy, sx = doe.sim_shape(oversample)
    return p, x0, y0, sy, sx


def _warn_nyquist(slope_ratio: torch.Tensor, lit: torch.Tensor, xy: torch.Tensor, field, wavelength, pitch) -> None:
    """Warn when the envelope's local phase slope exceeds Nyquist on lit samples."""
    if not bool(lit.any()):
        return
    r = torch.where(lit, slope_ratio.detach(), torch.zeros_like(slope_ratio))
    worst = int(torch.argmax(r))
    ratio = float(r.reshape(-1)[worst])
    if ratio > 1.0:
        x, y = (float(v) for v in xy.reshape(-1, 2)[worst])
        warnings.warn(
            f"DOE grid too coarse for field {list(map(float, field))} at {wavelength:g} µm: the wavefront's phase "
            f"slope reaches {ratio:.2f}× the Nyquist limit of the {pitch * 1e3:g} µm simulation pitch at "
            f"(x, y) = ({x:.4g}, {y:.4g}) mm on the DOE plane; the field aliases. Use a finer DOE pitch or "
            f"oversample ≥ {math.ceil(ratio * 1.05)}.", SamplingWarning, stacklevel=4)


#: peak bytes per simulation sample of building and propagating a DOE-plane field window (float64 interpolated
#: channels and coverage, the complex128 envelope, the DOE phase and the propagation's FFT buffers)
WINDOW_BYTES_PER_SAMPLE = 192


def check_window_memory(ny: int, nx: int, p: float, device=None) -> None:
    """Refuse (:class:`~raywave.utils.errors.MemoryLimitError`) a field window of ny×nx simulation samples of
    pitch ``p`` mm that would not fit in memory, before anything of that size is allocated."""
    check_allocation(float(ny) * float(nx) * WINDOW_BYTES_PER_SAMPLE,
                     f"the {ny}×{nx}-sample DOE-plane field (simulation pitch {p * 1e3:.3g} µm)",
                     "use a coarser DOE pitch (doe pitch / --doe-pitch), a lower oversample (--oversample) or a "
                     "smaller DOE", device)


def _window_for_bbox(bbox, margin: float, p, x0, y0, sy, sx):
    """Simulation-grid index ranges [j0, j1] (inclusive) covering bbox ± margin (unclamped)."""
    xmin, xmax, ymin, ymax = bbox
    jx0 = math.floor((xmin - margin - x0) / p)
    jx1 = math.ceil((xmax + margin - x0) / p)
    jy0 = math.floor((ymin - margin - y0) / p)
    jy1 = math.ceil((ymax + margin - y0) / p)
    return jy0, jy1, jx0, jx1


def _empty_field(doe, oversample, carrier, n, wavelength, z, center, rays, mode) -> DOEField:
    p, x0, y0, _, _ = _sim_grid(doe, oversample)
    env = torch.zeros((1, 1), dtype=torch.complex128, device=doe.device)
    return DOEField(env, (0, 0, 1, 1), (x0, y0), p, carrier, n, wavelength, z, center, rays, mode)


def _crop_to_lit(weight: torch.Tensor, *tensors):
    """Row/column bounds of the non-zero part of ``weight`` (ny, nx)."""
    rows = torch.nonzero(weight.detach().amax(1) > 0).squeeze(1)
    cols = torch.nonzero(weight.detach().amax(0) > 0).squeeze(1)
    if rows.numel() == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _common_setup(lens, doe, field, wavelength, z_doe, z_sensor, chief_doe, chief_sensor, oversample, field_type):
    """What both field constructions start from: field type, field (2,), wavelength (1,), medium index,
    simulation grid (p, x0, y0, sy, sx), carrier (α, β), chief-ray centre on the sensor, DOE → sensor distance."""
    field = torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(2)
    wl = torch.tensor([float(wavelength)], dtype=torch.float64, device=lens.device)
    carrier = tuple(float(v) for v in chief_doe.d[:2].detach())
    return (field_type or lens.field_type, field, wl, _medium_index(lens, wavelength), _sim_grid(doe, oversample),
            carrier, (chief_sensor.o[0], chief_sensor.o[1]), z_sensor - z_doe)


# ---------------------------------------------------------------------------------------------------------
# accurate mode
# ---------------------------------------------------------------------------------------------------------
def _trace_uv(lens, uv, field, wavelength, depth, z_doe, field_type, record=False, ep_z=None):
    """Trace rays crossing the entrance plane at ``uv`` (N, 2) to the DOE plane (apertures ignored)."""
    rays = rays_through(lens, uv[None, None], field[None], field_type, wavelength.reshape(1), depth=depth, ep_z=ep_z)
    res = lens.trace(rays, apertures=False, record=record)
    out, rec = res if record else (res, None)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, n)
    return rays, out, at, rec


@dataclass
class _TraceRequest:
    """One :func:`_trace_uv` call that a field construction (a generator, see :func:`run_batched`) asks for:
    rays through the entrance-plane points ``uv`` (N, 2) mm of field (2,) at wavelength (1,) µm, traced to the
    plane ``z_doe`` mm. ``grad``: traced with autograd (when the caller has it on); else without."""

    lens: object
    uv: torch.Tensor
    field: torch.Tensor
    wavelength: torch.Tensor
    depth: object
    z_doe: float
    field_type: str
    record: bool
    ep_z: float | None
    grad: bool

    def run(self):
        with torch.set_grad_enabled(self.grad and torch.is_grad_enabled()):
            return _trace_uv(self.lens, self.uv, self.field, self.wavelength, self.depth, self.z_doe, self.field_type,
                             record=self.record, ep_z=self.ep_z)

    def group_key(self) -> tuple:
        d = self.depth
        return (id(self.lens), float(self.wavelength.reshape(-1)[0]), float(self.z_doe), self.field_type, self.record,
                self.ep_z, self.grad, None if d is None else float(d), self.uv.device)


def _slice_bundle(b, g: int, n: int):
    """Request ``g``'s first ``n`` rays of a batched bundle (G, 1, N_max), as a (1, 1, n) bundle."""
    wl = b.wavelength if b.wavelength.ndim < 3 or b.wavelength.shape[0] == 1 else b.wavelength[g:g + 1]
    return type(b)(b.o[g:g + 1, :, :n], b.d[g:g + 1, :, :n], wl, b.valid[g:g + 1, :, :n], b.opl[g:g + 1, :, :n])


def _trace_group(reqs: list) -> list:
    """The :func:`_trace_uv` results of requests that share lens, wavelength, plane, depth and mode, from one batched
    trace: the rays of request g are row g of a (G, 1, N_max) bundle (the shorter requests padded with copies of
    their first ray, traced and dropped). Every ray is traced on its own (elementwise), so each request gets the
    values its own call would give (up to the last-bit rounding of vectorised transcendental functions)."""
    if len(reqs) == 1:
        return [reqs[0].run()]
    r0 = reqs[0]
    sizes = [r.uv.shape[0] for r in reqs]
    n_max = max(sizes)
    uv = torch.stack([torch.cat([r.uv, r.uv[:1].expand(n_max - r.uv.shape[0], 2)]) if r.uv.shape[0] < n_max
                      else r.uv for r in reqs])[:, None]
    fields = torch.stack([r.field.reshape(2) for r in reqs])
    with torch.set_grad_enabled(r0.grad and torch.is_grad_enabled()):
        rays = rays_through(r0.lens, uv, fields, r0.field_type, r0.wavelength.reshape(1), depth=r0.depth, ep_z=r0.ep_z)
        res = r0.lens.trace(rays, apertures=False, record=r0.record)
        out, rec = res if r0.record else (res, None)
        n = r0.lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(r0.z_doe, n)
    results = []
    for g, k in enumerate(sizes):
        rec_g = None
        if rec is not None:
            rec_g = type(rec)([tuple(c[g:g + 1, :, :k] for c in pts) for pts in rec.points],
                              [v[g:g + 1, :, :k] for v in rec.valid])
        results.append((_slice_bundle(rays, g, k), _slice_bundle(out, g, k), _slice_bundle(at, g, k), rec_g))
    return results


def run_serial(gen):
    """Run one field construction (a generator of :class:`_TraceRequest`, see :func:`run_batched`) with one trace
    per request; returns its result."""
    try:
        req = next(gen)
        while True:
            req = gen.send(req.run())
    except StopIteration as stop:
        return stop.value


def run_batched(gens: list) -> list:
    """Run several field constructions (generators that yield :class:`_TraceRequest` and return a
    :class:`DOEField`) together: in every round, the pending trace requests of all constructions that share a lens,
    wavelength, plane and mode are traced as one batch (:func:`_trace_group`: one ray trace for all fields instead
    of one per field, large enough for the elementwise kernels to use every thread). Each construction sees the
    results its own calls would give, so the fields equal :func:`run_serial`'s. Returns their results in order."""
    results = [None] * len(gens)
    pending = {}
    for i, g in enumerate(gens):
        try:
            pending[i] = next(g)
        except StopIteration as stop:
            results[i] = stop.value
    while pending:
        groups: dict = {}
        for i, req in pending.items():
            groups.setdefault(req.group_key(), []).append(i)
        answers = {}
        for idx in groups.values():
            for i, res in zip(idx, _trace_group([pending[i] for i in idx])):
                answers[i] = res
        pending = {}
        for i, res in answers.items():
            try:
                pending[i] = gens[i].send(res)
            except StopIteration as stop:
                results[i] = stop.value
    return results


def _landing_and_jacobian(lens, uv, field, wl, depth, z_doe, field_type, h, ep_z):
    """Landing points X (N, 2), validity (N,) and ∂X/∂uv (N, 2, 2) (forward differences, step h), from one
    batched trace of the 3N rays uv, uv + h·e_u, uv + h·e_v (a generator: yields that trace's request)."""
    n = uv.shape[0]
    du = torch.tensor([[h, 0.0], [0.0, h]], dtype=uv.dtype, device=uv.device)
    allv = torch.cat([uv, uv + du[0], uv + du[1]])
    _, _, at, _ = yield _TraceRequest(lens, allv, field, wl, depth, z_doe, field_type, False, ep_z, False)
    x = at.o[0, 0, :, :2]
    x0, xu, xv = x[:n], x[n:2 * n], x[2 * n:]
    jac = torch.stack([(xu - x0) / h, (xv - x0) / h], -1)
    return x0, at.valid[0, 0, :n], jac


def _solve2(j, r):
    """Solve j·s = r for 2×2 systems (N, 2, 2), (N, 2); singular systems give 0."""
    det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
    ok = det.abs() > 1e-300
    det = torch.where(ok, det, torch.ones_like(det))
    s0 = (j[:, 1, 1] * r[:, 0] - j[:, 0, 1] * r[:, 1]) / det
    s1 = (-j[:, 1, 0] * r[:, 0] + j[:, 0, 0] * r[:, 1]) / det
    return torch.where(ok[:, None], torch.stack([s0, s1], -1), torch.zeros_like(r)), ok


def _invert_to_nodes(lens, targets, uv_c, x_c, jac_c, field, wl, depth, z_doe, field_type, h, max_step, ep_z):
    """Newton: entrance-plane uv (N, 2) whose rays land on ``targets`` (N, 2) on the DOE plane.

    Every iteration is one batched trace (the rays and their two finite-difference neighbours). Steps longer
    than ``max_step`` (mm on the entrance plane) are shortened, which keeps the iteration inside the traceable
    region. Converged rays stay where they are, so each ray's iterates do not depend on the others. Returns (uv,
    converged (N,), Jacobian at the last iterate (N, 2, 2)); all detached (a generator: yields its traces)."""
    targets, uv_c, x_c, jac_c = (t.detach() for t in (targets, uv_c, x_c, jac_c))
    step0, _ = _solve2(jac_c.expand(targets.shape[0], 2, 2), targets - x_c)
    uv = uv_c + step0
    for _ in range(_NEWTON_ITERS):
        x, valid, jac = yield from _landing_and_jacobian(lens, uv, field, wl, depth, z_doe, field_type, h, ep_z)
        err = x - targets
        conv = valid & (err.abs().amax(-1) <= _NEWTON_TOL)
        if bool((conv | ~valid).all()):
            break
        step, ok = _solve2(jac, err)
        big = step.abs().amax(-1, keepdim=True)
        step = torch.where(big > max_step, step * (max_step / big), step)
        uv = torch.where((valid & ok & ~conv)[:, None], uv - step, uv)
    return uv, conv, jac


def _nearest_fill(values: torch.Tensor, good: torch.Tensor, xy: torch.Tensor, grad_xy: torch.Tensor | None = None):
    """Replace values (K, C) at ``~good`` nodes by their nearest good node's value, plus a first-order
    extension ``grad_xy·(x − x_v)`` for the first channel when ``grad_xy`` (K, 2) is given."""
    bad = ~good
    if not bool(bad.any()) or not bool(good.any()):
        return values
    gi = torch.nonzero(good).squeeze(1)
    bi = torch.nonzero(bad).squeeze(1)
    d = torch.cdist(xy[bi].detach(), xy[gi].detach())
    near = gi[d.argmin(1)]
    filled = values[near].clone()
    if grad_xy is not None:
        filled[:, 0] = filled[:, 0] + (grad_xy[near] * (xy[bi] - xy[near])).sum(-1)
    out = values.clone()
    out[bi] = filled
    return out


# ---- the stop's edge diffracting from the exit pupil: the Fresnel (knife-edge) step to the DOE plane
class _FresnelCS(torch.autograd.Function):
    """Fresnel integrals ``C(ν) = ∫₀^ν cos(πt²/2) dt`` and ``S(ν)`` (scipy, ~1e-15) of a real tensor, with the
    exact derivatives ``cos(πν²/2)``, ``sin(πν²/2)``."""

    @staticmethod
    def forward(ctx, nu):
        from scipy.special import fresnel

        s_, c_ = fresnel(nu.detach().cpu().numpy())
        ctx.save_for_backward(nu)
        return torch.from_numpy(c_).to(nu), torch.from_numpy(s_).to(nu)

    @staticmethod
    def backward(ctx, gc, gs):
        (nu,) = ctx.saved_tensors
        ph = 0.5 * math.pi * nu * nu
        out = torch.zeros_like(nu)
        if gc is not None:
            out = out + gc * torch.cos(ph)
        if gs is not None:
            out = out + gs * torch.sin(ph)
        return out


def _smoothstep(t: torch.Tensor) -> torch.Tensor:
    t = t.clamp(0.0, 1.0)
    return t * t * t * (10.0 + t * (6.0 * t - 15.0))


#: the edge wave's tail inside the beam is kept up to this many times the outer band's Fresnel parameter
INNER_TAIL = 1.0


def _nu_inner(ripple_zones: float) -> float:
    """Fresnel parameter inside the beam beyond which the edge wave's tail is dropped."""
    return INNER_TAIL * math.sqrt(2.0) * ripple_zones


def _zone_estimate(wavelength: float, n: float, dz: float, dz_focus: float, alpha: float, beta: float) -> float:
    """Upper estimate (mm) of the stop edge's Fresnel zone on the DOE plane ``sqrt(λ/n·|L|)`` (see
    :func:`_fresnel_scale`) from the chief ray: ``L = dz·M/cos³θ`` with the convergence ``M`` towards a focus
    ``dz_focus`` beyond the edge's plane (at least 0.1, at most 1), 30 % wider for the marginal rays' tilt."""
    m = min(max(abs(dz_focus - dz) / max(abs(dz_focus), 1e-12), 0.1), 1.0)
    cos2 = max(1.0 - alpha * alpha - beta * beta, 0.1)
    return 1.3 * math.sqrt(wavelength * 1e-3 / n * abs(dz) * m / cos2**1.5)


def _fresnel_scale(slopes, nx, ny, h_node: float, dz: float, lam_m: float, pitch: float) -> torch.Tensor:
    """Fresnel scale ``g = sqrt(2 / (λ_m L))`` (1/mm) of the stop's edge at the DOE-plane nodes (ky, kx), so that
    ``ν = g · s`` (s: signed DOE-plane distance to the edge's geometric shadow) is the knife-edge's Fresnel
    parameter.

    The edge is sharp on a plane ``dz`` mm before the DOE plane (the exit pupil); the wave runs along the local
    ray (direction cosines ``t``, ``γ``; straight lines in the image medium of wavelength ``λ_m = λ/n``). In the
    DOE-plane coordinates along the edge's normal ``n̂`` the knife-edge diffracts over the effective length

        ``L = dz · q · M``,  ``q = (1 − (n̂ × t)²) / γ³``,  ``M = |K⁻ᵀ n̂|``,  ``K = ∂x_edge/∂x_doe = I − dz ∇(t/γ)``:

    ``q`` the tilted plane wave's Fresnel length in plane coordinates (the angular spectrum's second order about
    the ray: ``1/γ³`` across the tilt, ``1/γ`` along it), ``M`` the local magnification of the edge's normal
    distance from the edge's plane to the DOE plane (a converging wave: the Fresnel scaling theorem,
    ``L = d (R − d)/R`` for a sphere of radius R). ``L`` is kept ≥ ``(1.5 p)²/λ_m`` so that the edge is never
    sharper than 1.5 pixels (anti-aliasing when the DOE sits at the exit pupil). Args: ``slopes`` (4, ky, kx):
    ``t_x/γ, t_y/γ, t_x, t_y`` at the nodes; ``nx, ny`` (ky, kx) the edge normal; ``h_node`` node spacing (mm).
    Differentiable with respect to the ray directions."""
    a, b, tx, ty = slopes
    da_dy, da_dx = torch.gradient(a, spacing=h_node, dim=(0, 1))
    db_dy, db_dx = torch.gradient(b, spacing=h_node, dim=(0, 1))
    k00, k01, k10, k11 = 1 - dz * da_dx, -dz * da_dy, -dz * db_dx, 1 - dz * db_dy
    det = k00 * k11 - k01 * k10
    det = torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    mx = (k11 * nx - k10 * ny) / det
    my = (-k01 * nx + k00 * ny) / det
    m_n = torch.sqrt(mx * mx + my * my + 1e-300)
    g2 = (1 - tx * tx - ty * ty).clamp_min(1e-6)
    q = (1 - (nx * ty - ny * tx) ** 2) / (g2 * torch.sqrt(g2))
    length = (abs(dz) * q * m_n).clamp_min((1.5 * pitch) ** 2 / lam_m)
    return torch.sqrt(2.0 / (lam_m * length))


def stop_edge_factor(nu: torch.Tensor, dz: float, ripple_zones: float, g: torch.Tensor, pitch: float,
                     curvature: torch.Tensor | None = None) -> torch.Tensor:
    """The knife-edge Fresnel diffraction factor (complex128, same shape as ``nu``) that multiplies the
    geometric-optics field near the stop edge's shadow on the DOE plane.

    ``D(ν) = ((1 − i)/2)·[(C(ν) + ½) + i(S(ν) + ½)]`` (Fresnel integrals; ``exp(−iωt)``: the kernel
    ``exp(+iπν²/2)``): 1 deep in the beam, ½ on the geometric edge (¼ of the intensity), → 0 in the shadow;
    its complex conjugate when the DOE plane lies before the edge's plane (``dz < 0``). Kept: the band
    ``ν ≥ −ν_max``, ``ν_max = ripple_zones·√2`` (ripple_zones Fresnel zones outside the shadow's edge, rolled off
    over the last zone), and the edge wave's tail inside the beam up to ``ν_b = min(3 ν_max, 0.6/(g p))`` (beyond,
    its fringes near the grid's Nyquist frequency and it leaves the PSF crop), blended smoothly to 1 from
    ``ν_b/2``. ``curvature``: ``s·κ`` (signed distance to the edge times the curvature ``−∇·n̂`` of the edge's
    level lines, > 0 for a convex aperture): the edge wave ``D − step`` of a curved edge converges (inside) or
    spreads (outside) like a cylindrical wave, amplitude ``sqrt(1 + s κ)``. Evaluated on the band only (1 inside,
    0 outside). Differentiable with respect to ``ν`` (exactly)."""
    nu_max = math.sqrt(2.0) * ripple_zones
    if isinstance(g, torch.Tensor):
        nu_b = torch.clamp(0.6 / (g.detach() * pitch), max=_nu_inner(ripple_zones)).clamp_min(2.0)
    else:
        nu_b = torch.full_like(nu.detach(), max(min(0.6 / (float(g) * pitch), _nu_inner(ripple_zones)), 2.0))
    inside = nu.detach() >= nu_b
    band = (nu.detach() > -nu_max) & ~inside
    out = inside.to(torch.complex128)
    idx = band.nonzero(as_tuple=True)
    if idx[0].numel() == 0:
        return out
    v = nu[idx]
    c_, s_ = _FresnelCS.apply(v)
    d = torch.complex(c_ + 0.5, s_ + 0.5)
    d = d * complex(0.5, -0.5) if dz >= 0 else d.conj() * complex(0.5, 0.5)
    w_out = _smoothstep((v + nu_max) / math.sqrt(2.0))
    nb = nu_b[idx]
    w_in = 1.0 - _smoothstep((v - 0.5 * nb) / (0.5 * nb))
    if curvature is not None:
        f = torch.sqrt(1.0 + curvature[idx].clamp(-0.9, 3.0))  # noqa: the edge wave's cylindrical spreading
        val = torch.where(v > 0, 1.0 + (d - 1.0) * f * w_in, d * f) * w_out
    else:
        val = (1.0 + (d - 1.0) * w_in) * w_out
    return out.index_put(idx, val)


#: stop-rim points at which :func:`stop_rim_images` finds the edge's image
RIM_POINTS = 64


def stop_rim_images(lens, field, wavelength: float, depth, field_type: str | None = None, k: int = RIM_POINTS):
    """Where the stop's rim is sharp, seen by one source: z (mm) of the image of every rim point along the ray
    that the source sends through it, ``(theta (k,), z (k,))`` with ``theta`` the rim point's azimuth on the stop
    (``atan2(y, x)`` of the stop coordinates); None when the rays cannot be traced.

    The image of a stop point P is where the rays through P from neighbouring sources cross (straight lines in
    the image medium, usually extended backwards to a virtual point inside the lens): the exit pupil is the
    image of the stop's centre, but off axis and at the rim the pupil's own aberrations move it (pupil spherical
    aberration, astigmatism). The neighbouring source is displaced along the rim point's radial direction (the
    edge's normal, the direction its Fresnel diffraction runs), to first order from central differences;
    the crossing is the closest approach of the two rays. Differentiable with respect to the lens (the rays are
    traced with autograd when it is on)."""
    field_type = field_type or lens.field_type
    f = torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(2)
    fmax = max([abs(float(v)) for v in getattr(lens, "fields", [])] + [0.0]) or 1.0
    eps = 1e-3 * fmax
    ex = torch.tensor([eps, 0.0], dtype=f.dtype, device=f.device)
    ey = torch.tensor([0.0, eps], dtype=f.dtype, device=f.device)
    fields = torch.stack([f, f + ex, f + ey, f - ex, f - ey])  # central differences
    theta = torch.arange(k, dtype=torch.float64, device=lens.device) * (2 * math.pi / k)
    c, s = torch.cos(theta), torch.sin(theta)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rays = point_source_rays(lens, fields, torch.tensor([float(wavelength)], dtype=torch.float64),
                                 pupil=(c, s), aim="full", depth=depth, field_type=field_type)
        out = lens.trace(rays, apertures=False)
    o, d, v = out.o[:, 0], out.d[:, 0], out.valid[:, 0]  # (5, k, 3)
    if not bool(v.all()):
        return None
    do = c[:, None] * (o[1] - o[3]) + s[:, None] * (o[2] - o[4])  # (k, 3): the radially displaced source's ray
    dd = c[:, None] * (d[1] - d[3]) + s[:, None] * (d[2] - d[4])
    a = d[0]

    def perp(v_):
        return v_ - (v_ * a).sum(-1, keepdim=True) * a

    po, pd = perp(do), perp(dd)
    t = -(po * pd).sum(-1) / (pd * pd).sum(-1).clamp_min(1e-300)
    z = o[0, :, 2] + t * a[:, 2]
    if not bool(torch.isfinite(z.detach()).all()):
        return None
    return theta, z


def _rim_z(rim, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """z of the stop rim's image (:func:`stop_rim_images`) at the azimuth of stop points (xs, ys), periodic linear
    interpolation (differentiable; the stop's centre, where the azimuth is undefined, gets the image of azimuth 0)."""
    theta, z = rim
    k = theta.numel()
    ok = (xs * xs + ys * ys).detach() > 0
    az = torch.atan2(torch.where(ok, ys, torch.zeros_like(ys)), torch.where(ok, xs, torch.ones_like(xs)))
    az = torch.remainder(az, 2 * math.pi)
    u = az / (2 * math.pi / k)
    i0 = torch.floor(u.detach()).long().clamp(0, k - 1)
    w = u - i0
    return z[i0] * (1 - w) + z[(i0 + 1) % k] * w


def accurate_field(lens, doe, field, wavelength: float, depth, z_doe: float, z_sensor: float, chief_doe, chief_sensor,
                   nodes: int = 64, oversample: int = 1, field_type: str | None = None, check: bool = True,
                   chief_uv=None, virtual: bool = False, stop_plane: float | None = None,
                   ripple_zones: float | None = None) -> DOEField:
    """The accurate DOE-plane field for one field point (2,) and one wavelength (µm).

    Args:
        virtual: build the field on a plane ``z_doe`` that may lie inside the lens (reached by extending the
            rays leaving the last surface along straight lines in the image medium, e.g. the exit pupil),
            on the DOE's simulation lattice extended without bound and without the DOE aperture (the
            returned window indices may be negative or beyond the DOE grid).
        nodes: number of traced nodes across the larger side of the lit footprint (the ray budget is about
            ``nodes²``); the field is smooth, so 32–64 are plenty for most lenses.
        chief_doe, chief_sensor: the chief ray (RayBundle, scalar batch) at the DOE and at the sensor.
        chief_uv: its entrance-plane point (2,) mm, if known (saves aiming it again).
        stop_plane: z (mm) of the plane where the stop's edge is sharp (the exit pupil): the stop's edge is then
            not cut sharply on this plane but carries its Fresnel diffraction from that plane (the knife-edge
            factor of :func:`stop_edge_factor`); None: the paper's sharp edge on this plane.
        ripple_zones: with ``stop_plane``: Fresnel zones of the edge's ripples kept outside the geometric
            footprint (default :data:`RIPPLE_ZONES`).
    """
    return run_serial(accurate_field_steps(lens, doe, field, wavelength, depth, z_doe, z_sensor, chief_doe,
                                           chief_sensor, nodes=nodes, oversample=oversample, field_type=field_type,
                                           check=check, chief_uv=chief_uv, virtual=virtual, stop_plane=stop_plane,
                                           ripple_zones=ripple_zones))


def accurate_field_steps(lens, doe, field, wavelength: float, depth, z_doe: float, z_sensor: float, chief_doe, chief_sensor,
                   nodes: int = 64, oversample: int = 1, field_type: str | None = None, check: bool = True,
                   chief_uv=None, virtual: bool = False, stop_plane: float | None = None,
                   ripple_zones: float | None = None, bbox=None, stop_rim=None):
    """:func:`accurate_field` as a generator: yields the :class:`_TraceRequest` of every ray trace it needs and
    receives its result, returns the :class:`DOEField` (run it with :func:`run_serial`, or many together with
    :func:`run_batched`: one batched trace per round for all of them). ``bbox``: the lit footprint on the plane
    (:func:`footprints`; ``False``: none, every ray vignetted) when the caller traced it already (None: traced
    here). ``stop_rim``: with ``stop_plane``, the images of the stop's rim (:func:`stop_rim_images`): the edge's
    Fresnel step then runs from the rim point's own image at every node (its azimuth on the stop) instead of from
    the plane ``stop_plane``."""
    field_type, field, wl, n, (p, x0, y0, sy, sx), (alpha, beta), center, zprop = _common_setup(
        lens, doe, field, wavelength, z_doe, z_sensor, chief_doe, chief_sensor, oversample, field_type)
    if bbox is False:  # given: every ray is vignetted
        bbox = None
    elif bbox is None:
        bbox = _footprint(lens, field, wl, depth, z_doe, virtual=virtual)
    if bbox is None:
        return _empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, 0, "accurate")

    # ---- node grid: spacing h, symmetric about the chief ray's landing point (so a symmetric lens gives an
    # exactly symmetric field), covering the footprint + margin; nodes need not sit on simulation pixels
    xcd, ycd = (float(v) for v in chief_doe.o[:2].detach())
    extent = max(bbox[1] - bbox[0], bbox[3] - bbox[2], p)
    h_node = extent / max(nodes - 1, 2)
    margin = 2.5 * h_node + 2 * p
    if stop_plane is not None:
        ripple_zones = RIPPLE_ZONES if ripple_zones is None else float(ripple_zones)
        z_edge = stop_plane
        if stop_rim is not None:  # the rim image farthest from the DOE plane sets the widest band
            zr = stop_rim[1].detach()
            z_far = float(zr.min() if z_doe >= stop_plane else zr.max())
            if (z_doe - z_far) * (z_doe - stop_plane) > 0 and abs(z_doe - z_far) > abs(z_doe - stop_plane):
                z_edge = z_far
        margin += (ripple_zones + 1) * _zone_estimate(wavelength, n, z_doe - z_edge, z_sensor - z_edge, alpha, beta)
    half_x = max(xcd - bbox[0], bbox[1] - xcd) + margin
    half_y = max(ycd - bbox[2], bbox[3] - ycd) + margin
    kx = 2 * math.ceil(half_x / h_node) + 1
    ky = 2 * math.ceil(half_y / h_node) + 1
    dev = lens.device
    gx = xcd + (torch.arange(kx, dtype=torch.float64, device=dev) - (kx - 1) / 2) * h_node
    gy = ycd + (torch.arange(ky, dtype=torch.float64, device=dev) - (ky - 1) / 2) * h_node
    tx, ty = torch.meshgrid(gx, gy, indexing="xy")  # (ky, kx)
    targets = torch.stack([tx, ty], -1).reshape(-1, 2)

    # ---- chief ray's entrance-plane point and Jacobian: the linear first guess
    ep_z = entrance_plane_z(lens)
    if chief_uv is None:
        ep_rays = point_source_rays(lens, field, wl, pupil=(torch.zeros(1), torch.zeros(1)), aim="full", depth=depth)
        o, d = ep_rays.o[0, 0, 0].detach(), ep_rays.d[0, 0, 0].detach()
        chief_uv = o[:2] + d[:2] * (ep_z - o[2]) / d[2]
    uv_c = torch.as_tensor(chief_uv, dtype=torch.float64, device=lens.device).reshape(1, 2)
    r_ep = 0.5 * float(lens.paraxial().epd)
    h = 1e-6 * max(r_ep, 1e-3)
    x_c, _, jac_c = yield from _landing_and_jacobian(lens, uv_c, field, wl, depth, z_doe, field_type, h, ep_z)
    uv, conv, jac = yield from _invert_to_nodes(lens, targets, uv_c, x_c, jac_c, field, wl, depth, z_doe, field_type, h,
                                     max_step=0.25 * r_ep, ep_z=ep_z)

    # ---- the differentiable trace of the node rays. The landing point of a node's ray must stay on its node
    # when the lens changes: one Newton step with the (detached) Jacobian, uv_lin = uv − J⁻¹(X(uv) − T), equals
    # uv in value and carries d(uv)/dθ = −J⁻¹ ∂X/∂θ, so everything traced at uv_lin (path, directions, aperture
    # slacks, ray density) has its exact first-order derivative with respect to the lens parameters.
    _, _, at0, _ = yield _TraceRequest(lens, uv, field, wl, depth, z_doe, field_type, False, ep_z, True)
    jinv_step, _ = _solve2(jac, (at0.o[0, 0, :, :2] - targets))
    uv_lin = uv - jinv_step
    rays, out, at, rec = yield _TraceRequest(lens, uv_lin, field, wl, depth, z_doe, field_type, True, ep_z, True)
    X = at.o[0, 0, :, :2]
    dvec = at.d[0, 0]
    good = conv & at.valid[0, 0]
    phi = at.opl[0, 0] + n * ((targets - X) * dvec[:, :2]).sum(-1)  # Malus–Dupin: Φ at the node itself
    w0 = source_weight(lens, rays, depth)[0, 0]
    gamma = dvec[:, 2]
    slacks = [s.aperture.slack(*(c[0, 0] for c in rec.points[i + 1][:2]))
              for i, s in enumerate(lens.surfaces) if s.aperture is not None]
    is_stop = [i == lens.stop_index for i, s in enumerate(lens.surfaces) if s.aperture is not None]
    diffracting = stop_plane is not None and any(is_stop)
    slopes = [dvec[:, 0] / dvec[:, 2], dvec[:, 1] / dvec[:, 2], dvec[:, 0], dvec[:, 1]] if diffracting else []

    # ---- nodes whose ray failed (missed a surface, TIR, Newton) take their nearest good neighbour's values
    if not bool(good.any()):
        warnings.warn(f"no ray could be traced to the DOE plane for field {field.tolist()} at {wavelength:g} µm",
                      SamplingWarning, stacklevel=3)
        return _empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, targets.shape[0], "accurate")
    chan = torch.stack([phi, w0, gamma, uv_lin[:, 0], uv_lin[:, 1]] + slacks + slopes, -1)
    chan = _nearest_fill(chan, good, targets, grad_xy=n * dvec[:, :2])
    grid = chan.T.reshape(-1, ky, kx)
    phi_g, w0_g, gamma_g, u_g, v_g = grid[:5]
    # ray density |det ∂uv/∂x| by central differences over the node grid
    du_dy, du_dx = torch.gradient(u_g, spacing=h_node, dim=(0, 1))
    dv_dy, dv_dx = torch.gradient(v_g, spacing=h_node, dim=(0, 1))
    det = du_dx * dv_dy - du_dy * dv_dx
    amp2 = w0_g * det.abs() / gamma_g
    # distance (DOE-plane mm) to the nearest aperture edge: slack / |∇_x slack|
    dist = None
    stop_edge = None  # (distance, edge normal) of the stop's edge when it diffracts from stop_plane
    other = None  # distance to the nearest other edge
    for j, sl in enumerate(grid[5:5 + len(slacks)]):
        gy_, gx_ = torch.gradient(sl.detach(), spacing=h_node, dim=(0, 1))
        gn = torch.sqrt(gx_**2 + gy_**2).clamp_min(1e-12)
        dj = sl / gn
        dist = dj if dist is None else torch.minimum(dist, dj)
        if diffracting and is_stop[j]:
            # the Fresnel step reads the distance far from the edge (ν = g·s over several zones) and the edge's
            # normal (Fresnel length, curvature): both differentiated, |∇ slack| (the ray map's magnification of
            # the stop) included; same values as the detached ones
            gy_l, gx_l = torch.gradient(sl, spacing=h_node, dim=(0, 1))
            n2 = gx_l**2 + gy_l**2
            ok = n2 > 1e-24  # = the clamp at 1e-12 below, with a finite derivative at the stop's centre (kink)
            gn_l = torch.where(ok, safe_sqrt(n2, ok), torch.full_like(n2, 1e-12))
            stop_edge = (sl / gn_l, gx_l / gn_l, gy_l / gn_l)
        elif diffracting:
            other = dj if other is None else torch.minimum(other, dj)
    # only the distance near an edge matters; clamping keeps the cubic interpolation from ringing where
    # the slack has a kink (a circular aperture's centre) or far from any edge
    lim = 3.0 * h_node
    dist = torch.full_like(phi_g, lim) if dist is None else dist.clamp(-lim, lim)
    if diffracting:  # the stop's edge gets its own channels: distance and Fresnel scale
        dz_edge = z_doe - stop_plane
        if stop_rim is not None:  # the rim point's own image, by the node ray's azimuth on the stop
            sx_, sy_ = (c[0, 0] for c in rec.points[lens.stop_index + 1][:2])
            dz_n = z_doe - _rim_z(stop_rim, sx_, sy_)
            dz_n = _nearest_fill(dz_n[:, None], good, targets)[:, 0].reshape(ky, kx)
            if bool((dz_n * dz_edge > 0).all()):  # same side of the DOE plane as the pupil (else: the plane)
                dz_edge = dz_n
        g_s = _fresnel_scale(grid[5 + len(slacks):], stop_edge[1], stop_edge[2], h_node, dz_edge,
                             wavelength * 1e-3 / n, p)
        # ν = g·s and s·κ vary smoothly: interpolated as they are (clamped where the factor is 1 or 0 anyway)
        nu_lim = _nu_inner(ripple_zones) + 4.0
        s_stop = stop_edge[0]
        ndy = torch.gradient(stop_edge[2], spacing=h_node, dim=0)[0]
        ndx = torch.gradient(stop_edge[1], spacing=h_node, dim=1)[0]
        near = (s_stop * g_s).detach().abs() < nu_lim
        g_max = float(g_s.detach()[near].max()) if bool(near.any()) else float(g_s.detach().max())
        edge_chan = ([] if other is None else [other.clamp(-lim, lim)]) + [
            (s_stop * g_s).clamp(-nu_lim, nu_lim), (s_stop * -(ndx + ndy)).clamp(-0.9, 3.0)]
    else:
        edge_chan = []
    lit_nodes = (dist > -h_node) & good.reshape(ky, kx)
    fold = (det.detach() * det.detach()[ky // 2, kx // 2] <= 0) & lit_nodes
    if check and bool(fold.any()):
        warnings.warn(f"the ray map from the pupil to the DOE plane folds (a caustic lies between the lens and the "
                      f"DOE) for field {field.tolist()} at {wavelength:g} µm; the accurate field is wrong there: "
                      "use mode='faithful' or move the DOE", SamplingWarning, stacklevel=3)
    if check:
        slope = n * torch.sqrt((dvec[:, 0] - alpha) ** 2 + (dvec[:, 1] - beta) ** 2).reshape(ky, kx)
        ratio = slope * (2 * p) / (wavelength * 1e-3)
        _warn_nyquist(ratio, lit_nodes, targets, field.tolist(), wavelength, p)

    # ---- reference removal (chief OPL, carrier), interpolation to the fine grid
    phi_c = phi_g[ky // 2, kx // 2].detach()
    phi_env = phi_g - phi_c - n * (alpha * tx + beta * ty)
    # fine window: the simulation pixels inside the node span, clamped to the DOE grid
    jx0, jy0 = math.ceil((float(gx[0]) - x0) / p), math.ceil((float(gy[0]) - y0) / p)
    jx1, jy1 = math.floor((float(gx[-1]) - x0) / p), math.floor((float(gy[-1]) - y0) / p)
    if not virtual:
        jx0, jy0, jx1, jy1 = max(0, jx0), max(0, jy0), min(sx - 1, jx1), min(sy - 1, jy1)
    if jx1 < jx0 or jy1 < jy0:
        return _empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, targets.shape[0], "accurate")
    check_window_memory(jy1 - jy0 + 1, jx1 - jx0 + 1, p, dev)
    pos_x = (x0 + torch.arange(jx0, jx1 + 1, dtype=torch.float64, device=dev) * p - float(gx[0])) / h_node
    pos_y = (y0 + torch.arange(jy0, jy1 + 1, dtype=torch.float64, device=dev) * p - float(gy[0])) / h_node
    # amplitude sqrt(amp2): zero where the ray density vanishes (a dead or degenerate node), with a finite
    # (zero) gradient there: sqrt's derivative at 0 is infinite, so the double-where keeps it out of the graph
    lit_amp = amp2 > 0
    amp = torch.where(lit_amp, safe_sqrt(amp2, lit_amp), torch.zeros_like(amp2))
    fine = upsample_nodes(torch.stack([phi_env, amp] + ([] if diffracting else [dist])
                                      + edge_chan),
                          pos_y=pos_y.clamp(0, ky - 1), pos_x=pos_x.clamp(0, kx - 1))
    win = (jy0, jx0, jy1 - jy0 + 1, jx1 - jx0 + 1)
    if diffracting:
        edge = stop_edge_factor(fine[-2], z_doe - stop_plane, ripple_zones, g_max, p, curvature=fine[-1])
        cov = edge_coverage(fine[2], p) if other is not None else None
    else:
        edge = None
        cov = edge_coverage(fine[2], p)
    if not virtual:
        dcov = doe.coverage(win, oversample, device=dev)
        cov = dcov if cov is None else cov * dcov
    if edge is not None:  # the Fresnel factor is 0 beyond the ripple band
        band = (fine[-2].detach() > -math.sqrt(2.0) * ripple_zones).to(torch.float64)
        b = _crop_to_lit(band if cov is None else cov * band)
    else:
        b = _crop_to_lit(cov)
    if b is None:
        return _empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, targets.shape[0], "accurate")
    a0, a1, b0, b1 = b
    fine = fine[:, a0:a1, b0:b1]
    win = (win[0] + a0, win[1] + b0, a1 - a0, b1 - b0)
    k = 2 * math.pi / (wavelength * 1e-3)
    env = torch.polar(fine[1] if cov is None else fine[1] * cov[a0:a1, b0:b1], k * fine[0])
    if edge is not None:
        env = env * edge[a0:a1, b0:b1]
    origin = (x0 + win[1] * p, y0 + win[0] * p)
    return DOEField(env, win, origin, p, (alpha, beta), n, float(wavelength), zprop, center, targets.shape[0] + 1,
                    "accurate")


#: default width (Fresnel zones of the exit pupil → DOE distance) of the band around the geometric footprint
#: on the DOE plane that keeps the stop edge's diffraction ripples (see :func:`exit_pupil_field`)
RIPPLE_ZONES = 4.0
#: largest beam extent (simulation samples a side) on the exit-pupil plane that :func:`exit_pupil_field` accepts
MAX_XP_SAMPLES = 8192
#: ``method="auto"`` of :func:`exit_pupil_field`: the exact angular-spectrum construction up to this beam extent
#: (simulation samples a side on the exit-pupil plane), the Fresnel step beyond
AUTO_ASM_SAMPLES = 3072


def exit_pupil_field(lens, doe, field, wavelength: float, depth, z_xp: float, z_doe: float, z_sensor: float,
                     chief_xp, chief_doe, chief_sensor, nodes: int = 64, oversample: int = 1,
                     field_type: str | None = None, check: bool = True, chief_uv=None,
                     ripple_zones: float | None = None, method: str = "auto", rim_images: bool = True) -> DOEField:
    """The accurate DOE-plane field with the stop's sharp edge formed where it belongs: at the exit pupil.

    ``method="fresnel"``: the analytic step. The geometric-optics field is built on the DOE plane
    itself (:func:`accurate_field`, rays traced past the stop's edge without apertures), and the stop's edge,
    instead of being cut sharply there, is multiplied by the knife-edge Fresnel factor of the edge sharp on the
    exit-pupil plane (:func:`stop_edge_factor`, with the local Fresnel length of :func:`_fresnel_scale`: the
    distance from the exit pupil along the ray, the ray's tilt and the wave's local convergence). Costs about
    what the DOE-plane edge costs (a few times), on the DOE's grid, for a beam of any size. Other apertures'
    edges stay on the DOE plane. ``chief_xp`` is not used.

    ``method="asm"``: the exact construction (the reference the Fresnel step is measured against). The
    geometric-optics field is built by :func:`accurate_field` on the exit-pupil plane ``z_xp`` (usually a
    virtual plane inside the lens: the rays leaving the last surface travel on straight lines in the image
    medium, so extending them backwards is exact), where the image of the stop's edge is sharp; it is then
    propagated to the DOE plane by the windowed angular spectrum (:func:`raywave.wave.propagate_window`,
    chief-ray carrier removed), which adds the Fresnel diffraction of the edge between the two planes (that
    the DOE-plane construction, with its hard edge at the DOE, leaves out). The output window is the DOE-plane
    footprint plus ``ripple_zones`` Fresnel zones ``sqrt(λ (z_doe − z_xp)/n)`` for the edge's ripples,
    clamped to the DOE grid; the DOE aperture is applied there. Differentiable like :func:`accurate_field`.

    Args: as :func:`accurate_field`, plus ``z_xp`` (mm) and ``chief_xp`` (the chief ray on that plane).
    ``method="asm"`` raises ValueError when the beam on the exit-pupil plane spans more than
    :data:`MAX_XP_SAMPLES` simulation samples (a large beam: the field there would not fit in memory).
    ``method="auto"``: "asm" up to :data:`AUTO_ASM_SAMPLES` samples, else "fresnel". ``rim_images`` (Fresnel step):
    each node's step runs from its stop-rim point's own image (:func:`stop_rim_images`); False: from the
    exit-pupil plane for every node (the step before the per-node distance)."""
    return run_serial(exit_pupil_field_steps(lens, doe, field, wavelength, depth, z_xp, z_doe, z_sensor, chief_xp,
                                             chief_doe, chief_sensor, nodes=nodes, oversample=oversample,
                                             field_type=field_type, check=check, chief_uv=chief_uv,
                                             ripple_zones=ripple_zones, method=method, rim_images=rim_images))


def exit_pupil_field_steps(lens, doe, field, wavelength: float, depth, z_xp: float, z_doe: float, z_sensor: float,
                     chief_xp, chief_doe, chief_sensor, nodes: int = 64, oversample: int = 1,
                     field_type: str | None = None, check: bool = True, chief_uv=None,
                     ripple_zones: float | None = None, method: str = "auto", rim_images: bool = True) -> DOEField:
    """:func:`exit_pupil_field` as a generator of trace requests (see :func:`accurate_field_steps`)."""
    ripple_zones = RIPPLE_ZONES if ripple_zones is None else float(ripple_zones)
    p_sim = doe.pitch / oversample
    xb = None
    if method in ("auto", "asm"):
        xb = _footprint(lens, torch.as_tensor(field, dtype=torch.float64, device=lens.device).reshape(2),
                        torch.tensor([float(wavelength)], dtype=torch.float64, device=lens.device), depth, z_xp,
                        virtual=True)
    if method == "auto":
        big = xb is not None and max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > AUTO_ASM_SAMPLES
        method = "fresnel" if big else "asm"
    if method == "fresnel":
        rim = stop_rim_images(lens, field, wavelength, depth, field_type) if rim_images else None
        fd = yield from accurate_field_steps(lens, doe, field, wavelength, depth, z_doe, z_sensor, chief_doe,
                                             chief_sensor, nodes=nodes, oversample=oversample, field_type=field_type,
                                             check=check, chief_uv=chief_uv, stop_plane=z_xp,
                                             ripple_zones=ripple_zones, stop_rim=rim)
        return replace(fd, stop_edge="exit_pupil")
    if method != "asm":
        raise ValueError(f"method must be 'auto', 'fresnel' or 'asm', got {method!r}")
    if xb is not None and max(xb[1] - xb[0], xb[3] - xb[2]) / p_sim > MAX_XP_SAMPLES:
        raise ValueError(f"stop_edge='exit_pupil': the beam is {xb[1] - xb[0]:.3g}×{xb[3] - xb[2]:.3g} mm on the "
                         f"exit-pupil plane z = {z_xp:.4g} mm, over {MAX_XP_SAMPLES} samples of {p_sim * 1e3:g} µm "
                         "a side, too large for the exact angular-spectrum construction: use the Fresnel step "
                         "(HybridLens(edge_step='fresnel'), the default) or stop_edge='doe'")
    fx = yield from accurate_field_steps(lens, doe, field, wavelength, depth, z_xp, z_sensor, chief_xp, chief_sensor,
                                         nodes=nodes, oversample=oversample, field_type=field_type, check=check,
                                         chief_uv=chief_uv, virtual=True)
    _, fld, wl, n, (p, x0, y0, sy, sx), _, center, zprop = _common_setup(
        lens, doe, field, wavelength, z_doe, z_sensor, chief_doe, chief_sensor, oversample, field_type)
    carrier = fx.carrier  # the chief ray's direction: the same on both planes
    bbox = _footprint(lens, fld, wl, depth, z_doe)  # also checks that the DOE plane lies behind the lens
    if bbox is None or float(fx.power.detach()) == 0.0:
        return replace(_empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays, "accurate"),
                       stop_edge="exit_pupil")
    dz = z_doe - z_xp
    margin = ripple_zones * math.sqrt(wavelength * 1e-3 * abs(dz) / n) + 4 * p
    jy0, jy1, jx0, jx1 = _window_for_bbox(bbox, margin, p, x0, y0, sy, sx)
    jy0, jx0, jy1, jx1 = max(jy0, 0), max(jx0, 0), min(jy1, sy - 1), min(jx1, sx - 1)
    if jy1 < jy0 or jx1 < jx0:
        return replace(_empty_field(doe, oversample, carrier, n, wavelength, zprop, center, fx.rays, "accurate"),
                       stop_edge="exit_pupil")
    win = (jy0, jx0, jy1 - jy0 + 1, jx1 - jx0 + 1)
    check_window_memory(win[2], win[3], p, lens.device)
    origin = (x0 + jx0 * p, y0 + jy0 * p)
    u = propagate_window(fx.envelope, p, wavelength, dz, fx.origin, origin, win[2:], n=n, carrier=carrier)
    u = u * doe.coverage(win, oversample, device=u.device).to(u.dtype)
    return DOEField(u, win, origin, p, carrier, n, float(wavelength), zprop, center, fx.rays, "accurate",
                    stop_edge="exit_pupil")


# ---------------------------------------------------------------------------------------------------------
# faithful mode (the paper's splatting)
# ---------------------------------------------------------------------------------------------------------
def faithful_field(lens, doe, field, wavelength: float, depth, z_doe: float, z_sensor: float, chief_doe, chief_sensor,
                   n_rays: int = 100_000, oversample: int = 1, full_grid: bool = False, generator=None,
                   field_type: str | None = None, check: bool = True, dtype=torch.float64) -> DOEField:
    """The paper's DOE-plane field: ``n_rays`` rays sampled uniformly at random over the pupil (slightly
    overfilled so that the real apertures cut the beam), each ray's complex amplitude ``d_z · exp(i k OPL)``
    spread bilinearly into its four neighbouring pixels.

    ``full_grid=True`` returns the whole DOE simulation grid with no carrier removed (as the paper's full
    angular-spectrum propagation needs); otherwise the lit window, demodulated by the chief-ray carrier.
    ``generator`` (torch.Generator) makes the ray sample replayable. ``dtype`` is the tracing precision:
    float32 reproduces the precision failure of the paper's Fig. S2 (the optical paths of ~10⁴ waves lose
    a sizeable fraction of a wave); the field is always assembled in complex128 afterwards."""
    field_type, field, wl, n, (p, x0, y0, sy, sx), (alpha, beta), center, zprop = _common_setup(
        lens, doe, field, wavelength, z_doe, z_sensor, chief_doe, chief_sensor, oversample, field_type)
    dev = lens.device
    r = 1.05 * torch.sqrt(torch.rand(n_rays, generator=generator, dtype=torch.float64))
    t = 2 * math.pi * torch.rand(n_rays, generator=generator, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rays = point_source_rays(lens, field, wl, pupil=(r * torch.cos(t), r * torch.sin(t)), aim="chief", depth=depth,
                                 dtype=dtype)
    out = lens.trace(rays)
    _check_beyond_last_surface(out, z_doe)
    nn_ = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, nn_)
    xy, dvec, opl = at.o[0, 0, :, :2], at.d[0, 0], at.opl[0, 0]
    inside = inside_doe(doe, xy)
    passed = at.valid[0, 0]
    valid = passed & inside
    # the rays sample the pupil uniformly: the blocked power fraction is the blocked ray fraction
    clipped = float((passed & ~inside).sum()) / max(int(passed.sum()), 1)
    beam_half = float(xy.detach()[passed].abs().max()) if bool(passed.any()) else 0.0
    if not bool(valid.any()):
        return replace(_empty_field(doe, oversample, (alpha, beta), n, wavelength, zprop, center, n_rays, "faithful"),
                       clipped=clipped, beam_half=beam_half)
    xy, dvec, opl = xy[valid], dvec[valid], opl[valid]
    k = 2 * math.pi / (wavelength * 1e-3)
    ref = opl.detach().min()
    phase = (k * (opl - ref)).to(torch.float64)  # formed in the tracing precision
    xy, dvec = xy.to(torch.float64), dvec.to(torch.float64)
    if full_grid:
        win = (0, 0, sy, sx)
        carrier = (0.0, 0.0)
    else:
        # the lit window: each ray's phasor is demodulated by the chief ray's carrier *before* it is spread,
        # so the spread envelope varies slowly even for off-axis light (the paper's full grid spreads the
        # carrier itself and aliases once the local fringe frequency passes Nyquist: see the warning)
        phase = phase - k * n * (alpha * xy[:, 0] + beta * xy[:, 1])
        xs = xy.detach()
        bbox = (float(xs[:, 0].min()), float(xs[:, 0].max()), float(xs[:, 1].min()), float(xs[:, 1].max()))
        jy0, jy1, jx0, jx1 = _window_for_bbox(bbox, 2 * p, p, x0, y0, sy, sx)
        jy0, jx0, jy1, jx1 = max(jy0, 0), max(jx0, 0), min(jy1, sy - 1), min(jx1, sx - 1)
        win = (jy0, jx0, jy1 - jy0 + 1, jx1 - jx0 + 1)
        carrier = (alpha, beta)
    check_window_memory(win[2] * (2 if full_grid else 1), win[3] * (2 if full_grid else 1), p, dev)
    origin = (x0 + win[1] * p, y0 + win[0] * p)
    u = splat_bilinear(xy[:, 0], xy[:, 1], torch.polar(dvec[:, 2], phase), origin, p, win[2:])
    if check:
        slope = n * torch.sqrt((dvec[:, 0] - carrier[0]) ** 2 + (dvec[:, 1] - carrier[1]) ** 2)
        ratio = slope * (2 * p) / (wavelength * 1e-3)
        _warn_nyquist(ratio, torch.ones_like(ratio, dtype=torch.bool), xy, field.tolist(), wavelength, p)
    u = u * doe.coverage(win, oversample, device=dev).to(u.dtype)
    return DOEField(u, win, origin, p, carrier, n, float(wavelength), zprop, center, n_rays, "faithful", full_grid,
                    clipped=clipped, beam_half=beam_half)
