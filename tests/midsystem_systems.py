"""The raywave side of the two-lens test system of tests/wave_truth_doe.py (issue 46): lens A as raywave's
``IdealLens`` (exact for collimated light), lens B as a thin phase surface with the reference's exact
sphere-to-sphere phase (the lens that is perfect for the beam it receives), the DOE between them."""

from __future__ import annotations

import dataclasses
import math

import torch

import raywave.hybrid.coherent.accurate as _accurate
import raywave.hybrid.coherent.exit_pupil as _exit_pupil
import raywave.hybrid.coherent.stop_edge as _stop_edge
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


def weighted_psf_loss(ml, field, ks: int = 16, wavelength: float = 0.55):
    """``loss()`` = Σ w·PSF of the mid-system lens ``ml`` at ``field`` (deg) and ``wavelength`` (µm), ``ks`` × ``ks``
    pixels, with fixed random weights ``w`` (seed 3): the scalar the finite-difference checks differentiate. Its
    warnings are silenced inside (the weak orders' sampling: pixel loss, orders left out, named by the sampling
    report of a plain PSF call)."""
    import warnings

    w = torch.rand(ks, ks, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return (ml.psf([field], wavelength, ks=ks)[0, 0] * w).sum()

    return loss


def focal_lengths(doe, lens) -> dict:
    """The parameters of the checks: the DOE's focal length and lens A's (the first surface's ideal lens)."""
    return {"doe focal length": doe.focal_length, "lens A focal length": lens.surfaces[0].interaction.focal_length}


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


def central_difference_terms(psf, w: torch.Tensor, prm: torch.Tensor, step: float, floor: float = 1e-2):
    """The per-pixel terms ``w·(psf(p + h) − psf(p − h)) / 2h`` of the central difference of ``Σ w·psf()`` with
    respect to the 0-d parameter ``prm`` at ``h = step · max(|p|, floor)`` (the parameter is restored); their sum is
    the derivative, their absolute sum the scale a near-cancelling sum is judged against."""
    h = step * max(abs(float(prm.detach())), floor)
    with torch.no_grad():
        prm += h
    pp = psf().detach()
    with torch.no_grad():
        prm -= 2 * h
    pm = psf().detach()
    with torch.no_grad():
        prm += h
    return w * (pp - pm) / (2 * h)


def assert_central_differences(loss, params: dict, rel: float, step: float = 1e-6) -> None:
    """The autograd gradient of the scalar ``loss()`` with respect to each 0-d parameter of ``params`` (name →
    tensor) within ``rel`` of its central difference at the step ``step`` × max(|value|, 1) (the parameter is
    restored; :func:`central_differences`)."""
    for name, _, g, fd in central_differences(loss, params, (step,)):
        assert abs(g - fd) <= rel * abs(fd), (name, g, fd)


class FrozenMesh:
    """The exact stop edge's discretisation held in finite differences, as the engine's gradient holds it (issue 46):
    while active, the step plane (``exit_pupil._rim_step_plane``: the plane ``z_edge`` just beyond the stop rim's
    images where the construction builds its field before the angular spectrum carries it to the engine's plane) and
    the node grid (``accurate._node_layout``: its spacing from the beam's extent, centred on the chief ray's point)
    that the first call of a loss wrapped by :meth:`loss` chose are replayed, in the same order, by every later call;
    and the stop rim images' source nudge (``stop_edge.RIM_NUDGE``) is ``rim_nudge`` (the engine's 1e-5 rounds the
    rim images' crossing at ~1e-10 of a weighted PSF sum, noise that central differences divide by their step).

    The plane and the grid are the construction's mesh: the field it builds on the engine's plane does not depend
    on them but for its discretisation error, so their motion under a perturbation adds only that error's
    derivative (measured: ``dL/dz_edge`` = −1.84e-5 per mm for order +17 of the 16-level DOE, the plane moving 0.6 mm
    per mm of the DOE's focal length, against ``dL/df`` = −2.2e-2; docs/ray-wave.md "A DOE inside the lens").
    ``plane``, ``nodes``: which to hold; ``rim_nudge`` None: the engine's."""

    def __init__(self, rim_nudge: float | None = 1e-3, plane: bool = True, nodes: bool = True):
        self.rim_nudge, self.hold = rim_nudge, (plane, nodes)
        self.memo, self.calls, self.recording, self.saved = {}, {}, True, None

    def __enter__(self):
        self.saved = (_exit_pupil._rim_step_plane, _accurate._node_layout, _stop_edge.RIM_NUDGE)
        plane, nodes, nudge = self.saved
        if self.hold[0]:
            _exit_pupil._rim_step_plane = lambda *a: self._replay("plane", plane(*a))
        if self.hold[1]:
            _accurate._node_layout = lambda b, bbox: self._nodes(nodes(b, bbox))
        _stop_edge.RIM_NUDGE = nudge if self.rim_nudge is None else float(self.rim_nudge)
        return self

    def __exit__(self, *exc):
        _exit_pupil._rim_step_plane, _accurate._node_layout, _stop_edge.RIM_NUDGE = self.saved

    def _replay(self, name: str, value):
        i = self.calls.get(name, 0)
        self.calls[name] = i + 1
        if self.recording:
            self.memo[name, i] = value
            return value
        if (name, i) not in self.memo:
            raise RuntimeError(f"FrozenMesh: call {i} of {name} was not made by the first evaluation")
        return self.memo[name, i]

    def _nodes(self, nd):
        kept = self._replay("nodes", nd)
        return dataclasses.replace(kept)  # the same grid, its node tensors made afresh

    def loss(self, fn):
        """``fn`` (a loss without arguments) whose first call records the mesh and later calls replay it."""
        def wrapped():
            self.calls = {}
            try:
                return fn()
            finally:
                self.recording = False
        return wrapped
