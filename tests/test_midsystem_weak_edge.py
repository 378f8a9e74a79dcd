"""``MidSystemLens(weak_edge="doe")`` (issue 46, the mid-system DOE's cost): the strongest diffraction order with
the exact stop edge in its own engine call, the weaker orders with the DOE-plane edge as the sources of ONE engine
call. Checked against the same construction done order by order (each weak order in its own engine, its phase at
its own chief ray), and its gradients against central differences; its accuracy against the wave reference:
tests/test_midsystem_accuracy.py::test_midsystem_16_levels_weak_orders_doe_edge."""

import cmath
import math
import sys
import warnings
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

import raywave.hybrid.coherent.accurate as accurate  # noqa: E402
from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.midsystem import (DOEPhaseSurface, MidSystemLens, _absolute_phase, _pupil_phase,  # noqa: E402
                                      _sum_orders)

PITCH, PS = 1e-3, 2e-3
EXACT = dict(stop_edge="exit_pupil", edge_step="asm")


def _lens(field, n=800, parts=None, **kw):
    """The 16-level DOE (f 50 mm, ``n`` 1 µm pixels) 3 mm after lens A: ``(doe, lens, MidSystemLens)``; ``parts``:
    the ``(doe, lens)`` to use (else new ones)."""
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    if parts is None:
        doe = FresnelDOE(50.0, n, PITCH, wavelength=0.55)
        doe.fabricate(16)
        parts = (doe, M.two_lens(sys_))
    doe, lens = parts
    return doe, lens, MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=n * PITCH,
                                    final_pitch=PITCH, sensor_pitch=PS, **kw)


def test_weak_edge_is_checked():
    doe = FresnelDOE(50.0, 100, PITCH, wavelength=0.55)
    with pytest.raises(ValueError, match="weak_edge"):
        MidSystemLens(M.two_lens(W.TwoLensSystem(f_doe=50.0)), doe, 0, 3.0, final_distance=0.01, final_size=0.1,
                      final_pitch=PITCH, weak_edge="asm")


def test_weak_edge_equals_the_orders_built_one_by_one():
    """At 1°, orders 1, −15, +17 of the 16-level DOE: the field on the engine's plane of ``weak_edge="doe"`` equals
    the sum built order by order (order 1 by its exact-edge engine, each weak order by its own DOE-plane-edge engine
    with its phase from its chief ray, :func:`_absolute_phase`, and its Gouy phase from :meth:`MidSystemLens.
    caustics`) to the batched aiming's rounding (measured max |Δ| / max |u| ~1e-12)."""
    field = (0.0, 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # order −31: under-sampled, left out
        doe, lens, ml = _lens(field, min_efficiency=1e-3, weak_edge="doe", **EXACT)
        fd, hl, orders = ml.source_field(field, 0.55)
        one = _lens(field, parts=(doe, lens), min_efficiency=1e-3, stop_edge="doe")[2]  # the same DOE and lens
        pms = [DOEPhaseSurface(doe).phase_map()]
        kept = [o for o in orders if abs(o[0]) < 20]  # orders 1, −15, +17
        assert sorted(s for s, _ in kept) == [-15.0, 1.0, 17.0]
        hl0 = ml.order_lens(kept[0][0], None, pms)
        fd0 = hl0.doe_fields([field], [0.55])[0][0]
        nc0 = ml.caustics(hl0, field, 0.55)
        parts = [(fd0, kept[0][1], _pupil_phase(hl0, fd0, field, 0.55, None))]
        for scale, c in kept[1:]:
            h = one.order_lens(scale, None, pms)
            f = h.doe_fields([field], [0.55])[0][0]
            parts.append((f, c * cmath.exp(-0.5j * math.pi * (one.caustics(h, field, 0.55) - nc0)),
                          _absolute_phase(h, f, field, 0.55, None)))
        ref = _sum_orders(parts, ml.final, 0.55)
    assert fd.box == ref.box and fd.carrier == ref.carrier
    err = float((fd.envelope - ref.envelope).abs().max() / ref.envelope.abs().max())
    assert err < 1e-8, err


@pytest.mark.slow
def test_weak_edge_gradients_by_finite_differences():
    """d(Σ w·PSF) with respect to the DOE's focal length and lens A's, at 1°, orders 1 (the exact edge) and −15 (the
    DOE-plane edge), against central differences (measured 3.3e-5 relative for the DOE's focal length). Order +17
    (it focuses 2.1 mm after the DOE, before lens B): :func:`test_focused_weak_order_gradients_by_finite_differences`
    (the DOE-plane edge; with the exact edge: :func:`test_focused_order_exact_edge_gradients_by_finite_differences`,
    the construction's mesh held)."""
    field = (0.0, 1.0)
    doe, lens, ml = _lens(field, min_efficiency=1e-3, orders=[1, -15], weak_edge="doe", **EXACT)
    loss = M.weighted_psf_loss(ml, field)

    params = M.focal_lengths(doe, lens)
    M.assert_central_differences(loss, params, 2e-4)


def test_focused_weak_order_gradients_by_finite_differences():
    """Order +17 alone with the DOE-plane edge (it focuses 2.1 mm after the DOE, before lens B; its PSF crop is a
    wide disk's centre, where the stop's edge waves matter), at 1°: d(Σ w·PSF) with respect to the DOE's focal length
    and lens A's against central differences, measured 2.5e-5 and 6.0e-6 relative (1.1e-3 and 1.4e-3 while the
    engine's aperture-edge distance ``slack/|∇slack|`` held |∇slack| constant: its interpolated value near the edge
    combines nodes up to 2 node spacings away, where the slack is not 0).

    The step is 1e-7 (5 nm of the focal length): the DOE-plane cut's coverage ``clamp(0.5 + d/p, 0, 1)`` is
    piecewise linear in each sample's edge distance, and this order's edge sweeps ~8 nm per µm of the focal length,
    so a sample leaves the ramp about every 0.1 µm of it, each changing the slope by up to ~5 % (the analytic gradient
    is the slope of the piece; a step of 1e-6, ±50 nm, straddles such kinks and reads 1.4 %)."""
    field = (0.0, 1.0)
    # the DOE-plane edge (stop_edge="doe"): the default "auto" takes the exit-pupil edge for this focusing order
    doe, lens, ml = _lens(field, min_efficiency=1e-3, orders=[17], stop_edge="doe")
    loss = M.weighted_psf_loss(ml, field)

    params = M.focal_lengths(doe, lens)
    M.assert_central_differences(loss, params, 2e-4, step=1e-7)


@pytest.mark.slow
def test_focused_weak_order_with_order_1_gradients_by_finite_differences():
    """Orders 1 (the exact edge) and +17 (the DOE-plane edge, ``weak_edge="doe"``) at 1°: d(Σ w·PSF) against central
    differences at the step 1e-7 (see :func:`test_focused_weak_order_gradients_by_finite_differences`), measured
    6.4e-4 (the DOE's focal length) and 4.3e-6 (lens A's) relative; before the edge distance's |∇slack| was
    differentiated 1.6e-3 and 7.8e-5, and at the step 1e-6 (a coverage kink inside it) 1.5 %. This derivative is
    small (7.5e-5, the orders' terms nearly cancel): the PSF's rounding (~1e-12 between calls, the aiming's
    tolerance) over the 1e-5 mm difference is ~1e-3 of it, hence the bar."""
    field = (0.0, 1.0)
    doe, lens, ml = _lens(field, min_efficiency=1e-3, orders=[1, 17], weak_edge="doe", **EXACT)
    loss = M.weighted_psf_loss(ml, field)

    params = M.focal_lengths(doe, lens)
    M.assert_central_differences(loss, params, 2e-3, step=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("orders", [[17], [1, 17]])
def test_focused_order_exact_edge_gradients_by_finite_differences(orders):
    """Order +17 (it focuses 2.1 mm after the DOE, before lens B) with the exact stop edge, alone and with order 1
    (every order exact), at 1°: d(Σ w·PSF) with respect to the DOE's focal length and lens A's against central
    differences (steps 1e-6 and 1e-5), the rim images' source nudge 1e-3 (the engine's 1e-5 rounds the loss at
    ~1e-10).

    With the construction's mesh held as the gradient holds it (:class:`midsystem_systems.FrozenMesh`: the step plane
    beyond the rim images and the node grid), measured 2.6e-5 / 6.9e-5 (+17 alone: the DOE's focal length, lens A's)
    and 1.2e-5 / 1.8e-7 (1 and +17); with the mesh free 8.5e-4 / 8.1e-5 and 1.7e-3 / 2.4e-6: the mesh's motion, the
    derivative of the construction's discretisation error (dL/dz_edge = −1.84e-5 per mm, the plane moving 0.60 mm per
    mm of the DOE's focal length). Before 2026-11-30 (h46d) +17's stop edge was not formed at all on its step plane,
    which lies before the rim images (:func:`test_edge_formed_on_a_step_plane_before_the_rim_images`), and its
    gradient read −8.3e-5 against +2.27e-4 (the derivative is −2.2e-2)."""
    field = (0.0, 1.0)
    doe, lens, ml = _lens(field, min_efficiency=1e-3, orders=orders, **EXACT)
    loss = M.weighted_psf_loss(ml, field)

    # the DOE's focal length at the step 1e-6 (1 and +17: a small jump lies within 5e-6), lens A's at 1e-5 (the loss
    # still rounds at ~3e-11 with the nudge 1e-3: ~2e-4 of this derivative at 1e-6)
    doe_f, lens_f = ({k: v} for k, v in M.focal_lengths(doe, lens).items())
    with M.FrozenMesh() as mesh:
        held = mesh.loss(loss)
        M.assert_central_differences(held, doe_f, 2e-4, step=1e-6)
        M.assert_central_differences(held, lens_f, 2e-4, step=1e-5)
    with M.FrozenMesh(plane=False, nodes=False):  # the nudge alone
        M.assert_central_differences(loss, doe_f, 3e-3, step=1e-6)
        M.assert_central_differences(loss, lens_f, 3e-3, step=1e-5)


def test_edge_formed_on_a_step_plane_before_the_rim_images(monkeypatch):
    """Order +17 alone with the exact edge at 1°: its step plane (z 14.60 mm) lies 0.46 mm before its rim images
    (15.06–15.25 mm), where the stop's edge wave still converges on them and no focus of the beam lies between. The
    knife edge's Fresnel parameter ν has the sign of the distance to the edge's shadow and grows inside the beam
    (measured 71 at the node nearest the stop's centre, ±23 at the grid's rim), and the PSF (ks 32) is 3.3e-3 (L1)
    from the one with ν from the local Fresnel scale (``PATH_DIFFERENCE_NU=False``, ``ν = g·s``). Before 2026-11-30
    (h46d) the path difference kept the sign it has with a focus between the plane and the images
    (tests/test_hybrid_stop_edge.py::test_path_difference_nu_before_the_rims_images), ≤ 0 at every node here: ν was
    ~1e-150 over the whole plane (no edge), 4.8e-2 from the local scale's PSF."""
    seen = []
    orig = accurate._stop_edge_maps

    def spy(b, nd, traced, maps):
        out = orig(b, nd, traced, maps)
        seen.append((b.z_doe, b.given.stop_rim, maps["stop"][0].detach(), out["nu_raw"]))
        return out

    monkeypatch.setattr(accurate, "_stop_edge_maps", spy)
    field = (0.0, 1.0)
    psfs = []
    for flag in (True, False):
        monkeypatch.setattr(accurate, "PATH_DIFFERENCE_NU", flag)
        _, _, ml = _lens(field, min_efficiency=1e-3, orders=[17], **EXACT)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # order +17's pixel loss (named by the sampling report)
            p = ml.psf([field], 0.55, ks=32)[0, 0]
        psfs.append(p / p.sum())
    assert float((psfs[0] - psfs[1]).abs().sum()) < 6e-3
    z, rim, s, nu = seen[0]
    assert z < float(rim[1].min())  # the plane before every rim image
    ky, kx = nu.shape
    assert float(nu[ky // 2, kx // 2]) > 50.0
    far = s.abs() > 0.05  # nodes more than 50 µm from the shadow's edge (~3 Fresnel units)
    assert bool((torch.sign(nu[far]) == torch.sign(s[far])).all())
    assert float(nu[far].abs().min()) > 2.0


def test_exact_edge_step_transfer_is_memoised():
    """The exact edge step's window transfer function (raywave.hybrid.coherent.exit_pupil.edge_transfer) is kept by
    the MidSystemLens for its order engines: a second PSF of the unchanged lens reuses it (a hit) and is the first
    bit for bit; a moved source misses (its own geometry) and gives what a fresh lens gives."""
    from raywave.hybrid.coherent.exit_pupil import EDGE_TRANSFER_MEMO

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doe, lens, ml = _lens((0.0, 1.0), min_efficiency=1e-3, weak_edge="doe", **EXACT)
        first = ml.psf([(0.0, 1.0)], 0.55, ks=32)
        assert len(ml._edge_transfers) == 1
        key, kept = next(iter(ml._edge_transfers.items()))
        again = ml.psf([(0.0, 1.0)], 0.55, ks=32)
        assert torch.equal(first, again) and ml._edge_transfers[key] is kept and len(ml._edge_transfers) == 1
        moved = ml.psf([(0.0, 0.5)], 0.55, ks=32)
        assert len(ml._edge_transfers) == min(2, EDGE_TRANSFER_MEMO)
        fresh = _lens((0.0, 1.0), parts=(doe, lens), min_efficiency=1e-3, weak_edge="doe", **EXACT)[2]
        assert torch.equal(moved, fresh.psf([(0.0, 0.5)], 0.55, ks=32))
