"""The weak diffraction orders of a mid-system DOE with the exact stop edge (issue 46): their edge waves in the PSF
crop (:class:`raywave.hybrid.midsystem._CropRims`) and their absolute phases read over the pupil
(:func:`raywave.hybrid.midsystem._pupil_phase`), on the two-lens system of tests/wave_truth_doe.py with the 16-level
Fresnel DOE (f 50 mm): order −15 (0.44 % of the light) is wide on the sensor where order 1 focuses, and its stop rim
is imaged with aberrations (the DOE's −15 × power is a −3.3 mm lens)."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import midsystem_systems as M  # noqa: E402
import wave_truth_doe as W  # noqa: E402

from raywave.doe.params import FresnelDOE  # noqa: E402
from raywave.hybrid.coherent import stop_rim_images_all  # noqa: E402
from raywave.hybrid.midsystem import (DOEPhaseSurface, MidSystemLens, _absolute_phase, _CropRims,  # noqa: E402
                                      _pupil_phase, order_coefficients)
from raywave.lens.sources import point_source_rays  # noqa: E402

N, PITCH, PS, KS = 1000, 1e-3, 2e-3, 32
LAM = 0.55


def _system(field, **kw):
    doe = FresnelDOE(50.0, N, PITCH, wavelength=LAM)
    doe.fabricate(16)
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    ml = MidSystemLens(M.two_lens(sys_), doe, 0, sys_.gap1, final_distance=0.01, final_size=N * PITCH,
                       final_pitch=PITCH, sensor_pitch=PS, min_efficiency=0.0, **kw)
    return sys_, doe, ml


def _path_by_sources(optics, field, theta, q):
    """The optical path from the source through each rim point (azimuths ``theta``) to the sensor point ``q`` (x, y,
    z), by other machinery than :class:`_CropRims`: the ray of ANOTHER source through the rim point (the rays that
    the rim point diffracts are those of all sources through it), Newton over that source's field angle until it
    meets ``q``; its path from the rim point on, plus the source's own path to the rim point."""
    wl = torch.tensor([LAM], dtype=torch.float64)
    k = theta.numel()
    idx = torch.arange(k)
    s = optics.stop_index

    def trace(fl):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rays = point_source_rays(optics, fl, wl, pupil=(torch.cos(theta), torch.sin(theta)), aim="full")
            at = optics.trace(rays, stop=s + 1, apertures=False)
            out = optics.trace(at, start=s + 1, apertures=False).propagate_to_z(q[2], 1.0)
        return out.o[idx, 0, idx, :2], out.opl[idx, 0, idx], at.opl[idx, 0, idx]

    with torch.no_grad():
        f0 = torch.tensor(field, dtype=torch.float64).expand(k, 2).clone()
        own = trace(f0)[2]
        f = f0.clone()
        for _ in range(10):
            h, _, _ = trace(f)
            e = 1e-4
            jac = torch.stack([(trace(f + torch.tensor([e, 0.0]))[0] - h) / e,
                               (trace(f + torch.tensor([0.0, e]))[0] - h) / e], -1)
            f = f - torch.linalg.solve(jac, (h - torch.tensor(q[:2]))[..., None])[..., 0]
        h, opl, at_rim = trace(f)
    assert float((h - torch.tensor(q[:2])).abs().max()) < 1e-9
    return own + opl - at_rim


@pytest.mark.parametrize("field", [(0.0, 0.0), (0.0, 1.5)])
def test_crop_rims_reproduce_the_diffracted_path(field):
    """Order −15: the path of the edge wave from each rim image to the crop's centre (order 1's focus),
    ``Φ_E + n|Q − E|``, against the path of the diffracted ray traced from the rim point to it (aimed by another
    source's field angle): the traced rim images (the tangential focus, z −1.823 mm on axis) are 0.373 wave off on
    axis (the edge wave's rings reversed) and 0.12 … 0.88 wave at 1.5°; the crop rims (z −2.069 mm on axis) 9e-9 /
    4.5e-7 wave; and they stay on the rim rays (the edge where geometric optics puts it)."""
    _, _, ml = _system(field, orders=[1, -15])
    one = ml.order_lens(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        q = (*[float(v) for v in one.doe_fields([field], [LAM])[0][0].center], one.sensor_z())
    hl = ml.order_lens(-15.0)
    optics = hl.optics
    f = torch.tensor([field], dtype=torch.float64)
    rim = stop_rim_images_all(optics, f, [LAM], None)[0][0]
    moved = _CropRims(q[:2], q[2]).one(optics, f[0], LAM, None, rim)
    assert moved is not rim
    truth = _path_by_sources(optics, field, rim[0], q)
    qt = torch.tensor(q, dtype=torch.float64)

    def waves(r):
        return ((r.opl + torch.linalg.vector_norm(qt - r.points, dim=-1) - truth) / (LAM * 1e-3)).detach()

    before, after = waves(rim), waves(moved)
    if field == (0.0, 0.0):
        assert 0.3 < float(before.abs().min()) and float(before.abs().max()) < 0.45  # measured 0.374
    assert float(after.abs().max()) < 1e-6
    # the moved images lie on the rim rays: the source's own rays through the rim points pass through them
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rays = point_source_rays(optics, f, torch.tensor([LAM], dtype=torch.float64),
                                 pupil=(torch.cos(rim[0]), torch.sin(rim[0])), aim="full")
        out = optics.trace(rays, apertures=False).propagate_to_z(moved.points[:, 2].detach()[None, None], 1.0)
    assert float((out.o[0, 0] - moved.points.detach()).abs().max()) < 1e-9


def test_pupil_phase_equals_the_chief_point_on_a_geometric_field():
    """Without edge waves inside the beam (the DOE-plane cut), the absolute phase read over the pupil equals the one
    read at the chief ray's point (at 1.5°: 3.6e-5 wave for order 1, 1.7e-6 for order −15, whose envelope's phase
    curves by tens of radians over its window)."""
    field = (0.0, 1.5)
    _, _, ml = _system(field, orders=[1, -15])
    for scale in (1.0, -15.0):
        hl = ml.order_lens(scale)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fd = hl.doe_fields([field], [LAM])[0][0]
        a = _absolute_phase(hl, fd, field, LAM, None)
        b = _pupil_phase(hl, fd, field, LAM, None)
        d = float((a - b).detach()) / (LAM * 1e-3)
        assert abs(d - round(d)) < 1e-3, (scale, d)


@pytest.mark.slow
@pytest.mark.parametrize("field,bar", [((0.0, 0.0), 2e-2), ((0.0, 1.5), 3e-2)])
def test_weak_order_alone_with_crop_rims(field, bar):
    """Order −15 alone, exact edge, its rim images moved for its own PSF centre, against the reference fed
    ``c₋₁₅e^{−i15φ0}``: measured 1.4e-2 (0°) / 2.3e-2 (1.5°); with the traced rim images 0.46 / 0.47 (the edge
    wave's rings in opposite phase at the centre)."""
    sys_, doe, ml = _system(field, orders=[-15], stop_edge="exit_pupil", edge_step="asm")
    hl = ml.order_lens(-15.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fd = hl.doe_fields([field], [LAM])[0][0]
        hl.use_rim_images(_CropRims(fd.center, hl.sensor_z()))
        fd = hl.doe_fields([field], [LAM])[0][0]
    psf, center, _ = hl.propagate(fd, KS)
    phi0 = DOEPhaseSurface(doe).phase_map()[2:-2, 2:-2].detach().numpy()
    c = order_coefficients(16, True, 1.0, [-15])[-15]
    ref = W.sensor_psf(sys_, N, PITCH, c * np.exp(-15j * phi0), center.detach().numpy(), PS, KS)
    assert W.rel_l1(psf.detach().numpy(), ref) < bar


def test_use_rim_images_refuses_a_non_callable():
    _, _, ml = _system((0.0, 0.0), orders=[1])
    with pytest.raises(TypeError, match="use_rim_images"):
        ml.order_lens(1.0).use_rim_images(3)
    assert math.isfinite(ml.order_lens(1.0).use_rim_images(None).sensor_z())


@pytest.mark.slow
def test_exact_edge_orders_gradients_by_finite_differences():
    """The exact edge with orders 1 and −15 (the crop rims and the pupil-read phases in the graph), at 1°:
    d(Σ w·PSF) with respect to the DOE's focal length and lens A's against central differences (measured 1.8e-5 and
    4.7e-6 relative)."""
    field = (0.0, 1.0)
    sys_ = W.TwoLensSystem(f_doe=50.0, field=field)
    doe = FresnelDOE(50.0, 800, PITCH, wavelength=LAM)
    doe.fabricate(16)
    lens = M.two_lens(sys_)
    ml = MidSystemLens(lens, doe, 0, sys_.gap1, final_distance=0.01, final_size=0.8, final_pitch=PITCH,
                       sensor_pitch=PS, min_efficiency=1e-3, orders=[1, -15], stop_edge="exit_pupil", edge_step="asm")
    w = torch.rand(16, 16, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # order −15's pixel loss and the DOE aperture's clipping (named elsewhere)
            return (ml.psf([field], LAM, ks=16)[0, 0] * w).sum()

    params = {"doe focal length": doe.focal_length, "lens A focal length": lens.surfaces[0].interaction.focal_length}
    M.assert_central_differences(loss, params, 2e-4)
