"""The precision study (paper Fig. S2): float32 tracing breaks the DOE-plane phase, float64 does not.

References are analytic: a perfect lens delivers a spherical wave to its focus, and light from a point
source through a flat air gap has the optical path of the straight line from the source."""

import math

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.hybrid.precision import ray_phase_error
from raywave.lens.build import ideal_lens
from raywave.lens.lens import Lens
from raywave.materials import get_material
from raywave.surfaces.aperture import CircularAperture
from raywave.surfaces.geometry import Plane
from raywave.surfaces.surface import Surface

LAM = 0.55
K = 2 * math.pi / (LAM * 1e-3)


def test_float64_phase_at_the_doe_matches_the_perfect_spherical_wave():
    f, z_doe = 10.0, 6.0
    lens = ideal_lens(f, f_number=4, wavelengths=(LAM,))
    r = ray_phase_error(lens, z_doe, (0.0, 0.0), LAM, n=65, dtype=torch.float64)
    # every ray reaches the focus (0, 0, f) with the same optical path: OPL(P) = C − |F − P|
    dist = torch.sqrt(r["xy"].pow(2).sum(-1) + (f - z_doe) ** 2)
    resid = K * (r["opl64"] + dist)
    resid = resid - resid.mean()
    assert float(resid.abs().max()) < 1e-6  # rad


@pytest.fixture(scope="module")
def air_gap():
    """A flat window of air: the OPL from a point source is the straight-line distance."""
    s = Surface(Plane(), get_material("AIR"), 5.0, aperture=CircularAperture(1.0), is_stop=True)
    return Lens([s], wavelengths=(LAM,), primary=0, object_distance=1e4)


def test_float32_tracing_loses_radians_of_phase_at_a_10_m_object_while_float64_keeps_it(air_gap):
    z_doe, depth = 3.0, 1e4
    exact = {}
    for dt in (torch.float32, torch.float64):
        r = ray_phase_error(air_gap, z_doe, (0.0, 0.0), LAM, n=65, dtype=dt, depth=depth)
        d = torch.sqrt(r["xy"].pow(2).sum(-1) + (z_doe + depth) ** 2)
        resid = K * (r["opl"] - d)
        exact[dt] = float((resid - resid.mean()).abs().max())
    assert exact[torch.float64] < 1e-5  # rad
    assert exact[torch.float32] > 0.1  # rad, from ray to ray: not a smooth error


def test_float32_tracing_breaks_the_phase_of_a_real_lens():
    """The bundled asphere, object at 10 m: float32 loses radians (measured RMS ≈ 5.9 rad, max ≈ 16 rad);
    the error grows with the optical path (≈ 0.07 rad RMS at 0.1 m, 0.5 rad at 1 m)."""
    from raywave.lens.build import bundled_lens_path, load_lens

    lens = load_lens(bundled_lens_path("asphere_hk51"))
    z_doe = float(lens.vertex_z()[-1].detach()) + 0.7
    rms = [ray_phase_error(lens, z_doe, (0.0, 0.0), 0.55, n=65, depth=d)["rms"] for d in (1e2, 1e3, 1e4)]
    assert rms[0] < rms[1] < rms[2]
    assert rms[2] > 1.0


def test_float32_tracing_changes_the_psf_float64_does_not():
    lens = ideal_lens(5.0, f_number=8, wavelengths=(LAM,), object_distance=1e4)
    hl = HybridLens(lens, BlankDOE(500, 2e-3), 2.0, sensor_pitch=2e-3)
    kw = dict(ks=24, mode="faithful", rays=60_000, depth=1e4)
    p64 = hl.psf((0, 0), LAM, generator=torch.Generator().manual_seed(0), **kw)
    p64b = hl.psf((0, 0), LAM, generator=torch.Generator().manual_seed(0), **kw)
    p32 = hl.psf((0, 0), LAM, generator=torch.Generator().manual_seed(0), trace_dtype=torch.float32, **kw)
    assert torch.equal(p64, p64b)  # replayable
    assert float((p32 - p64).abs().sum()) > 0.1


def test_accurate_mode_refuses_single_precision():
    hl = HybridLens(ideal_lens(5.0, f_number=8), BlankDOE(100, 2e-3), 2.0)
    with pytest.raises(ValueError, match="float64"):
        hl.psf((0, 0), LAM, trace_dtype=torch.float32)
