"""The DOE grid: geometry, windows on the oversampled simulation grid, apertures, modules."""

import math

import pytest
import torch

from raywave.doe import BlankDOE, PixelDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import ideal_lens


def test_pixel_centres_and_simulation_grid():
    doe = BlankDOE((4, 6), 0.01)
    assert doe.size == pytest.approx((0.06, 0.04))
    x0, y0 = doe.sim_origin(1)
    assert (x0, y0) == pytest.approx((-0.025, -0.015))  # pixel [0, 0] centre, grid centred on the axis
    x0q, y0q = doe.sim_origin(3)
    assert x0q == pytest.approx(-0.03 + 0.01 / 6)  # first sub-sample centre of the first DOE pixel


def test_windowed_phase_holds_each_doe_pixel_over_its_subsamples():
    ph = torch.arange(20, dtype=torch.float64).reshape(4, 5)
    doe = PixelDOE(ph, 0.01)
    full = doe.phase(0.55, oversample=3)
    assert full.shape == (12, 15)
    assert torch.equal(full, ph.repeat_interleave(3, 0).repeat_interleave(3, 1))
    win = doe.phase(0.55, (4, 2, 5, 7), oversample=3)
    assert torch.equal(win, full[4:9, 2:9])
    with pytest.raises(ValueError, match="outside the DOE"):
        doe.phase(0.55, (10, 0, 5, 5), oversample=3)


def test_design_wavelength_scales_the_phase_as_a_fixed_optical_path():
    doe = PixelDOE(torch.full((2, 2), 1.0), 0.01, design_wavelength=0.5)
    assert float(doe.phase(1.0)[0, 0]) == pytest.approx(0.5)
    assert float(PixelDOE(torch.ones(2, 2), 0.01).phase(1.0)[0, 0]) == 1.0


def test_circular_aperture_coverage_has_the_circle_area():
    doe = BlankDOE(400, 0.005, aperture="circle")
    cov = doe.coverage((0, 0, 400, 400))
    area = float(cov.sum()) * 0.005**2
    assert area == pytest.approx(math.pi * 1.0**2, rel=1e-4)
    assert float(cov.min()) == 0.0 and float(cov.max()) == 1.0


def test_bad_doe_arguments_are_errors():
    with pytest.raises(ValueError, match="aperture"):
        BlankDOE(10, 0.01, aperture="hexagon")
    with pytest.raises(ValueError, match="2-D"):
        PixelDOE(torch.zeros(3), 0.01)
    with pytest.raises(ValueError, match="shape"):
        BlankDOE((0, 4), 0.01)


def test_hybrid_lens_is_a_module_with_real_parameters():
    hl = HybridLens(ideal_lens(5.0, f_number=8), PixelDOE(torch.zeros(50, 50), 2e-3), 2.0)
    names = dict(hl.named_parameters())
    assert "doe.phase_map" in names and "lens.surfaces.0.interaction.focal_length" in names
    assert all(p.dtype == torch.float64 for p in hl.parameters())
    sd = hl.state_dict()
    hl2 = HybridLens(ideal_lens(5.0, f_number=8), PixelDOE(torch.ones(50, 50), 2e-3), 2.0)
    hl2.load_state_dict(sd)
    assert torch.equal(hl2.doe.phase_map, hl.doe.phase_map)
    assert hl.to("cpu") is hl and hl.doe.device.type == "cpu"
    assert torch.get_default_dtype() == torch.float32  # the library never changes the global default


def test_window_phasors_of_far_apart_windows_are_each_windows_phase():
    """A batch of windows far apart (a map's mirror images) takes each window's own phase instead of their union's;
    windows that overlap, or reach beyond the grid, take the union's: every path gives exp(iφ) of each window's phase
    (a pixel map and an analytic phase, oversampled)."""
    from raywave.doe.params import RadialDOE
    from raywave.utils.phasor import unit_phasor

    g = torch.Generator().manual_seed(4)
    does = [PixelDOE(torch.randn((300, 300), generator=g, dtype=torch.float64), 2e-3),
            RadialDOE(torch.linspace(0.0, 40.0, 64, dtype=torch.float64), 300, 2e-3, radius=0.3)]
    for doe in does:
        for corners in ([(10, 20), (400, 450), (10, 450), (400, 20)],  # far apart: per window
                        [(100, 100), (130, 110)],  # overlapping: the union
                        [(-5, 500), (300, 300)]):  # one beyond the grid: the union, edges repeated
            ph = doe.window_phasors(0.53, corners, (90, 80), 2)
            for (iy, ix), got in zip(corners, ph):
                if iy >= 0 and iy + 90 <= 600 and ix >= 0 and ix + 80 <= 600:
                    assert torch.equal(got, unit_phasor(doe.phase(0.53, (iy, ix, 90, 80), 2)))
