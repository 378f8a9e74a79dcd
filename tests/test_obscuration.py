"""Central obscurations in the aperture model, the JSON lens format, .zmx (OBSC / OBSQ / OBDC, annular CLAP) and
CODE V .seq (CIR OBS r); all checks analytic (Optiland reads CODE V's CIR OBS as a clear aperture, and has no
OBSC), with Optiland's annular CLAP as an independent reading."""

from __future__ import annotations

import copy

import pytest
import torch

from aperture_singlet import singlet_seq, singlet_zmx, zmx_head
from raywave.io import read_lens_spec
from raywave.io.errors import LensFileError
from raywave.io.json_format import validate_spec
from raywave.lens.build import lens_from_spec, lens_to_spec, load_lens, save_lens
from raywave.rays.bundle import RayBundle
from raywave.surfaces.aperture import (CircularAperture, Obscuration, OpenAperture, SquareAperture,
                                       aperture_from_spec)

try:  # the test-only reference; imported at collection, as tests/test_zmx_corpus.py does
    import optiland.fileio as _optiland_fileio
except ImportError:  # pragma: no cover
    _optiland_fileio = None

R, R_OBS = 5.0, 2.0


def _spec(aperture0=None, obs_surface=None):
    """An f = 100 mm N-BK7-like singlet (model glass), stop on surface 0 (EPD 10 mm, R = 5 mm)."""
    surfaces = [
        {"type": "standard", "radius": 102.4, "thickness": 3.6, "material": {"model": {"nd": 1.5168, "vd": 64.17}},
         "stop": True, "semi_diameter": 12.7, "aperture": aperture0},
        {"type": "standard", "radius": -102.4, "thickness": 98.47, "material": "air", "semi_diameter": 12.7,
         "aperture": obs_surface},
    ]
    return {"format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"},
            "name": "obscured singlet", "object": {"distance": "inf"}, "system_aperture": {"epd": 2 * R},
            "fields": {"type": "angle", "values": [0.0]}, "wavelengths": {"values": [0.5875618], "primary": 0},
            "surfaces": surfaces}


def _axial_rays(heights_x, heights_y=None):
    x = torch.as_tensor(heights_x, dtype=torch.float64)
    y = torch.zeros_like(x) if heights_y is None else torch.as_tensor(heights_y, dtype=torch.float64)
    o = torch.stack([x, y, torch.full_like(x, -1.0)], -1)
    return RayBundle.create(o, torch.tensor([0.0, 0.0, 1.0]), 0.5875618)


def test_aperture_contains_and_slack_analytic():
    a = CircularAperture(R, Obscuration("circle", radius=R_OBS))
    r = torch.tensor([0.0, 1.0, 1.999, 2.001, 3.5, 4.999, 5.001, 7.0], dtype=torch.float64)
    ok = a.contains(r, torch.zeros_like(r))
    assert ok.tolist() == [False, False, False, True, True, True, False, False]
    s = a.slack(r, torch.zeros_like(r))
    torch.testing.assert_close(s, torch.minimum(R - r, r - R_OBS), rtol=0, atol=1e-12)
    assert torch.isfinite(s).all()
    # gradients finite at the centre too (no NaN from the sqrt)
    x = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    a.slack(x, torch.zeros_like(x)).sum().backward()
    assert torch.isfinite(x.grad).all()
    # decentred circle, rectangle, open aperture
    d = Obscuration("circle", radius=1.0, decenter=(2.0, -1.0))
    assert d.blocks(torch.tensor([2.5, 0.0]), torch.tensor([-1.0, 0.0])).tolist() == [True, False]
    q = SquareAperture(3.0, Obscuration("rectangle", half_width_x=1.0, half_width_y=0.5))
    assert q.contains(torch.tensor([0.0, 0.0, 1.5, 2.9]), torch.tensor([0.4, 0.6, 0.0, 2.9])).tolist() == [
        False, True, True, True]
    o = OpenAperture({"shape": "circle", "radius": 1.0})
    assert o.extent is None
    assert o.contains(torch.tensor([0.5, 100.0]), torch.tensor([0.0, 0.0])).tolist() == [False, True]
    with pytest.raises(ValueError, match="obscuration radius"):
        Obscuration("circle", radius=0.0)


@pytest.mark.parametrize("where", ["stop", "other"])
def test_trace_blocks_inside_obscuration(where):
    """Parallel rays at radius < r_obs are blocked, between r_obs and R pass, beyond R are blocked."""
    obs = {"shape": "circle", "radius": R_OBS}
    if where == "stop":
        spec = _spec({"shape": "circle", "radius": R, "obscuration": obs})
    else:
        spec = _spec(None, {"shape": "none", "obscuration": obs})
    lens = lens_from_spec(validate_spec(spec))
    h = [0.0, 0.5, 1.9, 2.1, 3.0, 4.9, 5.1]
    out = lens.trace(_axial_rays(h))
    if where == "stop":
        assert out.valid.tolist() == [False, False, False, True, True, True, False]
    else:  # the obscuration sits on surface 1: the ray height there is (1 - 3.6 (n-1)/n / 102.4 ...) h, close to h
        assert out.valid.tolist()[:3] == [False, False, False] and out.valid.tolist()[3:6] == [True] * 3
    assert torch.isfinite(out.o).all() and torch.isfinite(out.d).all()


def test_geometric_collected_power_fraction():
    """Uniform parallel rays over the entrance pupil: the fraction passing an obscured stop = 1 − (r_obs/R)²."""
    lens = lens_from_spec(validate_spec(_spec({"shape": "circle", "radius": R,
                                               "obscuration": {"shape": "circle", "radius": R_OBS}})))
    n = 401
    c = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 * R - R
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    inside = (xx**2 + yy**2) <= R * R
    out = lens.trace(_axial_rays(xx[inside], yy[inside]))
    frac = float(out.valid.double().mean())
    assert frac == pytest.approx(1 - (R_OBS / R) ** 2, rel=5e-3)


@pytest.mark.parametrize("edge", [dict(stop_edge="doe"), dict(edge_step="asm")], ids=["doe", "exit_pupil_asm"])
def test_psf_engine_power_of_obscured_pupil(edge):
    """The ray-wave engine (HybridLens field at the DOE plane): the power of an obscured circular pupil over the
    unobscured one is 1 − (r_obs/R)² (analytic; free propagation conserves it), within a few %: the DOE-plane
    edge and the exact exit-pupil construction. The Fresnel edge step warns instead: the obscuration's shadow on the
    DOE plane (0.075 mm radius) is not large against the edge's Fresnel zone (0.05 mm); it gets 0.859. The default
    (adaptive) step's error estimate (issue 47: the zone 0.34 × the shadow's radius, over 0.3) takes the exact
    construction there: 0.8405 against the unobscured pupil's default."""
    from raywave.doe import PixelDOE
    from raywave.hybrid import HybridLens, StopEdgeWarning
    from raywave.lens.build import ideal_lens

    n, p = 400, 2e-3
    powers = []
    for r_obs in (None, 0.4):
        lens = ideal_lens(5.0, f_number=8, wavelengths=(0.55,))
        stop = lens.surfaces[lens.stop_index]
        if r_obs is not None:
            r_stop = float(stop.aperture.radius)
            stop.aperture.obscuration = Obscuration("circle", radius=r_obs * r_stop)
        hl = HybridLens(lens, PixelDOE(torch.zeros(n, n, dtype=torch.float64), p), 2.0, sensor_pitch=2e-3, **edge)
        fd = hl.doe_fields((0.0, 0.0), 0.55, rays=24)[0][0]
        powers.append(float(fd.power.detach()))
    ratio = powers[1] / powers[0]
    assert ratio == pytest.approx(1 - 0.4**2, rel=0.01)  # measured 0.8380 (doe), 0.8388 (exit pupil, asm)
    if edge.get("stop_edge") == "doe":
        with pytest.warns(StopEdgeWarning, match="edge_step='asm'"):
            HybridLens(lens, PixelDOE(torch.zeros(n, n, dtype=torch.float64), p), 2.0, sensor_pitch=2e-3,
                       edge_step="fresnel").doe_fields((0.0, 0.0), 0.55, rays=24)
        unobscured = ideal_lens(5.0, f_number=8, wavelengths=(0.55,))
        fds = [HybridLens(x, PixelDOE(torch.zeros(n, n, dtype=torch.float64), p), 2.0,
                          sensor_pitch=2e-3).doe_fields((0.0, 0.0), 0.55, rays=24)[0][0] for x in (unobscured, lens)]
        assert [fd.info.edge_step for fd in fds] == ["fresnel", "asm"]
        assert float(fds[1].power.detach()) / float(fds[0].power.detach()) == pytest.approx(1 - 0.4**2, rel=0.005)


def test_json_round_trip(tmp_path):
    for ap0, ap1 in (({"shape": "circle", "radius": R, "obscuration": {"shape": "circle", "radius": R_OBS,
                                                                          "decenter": [0.1, -0.2]}}, None),
                     (None, {"shape": "none", "obscuration": {"shape": "rectangle", "half_width_x": 1.0,
                                                              "half_width_y": 0.5}})):
        lens = lens_from_spec(validate_spec(_spec(ap0, ap1)))
        save_lens(lens, tmp_path / "l.json")
        back = load_lens(tmp_path / "l.json")
        s0, s1 = lens_to_spec(lens)["surfaces"], lens_to_spec(back)["surfaces"]
        assert [s["aperture"] for s in s0] == [s["aperture"] for s in s1]
        want = ap1 if ap0 is None else ap0
        got = s1[1]["aperture"] if ap0 is None else s1[0]["aperture"]
        assert got["obscuration"] == want["obscuration"]


@pytest.mark.parametrize("ap, msg", [
    ({"shape": "circle", "radius": 5, "obscuration": {"shape": "circle", "radius": 2, "colour": 1}}, "unknown key"),
    ({"shape": "circle", "radius": 5, "obscuration": {"shape": "circle", "radius": 6}}, "covers the whole"),
    ({"shape": "circle", "radius": 5, "obscuration": {"shape": "oval", "radius": 1}}, "obscuration shape"),
    ({"shape": "circle", "radius": 5, "obscuration": {"shape": "circle", "radius": -1}}, "must be > 0"),
    ({"shape": "circle", "radius": 5, "obscuration": {"shape": "rectangle", "radius": 1}}, "belongs to a 'circle'"),
    ({"shape": "none"}, "needs an \"obscuration\""),
    ({"shape": "none", "radius": 3, "obscuration": {"radius": 1}}, "'none' aperture has only"),
])
def test_json_errors(ap, msg):
    with pytest.raises(LensFileError, match=msg):
        validate_spec(_spec(None, ap))


def test_json_stop_needs_clear_aperture():
    with pytest.raises(LensFileError, match="stop needs a clear aperture"):
        validate_spec(_spec({"shape": "none", "obscuration": {"radius": 1.0}}))


_ZMX = singlet_zmx("{obs}", name="OBSCURED SINGLET")
_SEQ = singlet_seq("{obs}", title="OBSCURED SINGLET")


def _read(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return read_lens_spec(p)


def test_zmx_and_seq_give_the_same_obscuration(tmp_path):
    zmx = _read(tmp_path, "o.zmx", _ZMX.format(obs="  OBSC 0 2.0"))
    seq = _read(tmp_path, "o.seq", _SEQ.format(obs="  CIR OBS 2.0"))
    want = {"shape": "none", "obscuration": {"shape": "circle", "radius": 2.0}}
    assert zmx["surfaces"][0]["aperture"] == want
    assert seq["surfaces"][0]["aperture"] == want
    # addressed form: CIR S1 OBS r after the surfaces
    seq2 = _read(tmp_path, "o2.seq", _SEQ.format(obs="").replace("GO", "CIR S1 OBS 2.0\nGO"))
    assert seq2["surfaces"][0]["aperture"] == want
    # an obscuration addressed to the image surface (S4 here) is refused, not dropped
    with pytest.raises(LensFileError, match="image surface"):
        _read(tmp_path, "o3.seq", _SEQ.format(obs="").replace("GO", "CIR S4 OBS 2.0\nGO"))
    # the same rays are blocked by both lenses
    h = [0.0, 1.5, 2.5, 4.5]
    for spec in (zmx, seq):
        out = lens_from_spec(spec).trace(_axial_rays(h))
        assert out.valid.tolist() == [False, False, True, True]


def test_zmx_decentre_annulus_and_rectangle(tmp_path):
    zmx = _read(tmp_path, "d.zmx", _ZMX.format(obs="  OBDC 0.5 -0.25\n  OBSC 0 2.0"))
    assert zmx["surfaces"][0]["aperture"]["obscuration"] == {"shape": "circle", "radius": 2.0,
                                                             "decenter": [0.5, -0.25]}
    sq = _read(tmp_path, "q.zmx", _ZMX.format(obs="  OBSQ 1.5 0.5"))
    assert sq["surfaces"][0]["aperture"]["obscuration"] == {"shape": "rectangle", "half_width_x": 1.5,
                                                            "half_width_y": 0.5}
    ann = _read(tmp_path, "a.zmx", _ZMX.format(obs="  CLAP 2.0 6.0 0"))
    assert ann["surfaces"][0]["aperture"] == {"shape": "circle", "radius": 6.0,
                                              "obscuration": {"shape": "circle", "radius": 2.0}}
    # issue 44: an annular obscuration (a ring), a decentred clear aperture, a rectangle of unequal half widths
    ring = _read(tmp_path, "b.zmx", _ZMX.format(obs="  OBSC 1.0 2.0"))
    assert ring["surfaces"][0]["aperture"] == {"shape": "none", "obscuration": {"shape": "annulus",
                                                                                "inner_radius": 1.0, "radius": 2.0}}
    dec = _read(tmp_path, "c.zmx", _ZMX.format(obs="  CLAP 0 6.0 0\n  OBDC 0.5 0"))
    assert dec["surfaces"][0]["aperture"] == {"shape": "circle", "radius": 6.0, "decenter": [0.5, 0.0]}
    rect = _read(tmp_path, "e.zmx", _ZMX.format(obs="  SQAP 4.24 1.92"))
    assert rect["surfaces"][0]["aperture"] == {"shape": "rectangle", "half_width_x": 4.24, "half_width_y": 1.92}
    with pytest.raises(LensFileError, match="OBSC minimum radius 3.0 must be >= 0 and < the maximum radius 2.0"):
        _read(tmp_path, "f.zmx", _ZMX.format(obs="  OBSC 3.0 2.0"))


def test_zmx_write_read_round_trip(tmp_path):
    from raywave.io import write_lens_spec

    for obs in ("  OBSC 0 2.0\n  OBDC 0.5 -0.25", "  CLAP 2.0 6.0 0", "  OBSQ 1.5 0.5", "  OBSC 1.0 2.0",
                "  SQAP 4.24 1.92\n  OBDC 0.5 -0.25", "  CLAP 0 6.0 0\n  OBDC 0.5 0"):
        spec = _read(tmp_path, "r.zmx", _ZMX.format(obs=obs))
        write_lens_spec(spec, tmp_path / "w.zmx")
        back = read_lens_spec(tmp_path / "w.zmx")
        assert back["surfaces"][0]["aperture"] == spec["surfaces"][0]["aperture"]


def test_annular_clap_matches_optiland(tmp_path):
    """Optiland reads CLAP rmin rmax as an annulus: same pass/block for rays across it."""
    if _optiland_fileio is None:
        pytest.skip("optiland is not installed")
    p = tmp_path / "a.zmx"
    p.write_text(_ZMX.format(obs="  CLAP 2.0 6.0 0"))
    ol = _optiland_fileio.load_zemax_file(str(p))
    ap = ol.surfaces[1].aperture  # surface 1 (after the object)
    x = [0.0, 1.5, 2.5, 5.5, 6.5]
    import numpy as np
    ol_ok = np.asarray(ap.contains(np.array(x), np.zeros(len(x))), dtype=bool).tolist()
    ours = aperture_from_spec(read_lens_spec(p)["surfaces"][0]["aperture"])
    rw_ok = ours.contains(torch.tensor(x, dtype=torch.float64), torch.zeros(len(x), dtype=torch.float64)).tolist()
    assert rw_ok == ol_ok == [False, False, True, True, False]


def test_exit_pupil_model_obscured_pupil():
    """The exit-pupil (Huygens) model: an obscured stop (the chief ray blocked on axis) collects 1 − ε² of the power
    (used pupil cells), and the on-axis peak irradiance per collected power scales as 1 − ε² (peak ∝ area²)."""
    from raywave.lens.build import ideal_lens
    from raywave.models.exit_pupil import huygens_psf

    eps, out = 0.5, []
    for obscured in (False, True):
        lens = ideal_lens(5.0, f_number=8, wavelengths=(0.55,))
        stop = lens.surfaces[lens.stop_index]
        if obscured:
            stop.aperture.obscuration = Obscuration("circle", radius=eps * float(stop.aperture.radius))
        out.append(huygens_psf(lens, (0.0, 0.0), 0.55, ks=9, pitch=0.5e-3, n_pupil=96, oversample=1))
    (h0, h1), want = out, 1 - eps**2
    assert h1.n_rays / h0.n_rays == pytest.approx(want, rel=0.03)
    peak = [float(h.psf[4, 4]) * h.energy_fraction for h in out]  # per unit power reaching the sensor plane
    assert peak[1] / peak[0] == pytest.approx(want, rel=0.02)


_CASS_ZMX = zmx_head("CASSEGRAIN", 100, 0.55) + """SURF 1
  COMM "secondary shadow"
  TYPE STANDARD
  CURV 0.0
  DISZ 150
  OBSC 0 13
SURF 2
  STOP
  TYPE STANDARD
  CURV -2.5E-3
  DISZ -150
  GLAS MIRROR 0 0 0 0
  DIAM 50 1 0 0 1 ""
SURF 3
  TYPE STANDARD
  CURV -7.5E-3
  DISZ 200
  GLAS MIRROR 0 0 0 0
  DIAM 13 1 0 0 1 ""
SURF 4
  TYPE STANDARD
  CURV 0.0
  DISZ 0
"""

_CASS_SEQ = """RDM
TITLE 'CASSEGRAIN'
EPD 100.0
DIM M
WL 550.0
REF 1
YAN 0.0
SO 0.0 1e13
S 0.0 150.0
  CIR OBS 13.0
STO -400.0 -150.0 REFL
  CIR 50.0
S -133.3333333333333 200.0 REFL
  CIR 13.0
SI 0.0 0.0
GO
"""


def test_cassegrain_zmx_and_seq(tmp_path):
    """A Cassegrain (spherical primary R −400, secondary R −133.3 at −150, EPD 100) with the secondary's shadow as
    OBSC 0 13 / CIR OBS 13 on a dummy surface in front: both files give the same aperture and the same rays; the
    fraction of an axial beam reaching the image is 1 − (13/50)²; EFL = f1·m = 200·4 = 800 mm (analytic)."""
    want = {"shape": "none", "obscuration": {"shape": "circle", "radius": 13.0}}
    n = 201
    c = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 100.0 - 50.0
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    inside = xx**2 + yy**2 <= 50.0**2
    valid = []
    for name, text in (("c.zmx", _CASS_ZMX), ("c.seq", _CASS_SEQ)):
        spec = _read(tmp_path, name, text)
        assert spec["surfaces"][0]["aperture"] == want
        lens = lens_from_spec(spec)
        assert float(lens.paraxial().efl) == pytest.approx(800.0, rel=1e-9)
        valid.append(lens.trace_to_image(_axial_rays(xx[inside], yy[inside])).valid)
    assert torch.equal(valid[0], valid[1])
    assert float(valid[0].double().mean()) == pytest.approx(1 - (13 / 50) ** 2, rel=3e-3)


def test_obscured_stop_from_zmx_and_seq(tmp_path):
    """An obscuration on the stop: the stop keeps a clear circle (sized from the EPD) with the obscuration."""
    zmx = _ZMX.format(obs="").replace('  STOP\n', '  STOP\n  OBSC 0 1.5\n')
    seq = _SEQ.format(obs="").replace("STO 102.4 3.6 NBK7_SCHOTT\n  CIR 12.7", "STO 102.4 3.6 NBK7_SCHOTT\n  CIR 12.7\n"
                                      "  CIR OBS 1.5")
    for name, text in (("s.zmx", zmx), ("s.seq", seq)):
        spec = _read(tmp_path, name, text)
        ap = spec["surfaces"][1]["aperture"]
        assert ap == {"shape": "circle", "radius": 12.7, "obscuration": {"shape": "circle", "radius": 1.5}}
        lens = lens_from_spec(spec)
        assert float(lens.surfaces[1].aperture.radius) == pytest.approx(R, rel=1e-6)  # from EPD 10 (stop in air)
        out = lens.trace(_axial_rays([0.0, 1.4, 1.6, 4.9, 5.1]))
        assert out.valid.tolist() == [False, False, True, True, False]
