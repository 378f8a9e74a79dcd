"""Issue 43: the field stage of many accurate constructions as one batched computation.

After its ray stage an accurate construction yields a field request (:class:`raywave.hybrid.coherent.accurate.
_FieldRequest`); :func:`raywave.hybrid.coherent.run_batched` answers the pending ones of a plane, DOE and mode with
one :func:`~raywave.hybrid.coherent.accurate._fine_fields`, which on an accelerator pads the constructions' node maps
and fine windows to common shapes and runs the interpolation, the coverage, the ripple band, the crop and the
envelope with its knife-edge factor as batched tensor ops (:func:`~raywave.hybrid.coherent.accurate.
_fine_field_batch`). Here the CPU is made to take that path (``BATCHED_FIELD_STAGE = True``) and compared with the
per-construction path (:func:`~raywave.hybrid.coherent.accurate._fine_field` each) on the bundled ``hybrid_asphere``,
on and off axis, with the default (exit-pupil) edge and the DOE-plane edge: every envelope and box, and the gradients
of a loss of the PSFs with respect to the DOE's and a lens parameter.

The reference interpolates with the dense products (the accelerator's plan, ``raywave.utils.devices.accelerator``
forced: what an accelerator's per-construction path does); the CPU's banded products sum the same terms in another order, which moves an envelope
by up to ~2e-12 of its peak (its phase k·φ, k ≈ 1.3e4 /mm, carries φ's rounding), in either path.
"""

import sys
import warnings
from pathlib import Path

import pytest
import torch

import raywave.hybrid.coherent.accurate as acc
import raywave.utils.devices as devices
import raywave.wave.field as field_mod
from raywave.assembly.build import load_hybrid
from raywave.doe import Binary2DOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path

sys.path.insert(0, str(Path(__file__).parent))
from loss_grads import loss_and_grads  # noqa: E402

FIELDS = [(0.0, 0.0), (0.0, 6.0), (4.0, 3.0), (-7.0, -9.0)]
WLS = [0.66, 0.47]


@pytest.fixture(scope="module")
def asphere():
    return load_hybrid(bundled_lens_path("hybrid_asphere"))


@pytest.fixture(scope="module")
def trainable(asphere):
    """The bundled asphere's lens behind a trainable DOE (BINARY_2 coefficients) with a circular aperture that
    clips the off-axis beams (the batched path's DOE coverage)."""
    doe = Binary2DOE([-40.0, 3.0], 1.4, (2400, 2400), 1e-3, aperture="circle")
    return HybridLens(asphere.lens, doe, 0.7, sensor_pitch=3e-3)


@pytest.fixture
def dense(monkeypatch):
    """Both paths take the accelerator's plan, its dense interpolation products included (its arithmetic)."""
    monkeypatch.setattr(devices, "accelerator", lambda x: True)


def _doe_fields(hl, batched: bool, monkeypatch):
    monkeypatch.setattr(acc, "BATCHED_FIELD_STAGE", batched)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            return hl.doe_fields(FIELDS, WLS, rays=24)


@pytest.mark.parametrize("stop_edge", ["exit_pupil", "doe", "circle"])
def test_batched_field_stage_equals_per_construction(asphere, trainable, stop_edge, dense, monkeypatch):
    """Every construction's envelope and box from the batched field stage equal the per-construction path's (to
    1e-12 of the envelope's peak), and the batched path is the one taken. ``circle``: the trainable DOE's circular
    aperture clips the beams (the default edge)."""
    hl = trainable if stop_edge == "circle" else asphere
    if stop_edge != "circle":
        monkeypatch.setattr(hl, "stop_edge", stop_edge)
    ref = _doe_fields(hl, False, monkeypatch)
    sizes = []
    real = acc._fine_field_batch

    def spy(reqs, *a):
        sizes.append(len(reqs))
        return real(reqs, *a)

    monkeypatch.setattr(acc, "_fine_field_batch", spy)
    got = _doe_fields(hl, True, monkeypatch)
    # one group (no mirror images among FIELDS: each one built), in batches of FIELD_BATCH_SAMPLES
    assert sum(sizes) == len(FIELDS) * len(WLS) and max(sizes) > 1
    for row_r, row_g in zip(ref, got):
        for r, g in zip(row_r, row_g):
            assert g.box == r.box
            assert g.envelope.shape == r.envelope.shape
            peak = float(r.envelope.abs().max())
            assert peak > 0
            assert float((g.envelope - r.envelope).abs().max()) <= 1e-12 * peak


def test_batched_field_stage_against_the_cpu_path(asphere, monkeypatch):
    """Against the CPU's own per-construction path (banded interpolation products): the same boxes, envelopes to
    its products' rounding (see the module docstring)."""
    ref = _doe_fields(asphere, False, monkeypatch)
    got = _doe_fields(asphere, True, monkeypatch)
    for row_r, row_g in zip(ref, got):
        for r, g in zip(row_r, row_g):
            assert g.box == r.box
            assert float((g.envelope - r.envelope).abs().max()) <= 1e-11 * float(r.envelope.abs().max())


def _loss_grads(hl, batched: bool, monkeypatch):
    monkeypatch.setattr(acc, "BATCHED_FIELD_STAGE", batched)
    return loss_and_grads(hl, FIELDS[1:3], WLS)


@pytest.mark.parametrize("stop_edge", ["exit_pupil", "doe"])
def test_batched_field_stage_gradients(trainable, stop_edge, dense, monkeypatch):
    """Autograd through the batched field stage: a weighted sum of the PSFs and its gradients with respect to the
    DOE's parameters and a lens curvature equal the per-construction path's (1e-10 relative)."""
    monkeypatch.setattr(trainable, "stop_edge", stop_edge)
    assert [p for p in trainable.doe.parameters() if p.requires_grad]
    l_ref, g_ref = _loss_grads(trainable, False, monkeypatch)
    sizes = []
    real = acc._fine_field_batch
    monkeypatch.setattr(acc, "_fine_field_batch", lambda reqs, *a: sizes.append(len(reqs)) or real(reqs, *a))
    l_got, g_got = _loss_grads(trainable, True, monkeypatch)
    assert sizes and max(sizes) > 1
    assert l_got == pytest.approx(l_ref, rel=1e-12)
    for a, b in zip(g_ref, g_got):
        scale = float(a.abs().max())
        assert scale > 0
        assert float((a - b).abs().max()) <= 1e-10 * scale


def test_run_serial_is_a_group_of_one(asphere, monkeypatch):
    """One construction alone (``accurate_field``: :func:`run_serial`) answers its field request itself: the batched
    stage never runs for it."""
    monkeypatch.setattr(acc, "BATCHED_FIELD_STAGE", True)
    monkeypatch.setattr(acc, "_fine_field_batch", lambda *a: pytest.fail("a group of one was batched"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with torch.no_grad():
            one = asphere.doe_fields([(0.0, 6.0)], [0.53], rays=24)
    assert one[0][0].envelope.abs().max() > 0


def test_cubic_matrices_are_cubic_matrix_bit_for_bit():
    """:func:`raywave.wave.field.cubic_matrices`: each grid's rows equal :func:`cubic_matrix`'s bit for bit (its
    ghost folding at both ends included), zeros beyond its nodes; one node count per grid or per position."""
    gen = torch.Generator().manual_seed(0)
    ns = [3, 5, 17, 40]
    pos = [(torch.rand(50, dtype=torch.float64, generator=gen) * (n + 3) - 2).clamp(0, n - 1) for n in ns]
    nn = torch.tensor(ns, dtype=torch.float64)[:, None]
    for counts in (nn, nn.expand(-1, 50)):
        m = field_mod.cubic_matrices(torch.stack(pos), counts, max(ns))
        for i, n in enumerate(ns):
            assert torch.equal(m[i, :, :n], field_mod.cubic_matrix(pos[i], n))
            assert not m[i, :, n:].any()


def test_edge_envelope_with_per_row_constants():
    """:func:`~raywave.hybrid.coherent.stop_edge.edge_envelope` on windows stacked by rows, each row with its own
    window's ripple zones and Fresnel scale ((R, 1) tensors), equals one call per window with its floats bit for
    bit, and so do its gradients (the hand-written backward)."""
    from raywave.hybrid.coherent.stop_edge import edge_envelope

    gen = torch.Generator().manual_seed(1)
    consts = [(5.0, 40.0), (7.5, 25.0), (5.0, 90.0)]  # (ripple zones, g_max 1/mm)
    ny, nx, p = 6, 50, 1e-3

    def inputs():
        amp = torch.rand(3, ny, nx, dtype=torch.float64, generator=gen).requires_grad_(True)
        angle = (100 * torch.rand(3, ny, nx, dtype=torch.float64, generator=gen)).requires_grad_(True)
        nu = (30 * torch.rand(3, ny, nx, dtype=torch.float64, generator=gen) - 15).requires_grad_(True)
        kap = (torch.rand(3, ny, nx, dtype=torch.float64, generator=gen) - 0.5).requires_grad_(True)
        return amp, angle, nu, kap

    ins = inputs()
    w = torch.rand(3, ny, nx, dtype=torch.complex128, generator=gen)
    rz = torch.tensor([c[0] for c in consts], dtype=torch.float64).repeat_interleave(ny)[:, None]
    g = torch.tensor([c[1] for c in consts], dtype=torch.float64).repeat_interleave(ny)[:, None]
    flat = [t.reshape(-1, nx) for t in ins]
    env = edge_envelope(flat[0], flat[1], flat[2], 0.5, rz, g, p, kappa=flat[3]).reshape(3, ny, nx)
    (env * w).real.sum().backward()
    grads = [t.grad.clone() for t in ins]
    for t in ins:
        t.grad = None
    one = torch.stack([edge_envelope(ins[0][i], ins[1][i], ins[2][i], 0.5, c[0], c[1], p, kappa=ins[3][i])
                       for i, c in enumerate(consts)])
    (one * w).real.sum().backward()
    assert torch.equal(env, one)
    for a, t in zip(grads, ins):
        assert torch.equal(a, t.grad)
    with torch.no_grad():
        assert torch.equal(edge_envelope(*flat[:3], 0.5, rz, g, p, kappa=flat[3]).reshape(3, ny, nx), one)
