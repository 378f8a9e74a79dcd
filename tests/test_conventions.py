"""Sign and orientation conventions, in one place (cf. POPPY). See docs/conventions.md.

* Lengths mm, wavelengths µm, light travels toward +z, the first vertex is at z = 0.
* A positive radius (curvature) has its centre of curvature at +z: the surface bulges toward the object.
* A field angle +θy means a chief ray travelling with +y slope; it lands at +y on the image plane.
  An object point at +y (object_height field) images at -y: a real image is inverted.
* Thicknesses are vertex-to-vertex along +z; the last one is the distance to the image plane.
* Wavefront OPD = OPL(chief ray) - OPL(ray) to the reference sphere: positive for an under-corrected
  positive singlet (positive W040), as OpticStudio reports it.
"""

import math

import torch

from conftest import std
from raywave.lens.analysis import seidel, wavefront_opd
from raywave.lens.lens import Lens
from raywave.lens.sources import chief_ray
from raywave.rays.bundle import RayBundle
from raywave.surfaces.geometry import Standard


def test_positive_radius_bulges_toward_object():
    g = Standard(1 / 10.0)
    sag = g.sag(torch.tensor([0.0]), torch.tensor([2.0]))
    assert float(sag) > 0  # the rim lies at +z of the vertex: centre of curvature at +z


def test_positive_field_angle_lands_at_positive_y():
    lens = Lens([std(50.0, 4.0, 1.5, stop=True, ap=5.0), std(-50.0, 48.0)], fields=[0.0, 5.0])
    out = lens.trace_to_image(chief_ray(lens, (0.0, 5.0)))
    assert float(out.o[..., 1]) > 0
    out = lens.trace_to_image(chief_ray(lens, (3.0, 0.0)))
    assert float(out.o[..., 0]) > 0


def test_real_image_is_inverted():
    lens = Lens([std(50.0, 4.0, 1.5, stop=True, ap=5.0), std(-50.0, 100.0)], object_distance=100.0,
                fields=[0.0, 2.0], field_type="object_height")
    out = lens.trace_to_image(chief_ray(lens, (0.0, 2.0)))
    assert float(out.o[..., 1]) < 0


def test_ray_direction_tilt_moves_focus_the_same_way():
    """A collimated bundle tilted toward +y focuses at +y = f·tanθ on the focal plane of an ideal lens."""
    from raywave.materials.base import Air
    from raywave.surfaces.geometry import Plane
    from raywave.surfaces.interaction import IdealLens
    from raywave.surfaces.surface import Surface

    f, th = 50.0, math.radians(3.0)
    lens = Lens([Surface(Plane(), Air(), f, interaction=IdealLens(f), is_stop=True)])
    y0 = torch.linspace(-2, 2, 5, dtype=torch.float64)
    o = torch.stack([torch.zeros_like(y0), y0, torch.full_like(y0, -1.0)], -1)
    d = torch.tensor([0.0, math.sin(th), math.cos(th)], dtype=torch.float64).expand(5, 3)
    out = lens.trace_to_image(RayBundle.create(o, d, 0.55))
    assert torch.allclose(out.o[:, 1], torch.full((5,), f * math.tan(th), dtype=torch.float64), atol=1e-12)


def test_opd_sign_positive_spherical_for_positive_singlet():
    lens = Lens([std(100.0, 4.0, 1.5, stop=True, ap=6.0), std(-100.0, 97.0)], fields=[0.0])
    from raywave.lens.analysis import refocus

    refocus(lens, method="paraxial")
    assert seidel(lens)["W040"] > 0
    opd, px, py, valid = wavefront_opd(lens)
    edge = (px**2 + py**2 > 0.8) & valid
    assert float(opd[edge].mean()) > 0  # OPD = OPL(chief) - OPL(ray): marginal rays are short (paraxial focus)


def test_z_grows_along_the_lens():
    lens = Lens([std(20.0, 3.0, 1.5, stop=True, ap=3.0), std(-20.0, 10.0), std(30.0, 2.0, 1.6), std(math.inf, 5.0)])
    z = lens.vertex_z()
    assert torch.equal(z, torch.tensor([0.0, 3.0, 13.0, 15.0], dtype=torch.float64))
    assert float(lens.image_z()) == 20.0


def test_psf_array_and_doe_sign_conventions():
    """[iy, ix] with both increasing; +y field → PSF centre at +y; a DOE phase rising toward +x moves the PSF
    toward +x; the chief ray is the centre of pixel [ks//2, ks//2] (also for an odd ks)."""
    from raywave.doe import PixelDOE
    from raywave.hybrid import HybridLens
    from raywave.lens.build import ideal_lens

    n, p = 500, 2e-3
    x = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * p
    tilt = (2 * math.pi * x / 0.04)[None, :].expand(n, n)  # 40 µm period, rising toward +x
    lens = ideal_lens(5.0, f_number=8, wavelengths=(0.55,))
    flat = HybridLens(lens, PixelDOE(torch.zeros(n, n), p), 2.0, sensor_pitch=2e-3)
    tilted = HybridLens(lens, PixelDOE(tilt, p), 2.0, sensor_pitch=2e-3)
    res = flat.psf_result((0.0, 1.0), 0.55, ks=15, rays=24)
    assert float(res.center[0, 0, 1]) > 0
    a = res.psf[0, 0].detach()
    assert int(a.argmax()) == 7 * 15 + 7
    b = tilted.psf((0.0, 1.0), 0.55, ks=15, rays=24)[0, 0].detach()
    cols = torch.arange(15, dtype=torch.float64)
    assert float((b.sum(0) * cols).sum()) > float((a.sum(0) * cols).sum()) + 1  # toward +x (increasing ix)
