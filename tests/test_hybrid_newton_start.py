"""The accurate construction's cheaper ray aiming and the exit-pupil edge's batched diagnostics (issues 17 and 19:
the cost of the default stop edge). Each is a change of the computation's path, not of its result:

* the nodes' Newton start interpolated from a coarse solve, and chord steps with that start's Jacobian
  (:func:`raywave.hybrid.coherent.accurate._coarse_start`): the same fields to the rounding of the optical path,
  with far fewer rays traced;
* the stop rim's images of many sources from one trace (:func:`stop_rim_images_many`);
* the Fresnel integrals split over threads (:func:`raywave.hybrid.coherent.stop_edge._fresnel_threads`).
"""

import warnings

import numpy as np
import pytest
import torch

from raywave.assembly.build import load_hybrid
from raywave.hybrid import coherent
from raywave.hybrid.coherent import accurate as accurate_mod
from raywave.hybrid.coherent import tracing as tracing_mod
from raywave.lens.build import bundled_lens_path


def _fields(hl, fields, wl):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            return [fd for row in hl.doe_fields(fields, wl) for fd in row]


def _counting(monkeypatch) -> list:
    """Count the rays of every batched trace into the list returned (append a new list to start a new count)."""
    counts = [[]]
    run = tracing_mod._trace_group

    def counted(reqs):
        counts[-1].append(sum(r.uv.shape[0] for r in reqs))
        return run(reqs)

    rows = tracing_mod._trace_rows  # the Newton rounds' traces (one bundle of single-ray rows)

    def counted_rows(aim, uv, *args, **kwargs):
        counts[-1].append(uv.shape[0])
        return rows(aim, uv, *args, **kwargs)

    monkeypatch.setattr(tracing_mod, "_trace_group", counted)
    monkeypatch.setattr(tracing_mod, "_trace_rows", counted_rows)
    return counts


@pytest.mark.parametrize("name,stop_edge,fields", [
    ("cooke_triplet", "doe", [(0.0, 0.0), (0.0, 14.0)]),
    ("hybrid_asphere", None, [(0.0, 10.0)]),  # the default: the exit-pupil edge (Fresnel step)
])
def test_coarse_start_changes_the_path_not_the_field(monkeypatch, name, stop_edge, fields):
    """Fields with the coarse start and chord steps equal those of the chief ray's linear start and Newton steps to
    ~1e-9 of the peak amplitude (the rounding of optical paths of ~100 mm: 1e-14 mm is 1e-10 rad; tightening the
    Newton tolerance of the old path moves them as much), with under 60 % of the rays traced."""
    kw = {} if stop_edge is None else {"stop_edge": stop_edge}
    hl = load_hybrid(bundled_lens_path(name), **kw)
    wl = 0.55
    counts = _counting(monkeypatch)
    new = _fields(hl, fields, wl)
    monkeypatch.setattr(accurate_mod, "COARSE_STRIDE", 10**6)  # every grid is "too small": the old path
    counts.append([])
    old = _fields(hl, fields, wl)
    assert sum(counts[0]) < 0.6 * sum(counts[1])
    for a, b in zip(new, old):
        assert a.box == b.box
        peak = float(b.envelope.abs().max())
        assert float((a.envelope - b.envelope).abs().max()) <= 1e-8 * peak


def test_newton_takes_the_linear_start_where_the_given_start_is_missing():
    """Nodes whose start (or Jacobian) is NaN take the chief ray's linear start and Newton steps, the others chord
    steps from theirs; every node converges to the same landing point."""
    from raywave.hybrid.coherent.accurate import entrance_pupil
    from raywave.hybrid.coherent.record import _NEWTON_TOL

    hl = load_hybrid(bundled_lens_path("hybrid_asphere"), stop_edge="doe")
    lens, z = hl.optics, hl.doe_z()
    ft = lens.field_type
    f = torch.tensor([0.0, 5.0], dtype=torch.float64)
    wl = torch.tensor([0.55], dtype=torch.float64)
    ep_z, r_ep = entrance_pupil(lens)
    h = 1e-6 * r_ep
    g = torch.linspace(-0.3, 0.3, 7, dtype=torch.float64)
    with torch.no_grad():
        cd = coherent.chief_rays(lens, f[None], wl, None, z, hl.sensor_z())
        xc = cd[0].o[0, 0, :2]
        targets = torch.stack(torch.meshgrid(xc[0] + g, xc[1] + g, indexing="xy"), -1).reshape(-1, 2)
        uv_c = cd[2][0, 0].reshape(1, 2)
        x_c, _, jac_c = coherent.run_serial(tracing_mod._landing_and_jacobian(lens, uv_c, f, wl, None, z, ft, h,
                                                                              ep_z))
        aim = tracing_mod._Aim(lens, f, wl, None, z, ft, h, ep_z)
        ref_uv, ref_conv, ref_jac, _ = coherent.run_serial(tracing_mod._invert_to_nodes(
            aim, targets, (uv_c, x_c, jac_c), 0.25 * r_ep))
        uv0 = ref_uv + 1e-7  # a good start everywhere but a few nodes
        uv0[::3] = float("nan")
        jac0 = ref_jac * (1 + 1e-4)
        jac0[1::5] = float("nan")
        uv, conv, _, x = coherent.run_serial(tracing_mod._invert_to_nodes(
            aim, targets, (uv_c, x_c, jac_c), 0.25 * r_ep, (uv0, jac0)))
    assert bool(ref_conv.all()) and bool(conv.all())
    assert float((x - targets).abs().max()) <= _NEWTON_TOL
    assert float((uv - ref_uv).abs().max()) <= 1e-9


def _aim_case(field_deg: float, wl_um: float) -> tuple:
    """The bundled asphere's node aiming for one source (0, ``field_deg``) at ``wl_um``: ``(aim, chief, r_ep,
    chief ray's landing point (2,) as host numbers)``, as a construction sets it up (no autograd)."""
    from raywave.hybrid.coherent.accurate import entrance_pupil

    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    lens, z = hl.optics, hl.doe_z()
    f = torch.tensor([0.0, field_deg], dtype=torch.float64)
    wl = torch.tensor([wl_um], dtype=torch.float64)
    ep_z, r_ep = entrance_pupil(lens)
    h = 1e-6 * r_ep
    with torch.no_grad():
        cd = coherent.chief_rays(lens, f[None], wl, None, z, hl.sensor_z())
        uv_c = cd[2][0, 0].reshape(1, 2)
        x_c, _, jac_c = coherent.run_serial(tracing_mod._landing_and_jacobian(lens, uv_c, f, wl, None, z,
                                                                              lens.field_type, h, ep_z))
    aim = tracing_mod._Aim(lens, f, wl, None, z, lens.field_type, h, ep_z)
    return aim, (uv_c, x_c, jac_c), r_ep, cd[0].o[0, 0, :2].tolist()


def _solves_and_rounds(calls: list) -> tuple:
    """Run each generator factory of ``calls`` (:func:`coherent.run_serial`), counting its Newton rounds: ``(answers,
    rounds)``."""
    rounds = []
    rows = tracing_mod._landing_rounds

    def counted(*args):
        rounds[-1] += 1
        return rows(*args)

    tracing_mod._landing_rounds = counted
    try:
        out = []
        for call in calls:
            rounds.append(0)
            with torch.no_grad():
                out.append(coherent.run_serial(call()))
    finally:
        tracing_mod._landing_rounds = rows
    return out, rounds


def _landed(aim, uv) -> tuple:
    """Landing points (N, 2) and validity (N,) of ``aim``'s rays through ``uv`` (N, 2)."""
    with torch.no_grad():
        return tracing_mod._trace_rows(aim, uv, aim.field.expand(uv.shape[0], 2), aim.wavelength.expand(uv.shape[0]))


def test_a_seed_solve_stops_after_its_last_step_unconfirmed():
    """``finish`` (the coarse start's seeds): a ray within ``finish`` of its target takes its Newton step and stops,
    without the trace that confirms it. Traced afterwards, every such ray lands within the full tolerance (Newton's
    error after a step from ≤ 1e-6 mm is ~1e-12 mm), and the solve takes fewer rounds."""
    from raywave.hybrid.coherent.accurate import COARSE_FINISH
    from raywave.hybrid.coherent.record import _NEWTON_TOL

    aim, chief, r_ep, xc = _aim_case(12.0, 0.47)
    g = torch.linspace(-0.6, 0.6, 9, dtype=torch.float64)
    targets = torch.stack(torch.meshgrid(xc[0] + g, xc[1] + g, indexing="xy"), -1).reshape(-1, 2)
    out, rounds = _solves_and_rounds([lambda f=f: tracing_mod._invert_to_nodes(aim, targets, chief, 0.25 * r_ep,
                                                                               finish=f) for f in (None, COARSE_FINISH)])
    (ref_uv, ref_conv, _, ref_x), (uv, conv, _, x) = out
    landed, valid = _landed(aim, uv)
    assert bool(ref_conv.all()) and bool(conv.all()) and bool(valid.all())
    assert ref_x is not None and x is None  # the last steps were not traced: no landing points to give
    assert float((landed - targets).abs().max()) <= _NEWTON_TOL
    assert float((uv - ref_uv).abs().max()) <= 1e-9
    assert rounds[1] < rounds[0], rounds


def test_nodes_settle_before_the_node_traces_own_step():
    """``settle`` (the node inversion's): a ray whose error after one more step, predicted from its last two, is
    within ``settle`` stops where it is, converged, and the caller's step J⁻¹(X − T) from there (the node trace's)
    lands it within ``settle``; fewer rounds than confirming every node by a trace of its own."""
    from raywave.hybrid.coherent.accurate import NODE_SETTLE, _coarse_start, _Nodes
    from raywave.hybrid.coherent.record import _NEWTON_TOL

    aim, chief, r_ep, xc = _aim_case(14.0, 0.47)
    nd = _Nodes(xc[0], xc[1], 32.0, 32.0, 2.4 / 64, 65, 65, aim.field.device)  # 65² nodes over ±1.2 mm
    with torch.no_grad():
        start = coherent.run_serial(_coarse_start(aim, nd, chief, 0.25 * r_ep))
    out, rounds = _solves_and_rounds([lambda s=s: tracing_mod._invert_to_nodes(aim, nd.targets, chief, 0.25 * r_ep,
                                                                               start, settle=s)
                                      for s in (None, NODE_SETTLE)])
    landed = []
    for inv in out:
        x, valid = _landed(aim, inv[0] - inv.step)  # the node trace's step
        landed.append(x[valid & inv[1]] - nd.targets[valid & inv[1]])
    assert bool(out[0][1].all()) and torch.equal(out[0][1], out[1][1])
    assert float(landed[0].abs().max()) <= _NEWTON_TOL and float(landed[1].abs().max()) <= NODE_SETTLE
    assert rounds[1] < rounds[0], rounds


def test_rim_images_of_many_sources_equal_one_call_each():
    hl = load_hybrid(bundled_lens_path("hybrid_asphere"))
    fields = torch.tensor([[0.0, 0.0], [0.0, 7.0], [5.0, -9.0], [0.0, 17.5]], dtype=torch.float64)
    with torch.no_grad():
        many = coherent.stop_rim_images_many(hl.optics, fields, 0.53, None)
        one = [coherent.stop_rim_images(hl.optics, f, 0.53, None) for f in fields]
    for m, o in zip(many, one):
        assert torch.equal(m[0], o[0])
        # the rays' aiming iterates over the whole batch: the images agree to its convergence, not bitwise
        assert float((m[1] - o[1]).abs().max()) <= 1e-9


def test_fresnel_integrals_split_over_threads_equal_one_call():
    from scipy.special import fresnel

    from raywave.hybrid.coherent.stop_edge import _FRESNEL_CHUNK, _fresnel_threads

    x = np.random.default_rng(3).normal(0.0, 6.0, 3 * _FRESNEL_CHUNK + 17)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        c_, s_ = _fresnel_threads(x)
    finally:
        torch.set_num_threads(threads)
    s_ref, c_ref = fresnel(x)
    assert np.array_equal(c_, c_ref) and np.array_equal(s_, s_ref)
    small = x[:100]
    assert np.array_equal(_fresnel_threads(small)[0], fresnel(small)[1])
