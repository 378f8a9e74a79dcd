"""Issue 43: the batched field stage's envelopes kept as rows of their batch (:class:`~raywave.hybrid.coherent.record.
EnvelopeRow`, :meth:`~raywave.hybrid.coherent.record.DOEField.deferred`) and what reads them batched: the
propagation's padded windows (:func:`raywave.hybrid.batched._gathered_rows`), the darkness test
(:func:`raywave.hybrid.hybrid_lens._dark_many`) and the mirror images (:func:`raywave.hybrid.mirror.mirror_fields`).
Each must give exactly (``torch.equal``) what the one-field-at-a-time code gives on the made envelope."""

import torch

from raywave.hybrid.batched import _gathered_rows
from raywave.hybrid.coherent.record import DOEField, EnvelopeRow, FieldInfo
from raywave.hybrid.hybrid_lens import _dark, _dark_many
from raywave.hybrid.mirror import mirror_field, mirror_fields
from raywave.wave.grid import Grid


def _base(seed: int, shape=(3, 7, 9)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.complex(torch.randn(shape, generator=g, dtype=torch.float64),
                         torch.randn(shape, generator=g, dtype=torch.float64))


def _deferred(row: EnvelopeRow, sim: Grid, at=(2, 3)) -> DOEField:
    a, b = row.shape
    box = (at[0], at[0] + a, at[1], at[1] + b)
    grid = Grid(sim.position(box[0], box[2]), sim.pitch, (a, b))
    centre = (torch.tensor(0.25, dtype=torch.float64), torch.tensor(-0.5, dtype=torch.float64))
    return DOEField.deferred(row, grid, (0.55, 1.0, (0.01, -0.02)), box, 10.0, centre, FieldInfo(5, "accurate"))


def test_an_envelope_row_is_its_batch_rows_corner_flipped_as_asked():
    base = _base(0)
    for flip in ((False, False), (True, False), (False, True), (True, True)):
        row = EnvelopeRow(base, 1, (4, 6), flip)
        ref = base[1, :4, :6]
        dims = [d for d, on in ((-1, flip[0]), (-2, flip[1])) if on]
        assert torch.equal(row.make(), ref.flip(dims) if dims else ref)
    assert EnvelopeRow(base, 1, (4, 6)).flipped(True, True).flipped(True, False).flip == (False, True)


def test_gathered_rows_equal_each_envelope_padded_and_stacked():
    b0, b1 = _base(1), _base(2, (2, 5, 8))
    rows = [EnvelopeRow(b0, 2, (5, 9)), EnvelopeRow(b1, 0, (3, 8), (True, False)), EnvelopeRow(b0, 0, (7, 2)),
            EnvelopeRow(b1, 1, (5, 4), (True, True)), EnvelopeRow(b0, 1, (1, 1), (False, True))]
    shape = (8, 11)
    ref = torch.stack([torch.nn.functional.pad(e, (0, shape[1] - e.shape[-1], 0, shape[0] - e.shape[-2]))
                       for e in (r.make() for r in rows)])
    assert torch.equal(_gathered_rows(rows, shape), ref)
    assert torch.equal(_gathered_rows(rows[:1], shape), ref[:1])  # one base: no reorder


def test_dark_many_of_rows_equals_each_fields_test():
    base = _base(3)
    base[1] = 0.0
    base[2, :3, :4] = 0.0  # dark in its own corner, lit beyond it (the padding is not the field's)
    sim = Grid((-1.0, -1.0), (0.01, 0.01), (40, 40))
    fds = [_deferred(EnvelopeRow(base, t, s), sim) for t, s in ((0, (4, 5)), (1, (7, 9)), (2, (3, 4)), (2, (4, 4)))]
    assert _dark_many(fds) == [_dark(fd) for fd in fds] == [False, True, True, False]


def test_a_deferred_record_reads_without_making_its_envelope_and_mirrors_as_the_made_one():
    base = _base(4)
    sim = Grid((-0.2, -0.2), (0.01, 0.01), (40, 40))
    fd = _deferred(EnvelopeRow(base, 2, (5, 6)), sim)
    assert fd.grid.shape == (5, 6) and fd.wavelength == 0.55 and fd.carrier == (0.01, -0.02)
    assert fd._field is None and fd.device == base.device
    kept = fd.with_info(stop_edge="exit_pupil")
    assert kept._field is None and kept.stop_edge == "exit_pupil"
    assert torch.equal(fd.envelope, base[2, :5, :6])
    eager = DOEField(fd.field, fd.box, fd.z, fd.center, FieldInfo(5, "accurate"))  # a made record: flipped now
    for flips in ((True, False), (False, True), (True, True), (False, False)):
        got, ref = mirror_field(fd, sim, *flips), mirror_field(eager, sim, *flips)
        assert got._field is None and torch.equal(got.envelope, ref.envelope)
        assert got.box == ref.box and got.carrier == ref.carrier and got.grid.origin == ref.grid.origin
        assert all(torch.equal(a, b) for a, b in zip(got.center, ref.center))


def test_mirror_fields_negate_the_centres_as_each_fields_own():
    base = _base(5)
    sim = Grid((-0.2, -0.2), (0.01, 0.01), (40, 40))
    fds = [_deferred(EnvelopeRow(base, t, (4, 5)), sim, (t, 2 * t)) for t in range(3)]
    todo = [(fds[0], True, False), (fds[1], False, True), (fds[2], True, True), (fds[0], False, False)]
    for got, (fd, fx, fy) in zip(mirror_fields(todo, sim), todo):
        ref = mirror_field(fd, sim, fx, fy)
        assert all(torch.equal(a, b) for a, b in zip(got.center, ref.center))
        assert got.box == ref.box and torch.equal(got.envelope, ref.envelope)


def test_padded_stack_zeroes_the_padding():
    """padded_stack (issue 43: only the padding zeroed, no zero fill of the whole batch first): each envelope in its
    corner and exact zeros elsewhere (the batch is allocated empty), padded along rows, columns and both; its
    gradient each envelope's corner of the batch's."""
    from raywave.hybrid.batched import padded_stack

    envs = [_base(s, shape)[0] for s, shape in ((1, (1, 7, 9)), (2, (1, 4, 11)), (3, (1, 8, 3)))]
    shape = (8, 11)
    got = padded_stack(envs, shape)
    want = torch.zeros((3, *shape), dtype=envs[0].dtype)
    for i, e in enumerate(envs):
        want[i, :e.shape[0], :e.shape[1]] = e
    assert torch.equal(got, want)
    leaves = [e.clone().requires_grad_() for e in envs]
    out = padded_stack(leaves, shape)
    w = _base(9, (3, *shape))
    grads = torch.autograd.grad((out * w).real.sum(), leaves)
    for i, (e, gr) in enumerate(zip(envs, grads)):
        assert torch.equal(gr, w[i, :e.shape[0], :e.shape[1]].conj())


def test_a_made_cpu_records_mirror_image_is_flipped_where_it_is_read():
    """Issue 47 (h47p): on a CPU without autograd a made record's mirror image is deferred (no flipped copy of its
    own); the propagation's padded stack copies its row in reverse (:meth:`EnvelopeRow.copy_into`) and the darkness
    test reads it unflipped: the values of the flipped envelope exactly, for every flip, from a contiguous and from
    a strided envelope. With autograd the image is flipped at once (its graph through the flip)."""
    from raywave.hybrid.batched import padded_stack

    sim = Grid((-0.2, -0.2), (0.01, 0.01), (40, 40))
    for env in (_base(6)[1, :5, :7].contiguous(), _base(7)[2, 1:6, ::2]):  # contiguous, strided (5, 5)
        fd = DOEField.on_box(env, (3, 3 + env.shape[0], 4, 4 + env.shape[1]), sim, (0.55, 1.0, (0.01, -0.02)),
                             10.0, (0.1, -0.3), FieldInfo(5, "accurate"))
        made = [env]
        for flips in ((True, False), (False, True), (True, True)):
            dims = [d for d, on in ((-1, flips[0]), (-2, flips[1])) if on]
            got = mirror_field(fd, sim, *flips)
            assert got.pending_row is not None
            made.append(env.flip(dims))
            stack = padded_stack([got.pending_row, env, _base(8)[0]], (9, 10))
            want = padded_stack([env.flip(dims), env, _base(8)[0]], (9, 10))
            assert torch.equal(stack, want)
            assert _dark_many([fd, got]) == [False, False]
            assert torch.equal(got.envelope, env.flip(dims)) and got.pending_row is None  # made when read
        dark = DOEField.on_box(torch.zeros_like(env), fd.box, sim, (0.55, 1.0, (0.0, 0.0)), 10.0, (0.0, 0.0),
                               FieldInfo(5, "accurate"))
        assert _dark_many([fd, mirror_field(dark, sim, True, True)]) == [False, True]
    leaf = _base(9)[0, :4, :6].clone().requires_grad_()
    fd = DOEField.on_box(leaf, (0, 4, 0, 6), sim, (0.55, 1.0, (0.0, 0.0)), 10.0, (0.0, 0.0), FieldInfo(5, "accurate"))
    img = mirror_field(fd, sim, True, False)
    assert img.pending_row is None and img.envelope.requires_grad
    assert torch.equal(img.envelope.detach(), leaf.detach().flip(-1))
