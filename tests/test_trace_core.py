"""Ray tracing core: analytic checks, NaN safety, gradients, dtype."""

import math

import pytest
import torch

from raywave.lens import analysis, paraxial
from raywave.lens.lens import Lens
from raywave.lens.sources import chief_ray, point_source_rays
from raywave.materials.base import Air, ConstantIndex
from raywave.rays.bundle import RayBundle
from raywave.surfaces.aperture import CircularAperture, SquareAperture
from raywave.surfaces.geometry import EvenAsphere, Standard
from raywave.surfaces.interaction import refract
from raywave.surfaces.surface import Surface
from tests.conftest import std


@pytest.mark.parametrize("n,r1,r2,t", [(1.5, 50.0, -50.0, 5.0), (1.7, 30.0, 200.0, 8.0), (1.5168, 100.0, math.inf, 3.0)])
def test_thick_lens_efl_bfl(n, r1, r2, t):
    lens = Lens([std(r1, t, n, stop=True, ap=5.0), std(r2, 80.0)])
    p = lens.paraxial()
    c1, c2 = 1 / r1, (0.0 if r2 == math.inf else 1 / r2)
    phi = (n - 1) * (c1 - c2 + (n - 1) * t * c1 * c2 / n)
    f = 1 / phi
    assert p.efl == pytest.approx(f, rel=1e-12)
    assert p.bfl == pytest.approx(f * (1 - (n - 1) * t * c1 / n), rel=1e-12)
    # front focal point: z = -f (1 + (n-1) t c2 / n)
    assert p.ffl == pytest.approx(-f * (1 + (n - 1) * t * c2 / n), rel=1e-12)
    # real-ray EFL converges to the paraxial one
    assert float(analysis.real_ray_efl(lens)) == pytest.approx(f, rel=1e-6)


def test_thin_lens_limit_and_imaging_equation():
    f = 100.0
    lens = Lens([std(2 * (1.5 - 1) * f, 1e-6, 1.5, stop=True, ap=0.01), std(-2 * (1.5 - 1) * f, 150.0)],
                object_distance=300.0)
    z_img = float(paraxial.paraxial_image_distance(lens, 0.55))
    assert z_img == pytest.approx(1 / (1 / f - 1 / 300.0), rel=1e-6)


def test_plate_focal_shift():
    """A plane-parallel plate of thickness t and index n shifts a converging focus by t(1 - 1/n)."""
    f, t, n = 100.0, 10.0, 1.5
    from raywave.surfaces.interaction import IdealLens
    from raywave.surfaces.geometry import Plane

    base = [Surface(Plane(), Air(), 20.0, interaction=IdealLens(f), aperture=CircularAperture(2.0), is_stop=True)]
    without = Lens(base + [std(math.inf, 10.0), std(math.inf, 100.0)])
    base2 = [Surface(Plane(), Air(), 20.0, interaction=IdealLens(f), aperture=CircularAperture(2.0), is_stop=True)]
    with_plate = Lens(base2 + [std(math.inf, t, n), std(math.inf, 100.0)])
    shift = float(paraxial.paraxial_image_distance(with_plate, 0.55) - paraxial.paraxial_image_distance(without, 0.55))
    assert shift == pytest.approx(t * (1 - 1 / n), rel=1e-12)
    # real marginal rays: the plate's spherical aberration is tiny at NA 0.02, the focus shift real
    analysis.refocus(with_plate, method="rms")
    analysis.refocus(without, method="rms")
    real_shift = float(with_plate.image_z() - without.image_z())
    assert real_shift == pytest.approx(t * (1 - 1 / n), rel=1e-3)


@pytest.mark.parametrize("tilt_deg", [0.0, 10.0, 30.0])
@pytest.mark.parametrize("inc_deg", [0.0, 20.0, -35.0])
def test_snell_at_tilted_plane(tilt_deg, inc_deg):
    n1, n2 = 1.0, 1.5
    a = math.radians(tilt_deg)
    nx, ny, nz = (torch.tensor(v, dtype=torch.float64) for v in (0.0, -math.sin(a), math.cos(a)))
    th = math.radians(inc_deg)
    dx, dy, dz = (torch.tensor(v, dtype=torch.float64) for v in (0.0, math.sin(th), math.cos(th)))
    ox, oy, oz, ok = refract(dx, dy, dz, nx, ny, nz, torch.tensor(n1, dtype=torch.float64), torch.tensor(n2, dtype=torch.float64))
    assert bool(ok)
    # angle of incidence/refraction measured from the normal
    sin_i = math.sin(th + a)
    cos_r = float(ox * nx + oy * ny + oz * nz)
    sin_r = math.sqrt(1 - cos_r**2)
    assert sin_r == pytest.approx(abs(n1 * sin_i / n2), rel=1e-12)
    # coplanar with incidence plane and unit length
    assert float(ox) == 0.0
    assert float(ox**2 + oy**2 + oz**2) == pytest.approx(1.0, abs=1e-15)


def test_total_internal_reflection_is_invalid_not_nan():
    # glass-to-air at a steep angle
    lens = Lens([std(math.inf, 5.0, 1.5, stop=True), std(10.0, 20.0)])
    rays = RayBundle.create([[0.0, 9.0, -1.0], [0.0, 0.1, -1.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], 0.55)
    out = lens.trace_to_image(rays)
    assert out.valid.tolist() == [False, True]
    assert torch.isfinite(out.o).all() and torch.isfinite(out.opl).all()


def test_missing_and_vignetted_rays_no_nan_forward_backward(cooke_const, device):
    lens = cooke_const.to(device)
    o = torch.tensor([[0.0, y, -5.0] for y in (0.0, 3.0, 50.0, 1e4)], dtype=torch.float64, device=device)
    d = torch.tensor([[0.0, 0.0, 1.0]] * 4, dtype=torch.float64, device=device)
    rays = RayBundle.create(o, d, 0.55)
    out = lens.trace_to_image(rays)
    assert out.valid.tolist() == [True, True, False, False]
    loss = (out.o[..., :2] ** 2).sum() + out.opl.sum()
    loss.backward()
    for p in lens.parameters():
        if p.grad is not None:
            assert torch.isfinite(p.grad).all()


def test_sphere_far_side_is_not_hit():
    # A ray far outside a strongly curved sphere's diameter misses it (no far-hemisphere solution).
    geom = Standard(1 / 5.0)
    t, ok = geom.intersect(*(torch.tensor(v, dtype=torch.float64) for v in (0.0, 6.0, -1.0, 0.0, 0.0, 1.0)))
    assert not bool(ok)
    t, ok = geom.intersect(*(torch.tensor(v, dtype=torch.float64) for v in (0.0, 3.0, -1.0, 0.0, 0.0, 1.0)))
    assert bool(ok) and float(t) == pytest.approx(1 + 5 - math.sqrt(25 - 9), rel=1e-14)


def test_asphere_intersection_converges_and_matches_sag(asphere_const):
    g = asphere_const.surfaces[1].geometry
    y = torch.linspace(-1.4, 1.4, 29, dtype=torch.float64)
    ox, oy, oz = 0.3 * torch.ones_like(y), y, torch.full_like(y, -2.0)
    d = torch.tensor([0.05, -0.1, 1.0], dtype=torch.float64)
    d = d / d.norm()
    dx, dy, dz = (torch.full_like(y, float(v)) for v in d)
    t, ok = g.intersect(ox, oy, oz, dx, dy, dz)
    assert ok.all()
    x, yy, z = ox + t * dx, oy + t * dy, oz + t * dz
    assert torch.allclose(z, g.sag(x, yy), atol=1e-13, rtol=0)


def test_asphere_intersection_equals_an_independent_root(asphere_const):
    """The intersection's Newton iteration stops when its next step is predicted within 1e-12 mm (issue 43):
    the ray parameters equal scipy's bracketed root of the sag equation, written out here with numpy, to 1e-12 mm,
    with and without autograd, for steep and off-axis rays."""
    from scipy.optimize import brentq

    g = asphere_const.surfaces[1].geometry
    c, k = float(g.curvature), float(g.conic)
    a = g.coefficients.detach().numpy()

    def sag(r2):
        return c * r2 / (1 + math.sqrt(1 - (1 + k) * c * c * r2)) + sum(ai * r2 ** (i + 1) for i, ai in enumerate(a))

    gen = torch.Generator().manual_seed(7)
    n = 40
    ox, oy = (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5) * 2.0, torch.linspace(-1.3, 1.3, n,
                                                                                                dtype=torch.float64)
    oz = torch.full((n,), -2.0, dtype=torch.float64)
    d = torch.stack([0.3 * (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5), -0.25 * oy,
                     torch.ones(n, dtype=torch.float64)], -1)
    d = d / d.norm(dim=-1, keepdim=True)
    ref = [brentq(lambda t: oz[i].item() + t * d[i, 2].item()
                  - sag((ox[i].item() + t * d[i, 0].item()) ** 2 + (oy[i].item() + t * d[i, 1].item()) ** 2),
                  0.0, 6.0, xtol=1e-15, rtol=1e-15) for i in range(n)]
    ref = torch.tensor(ref, dtype=torch.float64)
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            t, ok = g.intersect(ox, oy, oz, *d.unbind(-1))
        assert bool(ok.all())
        assert float((t.detach() - ref).abs().max()) <= 1e-12


def test_a_surface_between_two_airs_keeps_the_directions():
    """A curved surface with air on both sides (a dummy surface, a stop) refracts nothing: the tracer skips its
    Snell step (issue 43), and the rays equal those refracted by Snell's law with n1 = n2 to rounding."""
    dummy = std(12.0, 4.0, ap=6.0)
    lens = Lens([dummy, std(20.0, 3.0, 1.5, stop=True, ap=3.0), std(-20.0, 30.0)])
    assert lens._identity_refractions() == [True, False, False]
    rays = point_source_rays(lens, torch.tensor([[0.0, 8.0]], dtype=torch.float64), 0.55, pupil=("grid", 9))
    out, rec = lens.trace(rays, stop=1, record=True)
    d_in = rays.d.unbind(-1)
    assert all(torch.equal(a, b) for a, b in zip(out.d.unbind(-1), d_in))
    x, y, z = rec.points[1]
    nx, ny, nz = dummy.geometry.normal(x, y, z - lens.vertex_z()[0])
    one = torch.ones((), dtype=torch.float64)
    dx, dy, dz, ok = refract(*d_in, nx, ny, nz, one, one)
    assert bool(ok.all())
    assert max(float((a - b).abs().max()) for a, b in zip((dx, dy, dz), d_in)) <= 1e-15
    assert torch.equal(out.valid, rays.valid & dummy.aperture.contains(x, y))


def test_a_flat_surfaces_intersection_without_autograd_is_the_general_forms():
    """Without autograd a flat standard surface (c = 0) takes its intersection in a few ops (issue 43): the same
    values as the general conic form, bit for bit, for rays from either side, along the plane and at its vertex; and
    after the curvature changes (an optimiser's step) the general form again."""
    g = Standard(0.0, -0.7)
    gen = torch.Generator().manual_seed(0)
    n = 20000
    o = torch.randn(3, n, generator=gen, dtype=torch.float64) * torch.tensor([[5.0], [5.0], [3.0]],
                                                                               dtype=torch.float64)
    d = torch.randn(3, n, generator=gen, dtype=torch.float64)
    d[2, :10], d[2, 10:20], o[2, 20:30] = 0.0, -0.0, 0.0
    d = d / d.norm(dim=0)
    for front in (True, False):
        with torch.no_grad():
            fast = g.intersect(*o, *d, front=front)
        general = g.intersect(*o, *d, front=front)  # with autograd: the general form
        assert torch.equal(fast[0], general[0].detach()) and torch.equal(fast[1], general[1])
    with torch.no_grad():
        g.curvature.add_(0.01)
        t, _ = g.intersect(*o, *d, front=True)
    assert not g._is_flat()
    assert torch.equal(t, g.intersect(*o, *d, front=True)[0].detach())


def test_gradcheck_full_trace(asphere_const, cooke_const):
    """Gradients of image-plane positions and OPL w.r.t. curvature, conic, aspheric terms, thickness."""
    from raywave.rays.pupil import hexapolar

    px, py = hexapolar(2)
    for lens in (asphere_const, cooke_const):
        # pupil inside the stop edge, so that no ray sits exactly on an aperture boundary
        rays = point_source_rays(lens, [[0.0, 0.0], [0.0, 3.0]], [0.55], pupil=(0.8 * px, 0.8 * py))
        g = lens.surfaces[1].geometry
        params = {"surfaces.1.geometry.curvature": g.curvature, "surfaces.1.thickness": lens.surfaces[1].thickness}
        if isinstance(g, EvenAsphere):
            params.update({"surfaces.1.geometry.conic": g.conic, "surfaces.1.geometry.coefficients": g.coefficients})
        keys = list(params)

        def run(*vals):
            with torch.nn.utils.stateless._reparametrize_module(lens, dict(zip(keys, vals))):
                out = lens.trace_to_image(rays)
            return out.o[..., :2], out.opl

        inputs = tuple(params[k].detach().clone().requires_grad_(True) for k in keys)
        assert torch.autograd.gradcheck(run, inputs, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_float64_default_and_explicit_float32(cooke_const):
    rays = point_source_rays(cooke_const, (0.0, 10.0), [0.55], pupil=("grid", 5))
    assert rays.dtype == torch.float64
    out = cooke_const.trace_to_image(rays)
    assert out.o.dtype == torch.float64 and out.opl.dtype == torch.float64
    r32 = rays.to(dtype=torch.float32)
    out32 = cooke_const.trace_to_image(r32)
    assert out32.o.dtype == torch.float32
    assert torch.get_default_dtype() == torch.float32  # the library never changes the global default


def test_chunked_trace_equals_direct(cooke_const, monkeypatch):
    import raywave.lens.lens as lensmod

    rays = point_source_rays(cooke_const, [[0.0, 0.0], [0.0, 14.0]], [0.5, 0.6], pupil=("grid", 25))
    direct = cooke_const.trace_to_image(rays)
    monkeypatch.setattr(lensmod, "TRACE_CHUNK", 37)
    chunked = cooke_const.trace_to_image(rays)
    assert torch.equal(direct.o, chunked.o) and torch.equal(direct.opl, chunked.opl)
    assert torch.equal(direct.valid, chunked.valid)


def test_square_aperture_clips():
    lens = Lens([Surface(Standard(0.0), Air(), 10.0, aperture=SquareAperture(1.0), is_stop=True)])
    rays = RayBundle.create([[0.9, 0.9, -1.0], [1.1, 0.0, -1.0], [0.0, 0.0, -1.0]], [[0, 0, 1.0]] * 3, 0.55)
    assert lens.trace(rays).valid.tolist() == [True, False, True]


def test_overlapping_and_negative_thickness_rejected():
    with pytest.raises(ValueError, match="overlap"):
        Lens([std(10.0, 0.1, 1.5, ap=5.0), std(-10.0, 10.0, ap=5.0)])
    with pytest.raises(ValueError, match="negative thickness"):
        Lens([std(math.inf, -1.0, 1.5, ap=5.0), std(math.inf, 10.0, ap=5.0)])
    with pytest.raises(ValueError, match="stop"):
        Lens([std(math.inf, 1.0, stop=True), std(math.inf, 1.0, stop=True)])


def test_ray_aiming_hits_stop_points(cooke_const, device):
    cooke_const = cooke_const.to(device)
    px = torch.tensor([0.0, 0.5, -0.7, 0.0, 0.99], dtype=torch.float64, device=device)
    py = torch.tensor([0.0, 0.5, 0.2, -1.0, 0.0], dtype=torch.float64, device=device)
    rays = point_source_rays(cooke_const, [[0.0, 20.0], [5.0, 12.0]], [0.48, 0.65], pupil=(px, py))
    # apertures off: the ray aimed at the stop's rim (py = -1) lands on it to ~1e-15 mm, inside or just outside
    # the aperture by rounding (seen both ways on CPUs and GPUs); this test is about the aim, not the clipping
    out = cooke_const.trace(rays, stop=cooke_const.stop_index + 1, apertures=False)
    assert out.o.device.type == device
    r = cooke_const.stop_radius()
    assert torch.allclose(out.o[..., 0], px * r, atol=1e-10)
    assert torch.allclose(out.o[..., 1], py * r, atol=1e-10)


def test_third_order_spherical_of_slow_singlet():
    """W040 from the Seidel sum equals the ρ⁴ term of the real-ray OPD of an F/10 singlet (to 1 %)."""
    for conic in (0.0, -0.6):
        lens = Lens([std(100.0, 4.0, 1.5, stop=True, ap=5.0, conic=conic), std(math.inf, 190.0)])
        analysis.refocus(lens)  # paraxial focus: no defocus term
        w040 = float(analysis.seidel(lens, 0.55, field=0.0)["W040"]) / 0.55e-3
        opd, px, py, v = analysis.wavefront_opd(lens, (0.0, 0.0), 0.55, pupil=("grid", 21))
        rho2 = px**2 + py**2
        basis = torch.stack([torch.ones_like(rho2), rho2, rho2**2, rho2**3], -1)
        coef = torch.linalg.lstsq(basis, opd[0, 0][:, None]).solution.ravel()
        assert abs(float(coef[1])) < 1e-3 * abs(w040)  # at the paraxial focus
        assert float(coef[2]) == pytest.approx(w040, rel=1e-2)
