"""Trace requests of the accurate construction (run one source at a time or batched per wavelength and
plane), the Newton aiming of rays at the DOE-plane nodes, and nearest-node filling."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass, fields

import numpy as np
import torch

from raywave.lens.lens import trace_chunk
from raywave.lens.sources import _source_part, rays_through
from raywave.rays.bundle import RayBundle
from raywave.hybrid.coherent.record import _NEWTON_ITERS, _NEWTON_TOL
from raywave.utils.errors import check_allocation


@contextmanager
def per_source(lens, orders, index=None):
    """While it is open, the traces of ``lens`` carry a per-source value (issue 46: a mid-system DOE's diffraction
    order, :class:`raywave.hybrid.midsystem.DOEPhaseSurface`): every module of ``lens`` with a ``source_rows``
    method is handed ``orders`` (a list of opaque per-source values, one per source; None entries: the module's own
    default) and ``index`` ((R,) long: row r of the traced bundles (R, W, N) is source ``index[r]``; None: row r is
    source r), and cleared on exit. A no-op when ``orders`` is None or all None (an ordinary lens, an ordinary
    source)."""
    if orders is None or all(o is None for o in orders):
        yield
        return
    mods = [m for m in lens.modules() if hasattr(m, "source_rows")]
    for m in mods:
        m.source_rows(list(orders), index)
    try:
        yield
    finally:
        for m in mods:
            m.source_rows(None, None)


def _trace_uv(lens, uv, field, wavelength, depth, z_doe, field_type, record=False, ep_z=None, order=None):
    """Trace rays crossing the entrance plane at ``uv`` (N, 2) to the DOE plane (apertures ignored); ``order``: the
    source's per-source value (:func:`per_source`)."""
    rays = rays_through(lens, uv[None, None], field[None], field_type, wavelength.reshape(1), depth=depth, ep_z=ep_z)
    with per_source(lens, [order]):
        res = lens.trace(rays, apertures=False, record=record)
    out, rec = res if record else (res, None)
    n = lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
    at = out.propagate_to_z(z_doe, n)
    return rays, out, at, rec


@dataclass
class _TraceRequest:
    """One :func:`_trace_uv` call that a field construction (a generator, see :func:`run_batched`) asks for:
    rays through the entrance-plane points ``uv`` (N, 2) mm of field (2,) at wavelength (1,) µm, traced to the
    plane ``z_doe`` mm. ``grad``: traced with autograd (when the caller has it on); else without. ``order``: the
    source's per-source value (:func:`per_source`; requests that differ only in it are traced together)."""

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
    order: object = None

    def run(self):
        with torch.set_grad_enabled(self.grad and torch.is_grad_enabled()):
            return _trace_uv(self.lens, self.uv, self.field, self.wavelength, self.depth, self.z_doe, self.field_type,
                             record=self.record, ep_z=self.ep_z, order=self.order)

    def group_key(self) -> tuple:
        d = self.depth
        # no wavelength: the rays of every wavelength go into one trace (each row carries its own)
        return (id(self.lens), float(self.z_doe), self.field_type, self.record, self.ep_z, self.grad,
                None if d is None else float(d), self.uv.device)


def _rows(t: torch.Tensor, sizes: list) -> list:
    """Each request's row of a batched ``t`` (G, 1, N_max, ...): ``t[g:g + 1, :, :sizes[g]]`` for every g, as views
    from one split (slicing each row dispatches two or three ops; a GPU launches each)."""
    n_max = t.shape[2]
    return [p if k == n_max else p.narrow(2, 0, k) for p, k in zip(t.split(1, 0), sizes)]


def _split_bundle(b, sizes: list) -> list:
    """Request g's first ``sizes[g]`` rays of a batched bundle (G, 1, N_max), as (1, 1, n) bundles, for every g: each
    field split into the rows when first read (:class:`_RowBundle`; issue 43: the readers of a batched trace read a
    few of its bundles' fields, e.g. none of the rays leaving the last surface)."""
    shared = _SplitBundle(b, sizes)
    return [_RowBundle(shared, g) for g in range(len(sizes))]


class _SplitBundle:
    """A batched trace's bundle ``b`` (G, 1, N_max) whose fields are split into the requests' rows (:func:`_rows`)
    when first read."""

    def __init__(self, b, sizes: list):
        self.b, self.sizes, self.cache = b, sizes, {}

    def rows(self, name: str) -> list:
        """Every request's row of the field ``name`` of ``b``."""
        hit = self.cache.get(name)
        if hit is None:
            v = getattr(self.b, name)
            if name == "wavelength":  # one wavelength for all rows, or one per row
                hit = [v] * len(self.sizes) if v.ndim < 3 or v.shape[0] == 1 else v.split(1, 0)
            else:
                hit = _rows(v, self.sizes)
            self.cache[name] = hit
        return hit


class _RowBundle(RayBundle):
    """Request ``g``'s :class:`~raywave.rays.RayBundle` (1, 1, n) of a :class:`_SplitBundle`: a bundle whose fields
    are the batched bundle's rows, each split when first read (then kept). Built with the bundle's own fields (as
    :func:`dataclasses.replace` does), an ordinary bundle."""

    def __init__(self, *args, **kwargs):
        if len(args) != 2 or kwargs or not isinstance(args[0], _SplitBundle):
            RayBundle.__init__(self, *args, **kwargs)
            return
        object.__setattr__(self, "_shared", args[0])
        object.__setattr__(self, "_g", args[1])

    def __getattr__(self, name: str):
        if name not in _BUNDLE_FIELDS or "_shared" not in self.__dict__:
            raise AttributeError(name)
        value = self._shared.rows(name)[self._g]
        object.__setattr__(self, name, value)
        return value


#: the fields of a :class:`~raywave.rays.RayBundle`
_BUNDLE_FIELDS = frozenset(f.name for f in fields(RayBundle))


def _trace_group(reqs: list) -> list:
    """The :func:`_trace_uv` results of requests that share lens, plane, depth and mode, from one batched trace: the
    rays of request g are row g of a (G, 1, N_max) bundle with its own wavelength (the shorter requests padded with
    copies of their first ray, traced and dropped). Every ray is traced on its own (elementwise), so each request
    gets the values its own call would give (up to the last-bit rounding of vectorised transcendental functions)."""
    if len(reqs) == 1:
        return [reqs[0].run()]
    r0 = reqs[0]
    sizes = [r.uv.shape[0] for r in reqs]
    n_max = max(sizes)
    orders = [r.order for r in reqs]
    if any(o is not None for o in orders) and len(reqs) * n_max > 2 * trace_chunk(r0.uv.device):
        # per-source rows must stay rows: the lens would trace so large a bundle in flat chunks
        half = len(reqs) // 2
        return _trace_group(reqs[:half]) + _trace_group(reqs[half:])
    uv = _padded_rows([r.uv for r in reqs], sizes, n_max)[:, None]
    fields = torch.stack([_shaped(r.field, (2,)) for r in reqs])
    wls = torch.cat([_shaped(r.wavelength, (1,)) for r in reqs]).reshape(-1, 1, 1)  # a wavelength per row
    with torch.set_grad_enabled(r0.grad and torch.is_grad_enabled()):
        rays = rays_through(r0.lens, uv, fields, r0.field_type, wls, depth=r0.depth, ep_z=r0.ep_z)
        with per_source(r0.lens, orders):
            res = r0.lens.trace(rays, apertures=False, record=r0.record)
        out, rec = res if r0.record else (res, None)
        n = r0.lens.surfaces[-1].material.n(out.wavelength).to(out.dtype)
        at = out.propagate_to_z(r0.z_doe, n)
    recs = [None] * len(sizes)
    if rec is not None:  # every surface's points and validity, split into the requests' rows when first read
        shared = _SplitRecord(rec, sizes)
        recs = [_RowRecord(shared, g) for g in range(len(sizes))]
    return list(zip(_split_bundle(rays, sizes), _split_bundle(out, sizes), _split_bundle(at, sizes), recs))


def _shaped(t: torch.Tensor, shape: tuple) -> torch.Tensor:
    """``t.reshape(shape)``, or ``t`` itself when it has that shape already (a reshape dispatches an op)."""
    return t if tuple(t.shape) == shape else t.reshape(shape)


def _padded_rows(parts: list, sizes: list, n_max: int) -> torch.Tensor:
    """The rows ``parts`` (each (n_g, 2)) as one (G, n_max, 2) tensor, each row padded with copies of its first
    point: one concatenation and one gather (issue 43: not a concatenation per row)."""
    if all(k == n_max for k in sizes):
        return torch.stack(parts)
    flat = torch.cat(parts)
    dev = flat.device
    size = torch.tensor(sizes, dtype=torch.long, device=dev)
    start = torch.cumsum(size, 0) - size
    j = torch.arange(n_max, dtype=torch.long, device=dev)
    idx = start[:, None] + torch.where(j[None] < size[:, None], j[None], 0)  # (G, n_max)
    return flat[idx]


def cat_rows(bundles: list, name: str, flat: bool = False) -> torch.Tensor:
    """``torch.cat([getattr(b, name) for b in bundles], 2)``: the field ``name`` ("o", "d", "valid" or "opl") of
    bundles (1, 1, n_b, ...) concatenated along the rays (``flat``: ``[0, 0]`` of it, (N, ...)). Rows of one batched
    trace (:func:`_split_bundle`) whose field is not split yet are gathered from the batched tensor at once (issue 43:
    one gather for a run of rows instead of a split, a narrow per row and a concatenation); the same values."""
    return _cat_runs([(getattr(b, "_shared", None), getattr(b, "_g", None), b) for b in bundles],
                     lambda shared: getattr(shared.b, name), lambda b: getattr(b, name),
                     lambda b: name in b.__dict__, flat)


def cat_points(records: list, k: int, c: int, flat: bool = False) -> torch.Tensor:
    """``torch.cat([r.points[k][c] for r in records], 2)`` (``flat``: ``[0, 0]`` of it): coordinate ``c`` of the
    traced points on surface ``k`` of the trace records, concatenated along the rays; rows of one batched trace
    (:class:`_RowRecord`) gathered from it at once (as :func:`cat_rows`)."""
    def own(r):
        shared = getattr(getattr(r, "points", None), "shared", None)
        return shared, getattr(r.points, "g", None), r

    return _cat_runs([own(r) for r in records], lambda shared: shared.rec.points[k][c],
                     lambda r: r.points[k][c], lambda r: r.points.shared.cache.get(("points", k)) is not None, flat)


def _cat_runs(rows: list, batched, single, split, flat: bool) -> torch.Tensor:
    """The concatenation of :func:`cat_rows` / :func:`cat_points`: ``rows`` [(shared, g, row)] (shared None: not a
    row of a batched trace), ``batched(shared)`` the batched tensor (G, 1, N_max, ...), ``single(row)`` a row's own
    tensor (1, 1, n, ...), ``split(row)`` whether the row's tensor exists already."""
    parts, run = [], []

    def close():
        if run:
            t = batched(run[0][0])
            n_max = t.shape[2]
            idx = np.concatenate([g * n_max + np.arange(run[0][0].sizes[g]) for _, g, _ in run])
            idx = torch.from_numpy(idx if flat else idx[None, None]).to(t.device)
            parts.append(t.flatten(0, 2)[idx])
            run.clear()

    for shared, g, row in rows:
        if shared is not None and not split(row) and (not run or run[0][0] is shared):
            run.append((shared, g, row))
            continue
        close()
        if shared is not None and not split(row):
            run.append((shared, g, row))
        else:
            t = single(row)
            parts.append(t[0, 0] if flat else t)
    close()
    if len(parts) == 1:
        return parts[0]
    return torch.cat(parts, 0 if flat else 2)


class _SplitRecord:
    """A batched trace's :class:`~raywave.lens.lens.TraceRecord` (rows (G, 1, N_max)) whose surfaces are split into
    the requests' rows (:func:`_rows`) when first read: most readers need a surface or two (issue 43)."""

    def __init__(self, rec, sizes: list):
        self.rec, self.sizes, self.cache = rec, sizes, {}

    def rows(self, kind: str, k: int) -> list:
        """Every request's rows of ``rec.points[k]`` (a tuple each) or ``rec.valid[k]``."""
        hit = self.cache.get((kind, k))
        if hit is None:
            v = getattr(self.rec, kind)[k]
            hit = list(zip(*(_rows(c, self.sizes) for c in v))) if kind == "points" else _rows(v, self.sizes)
            self.cache[kind, k] = hit
        return hit


class _RowSurfaces:
    """Request ``g``'s ``points`` or ``valid`` list of a :class:`_SplitRecord` (a read-only sequence)."""

    def __init__(self, shared: _SplitRecord, g: int, kind: str):
        self.shared, self.g, self.kind = shared, g, kind

    def __len__(self) -> int:
        return len(getattr(self.shared.rec, self.kind))

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(len(self))[k]]
        return self.shared.rows(self.kind, range(len(self))[k])[self.g]


class _RowRecord:
    """Request ``g``'s :class:`~raywave.lens.lens.TraceRecord` of a batched trace: ``points`` (per surface (x, y, z)
    (1, 1, n) each) and ``valid`` (per surface (1, 1, n)), as its own trace's record gives them."""

    def __init__(self, shared: _SplitRecord, g: int):
        self.points = _RowSurfaces(shared, g, "points")
        self.valid = _RowSurfaces(shared, g, "valid")


def run_serial(gen):
    """Run one field construction (a generator of :class:`_TraceRequest`, see :func:`run_batched`) with one trace
    per request; returns its result."""
    try:
        req = next(gen)
        while True:
            req = gen.send(req.run())
    except StopIteration as stop:
        return stop.value


class _Pause:
    """What a field construction yields (:data:`PAUSE`) between its ray stage (every trace done; the per-node maps
    formed) and its field stage (the fine envelope on the simulation grid, the construction's largest arrays):
    :func:`run_serial` and :func:`run_batched` go on at once; ``run_batched(..., pause=True)`` stops it there (a
    :class:`Paused`), so that a caller can run the ray stage of many groups of sources in one pass and then build
    the groups' fields one group at a time (issue 43)."""

    def run(self):
        return None


#: the marker a construction yields between its ray stage and its field stage (:class:`_Pause`)
PAUSE = _Pause()


@dataclass
class Paused:
    """A field construction stopped at its :data:`PAUSE` (:func:`run_batched` with ``pause=True``): hand it to
    :func:`run_batched` again to finish it."""

    gen: object


def _advance(gen, value, start: bool, pause: bool):
    """``(request, None)``: the construction ``gen``'s next trace request after receiving ``value`` (``start``: its
    first), past every :data:`PAUSE` unless ``pause`` (then the marker itself); ``(None, result)`` when it
    returned."""
    try:
        req = next(gen) if start else gen.send(value)
        while isinstance(req, _Pause) and not pause:
            req = gen.send(None)
    except StopIteration as stop:
        return None, stop.value
    return req, None


def run_batched(gens: list, pause: bool = False) -> list:
    """Run several field constructions (generators that yield :class:`_TraceRequest` and return a
    :class:`DOEField`) together: in every round, the pending trace requests of all constructions that share a lens,
    plane and mode (whatever their wavelengths) are traced as one batch (:func:`_trace_group`: one ray trace for all
    fields instead of one per field, large enough for the elementwise kernels to use every thread). A request with a
    ``run_group`` (the field stage's :class:`~raywave.hybrid.coherent.accurate._FieldRequest`) is answered for its
    group by that function; one marked ``deferred`` waits until no other request is pending. Each construction
    sees the results its own calls would give, so the fields equal :func:`run_serial`'s. Returns their results in
    order. ``pause``: each construction stops at its :data:`PAUSE` (its ray stage done) and is returned as a
    :class:`Paused`; ``gens`` may hold :class:`Paused` constructions (they go on from there) and finished results
    (passed through)."""
    results = [None] * len(gens)
    running = {}
    pending = {}
    for i, g in enumerate(gens):
        resume = isinstance(g, Paused)
        if not (resume or hasattr(g, "send")):
            results[i] = g  # finished already
            continue
        running[i] = g.gen if resume else g
        req, res = _advance(running[i], None, not resume, pause)
        _file_step(i, req, res, running[i], results, pending)
    while pending:
        # a deferred request (a construction's field stage) waits until no trace is pending: the constructions still
        # tracing then join its batch
        now = {i: r for i, r in pending.items() if not getattr(r, "deferred", False)} or pending
        groups: dict = {}
        for i, req in now.items():
            groups.setdefault(req.group_key(), []).append(i)
        answers = {}
        for idx in groups.values():
            reqs = [pending[i] for i in idx]
            run = getattr(reqs[0], "run_group", None) or (
                _invert_group if isinstance(reqs[0], _InvertRequest) else _trace_group)
            for i, res in zip(idx, run(reqs)):
                answers[i] = res
        pending = {i: r for i, r in pending.items() if i not in now}
        for i, res in answers.items():
            req, out = _advance(running[i], res, False, pause)
            _file_step(i, req, out, running[i], results, pending)
    return results


def _file_step(i: int, req, out, gen, results: list, pending: dict) -> None:
    """File construction ``i`` after one step of its generator ``gen``: finished (``out`` into ``results``), paused
    at its ray stage (a :class:`Paused` into ``results``), or waiting on the request ``req`` (into ``pending``)."""
    if req is None:
        results[i] = out
    elif isinstance(req, _Pause):
        results[i] = Paused(gen)
    else:
        pending[i] = req


def _landing_and_jacobian(lens, uv, field, wl, depth, z_doe, field_type, h, ep_z, need_jac=None):
    """Landing points X (N, 2), validity (N,) and ∂X/∂uv (N, 2, 2) (forward differences, step h), from one
    batched trace of the 3N rays uv, uv + h·e_u, uv + h·e_v (a generator: yields that trace's request).
    ``need_jac`` (N,) bool: only those rays get their two neighbours traced (the others' Jacobians are NaN)."""
    allv = _with_neighbours(uv, h, need_jac)
    _, _, at, _ = yield _TraceRequest(lens, allv, field, wl, depth, z_doe, field_type, False, ep_z, False)
    return _landing_from(at, uv.shape[0], h, need_jac)


def _with_neighbours(uv, h: float, need_jac=None):
    """The rays ``uv`` (N, 2) followed by the two finite-difference neighbours ``+h·e_u``, ``+h·e_v`` of those that
    ``need_jac`` (N,) bool marks (None: all): (N + 2M, 2)."""
    return torch.cat([uv, *_neighbours(uv if need_jac is None else uv[need_jac], h)])


def _neighbours(uv, h: float) -> tuple:
    """The two finite-difference neighbour sets ``(uv + h·e_u, uv + h·e_v)`` of the rays ``uv`` (M, 2), each (M, 2)."""
    du = torch.tensor([[h, 0.0], [0.0, h]], dtype=uv.dtype, device=uv.device)
    return uv + du[0], uv + du[1]


def _difference_jacobian(x0, xu, xv, h: float):
    """Forward-difference Jacobians ∂X/∂uv (M, 2, 2) from the landing points ``x0`` (M, 2) and those of the two
    neighbour sets ``xu``, ``xv`` (:func:`_neighbours`), step ``h`` mm."""
    return torch.stack([(xu - x0) / h, (xv - x0) / h], -1)


def _landing_from(at, n: int, h: float, need_jac=None):
    """Landing points (n, 2), validity (n,) and forward-difference Jacobians (n, 2, 2) (NaN where ``need_jac`` is
    False) from the traced rays ``at`` of :func:`_with_neighbours` (a (1, 1, n + 2M) bundle on the plane)."""
    x = at.o[0, 0, :, :2]
    m = (x.shape[0] - n) // 2
    x0, xu, xv = x[:n], x[n:n + m], x[n + m:]
    xj = x0 if need_jac is None else x0[need_jac]
    jac_j = _difference_jacobian(xj, xu, xv, h)
    if need_jac is None:
        return x0, at.valid[0, 0, :n], jac_j
    jac = torch.full((n, 2, 2), math.nan, dtype=x.dtype, device=x.device)
    jac[need_jac] = jac_j
    return x0, at.valid[0, 0, :n], jac


def _solve2(j, r):
    """Solve j·s = r for 2×2 systems (N, 2, 2), (N, 2); singular systems give 0."""
    (j00, j01), (j10, j11) = (row.unbind(1) for row in j.unbind(1))  # views from three ops (issue 43: not eight)
    r0, r1 = r.unbind(1)
    det = j00 * j11 - j01 * j10
    ok = det.abs() > 1e-300
    det = torch.where(ok, det, torch.ones_like(det))
    s0 = (j11 * r0 - j01 * r1) / det
    s1 = (-j10 * r0 + j00 * r1) / det
    return torch.where(ok[:, None], torch.stack([s0, s1], -1), torch.zeros_like(r)), ok


#: chord rounds (the start's Jacobian kept, no finite-difference rays) a node takes before it switches to Newton
CHORD_ROUNDS = 3
#: :func:`_invert_to_nodes`: a Newton (or chord) step that lands a ray on one that cannot be traced (it misses a
#: surface, e.g. beyond the rim of a strongly stretched ray map) is halved back towards the last traced iterate up
#: to this many times before the node is given up (issue 47, class C: the Olympus M.Zuiko 12 mm at 0.7 field lost
#: the beam's last 5 % of the stop radius and the ripple band on its stretched side; 2 halvings give its PSF 6 mm
#: before the sensor as 6 do, at +10 % CPU; each one more converges more far nodes: 2.2 mm before the sensor 1 / 2 / 6
#: halvings cost 1.7 / 3.1 / 3.4× the CPU of none)
BACKTRACK_HALVINGS = 2
#: the largest landing error (mm on the DOE plane) from which :func:`_invert_to_nodes`' ``settle`` leaves the last
#: step to the caller, whatever the predicted convergence
_SETTLE_CAP = 1e-6
#: the safety factor on :func:`_invert_to_nodes`' predicted error for ``settle`` (the error vector turns from round to
#: round: a ray predicted at 1e-11 mm was seen to land at 3.6e-11 mm)
_SETTLE_MARGIN = 10.0


@dataclass(frozen=True)
class _Aim:
    """How a construction's rays are aimed: rays of ``field`` (2,) at ``wavelength`` (1,) µm and ``depth`` through
    entrance-plane points (the plane ``ep_z`` mm), traced to the plane ``z_doe`` mm (``field_type``: the lens's
    field type), Jacobians by forward differences of step ``h`` mm on the entrance plane; ``order``: the source's
    per-source value (:func:`per_source`)."""

    lens: object
    field: torch.Tensor
    wavelength: torch.Tensor
    depth: object
    z_doe: float
    field_type: str
    h: float
    ep_z: float | None
    order: object = None

    def landing(self, uv, need_jac=None):
        """Generator: :func:`_landing_and_jacobian` of the rays ``uv`` (N, 2) (with this source's ``order``)."""
        allv = _with_neighbours(uv, self.h, need_jac)
        _, _, at, _ = yield self.request(allv, False, False)
        return _landing_from(at, uv.shape[0], self.h, need_jac)

    def neighbours_jacobian(self, uv, x0):
        """Generator: ∂X/∂uv (N, 2, 2) at the rays ``uv`` (N, 2) whose landing points ``x0`` (N, 2) are known (a
        trace of them already done): forward differences from one trace of their two neighbour sets alone
        (:meth:`landing`'s Jacobian without tracing the rays themselves again; issue 46: a third of the trace that
        the lens gradient's exact Jacobian costs)."""
        _, _, at, _ = yield self.request(torch.cat(_neighbours(uv, self.h)), False, False)
        xu, xv = at.o[0, 0, :, :2].split(uv.shape[0])
        return _difference_jacobian(x0, xu, xv, self.h)

    def request(self, uv, record: bool, grad: bool) -> "_TraceRequest":
        """The :class:`_TraceRequest` of the rays ``uv`` (N, 2)."""
        return _TraceRequest(self.lens, uv, self.field, self.wavelength, self.depth, self.z_doe, self.field_type,
                             record, self.ep_z, grad, self.order)


@dataclass
class _LandingRequest:
    """A construction's chief-ray landing (:meth:`_Aim.landing` of its one ray ``uv`` (2,) or (1, 2), no autograd):
    answered with ``(X (1, 2), ∂X/∂uv (1, 2, 2))``. :func:`run_batched` answers the pending ones of constructions
    that share a lens, plane and mode with one trace of all their rays and neighbours, a single-ray row each
    (:func:`_trace_rows`; issue 43: no per-construction slicing): each value its own call's."""

    aim: _Aim
    uv: torch.Tensor

    def run(self):
        return _landing_group([self])[0]

    @staticmethod
    def run_group(reqs: list) -> list:
        return _landing_group(reqs)

    def group_key(self) -> tuple:
        a = self.aim
        d = a.depth
        return ("landing", id(a.lens), float(a.z_doe), a.field_type, a.ep_z, a.h, None if d is None else float(d),
                self.uv.device)


def _landing_group(reqs: list) -> list:
    """The answers ``[(X (1, 2), ∂X/∂uv (1, 2, 2))]`` of :class:`_LandingRequest` s (one lens, plane and mode): the
    rays and their finite-difference neighbours ``+h·e_u``, ``+h·e_v`` of all requests in one trace."""
    a0 = reqs[0].aim
    h, g = a0.h, len(reqs)
    uv = torch.stack([_shaped(r.uv, (2,)) for r in reqs])  # (G, 2)
    du = torch.tensor([[h, 0.0], [0.0, h]], dtype=uv.dtype, device=uv.device)
    allv = torch.cat([uv, uv + du[0], uv + du[1]])  # (3G, 2): the rays, then each neighbour set
    rows = torch.arange(g, device=uv.device).repeat(3)
    fields = torch.stack([_shaped(r.aim.field, (2,)) for r in reqs])[rows]
    wls = torch.cat([_shaped(r.aim.wavelength, (1,)) for r in reqs])[rows]
    orders = [r.aim.order for r in reqs]
    if any(o is not None for o in orders):
        x, _ = _trace_rows(a0, allv, fields, wls, orders, rows)
    else:
        x, _ = _trace_rows(a0, allv, fields, wls)
    x0, xu, xv = x.split(g)
    jac = torch.stack([(xu - x0) / h, (xv - x0) / h], -1)  # (G, 2, 2), as _landing_from's
    return list(zip(x0.split(1), jac.split(1)))


def _invert_to_nodes(aim: _Aim, targets, chief: tuple, max_step: float, start: tuple | None = None,
                     finish: float | None = None, settle: float | None = None):
    """Newton: entrance-plane uv (N, 2) whose rays (``aim``) land on ``targets`` (N, 2) on the DOE plane, from the
    chief ray's linear guess (``chief`` = its entrance-plane point (1, 2), landing point (1, 2) and Jacobian
    ∂X/∂uv (1, 2, 2)), or from ``start[0]`` (N, 2) where it is finite (a better start, e.g. interpolated from a
    coarser solve).

    Every iteration is one batched trace (the rays and their two finite-difference neighbours) of the rays that
    are still moving: a converged or dead ray keeps its uv, so its landing point and Jacobian are those it was
    last traced with (each ray is traced on its own, so tracing it again would give the same values). Steps
    longer than ``max_step`` (mm on the entrance plane) are shortened, which keeps the iteration inside the
    traceable region. ``start[1]`` (N, 2, 2): a Jacobian ∂X/∂uv known near the solution (from the coarse solve):
    where it and ``start[0]`` are finite, the node first takes up to :data:`CHORD_ROUNDS` chord steps with it (its
    ray alone traced, no neighbours), then Newton steps. Returns (uv, converged (N,), Jacobian at the last iterate
    (N, 2, 2) (a chord node's: the start's), landing points (N, 2) at ``uv`` or None where some ray moved after its
    last trace, i.e. the iteration did not settle); all detached (a generator: yields one :class:`_InvertRequest`,
    which :func:`run_batched` solves together with the other constructions' as one set of rays).

    ``finish`` (mm on the DOE plane, for solutions that only seed another solve, e.g. :func:`_coarse_start`'s): a
    Newton ray whose landing error is at most ``finish`` takes its step and stops there, converged, without the
    trace that would confirm it (Newton's error after the step is ~ error² × the map's curvature, 1e-12 mm from
    1e-6 mm); its landing points are then None. Without it, every ray is confirmed by its own trace.

    ``settle`` (mm, for a caller that takes one more step J⁻¹(X − T) from the last iterate itself and traces its
    rays there, as :func:`~raywave.hybrid.coherent.accurate._trace_nodes` does): a ray whose error after that step,
    predicted from its last two (``e²/e_prev``: linear convergence, pessimistic for Newton's), is at most
    ``settle`` / :data:`_SETTLE_MARGIN` stops where it is, converged, with its landing point and Jacobian: the
    caller's step is the one the next round would have confirmed.

    ``targets`` may also be a node grid (:class:`~raywave.hybrid.coherent.accurate._Nodes`: its ``targets``), whose
    targets the group then builds for all its grids at once (one transfer; issue 43: not ~14 ops a grid)."""
    uv0, jac0 = (None, None) if start is None else start
    req = _InvertRequest(aim, _detached(targets), tuple(_detached(c) for c in chief), float(max_step),
                         (_detached(uv0), _detached(jac0)), finish, settle)
    return (yield req)


def _detached(t):
    """``t.detach()`` where ``t`` is a tensor with autograd history, else ``t`` itself (a node grid, None, a tensor
    without history: issue 43, a detach dispatches an op)."""
    return t.detach() if isinstance(t, torch.Tensor) and t.requires_grad else t


def _group_targets(reqs: list) -> torch.Tensor:
    """The targets (N, 2) of the :class:`_InvertRequest` s ``reqs`` concatenated in order: tensors as they are, node
    grids built together (their class's ``concat_targets``: each grid's ``targets`` a view of the result)."""
    ts = [r.targets for r in reqs]
    grids = [t for t in ts if not isinstance(t, torch.Tensor)]
    if not grids:
        return torch.cat(ts)
    whole = type(grids[0]).concat_targets(grids)
    return whole if len(grids) == len(ts) else torch.cat([t if isinstance(t, torch.Tensor) else t.targets for t in ts])


def _count(t) -> int:
    """The number of targets of an :class:`_InvertRequest`'s ``targets`` (a tensor (N, 2) or a node grid)."""
    return t.shape[0] if isinstance(t, torch.Tensor) else t.count


@dataclass
class _InvertRequest:
    """One :func:`_invert_to_nodes` call (its arguments, detached; ``targets`` (N, 2) or a node grid): a construction
    yields it like a trace request, and :func:`run_batched` solves the pending ones of constructions that share a
    lens, plane and mode together (:func:`_invert_group`)."""

    aim: _Aim
    targets: torch.Tensor
    chief: tuple
    max_step: float
    start: tuple
    finish: float | None = None
    settle: float | None = None

    def run(self):
        return _invert_group([self])[0]

    def group_key(self) -> tuple:
        a = self.aim
        d = a.depth
        return ("invert", id(a.lens), float(a.z_doe), a.field_type, a.ep_z, a.h,
                None if d is None else float(d), self.targets.device, self.finish, self.settle)


def _invert_group(reqs: list) -> list:
    """:func:`_invert_to_nodes` for every request of ``reqs`` (:class:`_InvertRequest`, one lens, plane and mode) at
    once: their rays are one set, every Newton round is one batched trace (:func:`_trace_group`, a row per request)
    and one set of elementwise updates. Each ray's iteration is its own (its trace, its 2×2 solve, its step), so
    every request gets what a call of its own gives; a request whose rays all stopped leaves the rounds, as its
    own iteration would have ended there."""
    finish, settle = reqs[0].finish, reqs[0].settle  # one per group (:meth:`_InvertRequest.group_key`)
    sizes = [_count(r.targets) for r in reqs]
    dev = reqs[0].targets.device
    rid = torch.repeat_interleave(torch.arange(len(reqs), device=dev), torch.tensor(sizes, device=dev))
    targets = _group_targets(reqs)
    uv_c = torch.stack([_shaped(r.chief[0], (2,)) for r in reqs])[rid]  # (each (2,) or (1, 2))
    x_c = torch.cat([r.chief[1] for r in reqs])[rid]
    jac_c = torch.cat([_shaped(r.chief[2], (1, 2, 2)) for r in reqs])[rid]
    max_step = torch.tensor([r.max_step for r in reqs], dtype=targets.dtype, device=dev)[rid][:, None]
    n = targets.shape[0]
    h = reqs[0].aim.h  # one per group (:meth:`_InvertRequest.group_key`)
    sources = (torch.stack([_shaped(r.aim.field, (2,)) for r in reqs]),
               torch.cat([_shaped(r.aim.wavelength, (1,)) for r in reqs]), [r.aim.order for r in reqs],
               torch.tensor([[h, 0.0], [0.0, h]], dtype=targets.dtype, device=dev).unbind(0))
    a0 = reqs[0].aim  # (lens, depth, field type and entrance plane: one per group)
    with torch.no_grad():
        part = _source_part(a0.lens, sources[0], a0.field_type, sources[1].reshape(-1, 1, 1), depth=a0.depth,
                            ep_z=a0.ep_z)
        sources += (part, a0.lens.indices(part[0]))  # (and the lens media's indices (G, 1, 1): once, not a round)
    step0, _ = _solve2(jac_c, targets - x_c)
    uv = uv_c + step0
    chord = torch.zeros(n, dtype=torch.bool, device=dev)
    nan2 = torch.full((1, 2), math.nan, dtype=targets.dtype, device=dev)
    if any(r.start[0] is not None for r in reqs):  # (else every ray starts from the linear guess)
        uv0 = torch.cat([r.start[0] if r.start[0] is not None else nan2.expand(k, 2) for r, k in zip(reqs, sizes)])
        start = torch.isfinite(uv0).all(-1)
        uv = torch.where(start[:, None], uv0, uv)
    jac = torch.zeros((n, 2, 2), dtype=targets.dtype, device=dev)
    chording = any(r.start[0] is not None and r.start[1] is not None for r in reqs)  # (else no chord node: none of
    # the chord masks' ops)
    if chording:
        jac0 = torch.cat([r.start[1] if (r.start[0] is not None and r.start[1] is not None)
                          else nan2.new_full((k, 2, 2), math.nan) for r, k in zip(reqs, sizes)])
        chord = start & torch.isfinite(jac0).flatten(1).all(-1)
        jac[chord] = jac0[chord]
    x = torch.zeros_like(targets)
    valid = torch.zeros(n, dtype=torch.bool, device=dev)
    live = torch.arange(n, device=dev)  # the rays moved since their last trace
    finished = torch.zeros(n, dtype=torch.bool, device=dev)  # stopped after an unconfirmed last step (``finish``)
    settled = torch.zeros(n, dtype=torch.bool, device=dev)  # stopped before the caller's last step (``settle``)
    # the last traced error of each ray (0 before its first: a first round never settles)
    e_prev = torch.zeros(n, dtype=targets.dtype, device=dev) if settle is not None else None
    # each ray's last step (from the chief ray for its start): a step onto an untraceable ray is halved back
    # (:data:`BACKTRACK_HALVINGS` times at most) instead of ending the ray there
    last_step = uv - uv_c
    halvings = torch.zeros(n, dtype=torch.int64, device=dev)
    moved_last: set[int] = set()
    for it in range(_NEWTON_ITERS):
        if it == CHORD_ROUNDS:
            chording = False  # from here on every moving node takes Newton steps
        if live.numel() == 0:
            break
        x_l, valid_l, jac_l = _landing_rounds(reqs, sources, rid, live, uv, chord if chording else None)
        if chording:
            jac_l = torch.where(chord[live][:, None, None], jac[live], jac_l)
        x[live], valid[live], jac[live] = x_l, valid_l, jac_l
        back = ~valid_l & (halvings[live] < BACKTRACK_HALVINGS)  # stepped onto a ray that misses a surface
        back_rays = live[back]
        if back_rays.numel():
            last_step[back_rays] = 0.5 * last_step[back_rays]
            uv[back_rays] = uv[back_rays] - last_step[back_rays]
            halvings[back_rays] += 1
        err = x_l - targets[live]
        step, ok = _solve2(jac_l, err)
        e = err.abs().amax(-1)
        move = valid_l & ~(e <= _NEWTON_TOL) & ok
        big = step.abs().amax(-1, keepdim=True)
        ms = max_step[live]
        over = big > ms
        step = torch.where(over, step * (ms / big), step)
        if settle is not None:  # the caller's own step takes these rays to within ``settle``: no further round
            stay = move & (e <= _SETTLE_CAP) & (_SETTLE_MARGIN * e * e <= settle * e_prev[live]) & ~over[:, 0]
            settled.index_fill_(0, live[stay], True)
            e_prev[live] = torch.where(valid_l, e, e_prev[live])
            move = move & ~stay
        moved = live[move]
        uv[moved] = uv[moved] - step[move]
        last_step[moved] = -step[move]
        if finish is not None:  # the last step of a seed's ray, unconfirmed (no trace of its own for it)
            last = move & (e <= finish) & ~over[:, 0]
            finished.index_fill_(0, live[last], True)
            move = move & ~last
            moved = live[move]
        live = moved if not back_rays.numel() else torch.cat([moved, back_rays]).sort().values
        if it == _NEWTON_ITERS - 1:  # the last iteration moved these requests' rays: their landing points are stale
            moved_last.update(torch.unique(rid[live]).tolist())
    err = x - targets
    conv = valid & (err.abs().amax(-1) <= _NEWTON_TOL) | finished | settled
    if finish is not None:  # their landing points are those before the last step
        moved_last.update(torch.unique(rid[finished]).tolist())
    # each request's rows as views from one split per tensor (slicing and copying each dispatches 8 ops a request;
    # the requests hold all their rows anyway)
    parts = zip(uv.split(sizes), conv.split(sizes), jac.split(sizes), x.split(sizes))
    if finish is not None:  # a seed's solve: no node trace follows, no step
        return [_Inverted((u, c, j, None if g in moved_last else xg), None) for g, (u, c, j, xg) in enumerate(parts)]
    # the Newton step J⁻¹(X − T) at the last iterate of every ray at once and the points uv − J⁻¹(X − T) (what a
    # construction's node trace takes without autograd; issue 43: one 2×2 solve and one difference for the group
    # instead of one each per construction)
    step, _ = _solve2(jac, err)
    steps = zip(step.split(sizes), (uv - step).split(sizes))
    return [_Inverted((u, c, j, None if g in moved_last else xg), *((None, None) if g in moved_last else st))
            for g, ((u, c, j, xg), st) in enumerate(zip(parts, steps))]


class _Inverted(tuple):
    """:func:`_invert_to_nodes`' answer ``(uv, converged, Jacobian, landing points or None)``, with ``step`` (N, 2):
    the Newton step J⁻¹(X − T) at ``uv`` from the group's one solve, and ``lin`` (N, 2): ``uv − step`` (both None
    where the landing points are None, and for a seed's solve: ``finish``)."""

    def __new__(cls, values: tuple, step, lin=None):
        out = super().__new__(cls, values)
        out.step, out.lin = step, lin
        return out


def _landing_rounds(reqs: list, sources: tuple, rid, live, uv, chord):
    """One Newton round's trace for the ``live`` rays (sorted indices into the set of :func:`_invert_group`): each
    ray and, unless it takes chord steps, its two finite-difference neighbours (the rays of
    :func:`_landing_and_jacobian`), all requests' rays as one bundle of single-ray rows (each with its own source and
    wavelength, shape (R, 1, 1): no per-request slicing, issue 43; ``sources`` = the requests' fields (G, 2),
    wavelengths (G,) µm, per-source values [G] (:func:`per_source`), the neighbours' offsets ``(h·e_u, h·e_v)``
    (each (2,)) and the sources' :func:`_source_part` (their directions, checks and index), made once for the group).
    Returns the landing points (L, 2), validity
    (L,) and Jacobians (L, 2, 2) of the live rays (NaN for chord rays, whose Jacobian is kept). ``chord`` None: no
    chord ray (every live ray with its neighbours, none of the masks' ops)."""
    r0 = reqs[0].aim
    h = r0.h  # one per group (:meth:`_InvertRequest.group_key`)
    rid_l, uv_l = rid[live], uv[live]
    if chord is None:
        nl = uv_l.shape[0]
        rows = torch.cat([rid_l, rid_l, rid_l])
        allv = torch.cat([uv_l, uv_l + sources[3][0], uv_l + sources[3][1]])
    else:
        du = sources[3]
        need = ~chord[live]
        nl, nj = uv_l.shape[0], int(need.sum())
        uj = uv_l[need]
        rows = torch.cat([rid_l, rid_l[need], rid_l[need]])
        allv = torch.cat([uv_l, uj + du[0], uj + du[1]])
    part = _part_rows(sources[4], rows)  # the sources' directions, checks and index: once for the group
    n_all = [None if v is None else v[rows] for v in sources[5]]  # and the glass indices
    if any(o is not None for o in sources[2]):  # per-source values (a mid-system DOE's orders): each row's own
        x, valid = _trace_rows(r0, allv, None, None, sources[2], rows, part, n_all)
    else:
        x, valid = _trace_rows(r0, allv, None, None, part=part, n_all=n_all)
    if chord is None:
        x0, xu, xv = x.split(nl)
        return x0, valid[:nl], torch.stack([(xu - x0) / h, (xv - x0) / h], -1)
    x0, xu, xv = x[:nl], x[nl:nl + nj], x[nl + nj:]
    jac = torch.full((nl, 2, 2), math.nan, dtype=x.dtype, device=x.device)
    jac[need] = torch.stack([(xu - x0[need]) / h, (xv - x0[need]) / h], -1)
    return x0, valid[:nl], jac


def _trace_rows(aim: _Aim, uv, fields, wavelengths, orders=None, rows=None, part=None, n_all=None):
    """Landing points (R, 2) and validity (R,) on ``aim``'s plane of R rays, each with its own source: entrance-plane
    points ``uv`` (R, 2) mm, ``fields`` (R, 2), ``wavelengths`` (R,) µm (``aim``'s lens, depth, field type and
    entrance plane), traced without autograd as one bundle (R, 1, 1) (every ray on its own). ``orders``: the
    sources' per-source values (:func:`per_source`), ``rows`` (R,) long: each ray's source among them. ``part``:
    what the rays' sources alone decide (:func:`_source_part` of ``fields`` and ``wavelengths``, each row's, e.g.
    :func:`_part_rows` of the sources' own), when the caller has it (``fields`` and ``wavelengths`` are then not
    read, and may be None). ``n_all``: the lens media's indices at the rows' wavelengths (:meth:`Lens.indices`,
    each (R, 1, 1) or None), when the caller has them."""
    chunk = trace_chunk(uv.device)
    if orders is not None and any(o is not None for o in orders) and uv.shape[0] > 2 * chunk:
        def cut(i):
            return None if n_all is None else [None if v is None else v[i:i + chunk] for v in n_all]
        parts = [_trace_rows(aim, uv[i:i + chunk], *(None if t is None else t[i:i + chunk]
                                                     for t in (fields, wavelengths)),
                             orders, rows[i:i + chunk], None if part is None else _part_rows(part, slice(i, i + chunk)),
                             cut(i))
                 for i in range(0, uv.shape[0], chunk)]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    with torch.no_grad():
        if part is None:
            part = _source_part(aim.lens, fields, aim.field_type, wavelengths.reshape(-1, 1, 1), depth=aim.depth,
                                ep_z=aim.ep_z)
        rays = rays_through(aim.lens, uv[:, None, None], fields, aim.field_type, None, depth=aim.depth, ep_z=aim.ep_z,
                            source=part)
        with per_source(aim.lens, orders, rows):
            out = aim.lens.trace(rays, apertures=False, n_all=n_all)
        n = (aim.lens.surfaces[-1].material.n(out.wavelength) if n_all is None else n_all[-1]).to(out.dtype)
        at = out.propagate_to_z(aim.z_doe, n)
    return at.o[:, 0, 0, :2], at.valid[:, 0, 0]


def _part_rows(part: tuple, idx) -> tuple:
    """:func:`_source_part` ``part`` of G sources (each tensor's first axis a source) → that of the rows ``idx`` (an
    index tensor or a slice into its sources): ``(wavelengths, ep_z, directions, points, wide, index)``, each
    source's values gathered (the same values :func:`_source_part` gives for the rows' own fields: it works row by
    row)."""
    wl, ep_z, d_inf, pts, wide, n0 = part
    return (wl[idx], ep_z, *(None if t is None else t[idx] for t in (d_inf, pts, wide)), n0[idx])


def _nearest_fill(values: torch.Tensor, good: torch.Tensor, xy: torch.Tensor, grad_xy: torch.Tensor | None = None):
    """Replace values (K, C) at ``~good`` nodes by their nearest good node's value, plus a first-order
    extension ``grad_xy·(x − x_v)`` for the first channel when ``grad_xy`` (K, 2) is given."""
    bad = ~good
    if not all(torch.stack([bad.any(), good.any()]).tolist()):  # (one host read)
        return values
    gi = torch.nonzero(good).squeeze(1)
    bi = torch.nonzero(bad).squeeze(1)
    check_allocation(16.0 * bi.numel() * gi.numel(), f"the node grid's nearest-node fill ({bi.numel()} × "
                     f"{gi.numel()} distances)", "fewer nodes (rays; raywave: --rays) or a finer DOE pitch "
                     "(--doe-pitch, in mm: a pitch as large as the beam widens the node grid's margin)", xy.device)
    d = torch.cdist(xy[bi].detach(), xy[gi].detach())
    near = gi[d.argmin(1)]
    filled = values[near].clone()
    if grad_xy is not None:
        filled[:, 0] = filled[:, 0] + (grad_xy[near] * (xy[bi] - xy[near])).sum(-1)
    out = values.clone()
    out[bi] = filled
    return out
