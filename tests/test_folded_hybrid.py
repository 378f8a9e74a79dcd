"""The ray-wave engine on folded, decentred, tilted and mirrored lenses (issue 18): the rays leaving the last surface
are put into the image-space frame (raywave/lens/frames.py: the local frame after the last coordinate break, z
along the light), where the DOE plane and the sensor lie perpendicular to its axis.

Checked against the same lens without the fold: a fold mirror (one reflection: the z flip) and a periscope (two)
give the unfolded lens's PSFs and centres to ~1e-12; a decentred image space gives the straight lens's PSF with
its centre moved by minus the decentre (blank DOE: nothing on it marks the decentre); a tilt + decentre followed by
its inverse is the straight lens; the PSF crop of a tilted image space is centred where the real chief ray meets
the tilted sensor (Lens.trace_to_image + Lens.image_coordinates, the tracer checked against Optiland in
tests/test_zmx_corpus.py)."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from raywave.doe import BlankDOE, CubicDOE
from raywave.hybrid import HybridLens
from raywave.io.zmx import read_zmx
from raywave.lens.build import lens_from_spec
from raywave.lens.frames import ImageSpaceLens, image_space, image_space_frame
from raywave.lens.sources import chief_ray
from raywave.rays.bundle import RayBundle

ZMX = Path(__file__).resolve().parent / "data" / "zmx"


def _cb(dx=0.0, dy=0.0, tx=0.0, ty=0.0, tz=0.0, order=0, t=0.0):
    return {"type": "coordinate_break", "decenter": [dx, dy], "tilt": [tx, ty, tz], "order": order, "thickness": t}


MIRROR = {"radius": "inf", "thickness": 0.0, "material": "mirror"}
SINGLET = [{"radius": 30.0, "thickness": 3.0, "material": {"index": 1.5168}, "stop": True},
           {"radius": -200.0, "thickness": 10.0}]
BASE = {"system_aperture": {"epd": 4.0}, "wavelengths": {"values": [0.55], "primary": 0},
        "fields": {"type": "angle", "values": [0.0, 1.0]}}


def _lens(*tail, last=None):
    """The singlet followed by ``tail`` surfaces (its last thickness ``last`` when given)."""
    head = [SINGLET[0], dict(SINGLET[1], thickness=SINGLET[1]["thickness"] if last is None else last)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lens_from_spec(dict(BASE, surfaces=head + list(tail)))


def _psfs(lens, d, doe, fields, ks=16, **kw):
    """PSFs at 0.55 µm on 2 µm pixels (24 traced nodes across the beam: these are comparisons, not accuracy).

    The DOE-plane edge unless ``stop_edge`` is given: these tests check that a fold is a rigid motion to 1e-10,
    and with the exit-pupil edge the node grid reaches far past the beam (its ripple band, here 0.33 mm around a
    0.39 mm beam 5 mm before focus), where the outermost node rays (pupil radius ~2.5× the stop's) converge or
    fail differently with the fold's rounding: those PSFs agree to ~4e-7 (test_fold_with_the_exit_pupil_edge)."""
    kw.setdefault("stop_edge", "doe")
    hl = HybridLens(lens, doe, d, sensor_pitch=0.002, **kw)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return hl.psf_result(fields, [0.55], ks=ks, rays=24)


def _cubic():
    return CubicDOE(15.0, (160, 160), 0.004)  # 0.64 mm square, an asymmetric phase (x³ + y³)


def test_image_space_view_is_the_lens_itself_without_folds():
    lens = _lens(last=49.0)
    assert image_space(lens) is lens
    view = image_space(_lens(_cb(dy=0.1, t=30.0), last=19.0))
    assert isinstance(view, ImageSpaceLens) and image_space(view) is view
    assert float(view.image_z().detach()) == pytest.approx(3.0 + 19.0 + 30.0)
    with pytest.raises(AttributeError, match="read-only"):
        view.name = "x"


def test_fold_mirror_psf_equals_the_unfolded_lens():
    """The corpus fold (AC254-100, COORDBRK 45°, flat mirror, COORDBRK 45°, thickness −24.513): light leaves along
    −z of the image plane's frame; the engine's PSFs and centres equal those of the doublet without the fold."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = read_zmx(ZMX / "fold_mirror_doublet.zmx")
    folded = lens_from_spec(spec)
    flat = dict(spec, surfaces=spec["surfaces"][:3])
    flat["surfaces"][2] = dict(flat["surfaces"][2], thickness=spec["surfaces"][2]["thickness"]
                               - spec["surfaces"][5]["thickness"])
    straight = lens_from_spec(flat)
    assert image_space_frame(folded)[2] == -1
    f = [(0.0, 0.0), (0.3, 1.0)]
    doe = CubicDOE(20.0, (200, 200), 0.004)
    a = _psfs(folded, 18.0, doe, f)
    b = _psfs(straight, 40.0 + 18.0, doe, f)
    assert float(b.psf.max()) > 0.01
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.center.numpy(), b.center.numpy(), rtol=0, atol=1e-12)
    assert float(a.center[1, 0, 1]) == pytest.approx(1.17189, abs=1e-4)  # ~100 mm · tan 1° on the tilted sensor


def test_a_folded_lens_file_without_a_doe_gets_the_default_one():
    """`raywave psf` on a folded lens file with no DOE (the corpus fold): the default blank DOE is sized and placed
    in the image-space frame (it used to fail: "beam_half_extent is not supported for a lens with coordinate
    breaks"); its PSF equals the unfolded doublet's with the same DOE on the same plane (40 mm further along)."""
    from raywave.assembly.build import load_hybrid

    path = ZMX / "fold_mirror_doublet.zmx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hl = load_hybrid(path, fields=[[0.0, 1.0], [0.0, 0.0]], field_type="angle", stop_edge="doe")
        spec = read_zmx(path)
    info = hl.doe_info
    assert info["source"] == "default" and info["distance_rule"] in ("half_way", "beam_fit", "before_caustic")
    assert 0 < info["distance"] < 24.513
    flat = dict(spec, surfaces=spec["surfaces"][:3])
    flat["surfaces"][2] = dict(flat["surfaces"][2], thickness=spec["surfaces"][2]["thickness"]
                               - spec["surfaces"][5]["thickness"])
    straight = lens_from_spec(flat)
    gap = spec["surfaces"][2]["thickness"]
    b = _psfs(straight, gap + info["distance"], hl.doe, [(0.0, 1.0)])
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = HybridLens(hl.lens, hl.doe, info["distance"], sensor_pitch=0.002, stop_edge="doe").psf_result(
            [(0.0, 1.0)], [0.55], ks=16, rays=24)
    assert float(b.psf.max()) > 0.01
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("second", [-45.0, 45.0], ids=["periscope", "u-turn"])
def test_two_mirrors_psf_equals_the_unfolded_lens(second):
    """Two flat mirrors (a periscope, light along +z again 8 mm higher; or a U-turn, light along −z): the image-space
    frame is a rigid motion of the unfolded lens's, and the PSFs agree."""
    folded = _lens(_cb(tx=45.0), MIRROR, _cb(tx=45.0, t=-8.0), _cb(tx=second), MIRROR, _cb(tx=second, t=31.0))
    straight = _lens(last=10.0 + 8.0 + 31.0)
    rot, origin, sign = image_space_frame(folded)
    assert sign == 1 and float(rot[2, 2]) == pytest.approx(-1.0 if second > 0 else 1.0)
    f = [(0.2, -0.7)]
    a = _psfs(folded, 26.0, _cubic(), f)
    b = _psfs(straight, 10.0 + 8.0 + 26.0, _cubic(), f)
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.center.numpy(), b.center.numpy(), rtol=0, atol=1e-12)


def test_fold_with_the_exit_pupil_edge():
    """The periscope with the default exit-pupil edge (Fresnel step): the same PSF as the unfolded lens to ~1e-6
    (see :func:`_psfs`), the same centre to 1e-12."""
    folded = _lens(_cb(tx=45.0), MIRROR, _cb(tx=45.0, t=-8.0), _cb(tx=-45.0), MIRROR, _cb(tx=-45.0, t=31.0))
    straight = _lens(last=10.0 + 8.0 + 31.0)
    f = [(0.2, -0.7)]
    a = _psfs(folded, 26.0, _cubic(), f, stop_edge=None)
    b = _psfs(straight, 10.0 + 8.0 + 26.0, _cubic(), f, stop_edge=None)
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=2e-6)
    np.testing.assert_allclose(a.center.numpy(), b.center.numpy(), rtol=0, atol=1e-12)


def test_decentred_image_space_moves_the_crop_only():
    """A decentre after the lens (DOE and sensor moved by (0.3, −0.2) mm): with a blank DOE larger than the beam the
    PSF is the straight lens's, its centre in the sensor's own coordinates moved by minus the decentre."""
    dec = _lens(_cb(dx=0.3, dy=-0.2, t=36.0), last=13.0)
    straight = _lens(last=49.0)
    doe = BlankDOE((700, 700), 0.004)  # 2.8 mm: the 1° beam stays on it after the decentre
    f = [(0.0, 0.0), (0.5, 1.0)]
    a, b = _psfs(dec, 30.0, doe, f), _psfs(straight, 43.0, doe, f)
    assert float(b.psf.sum((-1, -2)).min()) == pytest.approx(1.0)  # every PSF lit
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.center.numpy(), (b.center - torch.tensor([0.3, -0.2], dtype=torch.float64)).numpy(),
                               rtol=0, atol=1e-12)


def test_tilt_and_decentre_followed_by_their_inverse_is_the_straight_lens():
    """COORDBRK (decentre, tilts x, y, z; order 0) and the same break negated with order 1 (its inverse) before the
    DOE: the image-space frame is the straight one up to rounding, and so are the PSFs (a real DOE)."""
    brk = dict(dx=0.4, dy=-0.25, tx=3.0, ty=-2.0, tz=15.0)
    inv = {k: -v for k, v in brk.items()}
    pair = _lens(_cb(**brk, t=0.0), _cb(**inv, order=1, t=36.0), last=13.0)
    assert pair.is_folded
    straight = _lens(last=49.0)
    f = [(0.3, 0.8)]
    a = _psfs(pair, 30.0, _cubic(), f)
    b = _psfs(straight, 43.0, _cubic(), f)
    np.testing.assert_allclose(a.psf.numpy(), b.psf.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.center.numpy(), b.center.numpy(), rtol=0, atol=1e-12)


def test_tilted_image_space_crop_follows_the_real_chief_ray():
    """DOE and sensor tilted (0.6°, −0.4°) and decentred after the lens: the PSF is centred where the real chief ray meets
    the tilted image plane, in that plane's coordinates, and the DOE plane is perpendicular to the tilted axis."""
    lens = _lens(_cb(dx=0.05, tx=0.6, ty=-0.4, t=36.0), last=13.0)
    f = (0.4, 0.9)
    r = _psfs(lens, 30.0, BlankDOE((700, 700), 0.004), [f])
    with torch.no_grad():
        cr = lens.image_coordinates(lens.trace_to_image(chief_ray(lens, f, 0.55)))
    np.testing.assert_allclose(r.center[0, 0].numpy(), cr.o[0, 0, 0, :2].numpy(), rtol=0, atol=1e-12)
    assert float(r.psf.sum()) == pytest.approx(1.0) and bool(torch.isfinite(r.psf).all())
    # the engine's DOE plane: the chief ray's view-frame point lies doe_distance after the last vertex along the
    # tilted local axis (its z in the view frame), i.e. the plane perpendicular to that axis
    view = image_space(lens)
    rot, origin, _ = image_space_frame(lens)
    with torch.no_grad():
        out = view.trace(chief_ray(lens, f, 0.55), apertures=False)
        g = lens.trace(chief_ray(lens, f, 0.55), apertures=False)
    z_doe = float(lens.vertex_z()[-1].detach()) + 30.0
    at = out.propagate_to_z(z_doe, 1.0)
    p_global = g.o + g.d * ((at.opl - g.opl) / 1.0).unsqueeze(-1)  # the same point, reached in global coordinates
    local = (p_global - origin) @ rot
    assert float(local[0, 0, 0, 2]) == pytest.approx(30.0, abs=1e-10)


def test_exit_pupil_edge_on_the_folded_lens():
    """stop_edge='exit_pupil' (the exit pupil found in the image-space frame) also gives the unfolded lens's PSF."""
    folded = _lens(_cb(tx=45.0), MIRROR, _cb(tx=45.0, t=-39.0), last=10.0)
    straight = _lens(last=49.0)
    kw = dict(stop_edge="exit_pupil", edge_step="fresnel")
    ha = HybridLens(folded, _cubic(), 26.0, sensor_pitch=0.002, **kw)
    hb = HybridLens(straight, _cubic(), 36.0, sensor_pitch=0.002, **kw)
    assert ha.exit_pupil_z() == pytest.approx(hb.exit_pupil_z(), abs=1e-9)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, b = ha.psf((0.1, 0.6), ks=16, rays=24), hb.psf((0.1, 0.6), ks=16, rays=24)
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-10)


def test_engine_refusals_name_the_problem():
    from raywave.assembly.build import hybrid_from_spec

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = read_zmx(ZMX / "decentered_tilted_doublet.zmx")
    with pytest.raises(ValueError, match=r"paraxial entrance pupil.*surface 2 is tilted by 2 degrees"):
        hybrid_from_spec(spec)
    with pytest.raises(ValueError, match="doe_distance must lie between"):
        HybridLens(_lens(_cb(tx=45.0), MIRROR, _cb(tx=45.0, t=-39.0), last=10.0), _cubic(), 40.0)


def test_trace_record_is_in_each_surfaces_frame():
    """The view's record holds every surface's points in its own frame (where its aperture is defined)."""
    lens = _lens(_cb(dx=0.2, tx=10.0), {"radius": "inf", "thickness": 30.0, "aperture": {"shape": "circle",
                                                                                         "radius": 3.0}}, last=6.0)
    view = image_space(lens)
    rays = RayBundle.create(torch.tensor([[0.1, 0.2, -1.0]], dtype=torch.float64),
                            torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), 0.55)
    with torch.no_grad():
        _, rec = view.trace(rays, record=True)
        g = lens.trace(rays, stop=4)
    local = lens.surface_coordinates(g, 3)
    np.testing.assert_allclose(torch.stack(rec.points[4], -1).detach().numpy(), local.o.detach().numpy(), atol=1e-13)
    assert abs(float(local.o[0, 2])) < 1e-12  # on the plane surface's vertex plane


def test_cli_psf_on_the_folded_example(tmp_path, capsys):
    """`raywave psf examples/folded_hybrid.json` (fold mirror + decentred, tilted DOE and sensor block): exit 0, the
    PSF centred on the tilted sensor where the real chief ray meets it."""
    from raywave.cli.main import main

    path = Path(__file__).resolve().parents[1] / "examples" / "folded_hybrid.json"
    assert main(["psf", str(path), "--field", "0", "0.5", "--ks", "16", "--rays", "24", "--json",
                 "-o", str(tmp_path / "psf.npy")]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    lens = lens_from_spec(_example_spec(path))
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cr = lens.image_coordinates(lens.trace_to_image(chief_ray(lens, (0.0, 0.5))))
    np.testing.assert_allclose(out["center_mm"], cr.o[0, 0, 0, :2].numpy(), atol=1e-9)
    assert np.load(tmp_path / "psf.npy").shape[-2:] == (16, 16)


def _example_spec(path):
    from raywave.io import read_hybrid_spec

    return read_hybrid_spec(path)[0]


def test_straight_axis_models_and_the_map_grid_refuse_a_folded_lens():
    """The comparison models and the PSF map's chief-ray field grid read the lens along one straight axis: on a
    folded lens they refuse by name instead of returning a wrong PSF; the ray-wave model is accepted."""
    from raywave.imaging.psfmap import field_grid
    from raywave.models import make_model

    folded = _lens(_cb(tx=45.0), MIRROR, _cb(tx=45.0, t=-39.0), last=10.0)
    hl = HybridLens(folded, BlankDOE((64, 64), 0.004), 1.0, sensor_pitch=0.002)
    for name in ("paraxial", "pupil", "raytrace", "exit_pupil"):
        with pytest.raises(ValueError, match="straight optical axis"):
            make_model(name, hl)
    assert make_model("raywave", hl) is not None and make_model("raywave_doe", hl) is not None
    # built directly, not through make_model: the same clear refusal
    from raywave.models import ExitPupilModel, LocalGratingModel, ParaxialModel, PupilModel

    for cls in (ExitPupilModel, ParaxialModel, PupilModel, LocalGratingModel):
        with pytest.raises(ValueError, match=f"the {cls.name!r} model assumes one straight optical axis"):
            cls(hl)
    with pytest.raises(ValueError, match="fields="):
        field_grid(hl, (2, 2), sensor_size=(1.0, 1.0))
