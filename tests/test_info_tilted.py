"""`raywave info` on a tilted or decentred lens (issue 44): no paraxial data, said with the reason; the chief-ray
image points and the real-ray working F/# from real rays aimed at the stop (analytic on a decentred ideal lens;
against Optiland's real trace on the tilted doublet of tests/data/zmx)."""

import json
import math

import numpy as np
import pytest
import torch

from raywave.cli.lens_commands import real_ray_info
from raywave.cli.main import main
from raywave.lens.build import lens_from_spec, load_lens
from raywave.rays.bundle import RayBundle

F, R_STOP, DY = 5.0, 5.0 / 16, 1.0


def _decentred_ideal_spec():
    """A flat stop (radius R, F/8 for f = 5 mm) at z = 0, then a perfect f = 5 mm lens decentred by 1 mm in y (and
    back): parallel rays at angle θ meet at y = 1 + f tan θ on the focal plane, whatever their height."""
    cb = {"type": "coordinate_break", "decenter": [0.0, DY], "tilt": [0.0, 0.0, 0.0], "thickness": 0.0}
    back = dict(cb, decenter=[0.0, -DY], thickness=0.0)
    return {"format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"},
            "name": "decentred ideal lens", "object": {"distance": "inf"}, "system_aperture": {"epd": 2 * R_STOP},
            "fields": {"type": "angle", "values": [0.0, 3.0, 6.0]}, "wavelengths": {"values": [0.55], "primary": 0},
            "surfaces": [{"type": "standard", "radius": "inf", "thickness": 0.0, "stop": True}, cb,
                         {"type": "paraxial", "focal_length": F, "thickness": F}, back]}


def _expected_fnum() -> float:
    """1 / (2 mean sin θ'): θ' between the chief ray (stop centre -> focus (0, DY, F)) and the rays from the stop's
    rim points (±R, 0), (0, ±R) to the same focus."""
    focus = np.array([0.0, DY, F])
    chief = focus / np.linalg.norm(focus)
    sins = []
    for x, y in ((R_STOP, 0.0), (-R_STOP, 0.0), (0.0, R_STOP), (0.0, -R_STOP)):
        d = focus - np.array([x, y, 0.0])
        d /= np.linalg.norm(d)
        sins.append(np.linalg.norm(np.cross(d, chief)))
    return 1.0 / (2.0 * float(np.mean(sins)))


def test_decentred_ideal_lens_real_ray_info_is_analytic(tmp_path, capsys):
    spec = _decentred_ideal_spec()
    lens = lens_from_spec(spec)
    info = real_ray_info(lens)
    for f, xy in zip(info["fields"], info["chief_image_xy"]):
        assert xy[0] == pytest.approx(0.0, abs=1e-12)
        assert xy[1] == pytest.approx(DY + F * math.tan(math.radians(f)), abs=1e-9)
    assert info["fnum_real"] == pytest.approx(_expected_fnum(), rel=1e-9)
    p = tmp_path / "dec.json"
    p.write_text(json.dumps(spec))
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "no paraxial data" in out and "surface 2 is decentred by 1 mm" in out
    assert f"{DY + F * math.tan(math.radians(6.0)):.6f}" in out and f"{_expected_fnum():.6f}" in out
    assert main(["info", str(p), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["paraxial"] is None and "decentred" in got["reason"]
    assert got["fnum_real"] == pytest.approx(info["fnum_real"], rel=1e-12)


def test_tilted_doublet_chief_rays_match_optiland():
    """tests/data/zmx/decentered_tilted_doublet.zmx (element decentred 0.5 mm, tilted 2°; stop on the first surface
    at z = 0, object at infinity): the chief ray at angle θ passes the origin. Optiland traces that ray to the image
    plane (global coordinates); raywave's info gives the same point in the image plane's frame."""
    from optiland.fileio import load_zemax_file
    from optiland.rays import RealRays

    path = "tests/data/zmx/decentered_tilted_doublet.zmx"
    lens = load_lens(path)
    with pytest.raises(ValueError, match="paraxial quantities are undefined"):
        lens.paraxial()
    info = real_ray_info(lens)
    o = load_zemax_file(path)
    wl = lens.primary_wavelength
    for f, xy in zip(info["fields"], info["chief_image_xy"]):
        t = math.radians(f)
        x0, y0, z0, L, M, N = 0.0, -5.0 * math.tan(t), -5.0, 0.0, math.sin(t), math.cos(t)
        rays = RealRays(np.array([x0]), np.array([y0]), np.array([z0]), np.array([L]), np.array([M]),
                        np.array([N]), np.ones(1), np.full(1, wl))
        o.surfaces.trace(rays, skip=1)
        with torch.no_grad():
            ours = lens.trace_to_image(RayBundle.create([[x0, y0, z0]], [[L, M, N]], wl))
            np.testing.assert_allclose(ours.o[0].numpy(), [float(rays.x[0]), float(rays.y[0]), float(rays.z[0])],
                                       rtol=0, atol=1e-9)
            local = lens.image_coordinates(ours).o[0, :2].numpy()
        np.testing.assert_allclose(xy, local, rtol=0, atol=1e-9)
    assert 5.0 < info["fnum_real"] < 6.5  # the untilted doublet's working F/# is 5.60 (EFL 33.6 mm, EPD 6 mm)
