"""CODE V surface decentres and tilts (XDE / YDE / ZDE, ADE / BDE / CDE; basic, DAR, BEN, REV) read as coordinate
breaks (raywave/io/codev.py, ``_breaks``), and a .zmx DOE plane right after a coordinate break or a mirror.

Optiland 0.6.3 is no reference here (it reads every CODE V decentre as a per-surface DAR, drops ZDE and takes ADE as
a right-handed tilt), so these checks are analytic or equivalences:

* CODE V's ADE and BDE are left-handed, CDE right-handed (the KDP-2 program manual, "Surface tilts": "ALPHA and
  BETA are left-handed positive and GAMMA is right-handed positive ... agrees with CODE-V and ACCOS-V. In ZEMAX,
  the ALPHA and BETA sign conventions are right-handed positive"; rayoptics' ``euler2opt`` negates alpha and beta
  for the same reason). So ADE, BDE, CDE = a, b, c is an OpticStudio coordinate break with tilts −a, −b, +c, and a
  positive ADE turns a surface's normal toward +y, a positive BDE toward −x;
* a flat surface in air tilted and returned (DAR) does nothing to the rays;
* a basic decentre of the stop equals the .zmx with a COORDBRK before it; a decentred image plane equals the .zmx
  with a COORDBRK before the image;
* a 45° fold mirror with BEN equals the .zmx COORDBRK + MIRROR + COORDBRK, and both give the unfolded lens's image;
* REV with the values of a DEC undoes it;
* a tilted plate shifts a ray by t·sinθ(1 − cosθ/√(n² − sin²θ)) in the direction of its tilted normal.
"""

import math
import warnings

import numpy as np
import pytest
import torch

from raywave.io import LensFileError, read_lens_spec
from raywave.lens.build import lens_from_spec
from raywave.rays.bundle import RayBundle

GLASS = "1.5168:64.17"  # the model glass nd 1.5168, vd 64.17 ({"model": ...}), as GLAS ___BLANK 1 0 1.5168 64.17
ZMX_GLASS = "  GLAS ___BLANK 1 0 1.5168 64.17\n"


def _seq(tmp_path, body: str, name: str = "x.seq"):
    """A .seq (EPD 4 mm, 550 nm, on-axis and 1° fields, distant object) with the surface lines ``body``."""
    p = tmp_path / name
    p.write_text("RDM\nTITLE 'decentre test'\nEPD 4\nDIM M\nWL 550\nREF 1\nYAN 0 1\nSO 0 1e10\n" + body + "SI 0 0\n")
    return p


def _zmx(tmp_path, surfaces: list, name: str = "x.zmx"):
    """A .zmx (ENPD 4, 0.55 µm, distant object) with the SURF blocks ``surfaces`` (text after "SURF k") and an
    image surface."""
    head = ("VERS 190513 80 123457\nMODE SEQ\nNAME decentre test\nUNIT MM X W X CM MR CPMM\nENPD 4\n"
            "FTYP 0 0 1 1 0 0 0\nXFLN 0\nYFLN 0\nWAVM 1 0.55 1\nPWAV 1\n"
            "SURF 0\n  TYPE STANDARD\n  CURV 0.0\n  DISZ INFINITY\n")
    body = "".join(f"SURF {k}\n{s}" for k, s in enumerate(surfaces + ["  TYPE STANDARD\n  CURV 0.0\n  DISZ 0\n"],
                                                             start=1))
    p = tmp_path / name
    p.write_text(head + body)
    return p


def _std(curv: float, disz: float, glass: str = "", stop: bool = False) -> str:
    return ("  STOP\n" if stop else "") + f"  TYPE STANDARD\n  CURV {curv!r}\n  DISZ {disz!r}\n" + glass


def _cbz(dx=0.0, dy=0.0, tx=0.0, ty=0.0, tz=0.0, order=0, disz=0.0) -> str:
    parms = "".join(f"  PARM {i} {v!r}\n" for i, v in enumerate((dx, dy, tx, ty, tz, order), start=1))
    return f"  TYPE COORDBRK\n{parms}  DISZ {disz!r}\n"


def _lens(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lens_from_spec(read_lens_spec(path))


def _rays(shift=(0.0, 0.0)):
    """25 skew rays (0.55 µm) from z = −5 mm, all through the 4 mm stop."""
    g = torch.linspace(-1.0, 1.0, 5, dtype=torch.float64)
    y, x = torch.meshgrid(g, g, indexing="ij")
    o = torch.stack([0.7 * x.reshape(-1) + 0.1 + shift[0], y.reshape(-1) + shift[1],
                     torch.full((25,), -5.0, dtype=torch.float64)], -1)
    d = torch.tensor([0.01, -0.02, 1.0], dtype=torch.float64)
    return RayBundle.create(o, (d / d.norm()).expand_as(o), 0.55)


def _image(lens, rays=None):
    """The rays on the image plane, in its own frame (x, y on the sensor), all valid."""
    with torch.no_grad():
        out = lens.image_coordinates(lens.trace_to_image(_rays() if rays is None else rays))
    assert bool(out.valid.all())
    return out


def _same(a, b, atol):
    """The same x, y on the image plane (its own frame; z is 0 there for a lens with breaks, the global z
    without), directions and optical paths."""
    for u, v in ((a.o[:, :2], b.o[:, :2]), (a.d, b.d), (a.opl, b.opl)):
        np.testing.assert_allclose(u.numpy(), v.numpy(), rtol=0, atol=atol)


SINGLET = f"S 30 3 {GLASS}\n  STO\nS -200 "  # + its back distance


# ------------------------------------------------------------------------------------------------ (a) DAR, flat
def test_dar_on_a_flat_surface_in_air_changes_no_ray(tmp_path):
    """A flat air surface 5 mm after the singlet, moved by (0.2, −0.3, 0.5) mm and tilted (10°, −7°, 20°) with DAR:
    the rays, their optical paths and the image plane are those of the lens without it (1e-12)."""
    plain = _lens(_seq(tmp_path, SINGLET + "5\nS 0 42\n", "plain.seq"))
    spec = read_lens_spec(_seq(tmp_path, SINGLET + "5\nS 0 42\n  XDE 0.2; YDE -0.3; ZDE 0.5\n"
                               "  ADE 10; BDE -7; CDE 20; DAR\n", "dar.seq"))
    kinds = [s["type"] for s in spec["surfaces"]]
    assert kinds == ["standard", "standard", "coordinate_break", "coordinate_break", "standard", "coordinate_break"]
    assert spec["surfaces"][2]["thickness"] == 0.5 and spec["surfaces"][3]["tilt"] == [-10.0, 7.0, 20.0]
    assert spec["surfaces"][5]["order"] == 1 and spec["surfaces"][5]["thickness"] == 42.0 - 0.5
    dar = lens_from_spec(spec)
    assert dar.is_folded
    rot, t = (v.detach() for v in dar.image_frame())
    np.testing.assert_allclose(rot.numpy(), np.eye(3), rtol=0, atol=1e-15)
    np.testing.assert_allclose(t.numpy(), [0.0, 0.0, 3.0 + 5.0 + 42.0], rtol=0, atol=1e-13)
    with torch.no_grad():  # the moved surface is really met elsewhere (global points: not a no-op)
        _, rec = dar.trace(_rays(), record=True)
        _, ref = plain.trace(_rays(), record=True)
    moved = torch.stack(rec.points[5]) - torch.stack(ref.points[3])
    assert float(moved.abs().max()) > 0.3
    _same(_image(dar), _image(plain), 1e-12)


# ------------------------------------------------------------------------------------------- (b) DEC vs COORDBRK
def test_basic_decentre_of_the_stop_equals_the_zmx_coordinate_break(tmp_path):
    """YDE 0.2 on a flat stop 2 mm before the singlet (basic decentre: the singlet and the image follow it) is the
    .zmx COORDBRK decentre y 0.2 before the stop (1e-12), and the whole image space is moved by 0.2 mm: rays moved
    by 0.2 mm meet the image plane where the plain lens's rays do, in its own coordinates."""
    body = "S 0 2\n  STO\n  YDE 0.2\n" + SINGLET.replace("\n  STO", "") + "47\n"
    cv = _lens(_seq(tmp_path, body))
    zx = _lens(_zmx(tmp_path, [_cbz(dy=0.2), _std(0.0, 2.0, stop=True), _std(1 / 30, 3.0, ZMX_GLASS),
                               _std(-1 / 200, 47.0)]))
    a, b = _image(cv), _image(zx)
    _same(a, b, 1e-12)
    plain = _lens(_seq(tmp_path, "S 0 2\n  STO\n" + SINGLET.replace("\n  STO", "") + "47\n", "plain.seq"))
    moved = _image(cv, _rays(shift=(0.0, 0.2)))
    _same(moved, _image(plain), 1e-12)
    rot, t = (v.detach() for v in cv.image_frame())
    assert float(t[1]) == pytest.approx(0.2, abs=1e-15)
    # the intercepts in global coordinates: the plain lens's + 0.2 in y
    with torch.no_grad():
        g = cv.trace_to_image(_rays(shift=(0.0, 0.2)))
    np.testing.assert_allclose((g.o[:, 1] - 0.2).numpy(), _image(plain).o[:, 1].numpy(), rtol=0, atol=1e-12)


def test_decentred_and_tilted_image_surface_equals_a_zmx_break_before_the_image(tmp_path):
    """XDE, ZDE, ADE, BDE on SI (a tilted image plane) = COORDBRK (decentre x, thickness ZDE) + COORDBRK (tilts −ADE,
    −BDE) before the .zmx image (1e-12)."""
    p = tmp_path / "si.seq"
    p.write_text(_seq(tmp_path, SINGLET + "47\n").read_text().replace(
        "SI 0 0\n", "SI 0 0\n  XDE 0.1; ZDE -0.4; ADE 2; BDE -1.5\n"))
    cv = _lens(p)
    zx = _lens(_zmx(tmp_path, [_std(1 / 30, 3.0, ZMX_GLASS, stop=True), _std(-1 / 200, 47.0),
                               _cbz(dx=0.1, disz=-0.4), _cbz(tx=-2.0, ty=1.5)]))
    _same(_image(cv), _image(zx), 1e-12)


# ---------------------------------------------------------------------------------------------- (c) BEN fold
def test_ben_fold_mirror_equals_the_zmx_fold_and_the_unfolded_lens(tmp_path):
    """ADE 45 + BEN on a flat REFL surface 20 mm after the singlet (27 mm to the image after it) is the .zmx fold
    COORDBRK (tilt x −45) + MIRROR + COORDBRK (−45) (1e-12) and images like the unfolded singlet (47 mm back
    distance): the same x, y on the image plane and the same optical paths (1e-10). A positive ADE (left-handed)
    turns the mirror's normal toward +y, so the folded light travels toward −y."""
    cv = _lens(_seq(tmp_path, SINGLET + "20\nS 0 -27 REFL\n  ADE 45; BEN\n"))
    zx = _lens(_zmx(tmp_path, [_std(1 / 30, 3.0, ZMX_GLASS, stop=True), _std(-1 / 200, 20.0), _cbz(tx=-45.0),
                               _std(0.0, 0.0, "  GLAS MIRROR 0 0 1.5 40\n"), _cbz(tx=-45.0, disz=-27.0)]))
    unfolded = _lens(_seq(tmp_path, SINGLET + "47\n", "unfolded.seq"))
    a = _image(cv)
    _same(a, _image(zx), 1e-12)
    b = _image(unfolded)
    np.testing.assert_allclose(a.o[:, :2].numpy(), b.o[:, :2].numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.opl.numpy(), b.opl.numpy(), rtol=0, atol=1e-10)
    with torch.no_grad():
        g = cv.trace_to_image(_rays())
    assert float(g.d[:, 1].max()) < -0.99  # toward −y after the fold
    np.testing.assert_allclose(cv.image_frame()[1].detach().numpy(), [0.0, -27.0, 23.0], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------------------------- (d) REV
def test_rev_undoes_a_dec(tmp_path):
    """A basic decentre (x, y, z, α, β, γ) on a flat air surface and REV with the same values on the next one: the
    lens after them is back on its axis (image frame and rays of the plain lens, 1e-12). And a singlet tilted as a
    unit (DEC on its front, REV on its back) is the .zmx COORDBRK … inverse COORDBRK (order 1) pair."""
    dec = "  XDE 0.3; YDE -0.2; ZDE 0.7; ADE 4; BDE -3; CDE 25\n"
    both = _lens(_seq(tmp_path, "S 0 0\n" + dec + "S 0 2\n  REV\n" + dec + SINGLET + "47\n"))
    plain = _lens(_seq(tmp_path, "S 0 0\nS 0 2\n" + SINGLET + "47\n", "plain.seq"))
    rot, t = (v.detach() for v in both.image_frame())
    np.testing.assert_allclose(rot.numpy(), np.eye(3), rtol=0, atol=1e-15)
    np.testing.assert_allclose(t.numpy(), [0.0, 0.0, 2.0 + 3.0 + 47.0], rtol=0, atol=1e-13)
    _same(_image(both), _image(plain), 1e-12)
    tilted = _lens(_seq(tmp_path, f"S 0 2\n  STO\nS 30 3 {GLASS}\n  YDE 0.1; ADE 1.5\nS -200 47\n  REV\n"
                        "  YDE 0.1; ADE 1.5\n", "tilted.seq"))
    zx = _lens(_zmx(tmp_path, [_std(0.0, 2.0, stop=True), _cbz(dy=0.1, tx=-1.5), _std(1 / 30, 3.0, ZMX_GLASS),
                               _std(-1 / 200, 0.0), _cbz(dy=-0.1, tx=1.5, order=1, disz=47.0)]))
    _same(_image(tilted), _image(zx), 1e-12)


# ----------------------------------------------------------------------------------------- (e) tilt signs
@pytest.mark.parametrize("before,tilt,direction", [("", "ADE 20", (0.0, 1.0)), ("", "ADE -20", (0.0, -1.0)),
                                                   ("", "BDE 20", (-1.0, 0.0)), ("", "BDE -20", (1.0, 0.0)),
                                                   ("S 0 1\n  CDE 90\n", "ADE 20", (-1.0, 0.0))],
                         ids=["ADE+", "ADE-", "BDE+", "BDE-", "CDE90-then-ADE+"])
def test_tilted_plate_shifts_a_ray_by_the_plate_formula(tmp_path, before, tilt, direction):
    """A plane-parallel plate (t = 5 mm) tilted by 20°: an axial ray leaves parallel to the axis, shifted by
    t·sinθ(1 − cosθ/√(n² − sin²θ)) toward the plate's tilted normal: +y for ADE > 0 (left-handed α), −x for BDE > 0
    (left-handed β); CDE 90 on a surface before (right-handed γ) turns the new y onto −x (1e-12)."""
    t, theta = 5.0, math.radians(20.0)
    p = _seq(tmp_path, f"S 0 2\n{before}S 0 {t} {GLASS}\n  {tilt}\nS 0 10\n")
    lens = _lens(p)
    wl = torch.tensor(0.55, dtype=torch.float64)
    n = max(float(v.detach()) for v in lens.indices(wl))
    o = torch.tensor([[0.0, 0.0, -5.0], [0.3, -0.4, -5.0]], dtype=torch.float64)
    rays = RayBundle.create(o, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(o), 0.55)
    with torch.no_grad():
        out = lens.trace(rays)
    assert bool(out.valid.all())
    np.testing.assert_allclose(out.d.numpy(), [[0.0, 0.0, 1.0]] * 2, rtol=0, atol=1e-15)
    shift = t * math.sin(theta) * (1 - math.cos(theta) / math.sqrt(n * n - math.sin(theta) ** 2))
    assert shift > 0.5  # ~0.63 mm: a sign error cannot hide
    expect = o[:, :2].numpy() + shift * np.array(direction)
    np.testing.assert_allclose(out.o[:, :2].numpy(), expect, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------- (f) errors
@pytest.mark.parametrize("body,match", [
    ("S 0 1\nS 0 2\n  XDE 0.1; DAR; BEN\n" + SINGLET + "47\n", r"surface 2: two decentre types on one surface "
                                                               r"\(DAR and BEN\)"),
    ("S 0 1\n  YDE abc\n" + SINGLET + "47\n", r"surface 1: YDE abc: needs one finite number"),
    ("S 0 1\n  ADE 1 2\n" + SINGLET + "47\n", r"surface 1: ADE 1 2: needs one finite number"),
    ("S 0 1\n  XDE S9 0.1\n" + SINGLET + "47\n", r"surface 1: XDE S9 0.1: no surface 9"),
    ("S 0 1\n  DAR 3\n" + SINGLET + "47\n", r"surface 1: DAR 3: the decentre type takes no value"),
], ids=["two-types", "not-a-number", "two-numbers", "no-such-surface", "type-with-value"])
def test_bad_decentres_are_errors_naming_the_surface(tmp_path, body, match):
    with pytest.raises(LensFileError, match=match):
        read_lens_spec(_seq(tmp_path, body))


def test_unsupported_decentres_are_errors_naming_the_surface(tmp_path):
    text = _seq(tmp_path, SINGLET + "47\n").read_text()
    for old, new, match in [
        ("SO 0 1e10\n", "SO 0 1e10\n  YDE 0.5\n", r"object surface \(SO\): a decentred or tilted object"),
        ("SO 0 1e10\n", "SO 0 1e10\n  ADE S0 2\n", r"object surface \(SO\): a decentred or tilted object"),
        ("SI 0 0\n", "SI 0 0\n  ADE 1; REV\n", r"image surface \(SI\): a reverse decentre \(REV\)"),
        ("RDM\n", "RDM\nXDE 0.1\n", r"XDE: a decentre before the first surface"),
        ("S -200 ", "  DIF DOE\n  HOR 1; HWL 550; HCT R\n  HCO C1 -0.0018\nS -200 ",
         r"surface 1: diffractive surface \(DIF\) is not supported"),  # was skipped: a DOE read as no DOE
    ]:
        p = tmp_path / "bad.seq"
        p.write_text(text.replace(old, new, 1))
        with pytest.raises(LensFileError, match=match):
            read_lens_spec(p)


def test_zero_decentres_and_a_type_alone_change_nothing(tmp_path):
    """CODE V exports write zero decentres (and types) on centred surfaces: no coordinate break is made; an Sk
    qualifier addresses another surface."""
    plain = read_lens_spec(_seq(tmp_path, SINGLET + "47\n", "plain.seq"))
    zero = read_lens_spec(_seq(tmp_path, SINGLET + "47\n  XDE 0; YDE 0; ZDE 0; ADE 0; BDE 0; CDE 0; DAR\n"))
    assert zero == plain
    addressed = read_lens_spec(_seq(tmp_path, SINGLET + "47\n  YDE S1 0.25\n", "s1.seq"))
    assert [s["type"] for s in addressed["surfaces"]] == ["coordinate_break", "standard", "standard"]
    assert addressed["surfaces"][0]["decenter"] == [0.0, 0.25]


def test_decentres_scale_with_the_lens_units(tmp_path):
    """DIM C: XDE / YDE / ZDE in cm -> mm; the angles stay degrees."""
    p = tmp_path / "cm.seq"
    p.write_text(_seq(tmp_path, "S 3 0.3 " + GLASS + "\n  STO\n  XDE 0.01; ZDE 0.02; ADE 1\nS -20 4.7\n")
                 .read_text().replace("DIM M", "DIM C"))
    s = read_lens_spec(p)["surfaces"]
    assert s[0]["decenter"] == [0.1, 0.0] and s[0]["thickness"] == 0.2 and s[1]["tilt"] == [-1.0, 0.0, 0.0]
