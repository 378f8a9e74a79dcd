"""Every field type × finite / infinite object × stop edge gives a PSF (or a clear error where the combination
means nothing), and the same object point gives the same PSF whichever way it is named.

raywave's field types are "angle" (degrees) and "object_height" (mm on the object plane; there are no
image-height fields). An angle θ from an object at distance D names the object point at height
``tan θ · (−D − z_ep)`` (z_ep: the paraxial entrance-pupil plane), so an object-height field there must give
exactly the same PSF. An object at infinity cannot be named by a height: that is an error naming the problem.
Issue 19's bug: a lens with object-height fields and its object at infinity raised that error with
``stop_edge="exit_pupil"`` even when ``depth`` was passed (the exit pupil was located with the lens's own
object); the exit pupil is the stop's image and does not depend on the object.
"""

import copy
import math

import pytest
import torch

from raywave.doe import BlankDOE
from raywave.hybrid import HybridLens
from raywave.lens.build import bundled_lens_path, load_lens
from raywave.lens.sources import entrance_plane_z

WL, PS, KS, DEPTH, THETA = 0.53, 3e-3, 16, 200.0, 5.0
EDGES = ("doe", "exit_pupil")

pytestmark = pytest.mark.filterwarnings("ignore::raywave.hybrid.SensorCropWarning")


@pytest.fixture(scope="module")
def lenses():
    angle = load_lens(bundled_lens_path("asphere_hk51"))  # angle fields, object at infinity
    height = copy.deepcopy(angle)
    height.field_type = "object_height"
    height.fields = [0.0, 20.0, 40.0]
    height_finite = copy.deepcopy(height)
    height_finite.object_distance = DEPTH
    return angle, height, height_finite


def _psf(lens, edge, field, depth):
    hl = HybridLens(lens, BlankDOE(2600, 1e-3), 0.7, sensor_pitch=PS, stop_edge=edge)
    r = hl.psf_result(field, WL, ks=KS, depth=depth, rays=24)
    return r.psf[0, 0].detach(), r.center[0, 0].detach()


def _height(lens):
    """The object height that names the same point as THETA from DEPTH."""
    return math.tan(math.radians(THETA)) * (-DEPTH - entrance_plane_z(lens))


@pytest.mark.parametrize("edge", EDGES)
def test_every_field_type_and_object_distance(lenses, edge):
    angle, height, height_finite = lenses
    inf_psf, inf_c = _psf(angle, edge, (0.0, THETA), None)  # angle × infinite object
    assert abs(float(inf_psf.sum()) - 1) < 1e-12 and float(inf_c[1]) > 0
    ref, ref_c = _psf(angle, edge, (0.0, THETA), DEPTH)  # angle × finite object (depth)
    assert abs(float(ref.sum()) - 1) < 1e-12
    h = _height(angle)
    # object height × finite object: given by depth to a lens whose own object is at infinity (the bug) ...
    p1, c1 = _psf(height, edge, (0.0, h), DEPTH)
    # ... and by the lens's own object distance
    p2, c2 = _psf(height_finite, edge, (0.0, h), None)
    for p, c in ((p1, c1), (p2, c2)):
        assert torch.allclose(c, ref_c, atol=1e-9)
        assert float((p - ref).abs().sum()) < 1e-8
    # object height × infinite object: meaningless, a clear error
    with pytest.raises(ValueError, match="distant object.*angle fields"):
        _psf(height, edge, (0.0, h), None)


def test_exit_pupil_does_not_depend_on_the_field_type_or_object(lenses):
    angle, height, height_finite = lenses
    z = [HybridLens(lens, BlankDOE(100, 1e-3), 0.7).exit_pupil_z() for lens in lenses]
    assert z[1] == pytest.approx(z[0], abs=1e-6) and z[2] == pytest.approx(z[0], abs=1e-6)
