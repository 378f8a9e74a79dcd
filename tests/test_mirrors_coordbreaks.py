"""Mirrors (GLAS MIRROR / CODE V REFL / JSON "mirror") and coordinate breaks (COORDBRK), checked against closed
forms and against the same lens built without them (the corpus test, tests/test_zmx_corpus.py, compares the .zmx
files with Optiland).

Conventions (OpticStudio's, which Optiland follows): after a mirror the thicknesses are negative and the light
travels toward −z; the paraxial index changes sign at each reflection, so the image-space EFL of a single concave
mirror of radius R (R < 0: centre of curvature toward the incoming light) is R / 2 (negative, n' = −1) and its
magnitude |R| / 2. A coordinate break with order 0 decentres, then tilts about x, the new y, the new z
(right-handed); order 1 runs the same steps backwards.
"""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from raywave.io import LensFileError, read_lens_spec, write_lens_spec
from raywave.io.json_format import validate_spec
from raywave.io.spec import canonical_spec
from raywave.io.zmx import read_zmx
from raywave.lens import analysis
from raywave.lens.build import lens_from_spec, lens_to_spec
from raywave.lens.paraxial import ParaxialUndefinedError
from raywave.rays.bundle import RayBundle
from raywave.surfaces.interaction import CoordinateBreak

ZMX = Path(__file__).resolve().parent / "data" / "zmx"


def _mirror_spec(radius, conic=0.0, epd=10.0, thickness=None):
    return {"surfaces": [{"type": "standard", "radius": radius, "conic": conic,
                          "thickness": radius / 2 if thickness is None else thickness, "material": "mirror",
                          "stop": True}],
            "system_aperture": {"epd": epd}, "wavelengths": {"values": [0.5], "primary": 0}}


def _cb(dx=0.0, dy=0.0, tx=0.0, ty=0.0, tz=0.0, order=0, t=0.0):
    return {"type": "coordinate_break", "decenter": [dx, dy], "tilt": [tx, ty, tz], "order": order, "thickness": t}


def _no_ap(spec):
    """The surfaces without the stop aperture (a lens writes the one its entrance pupil gave the stop)."""
    return [{k: v for k, v in s.items() if k != "aperture"} for s in spec["surfaces"]]


def _read(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = read_zmx(ZMX / f"{name}.zmx")
        return spec, lens_from_spec(spec)


# ---------------------------------------------------------------------------------------------------- mirrors
@pytest.mark.parametrize("radius", [-100.0, 100.0, -37.5])
def test_single_mirror_first_order(radius):
    """EFL = R/2 (image space, n' = -1), BFL = R/2 from the mirror (the focus lies at z = R/2), F/# = |R|/2 / EPD."""
    lens = lens_from_spec(_mirror_spec(radius))
    p = lens.paraxial()
    assert p.efl == pytest.approx(radius / 2, rel=1e-14) and abs(p.efl) == pytest.approx(abs(radius) / 2, rel=1e-14)
    with torch.no_grad():
        assert float(analysis.real_ray_efl(lens)) == pytest.approx(radius / 2, rel=1e-6)  # the same sign from rays
    assert p.bfl == pytest.approx(radius / 2, rel=1e-14)
    assert p.image_z_paraxial == pytest.approx(radius / 2, rel=1e-14)
    assert p.fnum == pytest.approx(abs(radius) / 2 / 10.0, rel=1e-14)
    assert p.epd == 10.0 and p.ep_z == 0.0 and p.xp_z == 0.0 and p.xpd == pytest.approx(10.0)


def test_parabolic_mirror_focuses_perfectly_and_sphere_has_the_exact_spherical_aberration():
    # a paraboloid images a distant axial point perfectly: every ray meets the axis at the focus, same OPL
    lens = lens_from_spec(_mirror_spec(-200.0, conic=-1.0, epd=80.0))
    r = torch.linspace(-36, 36, 9, dtype=torch.float64)
    o = torch.stack([r * 0.3, r, torch.full_like(r, -5.0)], -1)
    with torch.no_grad():
        out = lens.trace_to_image(RayBundle.create(o, torch.tensor([0.0, 0.0, 1.0]).expand_as(o), 0.5))
    assert bool(out.valid.all()) and float(out.d[:, 2].max()) < 0  # reflected toward -z
    np.testing.assert_allclose(out.o[:, :2].detach().numpy(), 0.0, atol=1e-12)
    np.testing.assert_allclose(out.o[:, 2].detach().numpy(), -100.0, rtol=1e-15)
    np.testing.assert_allclose(out.opl.detach().numpy(), float(out.opl[4].detach()), rtol=1e-14)
    # a sphere: the marginal ray's OPD against the reference sphere (centre: the paraxial focus F at z = R/2,
    # through the exit-pupil centre = the vertex), by hand: reflect at M on the sphere, meet |p - F| = |R|/2
    R, h, wl = -100.0, 10.0, 0.5
    sph = lens_from_spec(_mirror_spec(R, epd=2 * h))
    opd, _, _, valid = analysis.wavefront_opd(sph, (0.0, 0.0), pupil=(torch.tensor([1.0]), torch.tensor([0.0])))
    m = np.array([0.0, h, R + math.sqrt(R * R - h * h)])  # the sag is toward the incoming light
    nrm = (m - [0.0, 0.0, R]) / abs(R)
    d = np.array([0.0, 0.0, 1.0]) - 2 * nrm[2] * nrm
    w = m - [0.0, 0.0, R / 2]
    b, c = w @ d, w @ w - (R / 2) ** 2
    s = min((-b - math.sqrt(b * b - c), -b + math.sqrt(b * b - c)), key=abs)  # the point near M
    exact = -(m[2] + s) / (wl * 1e-3)  # OPL(chief) - OPL(ray), both from the plane z = 0 of the vertex
    assert bool(valid.all())
    assert float(opd.reshape(-1)[0].detach()) == pytest.approx(exact, rel=1e-9)
    assert exact == pytest.approx(h ** 4 / (4 * abs(R) ** 3) / (wl * 1e-3), rel=0.01)  # Seidel: ~5 waves


def test_cassegrain_matches_the_two_mirror_formula():
    """Classical Cassegrain of the corpus: f = f1 f2 / (f1 + f2 - d) (real-is-positive: f1 = 400, f2 = -133.3,
    d = 300) = 1600 mm; paraboloid + hyperboloid: the axial image is perfect at the design's 400 mm."""
    spec, lens = _read("cassegrain")
    f1, f2, d = 400.0, -800.0 / 6.0, 300.0
    p = lens.paraxial()
    assert p.efl == pytest.approx(f1 * f2 / (f1 + f2 - d), rel=1e-12)
    assert p.bfl == pytest.approx(400.0, rel=1e-12) and p.fnum == pytest.approx(8.0, rel=1e-12)
    assert float(analysis.rms_spot_radius(lens, fields=[0.0]).max().detach()) < 1e-9
    opd, _, _, v = analysis.wavefront_opd(lens, (0.0, 0.0))
    assert float(opd[v].abs().max()) < 1e-6


def test_mirror_in_json_and_zmx_round_trips(tmp_path):
    spec, lens = _read("cassegrain")
    assert [s["material"] for s in spec["surfaces"]] == ["mirror", "mirror"]
    assert [s.interaction.kind for s in lens.surfaces] == ["reflection", "reflection"]
    assert all(s.material.is_air for s in lens.surfaces)  # the medium after a mirror is the one before it
    back = lens_to_spec(lens)
    assert _no_ap(canonical_spec(back)) == _no_ap(canonical_spec(spec))
    for ext in ("json", "zmx"):
        write_lens_spec(spec, tmp_path / f"c.{ext}")
        assert canonical_spec(read_lens_spec(tmp_path / f"c.{ext}"))["surfaces"] == canonical_spec(spec)["surfaces"]


def test_mangin_mirror_in_glass_traces_back_through_the_glass():
    """A mirror behind glass: the medium after it is the glass; the return leg refracts out through the front."""
    spec = {"surfaces": [{"radius": -300.0, "thickness": 5.0, "material": {"index": 1.5}, "stop": True},
                         {"radius": -200.0, "thickness": -5.0, "material": "mirror"},
                         {"radius": -300.0, "thickness": -80.0, "material": "air"}],
            "system_aperture": {"epd": 20.0}, "wavelengths": {"values": [0.5], "primary": 0}}
    lens = lens_from_spec(spec)
    assert lens.surfaces[1].material.name == lens.surfaces[0].material.name
    # paraxial power by hand: refraction, reflection in glass (n' = -n), refraction back out (n: -1.5 -> -1)
    n, c1, c2 = 1.5, -1 / 300.0, -1 / 200.0
    m = np.eye(2)
    for phi, t_over_n in (((n - 1) * c1, 5.0 / n), (-2 * n * c2, -5.0 / -n), ((-1 + n) * c1, None)):
        m = np.array([[1, 0], [-phi, 1]]) @ m
        if t_over_n is not None:
            m = np.array([[1, t_over_n], [0, 1]]) @ m
    assert lens.paraxial().efl == pytest.approx(-1 / -m[1, 0], rel=1e-12)  # n' = -1: EFL = -1 / power
    y = torch.tensor([0.5, 2.0, 5.0], dtype=torch.float64)
    o = torch.stack([torch.zeros_like(y), y, torch.full_like(y, -5.0)], -1)
    out = lens.trace(RayBundle.create(o, torch.tensor([0.0, 0.0, 1.0]).expand_as(o), 0.5))
    assert bool(out.valid.all()) and float(out.d[:, 2].max()) < 0


# ------------------------------------------------------------------------------------------ coordinate breaks
def test_compound_tilt_is_intrinsic_and_order_one_runs_backwards():
    """OpticStudio: order 0 = decentre, tilt x, then about the *new* y, then the new z; order 1 = tilt z, new y, new
    x, then decentre. So one break equals the chain of single-step breaks, and (order 0; d, t) followed by
    (order 1; -t, -d) is the identity (OpticStudio's way to restore the axis)."""
    def frame(*breaks):
        surfaces = [_cb(**b) for b in breaks] + [{"radius": "inf", "thickness": 1.0, "stop": True}]
        lens = lens_from_spec({"surfaces": surfaces})
        return [v.detach() for v in lens.surface_frames()[0][-1]]

    a = dict(dx=0.3, dy=-1.2, tx=12.0, ty=-7.0, tz=31.0)
    rot, t = frame(a)
    rot2, t2 = frame(dict(dx=0.3, dy=-1.2), dict(tx=12.0), dict(ty=-7.0), dict(tz=31.0))
    np.testing.assert_allclose(rot.numpy(), rot2.numpy(), atol=1e-15)
    np.testing.assert_allclose(t.numpy(), t2.numpy(), atol=1e-15)
    rot3, t3 = frame(dict(a, order=1))
    rot4, t4 = frame(dict(tz=31.0), dict(ty=-7.0), dict(tx=12.0), dict(dx=0.3, dy=-1.2))
    np.testing.assert_allclose(rot3.numpy(), rot4.numpy(), atol=1e-15)
    np.testing.assert_allclose(t3.numpy(), t4.numpy(), atol=1e-15)
    rot5, t5 = frame(a, dict(dx=-0.3, dy=1.2, tx=-12.0, ty=7.0, tz=-31.0, order=1))
    np.testing.assert_allclose(rot5.numpy(), np.eye(3), atol=1e-15)
    np.testing.assert_allclose(t5.numpy(), 0.0, atol=1e-15)
    # right-handed: +45 deg about x turns the local z axis toward -y (Optiland's and OpticStudio's sign)
    np.testing.assert_allclose(frame(dict(tx=45.0))[0][:, 2].numpy(), [0, -math.sqrt(0.5), math.sqrt(0.5)], atol=1e-15)
    assert CoordinateBreak(tilt_x=1.0).transform()[0].dtype == torch.float64


def test_fold_mirror_is_the_unfolded_lens_on_the_image_plane():
    """The corpus fold (COORDBRK 45°, flat mirror, COORDBRK 45°, negative thickness) traces exactly like the same
    doublet without the fold: same intercepts in the image plane's frame, EFL and BFL with the sign of n' = -1."""
    spec, folded = _read("fold_mirror_doublet")
    kinds = [s.interaction.kind for s in folded.surfaces]
    assert kinds == ["refraction"] * 3 + ["coordinate_break", "reflection", "coordinate_break"]
    flat = dict(spec, surfaces=spec["surfaces"][:3])
    flat["surfaces"][2] = dict(flat["surfaces"][2], thickness=spec["surfaces"][2]["thickness"]
                               - spec["surfaces"][5]["thickness"])
    straight = lens_from_spec(flat)
    pf, ps = folded.paraxial(), straight.paraxial()
    assert pf.efl == pytest.approx(-ps.efl, rel=1e-14) and pf.fnum == pytest.approx(ps.fnum, rel=1e-14)
    assert pf.epd == ps.epd and pf.ep_z == ps.ep_z and pf.xpd == pytest.approx(ps.xpd, rel=1e-14)
    assert pf.bfl == pytest.approx(-(ps.bfl - spec["surfaces"][2]["thickness"]), rel=1e-12)
    with torch.no_grad():
        assert float(analysis.real_ray_efl(folded)) == pytest.approx(pf.efl, rel=1e-6)  # in the image frame
    x = torch.tensor([0.0, 0.3, -0.5, 0.2], dtype=torch.float64)
    y = torch.tensor([0.0, 0.6, 0.4, -0.7], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.004, 0.008, 1.0], [0.012, -0.01, 1.0], [-0.008, 0.006, 1.0]],
                     dtype=torch.float64)
    rays = RayBundle.create(torch.stack([x, y, torch.full_like(x, -5.0)], -1), d, 0.55)
    with torch.no_grad():
        a = folded.image_coordinates(folded.trace_to_image(rays))
        b = straight.trace_to_image(rays)
    assert bool(a.valid.all()) and bool(b.valid.all())
    np.testing.assert_allclose(a.o[:, :2].numpy(), b.o[:, :2].numpy(), atol=1e-12)
    np.testing.assert_allclose(a.o[:, 2].numpy(), 0.0, atol=1e-12)
    np.testing.assert_allclose(a.d.numpy() * [1, 1, -1], b.d.numpy(), atol=1e-14)  # the beam leaves along -z local
    np.testing.assert_allclose(a.opl.numpy(), b.opl.numpy(), rtol=1e-14)
    # in global coordinates the beam left along +y (the fold turned the axis by 90 degrees)
    g = folded.trace_to_image(rays)
    assert float(g.d[0, 1]) == pytest.approx(1.0, abs=1e-15)
    # the spot diagram works on the tilted image plane and equals the straight lens's
    sf, ss = analysis.rms_spot_radius(folded), analysis.rms_spot_radius(straight)
    np.testing.assert_allclose(sf.detach().numpy(), ss.detach().numpy(), rtol=1e-9)


def test_decentre_is_a_translation_of_the_rays():
    """A decentred element (COORDBRK dy, element, COORDBRK -dy) traces like the centred element met by rays
    shifted by -dy (and shifted back afterwards)."""
    elem = [{"radius": 20.0, "thickness": 3.0, "material": {"index": 1.6}},
            {"radius": -35.0, "thickness": 2.0}]
    base = {"surfaces": [{"radius": "inf", "thickness": 4.0, "stop": True}], "system_aperture": {"epd": 6.0},
            "wavelengths": {"values": [0.55], "primary": 0}}
    dec = dict(base, surfaces=base["surfaces"] + [_cb(dx=0.2, dy=0.7)] + elem + [_cb(dx=-0.2, dy=-0.7, t=30.0)])
    cen = dict(base, surfaces=base["surfaces"] + elem[:1] + [dict(elem[1], thickness=32.0)])
    ld, lc = lens_from_spec(dec), lens_from_spec(cen)
    o = torch.tensor([[0.0, 0.0, -3.0], [1.0, -0.5, -3.0], [-1.2, 1.1, -3.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.01, 0.02, 1.0], [-0.02, 0.0, 1.0]], dtype=torch.float64)
    shift = torch.tensor([0.2, 0.7, 0.0], dtype=torch.float64)
    with torch.no_grad():
        a = ld.trace_to_image(RayBundle.create(o, d, 0.55))
        b = lc.trace_to_image(RayBundle.create(o - shift, d, 0.55))
    np.testing.assert_allclose(a.o.numpy(), (b.o + shift).numpy(), atol=1e-12)
    np.testing.assert_allclose(a.d.numpy(), b.d.numpy(), atol=1e-15)
    with pytest.raises(ParaxialUndefinedError, match="surface 2 is decentred by 0.728011 mm from the optical axis"):
        ld.paraxial()
    assert ld.epd == 6.0  # the stop lies before the break: its entrance pupil is still defined
    with pytest.raises(ParaxialUndefinedError):
        lens_from_spec(dict(dec, system_aperture={"f_number": 4.0}))  # needs the EFL: undefined


def test_tilted_plate_is_undefined_but_a_tilted_flat_mirror_or_dummy_is_not():
    plate = {"surfaces": [{"radius": "inf", "thickness": 2.0, "stop": True}, _cb(tx=10.0),
                          {"radius": "inf", "thickness": 3.0, "material": {"index": 1.5}},
                          {"radius": "inf", "thickness": 20.0}], "system_aperture": {"epd": 4.0}}
    with pytest.raises(ParaxialUndefinedError, match="surface 2 is a plane tilted by 10 degrees"):
        lens_from_spec(plate).paraxial()
    dummy = dict(plate, surfaces=[dict(s, material="air") if s.get("type") != "coordinate_break" else s
                                  for s in plate["surfaces"]])
    p = lens_from_spec(dummy).paraxial()
    assert math.isinf(p.efl)


def test_ray_wave_engine_takes_folds_and_mirrors_but_refuses_an_undefined_paraxial_model():
    """The engine models folded and mirrored lenses in their image-space frame (tests/test_folded_hybrid.py); a lens
    whose paraxial entrance pupil is undefined (a tilted powered surface) is refused, naming the surface."""
    from raywave.assembly.build import hybrid_from_spec

    for name in ("fold_mirror_doublet", "cassegrain", "newtonian_telescope"):
        _, lens = _read(name)
        assert lens.wave_support_problem() is None, name
    spec, _ = _read("fold_mirror_doublet")
    hl = hybrid_from_spec(spec, doe_pitch=0.01, doe_size=2.0, doe_distance=10.0)
    assert hl.sensor_z() - hl.doe_z() == pytest.approx(24.513 - 10.0)
    spec, _ = _read("decentered_tilted_doublet")
    with pytest.raises(ValueError, match=r"ray-wave engine.*paraxial entrance pupil.*surface 2 is tilted by 2 degrees"):
        hybrid_from_spec(spec)
    _, lens = _read("newtonian_telescope")
    with pytest.raises(ValueError, match="wavefront_opd is not supported for a lens with coordinate breaks"):
        analysis.wavefront_opd(lens)


def test_coordinate_break_spec_validation_and_zmx_errors(tmp_path):
    good = {"surfaces": [{"radius": "inf", "thickness": 1.0, "stop": True}, _cb(tx=3.0, t=2.0),
                         {"radius": "inf", "thickness": 1.0}]}
    validate_spec(good)
    bad = dict(good, surfaces=[good["surfaces"][0], dict(_cb(order=2), material="N-BK7", tilt=[1.0, 2.0]),
                               good["surfaces"][2]])
    with pytest.raises(LensFileError) as e:
        validate_spec(bad)
    msg = str(e.value)
    assert "surfaces[1].material" in msg and "surfaces[1].tilt: must have 3 entries" in msg and "order" in msg
    with pytest.raises(ValueError, match=r"surfaces\[1\]: a coordinate break cannot be the aperture stop"):
        lens_from_spec(dict(good, surfaces=[good["surfaces"][0] | {"stop": False}, _cb() | {"stop": True},
                                            good["surfaces"][2]]))
    text = (ZMX / "fold_mirror_doublet.zmx").read_bytes().decode()
    p = tmp_path / "x.zmx"
    p.write_bytes(text.replace("  PARM 6 0", "  PARM 6 0\r\n  PARM 7 1.0", 1).encode())
    with pytest.raises(LensFileError, match="COORDBRK PARM 7 is not a coordinate-break parameter"):
        read_zmx(p)
    # a DOE plane right after a coordinate break is read (on the break's axis; tests/test_zmx_doe_after_fold.py),
    # 5 mm along the light (negative thicknesses after the mirror), so DISZ 5.0 there is refused by name
    lines = text.split("\r\n")
    k = max(i for i, ln in enumerate(lines) if ln.startswith("SURF "))
    doe = ["SURF 99", "  TYPE BINARY_2", "  CURV 0.0", "  DISZ 5.0", "  XDAT 1 0", "  XDAT 2 5"]
    p.write_bytes("\r\n".join(lines[:k] + doe + lines[k:]).replace("SURF 99", f"SURF {lines[k].split()[1]}")
                 .replace(f"{lines[k]}\r\n  TYPE STANDARD", f"SURF {int(lines[k].split()[1]) + 1}\r\n  TYPE STANDARD")
                 .encode())
    with pytest.raises(LensFileError, match=r"the DOE plane must lie before the image: its thickness \(DISZ\) must "
                                            r"be < 0 mm \(negative after an odd number of mirrors"):
        read_zmx(p)


def test_coordinate_breaks_round_trip_through_json_and_zmx(tmp_path):
    for name in ("fold_mirror_doublet", "newtonian_telescope", "decentered_tilted_doublet"):
        spec, lens = _read(name)
        cbs = [s for s in spec["surfaces"] if s["type"] == "coordinate_break"]
        assert cbs and all(set(s) <= {"type", "decenter", "tilt", "order", "thickness", "comment"} for s in cbs)
        assert _no_ap(canonical_spec(lens_to_spec(lens))) == _no_ap(canonical_spec(spec))
        for ext in ("json", "zmx"):
            write_lens_spec(spec, tmp_path / f"{name}.{ext}")
            back = read_lens_spec(tmp_path / f"{name}.{ext}")
            assert canonical_spec(back)["surfaces"] == canonical_spec(spec)["surfaces"], (name, ext)


def test_codev_refl_is_a_mirror(tmp_path):
    p = tmp_path / "m.seq"
    p.write_text("RDM;LEN\nTITLE 'SPHERICAL MIRROR'\nEPD 10\nDIM M\nWL 500\nYAN 0.0\nSO 0.0 1e10\n"
                 "S -100.0 -50.0 REFL\n  STO\nSI 0.0 0.0\nGO\n")
    spec = read_lens_spec(p)
    assert spec["surfaces"][0]["material"] == "mirror"
    assert lens_from_spec(spec).paraxial().efl == pytest.approx(-50.0, rel=1e-14)


def test_gradients_flow_through_frames():
    """Thicknesses stay differentiable through coordinate breaks and mirrors (dEFL/dt of the Newtonian's primary
    spacing is 0: a flat fold does not change the power; the image intercept moves with the final thickness)."""
    _, lens = _read("newtonian_telescope")
    rays = RayBundle.create(torch.tensor([[0.0, 10.0, -5.0]], dtype=torch.float64),
                            torch.tensor([[0.0, 0.01, 1.0]], dtype=torch.float64), 0.55)
    out = lens.trace_to_image(rays)
    out.o.sum().backward()
    g = [s.thickness.grad for s in lens.surfaces]
    assert all(x is not None and torch.isfinite(x) for x in g)
    assert float(g[-1].abs()) > 0


def test_straight_axis_analyses_name_the_surface_that_breaks_their_axis():
    """Analyses written for one straight +z axis refuse a fold by the coordinate break's index, and field_curvature
    (focus positions measured along +z) refuses light leaving toward -z by the last mirror's index."""
    _, folded = _read("fold_mirror_doublet")
    for fn in (analysis.field_curvature, analysis.best_focus_z, analysis.distortion):
        with pytest.raises(ValueError, match=r"not supported for a lens with coordinate breaks \(surface 3 "):
            fn(folded)
    with pytest.raises(ValueError, match=r"field_curvature is not supported for a lens whose light leaves toward -z "
                                         r"\(surface 0 is the last of an odd number of mirrors\)"):
        analysis.field_curvature(lens_from_spec(_mirror_spec(-100.0)))
