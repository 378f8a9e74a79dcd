"""The orders of a mid-system DOE as the sources of one engine call (issue 46's cost): the batched construction
(:meth:`MidSystemLens.source_field` with the DOE-plane edge) gives the field that one engine call per order gives
(the pre-batching path, kept for the exit-pupil edge), and the per-source phase surface refuses a trace whose rows
are not its sources."""

import math
import sys
import warnings
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.params import FresnelDOE, GratingDOE  # noqa: E402
from raywave.hybrid.coherent.tracing import per_source  # noqa: E402
from raywave.hybrid.midsystem import DOEPhaseSurface, MidSystemLens, _absolute_phase, _sum_orders  # noqa: E402


def _grating(field):
    sys_ = W.TwoLensSystem(f_doe=math.inf, field=field)
    doe = GratingDOE(0.05, 500, 1e-3)
    doe.fabricate(2)  # orders ±1, ±3, ±5
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=0.6, final_pitch=1e-3,
                       sensor_pitch=2e-3)
    return ml


def _per_order(ml, field, wl):
    """The field of ``field`` summed from one engine call per order (the path before batching; each order's absolute
    phase at its chief ray's point, as the batched path reads it)."""
    orders = ml.orders(wl)
    pms = [DOEPhaseSurface(d).phase_map() for d in ml.does]
    parts = []
    for j, (scale, c) in enumerate(orders):
        hl = ml.order_lens(scale, None, pms)
        fd = hl.doe_fields([tuple(field)], [wl])[0][0]
        nc = ml.caustics(hl, field, wl)
        nc0 = nc if j == 0 else nc0
        parts.append((hl, fd, c * complex(math.cos(-0.5 * math.pi * (nc - nc0)), math.sin(-0.5 * math.pi * (nc - nc0)))))
    return _sum_orders([(fd, c, _absolute_phase(hl, fd, field, wl, None)) for hl, fd, c in parts], ml.final,
                       wl), orders


@pytest.mark.parametrize("field", [(0.0, 0.0), (0.0, 1.5)])
def test_batched_orders_equal_one_call_per_order(field):
    ml = _grating(field)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fd, hl, orders = ml.source_field(field, 0.55)
        ref, orders_ref = _per_order(ml, field, 0.55)
    assert len(orders) == 6 and [s for s, _ in orders] == [s for s, _ in orders_ref]
    assert hl.lens.surfaces[1].interaction.phase.source_index == 0  # the one shared lens of the call
    assert fd.box == ref.box
    err = ((fd.envelope - ref.envelope).abs().sum() / ref.envelope.abs().sum()).detach()
    print("batched vs per order", float(err))
    assert float(err) < 1e-10


def test_per_source_surface_needs_its_rows():
    doe = FresnelDOE(50.0, 64, 1e-3, wavelength=0.55)
    surf = DOEPhaseSurface(doe, None, source_index=0)
    x = torch.zeros(3, 1, 5, dtype=torch.float64)
    with pytest.raises(RuntimeError, match="without its sources' orders"):
        surf(x, x, 0.55)
    holder = torch.nn.Module()
    holder.surf = surf
    with per_source(holder, [(1.0,), (2.0,)]):
        with pytest.raises(RuntimeError, match="rows are not the sources"):
            surf(x, x, 0.55)
    with per_source(holder, [(1.0,), (-1.0,), (3.0,)]):
        phi, gx, gy = surf(x + 0.01, x, 0.55)
    one = DOEPhaseSurface(doe, 1.0)(x + 0.01, x, 0.55)
    assert torch.equal(phi[1], -one[0][1]) and torch.equal(gx[2], 3.0 * one[1][2])
    assert surf._rows is None  # cleared when the block closes


def test_psf_result_batches_single_order_sources():
    """A continuous DOE (one order) at three fields and two wavelengths: :meth:`MidSystemLens.psf_result` builds each
    wavelength's fields in ONE engine call (:meth:`MidSystemLens._wavelength_fields`); each PSF equals the call for
    its source alone to the batched aiming's rounding."""
    sys_ = W.TwoLensSystem(f_doe=50.0)
    doe = FresnelDOE(50.0, 600, 1e-3, wavelength=0.55)
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=0.6, final_pitch=1e-3,
                       sensor_pitch=2e-3)
    fields, wls = [(0.0, 0.0), (0.0, 0.5), (0.3, -0.4)], [0.5, 0.55]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = ml.psf_result(fields, wls, ks=16)
        for i, f in enumerate(fields):
            for j, wl in enumerate(wls):
                one = ml.psf_result([f], wl, ks=16)
                assert torch.allclose(res.center[i, j], one.center[0, 0], rtol=0, atol=1e-12)
                err = float((res.psf[i, j] - one.psf[0, 0]).abs().sum() / one.psf[0, 0].abs().sum())
                assert err < 1e-9, (f, wl, err)
