"""The DOE-plane field record on the value types (issue 17, part 1): every construction returns a
:class:`DOEField` that holds a :class:`raywave.wave.Field` on a sub-:class:`raywave.wave.Grid` of the DOE's
simulation grid, its half-open box there, and the diagnostics in their own :class:`FieldInfo`; the DOE's phase
is sampled on that Grid. The earlier flat names read through to the same values."""

import math

import pytest
import torch

from raywave.doe import BlankDOE, PixelDOE
from raywave.hybrid import HybridLens
from raywave.hybrid.coherent import DOEField, FieldInfo, lit_box
from raywave.lens.build import ideal_lens
from raywave.utils.phasor import unit_phasor
from raywave.wave import Field, Grid


def _hybrid(stop_edge="exit_pupil", aperture="square"):
    lens = ideal_lens(5.0, f_number=4.0, wavelengths=(0.55,))
    doe = PixelDOE(torch.randn((600, 600), generator=torch.Generator().manual_seed(3), dtype=torch.float64), 2.5e-3,
                   aperture=aperture)
    return HybridLens(lens, doe, 1.0, sensor_pitch=2e-3, stop_edge=stop_edge, oversample=2)


@pytest.mark.parametrize("stop_edge,mode,aperture", [("exit_pupil", "accurate", "square"),
                                                     ("doe", "accurate", "circle"),
                                                     ("doe", "faithful", "square")])
def test_every_construction_holds_a_field_on_the_doe_grid(stop_edge, mode, aperture):
    hl = _hybrid(stop_edge, aperture)
    kw = {"rays": 20_000} if mode == "faithful" else {}
    fds = hl.doe_fields([(0.0, 0.0), (0.0, 3.0)], [0.5, 0.6], mode=mode, **kw)
    sim = hl.doe.sim_grid(hl.oversample)
    for row in fds:
        for fd in row:
            assert isinstance(fd, DOEField) and isinstance(fd.field, Field) and isinstance(fd.info, FieldInfo)
            assert fd.envelope.dtype == torch.complex128  # coherent data in float64
            iy0, iy1, ix0, ix1 = fd.box
            assert fd.grid == sim.window(iy0, iy1, ix0, ix1)  # the box is half-open, on the DOE's grid
            assert sim.locate(fd.grid) == fd.box
            assert not hasattr(fd, "window") and not hasattr(DOEField, "on_window")  # the legacy rectangle is gone
            assert (fd.origin, fd.pitch, fd.wavelength, fd.carrier) == (fd.grid.origin, fd.grid.pitch[0],
                                                                        fd.field.wavelength, fd.field.carrier)
            assert fd.mode == fd.info.mode == mode and fd.stop_edge == fd.info.stop_edge == stop_edge
            # the DOE's phase sampled on the field's Grid is the one on its index window
            ph = hl.doe.phase(fd.wavelength, fd.grid, hl.oversample)
            assert torch.equal(ph, hl.doe.phase(fd.wavelength, (iy0, ix0, iy1 - iy0, ix1 - ix0), hl.oversample))
            assert ph.shape == fd.envelope.shape
            # DOE.modulate applies it; window_phasors gives the same factor for a batch of windows
            mod = hl.doe.modulate(fd.field, hl.oversample)
            assert mod.grid == fd.grid and torch.equal(mod.envelope, fd.envelope * unit_phasor(ph))
            bat = hl.doe.window_phasors(fd.wavelength, [(iy0, ix0)], fd.grid.shape, hl.oversample)
            # the same factor; the product may round differently in the last bit (vectorised complex multiply)
            torch.testing.assert_close(bat[0] * fd.envelope, mod.envelope, rtol=0, atol=1e-15)
            assert float(fd.power.detach()) > 0


def test_copies_keep_the_data_and_separate_the_diagnostics():
    hl = _hybrid()
    fd = hl.doe_fields([(0.0, 3.0)], [0.55])[0][0]
    assert fd.chief_tan is not None
    d = fd.detach()
    assert d.chief_tan is None and not d.envelope.requires_grad and d.box == fd.box
    d.clipped = 0.25  # diagnostics of a copy are its own
    assert fd.clipped != 0.25 and d.info.clipped == 0.25
    e = fd.with_info(stop_edge="doe")
    assert e.stop_edge == "doe" and fd.stop_edge == "exit_pupil" and e.field is fd.field
    c = fd.to(torch.complex64)
    assert c.envelope.dtype == torch.complex64 and c.grid == fd.grid
    with pytest.raises(ValueError, match="box"):
        DOEField(fd.field, (0, 1, 0, 1), fd.z, fd.center, fd.info)
    with pytest.raises(TypeError, match="Field"):
        DOEField(fd.envelope, fd.box, fd.z, fd.center, fd.info)


def test_lit_box_is_half_open_covering_and_clamped():
    grid = Grid((-1.0, -1.0), 0.1, (21, 21))  # samples at -1.0, -0.9, ..., 1.0
    iy0, iy1, ix0, ix1 = lit_box(grid, (-0.25, 0.31, 0.0, 0.0), 0.0)
    x, _ = grid.coordinates()
    assert float(x[ix0]) <= -0.25 + 1e-12 and float(x[ix1 - 1]) >= 0.31 - 1e-12  # covers the box
    assert float(x[ix0 + 1]) > -0.25 and float(x[ix1 - 2]) < 0.31  # and no more
    assert lit_box(grid, (-5.0, 5.0, -5.0, 5.0), 0.0) == (0, 21, 0, 21)  # clamped to the grid
    assert lit_box(grid, (3.0, 4.0, 0.0, 0.0), 0.5) is None  # misses it
    # x 0.95 … 1.55 and y −0.25 … 0.25: samples 19.5 … and 7.5 … 12.5 rounded outward, x clamped at the end
    assert lit_box(grid, (1.2, 1.3, 0.0, 0.0), 0.25) == (7, 14, 19, 21)


def test_doe_windows_are_checked_in_either_form():
    doe = BlankDOE(10, 1e-2)
    sim = doe.sim_grid(2)
    assert sim.shape == (20, 20) and math.isclose(sim.pitch[0], 5e-3)
    assert doe.sim_window(sim.window(2, 5, 3, 9), 2) == (2, 3, 3, 6)
    assert doe.sim_window(None, 2) == (0, 0, 20, 20)
    with pytest.raises(ValueError, match="not on this grid"):
        doe.sim_window(sim.translated(1e-3, 0.0).window(0, 2, 0, 2), 2)
    with pytest.raises(ValueError, match="outside the DOE simulation grid"):
        doe.phase(0.55, (15, 0, 10, 2), 2)
    with pytest.raises(ValueError, match="pitch"):
        doe.coverage(Grid(sim.origin, 1e-3, (2, 2)), 2)
