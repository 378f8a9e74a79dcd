"""Fields with leading batch axes (issue 43): one Grid shared by the batch, per-element wavelength, index, carrier
and window; the batched propagation takes and returns such Fields and equals each element propagated alone."""

import math

import pytest
import torch

from raywave.wave import Field, Grid, propagate_window, window_transfer
from raywave.wave.propagation import WindowBatch, batch_transfer, propagate_batch

P = 1e-3


def _elements():
    """Three single fields on windows of different sizes and places, with their own λ, n, carrier and output
    window (host values), chosen so that each needs the FFT size of the whole batch."""
    g = torch.Generator().manual_seed(11)
    spec = [((0.0, 0.01), (100, 90), 0.53, 1.0, (0.1, 0.05), (0.05, 0.06)),
            ((-0.02, 0.0), (96, 92), 0.55, 1.0, (0.08, 0.02), (0.03, 0.04)),
            ((0.01, -0.01), (114, 106), 0.51, 1.33, (0.0, 0.0), (0.02, 0.01))]
    fields, outs = [], []
    for origin, shape, lam, n, carrier, out_origin in spec:
        u = torch.randn(*shape, dtype=torch.complex128, generator=g)
        fields.append(Field(u, Grid(origin, P, shape), lam, n, carrier))
        outs.append(Grid(out_origin, P, (41, 41)))
    return fields, outs


def test_a_batch_propagated_together_equals_each_field_propagated_alone():
    fields, outs = _elements()
    batch = Field.stack(fields)
    z = 1.5
    wb = WindowBatch.of(batch, outs, z)
    assert len({g.size for g in wb.geometries()}) == 1  # one FFT size: the batch is each one's own path
    res = propagate_batch(batch, outs, z)
    assert res.batch_shape == (3,) and res.grid.shape == (41, 41) and res.element_grids() == tuple(outs)
    assert res.wavelengths() == tuple(f.wavelength for f in fields)
    assert res.carriers() == tuple(f.carrier for f in fields)
    for i, (f, o) in enumerate(zip(fields, outs)):
        alone = propagate_window(f, o, z)
        got = res.element(i)
        assert got.grid == alone.grid == o and got.wavelength == alone.wavelength and got.n == alone.n
        assert float((got.envelope - alone.envelope).abs().max()) <= 1e-12 * float(alone.envelope.abs().max())


def test_a_reused_transfer_and_the_derivatives_match_the_single_path():
    fields, outs = _elements()
    batch = Field.stack(fields)
    z = 1.5
    tr = batch_transfer(WindowBatch.of(batch, outs, z), weight_derivative=True)
    shift = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    dz = torch.zeros((), dtype=torch.float64, requires_grad=True)
    w = torch.randn(3, 41, 41, dtype=torch.complex128, generator=torch.Generator().manual_seed(2))
    (propagate_batch(batch, outs, z, transfer=tr, shift=shift, dz=dz).envelope * w).real.sum().backward()
    dz_sum = 0.0
    for i, (f, o) in enumerate(zip(fields, outs)):
        s = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        d = torch.zeros((), dtype=torch.float64, requires_grad=True)
        (propagate_window(f, o, z, shift=s, dz=d).envelope * w[i]).real.sum().backward()
        assert torch.allclose(shift.grad[i], s.grad, rtol=1e-10, atol=1e-9 * float(s.grad.abs().max()))
        dz_sum += float(d.grad)
    assert math.isclose(float(dz.grad), dz_sum, rel_tol=1e-10)


def test_leading_batch_axes_are_kept_and_a_shared_grid_needs_no_windows():
    g = Grid((0.0, 0.0), P, (60, 50))
    u = torch.randn(2, 3, 60, 50, dtype=torch.complex128, generator=torch.Generator().manual_seed(4))
    lam = torch.tensor([[0.5, 0.55, 0.6], [0.5, 0.55, 0.6]], dtype=torch.float64)  # sources × wavelengths
    f = Field(u, g, lam, carrier=(0.05, 0.0))
    assert f.batch_shape == (2, 3) and f.count == 6 and f.windows is None and f.carrier == (0.05, 0.0)
    assert f.wavelengths() == (0.5, 0.55, 0.6) * 2 and not f.shared
    out = Grid((0.06, 0.0), P, (31, 31))
    res = propagate_batch(f, out, 1.0)
    assert res.envelope.shape == (2, 3, 31, 31) and res.grid == out and res.windows is None
    flat = propagate_batch(f.flat(), out, 1.0)
    assert torch.equal(flat.envelope.reshape(2, 3, 31, 31), res.envelope)
    # every element on the one grid: stacking them shares it (no windows, no padding)
    st = Field.stack([f.element(i) for i in range(6)])
    assert st.grid == g and st.windows is None and torch.equal(st.envelope, u.reshape(6, 60, 50))
    # elements that agree keep one value
    same = Field(u, g, [[0.5] * 3] * 2, n=torch.full((2, 3), 1.2, dtype=torch.float64))
    assert same.wavelength == 0.5 and same.n == 1.2 and same.shared


def test_stacked_windows_round_trip_and_the_true_field_follows_each_window():
    fields, _ = _elements()
    batch = Field.stack(fields)
    assert batch.grid.shape == (114, 106) and batch.grid.origin == fields[0].grid.origin
    for i, f in enumerate(fields):
        e = batch.element(i)
        assert e.grid == f.grid and torch.equal(e.envelope, f.envelope) and e.carrier == f.carrier
        ny, nx = f.grid.shape
        assert torch.allclose(batch.total()[i, :ny, :nx], f.total(), rtol=0, atol=1e-12 * float(f.envelope.abs().max()))
        assert not bool(batch.envelope[i, ny:].abs().any()) and not bool(batch.envelope[i, :, nx:].abs().any())
    assert torch.allclose(batch.power(), torch.stack([f.power() for f in fields]), rtol=1e-14)


def test_batched_field_errors_are_clear():
    g = Grid((0.0, 0.0), P, (8, 8))
    u = torch.zeros(3, 8, 8)
    with pytest.raises(ValueError, match="wavelength has shape"):
        Field(u, g, [0.5, 0.6])
    with pytest.raises(ValueError, match="carrier"):
        Field(u, g, 0.5, carrier=[(0.1, 0.0)] * 2)
    with pytest.raises(ValueError, match="windows must be one Grid per batch element"):
        Field(u, g, 0.5, windows=(g, g))
    with pytest.raises(ValueError, match=r"windows\[1\]"):
        Field(u, g, 0.5, windows=(g, Grid((0.0, 0.0), 2e-3, (8, 8)), g))
    with pytest.raises(ValueError, match=r"windows\[2\]"):
        Field(u, g, 0.5, windows=(g, g, Grid((0.0, 0.0), P, (9, 8))))
    with pytest.raises(ValueError, match="pitch"):
        Field.stack([Field(torch.zeros(8, 8), g, 0.5), Field(torch.zeros(8, 8), Grid((0, 0), 2e-3, (8, 8)), 0.5)])
    f = Field(u, g, [0.5, 0.55, 0.6])
    out = Grid((0.0, 0.0), P, (5, 5))
    with pytest.raises(ValueError, match="propagate_batch"):
        propagate_window(f, out, 1.0)  # elements that differ: the batched path
    with pytest.raises(ValueError, match="one per field of the batch"):
        propagate_batch(f, [out, out], 1.0)
    with pytest.raises(ValueError, match=r"out\[1\]"):
        propagate_batch(f, [out, Grid((0.0, 0.0), P, (6, 5)), out], 1.0)
    with pytest.raises(ValueError, match="shift must have the shape"):
        propagate_batch(f, out, 1.0, shift=torch.zeros(3))
    other = batch_transfer(WindowBatch.of(f, out, 2.0))
    with pytest.raises(ValueError, match="another batch"):
        propagate_batch(f, out, 1.0, transfer=other)
    with pytest.raises(ValueError, match="crop an element"):
        Field.stack([Field(torch.zeros(8, 8), g, 0.5), Field(torch.zeros(6, 8), g.window(0, 6, 0, 8), 0.5)]).crop(
            0, 2, 0, 2)


def test_the_pre_issue_43_call_forms_raise_a_type_error_that_says_how_to_migrate():
    u = torch.zeros(8, 8, dtype=torch.complex128)
    with pytest.raises(TypeError, match=r"Field\(u, raywave.wave.Grid\(in_origin, pitch"):
        propagate_window(u, 1e-3, 0.5, 1.0, (0.0, 0.0), (0.0, 0.0), (4, 4))
    with pytest.raises(TypeError, match="window_transfer takes a Field"):
        window_transfer((8, 8), (4, 4), 1e-3, 0.5, 1.0, (0.0, 0.0), (0.0, 0.0))
    with pytest.raises(TypeError, match="propagate_batch takes a batched"):
        propagate_batch(u[None], None, (4, 4))
    from raywave.hybrid.coherent import exit_pupil_field, faithful_field

    for fn in (faithful_field, exit_pupil_field):
        with pytest.raises(TypeError, match="Source"):
            fn(None, None, (0.0, 0.0), 0.55, None)
