"""Issue 43: the node-map stage of many accurate constructions as one batched computation.

After its node rays are traced an accurate construction yields a node-map request (:class:`raywave.hybrid.coherent.
accurate._NodeMapRequest`); :func:`raywave.hybrid.coherent.run_batched` answers the pending ones of a lens and mode
together: on an accelerator (:func:`raywave.utils.devices.accelerator`) as padded batches
(:func:`~raywave.hybrid.coherent.accurate._node_stage_batch`: the node grids of different sizes padded to a common
grid, each with its own boundary differences, the per-construction constants as tensors, the sign choices as masks,
two host reads per batch), on a CPU one by one (:func:`~raywave.hybrid.coherent.accurate._node_stage`). Here the
accelerator's plan is forced on the CPU and the batch compared with each construction's own call: the bundled
``hybrid_asphere`` (default exit-pupil edge with its rim images, and the DOE-plane edge), the same lens with a second
aperture (the other edges' map), a mid-system grating (per-source orders), nodes whose ray failed (the nearest-node
fill), the gradients, and the checks' warnings.

Every map is the per-construction one to 1e-12 of its largest value (bit for bit on this CPU) except the knife edge's
Fresnel parameter ν from the path difference to the rim images (:func:`~raywave.hybrid.coherent.accurate.
_path_difference_nu`): ``Δ = Φ_E + n|P − E| − Φ_P`` cancels paths of ~10 mm to ~1e-4 mm, so the last-bit rounding
of the vectorised cos / sin / atan2 of the rims' harmonics (which depends on an element's place in memory: a batch
pads the grids) moves ν by up to ~1e-11 of its largest value near the shadow's edge; the per-construction path moves
by as much when its nodes merely shift in memory (``test_path_difference_rounding_is_the_per_construction_paths_own``).
"""

import copy
import math
import sys
import warnings
from pathlib import Path

import pytest
import torch

import raywave.hybrid.coherent.accurate as acc
import raywave.hybrid.coherent.stop_edge as stop_edge
import raywave.utils.devices as devices
from raywave.assembly.build import load_hybrid
from raywave.doe import Binary2DOE, BlankDOE, PixelDOE
from raywave.hybrid import HybridLens, SamplingWarning
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.surfaces.aperture import CircularAperture

sys.path.insert(0, str(Path(__file__).parent))
from loss_grads import loss_and_grads  # noqa: E402

FIELDS = [(0.0, 0.0), (0.0, 6.0), (4.0, 3.0), (-7.0, -9.0)]
WLS = [0.66, 0.47]
#: ν from the path difference: the vectorised transcendental functions' rounding, amplified (module docstring)
NU_TOL = 1e-10


@pytest.fixture(scope="module")
def asphere():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


def _requests(monkeypatch, run) -> list:
    """The largest group of node-map requests of ``run()`` (no autograd) under the accelerator's plan."""
    seen = []
    real = acc._NodeMapRequest.run_group
    monkeypatch.setattr(acc._NodeMapRequest, "run_group", staticmethod(lambda reqs: seen.append(list(reqs))
                                                                       or real(reqs)))
    monkeypatch.setattr(devices, "accelerator", lambda x: True)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        run()
    return max(seen, key=len)


def _assert_batch_equals_one_by_one(reqs: list) -> dict:
    """The batch's maps against each construction's own (:func:`_node_stage`); returns the largest relative
    difference of every map."""
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        got = acc._node_stage_batch(reqs)
        ref = [r.run() for r in reqs]
    worst: dict = {}
    for g, r in zip(got, ref):
        if r is None:
            assert g is None
            continue
        # the batch's maps also say where they lie in its padded stack (the field stage reads them from there)
        assert isinstance(g.pop("batch"), acc._BatchedMaps)
        assert g.keys() == r.keys() == set(acc._FIELD_MAPS) & set(r)
        for k in r:
            if r[k] is None:
                assert g[k] is None
                continue
            if isinstance(r[k], float):  # g_max
                assert isinstance(g[k], float)
                err = abs(g[k] - r[k]) / abs(r[k])
            else:
                assert g[k].shape == r[k].shape and g[k].dtype == r[k].dtype
                assert g[k].requires_grad == r[k].requires_grad
                err = float((g[k] - r[k]).abs().max()) / float(r[k].abs().max())
            worst[k] = max(worst.get(k, 0.0), err)
            assert err <= (NU_TOL if k in ("nu", "nu_raw") else 1e-12), (k, err)
    return worst


@pytest.mark.parametrize("stop_edge_mode", ["exit_pupil", "doe"])
def test_batched_node_stage_equals_per_construction(asphere, stop_edge_mode, monkeypatch):
    """The bundled asphere, 4 fields × 2 wavelengths: node grids of different spacings (and, with the exit-pupil
    edge's ripple band, sizes) in one batch; the default edge (ν from the rim images' path differences, the rim planes chosen per construction) and the DOE-plane
    edge (no Fresnel channels)."""
    monkeypatch.setattr(asphere, "stop_edge", stop_edge_mode)
    reqs = _requests(monkeypatch, lambda: asphere.psf_result(FIELDS, WLS, ks=24))
    assert len(reqs) == len(FIELDS) * len(WLS)
    assert len({r.nd.h for r in reqs}) > 2
    if stop_edge_mode == "exit_pupil":  # the ripple band widens each grid by its own margin
        assert len({(r.nd.ky, r.nd.kx) for r in reqs}) > 2
    worst = _assert_batch_equals_one_by_one(reqs)
    assert ("nu" in worst) == (stop_edge_mode == "exit_pupil")
    for k in ("phi_env", "amp2", "dist"):
        assert worst[k] <= 1e-12


def test_batched_node_stage_with_a_second_aperture(asphere, monkeypatch):
    """A 1 mm aperture on the asphere's last surface clips the off-axis beams: the other edges' distance map (and the
    stop's apart) from the batch equals each construction's."""
    lens = copy.deepcopy(asphere.lens)
    lens.surfaces[2].aperture = CircularAperture(1.0)
    hl = HybridLens(lens, asphere.doe, asphere.doe_distance, sensor_pitch=asphere.sensor_pitch)
    reqs = _requests(monkeypatch, lambda: hl.psf_result([(0.0, 0.0), (0.0, 10.0), (5.0, 12.0)], [0.55], ks=24))
    assert len(reqs) == 3
    ref = [r.run() for r in reqs]
    assert all(m["other"] is not None for m in ref) and min(float(m["other"].min()) for m in ref) < 0
    assert "other" in _assert_batch_equals_one_by_one(reqs)


def test_batched_node_stage_of_a_mid_system_grating(monkeypatch):
    """A binary grating between two lenses (issue 46): its six orders are one call's sources, each traced with its
    own order (per-source rows), two apertures; the batch equals each order's own maps."""
    import midsystem_systems as M
    import wave_truth_doe as W
    from raywave.doe.params import GratingDOE
    from raywave.hybrid.midsystem import MidSystemLens

    sys_ = W.TwoLensSystem(f_doe=math.inf, field=(0.0, 1.5))
    doe = GratingDOE(0.05, 500, 1e-3)
    doe.fabricate(2)
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=0.6, final_pitch=1e-3,
                       sensor_pitch=2e-3)
    reqs = _requests(monkeypatch, lambda: ml.psf_result([(0.0, 1.5)], [0.55], ks=24))
    assert len(reqs) == 6 and len({r.b.src.order for r in reqs}) == 6
    _assert_batch_equals_one_by_one(reqs)


def test_batched_fresnel_scale_limit_ignores_the_beam_centre(monkeypatch):
    """Lens A alone (an ideal lens f 10 mm, F/12.5, tests/test_far_tails.py), a blank DOE 3 mm before the focus, the
    Fresnel step, on axis and off it: the batch's maps and its inner-tail scale ``g_max`` are each construction's
    own, and ``g_max`` is the edge's Fresnel scale ``sqrt(2/(λ L))``, L = 7 mm · 0.3 (41.6/mm), not the scale of the
    node on the beam's centre (its normal undefined: the shortest length's 0.94/pitch, 943/mm; issue 47)."""
    from raywave.lens.lens import Lens
    from raywave.materials import get_material
    from raywave.surfaces.geometry import Plane
    from raywave.surfaces.interaction import IdealLens
    from raywave.surfaces.surface import Surface
    a = Surface(Plane(), get_material("AIR"), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                is_stop=True)
    hl = HybridLens(Lens([a], wavelengths=(0.55,), primary=0), BlankDOE(1000, 1e-3), 7.0, sensor_pitch=2e-3,
                    stop_edge="exit_pupil", edge_step="fresnel")
    reqs = _requests(monkeypatch, lambda: hl.psf_result([(0.0, 0.0), (0.0, 0.2)], 0.55, ks=32))
    assert len(reqs) == 2
    _assert_batch_equals_one_by_one(reqs)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        for r in reqs:
            assert r.run()["g_max"] == pytest.approx(math.sqrt(2.0 / (0.55e-3 * 2.1)), rel=2e-2)


def test_batched_fill_of_failed_nodes(asphere, monkeypatch):
    """Nodes whose ray failed take their nearest good node's values (the optical path extended to first order) in
    the batch as in each construction's own fill; a construction with no traced node answers None."""
    reqs = _requests(monkeypatch, lambda: asphere.psf_result(FIELDS[:3], WLS[:1], ks=24))
    g = torch.Generator().manual_seed(3)
    bad_reqs = []
    for k, r in enumerate(reqs):
        good = r.traced[4].clone()
        if k == 1:
            good[:] = False  # nothing traced
        else:
            good &= torch.rand(good.shape, generator=g) > 0.2  # a fifth of the nodes failed
            good[: r.nd.kx] = False  # and the first row
        bad_reqs.append(acc._NodeMapRequest(r.b, r.nd, r.traced[:4] + (good,)))
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        assert acc._node_stage_batch(bad_reqs)[1] is None
    _assert_batch_equals_one_by_one(bad_reqs)


def test_path_difference_rounding_is_the_per_construction_paths_own(asphere, monkeypatch):
    """The per-construction ν moves by as much as the batch's when its nodes are only shifted by one place in
    memory before the rims' harmonics are evaluated (the vectorised functions' rounding; module docstring)."""
    reqs = _requests(monkeypatch, lambda: asphere.psf_result(FIELDS, WLS, ks=24))
    with torch.no_grad():
        ref = [r.run()["nu_raw"] for r in reqs]
        real = acc._rim_fourier

        def shifted(values, xs, ys):
            return real(values, torch.cat([xs[:1], xs]), torch.cat([ys[:1], ys]))[1:]

        monkeypatch.setattr(acc, "_rim_fourier", shifted)
        moved = [r.run()["nu_raw"] for r in reqs]
        got = [m["nu_raw"] for m in acc._node_stage_batch(reqs)]
    own = max(float((a - b).abs().max() / b.abs().max()) for a, b in zip(moved, ref))
    batch = max(float((a - b).abs().max() / b.abs().max()) for a, b in zip(got, ref))
    print(f"nu: shifted by one place {own:.2e}, batched {batch:.2e}")
    assert 0 < own < NU_TOL and batch < NU_TOL


def _loss_grads(hl, batched: bool, monkeypatch):
    real = acc._NodeMapRequest.run_group
    sizes = []
    monkeypatch.setattr(acc._NodeMapRequest, "run_group", staticmethod(
        (lambda reqs: sizes.append(len(reqs)) or real(reqs)) if batched else (lambda reqs: [r.run() for r in reqs])))
    out = loss_and_grads(hl, FIELDS[1:3], WLS)
    assert not batched or max(sizes) > 1
    return out


@pytest.mark.parametrize("stop_edge_mode", ["exit_pupil", "doe"])
def test_batched_node_stage_gradients(asphere, stop_edge_mode, monkeypatch):
    """Autograd through the batched node stage (the padding finite, the sign choices masks): a weighted sum of the
    PSFs and its gradients with respect to a trainable DOE's parameters and a lens curvature equal the
    per-construction stage's (1e-10 relative), the rest of the accelerator's plan the same in both."""
    doe = Binary2DOE([-40.0, 3.0], 1.4, (2400, 2400), 1e-3, aperture="circle")
    hl = HybridLens(asphere.lens, doe, 0.7, sensor_pitch=3e-3, stop_edge=stop_edge_mode)
    monkeypatch.setattr(devices, "accelerator", lambda x: True)
    l_ref, g_ref = _loss_grads(hl, False, monkeypatch)
    l_got, g_got = _loss_grads(hl, True, monkeypatch)
    assert l_got == pytest.approx(l_ref, rel=1e-12)
    for a, b in zip(g_ref, g_got):
        scale = float(a.abs().max())
        assert scale > 0 and torch.isfinite(b).all()
        assert float((a - b).abs().max()) <= 1e-10 * scale


def _warned(hl, fields, wls, batched: bool, monkeypatch) -> list:
    real = acc._node_stage_batch
    sizes = []
    monkeypatch.setattr(acc, "_node_stage_batch", (lambda reqs: sizes.append(len(reqs)) or real(reqs)) if batched
                        else (lambda reqs: [r.run() for r in reqs]))
    with warnings.catch_warnings(record=True) as got, torch.no_grad():
        warnings.simplefilter("always")
        hl.doe_fields(fields, wls, rays=24)
    assert not batched or sizes == [len(fields) * len(wls)]
    return [(w.category, str(w.message)) for w in got]


def test_batched_checks_warn_as_each_construction(monkeypatch):
    """The checks evaluated for the batch and read once warn as each construction's own: the DOE grid too coarse for
    the phase slope (a 4 µm grid behind the asphere: Nyquist, with the worst node's position) and the stop edge too
    curved for the Fresnel step (a 0.4 obscuration on an ideal lens's stop); same categories, words and order."""
    from raywave.hybrid import StopEdgeWarning
    from raywave.lens.build import ideal_lens
    from raywave.surfaces.aperture import Obscuration

    monkeypatch.setattr(devices, "accelerator", lambda x: True)
    coarse = HybridLens(load_lens(bundled_lens_path("asphere_hk51")), BlankDOE(1500, 4e-3), 0.7, sensor_pitch=3e-3)
    lens = ideal_lens(5.0, f_number=8, wavelengths=(0.55,))
    stop = lens.surfaces[lens.stop_index]
    stop.aperture.obscuration = Obscuration("circle", radius=0.4 * float(stop.aperture.radius))
    # the Fresnel step named: the default's error estimate takes the exact construction on this obscuration
    obscured = HybridLens(lens, PixelDOE(torch.zeros(400, 400, dtype=torch.float64), 2e-3), 2.0, sensor_pitch=2e-3,
                          edge_step="fresnel")
    for hl, fields, wls, category, words in (
            (coarse, [(0.0, 7.0), (0.0, 14.0), (5.0, 10.0)], [0.53, 0.47], SamplingWarning, "Nyquist limit"),
            (obscured, [(0.0, 0.0), (0.0, 1.0)], [0.55, 0.45], StopEdgeWarning, "radius of curvature")):
        ref = _warned(hl, fields, wls, False, monkeypatch)
        got = _warned(hl, fields, wls, True, monkeypatch)
        mine = [m for c, m in ref if c is category and words in m]
        assert len(mine) >= 2
        assert [m for c, m in got if c is category and words in m] == mine
        assert got == ref


def test_node_batch_cap_follows_the_device_memory(monkeypatch):
    """The node-map batches are capped by the device's memory on CUDA (~1 kB a node at the peak), by
    ``NODE_BATCH_SAMPLES`` elsewhere."""
    from raywave.hybrid.coherent import accurate as A

    assert A._node_batch_cap("cpu") == A.NODE_BATCH_SAMPLES

    class Props:
        total_memory = 16 * 2**30

    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda dev: Props)
    assert A._node_batch_cap("cuda:0") == 16 * 2**30 // 16384 < A.NODE_BATCH_SAMPLES
    Props.total_memory = 141 * 2**30
    assert A._node_batch_cap("cuda:0") == A.NODE_BATCH_SAMPLES
