"""The sampled-field value types (raywave.wave.grid: Grid, Field), the Field-level propagation, and the
compact WindowTransfer that window_transfer returns (issue 17)."""

import math
import sys
from pathlib import Path

import pytest
import torch

from raywave.wave import (Field, Grid, WindowTransfer, angular_spectrum, angular_spectrum_field, field_transfer,
                          propagate_field)

sys.path.insert(0, str(Path(__file__).parent))
from window_calls import transfer as _wt, window as _pw  # noqa: E402

LAM = 0.55


def test_grid_normalises_and_validates():
    g = Grid((0.1, -0.2), 1e-3, (4, 5))
    assert g.pitch == (1e-3, 1e-3) and g.shape == (4, 5) and isinstance(g.shape[0], int)
    assert Grid(torch.tensor([0.1, -0.2], dtype=torch.float64), (1e-3, 2e-3), [4.0, 5]).origin == (0.1, -0.2)
    for bad in (((0, 0), 0.0, (4, 5)), ((0, 0), 1e-3, (0, 5)), ((0, 0), 1e-3, (4,)), ((0,), 1e-3, (4, 5)),
                      ((0, math.inf), 1e-3, (4, 5)), ((0, 0), 1e-3, (4.5, 5))):
        with pytest.raises(ValueError, match="Grid"):
            Grid(*bad)
    with pytest.raises(Exception):
        g.shape = (1, 1)  # frozen


def test_grid_index_world_round_trips_and_half_open_windows():
    g = Grid((0.25, -0.5), (2e-3, 3e-3), (10, 20))
    x, y = g.position(3, 7)
    assert (x, y) == pytest.approx((0.25 + 7 * 2e-3, -0.5 + 3 * 3e-3))
    assert g.index_of(x, y) == pytest.approx((3, 7))
    xs, ys = g.coordinates()
    assert xs.shape == (20,) and ys.shape == (10,) and float(xs[7]) == pytest.approx(x) and float(ys[3]) == pytest.approx(y)
    assert g.extent == pytest.approx((0.25 - 1e-3, 0.25 + 19.5 * 2e-3, -0.5 - 1.5e-3, -0.5 + 9.5 * 3e-3))
    w = g.window(2, 6, 5, 20)  # rows 2..5, columns 5..19
    assert w.shape == (4, 15) and w.origin == pytest.approx(g.position(2, 5))
    assert g.locate(w) == (2, 6, 5, 20)
    for box in ((2, 2, 0, 1), (0, 11, 0, 1), (-1, 3, 0, 1)):
        with pytest.raises(ValueError, match="half-open"):
            g.window(*box)
    with pytest.raises(ValueError, match="not on this grid"):
        g.locate(w.translated(1e-4, 0.0))
    with pytest.raises(ValueError, match="pitch"):
        g.locate(Grid(w.origin, 1e-3, w.shape))


def test_field_validates_and_crops():
    g = Grid((0.0, 0.0), 1e-3, (6, 8))
    f = Field(torch.ones(2, 6, 8, dtype=torch.float64), g, LAM, carrier=(0.1, 0.0))
    assert f.envelope.dtype == torch.complex128 and f.carrier == (0.1, 0.0)
    assert Field(torch.ones(6, 8, dtype=torch.float32), g, LAM).envelope.dtype == torch.complex64
    c = f.crop(1, 4, 2, 8)
    assert c.envelope.shape == (2, 3, 6) and c.grid == g.window(1, 4, 2, 8) and c.wavelength == LAM
    assert torch.allclose(f.power(), torch.full((2,), 48 * 1e-6, dtype=torch.float64))
    # the true field carries exp(i 2π n α x/λ)
    x, _ = g.coordinates()
    expect = torch.polar(torch.ones(8, dtype=torch.float64), 2 * math.pi * 0.1 * x / (LAM * 1e-3))
    assert torch.allclose(f.total()[0, 3], expect)
    for kw, word in (({"wavelength": 0.0}, "wavelength"), ({"n": -1.0}, "n must"), ({"carrier": (0.8, 0.8)}, "carrier")):
        with pytest.raises(ValueError, match=word):
            Field(torch.ones(6, 8), g, **{"wavelength": LAM, **kw})
    with pytest.raises(ValueError, match="grid's shape"):
        Field(torch.ones(6, 7), g, LAM)
    with pytest.raises(TypeError, match="Grid"):
        Field(torch.ones(6, 8), (0, 0), LAM)


def _gauss(g: Grid, w0: float, centre=(0.0, 0.0)) -> torch.Tensor:
    x, y = g.coordinates()
    return torch.exp(-(((x[None, :] - centre[0]) ** 2 + (y[:, None] - centre[1]) ** 2) / w0**2)).to(torch.complex128)


def test_propagate_field_is_propagate_window_and_a_tilted_beam_walks_by_z_tan_theta():
    """A Gaussian envelope with carrier α: after z its centre sits at z·α/sqrt(1 − α²) (geometric walk-off)."""
    p, z, alpha = 2e-3, 1.0, 0.02
    g = Grid((-0.063, -0.063), p, (64, 64))
    f = Field(_gauss(g, 0.02), g, LAM, carrier=(alpha, 0.0))
    walk = z * alpha / math.sqrt(1 - alpha**2)
    out = Grid((walk - 0.063, -0.063), p, (64, 64))
    res = propagate_field(f, z, out)
    ref = _pw(f.envelope, p, LAM, z, g.origin, out.origin, out.shape, carrier=(alpha, 0.0))
    assert res.grid == out and res.carrier == f.carrier and torch.equal(res.envelope, ref)
    inten = res.envelope.abs() ** 2
    x, _ = out.coordinates()
    xc = float((inten.sum(0) * x).sum() / inten.sum())
    assert xc == pytest.approx(walk, abs=0.05 * p)
    t = field_transfer(f, z, out)
    assert torch.equal(propagate_field(f, z, out, transfer=t).envelope, ref)
    with pytest.raises(ValueError, match="pitch"):
        propagate_field(f, z, Grid(out.origin, 1e-3, out.shape))
    with pytest.raises(ValueError, match="carrier"):
        angular_spectrum_field(f, z)
    f0 = Field(_gauss(g, 0.02), g, LAM)
    assert torch.equal(angular_spectrum_field(f0, z).envelope, angular_spectrum(f0.envelope, p, LAM, z))


def test_window_transfer_keeps_its_tuple_form_and_the_band_path_matches_the_full_grid():
    u = _gauss(Grid((0.0, 0.0), 1e-3, (40, 36)), 0.01, (0.018, 0.02))
    args = (u.shape, (21, 23), 1e-3, LAM, 0.8, (0.0, 0.0), (0.03, 0.01), 1.0, (0.02, -0.01))
    for wd in (False, True):
        t = _wt(*args, weight_derivative=wd)
        assert isinstance(t, WindowTransfer) and len(t) == (3 if wd else 2)
        g, size, *rest = t
        assert g.shape == size and t[1] == size and t[-1 if not wd else -2] == size
        # the band holds every non-zero of the full G (and R)
        mask = torch.zeros(size, dtype=torch.bool)
        mask[t.rows[:, None], t.cols[None, :]] = True
        assert not bool(g[~mask].abs().any()) and torch.equal(g[mask].reshape(t.band.shape), t.band)
        if wd:
            assert rest[0].shape == (3, *size) and not bool(rest[0][:, ~mask].abs().any())
        band = _pw(u, 1e-3, LAM, 0.8, (0.0, 0.0), (0.03, 0.01), (21, 23), carrier=(0.02, -0.01),
                                transfer=t)
        full = _pw(u, 1e-3, LAM, 0.8, (0.0, 0.0), (0.03, 0.01), (21, 23), carrier=(0.02, -0.01),
                                transfer=tuple(t))
        assert torch.allclose(band, full, rtol=0, atol=1e-14 * float(full.abs().max()))
