"""Issue 43: the adaptive edge step's edge-focus test (:func:`raywave.hybrid.coherent.exit_pupil.edge_focus_many`)
is traced once for all of a call's sources, in the call's shared geometry, instead of once per source; each source
gets the values and the choice its own call gives."""

import math

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.hybrid.coherent import exit_pupil
from raywave.lens.build import bundled_lens_path, load_lens

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")


def _ideal_lens():
    """An ideal thin lens (f 10 mm, the stop on it, radius 0.4 mm), the sensor at its focus: a spherical wave at
    the stop's edge for every field (the adaptive step cuts the edge on the DOE plane)."""
    from raywave.lens.lens import Lens
    from raywave.materials import Air
    from raywave.surfaces.aperture import CircularAperture
    from raywave.surfaces.geometry import Plane
    from raywave.surfaces.interaction import IdealLens
    from raywave.surfaces.surface import Surface

    return Lens([Surface(Plane(), Air(), 10.0, aperture=CircularAperture(0.4), interaction=IdealLens(10.0),
                         is_stop=True)], wavelengths=(0.55,), primary=0, fields=(0.0, 1.0))


def test_edge_focus_of_many_sources_is_each_sources_own():
    """One trace for 4 fields × 3 wavelengths of the bundled asphere gives each source's (waves, focus z, NA, n)
    of its own call to the aiming's rounding."""
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    fields = torch.tensor([[0.0, 0.0], [0.0, 8.0], [5.0, 12.0], [0.0, 17.5]], dtype=torch.float64)
    wls = [0.47, 0.53, 0.66]
    many = exit_pupil.edge_focus_many(lens, fields, wls, None)
    assert len(many) == 4 and all(len(row) == 3 for row in many)
    for i in range(4):
        for j, wl in enumerate(wls):
            own = exit_pupil.edge_focus_many(lens, fields[i], [wl], None)[0][0]
            assert own == pytest.approx(many[i][j], rel=1e-9, abs=1e-12)
            assert math.isfinite(own[0]) and own[0] > 0.01  # an aspheric singlet: not a sphere at its edge
    assert exit_pupil.edge_aberration(lens, (0.0, 17.5), 0.53, None) == pytest.approx(many[3][1][0], rel=1e-9)


def test_a_psf_call_traces_the_edge_focus_once_and_keeps_each_sources_step(monkeypatch):
    """HybridLens (blank DOE, default adaptive edge step): a call of 3 fields × 2 wavelengths runs the edge-focus
    trace once (not per source) and every source's choice is its own ("doe" on the ideal lens's spherical wave);
    each PSF equals the one its own call gives."""
    lens = _ideal_lens()
    hl = HybridLens(lens, BlankDOE(900, 1e-3), 5.0, sensor_pitch=2e-3, mirror=False)
    fields = [(0.0, 0.0), (0.0, 0.5), (0.3, 0.5)]
    wls = [0.5, 0.6]
    calls = []
    real = exit_pupil.edge_focus_many
    monkeypatch.setattr(exit_pupil, "edge_focus_many", lambda *a, **k: calls.append(a[1]) or real(*a, **k))
    with torch.no_grad():
        geo = hl._accurate_geometry(hl._engine_fields(fields), wls, None)
        assert geo.edge[3] == [["doe", "doe"]] * 3
        calls.clear()
        psf = hl.psf(fields, wls, ks=16)
        assert len(calls) == 1 and torch.as_tensor(calls[0]).reshape(-1, 2).shape[0] == 3
        for i, f in enumerate(fields):
            own = hl.psf(f, wls, ks=16)
            assert float((own[0] - psf[i]).abs().max()) < 1e-12
    # the choice follows the sensor: 0.3 mm out of focus, the sphere's cut plane matters
    assert exit_pupil.adaptive_edge_steps(lens, hl.doe, torch.tensor(fields), wls, None,
                                          (hl.doe_z(), hl.sensor_z() - 0.3)) == [["fresnel", "fresnel"]] * 3


def test_parallel_edge_rays_have_no_focus_and_take_the_fresnel_step():
    """A lens without power (one flat window, the stop on it): the edge rays are parallel, the point closest to all
    of them is undefined; the edge is no sphere (inf waves, no focus), the adaptive step keeps the Fresnel step and
    the PSF is finite (was: a raw LinAlgError from a singular solve, a fuzzed lens file)."""
    from raywave.lens.lens import Lens
    from raywave.materials import Air
    from raywave.surfaces.aperture import CircularAperture
    from raywave.surfaces.geometry import Plane
    from raywave.surfaces.surface import Surface

    lens = Lens([Surface(Plane(), Air(), 10.0, aperture=CircularAperture(0.4), is_stop=True)], wavelengths=(0.55,),
                primary=0, fields=(0.0, 1.0))
    (row,) = exit_pupil.edge_focus_many(lens, [[0.0, 0.0]], [0.55], None)
    assert row[0] == (math.inf, None, None, None)
    hl = HybridLens(lens, BlankDOE(1200, 1e-3), 5.0)
    assert exit_pupil.adaptive_edge_step(lens, hl.doe, (0.0, 0.0), 0.55, None, float(hl.doe_z()),
                                         float(hl.sensor_z())) == "fresnel"
