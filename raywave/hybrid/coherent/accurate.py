"""The accurate construction (:func:`accurate_field`): exactly aimed rays at a coarse node grid, smooth
quantities interpolated, the phase formed last."""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass, field as dc_field
from typing import ClassVar

import numpy as np
import torch

from raywave.lens.paraxial import entrance_pupil_diameter
from raywave.lens.sources import chief_pupil, entrance_plane_z, point_source_rays, source_weight
from raywave.utils import devices
from raywave.utils.phasor import polar
from raywave.utils.errors import check_allocation
from raywave.utils.safe import safe_sqrt
from raywave.doe.base import DOE
from raywave.wave.field import cubic_matrices, cubic_matrix, edge_coverage, upsample_nodes_window
from raywave.wave.grid import Field, Grid
from raywave.hybrid.coherent.geometry import (_common_setup, _crop_to_lit, _empty_field, _footprint, _near_nodes,
                                              _nyquist_warning, _warn_nyquist, check_window_memory, inside_doe)
from raywave.hybrid.coherent.record import (_NEWTON_TOL, DOEField, EnvelopeRow, FieldInfo, SamplingWarning,
                                            StopEdgeWarning)
from raywave.hybrid.coherent.settings import ChiefRays, FieldSettings, Known, Planes, Source
from raywave.hybrid.coherent.stop_edge import (KAPPA_MAX, _fresnel_scale, _fresnel_scale_at, _nu_inner, _rim_cubic,
                                               _rim_fourier, _rim_fourier_rows, _rim_z, _rim_z_rows, _zone_estimate,
                                               edge_envelope, ripple_band)
from raywave.hybrid.coherent.tracing import (PAUSE, _Aim, _LandingRequest, _invert_to_nodes, _nearest_fill, _solve2,
                                             cat_points, cat_rows, per_source, run_serial)


def accurate_field(lens, doe, source: Source, planes: Planes, chief: ChiefRays,
                   settings: FieldSettings | None = None) -> DOEField:
    """The accurate DOE-plane field of one :class:`~raywave.hybrid.coherent.settings.Source` (field point,
    wavelength, depth) with its :class:`ChiefRays` on the plane ``planes.z_doe`` mm (the sensor at
    ``planes.z_sensor`` mm), sampled as ``settings`` say (:class:`FieldSettings`: nodes,
    oversampling, checks, a virtual plane, the stop edge's plane)."""
    return run_serial(accurate_field_steps(lens, doe, source, planes, chief, settings))


#: largest (Fresnel zone on the DOE plane) / (radius of curvature of the stop edge's shadow) for which the Fresnel
#: edge step is used without a warning: its local straight-edge expansion (with the cylindrical correction) holds
#: while the zone is small against the radius (the bundled asphere on axis: 0.05; a 0.4 obscuration 2 mm before
#: the DOE: 0.44, where the step gains 2 % of power that the exact construction conserves)
EDGE_CURVATURE_LIMIT = 0.25


def _stencil_traced(good: torch.Tensor, det: torch.Tensor, det_c: torch.Tensor) -> torch.Tensor:
    """The nodes where the edge normal's divergence describes the edge: ``good`` (..., KY, KX) bool the nodes whose
    ray was traced, ``det`` (..., KY, KX) the node map's Jacobian and ``det_c`` (broadcastable) its value on the
    beam's centre node → the nodes with every node within two steps along the grid (Manhattan distance ≤ 2: the
    central differences of the normal, itself central differences of the stop's slack) traced and on the centre's
    sheet of the ray map (the Jacobian's sign; a node beyond a grid's border counts as both, its differences being
    one-sided there; pass ``good`` True there). A bad node takes its nearest good node's values
    (:func:`~raywave.hybrid.coherent.tracing._nearest_fill`) and where the rays past the rim fold neighbouring nodes
    lie on different sheets: either way the normal jumps and its divergence says nothing of the edge's curvature
    (issue 47, h47s: the Ricoh GR 6 mm on axis, nodes beside the band's untraced corners, 5.6 × where the edge's own
    ratio is 0.066; the Pentax 6×7 300 mm at 0.7 field, a fold of the band 0.1 – 0.3 mm outside the shadow, 0.65 ×
    where it is 0.041)."""
    ok = good & (det * det_c > 0)
    for _ in range(2):
        nxt = ok.clone()
        nxt[..., 1:, :] &= ok[..., :-1, :]
        nxt[..., :-1, :] &= ok[..., 1:, :]
        nxt[..., :, 1:] &= ok[..., :, :-1]
        nxt[..., :, :-1] &= ok[..., :, 1:]
        ok = nxt
    return ok


def _warn_edge_curvature(div_n: torch.Tensor, g: torch.Tensor, near: torch.Tensor, field, wavelength: float) -> None:
    """Warn (:class:`StopEdgeWarning`) where the Fresnel step's edge curves too much for its Fresnel zone.
    ``div_n`` (ky, kx): divergence of the edge normal (−curvature, 1/mm); ``g``: Fresnel scale (1/mm, zone = √2/g);
    ``near``: the nodes within 2 Fresnel parameters of the edge."""
    if near.numel() == 0:
        return
    ratio = float(torch.where(near, div_n.abs() * math.sqrt(2.0) / g, -math.inf).amax())  # −inf: none near
    _edge_curvature_warning(ratio, field, wavelength, stacklevel=4)


def _edge_curvature_warning(ratio: float, field, wavelength: float, stacklevel: int) -> None:
    """:func:`_warn_edge_curvature`'s :class:`StopEdgeWarning` when the largest Fresnel zone / radius of curvature
    ``ratio`` (a host float) exceeds :data:`EDGE_CURVATURE_LIMIT` (``field`` a list, ``wavelength`` µm)."""
    if ratio > EDGE_CURVATURE_LIMIT:
        warnings.warn(f"field {field} at {wavelength:g} µm: the stop edge's Fresnel zone on the DOE plane is "
                      f"{ratio:.2g} × its radius of curvature there (a small obscuration or stop, or a DOE far from "
                      "the exit pupil): the Fresnel edge step is approximate (it can miss the power by a few %); "
                      "use HybridLens(edge_step='asm'), the exact construction", StopEdgeWarning,
                      stacklevel=stacklevel)


def entrance_pupil(lens) -> tuple[float, float]:
    """``(z, radius)`` mm of the lens's paraxial entrance pupil: the plane of the entrance-plane coordinates ``uv``
    (:func:`raywave.lens.sources.entrance_plane_z`) and half the paraxial entrance-pupil diameter (which scales the
    aiming's finite-difference step and its longest Newton step)."""
    return entrance_plane_z(lens), 0.5 * entrance_pupil_diameter(lens)


@dataclass(eq=False)
class _Nodes:
    """The regular node grid on the plane: node ``[j, i]`` at ``(gx[i], gy[j])`` mm, spacing ``h`` mm, ``gx[i] = x0 +
    (i − cx)·h``, ``gy[j] = y0 + (j − cy)·h`` (``x0``, ``y0`` mm and ``cx``, ``cy`` host numbers: the reference point
    and its place in the grid), ``kx`` × ``ky`` nodes on ``device``. The node coordinates are tensors made from the
    host numbers when first read: ``gx`` (kx,), ``gy`` (ky,), ``tx``, ``ty`` (ky, kx) and ``targets`` (ky·kx, 2) (the
    nodes in row-major order); :meth:`concat_targets` makes many grids' at once (issue 43: one transfer for a group
    instead of ~20 ops a grid)."""

    x0: float
    y0: float
    cx: float
    cy: float
    h: float
    kx: int
    ky: int
    device: torch.device
    cache: dict = dc_field(default_factory=dict, init=False, repr=False)

    @property
    def count(self) -> int:
        """The number of nodes."""
        return self.kx * self.ky

    def axes(self) -> tuple:
        """``(gx (kx,), gy (ky,))`` float64 numpy arrays (the host's arithmetic, each step rounded as a tensor's)."""
        return (self.x0 + (np.arange(self.kx, dtype=np.float64) - self.cx) * self.h,
                self.y0 + (np.arange(self.ky, dtype=np.float64) - self.cy) * self.h)

    def ends(self) -> tuple:
        """``(gy[0], gx[0], gy[-1], gx[-1])`` mm: the first and last node, host numbers (no tensor op)."""
        gx, gy = self.axes()
        return float(gy[0]), float(gx[0]), float(gy[-1]), float(gx[-1])

    def _host_targets(self) -> np.ndarray:
        gx, gy = self.axes()
        return np.stack([np.broadcast_to(gx[None, :], (self.ky, self.kx)),
                         np.broadcast_to(gy[:, None], (self.ky, self.kx))], -1).reshape(-1, 2)

    @property
    def gx(self) -> torch.Tensor:
        if "gx" not in self.cache:
            self.cache["gx"] = torch.from_numpy(self.axes()[0]).to(self.device)
        return self.cache["gx"]

    @property
    def gy(self) -> torch.Tensor:
        if "gy" not in self.cache:
            self.cache["gy"] = torch.from_numpy(self.axes()[1]).to(self.device)
        return self.cache["gy"]

    @property
    def tx(self) -> torch.Tensor:
        if "tx" not in self.cache:
            self.cache["tx"], self.cache["ty"] = torch.meshgrid(self.gx, self.gy, indexing="xy")  # (ky, kx)
        return self.cache["tx"]

    @property
    def ty(self) -> torch.Tensor:
        self.tx  # noqa: B018 (made with tx)
        return self.cache["ty"]

    @property
    def targets(self) -> torch.Tensor:
        if "targets" not in self.cache:
            self.cache["targets"] = torch.from_numpy(self._host_targets()).to(self.device)
        return self.cache["targets"]

    @staticmethod
    def concat_targets(nds: list) -> torch.Tensor:
        """The ``targets`` of the grids ``nds`` (one device) concatenated (N, 2), from one transfer; each grid's
        ``targets`` (and its axes ``gx``, ``gy``) then views of one tensor each (one split each)."""
        host = [nd.axes() for nd in nds]
        flat = np.concatenate([np.stack([np.broadcast_to(gx[None, :], (nd.ky, nd.kx)),
                                         np.broadcast_to(gy[:, None], (nd.ky, nd.kx))], -1).reshape(-1, 2)
                               for nd, (gx, gy) in zip(nds, host)])
        dev = nds[0].device
        whole = torch.from_numpy(flat).to(dev)
        axes = [torch.from_numpy(np.concatenate([h[k] for h in host])).to(dev).split([len(h[k]) for h in host])
                for k in (0, 1)]
        for nd, t, gx, gy in zip(nds, whole.split([nd.count for nd in nds]), *axes):
            nd.cache.setdefault("targets", t)
            nd.cache.setdefault("gx", gx)
            nd.cache.setdefault("gy", gy)
        return whole

    def as_map(self, v: torch.Tensor) -> torch.Tensor:
        """Per-node values ``(ky·kx, ...)`` → ``(..., ky, kx)`` maps."""
        return v.T.reshape(-1, self.ky, self.kx) if v.ndim == 2 else v.reshape(self.ky, self.kx)


@dataclass
class _Build:
    """One accurate construction: the lens and DOE, the :class:`Source`, the plane ``z_doe`` and the sensor
    ``z_sensor`` (mm), its :class:`ChiefRays`, the :class:`FieldSettings` and what the caller traced already
    (:class:`Known`); derived on
    creation: ``field`` (2,) and ``wl`` (1,) tensors, ``n`` the image medium's index, ``p`` the simulation pitch (mm),
    ``carrier`` the chief ray's direction cosines (α, β), ``center`` its sensor point, ``zprop`` the distance to the
    sensor (mm), ``field_type`` and ``ripple`` (the edge's ripple zones with a stop plane, else None)."""

    lens: object
    doe: object
    src: Source
    z_doe: float
    z_sensor: float
    chief: ChiefRays
    cfg: FieldSettings
    given: Known
    #: the edge band's power the DOE aperture blocks and the band's half reach (mm): :func:`_band_blocked`'s
    band_cut: tuple = (0.0, 0.0)

    def __post_init__(self):
        cfg, src = self.cfg, self.src
        self.field_type, self.field, self.wl, self.n, sim, self.carrier, self.center, self.zprop = _common_setup(
            self.lens, self.doe, src, (self.z_doe, self.z_sensor), self.chief, cfg.oversample, self.given.medium)
        self.p = sim[0]
        if cfg.sphere is not None:  # the envelope relative to the converging sphere (its own carrier): none
            self.carrier = (0.0, 0.0)
        self.ripple = None
        if cfg.stop_plane is not None:  # the band: the caller's, else RIPPLE_ZONES widened by the edge waves' reach
            reach = self.given.reach  # (the caller's: the crop's centre is not read)
            self.ripple = float(cfg.ripple_zones) if cfg.ripple_zones is not None else ripple_band(
                self.given.stop_rim, self.z_doe, self.z_sensor,
                None if reach is not ... else self.chief.sensor.o[:2].detach(), self.src.wavelength * 1e-3 / self.n,
                reach, cfg.crop_reach)

    def empty(self, rays: int) -> DOEField:
        """The field without light (``rays`` traced)."""
        return _empty_field(self.doe, self.cfg.oversample, self.carrier, self.n, self.src.wavelength, self.zprop,
                            self.center, rays, "accurate")


def accurate_field_steps(lens, doe, source: Source, planes: Planes, chief: ChiefRays,
                         settings: FieldSettings | None = None, known: Known | None = None):
    """:func:`accurate_field` as a generator: yields the :class:`_TraceRequest` of every ray trace it needs and
    receives its result, returns the :class:`DOEField` (run it with :func:`run_serial`, or many together with
    :func:`run_batched`: one batched trace per round for all of them). ``known`` (:class:`Known`): what the
    caller traced already for many sources at once (the lit footprint, the stop rim's images, the entrance pupil).

    Steps: the node grid over the footprint (:func:`_node_layout`), exactly aimed rays to every node
    (:func:`_trace_nodes`), the smooth per-node maps (a :class:`_NodeMapRequest`, :func:`_node_stage`, or with
    other constructions' :func:`_node_stages`: :func:`_node_maps`: optical path, ray density, distances
    to the edges; :func:`_stop_edge_maps`: the stop edge's Fresnel channels; the checks, :func:`_check_nodes`),
    a :data:`~raywave.hybrid.coherent.tracing.PAUSE` (the ray stage done), and the fine field (a
    :class:`_FieldRequest`: :func:`_fine_field`, or with other constructions' :func:`_fine_fields`)."""
    b = _Build(lens, doe, source, float(planes.z_doe), float(planes.z_sensor), chief, settings or FieldSettings(),
               known or Known())
    bbox = _lit_footprint(b)
    if bbox is None:
        return b.empty(0)
    nd = _node_layout(b, bbox)
    nodes = yield from _trace_nodes(b, nd)
    # the node-map stage: a request that run_batched answers for many constructions at once (_node_stages); the
    # maps the field stage reads (:data:`_FIELD_MAPS`), or None where no node's ray was traced
    maps = yield _NodeMapRequest(b, nd, nodes)
    if maps is not None and _band_at_grid_edge(b, nd, maps):  # the trimmed grid cut the ripple band: the wide one
        nd = _node_layout(b, bbox, NODE_MARGIN_WIDE)
        nodes = yield from _trace_nodes(b, nd)
        maps = yield _NodeMapRequest(b, nd, nodes)
    n_rays = nd.count
    del nodes
    if maps is not None:
        b.band_cut = _band_blocked(b, nd, maps)
    if maps is None:
        warnings.warn(f"no ray could be traced to the DOE plane for field {b.field.tolist()} at "
                      f"{source.wavelength:g} µm", SamplingWarning, stacklevel=3)
        return b.empty(n_rays)
    # the ray stage is done: a caller may stop here (run_batched(pause=True)) and build the fine field later, holding
    # only the maps the field stage reads (the traced rays and their records are dropped)
    yield PAUSE
    sim = doe.sim_grid(b.cfg.oversample)
    # the field stage: a request that run_batched answers for many constructions at once (_fine_fields)
    out = yield _FieldRequest(b, nd, maps, sim)
    if out is None:
        return b.empty(n_rays)
    return _window_field(b, *out, sim, n_rays + 1)


#: the node maps that the field stage (:func:`_fine_field`) reads
_FIELD_MAPS = ("phi_env", "amp2", "dist", "other", "nu", "nu_raw", "kappa", "g_max")


def _lit_footprint(b: _Build):
    """The lit footprint ``(xmin, xmax, ymin, ymax)`` mm on the plane, or None (every ray vignetted): the caller's
    (``b.given.bbox``; ``False``: none), else traced here (:func:`_footprint`)."""
    bbox = b.given.bbox
    if bbox is False:  # given: every ray is vignetted
        return None
    if bbox is None:
        return _footprint(b.lens, b.field, b.wl, b.src.depth, b.z_doe, virtual=b.cfg.virtual)
    return bbox


def _window_field(b: _Build, env: torch.Tensor, box, sim: Grid, rays: int) -> DOEField:
    """The :class:`DOEField` of the envelope ``env`` (ny, nx) complex128 on the half-open window ``box``
    ``(iy0, iy1, ix0, ix1)`` of ``sim``'s lattice, built from ``rays`` traced rays."""
    # on the DOE's simulation lattice (a virtual plane's box may extend beyond the DOE grid)
    grid = Grid(sim.position(box[0], box[2]), b.p, (box[1] - box[0], box[3] - box[2]))
    info = FieldInfo(rays, "accurate", band_clipped=b.band_cut[0], band_half=b.band_cut[1])
    if isinstance(env, EnvelopeRow):  # a row of the batched field stage's envelopes: made when first read
        return DOEField.deferred(env, grid, (float(b.src.wavelength), b.n, b.carrier), box, b.zprop, b.center, info)
    return DOEField(Field(env, grid, float(b.src.wavelength), b.n, b.carrier), box, b.zprop, b.center, info)


def _band_blocked(b: _Build, nd: _Nodes, maps: dict):
    """``(fraction, reach)``: the fraction of the source's power on the plane (the ray density times the knife-edge
    intensity ``|D(ν)|²``, summed over the nodes of the beam and of the stop edge's ripple band) that falls beyond the
    geometric shadow (ν < 0) and outside the DOE aperture, and the band's half reach ``max(|x|, |y|)`` mm (the
    square DOE that holds it), as 0-dim float64 tensors, not read here (the caller reads a call's at once:
    :meth:`~raywave.hybrid.HybridLens.doe_fields`); ``(0.0, 0.0)`` without a diffracting stop edge, on a virtual
    plane, on a grid without an aperture (the exact construction's lattice), or where the whole node grid lies inside
    the aperture (host numbers: most sources). ``|D(ν)|²`` beyond the shadow as ``1/(4 + 2π²ν²)`` (¼ on the edge,
    the far ripples' mean ``1/(2π²ν²)``; an estimate for a warning), 1 inside. The beam's own clipping is
    :func:`~raywave.hybrid.coherent.geometry.doe_clipping`'s; this is the edge's diffracted light beyond the shadow,
    which the DOE's edge also blocks (and diffracts again)."""
    doe, nu = b.doe, maps.get("nu_raw")
    if nu is None or b.cfg.stop_plane is None or b.cfg.virtual or not isinstance(doe, DOE):
        return 0.0, 0.0
    x0, x1 = nd.x0 - nd.cx * nd.h, nd.x0 + (nd.kx - 1 - nd.cx) * nd.h  # the node grid's corners (host numbers)
    y0, y1 = nd.y0 - nd.cy * nd.h, nd.y0 + (nd.ky - 1 - nd.cy) * nd.h
    w, h = doe.size
    if doe.aperture == "circle":
        inside = max(x0 * x0, x1 * x1) + max(y0 * y0, y1 * y1) <= (0.5 * min(w, h)) ** 2
    else:
        inside = max(-x0, x1) <= 0.5 * w and max(-y0, y1) <= 0.5 * h
    if inside:
        return 0.0, 0.0
    nu = nu.detach()
    beyond = nu < 0
    band = beyond & (nu > -math.sqrt(2.0) * b.ripple)
    power = maps["amp2"].detach().clamp_min(0.0) * torch.where(beyond, 1.0 / (4.0 + 2.0 * math.pi**2 * nu * nu),
                                                               1.0)
    power = torch.where(band | ~beyond, power, 0.0)
    out = torch.where(band & ~inside_doe(doe, torch.stack([nd.tx, nd.ty], -1)), power, 0.0).sum()
    reach = torch.where(band & (power > 0), torch.maximum(nd.tx.abs(), nd.ty.abs()), 0.0).amax()
    return out / power.sum().clamp_min(1e-300), reach


#: the most rays a node grid may hold (2048² nodes; the default 64 nodes per side give ~150² with the exit-pupil
#: edge's ripple band): beyond, its margin has grown without bound
MAX_NODE_RAYS = 2048 * 2048


def _check_node_count(kx: int, ky: int, nodes: int, extent: float, margin: float, stop_plane) -> None:
    """Refuse a node grid of more than :data:`MAX_NODE_RAYS` (a clear error instead of tracing 10⁷ rays until
    memory runs out): its margin (mm) around the beam's ``extent`` (mm) is what grew."""
    if kx * ky <= MAX_NODE_RAYS:
        return
    why = (" The margin is the stop edge's Fresnel ripple band (the stop's rim imaged far from the DOE plane: a stop "
           "that does not limit this beam, or an unphysical stop size); stop_edge='doe' forms the edge on the DOE "
           "plane instead." if stop_plane is not None else "")
    raise ValueError(f"the accurate field's node grid would be {kx}×{ky} rays (at most {MAX_NODE_RAYS}) for {nodes} "
                     f"requested per side: a {margin:.3g} mm margin around a {extent:.3g} mm beam on the DOE "
                     f"plane.{why}")


#: Fresnel zones (:func:`_zone_estimate`) the node grid reaches beyond the stop edge's ripple band
#: (:func:`_node_layout`). The estimate is an upper one (30 % over the chief ray's), so 0 leaves the bundled asphere
#: 7–12 nodes beyond the band (its interpolation needs 3; the Cooke triplet and the 50 mm singlet 5–7, the double Gauss
#: with the caustic fallback 4–5) where the 1 zone of before (issue 47, h47m) left 11–18 on the asphere: ~13 % fewer
#: node rays (a single PSF at 12.25° 109² instead of 117²). Where the band comes within :data:`NODE_SPARE` nodes of the
#: grid's edge all the same (:func:`_band_at_grid_edge`), the construction traces again with :data:`NODE_MARGIN_WIDE`
NODE_MARGIN_ZONES = 0.0
#: the margin (zones beyond the band) of the second trace where the first one's grid cut the band
NODE_MARGIN_WIDE = 1.0
#: nodes the grid must hold beyond the ripple band's last kept node (the field stage interpolates up to 3 node
#: spacings beyond it: :func:`~raywave.hybrid.coherent.geometry._near_nodes`)
NODE_SPARE = 3


def _band_at_grid_edge(b: _Build, nd: _Nodes, maps: dict) -> bool:
    """Whether the stop edge's ripple band (the nodes the field stage keeps: ``ν > −√2·ripple``) comes within
    :data:`NODE_SPARE` nodes of the node grid's edge (one host read); False without a diffracting stop edge. The
    caller asks once, after the trimmed grid: the wide grid's trace is not checked again."""
    if b.cfg.stop_plane is None or "nu_raw" not in maps or maps.get("nu_raw") is None:
        return False
    keep = maps["nu_raw"] > -math.sqrt(2.0) * b.ripple
    k = NODE_SPARE
    if keep.shape[0] <= 2 * k or keep.shape[1] <= 2 * k:
        return bool(keep.any())
    rim = torch.stack([keep[:k].any(), keep[-k:].any(), keep[:, :k].any(), keep[:, -k:].any()])
    return bool(rim.any())


def _node_layout(b: _Build, bbox, zones: float | None = None) -> _Nodes:
    """The node grid: spacing h, symmetric about the chief ray's landing point (so a symmetric lens gives an
    exactly symmetric field), covering the footprint ``bbox`` + a margin (with the stop edge diffracting from
    the stop plane, its ripple band and ``zones`` Fresnel zones more: :data:`NODE_MARGIN_ZONES` where None); nodes
    need not sit on simulation pixels."""
    zones = NODE_MARGIN_ZONES if zones is None else zones
    p, nodes, z_doe, stop_plane, stop_rim = b.p, b.cfg.nodes, b.z_doe, b.cfg.stop_plane, b.given.stop_rim
    xcd, ycd = b.chief.doe.o.tolist()[:2]  # (one host read)
    extent = max(bbox[1] - bbox[0], bbox[3] - bbox[2], p)
    h_node = extent / max(nodes - 1, 2)
    margin = 2.5 * h_node + 2 * p
    if stop_plane is not None:
        z_edge = stop_plane
        if stop_rim is not None:  # the rim image farthest from the DOE plane sets the widest band
            z_far = _host_extreme(stop_rim[1].tolist(), z_doe >= stop_plane)  # (one host read)
            if (z_doe - z_far) * (z_doe - stop_plane) > 0 and abs(z_doe - z_far) > abs(z_doe - stop_plane):
                z_edge = z_far
        margin += (b.ripple + zones) * _zone_estimate(b.src.wavelength, b.n, z_doe - z_edge, b.z_sensor - z_edge,
                                                  *b.carrier)
    half_x = max(xcd - bbox[0], bbox[1] - xcd) + margin
    half_y = max(ycd - bbox[2], bbox[3] - ycd) + margin
    kx = 2 * math.ceil(half_x / h_node) + 1
    ky = 2 * math.ceil(half_y / h_node) + 1
    _check_node_count(kx, ky, nodes, extent, margin, stop_plane)
    return _Nodes(xcd, ycd, (kx - 1) / 2, (ky - 1) / 2, h_node, kx, ky, b.lens.device)


def _host_extreme(values: list, smallest: bool) -> float:
    """The smallest (else the largest) of the host numbers ``values``, NaN if one is NaN (as a tensor's min/max)."""
    if any(math.isnan(v) for v in values):
        return math.nan
    return min(values) if smallest else max(values)


def _trace_nodes(b: _Build, nd: _Nodes):
    """Generator: aim a ray at every node (Newton on the entrance-plane point from the chief ray's linear
    guess), then trace them differentiably. Returns ``(uv_lin, rays, at, rec, good)``: the entrance-plane points
    (N, 2), the traced rays, their state on the plane, the per-surface record and the nodes whose ray converged
    and passed (N,)."""
    lens = b.lens
    ep_z, r_ep = entrance_pupil(lens) if b.given.entrance is None else b.given.entrance
    chief_uv = b.chief.uv
    if chief_uv is None:
        with per_source(lens, [b.src.order]):
            ep_rays = point_source_rays(lens, b.field, b.wl, pupil=chief_pupil(lens), aim="full", depth=b.src.depth)
        o, d = ep_rays.o[0, 0, 0].detach(), ep_rays.d[0, 0, 0].detach()
        chief_uv = o[:2] + d[:2] * (ep_z - o[2]) / d[2]
    uv_c = torch.as_tensor(chief_uv, dtype=torch.float64, device=lens.device)  # (2,) or (1, 2): the groups stack it
    aim = _Aim(lens, b.field, b.wl, b.src.depth, b.z_doe, b.field_type, 1e-6 * max(r_ep, 1e-3), ep_z, b.src.order)
    x_c, jac_c = yield _LandingRequest(aim, uv_c)  # batched with the other constructions' chief rays
    chief = (uv_c, x_c, jac_c)
    start = yield from _coarse_start(aim, nd, chief, 0.25 * r_ep)
    inverted = yield from _invert_to_nodes(aim, nd, chief, 0.25 * r_ep, start, settle=NODE_SETTLE)  # (the group makes nd.targets)
    uv, conv, jac, x_at = inverted
    # the differentiable trace of the node rays. The landing point of a node's ray must stay on its node when
    # the lens changes: one Newton step with the (detached) Jacobian, uv_lin = uv − J⁻¹(X(uv) − T), equals uv
    # in value and carries d(uv)/dθ = −J⁻¹ ∂X/∂θ, so everything traced at uv_lin (path, directions, aperture
    # slacks, ray density) has its exact first-order derivative with respect to the lens parameters.
    # (without autograd the landing points at uv are the Newton iteration's last ones: no trace)
    if x_at is None or torch.is_grad_enabled():
        _, _, at0, _ = yield aim.request(uv, False, True)
        x_at = at0.o[0, 0, :, :2]
    if start is not None and torch.is_grad_enabled():
        # the lens gradient needs the exact Jacobian at the solution (a chord node carries the coarse one): the
        # step's value comes from the iteration's Jacobian (as without autograd, so that a replay of this
        # construction is bitwise the forward pass), its derivative from the exact one (a zero-valued term)
        jac_exact = yield from aim.neighbours_jacobian(uv, x_at.detach())
        jinv_step, _ = _solve2(jac, x_at.detach() - nd.targets)
        jinv_step = jinv_step + _solve2(jac_exact, x_at - x_at.detach())[0]
    elif getattr(inverted, "lin", None) is not None and not torch.is_grad_enabled():
        jinv_step = None  # the inversion's own solve at these landing points and its uv − step (the same values)
    else:
        jinv_step, _ = _solve2(jac, (x_at - nd.targets))
    uv_lin = inverted.lin if jinv_step is None else uv - jinv_step
    rays, _, at, rec = yield aim.request(uv_lin, True, True)
    return uv_lin, rays, at, rec, conv & at.valid.reshape(-1)  # (one op: not two selects)


#: node stride of the coarse pre-solve (:func:`_coarse_start`); node grids with fewer than 4 coarse cells a side
#: skip it
COARSE_STRIDE = 4
#: landing error (mm on the DOE plane) at which a coarse node takes its last Newton step without a trace to confirm
#: it (:func:`~raywave.hybrid.coherent.tracing._invert_to_nodes`' ``finish``): the coarse solutions only seed the
#: interpolated start, whose own error is ~1e-6 mm, and the step takes 1e-6 mm to ~1e-12 mm (issue 43: the confirming
#: rounds each cost a whole trace for the last few rays)
COARSE_FINISH = 1e-6
#: predicted landing error (mm on the DOE plane) after the node trace's own Newton step at which a node's iteration
#: stops before confirming it (:func:`~raywave.hybrid.coherent.tracing._invert_to_nodes`' ``settle``; issue 43: the
#: rounds that only confirmed the last few nodes cost a whole trace each): the iteration's own tolerance, met after
#: that step instead of before it (a node's phase moves by ≤ 1e-6 rad; the Cooke triplet's DOE-plane fields moved by
#: 2.5e-9 of their peak)
NODE_SETTLE = _NEWTON_TOL


def _coarse_start(aim: _Aim, nd: _Nodes, chief: tuple, max_step: float):
    """Generator: the Newton start of every node (rays ``aim``, from the chief ray's ``(uv, X, ∂X/∂uv)``, Newton
    steps of at most ``max_step`` mm), ``(uv0 (N, 2), jac0 (N, 2, 2))``: the exact solution on every
    :data:`COARSE_STRIDE`-th node interpolated (separable cubic) to all nodes (entrance-plane mm), and the
    Jacobian ∂X/∂uv of that interpolant (the inverse of its node-grid differences); NaN where a coarse node that
    the interpolation uses did not converge (that node keeps the chief ray's linear guess and Newton). None
    for small grids. The interpolation is a :class:`_CoarseRequest` (batched over the constructions on an
    accelerator).

    The ray map is smooth, so the interpolated start lands within ~1e-6 mm of the node's own solution and its
    Jacobian is good to ~1e-4: chord steps (one ray per node, no finite-difference neighbours) converge in one or
    two rounds instead of four Newton rounds of three rays. Only the path changes: every node still converges on
    its own to the same tolerance (the fields agree with a chief-ray start to the rounding of the optical path,
    ~1e-13 mm)."""
    s = COARSE_STRIDE
    if min(nd.kx, nd.ky) < 4 * s + 1:
        return None
    kxc, kyc = -(-(nd.kx - 1) // s) + 1, -(-(nd.ky - 1) // s) + 1  # the coarse grid covers the node grid
    # every s-th node from the first (host numbers: the coarse grid's targets are made with the group's, in one
    # transfer)
    gy0, gx0, _, _ = nd.ends()
    coarse = _Nodes(gx0, gy0, 0.0, 0.0, s * nd.h, kxc, kyc, nd.device)
    uv, conv, _, _ = yield from _invert_to_nodes(aim, coarse, chief, max_step, finish=COARSE_FINISH)
    return (yield _CoarseRequest(uv, conv, (kyc, kxc), (nd.ky, nd.kx), nd.h))


@dataclass
class _CoarseRequest:
    """The coarse start's interpolation of one construction (:func:`_coarse_start`): the solutions ``uv`` (Nc, 2)
    and their convergence ``conv`` (Nc,) on the ``coarse`` = ``(kyc, kxc)`` grid of every :data:`COARSE_STRIDE`-th
    node, to the ``nodes`` = ``(ky, kx)`` grid of spacing ``h`` mm; answered with ``(uv0 (N, 2), jac0 (N, 2, 2))``.
    :func:`~raywave.hybrid.coherent.tracing.run_batched` answers the requests of a round together (``run_group``):
    on an accelerator as one padded batch (:func:`_coarse_batch`), on a CPU one by one (:func:`_coarse_one`)."""

    uv: torch.Tensor
    conv: torch.Tensor
    coarse: tuple
    nodes: tuple
    h: float

    def run(self):
        """This construction's interpolation alone (:func:`run_serial`)."""
        return _coarse_one(self)

    @staticmethod
    def run_group(reqs: list) -> list:
        """The answers of a group of requests, in order."""
        if len(reqs) > 1 and devices.accelerator(reqs[0].uv):
            return _coarse_batch(reqs)
        return [_coarse_one(r) for r in reqs]

    def group_key(self) -> tuple:
        """What the requests batched together share: the device (each carries its own grids)."""
        return ("coarse", self.uv.device)


def _start_jacobian(fine: torch.Tensor, grads: tuple) -> tuple:
    """``(uv0 (N, 2), jac0 (N, 2, 2))`` from the interpolated start ``fine`` (2, ky, kx) and its node-grid
    differences ``grads`` = ``((du/dy, dv/dy), (du/dx, dv/dx))`` (each (ky, kx)): ∂uv/∂X inverted to ∂X/∂uv."""
    (du_dy, dv_dy), (du_dx, dv_dx) = grads
    a = torch.stack([torch.stack([du_dx, du_dy], -1), torch.stack([dv_dx, dv_dy], -1)], -2).reshape(-1, 2, 2)
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    jac0 = torch.stack([torch.stack([a[:, 1, 1], -a[:, 0, 1]], -1), torch.stack([-a[:, 1, 0], a[:, 0, 0]], -1)],
                       -2) / det[:, None, None]
    return fine.reshape(2, -1).T, jac0


def _coarse_one(r: _CoarseRequest) -> tuple:
    """:class:`_CoarseRequest`'s answer: the coarse solutions interpolated (NaN where an unconverged coarse node is
    used), their central differences over the node grid (NaN spreads from unsure nodes), inverted."""
    s, (kyc, kxc), (ky, kx) = COARSE_STRIDE, r.coarse, r.nodes
    dev = r.uv.device
    my = cubic_matrix(torch.arange(ky, dtype=torch.float64, device=dev) / s, kyc)
    mx = cubic_matrix(torch.arange(kx, dtype=torch.float64, device=dev) / s, kxc)
    uv_map = r.uv.T.reshape(2, kyc, kxc)
    bad = (~r.conv).to(torch.float64).reshape(kyc, kxc)
    fine = my @ torch.where(r.conv.reshape(kyc, kxc), uv_map, torch.zeros_like(uv_map)) @ mx.T  # (2, ky, kx)
    unsure = (my.abs() @ bad @ mx.abs().T) > 0
    fine = torch.where(unsure, torch.full_like(fine, math.nan), fine)
    # ∂uv/∂X by central differences over the node grid (NaN spreads from unsure nodes), inverted to ∂X/∂uv
    return _start_jacobian(fine, torch.gradient(fine, spacing=r.h, dim=(1, 2)))


def _padded_gradient(f: torch.Tensor, h: torch.Tensor, n: torch.Tensor, dim: int) -> torch.Tensor:
    """:func:`torch.gradient` (edge order 1) along ``dim`` of zero-padded grids ``f`` (B, C, Y, X): grid ``b`` holds
    ``n[b]`` samples along ``dim`` (spacing ``h[b]``), the rest padding. Central differences inside, one-sided at
    both of each grid's own ends (the same arithmetic as :func:`torch.gradient` on the grid alone); 0 at the last
    place of a grid shorter than ``f`` (finite everywhere: autograd through the padding stays finite)."""
    f = f.movedim(dim, -1)
    out = torch.zeros_like(f)
    hb = h.reshape(-1, 1, 1, 1)
    out[..., 1:-1] = (f[..., 2:] - f[..., :-2]) / (2 * hb)
    out[..., :1] = (f[..., 1:2] - f[..., :1]) / hb
    last = (n - 1).reshape(-1, 1, 1, 1).expand(*f.shape[:-1], 1)
    end = (f.gather(-1, last) - f.gather(-1, last - 1)) / hb
    out.scatter_(-1, last, end)
    return out.movedim(-1, dim)


def _coarse_batch(reqs: list) -> list:
    """The answers of :class:`_CoarseRequest` ``reqs`` as one padded batch (an accelerator: a fixed number of kernel
    launches for any number of constructions): the coarse maps scattered into the largest coarse grid, both axes'
    cubic matrices (:func:`~raywave.wave.field.cubic_matrices`, zero beyond each grid's nodes), the differences per
    grid (:func:`_padded_gradient`) and the inversion batched. The same values as :func:`_coarse_one` up to the
    products' summation order (a Newton start: the nodes then converge on their own)."""
    s, dev = COARSE_STRIDE, reqs[0].uv.device
    kyc, kxc = max(r.coarse[0] for r in reqs), max(r.coarse[1] for r in reqs)
    ky, kx = max(r.nodes[0] for r in reqs), max(r.nodes[1] for r in reqs)
    nb = len(reqs)
    # every coarse node's flat place in the (B, kyc, kxc) padding (host integers: one transfer)
    place = np.concatenate([i * kyc * kxc + (np.arange(a * c) // c) * kxc + np.arange(a * c) % c
                            for i, (a, c) in enumerate(r.coarse for r in reqs)])
    place = torch.from_numpy(place).to(dev)
    conv = torch.cat([r.conv for r in reqs])
    uv = torch.where(conv[:, None], torch.cat([r.uv for r in reqs]), 0.0)
    uv_map = torch.zeros((nb * kyc * kxc, 2), dtype=torch.float64, device=dev).index_put_((place,), uv)
    uv_map = uv_map.reshape(nb, kyc, kxc, 2).permute(0, 3, 1, 2)
    bad = torch.zeros(nb * kyc * kxc, dtype=torch.float64, device=dev).index_put_((place,), (~conv).to(torch.float64))
    bad = bad.reshape(nb, kyc, kxc)
    sizes = torch.tensor([[*r.coarse, *r.nodes, r.h] for r in reqs], dtype=torch.float64, device=dev)
    # positions: node j of a grid at j / s coarse units (rows past a grid's own nodes: 0, discarded)
    pos_y = torch.arange(ky, dtype=torch.float64, device=dev)[None] / s
    pos_x = torch.arange(kx, dtype=torch.float64, device=dev)[None] / s
    pos_y = torch.where(pos_y <= (sizes[:, 2:3] - 1) / s, pos_y, 0.0)
    pos_x = torch.where(pos_x <= (sizes[:, 3:4] - 1) / s, pos_x, 0.0)
    my = cubic_matrices(pos_y, sizes[:, 0:1], kyc)  # (B, ky, kyc)
    mx = cubic_matrices(pos_x, sizes[:, 1:2], kxc)  # (B, kx, kxc)
    fine = my[:, None] @ uv_map @ mx.transpose(-1, -2)[:, None]  # (B, 2, ky, kx)
    unsure = (my.abs() @ bad @ mx.abs().transpose(-1, -2)) > 0
    fine = torch.where(unsure[:, None], math.nan, fine)
    h = sizes[:, 4]
    du_dy, dv_dy = _padded_gradient(fine, h, sizes[:, 2].long(), -2).unbind(1)
    du_dx, dv_dx = _padded_gradient(fine, h, sizes[:, 3].long(), -1).unbind(1)
    det = du_dx * dv_dy - du_dy * dv_dx  # (B, ky, kx)
    jac = torch.stack([torch.stack([dv_dy, -du_dy], -1), torch.stack([-dv_dx, du_dx], -1)], -2) / det[..., None, None]
    # every grid's own nodes in row-major order, gathered at once (host indices: one transfer) and split into the
    # answers (views; issue 43: not ~11 ops a construction)
    sizes = [a * c for a, c in (r.nodes for r in reqs)]
    at = np.concatenate([(np.arange(a * c) // c) * kx + np.arange(a * c) % c for a, c in (r.nodes for r in reqs)])
    grid = torch.from_numpy(np.repeat(np.arange(nb), sizes)).to(dev)
    at = torch.from_numpy(at).to(dev)
    uv0 = fine.flatten(2)[grid, :, at]  # (N, 2)
    jac0 = jac.flatten(1, 2)[grid, at]  # (N, 2, 2)
    return list(zip(uv0.split(sizes), jac0.split(sizes)))


def _node_maps(b: _Build, nd: _Nodes, traced: tuple, is_stop, diffracting) -> dict:
    """The smooth real per-node maps ``(ky, kx)`` of the wave on the plane (nodes whose ray failed take their
    nearest good neighbour's values): ``phi_env`` the optical path (Malus–Dupin to the node) less the chief
    ray's and the carrier's, ``amp2`` the irradiance from the ray density, ``det`` the pupil → plane Jacobian,
    ``dist`` the distance (mm) to the nearest aperture edge (clamped to ±3h), and with ``diffracting``:
    ``stop`` (distance, normal x, normal y) of the stop's edge, ``other`` the distance to the other edges,
    ``slopes`` the node rays' slopes. ``traced``: :func:`_trace_nodes`' ``(uv_lin, rays, at, rec, good)``."""
    lens, n, carrier = b.lens, b.n, b.carrier
    uv_lin, rays, at, rec, good = traced
    X, dvec = at.o[0, 0, :, :2], at.d[0, 0]
    phi = at.opl[0, 0] + n * ((nd.targets - X) * dvec[:, :2]).sum(-1)  # Malus–Dupin: Φ at the node itself
    w0 = source_weight(lens, rays, b.src.depth)[0, 0]
    slacks = [s.aperture.slack(*(c[0, 0] for c in rec.points[i + 1][:2]))
              for i, s in enumerate(lens.surfaces) if s.aperture is not None]
    slopes = [dvec[:, 0] / dvec[:, 2], dvec[:, 1] / dvec[:, 2], dvec[:, 0], dvec[:, 1]] if diffracting else []
    chan = torch.stack([phi, w0, dvec[:, 2], uv_lin[:, 0], uv_lin[:, 1]] + slacks + slopes, -1)
    grid = nd.as_map(_nearest_fill(chan, good, nd.targets, grad_xy=n * dvec[:, :2]))
    phi_g, w0_g, gamma_g = grid[:3]
    # ray density |det ∂uv/∂x| by central differences over the node grid
    (du_dy, dv_dy), (du_dx, dv_dx) = torch.gradient(grid[3:5], spacing=nd.h, dim=(1, 2))
    det = du_dx * dv_dy - du_dy * dv_dx
    ky, kx = nd.ky, nd.kx
    phi_env = phi_g - phi_g[ky // 2, kx // 2].detach() - n * (carrier[0] * nd.tx + carrier[1] * nd.ty)
    if b.cfg.sphere is not None:
        phi_env = phi_env + _sphere_path(b.cfg.sphere, b.z_doe, n, nd.tx, nd.ty)
    maps = {"phi_env": phi_env, "amp2": w0_g * det.abs() / gamma_g, "det": det, "slopes": grid[5 + len(slacks):],
            "phi": phi_g}
    maps.update(_edge_distances(grid[5:5 + len(slacks)], is_stop, diffracting, nd.h, ACTING_TOLERANCE * b.p))
    if maps["dist"] is None:  # no aperture at all: far from every edge
        maps["dist"] = torch.full_like(phi_g, 3.0 * nd.h)
    return maps


#: :func:`_acting`: an aperture's edge within this many simulation pitches of the stop's edge (inside the beam)
#: counts as the stop's edge itself (the two distances' first-order estimates differ by less near the rim)
ACTING_TOLERANCE = 2.0


def _acting(dj: torch.Tensor, s_stop: torch.Tensor, lim, tol) -> torch.Tensor:
    """The non-stop apertures' distances ``dj`` (..., A, ky, kx) (plane mm) with those that vignette none of the
    source's real rays set to +inf. A real ray's node lies inside the stop (``s_stop`` (..., ky, kx) > 0); an
    aperture vignettes where such a node is outside it (``dj < 0``) or, within ``lim`` of the stop's edge, nearer to
    its edge than to the stop's by more than ``tol`` (its edge then lies inside the beam's rim: a sliver thinner
    than the node spacing). An aperture that contains the beam (an element's clear aperture at or beyond the beam's
    rim, ``load_lens(..., clip_apertures=True)``) is no edge of it. The exit-pupil edge builds its ripple band from
    virtual node rays past the stop's rim, and such an aperture cut the band where those rays passed outside it,
    though it blocks no light (on axis 2.2e-2 of the bundled asphere's PSF, 6.8e-2 of the Nikkor 50 mm F/1.4's,
    with apertures at the beam's rim; now bit for bit the PSF without them). An aperture that vignettes the beam
    cuts as before, the band included."""
    s = s_stop.unsqueeze(-3)
    real = s > 0
    inside = (dj < 0) | ((dj < s - tol) & (s < lim))
    blocks = (inside & real).flatten(-2).any(-1)[..., None, None]  # (..., A, 1, 1)
    return torch.where(blocks, dj, torch.full_like(dj, math.inf))


def _edge_distances(slack_maps, is_stop, diffracting: bool, h_node: float, tol: float = 0.0) -> dict:
    """Distance (plane mm) to the nearest aperture edge, ``slack / |∇_x slack|``, clamped to ±3h (only the
    distance near an edge matters; clamping keeps the cubic interpolation from ringing where the slack has a kink,
    a circular aperture's centre, or far from any edge); with ``diffracting`` the stop's edge apart (``stop``:
    distance and unit normal, differentiated) and ``other`` (the other edges). ``slack_maps`` (A, ky, kx): every
    aperture's slack, their gradients taken at once."""
    if len(slack_maps) == 0:
        return {"dist": None, "stop": None, "other": None}
    # |∇ slack| differentiated too (issue 46): the interpolated distance near an edge is a cubic combination of
    # nodes up to 2h from it, where slack ≠ 0, so its derivative needs d|∇ slack|/dθ (the ray map's magnification of
    # the aperture; 1e-3 of the PSF gradient for a DOE order focused between the DOE and the next surface when it
    # was detached). The same values as before (the clamp at 1e-12 as a mask: finite derivatives at a kink's centre)
    gy_, gx_ = torch.gradient(slack_maps, spacing=h_node, dim=(1, 2))
    n2_all = gx_**2 + gy_**2
    ok_all = n2_all > 1e-24
    dj = slack_maps / torch.where(ok_all, safe_sqrt(n2_all, ok_all), torch.full_like(n2_all, 1e-12))  # (A, ky, kx)
    dist = dj.amin(0)
    stop, other = None, None
    if diffracting:
        stops = [j for j, s_ in enumerate(is_stop) if s_]
        others = [j for j, s_ in enumerate(is_stop) if not s_]
        if stops:
            # the Fresnel step reads the distance far from the edge (ν = g·s over several zones) and the edge's
            # normal (Fresnel length, curvature): both differentiated, |∇ slack| (the ray map's magnification of
            # the stop) included; same values as the detached ones
            sl = slack_maps[stops[-1]]
            gy_l, gx_l = torch.gradient(sl, spacing=h_node, dim=(0, 1))
            n2 = gx_l**2 + gy_l**2
            ok = n2 > 1e-24  # = the clamp at 1e-12 below, with a finite derivative at the stop's centre (kink)
            gn_l = torch.where(ok, safe_sqrt(n2, ok), torch.full_like(n2, 1e-12))
            stop = (sl / gn_l, gx_l / gn_l, gy_l / gn_l)
        if others:
            other = (dj[others] if stop is None else _acting(dj[others], stop[0], 3.0 * h_node, tol)).amin(0)
    lim = 3.0 * h_node
    return {"dist": dist.clamp(-lim, lim), "stop": stop, "other": None if other is None else other.clamp(-lim, lim)}


def _stop_edge_maps(b: _Build, nd: _Nodes, traced: tuple, maps: dict) -> dict:
    """The stop edge's channels when it diffracts from ``stop_plane`` (or from the rim's own images
    ``stop_rim``): ``nu`` = g·s (the Fresnel parameter of the node's distance to the edge, clamped where the
    factor is 1 or 0 anyway), ``kappa`` = κ·g/g_t² (the edge's curvature in Fresnel units, ``g_t`` the Fresnel
    scale along the edge), ``g_max`` the largest Fresnel scale near the edge. Warns (``check``) where the edge is
    too curved for the step. ``traced``: :func:`_trace_nodes`' ``(uv_lin, rays, at, rec, good)``."""
    lens, z_doe, stop_rim, ripple_zones = b.lens, b.z_doe, b.given.stop_rim, b.ripple
    wavelength, n, p = b.src.wavelength, b.n, b.p
    rec, good = traced[3], traced[4]
    dz_edge = z_doe - b.cfg.stop_plane
    rim_ok = False
    if stop_rim is not None:  # the rim point's own image, by the node ray's azimuth on the stop
        sx_, sy_ = (c[0, 0] for c in rec.points[lens.stop_index + 1][:2])
        dz_n = z_doe - _rim_z(stop_rim, sx_, sy_)
        dz_n = nd.as_map(_nearest_fill(dz_n[:, None], good, nd.targets)[:, 0])
        if bool((dz_n * dz_edge > 0).all()):  # same side of the DOE plane as the pupil (else: the plane)
            dz_edge, rim_ok = dz_n, True
    s_stop, nx_, ny_ = maps["stop"]
    # the Fresnel scales across the edge (g_s) and along it (g_t), in one evaluation: the edge's curvature in Fresnel
    # units is κ·g/g_t² (the kernel's lengths across and along the edge differ off axis, and on axis where the
    # wave's two curvatures do)
    g_s, g_t = _fresnel_scale(maps["slopes"], torch.stack([nx_, -ny_]), torch.stack([ny_, nx_]), nd.h, dz_edge,
                              wavelength * 1e-3 / n, p)
    # ν = g·s and κ·g/g_t² vary smoothly: interpolated as they are
    nu_lim = _nu_inner(ripple_zones) + 4.0
    div_n = torch.gradient(nx_, spacing=nd.h, dim=1)[0] + torch.gradient(ny_, spacing=nd.h, dim=0)[0]
    if rim_ok and getattr(stop_rim, "points", None) is not None and PATH_DIFFERENCE_NU:
        nu = _path_difference_nu(b, nd, (sx_, sy_), good, (maps["phi"], s_stop, g_s))
    else:
        nu = s_stop * g_s
    # the largest scale where the factor is evaluated (the band; it sets the inner tail's anti-aliasing limit):
    # deeper inside, a small beam's centre (an undefined edge normal) can have any scale
    nu_d = nu.detach()
    near = (nu_d > -math.sqrt(2.0) * ripple_zones) & (nu_d < _nu_inner(ripple_zones)) & _normal_defined(nx_, ny_)
    g_d = g_s.detach()
    g_max = float(torch.where(near.any(), torch.where(near, g_d, -math.inf).amax(), g_d.amax()))  # one host read
    if b.cfg.check:
        det = maps["det"].detach()
        traced_ = _stencil_traced(traced[4].reshape(nd.ky, nd.kx), det, det[nd.ky // 2, nd.kx // 2])
        _warn_edge_curvature(div_n.detach(), g_s.detach(), (nu.detach().abs() < 2.0) & traced_, b.field.tolist(),
                             wavelength)
    return {"nu": nu.clamp(-nu_lim, nu_lim), "nu_raw": nu.detach(),
            "kappa": (-div_n * g_s / (g_t * g_t)).clamp(-KAPPA_MAX, KAPPA_MAX), "g_max": g_max}


def _normal_defined(nx_: torch.Tensor, ny_: torch.Tensor) -> torch.Tensor:
    """Where the stop edge's normal (``nx_``, ``ny_``: unit, or ~0 where the distance map's gradient vanishes) is
    defined: not at a node on the beam's centre (the distance map's kink), whose zero normal gives a zero
    magnification and the shortest Fresnel length's scale (0.94/pitch). Issue 47: on lens A (F/12.5, Fresnel number
    12.5 on the DOE plane 3 mm before the focus) that node lies inside the inner tail (ν ≈ 5 < 5.66) and its scale,
    23× the edge's, took the inner tail's anti-aliasing limit ν_b to its floor 2: the far edge's waves were dropped
    beyond ~25 µm (the PSF's rings 0.22 / 0.58 off at 30–60 / 60–90 µm). Detached bool, the inputs' shape."""
    return (nx_.detach() ** 2 + ny_.detach() ** 2) > 0.5


#: the Fresnel step's ν from each node's optical path difference to the edge (:func:`_path_difference_nu`); False:
#: ``ν = g·s`` with the local Fresnel scale (the step before 2026-11-28)
PATH_DIFFERENCE_NU = True


#: the rim images' points and paths at a node's azimuth by trigonometric interpolation (:func:`_rim_fourier`, exact
#: for their smooth periodic dependence on the azimuth); False: the cubic (:func:`_rim_cubic`, before issue 47's fix)
RIM_FOURIER = True


def _path_difference_nu(b: _Build, nd: _Nodes, stop_xy: tuple, good, edge: tuple) -> torch.Tensor:
    """The knife edge's Fresnel parameter at the nodes ``(ky, kx)`` from the optical path difference ``Δ`` between
    the wave diffracted at the edge and the geometric one: ``ν = sign(s)·2·sqrt(Δ/λ)``, ``Δ = Φ_E + n|P − E| − Φ_P``
    with ``E`` the image of the stop's rim point at the node ray's azimuth (:class:`RimImages`: the edge's
    diffracted wave leaves it, on straight lines in the image medium), ``Φ_E`` the optical path to it, ``P`` the
    node on the plane ``z_doe`` and ``Φ_P`` its optical path (``phi``); ``Δ = ±(Φ_E − n|P − E| − Φ_P)`` where the
    plane lies before the rim's images (the wave still converges on them; the knife edge's factor is then the
    mirrored one): ``+`` where the beam passes a focus between the plane and the images (the difference is then
    ≥ 0), ``−`` where it does not (≤ 0: ``|Φ_E − Φ_P| ≤ n|P − E|``), chosen by the sign most nodes have. In the
    quadratic approximation this is ``g·s`` (:func:`_fresnel_scale`: ``Δ = n s²/(2L)``); unlike it, it holds where
    the wave's convergence changes across the edge's Fresnel zones (an aberrated beam, off axis: the local ``L`` at
    the node is not that of the path from the edge). Near the shadow's edge (``|s|`` below a tenth of a Fresnel
    unit) it blends into ``g·s``: ``g_eff² = (4Δ/λ + g² s₀²)/(s² + s₀²)``, smooth and with finite derivatives where
    ``Δ`` and ``s`` vanish together. ``stop_xy`` = ``(sx, sy)`` (N,) the node rays' stop coordinates, ``edge`` = ``(phi, s_stop, g_s)``
    (ky, kx); the rim images are ``b.given.stop_rim``. Differentiable."""
    rim, z_doe, wavelength, n = b.given.stop_rim, b.z_doe, b.src.wavelength, b.n
    sx, sy = stop_xy
    phi, s_stop, g_s = edge
    interp = _rim_fourier if RIM_FOURIER else _rim_cubic
    at_rim = interp(torch.cat([rim.points, rim.opl[:, None]], -1), sx, sy)  # (N, 4): x, y, z, Φ_E
    filled = nd.as_map(_nearest_fill(at_rim, good, nd.targets))  # (4, ky, kx)
    ex, ey, ez, phi_e = filled
    dx, dy, dz = nd.tx - ex, nd.ty - ey, z_doe - ez
    # the diffracted wave leaves E on its way to P, or (a DOE plane before the edge's images) converges on it
    sgn = 1.0 if bool((dz.detach() > 0).all()) else -1.0
    delta = phi_e + sgn * n * torch.sqrt(dx * dx + dy * dy + dz * dz) - phi
    if sgn < 0 and bool((delta.detach() < 0).sum() > (delta.detach() > 0).sum()):
        # converging on E with no focus of the beam between the plane and E: the difference is ≤ 0 (the optical path
        # is n-Lipschitz there, |Φ_E − Φ_P| ≤ n|P − E|), its size the knife edge's (issue 46: order +17 of a
        # mid-system 16-level DOE, its step plane 0.46 mm before its rim images; clamped, it set ν ≈ 0 over the whole
        # plane: no stop edge). With a focus between them (the stop imaged beyond the beam's focus) it is ≥ 0
        delta = -delta
    lam = wavelength * 1e-3
    s0 = 0.1 / g_s.detach()
    g2 = ((4.0 * delta / lam + g_s * g_s * s0 * s0) / (s_stop * s_stop + s0 * s0)).clamp_min(1e-300)
    return s_stop * torch.sqrt(g2)


def _sphere_path(sphere: tuple, z: float, n, tx: torch.Tensor, ty: torch.Tensor) -> torch.Tensor:
    """The optical path (mm) of the wave converging on the point ``sphere`` ``(x, y, z_f)`` mm from the nodes ``tx``,
    ``ty`` (ky, kx) mm of the plane ``z`` to it, less the centre node's (``n`` the medium's index): added to the
    optical path, it leaves the envelope relative to that sphere (:class:`FieldSettings` ``sphere``)."""
    fx, fy, fz = (float(v) for v in sphere)
    tx, ty = torch.broadcast_tensors(tx, ty)
    r = torch.sqrt((tx - fx) ** 2 + (ty - fy) ** 2 + (fz - z) ** 2)
    return n * (r - r[r.shape[0] // 2, r.shape[1] // 2].detach())


def _sphere_directions(sphere: tuple, z: float, x: torch.Tensor, y: torch.Tensor) -> tuple:
    """The direction cosines ``(α, β)`` towards the point ``sphere`` from the points ``x``, ``y`` mm of the plane
    ``z`` mm (the converging sphere's rays)."""
    fx, fy, fz = (float(v) for v in sphere)
    r = torch.sqrt((fx - x) ** 2 + (fy - y) ** 2 + (fz - z) ** 2)
    return (fx - x) / r, (fy - y) / r


def _check_nodes(b: _Build, nd: _Nodes, maps: dict, good, dvec) -> None:
    """Warn where the pupil → plane map folds (a caustic) or the envelope's phase slope passes Nyquist (``dvec``
    (N, 3) the node rays' directions)."""
    carrier, n, p, wavelength, field = b.carrier, b.n, b.p, b.src.wavelength, b.field
    ky, kx = nd.ky, nd.kx
    lit_nodes = (maps["dist"] > -nd.h) & good.reshape(ky, kx)
    det = maps["det"].detach()
    if bool(((det * det[ky // 2, kx // 2] <= 0) & lit_nodes).any()):
        _fold_warning(field.tolist(), wavelength, stacklevel=5)
    c0, c1 = carrier
    if b.cfg.sphere is not None:  # the envelope's phase slope relative to the sphere's rays
        c0, c1 = _sphere_directions(b.cfg.sphere, b.z_doe, nd.targets[:, 0], nd.targets[:, 1])
    slope = n * torch.sqrt((dvec[:, 0] - c0) ** 2 + (dvec[:, 1] - c1) ** 2).reshape(ky, kx)
    _warn_nyquist(slope * (2 * p) / (wavelength * 1e-3), lit_nodes, nd.targets, field.tolist(), wavelength, p)


def _fold_warning(field: list, wavelength: float, stacklevel: int) -> None:
    """:func:`_check_nodes`' :class:`SamplingWarning` that the ray map folds (``field`` a list, ``wavelength`` µm)."""
    warnings.warn(f"the ray map from the pupil to the DOE plane folds (a caustic lies between the lens and the "
                  f"DOE) for field {field} at {wavelength:g} µm; the accurate field is wrong there: "
                  "use mode='faithful' or move the DOE", SamplingWarning, stacklevel=stacklevel)


def _aperture_roles(b: _Build) -> tuple[list, bool]:
    """``(is_stop, diffracting)``: for every surface of the lens with an aperture, whether it is the stop; and
    whether the stop's edge diffracts from a plane of its own (``stop_plane`` set and a stop with an aperture)."""
    lens = b.lens
    is_stop = [i == lens.stop_index for i, s in enumerate(lens.surfaces) if s.aperture is not None]
    return is_stop, b.cfg.stop_plane is not None and any(is_stop)


def _node_stage(b: _Build, nd: _Nodes, traced: tuple) -> dict | None:
    """The node-map stage of one construction: :func:`_node_maps`, :func:`_stop_edge_maps` (the stop edge
    diffracting), :func:`_check_nodes` (``check``); returns the maps the field stage reads (:data:`_FIELD_MAPS`), or
    None when no node's ray was traced (``traced``: :func:`_trace_nodes`' ``(uv_lin, rays, at, rec, good)``)."""
    good = traced[-1]
    if not bool(good.any()):
        return None
    is_stop, diffracting = _aperture_roles(b)
    maps = _node_maps(b, nd, traced, is_stop, diffracting)
    if diffracting:
        maps.update(_stop_edge_maps(b, nd, traced, maps))
    if b.cfg.check:
        _check_nodes(b, nd, maps, good, traced[2].d[0, 0])
    return {k: v for k, v in maps.items() if k in _FIELD_MAPS}


class _NodeMapRequest:
    """The node-map stage of one construction (:func:`_node_stage`'s arguments: the :class:`_Build`, its
    :class:`_Nodes` and :func:`_trace_nodes`' result ``traced``), yielded by :func:`accurate_field_steps` after its
    node rays are traced; answered with the maps of :data:`_FIELD_MAPS` or None (no node traced).
    :func:`~raywave.hybrid.coherent.tracing.run_batched` answers the pending requests of a lens, mode and device
    together (``run_group``, :func:`_node_stages`): on an accelerator as padded batches (:func:`_node_stage_batch`),
    waiting (``deferred``) until no trace is pending so that every construction joins; on a CPU one by one."""

    def __init__(self, b: _Build, nd: _Nodes, traced: tuple):
        self.b, self.nd, self.traced = b, nd, traced
        self.deferred = devices.accelerator(nd.gx)

    def run(self):
        """This construction's node maps alone (:func:`_node_stage`; :func:`run_serial`)."""
        return _node_stage(self.b, self.nd, self.traced)

    @staticmethod
    def run_group(reqs: list) -> list:
        """The answers of a group of requests (one ``group_key``), in order (:func:`_node_stages`)."""
        return _node_stages(reqs)

    def group_key(self) -> tuple:
        """What the requests batched together share: the lens (its apertures and stop), whether the stop edge
        diffracts from a plane of its own, the checks, the stop rim's sampling (its points' count, whether it carries
        image points), the object depth and the device; each construction carries its own node grid, wavelength,
        medium, carrier, planes and ripple band."""
        b = self.b
        rim = b.given.stop_rim
        rim_key = None if rim is None else (int(rim[0].numel()), getattr(rim, "points", None) is not None)
        depth = b.src.depth
        return ("nodes", id(b.lens), b.cfg.stop_plane is not None, bool(b.cfg.check), rim_key,
                None if depth is None else float(depth), self.nd.gx.device)


#: a batch of :func:`_node_stage_batch` spans at most this many padded nodes (every construction's node grid padded
#: to the batch's largest; ~1 kB a node at the peak, its channels, differences and maps, the rims' harmonics in
#: blocks of :data:`~raywave.hybrid.coherent.stop_edge.RIM_FOURIER_BLOCK`: ~90 of the bundled asphere's ~150² grids)
NODE_BATCH_SAMPLES = 2**21


def _node_batch_cap(device) -> int:
    """Padded nodes a batch of :func:`_node_stage_batch` may span on ``device``: :data:`NODE_BATCH_SAMPLES`, on CUDA at
    most a 16 384th of the device's memory in nodes (~1 kB a node at the peak: at most ~6 % of the memory; a 16 GB
    GPU takes ~10⁶ nodes a batch, an H200 the full 2²¹)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return NODE_BATCH_SAMPLES
    return max(2**16, min(NODE_BATCH_SAMPLES, torch.cuda.get_device_properties(dev).total_memory // 16384))


def _node_stages(reqs: list) -> list:
    """:func:`_node_stage` of every :class:`_NodeMapRequest` of ``reqs`` (one ``group_key``), in order. On an
    accelerator (:func:`raywave.utils.devices.accelerator`) in padded batches of at most :func:`_node_batch_cap`
    nodes (:func:`_node_stage_batch`: a fixed number of kernels and two host reads per batch instead of ~480 ops
    and ~8 reads per construction), each construction's maps equal to its own call's to rounding; else one call
    each (the CPU: batched there, the padding and the rims' harmonics over every padded node make the stage 2.5×
    slower, 1.7× with autograd; its maps are the reference)."""
    if len(reqs) < 2 or not devices.accelerator(reqs[0].nd.gx) or not RIM_FOURIER:
        return [r.run() for r in reqs]
    out: list = [None] * len(reqs)
    for chunk in _field_chunks([(0, r.nd.ky, 0, r.nd.kx) for r in reqs], _node_batch_cap(reqs[0].nd.gx.device)):
        for j, res in zip(chunk, _node_stage_batch([reqs[j] for j in chunk])):
            out[j] = res
    return out


@dataclass
class _NodeBatch:
    """B node grids (one per construction) as one padded batch: every grid's nodes in the corner of a common
    ``(KY, KX)`` grid. ``sizes`` [(ky, kx)], ``pad`` (B·KY·KX,) long: the node (an index into the constructions'
    nodes concatenated in order) each padded place copies (beyond a grid: its nearest node, so that every padded
    value is one of its own grid's), ``valid`` (B, KY, KX) bool: the grid's own nodes, ``rid`` (N,) long: each
    concatenated node's construction, ``h`` (B,) mm the spacings."""

    sizes: list
    pad: torch.Tensor
    valid: torch.Tensor
    rid: torch.Tensor
    h: torch.Tensor

    @staticmethod
    def of(nds: list) -> "_NodeBatch":
        """The batch of the :class:`_Nodes` ``nds`` (host integers: one transfer each)."""
        dev = nds[0].gx.device
        sizes = [(nd.ky, nd.kx) for nd in nds]
        ky_max, kx_max = max(a for a, _ in sizes), max(c for _, c in sizes)
        jj, ii = np.arange(ky_max)[:, None], np.arange(kx_max)[None, :]
        offs = np.cumsum([0] + [a * c for a, c in sizes])
        pad = np.stack([o + np.minimum(jj, a - 1) * c + np.minimum(ii, c - 1) for o, (a, c) in zip(offs, sizes)])
        valid = np.stack([(jj < a) & (ii < c) for a, c in sizes])
        rid = np.repeat(np.arange(len(nds)), np.diff(offs))
        return _NodeBatch(sizes, torch.from_numpy(pad.reshape(-1)).to(dev), torch.from_numpy(valid).to(dev),
                          torch.from_numpy(rid).to(dev),
                          torch.tensor([nd.h for nd in nds], dtype=torch.float64, device=dev))

    @property
    def shape(self) -> tuple:
        """``(B, KY, KX)``."""
        return tuple(self.valid.shape)

    def padded(self, flat: torch.Tensor) -> torch.Tensor:
        """Per-node values ``flat`` (N, C) of the concatenated grids → padded maps (B, C, KY, KX)."""
        return flat[self.pad].reshape(*self.shape, -1).permute(0, 3, 1, 2)

    def gradients(self, f: torch.Tensor) -> tuple:
        """``(∂f/∂y, ∂f/∂x)`` of the padded maps ``f`` (B, C, KY, KX) by each grid's own differences
        (:func:`torch.gradient`'s edge rule per grid, :func:`_padded_gradient`): the values of ``torch.gradient(f[b],
        spacing=h[b], dim=(1, 2))`` on each grid alone."""
        size = torch.tensor(self.sizes, device=f.device)
        return _padded_gradient(f, self.h, size[:, 0], -2), _padded_gradient(f, self.h, size[:, 1], -1)

    def own(self, mask: torch.Tensor) -> torch.Tensor:
        """``mask`` (B, KY, KX) bool on each grid's own nodes only (False beyond)."""
        return mask & self.valid


def _batch_inputs(reqs: list, good: torch.Tensor) -> dict:
    """The traced node rays of the constructions ``reqs`` (:class:`_NodeMapRequest`) concatenated in order (one op
    per tensor): ``uv`` (N, 2) entrance-plane mm, ``rays_d`` (1, 1, N, 3) the rays' directions at the source,
    ``o``, ``d`` (N, 3) and ``opl`` (N,) on the plane, ``good`` (N,) (given, concatenated), ``targets`` (N, 2) mm and
    ``xy`` [(x, y)] (N,) mm the node rays on every surface with an aperture, in the lens's order."""
    tr = [r.traced for r in reqs]
    on = [i for i, s in enumerate(reqs[0].b.lens.surfaces) if s.aperture is not None]
    # (the rows of one batched trace gathered from it: cat_rows, cat_points)
    at = [t[2] for t in tr]
    return {"uv": torch.cat([t[0] for t in tr]), "rays_d": cat_rows([t[1] for t in tr], "d"),
            "o": cat_rows(at, "o", flat=True), "d": cat_rows(at, "d", flat=True),
            "opl": cat_rows(at, "opl", flat=True), "good": good,
            "targets": torch.cat([r.nd.targets for r in reqs]),
            "xy": [tuple(cat_points([t[3] for t in tr], i + 1, c, flat=True) for c in (0, 1)) for i in on]}


def _nearest_good(good: torch.Tensor, xy: torch.Tensor, spans: list) -> tuple:
    """The nearest good node of every bad node (:func:`~raywave.hybrid.coherent.tracing._nearest_fill`'s choice) in
    the concatenated grids: ``good`` (N,), node positions ``xy`` (N, 2) mm, ``spans`` [(start, end)] the grids that
    have both good and bad nodes. Returns ``(bad (M,), near (M,))`` long indices."""
    bads, nears = [], []
    for a, e in spans:
        gi = torch.nonzero(good[a:e]).squeeze(1)
        bi = torch.nonzero(~good[a:e]).squeeze(1)
        check_allocation(16.0 * bi.numel() * gi.numel(), f"the node grid's nearest-node fill ({bi.numel()} × "
                         f"{gi.numel()} distances)", "fewer nodes (rays; raywave: --rays) or a finer DOE pitch "
                         "(--doe-pitch, in mm: a pitch as large as the beam widens the node grid's margin)", xy.device)
        d = torch.cdist(xy[a:e][bi].detach(), xy[a:e][gi].detach())
        bads.append(bi + a)
        nears.append(gi[d.argmin(1)] + a)
    return torch.cat(bads), torch.cat(nears)


def _node_stage_batch(reqs: list) -> list:
    """:func:`_node_stage` of B constructions (:class:`_NodeMapRequest`, one ``group_key``) as batched tensor ops on
    their node grids padded to a common grid (:class:`_NodeBatch`): the per-node channels of every construction at
    once, the nearest-node fill, each grid's own boundary differences, the per-construction constants as (B, 1, 1)
    tensors and the discrete choices (the path difference's signs, the rim images' plane) as masks: two host reads
    for the batch (the traced nodes' counts; the Fresnel scales' maxima ``g_max`` with the checks' results) instead
    of ~8 per construction. Returns the maps of :data:`_FIELD_MAPS` of each (views of one padded batch; the same
    values as :func:`_node_stage` to rounding) or None (no node traced), the checks' warnings worded and ordered as
    each construction's own."""
    nodes = [r.nd for r in reqs]
    nb = _NodeBatch.of(nodes)
    good = torch.cat([r.traced[4] for r in reqs])
    count = torch.zeros(len(reqs), dtype=torch.float64, device=good.device).index_add_(
        0, nb.rid, good.to(torch.float64)).tolist()  # host read 1: the traced nodes
    lit = [k for k, c in enumerate(count) if c > 0]
    out: list = [None] * len(reqs)
    if not lit:
        return out
    if len(lit) < len(reqs):  # constructions without a traced node: None (their warning is the generator's)
        for k, res in zip(lit, _node_stage_batch([reqs[k] for k in lit])):
            out[k] = res
        return out
    is_stop, diffracting = _aperture_roles(reqs[0].b)
    x = _batch_inputs(reqs, good)
    spans = [(int(a), int(a + nd.ky * nd.kx)) for a, nd, c in
             zip(np.cumsum([0] + [nd.ky * nd.kx for nd in nodes]), nodes, count) if c < nd.ky * nd.kx]
    grid, k_of = _batch_node_channels(reqs, nb, x, spans, diffracting)
    maps = _batch_node_maps(reqs, nb, grid, k_of, (is_stop, diffracting))
    checks = []
    if diffracting:
        edge = _stop_edge_batch(reqs, nb, grid, k_of, maps, x["good"])
        checks.append(edge.pop("g_max"))
        if "curvature" in edge:
            checks.append(edge.pop("curvature"))
        maps.update(edge)
    if reqs[0].b.cfg.check:
        checks.extend(_check_nodes_batch(reqs, nb, grid, k_of, maps, x["good"]))
    return _batch_answers(reqs, nb, maps, checks, diffracting)


def _batch_node_channels(reqs: list, nb: _NodeBatch, x: dict, spans: list, diffracting: bool) -> tuple:
    """The per-node channels of :func:`_node_maps` for the batch's constructions, filled (:func:`_nearest_good`:
    bad nodes take their nearest good node's values, the optical path extended to first order) and padded
    (B, C, KY, KX): ``(grid, k_of)``, ``k_of`` the channel names' indices (``phi``, ``w0``, ``dx``, ``dy``, ``dz``
    the node rays' direction, ``u``, ``v`` entrance-plane mm, ``slack`` (first of the apertures' slacks), with the
    stop's edge diffracting ``sx``, ``sy`` the node rays on the stop)."""
    r0 = reqs[0].b
    lens, dev = r0.lens, x["o"].device
    n_node = torch.tensor([r.b.n for r in reqs], dtype=torch.float64, device=dev)[nb.rid]
    X, dvec = x["o"][:, :2], x["d"]
    phi = x["opl"] + n_node * ((x["targets"] - X) * dvec[:, :2]).sum(-1)  # Malus–Dupin: Φ at the node itself
    w0 = source_weight(lens, _Directions(x["rays_d"]), r0.src.depth)[0, 0]
    apertures = [s.aperture for s in lens.surfaces if s.aperture is not None]
    slacks = [a.slack(*xy) for a, xy in zip(apertures, x["xy"])]
    stop_xy = []
    if diffracting:
        stop_xy = list(x["xy"][[i == lens.stop_index for i, s in enumerate(lens.surfaces)
                                if s.aperture is not None].index(True)])
    names = ["phi", "w0", "dx", "dy", "dz", "u", "v"] + ["slack"] * len(slacks) + (["sx", "sy"] if stop_xy else [])
    chan = torch.stack([phi, w0, dvec[:, 0], dvec[:, 1], dvec[:, 2], x["uv"][:, 0], x["uv"][:, 1]] + slacks
                       + stop_xy, -1)
    if spans:  # nodes whose ray failed: their nearest good node's values (_nearest_fill's arithmetic)
        bi, near = _nearest_good(x["good"], x["targets"], spans)
        grad_xy = n_node[:, None] * dvec[:, :2]
        filled = chan[near].clone()
        filled[:, 0] = filled[:, 0] + (grad_xy[near] * (x["targets"][bi] - x["targets"][near])).sum(-1)
        chan = chan.index_put((bi,), filled)
    k_of = {}
    for k, name in enumerate(names):
        k_of.setdefault(name, k)
    return nb.padded(chan), k_of


class _Directions:
    """The directions ``d`` of a bundle of rays (what :func:`~raywave.lens.sources.source_weight` reads)."""

    def __init__(self, d: torch.Tensor):
        self.d = d


def _batch_scalars(reqs: list, columns) -> torch.Tensor:
    """Per-construction constants as one (B, K) float64 tensor (one transfer): ``columns(r)`` gives the K host floats
    of a :class:`_NodeMapRequest` (computed with the per-construction path's own expressions: the same doubles)."""
    return torch.tensor([columns(r) for r in reqs], dtype=torch.float64, device=reqs[0].nd.gx.device)


def _padded_axis(axes: list, sizes: list) -> torch.Tensor:
    """The node coordinates ``axes`` [(k_b,)] of B grids padded to (B·K,) with K = max k_b (beyond a grid's own: its
    last)."""
    k_max = max(sizes)
    start = np.concatenate([[0], np.cumsum(sizes)])[:-1]
    idx = np.stack([o + np.minimum(np.arange(k_max), k - 1) for o, k in zip(start, sizes)]).reshape(-1)
    return torch.cat(axes)[torch.from_numpy(idx).to(axes[0].device)]


def _batch_node_maps(reqs: list, nb: _NodeBatch, grid: torch.Tensor, k_of: dict, roles: tuple) -> dict:
    """:func:`_node_maps` (and :func:`_edge_distances`) of the batch from its padded channels ``grid``
    (:func:`_batch_node_channels`): the same maps, each (B, KY, KX) (``slopes`` (B, 4, KY, KX)), and ``tx``, ``ty``
    the node positions mm, ``center`` (B,) the flat index of each grid's centre node and (diffracting)
    ``slope_grads`` the y and x differences of the slopes ``t_x/γ, t_y/γ`` ((B, 2, KY, KX) each)."""
    is_stop, diffracting = roles
    c = _batch_scalars(reqs, lambda r: [r.b.n, r.b.carrier[0], r.b.carrier[1], 3.0 * r.nd.h,
                                        ACTING_TOLERANCE * r.b.p])[:, :, None, None]
    n, c0, c1, lim, tol = c.unbind(1)
    dev = grid.device
    bsz, _, ky_max, kx_max = grid.shape
    ch = grid.unbind(1)
    phi_g, w0_g, dx, dy, gamma_g = ch[:5]
    n_ap = len(is_stop)
    # the node positions (mm): grid b's gx at its columns, gy at its rows (clamped beyond its own, like the padding)
    tx = _padded_axis([r.nd.gx for r in reqs], [kx for _, kx in nb.sizes]).reshape(bsz, 1, kx_max)
    ty = _padded_axis([r.nd.gy for r in reqs], [ky for ky, _ in nb.sizes]).reshape(bsz, ky_max, 1)
    tx, ty = tx.expand(bsz, ky_max, kx_max), ty.expand(bsz, ky_max, kx_max)
    k_uv = k_of["u"]
    diff = [grid[:, k_uv:k_uv + 2 + n_ap]]
    slopes = None
    if diffracting:
        slopes = torch.stack([dx / gamma_g, dy / gamma_g, dx, dy], 1)
        diff.append(slopes[:, :2])
    grads = nb.gradients(torch.cat(diff, 1) if len(diff) > 1 else diff[0])
    if diffracting:  # the slopes' differences (_fresnel_scale's), (B, 2, KY, KX) each
        slope_grads = tuple(g_[:, 2 + n_ap:4 + n_ap] for g_ in grads)
    (du_dy, dv_dy), (du_dx, dv_dx) = (g[:, :2].unbind(1) for g in grads)
    det = du_dx * dv_dy - du_dy * dv_dx
    center = torch.tensor([(ky // 2) * kx_max + kx // 2 for ky, kx in nb.sizes], device=dev)
    phi_c = phi_g.reshape(bsz, -1).gather(1, center[:, None]).detach()[:, :, None]
    phi_env = phi_g - phi_c - n * (c0 * tx + c1 * ty)
    if any(r.b.cfg.sphere is not None for r in reqs):  # (the caustic fallback's scaled carry only)
        phi_env = phi_env + torch.stack([torch.zeros_like(phi_env[i]) if r.b.cfg.sphere is None else
                                         _sphere_path(r.b.cfg.sphere, r.b.z_doe, r.b.n, tx[i], ty[i])
                                         for i, r in enumerate(reqs)])
    maps = {"phi_env": phi_env, "amp2": w0_g * det.abs() / gamma_g, "det": det, "slopes": slopes, "phi": phi_g,
            "tx": tx, "ty": ty, "center": center, "slope_grads": slope_grads if diffracting else None}
    if n_ap == 0:  # no aperture at all: far from every edge
        maps.update(dist=lim.expand(bsz, ky_max, kx_max), stop=None, other=None)
        return maps
    # distance to the nearest aperture edge, slack / |∇ slack| (_edge_distances: the same values)
    sl = grid[:, k_of["slack"]:k_of["slack"] + n_ap]
    gy_, gx_ = grads[0][:, 2:2 + n_ap], grads[1][:, 2:2 + n_ap]
    n2_all = gx_**2 + gy_**2
    ok_all = n2_all > 1e-24
    den = torch.where(ok_all, safe_sqrt(n2_all, ok_all), torch.full_like(n2_all, 1e-12))
    dj = sl / den  # (B, A, KY, KX)
    dist = dj.amin(1)
    stop, other = None, None
    if diffracting:
        j = [k for k, s_ in enumerate(is_stop) if s_][-1]
        stop = (dj[:, j], gx_[:, j] / den[:, j], gy_[:, j] / den[:, j])
        others = [k for k, s_ in enumerate(is_stop) if not s_]
        if others:
            other = _acting(dj[:, others], stop[0], lim[:, None], tol[:, None]).amin(1)
    maps.update(dist=dist.clamp(-lim, lim), stop=stop, other=None if other is None else other.clamp(-lim, lim))
    return maps


def _stop_edge_batch(reqs: list, nb: _NodeBatch, grid: torch.Tensor, k_of: dict, maps: dict,
                     good: torch.Tensor) -> dict:
    """:func:`_stop_edge_maps` of the batch (``maps``: :func:`_batch_node_maps`'): ``nu``, ``nu_raw``, ``kappa``
    (B, KY, KX), ``g_max`` (B,) (a tensor: read with the checks) and with ``check`` ``curvature`` (B,): the ratio
    :func:`_warn_edge_curvature` compares with :data:`EDGE_CURVATURE_LIMIT`. Each construction's edge plane (its rim
    images where they all lie on the pupil's side of the plane, else the stop plane) and its ν (the path difference
    with rim images, :func:`_path_difference_batch`) chosen by masks, with no host read. ``good`` (N,): the
    concatenated nodes' traced flags (the curvature is read only where its stencil was traced, :func:`_stencil_traced`)."""
    r0 = reqs[0].b
    bsz, _, ky_max, kx_max = grid.shape

    def columns(r):
        b = r.b
        lam_m = b.src.wavelength * 1e-3 / b.n
        return [b.z_doe, b.z_doe - b.cfg.stop_plane, b.src.wavelength * 1e-3, lam_m, (1.5 * b.p) ** 2 / lam_m,
                _nu_inner(b.ripple) + 4.0, -math.sqrt(2.0) * b.ripple, _nu_inner(b.ripple), b.n]

    z_doe, dz0, lam, lam_m, min_len, nu_lim, band_lo, band_hi, n = _batch_scalars(reqs, columns)[:, :, None,
                                                                                                 None].unbind(1)
    rim_ok, dz_edge = None, dz0
    if r0.given.stop_rim is not None:  # the rim point's own image, by the node ray's azimuth on the stop
        sx, sy = grid[:, k_of["sx"]].reshape(bsz, -1), grid[:, k_of["sy"]].reshape(bsz, -1)
        z_rim = torch.stack([r.b.given.stop_rim[1] for r in reqs])
        dz_n = (z_doe[:, 0] - _rim_z_rows(z_rim, sx, sy)).reshape(bsz, ky_max, kx_max)
        rim_ok = ((dz_n * dz0 > 0) | ~nb.valid).flatten(1).all(1)  # same side of the DOE plane as the pupil
        dz_edge = torch.where(rim_ok[:, None, None], dz_n, dz0)
    s_stop, nx_, ny_ = maps["stop"]
    slopes, (gy, gx) = maps["slopes"], maps["slope_grads"]
    g = _fresnel_scale_at(((gy[:, :1], gy[:, 1:]), (gx[:, :1], gx[:, 1:])), (slopes[:, 2:3], slopes[:, 3:4]),
                          (torch.stack([nx_, -ny_], 1), torch.stack([ny_, nx_], 1)), dz_edge[:, None],
                          lam_m[:, None], min_len[:, None])
    g_s, g_t = g.unbind(1)
    gy_n, gx_n = nb.gradients(torch.stack([nx_, ny_], 1))
    div_n = gx_n[:, 0] + gy_n[:, 1]
    nu = s_stop * g_s
    if rim_ok is not None and getattr(r0.given.stop_rim, "points", None) is not None and PATH_DIFFERENCE_NU:
        nu = torch.where(rim_ok[:, None, None], _path_difference_batch(reqs, nb, grid, k_of, maps,
                                                                       (g_s, lam, n, z_doe)), nu)
    nu_d, g_d = nu.detach(), g_s.detach()
    near = nb.own((nu_d > band_lo) & (nu_d < band_hi) & _normal_defined(nx_, ny_))
    g_max = torch.where(near.flatten(1).any(1), torch.where(near, g_d, -math.inf).flatten(1).amax(1),
                        torch.where(nb.valid, g_d, -math.inf).flatten(1).amax(1))
    out = {"nu": nu.clamp(-nu_lim, nu_lim), "nu_raw": nu_d,
           "kappa": (-div_n * g_s / (g_t * g_t)).clamp(-KAPPA_MAX, KAPPA_MAX), "g_max": g_max}
    if r0.cfg.check:
        det = maps["det"].detach()
        det_c = det.reshape(bsz, -1).gather(1, maps["center"][:, None])[:, :, None]
        own_good = nb.padded(good[:, None])[:, 0] | ~nb.valid  # (beyond a grid's own nodes: traced, same sheet)
        traced_ = _stencil_traced(own_good, torch.where(nb.valid, det, det_c), det_c)
        out["curvature"] = torch.where(nb.own((nu_d.abs() < 2.0) & traced_), div_n.detach().abs() * math.sqrt(2.0)
                                       / g_d, -math.inf).flatten(1).amax(1)
    return out


def _path_difference_batch(reqs: list, nb: _NodeBatch, grid: torch.Tensor, k_of: dict, maps: dict,
                           consts: tuple) -> torch.Tensor:
    """:func:`_path_difference_nu` of the batch (B, KY, KX): every construction's rim images interpolated at its node
    rays' azimuths (:func:`~raywave.hybrid.coherent.stop_edge._rim_fourier_rows`), the two sign choices per
    construction as (B, 1, 1) masks. ``consts`` = ``(g_s (B, KY, KX), λ (mm), n, z_doe (mm))`` (the last three
    (B, 1, 1))."""
    g_s, lam, n, z_doe = consts
    bsz, _, ky_max, kx_max = grid.shape
    rims = [r.b.given.stop_rim for r in reqs]
    values = torch.cat([torch.stack([rm.points for rm in rims]), torch.stack([rm.opl for rm in rims])[..., None]], -1)
    at_rim = _rim_fourier_rows(values, grid[:, k_of["sx"]].reshape(bsz, -1), grid[:, k_of["sy"]].reshape(bsz, -1))
    ex, ey, ez, phi_e = at_rim.reshape(bsz, ky_max, kx_max, 4).unbind(-1)
    dx, dy, dz = maps["tx"] - ex, maps["ty"] - ey, z_doe - ez
    # the diffracted wave leaves E on its way to P, or (a DOE plane before the edge's images) converges on it
    sgn = ((dz.detach() > 0) | ~nb.valid).flatten(1).all(1).to(torch.float64)[:, None, None] * 2.0 - 1.0
    delta = phi_e + sgn * n * torch.sqrt(dx * dx + dy * dy + dz * dz) - maps["phi"]
    d_ = delta.detach()
    more_negative = nb.own(d_ < 0).flatten(1).sum(1) > nb.own(d_ > 0).flatten(1).sum(1)
    delta = torch.where(((sgn[:, 0, 0] < 0) & more_negative)[:, None, None], -delta, delta)
    s_stop = maps["stop"][0]
    s0 = 0.1 / g_s.detach()
    g2 = ((4.0 * delta / lam + g_s * g_s * s0 * s0) / (s_stop * s_stop + s0 * s0)).clamp_min(1e-300)
    return s_stop * torch.sqrt(g2)


def _check_nodes_batch(reqs: list, nb: _NodeBatch, grid: torch.Tensor, k_of: dict, maps: dict,
                       good: torch.Tensor) -> list:
    """:func:`_check_nodes` of the batch, evaluated but not read: ``[fold, any lit, Nyquist ratio, x, y]`` (B,) each:
    whether the ray map folds among the lit nodes, whether any node is lit, the largest phase slope / Nyquist on the
    lit nodes and the node (mm) where it is (the first, as :func:`~raywave.hybrid.coherent.geometry._warn_nyquist`
    finds it). ``good`` (N,): the concatenated nodes' traced flags."""
    bsz = grid.shape[0]
    c = _batch_scalars(reqs, lambda r: [r.b.n, r.b.carrier[0], r.b.carrier[1], -r.nd.h, 2 * r.b.p,
                                        r.b.src.wavelength * 1e-3])
    n, c0, c1, neg_h, two_p, lam = c[:, :, None, None].unbind(1)
    lit = nb.own((maps["dist"] > neg_h) & nb.padded(good[:, None])[:, 0])
    det = maps["det"].detach()
    det_c = det.reshape(bsz, -1).gather(1, maps["center"][:, None])[:, :, None]
    fold = ((det * det_c <= 0) & lit).flatten(1).any(1)
    if any(r.b.cfg.sphere is not None for r in reqs):  # relative to the sphere's rays (the scaled carry)
        c0, c1 = c0.expand(bsz, *grid.shape[2:]).clone(), c1.expand(bsz, *grid.shape[2:]).clone()
        for i, r in enumerate(reqs):
            if r.b.cfg.sphere is not None:
                c0[i], c1[i] = _sphere_directions(r.b.cfg.sphere, r.b.z_doe, maps["tx"][i], maps["ty"][i])
    slope = n * torch.sqrt((grid[:, k_of["dx"]] - c0) ** 2 + (grid[:, k_of["dy"]] - c1) ** 2)
    ratio = slope * two_p / lam
    r = torch.where(lit, ratio.detach(), torch.zeros_like(ratio)).flatten(1)
    at = torch.argmax(r, 1, keepdim=True)
    xy = torch.stack([maps["tx"], maps["ty"]], 1).reshape(bsz, 2, -1).gather(2, at[:, None].expand(bsz, 2, 1))
    return [fold, lit.flatten(1).any(1), r.gather(1, at)[:, 0], xy[:, 0, 0], xy[:, 1, 0]]


def _batch_answers(reqs: list, nb: _NodeBatch, maps: dict, checks: list, diffracting: bool) -> list:
    """Each construction's maps of :data:`_FIELD_MAPS` as views of one padded stack (its own grid's corner), and the
    checks' warnings (the edge's curvature, the fold, Nyquist: each construction's in its own call's order and
    words) from one host read of ``checks`` ((B,) tensors: ``g_max`` first with ``diffracting``, then the edge's
    curvature and :func:`_check_nodes_batch`'s with ``check``) and the constructions' fields."""
    check = reqs[0].b.cfg.check
    names = ["phi_env", "amp2", "dist"] + (["other"] if maps["other"] is not None else []) \
        + (["nu", "nu_raw", "kappa"] if diffracting else [])
    full = torch.stack([maps[k] for k in names], 1)  # (B, C, KY, KX)
    rows = [[] for _ in reqs]
    if checks:  # host read 2: the Fresnel scales' maxima and the checks, with the fields they name
        fields = torch.stack([r.b.field for r in reqs])
        rows = torch.cat([torch.stack([t.to(torch.float64) for t in checks], 1), fields], 1).tolist()
    out = []
    for j, (r, row, size) in enumerate(zip(reqs, rows, nb.sizes)):
        # the field stage's padded node maps (_padded_node_maps); each map's own view made when first read
        m = _LazyMaps(_BatchedMaps(full, j, tuple(names)), size)
        m.setdefault("other", None)
        if diffracting:
            m["g_max"] = row[0]
        if check:
            field, wavelength, vals = row[-2:], r.b.src.wavelength, row[1:] if diffracting else row
            if diffracting:
                _edge_curvature_warning(vals[0], field, wavelength, stacklevel=2)
                vals = vals[1:]
            fold, any_lit, ratio, x, y = vals[:5]
            if fold:
                _fold_warning(field, wavelength, stacklevel=2)
            if any_lit and ratio > 1.0:
                _nyquist_warning(ratio, (x, y), field, wavelength, r.b.p, stacklevel=2)
        out.append(m)
    return out


def _fine_field(b: _Build, nd: _Nodes, maps: dict, sim: Grid):
    """Interpolate the node maps to the simulation samples of the node span near the lit nodes, form the phase
    and the edges there, crop to the lit part. The DOE's aperture cuts the field (not on a virtual plane, whose
    window may extend beyond the DOE grid). Returns ``(envelope, box)`` (box: half-open ``(iy0, iy1, ix0, ix1)``
    on ``sim``'s lattice) or None when nothing is lit."""
    doe = None if b.cfg.virtual else b.doe
    oversample, wavelength, z_doe = b.cfg.oversample, b.src.wavelength, b.z_doe
    stop_plane, ripple_zones = b.cfg.stop_plane, b.ripple
    p = sim.pitch[0]
    x0, y0 = sim.origin
    gx, gy, h_node, ky, kx = nd.gx, nd.gy, nd.h, nd.ky, nd.kx
    diffracting, dist = "nu" in maps, maps["dist"]
    win = _span_window(nd, sim, doe is not None, "fresnel" if diffracting else "cut")
    if win is None:
        return None
    iy0, iy1, ix0, ix1 = win
    gx0, gy0 = torch.stack([gx[0], gy[0]]).tolist()  # (one host read)
    pos_x = (x0 + torch.arange(ix0, ix1, dtype=torch.float64, device=gx.device) * p - gx0) / h_node
    pos_y = (y0 + torch.arange(iy0, iy1, dtype=torch.float64, device=gx.device) * p - gy0) / h_node
    # interpolate only near the nodes that can be lit (inside the ripple band / the edges): the node span reaches
    # further (the traced margin), and the fine channels are the construction's largest arrays
    keep = (maps["nu_raw"] > -math.sqrt(2.0) * ripple_zones) if diffracting else dist.detach() > -2 * h_node
    near = _near_nodes(keep, pos_y, pos_x)
    if near is None:
        return None
    (ya, yb), (xa, xb) = near
    pos_y, pos_x = pos_y[ya:yb], pos_x[xa:xb]
    iy0, iy1, ix0, ix1 = iy0 + ya, iy0 + yb, ix0 + xa, ix0 + xb
    # amplitude sqrt(amp2): zero where the ray density vanishes (a dead or degenerate node), with a finite
    # (zero) gradient there: sqrt's derivative at 0 is infinite, so the double-where keeps it out of the graph
    amp2 = maps["amp2"]
    lit_amp = amp2 > 0
    amp = torch.where(lit_amp, safe_sqrt(amp2, lit_amp), torch.zeros_like(amp2))
    other = maps["other"]
    edge_chan = ([] if other is None else [other]) + [maps["nu"], maps["kappa"]] if diffracting else []
    nodes = torch.stack([maps["phi_env"], amp] + ([] if diffracting else [dist]) + edge_chan)
    grad = torch.is_grad_enabled() and nodes.requires_grad
    # with autograd the crop is read from the channels' values, then the interpolation's window taken by one op
    # (upsample_nodes_window) and split into channels, the coverage formed on the crop (elementwise: the same values):
    # the backward is the window's own banded products, where the reads of the whole window (the coverage's channel,
    # the crop's two slices) built three zero arrays of it and the interpolation's blocks a graph of slices
    fine, window = upsample_nodes_window(nodes, pos_y.clamp(0, ky - 1), pos_x.clamp(0, kx - 1))
    cov, b, dcov = _fine_coverage(fine, diffracting, other is not None, sim, (iy0, iy1, ix0, ix1), doe, oversample,
                                  ripple_zones)
    if b is None:
        return None
    a0, a1, b0, b1 = b
    ch = window(b, split=True)  # the channels (their gradients taken where they are: no stack)
    if grad and cov is not None:
        cov = _coverage(ch[2], p, diffracting, other is not None, None if dcov is None else dcov[a0:a1, b0:b1])
    elif cov is not None:
        cov = cov[a0:a1, b0:b1]
    edge = (z_doe - stop_plane, ripple_zones, maps["g_max"], p) if diffracting else None
    env = _envelope(ch, cov, 2 * math.pi / (wavelength * 1e-3), edge)
    return env, (iy0 + a0, iy0 + a1, ix0 + b0, ix0 + b1)


def _envelope(fine, cov: torch.Tensor | None, k: float, edge: tuple | None) -> torch.Tensor:
    """The envelope ``a·cov·exp(i k φ)`` (complex128 (ny, nx)) from the fine channels ``fine`` (C, ny, nx), or their
    views of one unbind (a tuple) (0: φ mm, 1: amplitude, with ``edge`` ``(dz, ripple_zones, g_max, pitch)``:
    ``[-2]`` ν and ``[-1]`` the edge's κ/g), times the knife-edge factor (:func:`edge_envelope`) with ``edge``;
    ``k = 2π/λ`` (1/mm)."""
    # the channels as views of one unbind: its backward stacks their gradients into one array, where each indexed
    # read's backward would allocate (and add) a zero array of the whole stack
    ch = fine.unbind(0) if isinstance(fine, torch.Tensor) else fine
    if edge is None:
        return polar(ch[1] if cov is None else ch[1] * cov, k * ch[0])
    dz, ripple_zones, g_max, p = edge
    # the coverage and k·φ taken with the knife edge (in its compiled loop without a graph: issue 47)
    return edge_envelope(ch[1], ch[0], ch[-2], dz, ripple_zones, g_max, p, kappa=ch[-1], scale=(cov, k))


def _span_window(nd: _Nodes, sim: Grid, clamp: bool, step: str = "cut"):
    """The fine window: the simulation samples inside the node span, half-open ``(iy0, iy1, ix0, ix1)`` indices on
    ``sim``'s lattice (pitch mm), clamped to the DOE grid with ``clamp`` (a virtual plane's window is not: it lies
    on the DOE grid's lattice extended); None when empty. Refuses a window too large for memory
    (:func:`check_window_memory` of ``step``: "fresnel" with the knife edge, "cut" without) before any array of its
    size exists."""
    ends = torch.stack([nd.gy[0], nd.gx[0], nd.gy[-1], nd.gx[-1]]).tolist()  # one host read
    return _span_bounds(ends, sim, clamp, nd.gx.device, step)


def _span_bounds(ends, sim: Grid, clamp: bool, device, step: str = "cut"):
    """:func:`_span_window` from the node span's ends ``(gy0, gx0, gy1, gx1)`` mm (host floats)."""
    p = sim.pitch[0]
    (x0, y0), (sy, sx) = sim.origin, sim.shape
    gy0, gx0, gy1, gx1 = ends
    iy0, ix0 = math.ceil((gy0 - y0) / p), math.ceil((gx0 - x0) / p)
    iy1, ix1 = math.floor((gy1 - y0) / p) + 1, math.floor((gx1 - x0) / p) + 1
    if clamp:
        iy0, iy1, ix0, ix1 = max(0, iy0), min(sy, iy1), max(0, ix0), min(sx, ix1)
    if iy1 <= iy0 or ix1 <= ix0:
        return None
    check_window_memory(iy1 - iy0, ix1 - ix0, p, device, step)  # before any array of the window's size
    return iy0, iy1, ix0, ix1


def _fine_coverage(fine: torch.Tensor, diffracting: bool, has_other: bool, sim: Grid, box, doe, oversample: int,
                   ripple_zones):
    """The fine window's amplitude coverage and its lit part. ``fine`` (C, ny, nx): the interpolated channels
    (index 2: the edge distance in mm, the other edges' with ``diffracting`` and ``has_other``; ``fine[-2]``: ν
    with ``diffracting``); ``box``: the window ``(iy0, iy1, ix0, ix1)`` on ``sim``; ``doe``: its aperture (None: a
    virtual plane). Returns ``(cov (ny, nx) float64 or None: 1 everywhere, crop, dcov)``: ``crop`` the half-open
    ``(a0, a1, b0, b1)`` of the lit samples in the window (with ``diffracting`` inside the ripple band), None
    when none is lit; ``dcov`` the DOE aperture's coverage of the window (None: a virtual plane)."""
    p = sim.pitch[0]
    dcov = None if doe is None else doe.coverage(sim.window(*box), oversample, device=fine.device)
    cov = _coverage(fine[2], p, diffracting, has_other, dcov)
    if diffracting:  # the Fresnel factor is 0 beyond the ripple band
        band = (fine[-2].detach() > -math.sqrt(2.0) * ripple_zones).to(torch.float64)
        return cov, _crop_to_lit(band if cov is None else cov * band), dcov
    return cov, _crop_to_lit(cov), dcov


def _coverage(dist: torch.Tensor, p: float, diffracting: bool, has_other: bool, dcov: torch.Tensor | None):
    """The amplitude coverage of :func:`_fine_coverage` (elementwise): the edge distance channel ``dist``'s
    :func:`~raywave.wave.field.edge_coverage` (pitch ``p`` mm; with ``diffracting`` only when ``has_other``) times
    the DOE's aperture coverage ``dcov`` (None: none); None where neither applies."""
    cov = edge_coverage(dist, p) if (has_other or not diffracting) else None
    if dcov is not None:
        cov = dcov if cov is None else cov * dcov
    return cov


@dataclass
class _FieldRequest:
    """The field stage of one construction (:func:`_fine_field`'s arguments: the :class:`_Build`, its
    :class:`_Nodes`, the node maps :data:`_FIELD_MAPS` and the simulation grid ``sim``), yielded by
    :func:`accurate_field_steps` after its :data:`~raywave.hybrid.coherent.tracing.PAUSE`; answered with
    ``(envelope, box)`` or None. :func:`~raywave.hybrid.coherent.tracing.run_batched` answers the pending requests
    that share a plane, DOE and mode with one :func:`_fine_fields` (``run_group``), after every pending trace
    (``deferred``: the constructions still tracing join the batch)."""

    b: _Build
    nd: _Nodes
    maps: dict
    sim: Grid
    deferred: ClassVar[bool] = True

    def run(self):
        """This construction's field stage alone (:func:`_fine_field`; :func:`run_serial`)."""
        return _fine_field(self.b, self.nd, self.maps, self.sim)

    @staticmethod
    def run_group(reqs: list) -> list:
        """The answers of a group of requests (one ``group_key``), in order (:func:`_fine_fields`)."""
        return _fine_fields(reqs)

    def group_key(self) -> tuple:
        """What the requests batched together share: the DOE (its simulation grid), virtual plane, oversampling,
        stop-edge mode (diffracting, other edges) and the knife edge's side, and the device."""
        b, maps = self.b, self.maps
        diffracting = "nu" in maps
        edge = (b.z_doe - b.cfg.stop_plane >= 0) if diffracting else None  # the knife edge's side: one per batch
        return ("field", id(b.doe), bool(b.cfg.virtual), int(b.cfg.oversample), diffracting,
                diffracting and maps.get("other") is not None, edge, self.nd.gx.device)


#: the field stage of a group of constructions (:func:`_fine_fields`) as one batched computation
#: (:func:`_fine_field_batch`): None on an accelerator only (every op a kernel launch; the CPU keeps
#: :func:`_fine_field` per construction, its banded interpolation ~3× cheaper than the dense products); True / False:
#: always / never (tests and benchmarks/ops_breakdown.py ``--accelerator`` force it on the CPU)
BATCHED_FIELD_STAGE = None
#: a batch of :func:`_fine_field_batch` spans at most this many padded samples of the constructions' node-span
#: windows (~100 bytes a sample at the peak) on the CPU; :data:`FIELD_BATCH_SAMPLES_ACCELERATOR` elsewhere
#: (:func:`_field_batch_cap`; the bundled asphere's 10×10×3 map: one batch per field group, ~9 constructions of
#: ~2·10⁶ samples)
FIELD_BATCH_SAMPLES = 2**23
FIELD_BATCH_SAMPLES_ACCELERATOR = 2**27


def _field_batch_cap(device) -> int:
    """Padded samples a batch of :func:`_fine_field_batch` may span on ``device``: :data:`FIELD_BATCH_SAMPLES` on the
    CPU, else :data:`FIELD_BATCH_SAMPLES_ACCELERATOR`, on CUDA at most a 256th of the device's memory in samples (a
    batch's arrays take ~100 bytes a sample at its peak: at most ~40 % of the memory)."""
    dev = torch.device(device)
    if not devices.accelerator(dev):
        return FIELD_BATCH_SAMPLES
    if dev.type != "cuda":
        return FIELD_BATCH_SAMPLES_ACCELERATOR
    return max(FIELD_BATCH_SAMPLES, min(FIELD_BATCH_SAMPLES_ACCELERATOR,
                                        torch.cuda.get_device_properties(dev).total_memory // 256))


def _batched_field_stage(device) -> bool:
    """Whether :func:`_fine_fields` batches on ``device`` (:data:`BATCHED_FIELD_STAGE`)."""
    if BATCHED_FIELD_STAGE is not None:
        return bool(BATCHED_FIELD_STAGE)
    return devices.accelerator(device)


def _fine_fields(reqs: list) -> list:
    """:func:`_fine_field` of every :class:`_FieldRequest` of ``reqs`` (one plane, DOE and mode: ``group_key``):
    ``[(envelope, box) or None]``. On an accelerator (:data:`BATCHED_FIELD_STAGE`) in padded batches
    (:func:`_fine_field_batch`: a few dozen kernels per batch instead of ~70 per construction), each result equal to
    its own call's to rounding (the dense products' sums); else one call each."""
    r0 = reqs[0]
    dev = r0.nd.gx.device
    if len(reqs) < 2 or not _batched_field_stage(dev):
        return [r.run() for r in reqs]
    doe = None if r0.b.cfg.virtual else r0.b.doe
    if doe is not None and (type(doe).coverage is not DOE.coverage or doe.aperture not in ("square", "circle")):
        return [r.run() for r in reqs]  # an aperture of its own: the DOE's coverage per window
    ends = _node_span_ends([r.nd for r in reqs])
    step = "fresnel" if "nu" in r0.maps else "cut"
    wins = [_span_bounds(e, r0.sim, doe is not None, dev, step) for e in ends]
    out: list = [None] * len(reqs)
    for chunk in _field_chunks(wins, _field_batch_cap(dev)):
        for j, res in zip(chunk, _fine_field_batch([reqs[j] for j in chunk], [wins[j] for j in chunk],
                                                   [ends[j] for j in chunk], doe)):
            out[j] = res
    return out


def _field_chunks(wins: list, cap: int) -> list:
    """The windows ``wins`` (``(iy0, iy1, ix0, ix1)`` or None: nothing to build) in consecutive batches whose
    padded size (count × the largest height × the largest width) stays within ``cap`` samples (a batch holds at
    least one): ``[[index into wins]]``."""
    chunks, cur, ny, nx = [], [], 0, 0
    for k, w in enumerate(wins):
        if w is None:
            continue
        ny2, nx2 = max(ny, w[1] - w[0]), max(nx, w[3] - w[2])
        if cur and (len(cur) + 1) * ny2 * nx2 > cap:
            chunks.append(cur)
            cur, ny2, nx2 = [], w[1] - w[0], w[3] - w[2]
        cur.append(k)
        ny, nx = ny2, nx2
    return chunks + ([cur] if cur else [])


def _node_span_ends(nds: list) -> list:
    """``[(gy0, gx0, gy1, gx1)]`` mm: the first and last node of every :class:`_Nodes` of ``nds`` (one host read;
    the node coordinates of all grids gathered at once)."""
    dev = nds[0].gx.device
    ends = []
    for axis in ("gy", "gx"):
        sizes = [getattr(nd, axis).numel() for nd in nds]
        last = list(itertools.accumulate(sizes))
        first = [a - n for a, n in zip(last, sizes)]
        ends.append(torch.cat([getattr(nd, axis) for nd in nds])[torch.tensor(first + [a - 1 for a in last],
                                                                              device=dev)])
    b = len(nds)
    return torch.stack([ends[0][:b], ends[1][:b], ends[0][b:], ends[1][b:]], 1).tolist()


def _first_last_rows(mask: torch.Tensor) -> list:
    """:func:`~raywave.hybrid.coherent.geometry._first_last` of every row of the bool ``mask`` (B, n): ``[any,
    first, n − (last + 1)]`` (B,) int64 each (valid where ``any``; the caller, who reads them, takes ``last + 1``
    on the host: one op less)."""
    m = mask.to(torch.int64)
    return [m.amax(-1), torch.argmax(m, -1), torch.argmax(m.flip(-1), -1)]


def _lattice_positions_host(start: list, n: int, origin: float, p: float, node0: list, h: list) -> np.ndarray:
    """``(B, n)`` float64 on the host: node-unit positions ``(origin + (start[b] + i)·p − node0[b]) / h[b]`` of the
    lattice samples ``start[b] + i`` (pitch ``p`` mm, origin mm) on construction b's node grid (first node
    ``node0[b]`` mm, spacing ``h[b]`` mm): :func:`_fine_field`'s arithmetic in its order (IEEE float64, each
    operation rounded once: the same values as on a device)."""
    idx = np.asarray(start, dtype=np.float64)[:, None] + np.arange(n, dtype=np.float64)
    return (origin + idx * p - np.asarray(node0, dtype=np.float64)[:, None]) / np.asarray(h, dtype=np.float64)[:, None]


def _first_last_host(pos: np.ndarray, n: list, lo: np.ndarray, hi: np.ndarray) -> list:
    """:func:`_first_last_rows` of the positions ``pos`` (B, N) within 3 node spacings of ``[lo, hi]`` (B,) and among
    each row's own ``n`` samples, on the host: ``[any, first, last + 1]`` (B,) int64 each."""
    m = (pos >= (lo - 3)[:, None]) & (pos <= (hi + 3)[:, None]) & (np.arange(pos.shape[1]) < np.asarray(n)[:, None])
    return [m.any(1).astype(np.int64), m.argmax(1), m.shape[1] - m[:, ::-1].argmax(1)]


def _inside_host(ny: list, nx: list, dev) -> torch.Tensor:
    """``(B, max ny, max nx)`` bool: each window's own ``ny[b] × nx[b]`` samples (two host masks sent and combined:
    three ops)."""
    iy = np.arange(max(ny)) < np.asarray(ny)[:, None]
    ix = np.arange(max(nx)) < np.asarray(nx)[:, None]
    return torch.from_numpy(iy[:, :, None]).to(dev) & torch.from_numpy(ix[:, None, :]).to(dev)


def _beyond_host(ny: list, nx: list, dev) -> torch.Tensor:
    """``(B, max ny, max nx)`` bool: the samples beyond each window's own ``ny[b] × nx[b]`` (two host masks sent and
    combined: three ops)."""
    by = np.arange(max(ny)) >= np.asarray(ny)[:, None]
    bx = np.arange(max(nx)) >= np.asarray(nx)[:, None]
    return torch.from_numpy(by[:, :, None]).to(dev) | torch.from_numpy(bx[:, None, :]).to(dev)


def _doe_coverage_batch(doe, oversample: int, starts: tuple, shape: tuple, dev):
    """:meth:`raywave.doe.DOE.coverage` of B windows at once: ``(B, ny, nx)`` float64 for the windows whose sample
    (0, 0) lies at ``starts`` = (iy0 (B,), ix0 (B,)) on the DOE's simulation grid (``shape`` (ny, nx): their padded
    size; samples beyond a window's own size are computed too), the same values; None for a square aperture (1)."""
    if doe.aperture == "square":
        return None
    f64 = dict(dtype=torch.float64, device=dev)
    x0, y0 = doe.sim_origin(oversample)
    p = doe.pitch / oversample
    x = x0 + (torch.tensor(starts[1], **f64)[:, None] + torch.arange(shape[1], **f64)) * p
    y = y0 + (torch.tensor(starts[0], **f64)[:, None] + torch.arange(shape[0], **f64)) * p
    r = torch.sqrt(x[:, None, :] ** 2 + y[:, :, None] ** 2)
    radius = 0.5 * min(doe.size)
    return (0.5 + (radius - r) / p).clamp(0.0, 1.0)


@dataclass(frozen=True)
class _BatchedMaps:
    """Where a construction's node maps lie in the padded stack of its node-map batch (:func:`_batch_answers`):
    ``full`` (B, C, KY, KX) (beyond a grid its nearest node's values), ``row`` its index, ``names`` the channels'."""

    full: torch.Tensor
    row: int
    names: tuple


_PENDING = object()  # a _LazyMaps entry not made yet


class _LazyMaps(dict):
    """A construction's node maps (:data:`_FIELD_MAPS`) from a node-map batch (:func:`_batch_answers`): ``"batch"``
    the :class:`_BatchedMaps` and every channel of its ``names`` a view of the padded stack's row cropped to the
    construction's own ``size`` ``(ky, kx)`` (``nu_raw`` detached), the views made on the first read of any of them
    (issue 43: four ops a construction; an accelerator's batched field stage reads the padded stack itself,
    :func:`_from_node_batch`, and never these). Read through ``[]``, :meth:`get`, :meth:`pop`, :meth:`items` or
    :meth:`values` (a plain ``dict(...)`` copy would see placeholders)."""

    def __init__(self, batch: _BatchedMaps, size: tuple):
        super().__init__({n: _PENDING for n in batch.names}, batch=batch)
        self._batch, self._size = batch, size

    def _fill(self) -> None:
        batch, (ky, kx) = self._batch, self._size
        if batch is None:
            return
        for n, v in zip(batch.names, batch.full[batch.row, :, :ky, :kx].unbind(0)):
            if dict.get(self, n) is _PENDING:
                dict.__setitem__(self, n, v.detach() if n == "nu_raw" else v)
        self._batch = None

    def __getitem__(self, k):
        v = dict.__getitem__(self, k)
        if v is _PENDING:
            self._fill()
            v = dict.__getitem__(self, k)
        return v

    def get(self, k, default=None):
        return self[k] if k in self else default

    def pop(self, k, *default):
        if k in self:
            v = self[k]
            del self[k]
            return v
        return dict.pop(self, k, *default)

    def items(self):
        self._fill()
        return dict.items(self)

    def values(self):
        self._fill()
        return dict.values(self)


def _padded_node_maps(reqs: list, diffracting: bool, has_other: bool):
    """The constructions' node maps zero-padded to common ``(KY, KX)``: ``(channels (C, B, KY, KX) in
    :func:`_fine_field`'s order (φ, amplitude, [distance], [other edges, ν, κ/g]), the keep source (B, KY, KX)
    detached (``nu_raw`` or the distance), valid nodes (B, KY, KX) bool)``. Differentiable."""
    ks = [(r.nd.ky, r.nd.kx) for r in reqs]
    ky_max, kx_max = max(k[0] for k in ks), max(k[1] for k in ks)
    names = ["phi_env", "amp2"] + ([] if diffracting else ["dist"]) + (["other"] if has_other else []) \
        + (["nu", "kappa"] if diffracting else [])
    keep = "nu_raw" if diffracting else "dist"
    dev = reqs[0].nd.gx.device
    valid = _inside_host([k[0] for k in ks], [k[1] for k in ks], dev)
    v = _from_node_batch(reqs, names + [keep], (ky_max, kx_max), valid)
    if v is None:  # each construction's maps stacked and zero-padded
        v = torch.stack([torch.nn.functional.pad(torch.stack([r.maps[n] for n in names] + [r.maps[keep].detach()]),
                                                 (0, kx_max - kx, 0, ky_max - ky)) for r, (ky, kx) in zip(reqs, ks)])
    ch = v.unbind(1)
    amp2 = ch[1]
    lit_amp = amp2 > 0  # (the zero padding: 0)
    amp = torch.where(lit_amp, safe_sqrt(amp2, lit_amp), torch.zeros_like(amp2))
    src = ch[-1]
    return torch.stack([ch[0], amp, *ch[2:-1]]), src.detach() if src.requires_grad else src, valid


def _from_node_batch(reqs: list, names: list, shape: tuple, valid: torch.Tensor):
    """The channels ``names`` of the constructions ``reqs`` taken from the padded stack of
    their node-map batch when they all come from one (:class:`_BatchedMaps`, an accelerator's): ``(B, C, KY, KX)``
    (``shape`` = ``(KY, KX)``), zero beyond each grid (``valid`` (B, KY, KX) its own nodes): the values of each
    construction's maps stacked and zero-padded, by a few ops for the batch instead of three a construction. None
    where they do not."""
    marks = [r.maps.get("batch") for r in reqs]
    m0 = marks[0]
    if m0 is None or any(m is None or m.full is not m0.full for m in marks):
        return None
    full = m0.full
    ky, kx = shape
    chan = torch.tensor([m0.names.index(n) for n in names], device=full.device)
    rows = [m.row for m in marks]
    v = full if rows == list(range(full.shape[0])) else full[torch.tensor(rows, device=full.device)]
    v = v.index_select(1, chan)[:, :, :ky, :kx]  # (the last channel is read detached: _padded_node_maps)
    return torch.where(valid[:, None], v, torch.zeros((), dtype=v.dtype, device=v.device))


def _fine_field_batch(reqs: list, wins: list, ends: list, doe) -> list:
    """:func:`_fine_field` of B constructions (:class:`_FieldRequest`, one ``group_key``) as batched tensor ops:
    their node maps padded to a common node grid (:func:`_padded_node_maps`), their fine windows to a common size,
    the cubic interpolation as two batched products (:func:`~raywave.wave.field.cubic_matrices`), the coverage, the
    ripple band, the crop to the lit samples (three host reads for the batch: the near-node ranges, the lit crops,
    and before, in :func:`_fine_fields`, the node spans ``wins``/``ends``) and the envelope with its knife-edge
    factor (:func:`~raywave.hybrid.coherent.stop_edge.edge_envelope`, each row with its window's constants).
    Returns ``[(envelope (ny, nx) complex128, box) or None]``, each a view of the batch's envelope."""
    r0 = reqs[0]
    sim, dev = r0.sim, r0.nd.gx.device
    p = sim.pitch[0]
    x0, y0 = sim.origin
    diffracting = "nu" in r0.maps
    has_other = diffracting and r0.maps["other"] is not None
    f64 = dict(dtype=torch.float64, device=dev)
    hs = [r.nd.h for r in reqs]
    rz = [r.b.ripple for r in reqs]
    vals, keep_src, valid = _padded_node_maps(reqs, diffracting, has_other)
    # the near-node ranges (_near_nodes) of every construction's span window: one host read. The host's values
    # (positions, masks, indices, per-construction constants) are built on the host and sent as one tensor each
    # (issue 43: a few ops each instead of a dozen; the positions the same float64 arithmetic, the same bits)
    thr = torch.tensor([[[-math.sqrt(2.0) * z if diffracting else -2 * h]] for z, h in zip(rz, hs)], **f64)
    keep = (keep_src > thr) & valid
    ny0 = [w[1] - w[0] for w in wins]
    nx0 = [w[3] - w[2] for w in wins]
    pos_y = _lattice_positions_host([w[0] for w in wins], max(ny0), y0, p, [e[0] for e in ends], hs)
    pos_x = _lattice_positions_host([w[2] for w in wins], max(nx0), x0, p, [e[1] for e in ends], hs)
    rows, cols = _first_last_rows(keep.any(2)), _first_last_rows(keep.any(1))
    kr = np.array(torch.stack([rows[0], rows[1], rows[2], cols[1], cols[2]], 1).tolist(), dtype=np.int64)
    kr[:, 2], kr[:, 4] = keep.shape[1] - kr[:, 2], keep.shape[2] - kr[:, 4]  # last + 1
    near = np.stack([kr[:, 0], *_first_last_host(pos_y, ny0, kr[:, 1], kr[:, 2] - 1),
                     *_first_last_host(pos_x, nx0, kr[:, 3], kr[:, 4] - 1)], 1).tolist()
    sel = [k for k, (kept, y_any, _, _, x_any, _, _) in enumerate(near) if kept and y_any and x_any]
    out: list = [None] * len(reqs)
    if not sel:
        return out
    if len(sel) < len(reqs):
        idx = torch.tensor(sel, device=dev)
        vals, valid = vals[:, idx], valid[idx]
    iy0 = [wins[k][0] + near[k][2] for k in sel]
    ix0 = [wins[k][2] + near[k][5] for k in sel]
    ny = [near[k][3] - near[k][2] for k in sel]
    nx = [near[k][6] - near[k][5] for k in sel]
    hs = [hs[k] for k in sel]
    py = _lattice_positions_host(iy0, max(ny), y0, p, [ends[k][0] for k in sel], hs)
    px = _lattice_positions_host(ix0, max(nx), x0, p, [ends[k][1] for k in sel], hs)
    # both axes' matrices in one call: (B, ny + nx, K), each position with its own axis's node count
    n_nodes = np.concatenate([np.repeat([[float(reqs[k].nd.ky)] for k in sel], max(ny), 1),
                              np.repeat([[float(reqs[k].nd.kx)] for k in sel], max(nx), 1)], 1)
    pos = np.minimum(np.maximum(np.concatenate([py, px], 1), 0.0), n_nodes - 1)
    m = cubic_matrices(torch.from_numpy(pos).to(dev), torch.from_numpy(n_nodes).to(dev), max(vals.shape[-2:]))
    my, mx = m[:, :max(ny), :vals.shape[-2]], m[:, max(ny):, :vals.shape[-1]]
    fine = my @ vals @ mx.mT  # (C, B, ny, nx)
    # the coverage, the ripple band and the lit crop (_fine_coverage, _crop_to_lit): one host read
    cov = None
    if not diffracting or has_other:
        cov = edge_coverage(fine[2], p)
    if doe is not None:
        dcov = _doe_coverage_batch(doe, r0.b.cfg.oversample, (iy0, ix0), fine.shape[-2:], dev)
        if dcov is not None:
            cov = dcov if cov is None else cov * dcov
    beyond = _beyond_host(ny, nx, dev)  # the samples beyond each window's own
    if diffracting:
        band_thr = torch.tensor([[[-math.sqrt(2.0) * rz[k]]] for k in sel], **f64)
        band = (fine[-2].detach() > band_thr).to(torch.float64)
        weight = band if cov is None else cov.detach() * band
    else:
        weight = cov.detach()
    weight = weight.masked_fill(beyond, 0.0)
    lit_r, lit_c = _first_last_rows(weight.amax(2) > 0), _first_last_rows(weight.amax(1) > 0)
    crops = [[a, b, weight.shape[1] - c, d, weight.shape[2] - e] for a, b, c, d, e in
             torch.stack([lit_r[0], lit_r[1], lit_r[2], lit_c[1], lit_c[2]], 1).tolist()]  # (last + 1 on the host)
    lit = [j for j, c in enumerate(crops) if c[0]]
    if not lit:
        return out
    # the lit crops gathered into one padded batch (B', hy, hx); samples beyond a crop: amplitude 0, outside the band
    hy = [crops[j][2] - crops[j][1] for j in lit]
    hx = [crops[j][4] - crops[j][3] for j in lit]
    bi = torch.tensor([[[j]] for j in lit], device=dev)
    ri = np.minimum(np.array([crops[j][1] for j in lit])[:, None] + np.arange(max(hy)), fine.shape[-2] - 1)
    ci = np.minimum(np.array([crops[j][3] for j in lit])[:, None] + np.arange(max(hx)), fine.shape[-1] - 1)
    ri, ci = torch.from_numpy(ri[:, :, None]).to(dev), torch.from_numpy(ci[:, None, :]).to(dev)
    fine = fine[:, bi, ri, ci]
    outer = _beyond_host(hy, hx, dev)
    ch = fine.unbind(0)
    amp = ch[1] if cov is None else ch[1] * cov[bi, ri, ci]
    amp = amp.masked_fill(outer, 0.0)
    ks = torch.tensor([[[2 * math.pi / (reqs[sel[j]].b.src.wavelength * 1e-3)]] for j in lit], **f64)
    angle = ks * ch[0]
    if not diffracting:
        env = polar(amp, angle)
    else:
        bs = [reqs[sel[j]].b for j in lit]
        rzr = torch.tensor([[rz[sel[j]]] for j in lit for _ in range(max(hy))], **f64)
        gr = torch.tensor([[reqs[sel[j]].maps["g_max"]] for j in lit for _ in range(max(hy))], **f64)
        nu = ch[-2].masked_fill(outer, -math.inf)
        shape2 = (-1, max(hx))
        env = edge_envelope(amp.reshape(shape2), angle.reshape(shape2), nu.reshape(shape2),
                            bs[0].z_doe - bs[0].cfg.stop_plane, rzr, gr, p,
                            kappa=ch[-1].reshape(shape2)).reshape(amp.shape)
    # each construction's envelope a view of the batch's: without autograd its row of the batch (EnvelopeRow: one
    # strided view when first read, none where the propagation and the darkness test read the batch; an as_strided
    # view's backward would allocate the whole batch per view)
    strided = not env.requires_grad
    rows = env.unbind(0) if not strided else [None] * len(lit)
    for t, (e, j) in enumerate(zip(rows, lit)):
        _, a0, a1, b0, b1 = crops[j]
        e = EnvelopeRow(env, t, (a1 - a0, b1 - b0)) if strided else e[:a1 - a0, :b1 - b0]
        out[sel[j]] = e, (iy0[j] + a0, iy0[j] + a1, ix0[j] + b0, ix0[j] + b1)
    return out
