"""The raywave side of the two-lens test system of tests/wave_truth_doe.py (issue 46): lens A as raywave's
``IdealLens`` (exact for collimated light), lens B as a thin phase surface with the reference's exact
sphere-to-sphere phase (the lens that is perfect for the beam it receives), the DOE between them."""

from __future__ import annotations

import math

import torch

from raywave.lens.lens import Lens
from raywave.materials import get_material
from raywave.surfaces.aperture import CircularAperture
from raywave.surfaces.geometry import Plane
from raywave.surfaces.interaction import Diffraction, IdealLens
from raywave.surfaces.surface import Surface


def sphere_pair_phase(p, q):
    """Phase callable of lens B: ``2π/λ · (±|X − p| − |X − q|)`` (p, q = (x, y, z) mm from B; + when p lies
    behind B: the beam converges on it), with its gradient."""
    sp = math.copysign(1.0, p[2])

    def phase(x, y, wavelength):
        k = 2 * math.pi / (wavelength * 1e-3)
        dpx, dpy = x - p[0], y - p[1]
        dqx, dqy = x - q[0], y - q[1]
        rp = torch.sqrt(dpx * dpx + dpy * dpy + p[2] ** 2)
        rq = torch.sqrt(dqx * dqx + dqy * dqy + q[2] ** 2)
        phi = k * (sp * rp - rq)
        return phi, k * (sp * dpx / rp - dqx / rq), k * (sp * dpy / rp - dqy / rq)

    return phase


def two_lens(sys) -> Lens:
    """The raywave lens of a :class:`wave_truth_doe.TwoLensSystem` (without the DOE: A, gap1 + gap2, B, sensor)."""
    air = get_material("AIR")
    a = Surface(Plane(), air, sys.gap1 + getattr(sys, "gap12", 0.0) + sys.gap2, aperture=CircularAperture(sys.radius_a),
                interaction=IdealLens(sys.f_a), is_stop=True, comment="lens A")
    p, q = sys.beam_focus(), sys.image()
    b = Surface(Plane(), air, float(q[2]), interaction=Diffraction(sphere_pair_phase(p, q)), comment="lens B")
    return Lens([a, b], wavelengths=(sys.wavelength,), primary=0, fields=(0.0,))


def two_lens_split(sys) -> Lens:
    """:func:`two_lens` with a surface in air ``gap1`` mm after A: a sphere of ``sys.doe_radius`` (a plane when
    infinite), where a conformal DOE sits (A, gap1, that surface, gap12 + gap2, B, sensor)."""
    from raywave.surfaces.geometry import Standard
    from raywave.surfaces.interaction import Refraction

    air = get_material("AIR")
    a = Surface(Plane(), air, sys.gap1, aperture=CircularAperture(sys.radius_a), interaction=IdealLens(sys.f_a),
                is_stop=True, comment="lens A")
    c = 0.0 if math.isinf(sys.doe_radius) else 1.0 / sys.doe_radius
    s = Surface(Standard(c), air, sys.gap12 + sys.gap2, interaction=Refraction(), comment="DOE substrate (air)")
    p, q = sys.beam_focus(), sys.image()
    b = Surface(Plane(), air, float(q[2]), interaction=Diffraction(sphere_pair_phase(p, q)), comment="lens B")
    return Lens([a, s, b], wavelengths=(sys.wavelength,), primary=0, fields=(0.0,))


def central_differences(loss, params: dict, steps=(1e-6,)) -> list:
    """``[(name, step, autograd gradient, central difference)]``: the autograd gradient of the scalar ``loss()`` with
    respect to each 0-d parameter of ``params`` (name → tensor) and its central difference at each relative step of
    ``steps`` (× max(|value|, 1); the parameter is restored)."""
    grads = torch.autograd.grad(loss(), list(params.values()))
    out = []
    for (name, prm), g in zip(params.items(), grads):
        for step in steps:
            h = step * max(abs(float(prm.detach())), 1.0)
            with torch.no_grad():
                prm += h
            lp = float(loss().detach())
            with torch.no_grad():
                prm -= 2 * h
            lm = float(loss().detach())
            with torch.no_grad():
                prm += h
            out.append((name, step, float(g), (lp - lm) / (2 * h)))
    return out


def assert_central_differences(loss, params: dict, rel: float, step: float = 1e-6) -> None:
    """The autograd gradient of the scalar ``loss()`` with respect to each 0-d parameter of ``params`` (name →
    tensor) within ``rel`` of its central difference at the step ``step`` × max(|value|, 1) (the parameter is
    restored; :func:`central_differences`)."""
    for name, _, g, fd in central_differences(loss, params, (step,)):
        assert abs(g - fd) <= rel * abs(fd), (name, g, fd)
