"""Lens-parameter gradients with ``HybridLens(stop_edge="exit_pupil")`` against central finite differences (the
training replay with this stop edge: tests/test_training_replay.py, slow).

A small case so that it runs in the default suite: the bundled asphere stopped down to a 0.8 mm stop (F/10, a
~1 mm beam on its virtual exit-pupil plane 6 mm inside the lens), a blank 3 µm DOE 0.7 mm after the lens, 3 µm
sensor pixels, ks 12, 24 nodes, 3° off axis. Both ways of bringing the edge to the DOE plane: the exact
angular-spectrum construction (``edge_step="asm"``) and the Fresnel step.

What the model differentiates (docs/ray-wave.md, Gradients with respect to focus): the exit-pupil plane, like the
DOE plane, is a constant of the model (held fixed in the finite differences too); the last thickness moves the
sensor (the DOE → sensor distance); an earlier thickness is differentiated with the DOE and sensor planes fixed in
space, so its finite difference holds them there as well. The chief ray's direction on the field's plane, the
carrier the envelopes are demodulated by (``_common_setup``), is a constant of the model too (a frame, not
physics): the finite differences hold it at its unperturbed value. Left free, it moves the windowed angular
spectrum's discrete band limit against the frequency grid, which the model does not differentiate: measured on
this case (``asm``, glass thickness), 5.6e-5 relative with the default output margin, 5e-4 / 2.6e-4 with margins
of 2 / 4 samples; held, 8.4e-6 for every margin.
"""

import warnings

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, load_lens

WL, PS, KS = 0.53, 3e-3, 12


def small_asphere():
    lens = load_lens(bundled_lens_path("asphere_hk51"))
    lens.surfaces[lens.stop_index].aperture.set_radius(0.4)
    return lens


def _frozen_carrier(setup):
    """``_common_setup`` whose carrier (entry 5) is the one of its first call per (field, wavelength, plane): the
    finite differences' perturbed lenses keep the unperturbed frame (see the module docstring)."""
    first = {}

    def frozen(*args):
        out = list(setup(*args))
        key = (tuple(torch.as_tensor(args[2].field, dtype=torch.float64).flatten().tolist()), float(args[2].wavelength))
        out[5] = first.setdefault(key, out[5])
        return tuple(out)

    return frozen


@pytest.mark.parametrize("edge_step", ["asm", "asm_rim", "fresnel"])
def test_exit_pupil_edge_lens_gradients_match_central_differences(edge_step, monkeypatch):
    """``asm``: the exact construction with its edge on the exit-pupil plane (at 3 µm pixels a 16-pixel Fresnel
    zone leaves no room for the rim images' step before the DOE); ``asm_rim``: its edge at the rim images, a
    6-pixel zone's step (0.6 mm) before the angular spectrum."""
    import raywave.hybrid.coherent.accurate as acc
    import raywave.hybrid.coherent.exit_pupil as xp

    lens = small_asphere()
    taken = []
    real = xp._rim_step_plane
    planes = []  # the rim step's plane: the first call's (a constant of the model, see the module docstring)

    def rim_step_plane(*a):
        planes.append(planes[0] if planes else real(*a))
        taken.append(planes[-1][0] is not None)
        return planes[-1]

    monkeypatch.setattr(xp, "_rim_step_plane", rim_step_plane)
    monkeypatch.setattr(acc, "_common_setup", _frozen_carrier(acc._common_setup))
    if edge_step == "asm_rim":
        monkeypatch.setattr(xp, "RIM_STEP_ZONE_PIXELS", 6.0)
    hl = HybridLens(lens, BlankDOE(400, PS), 0.7, sensor_pitch=PS, stop_edge="exit_pupil",
                    edge_step=edge_step.split("_")[0])
    z_xp, z_doe = hl.exit_pupil_z(), hl.doe_z()
    hl.exit_pupil_z = lambda wavelength=None: z_xp  # a constant of the model
    w = torch.randn(KS, KS, dtype=torch.float64, generator=torch.Generator().manual_seed(1))

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return (hl.psf((0.0, 3.0), WL, ks=KS, rays=24)[0, 0] * w).sum()

    curv, glass, last = lens.surfaces[1].geometry.curvature, lens.surfaces[1].thickness, lens.surfaces[-1].thickness
    hl.zero_grad()
    loss().backward()
    grads = {"curvature": float(curv.grad), "glass thickness": float(glass.grad), "sensor distance": float(last.grad)}
    for name, param in (("curvature", curv), ("glass thickness", glass), ("sensor distance", last)):
        if name == "glass thickness":  # the DOE and sensor planes stay where they are (see the module docstring)
            z_sen = hl.sensor_z()
            hl.doe_z, hl.sensor_z = (lambda: z_doe), (lambda: z_sen)
        eps = 1e-6 * abs(float(param.detach()))
        with torch.no_grad():
            param += eps
            lp = float(loss())
            param -= 2 * eps
            lm = float(loss())
            param += eps
        fd = (lp - lm) / (2 * eps)
        if name == "glass thickness":
            del hl.doe_z, hl.sensor_z  # back to the methods
        g = grads[name]
        print(f"{edge_step} {name}: autograd {g:.8e}, central difference {fd:.8e}")
        assert abs(g) > 1e-6 * max(abs(v) for v in grads.values())
        assert g == pytest.approx(fd, rel=1e-4), (name, g, fd)
    if edge_step != "fresnel":
        assert taken and all(t == (edge_step == "asm_rim") for t in taken)
