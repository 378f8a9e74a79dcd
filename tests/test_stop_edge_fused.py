"""The knife-edge envelope as one compiled loop (:func:`raywave.hybrid.coherent.stop_edge._envelope_dense`, issue 47):
the same values and gradients as the eager arithmetic on the band's samples (``RAYWAVE_COMPILE=0``: the blocks of
``_EdgeEnvelope._block_values``, the reference before the compiled loop) and as its own eager function, to rounding
(≤ 1e-14 of the largest value)."""

import pytest
import torch

import raywave.hybrid.coherent.stop_edge as se

TOL = 1e-14


@pytest.fixture(autouse=True)
def fresh_compiled_loops(monkeypatch):
    """The compiled loops as in a fresh process: a long test session's many window shapes and strides may have used up
    torch.compile's recompile limit, after which the loops fall back to the eager blocks for the process (by design:
    one FusedFallbackWarning); these tests check the compiled loop itself."""
    torch._dynamo.reset()
    for f in (se._envelope_dense, se._envelope_dense_grads, se._envelope_dense_scaled):
        monkeypatch.setattr(f, "_failed", False)
        monkeypatch.setattr(f, "_compiled", None)


def _inputs(shape=(37, 53), seed=5):
    gen = torch.Generator().manual_seed(seed)

    def r(lo, hi):
        return (torch.rand(shape, dtype=torch.float64, generator=gen) * (hi - lo) + lo).requires_grad_(True)

    # ν from deep in the shadow (beyond the band) through the band to deep inside the beam; κ/g across its clamps
    return r(0.0, 1.0), r(-300.0, 300.0), r(-12.0, 9.0), r(-0.7, 0.7)


def _close(a, b):
    return float((a - b).abs().max()) <= TOL * max(float(b.abs().max()), 1e-300)


def _run(ins, dz, rz, g, kappa: bool, w):
    out = se.edge_envelope(ins[0], ins[1], ins[2], dz, rz, g, 2e-3, kappa=ins[3] if kappa else None)
    used = ins if kappa else ins[:3]
    return out.detach(), torch.autograd.grad((torch.view_as_real(out) * w).sum(), used)


@pytest.mark.parametrize("dz", [0.8, -0.8])
@pytest.mark.parametrize("kappa", [True, False])
@pytest.mark.parametrize("per_row", [False, True])
def test_compiled_envelope_equals_the_eager_blocks(dz, kappa, per_row, monkeypatch):
    """Forward and every gradient (amplitude, phase, ν, κ/g) of the compiled loop against the eager band arithmetic,
    one value of the constants per window and per row (a batch's windows stacked by rows)."""
    ins = _inputs()
    rows = ins[0].shape[0]
    if per_row:
        rz = torch.linspace(5.0, 9.0, rows, dtype=torch.float64)[:, None]
        g = torch.linspace(20.0, 80.0, rows, dtype=torch.float64)[:, None]
    else:
        rz, g = 5.0, 40.0
    w = torch.randn(*ins[0].shape, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(9))
    assert se._dense_plan(ins[2].detach(), (dz >= 0, rz, g, 2e-3)) is not None or not se.compile_enabled()
    got, got_g = _run(ins, dz, rz, g, kappa, w)
    monkeypatch.setenv("RAYWAVE_COMPILE", "0")
    assert se._dense_plan(ins[2].detach(), (dz >= 0, rz, g, 2e-3)) is None  # the eager blocks
    want, want_g = _run(ins, dz, rz, g, kappa, w)
    assert _close(got, want)
    assert (got == 0).equal(want == 0)  # the shadow beyond the band exactly 0, as before
    for a, b in zip(got_g, want_g):
        assert _close(a, b)


def test_compiled_loop_equals_its_eager_function():
    """The compiled loop (forward and backward functions) against the same functions run eagerly (``__wrapped__``)."""
    amp, angle, nu, kap = (t.detach() for t in _inputs(seed=11))
    plan = se._dense_plan(nu, (True, 6.0, 30.0, 2e-3), compiled=False)
    args = (amp, angle, nu, kap, *plan)
    with torch.no_grad():
        for a, b in zip(se._envelope_dense(*args), se._envelope_dense.__wrapped__(*args)):
            assert _close(a, b)
        g_re, g_im = torch.randn(2, *nu.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
        for a, b in zip(se._envelope_dense_grads((g_re, g_im), *args),
                        se._envelope_dense_grads.__wrapped__((g_re, g_im), *args)):
            assert _close(a, b)


def test_a_band_beyond_the_table_takes_the_eager_blocks():
    """ν_max beyond the Fresnel table's range (|ν| ≥ 32: ripple zones far above MAX_RIPPLE_ZONES): no compiled loop
    (the eager blocks evaluate such a band with scipy's integrals)."""
    nu = torch.linspace(-40.0, 5.0, 64, dtype=torch.float64).reshape(8, 8)
    assert se._dense_plan(nu, (True, 30.0, 40.0, 2e-3)) is None
    assert se._dense_plan(nu, (True, 16.0, 40.0, 2e-3)) is not None or not se.compile_enabled()


@pytest.mark.parametrize("per_row", [False, True])
def test_compiled_envelope_in_blocks_of_rows_equals_one_call(per_row, monkeypatch):
    """A window in several blocks of rows (:data:`DENSE_BLOCK_SAMPLES`) gives the values of one call bit for bit."""
    amp, angle, nu, kap = (t.detach() for t in _inputs(shape=(23, 41), seed=3))
    rz = torch.linspace(5.0, 9.0, 23, dtype=torch.float64)[:, None] if per_row else 5.0
    g = torch.linspace(20.0, 80.0, 23, dtype=torch.float64)[:, None] if per_row else 40.0
    one = se.edge_envelope(amp, angle, nu, 0.8, rz, g, 2e-3, kappa=kap)
    monkeypatch.setattr(se, "DENSE_BLOCK_SAMPLES", 5 * 41)  # 5 blocks of 4–5 rows
    assert torch.equal(se.edge_envelope(amp, angle, nu, 0.8, rz, g, 2e-3, kappa=kap), one)


@pytest.mark.parametrize("dz", [0.8, -0.8])
@pytest.mark.parametrize("cov", [True, False])
@pytest.mark.parametrize("blocks", [False, True])
def test_scaled_envelope_equals_the_products_first(dz, cov, blocks, monkeypatch):
    """``edge_envelope``'s ``scale`` (the coverage and k·φ taken inside the compiled loop, on strided crops of a
    channel stack as the accurate construction passes them, issue 47) against the products formed first: the same
    values bit for bit (exact products), in one call and in blocks of rows, without a graph and with one."""
    if blocks:
        monkeypatch.setattr(se, "DENSE_BLOCK_SAMPLES", 5 * 41)
    gen = torch.Generator().manual_seed(3)
    stack = torch.rand(5, 45, 61, dtype=torch.float64, generator=gen)
    stack[0] = stack[0] * 0.02 - 0.01  # φ mm
    stack[3] = stack[3] * 21.0 - 12.0  # ν
    stack[4] = stack[4] * 1.4 - 0.7  # κ/g
    crop = stack[:, 3:40, 5:58]  # strided views, as the window's crop
    phi, amp, c, nu, kap = crop.unbind(0)
    c = c if cov else None
    k = 2 * torch.pi / 0.53e-3
    ref = se.edge_envelope(amp if c is None else amp * c, k * phi, nu, dz, 5.0, 40.0, 2e-3, kappa=kap)
    got = se.edge_envelope(amp, phi, nu, dz, 5.0, 40.0, 2e-3, kappa=kap, scale=(c, k))
    assert torch.equal(got, ref)
    amp_g = amp.clone().requires_grad_(True)
    got_g = se.edge_envelope(amp_g, phi, nu, dz, 5.0, 40.0, 2e-3, kappa=kap, scale=(c, k))
    assert torch.equal(got_g.detach(), ref)
