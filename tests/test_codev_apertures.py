"""CODE V .seq files as they come (issue 44): the image surface's thickness (a defocus), glass codes (never vd =
0), rectangular apertures (REX / REY), aperture decentres (ADX / ADY), annular obscurations (CIR OBS + CIR HOL),
a vignetting message that names the obscuration, and one file per unsupported aperture feature with its named
error (.seq and .zmx). Checks are analytic (paraxial image shift, ray counts, area ratios)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aperture_singlet import R_STOP, grid, parallel_rays, singlet_seq
from raywave.cli.lens_commands import format_info, lens_info
from raywave.io import read_lens_spec
from raywave.io.errors import LensFileError
from raywave.lens.analysis import real_ray_efl
from raywave.lens.build import lens_from_spec, load_lens

def _seq(tmp_path, ap="", glass="NBK7_SCHOTT", last="98.47", defocus="0.0", name="a.seq"):
    p = tmp_path / name
    p.write_text(singlet_seq(ap=ap, glass=glass, last=last, defocus=defocus))
    return p


# ---------------------------------------------------------------------------- image thickness
def test_image_surface_thickness_is_a_defocus(tmp_path):
    """SI 0 δ: the image plane sits δ beyond the last surface's thickness (CODE V's and rayoptics' reading). With
    the last thickness at the paraxial focus, the image plane is δ past the paraxial image (analytic shift)."""
    base = load_lens(_seq(tmp_path, name="b.seq"))
    bfl = base.paraxial().bfl
    focused = _seq(tmp_path, last=f"{bfl:.12f}", name="f.seq")
    for delta in (0.0, 0.25, -0.4):
        p = _seq(tmp_path, last=f"{bfl:.12f}", defocus=f"{delta}", name=f"d{delta}.seq")
        spec = read_lens_spec(p)
        assert spec["surfaces"][-1]["thickness"] == pytest.approx(bfl + delta, abs=1e-12)
        lens = lens_from_spec(spec)
        par = lens.paraxial()
        assert par.efl == pytest.approx(base.paraxial().efl, rel=1e-14)  # a defocus changes no first-order data
        z_img = float(lens.vertex_z()[-1].detach()) + float(lens.surfaces[-1].thickness.detach())
        assert z_img - par.image_z_paraxial == pytest.approx(delta, abs=1e-9)
    assert read_lens_spec(focused)["surfaces"][-1]["thickness"] == pytest.approx(bfl, abs=1e-12)


# ---------------------------------------------------------------------------- glass codes
@pytest.mark.parametrize("code, nd, vd", [("517642", 1.517, 64.2), ("517642.251", 1.517, 64.2),
                                          ("517000.520000", 1.517, 52.0), ("620041.603200", 1.620041, 60.32)])
def test_glass_codes(tmp_path, code, nd, vd):
    spec = read_lens_spec(_seq(tmp_path, glass=code))
    m = spec["surfaces"][1]["material"]["model"]
    assert m["nd"] == pytest.approx(nd, abs=1e-12) and m["vd"] == pytest.approx(vd, abs=1e-12)


def test_glass_code_with_zero_abbe_number_is_an_error(tmp_path):
    with pytest.raises(LensFileError, match=r":12: surface 2: glass code '517000.000000' has Abbe number vd = 0"):
        read_lens_spec(_seq(tmp_path, glass="517000.000000"))


# ---------------------------------------------------------------------------- apertures
@pytest.mark.parametrize("ap, dx, dy", [("  REX 4.24\n  REY 1.92", 0.0, 0.0),
                                        ("  REX 4.24; REY 1.92; ADX 0.5; ADY -0.25", 0.5, -0.25)])
def test_rectangular_and_decentred_aperture_vignetting_count(tmp_path, ap, dx, dy):
    spec = read_lens_spec(_seq(tmp_path, ap=ap))
    want_ap = {"shape": "rectangle", "half_width_x": 4.24, "half_width_y": 1.92}
    if dx or dy:
        want_ap["decenter"] = [dx, dy]
    assert spec["surfaces"][0]["aperture"] == want_ap
    x, y = grid()
    out = lens_from_spec(spec).trace(parallel_rays(x, y))
    want = (np.abs(x - dx) <= 4.24) & (np.abs(y - dy) <= 1.92) & (x * x + y * y <= R_STOP**2)
    assert bool((out.valid.numpy() == want).all())


def test_decentred_cir_is_a_real_aperture(tmp_path):
    spec = read_lens_spec(_seq(tmp_path, ap="  CIR 3.0\n  ADX 1.5; ADY 0.5"))
    assert spec["surfaces"][0]["aperture"] == {"shape": "circle", "radius": 3.0, "decenter": [1.5, 0.5]}
    x, y = grid()
    out = lens_from_spec(spec).trace(parallel_rays(x, y))
    want = ((x - 1.5) ** 2 + (y - 0.5) ** 2 <= 9.0) & (x * x + y * y <= R_STOP**2)
    assert bool((out.valid.numpy() == want).all())


def test_annular_obscuration_area_ratio(tmp_path):
    """CIR OBS 3 with CIR HOL 1.5 inside it: a ring blocks 1.5 <= r <= 3: 1 − (3² − 1.5²)/5² = 0.73 passes."""
    spec = read_lens_spec(_seq(tmp_path, ap="  CIR OBS 3.0\n  CIR HOL 1.5"))
    assert spec["surfaces"][0]["aperture"] == {"shape": "none", "obscuration": {
        "shape": "annulus", "inner_radius": 1.5, "radius": 3.0}}
    x, y = grid(step=0.04, half=R_STOP)
    inside = x * x + y * y <= R_STOP**2
    out = lens_from_spec(spec).trace(parallel_rays(x[inside], y[inside]))
    assert float(out.valid.double().mean()) == pytest.approx(1 - (9.0 - 2.25) / 25.0, abs=4e-3)


def test_rectangular_and_decentred_obscurations(tmp_path):
    spec = read_lens_spec(_seq(tmp_path, ap="  REX OBS 1.0; REY OBS 0.5; ADX OBS 0.2"))
    assert spec["surfaces"][0]["aperture"] == {"shape": "none", "obscuration": {
        "shape": "rectangle", "half_width_x": 1.0, "half_width_y": 0.5, "decenter": [0.2, 0.0]}}


def test_vignetting_message_names_the_obscuration(tmp_path, capsys):
    """A central obscuration (CIR OBS 2) blocks the near-axis ray of the real-ray EFL: the error says which surface
    and what blocks it; `raywave info` still prints the paraxial table, with that note."""
    lens = load_lens(_seq(tmp_path, ap="  CIR OBS 2.0\n  SLB 'secondary mirror shadow'"))
    with pytest.raises(ValueError, match=r"real-ray EFL ray at height 0\.005 mm is vignetted: surface 0 "
                                         r"\('secondary mirror shadow'\) blocks it .*its central obscuration \(circle "
                                         r"of radius 2 mm\).*height outside it"):
        real_ray_efl(lens)
    assert float(real_ray_efl(lens, height=3.0).detach()) == pytest.approx(lens.paraxial().efl, rel=2e-3)
    info = lens_info(lens)
    assert math.isnan(info["efl_real"]) and "central obscuration" in format_info(info)


# ---------------------------------------------------------------------------- one file per unsupported feature
@pytest.mark.parametrize("ap, msg", [
    ("  ELX 2.0", "surface 1: elliptical aperture (ELX) is not supported"),
    ("  POL 2.0", "surface 1: polygon aperture (POL) is not supported"),
    ("  CIR 3.0\n  ARO 30", "surface 1: ARO 30: a rotated aperture is not supported"),
    ("  REX 2.0", "surface 1: a rectangular aperture needs both REX and REY (got only REX)"),
    ("  CIR HOL 1.0", "surface 1: a hole (CIR HOL) without an obscuration (CIR OBS) around it"),
    ("  CIR OBS 1.0\n  CIR HOL 2.0", "surface 1: the hole (CIR HOL 2) must lie inside the obscuration (CIR OBS 1)"),
    ("  ADX 0.5", "surface 1: the surface has a decentred aperture (ADX / ADY) but no clear aperture (CIR r)"),
])
def test_unsupported_seq_aperture_features_are_named(tmp_path, ap, msg):
    with pytest.raises(LensFileError) as e:
        read_lens_spec(_seq(tmp_path, ap=ap))
    assert msg in str(e.value) and (".seq:11:" in str(e.value) or ".seq:12:" in str(e.value))  # the line


ZMX_HEAD = ("VERS 190513 80 123457\nMODE SEQ\nUNIT MM X W X CM MR CPMM\nENPD 10\nWAVM 1 0.5875618 1\n"
            "SURF 0\n  DISZ INFINITY\nSURF 1\n  DISZ 10\n{ap}\nSURF 2\n  STOP\n  CURV 0.01\n  DISZ 3\n"
            "  GLAS N-BK7 0 0 1.5168 64.17\nSURF 3\n  CURV -0.01\n  DISZ 95\nSURF 4\n  DISZ 0\n")


@pytest.mark.parametrize("ap, msg", [
    ("  ELAP 2 1", "surface 1: elliptical aperture (ELAP) is not supported"),
    ("  ELOB 2 1", "surface 1: elliptical obscuration (ELOB) is not supported"),
    ("  SPID 0.1 4", "surface 1: spider obscuration (SPID) is not supported"),
    ("  UDAP 0 0", "surface 1: user-defined aperture (UDAP) is not supported"),
    ("  OBSC 3 2", "surface 1: OBSC minimum radius 3.0 must be >= 0 and < the maximum radius 2.0"),
    ("  SQAP 0 2", "surface 1: empty aperture (SQAP half widths 0.0 x 2.0)"),
])
def test_unsupported_zmx_aperture_features_are_named(tmp_path, ap, msg):
    p = tmp_path / "u.zmx"
    p.write_text(ZMX_HEAD.format(ap=ap))
    with pytest.raises(LensFileError) as e:
        read_lens_spec(p)
    assert msg in str(e.value) and ":10:" in str(e.value)
