"""Issue 43: the accurate construction's set-up and ray stage with fewer dispatched ops per construction, each piece
giving the values, bit for bit, of what it replaces:

* the node grids from host numbers (:class:`raywave.hybrid.coherent.accurate._Nodes`): their targets made for an
  inversion group at once (``concat_targets``), the coarse start's grid as a node grid of its own;
* the rows of a batched trace split when first read (:func:`~raywave.hybrid.coherent.tracing._split_bundle`) and
  gathered back at once (:func:`~raywave.hybrid.coherent.tracing.cat_rows`, ``cat_points``);
* the Newton rounds' sources' part taken once per group (:func:`~raywave.hybrid.coherent.tracing._part_rows`);
* the 2×2 solve from unbound views (:func:`~raywave.hybrid.coherent.tracing._solve2`);
* host reads where the values are host numbers already (the rim images' farthest z).
"""

import dataclasses
import math

import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.hybrid.coherent import accurate as accurate_mod
from raywave.hybrid.coherent import tracing as tracing_mod
from raywave.lens.build import bundled_lens_path
from raywave.lens.sources import _source_part, entrance_plane_z
from raywave.rays.bundle import RayBundle


def _old_axes(xc: float, yc: float, h: float, kx: int, ky: int):
    """The node grid as :func:`_node_layout` made it before (tensor arithmetic)."""
    gx = xc + (torch.arange(kx, dtype=torch.float64) - (kx - 1) / 2) * h
    gy = yc + (torch.arange(ky, dtype=torch.float64) - (ky - 1) / 2) * h
    tx, ty = torch.meshgrid(gx, gy, indexing="xy")
    return gx, gy, tx, ty, torch.stack([tx, ty], -1).reshape(-1, 2)


@pytest.mark.parametrize("xc,yc,h,kx,ky", [(0.0, 0.0, 0.01, 65, 65), (-1.2345678901, 3.14159265358979, 0.0173, 81, 67),
                                           (2.5e-3, -7.75, 1.0 / 3.0, 17, 23)])
def test_node_grid_from_host_numbers_equals_the_tensor_grid(xc, yc, h, kx, ky):
    """Every coordinate of a node grid (axes, maps, targets), made alone or with other grids' at once, and the coarse
    start's grid of every ``COARSE_STRIDE``-th node, bit for bit as the tensor arithmetic made them."""
    nd = accurate_mod._Nodes(xc, yc, (kx - 1) / 2, (ky - 1) / 2, h, kx, ky, torch.device("cpu"))
    gx, gy, tx, ty, targets = _old_axes(xc, yc, h, kx, ky)
    for new, old in ((nd.gx, gx), (nd.gy, gy), (nd.tx, tx), (nd.ty, ty), (nd.targets, targets)):
        assert torch.equal(new, old)
    assert nd.ends() == (float(gy[0]), float(gx[0]), float(gy[-1]), float(gx[-1]))
    other = accurate_mod._Nodes(yc, xc, (ky - 1) / 2, (kx - 1) / 2, 2 * h, ky, kx, torch.device("cpu"))
    fresh = [dataclasses.replace(nd), other]
    whole = accurate_mod._Nodes.concat_targets(fresh)
    assert torch.equal(whole, torch.cat([targets, _old_axes(yc, xc, 2 * h, ky, kx)[4]]))
    assert torch.equal(fresh[0].targets, targets) and torch.equal(fresh[0].gx, gx) and torch.equal(fresh[0].gy, gy)
    # the coarse start's grid: nd.gx[0] + arange(kxc)·(s·h) before
    s = accurate_mod.COARSE_STRIDE
    kxc, kyc = -(-(kx - 1) // s) + 1, -(-(ky - 1) // s) + 1
    gy0, gx0, _, _ = nd.ends()
    coarse = accurate_mod._Nodes(gx0, gy0, 0.0, 0.0, s * h, kxc, kyc, torch.device("cpu"))
    gxc = gx[0] + torch.arange(kxc, dtype=torch.float64) * (s * h)
    gyc = gy[0] + torch.arange(kyc, dtype=torch.float64) * (s * h)
    cx, cy = torch.meshgrid(gxc, gyc, indexing="xy")
    assert torch.equal(coarse.targets, torch.stack([cx, cy], -1).reshape(-1, 2))


def test_host_extreme_is_the_tensor_min_and_max():
    """The rim images' farthest z read on the host: the tensor's min / max, NaN where one is NaN."""
    for v in ([3.0, -1.5, 2.25], [0.5], [1.0, math.nan, -2.0]):
        t = torch.tensor(v, dtype=torch.float64)
        for smallest in (True, False):
            got = accurate_mod._host_extreme(v, smallest)
            ref = float(t.min() if smallest else t.max())
            assert (math.isnan(got) and math.isnan(ref)) or got == ref


def _batched_bundle(sizes, n_max, gen):
    g = len(sizes)
    return RayBundle(torch.rand(g, 1, n_max, 3, generator=gen, dtype=torch.float64),
                     torch.rand(g, 1, n_max, 3, generator=gen, dtype=torch.float64),
                     torch.rand(g, 1, 1, generator=gen, dtype=torch.float64),
                     torch.rand(g, 1, n_max, generator=gen) > 0.3,
                     torch.rand(g, 1, n_max, generator=gen, dtype=torch.float64))


def test_lazy_rows_and_their_gathered_concatenation_equal_the_slices():
    """The rows of a batched bundle, split when first read, are the bundle's slices; :func:`cat_rows` of them (none,
    some or all split already, in order or not, mixed with an ordinary bundle) is their concatenation."""
    gen = torch.Generator().manual_seed(3)
    sizes = [5, 2, 7, 1]
    b = _batched_bundle(sizes, 7, gen)
    rows = tracing_mod._split_bundle(b, sizes)
    for g, (row, k) in enumerate(zip(rows, sizes)):
        assert isinstance(row, RayBundle) and row.shape == (1, 1, k)
        for name in ("o", "d", "valid", "opl"):
            assert torch.equal(getattr(row, name), getattr(b, name)[g:g + 1, :, :k])
        assert torch.equal(row.wavelength, b.wavelength[g:g + 1])
    moved = rows[1].replace(o=rows[1].o + 1.0)  # an ordinary bundle from a row's fields
    assert torch.equal(moved.d, rows[1].d) and torch.equal(moved.o, rows[1].o + 1.0)
    for name in ("o", "d", "valid", "opl"):
        fresh = tracing_mod._split_bundle(b, sizes)
        ref = torch.cat([getattr(r, name) for r in rows], 2)
        assert torch.equal(tracing_mod.cat_rows(fresh, name), ref)  # nothing split: one gather
        getattr(fresh[2], name)  # one row split
        order = [fresh[3], fresh[0], moved, fresh[2], fresh[1]]
        ref = torch.cat([getattr(r, name) for r in order], 2)
        assert torch.equal(tracing_mod.cat_rows(order, name), ref)
        assert torch.equal(tracing_mod.cat_rows(order, name, flat=True), ref[0, 0])


def test_gathered_record_points_equal_their_concatenation():
    """:func:`cat_points` of a batched trace's row records is the concatenation of each row's points."""
    gen = torch.Generator().manual_seed(4)
    sizes = [3, 6, 4]
    pts = [tuple(torch.rand(3, 1, 6, generator=gen, dtype=torch.float64) for _ in range(3)) for _ in range(2)]
    rec = type("Rec", (), {"points": pts, "valid": [torch.rand(3, 1, 6, generator=gen) > 0.5] * 2})()
    shared = tracing_mod._SplitRecord(rec, sizes)
    recs = [tracing_mod._RowRecord(shared, g) for g in range(3)]
    for k in (0, 1):
        for c in (0, 1, 2):
            ref = torch.cat([pts[k][c][g:g + 1, :, :n] for g, n in enumerate(sizes)], 2)
            assert torch.equal(tracing_mod.cat_points(recs, k, c), ref)
    recs[1].points[1]  # a surface split already
    assert torch.equal(tracing_mod.cat_points(recs, 1, 0, flat=True),
                       torch.cat([pts[1][0][g, 0, :n] for g, n in enumerate(sizes)]))


def test_solve2_from_views_equals_the_indexed_solve():
    """The 2×2 solve from unbound views: the values of the indexed formulas, singular systems 0."""
    gen = torch.Generator().manual_seed(5)
    j = torch.randn(50, 2, 2, generator=gen, dtype=torch.float64)
    j[3] = 0.0
    r = torch.randn(50, 2, generator=gen, dtype=torch.float64)
    det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
    ok = det.abs() > 1e-300
    det = torch.where(ok, det, torch.ones_like(det))
    s0 = (j[:, 1, 1] * r[:, 0] - j[:, 0, 1] * r[:, 1]) / det
    s1 = (-j[:, 1, 0] * r[:, 0] + j[:, 0, 0] * r[:, 1]) / det
    ref = torch.where(ok[:, None], torch.stack([s0, s1], -1), torch.zeros_like(r))
    got, got_ok = tracing_mod._solve2(j, r)
    assert torch.equal(got, ref) and torch.equal(got_ok, ok)
    got_t, _ = tracing_mod._solve2(j.transpose(1, 2).contiguous().transpose(1, 2), r)  # a strided Jacobian
    assert torch.equal(got_t, ref)


def test_newton_rows_with_the_groups_source_part_equal_their_own():
    """The Newton rounds' rows traced with their sources' part taken once for the group and gathered
    (:func:`_part_rows`) land exactly where the rows with their own part land."""
    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    lens, z = hl.optics, hl.doe_z()
    ep_z = entrance_plane_z(lens)
    gen = torch.Generator().manual_seed(2)
    fields = torch.tensor([[0.0, 0.0], [0.0, 7.0], [3.0, -5.0]], dtype=torch.float64)
    wls = torch.tensor([0.47, 0.55, 0.66], dtype=torch.float64)
    rows = torch.randint(0, 3, (90,), generator=gen)
    uv = 0.3 * (torch.rand(90, 2, generator=gen, dtype=torch.float64) - 0.5)
    aim = tracing_mod._Aim(lens, fields[0], wls[:1], None, z, lens.field_type, 1e-6, ep_z)
    ref = tracing_mod._trace_rows(aim, uv, fields[rows], wls[rows])
    part = _source_part(lens, fields, lens.field_type, wls.reshape(-1, 1, 1), ep_z=ep_z)
    got = tracing_mod._trace_rows(aim, uv, None, None, part=tracing_mod._part_rows(part, rows))
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
