"""The construction's window choices read their bounds from the device once (issue 43: a GPU stalls at every host
read), with the values of the ``nonzero``-based forms they replace, on random, empty, full and single-sample masks."""

import torch

from raywave.hybrid.coherent.geometry import _crop_to_lit, _near_nodes


def _crop_ref(weight):
    rows = torch.nonzero(weight.amax(1) > 0).squeeze(1)
    cols = torch.nonzero(weight.amax(0) > 0).squeeze(1)
    if rows.numel() == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _near_ref(keep, pos_y, pos_x, margin=3):
    rows = torch.nonzero(keep.any(1)).squeeze(1)
    cols = torch.nonzero(keep.any(0)).squeeze(1)
    if rows.numel() == 0:
        return None

    def span(pos, lo, hi):
        inside = torch.nonzero((pos >= lo - margin) & (pos <= hi + margin)).squeeze(1)
        return (int(inside[0]), int(inside[-1]) + 1) if inside.numel() else None

    ys, xs = span(pos_y, int(rows[0]), int(rows[-1])), span(pos_x, int(cols[0]), int(cols[-1]))
    return None if ys is None or xs is None else (ys, xs)


def _masks(g):
    yield torch.zeros(7, 9, dtype=torch.bool)
    yield torch.ones(7, 9, dtype=torch.bool)
    one = torch.zeros(7, 9, dtype=torch.bool)
    one[6, 0] = True
    yield one
    for p in (0.02, 0.1, 0.5):
        for _ in range(20):
            yield torch.rand(7, 9, generator=g) < p


def test_crop_to_lit_equals_the_nonzero_form():
    g = torch.Generator().manual_seed(0)
    for m in _masks(g):
        w = torch.rand(m.shape, generator=g, dtype=torch.float64) * m
        assert _crop_to_lit(w) == _crop_ref(w)


def test_near_nodes_equals_the_nonzero_form():
    g = torch.Generator().manual_seed(1)
    for m in _masks(g):
        for lo, hi in ((-2.0, 10.0), (3.0, 5.5), (20.0, 30.0), (-9.0, -4.5)):  # spans inside, partly, outside
            pos_y = torch.linspace(lo, hi, 31, dtype=torch.float64)
            pos_x = torch.linspace(lo - 1.0, hi + 2.0, 40, dtype=torch.float64)
            assert _near_nodes(m, pos_y, pos_x) == _near_ref(m, pos_y, pos_x)


def test_the_nyquist_warning_names_the_worst_lit_sample():
    """One host read for the three values; the warning's numbers as before: the worst lit sample, not a dark one."""
    import warnings

    from raywave.hybrid.coherent.geometry import _warn_nyquist
    from raywave.hybrid.coherent.record import SamplingWarning

    ratio = torch.tensor([[0.5, 3.0], [1.5, 0.2]], dtype=torch.float64)
    lit = torch.tensor([[True, False], [True, True]])
    xy = torch.arange(8, dtype=torch.float64).reshape(2, 2, 2)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        _warn_nyquist(ratio, lit, xy, [0.0, 1.0], 0.55, 1e-3)  # worst lit: 1.5 at (4, 5)
        _warn_nyquist(ratio, torch.zeros_like(lit), xy, [0.0, 1.0], 0.55, 1e-3)  # nothing lit: silent
        _warn_nyquist(ratio * 0.1, lit, xy, [0.0, 1.0], 0.55, 1e-3)  # below Nyquist: silent
    assert len(got) == 1 and issubclass(got[0].category, SamplingWarning)
    assert "1.50× the Nyquist" in str(got[0].message) and "(x, y) = (4, 5)" in str(got[0].message)
