"""CODE V .seq import (tests/data/codev) against Optiland's CODE V reader: first-order data and skew real rays to
1e-9, with raywave's indices in both tools (as tests/test_zmx_corpus.py).

Where Optiland 0.6.3 reads a file unlike CODE V, its model is corrected first: it puts the aspheric A (r⁴) term on
r² (every term one power low), and it takes a stop surface line ``STO r t`` for a stop flag on the surface before
(dropping the stop surface), so that file is given to it with the stop written as ``S r t`` + ``STO``.
"""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from raywave.io import LensFileError, detect_format, read_lens_spec
from raywave.lens.build import lens_from_spec
from raywave.rays.bundle import RayBundle

optiland = pytest.importorskip("optiland")
from optiland.fileio import load_codev_file  # noqa: E402
from optiland.materials import IdealMaterial  # noqa: E402
from optiland.rays import RealRays  # noqa: E402

DATA = Path(__file__).resolve().parent / "data" / "codev"
FILES = sorted(DATA.glob("*.seq"))
REL = 1e-9


def _scalar(x) -> float:
    return float(np.asarray(x).ravel()[0])


def _optiland(path, lens, tmp_path):
    text = path.read_text()
    if "\nSTO   " in text:  # Optiland reads a STO surface line as a flag on the surface before
        lines = []
        for line in text.splitlines():
            if line.startswith("STO   "):
                lines += ["S" + line[3:], "  STO"]
            else:
                lines.append(line)
        path = tmp_path / path.name
        path.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o = load_codev_file(str(path))
    n = [float(m.detach()) for m in lens.indices(torch.tensor(lens.primary_wavelength, dtype=torch.float64))]
    for i, surf in enumerate(o.surfaces.surfaces[1:-1], start=1):
        g = surf.geometry
        if type(g).__name__ == "EvenAsphere":  # A (r^4) read as the r^2 term: shift every term up one power
            g.coefficients = [0.0] + list(g.coefficients)
            g.tol, g.max_iter = 1e-15, 200
        surf.material_post = IdealMaterial(n[i])
    return o


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seq")
    out = {}
    for f in FILES:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # realistic files read without warnings
            spec = read_lens_spec(f)
        lens = lens_from_spec(spec)
        out[f.stem] = (spec, lens, _optiland(f, lens, tmp))
    return out


def test_reads_the_subset():
    assert len(FILES) == 3 and all(detect_format(f) == "codev" for f in FILES)
    cooke = read_lens_spec(DATA / "cooke_triplet.seq")
    assert cooke["name"] == "COOKE TRIPLET F/5 50MM" and cooke["system_aperture"] == {"epd": 10.0}
    assert cooke["object"] == {"distance": "inf"}
    assert cooke["wavelengths"] == {"values": [0.6562725, 0.5875618, 0.4861327], "primary": 1}
    assert cooke["fields"] == {"type": "angle", "values": [0.0, 14.0, 20.0]}
    s = cooke["surfaces"]
    assert [x["stop"] for x in s] == [False, False, False, True, False, False]
    assert s[0]["material"] == {"name": "NSK16", "catalog": "SCHOTT"} and s[3]["comment"] == "stop"
    assert s[0]["semi_diameter"] == 6.0 and s[5]["thickness"] == 42.20778
    asph = read_lens_spec(DATA / "asphere_singlet_nao.seq")
    assert asph["system_aperture"] == {"object_na": 0.08} and asph["object"] == {"distance": 60.0}
    assert asph["surfaces"][1]["aspheric"] == {"a2": 0.0, "a4": -1.2e-5, "a6": 3.4e-8, "a8": -2.1e-11}
    assert asph["surfaces"][1]["conic"] == -0.9
    assert asph["surfaces"][3]["material"] == {"model": {"nd": 1.517, "vd": 64.2}}
    assert asph["fields"]["type"] == "object_height"
    petz = read_lens_spec(DATA / "petzval_fno.seq")
    assert petz["system_aperture"] == {"f_number": 2.8} and petz["surfaces"][3]["stop"]
    assert petz["surfaces"][5]["material"] == {"name": "NSF5", "catalog": "SCHOTT"}  # continued line
    lens = lens_from_spec(petz)
    assert lens.surfaces[0].material.name == "N-BK7"  # NBK7_SCHOTT: CODE V drops the hyphen


@pytest.mark.parametrize("name", [f.stem for f in FILES])
def test_first_order_and_skew_rays_match_optiland(models, name):
    spec, lens, o = models[name]
    p = lens.paraxial()
    assert p.efl == pytest.approx(_scalar(o.paraxial.f2()), rel=REL)
    assert p.bfl == pytest.approx(_scalar(o.paraxial.F2()) + float(lens.surfaces[-1].thickness.detach()), rel=REL)
    assert p.epd == pytest.approx(_scalar(o.paraxial.EPD()), rel=REL)
    assert p.ep_z == pytest.approx(_scalar(o.paraxial.EPL()), rel=REL, abs=1e-12)
    assert p.xp_z == pytest.approx(lens.total_track() + _scalar(o.paraxial.XPL()), rel=REL)
    assert p.xpd == pytest.approx(abs(_scalar(o.paraxial.XPD())), rel=REL)
    h = 0.1 * p.epd
    x = np.array([0.0, 0.3 * h, -0.5 * h, 0.2 * h])
    y = np.array([0.0, 0.6 * h, 0.4 * h, -0.7 * h])
    L = np.array([0.0, 0.004, 0.006, -0.004])
    M = np.array([0.0, 0.004, -0.005, 0.003])
    N = np.sqrt(1 - L ** 2 - M ** 2)
    z = np.full(4, -0.5)
    wl = lens.primary_wavelength
    rays = RealRays(x.copy(), y.copy(), z.copy(), L.copy(), M.copy(), N.copy(), np.ones(4), np.full(4, wl))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        o.surfaces.trace(rays, skip=1)
    with torch.no_grad():
        out = lens.trace_to_image(RayBundle.create(np.stack([x, y, z], -1), np.stack([L, M, N], -1), wl))
    assert bool(out.valid.all())
    np.testing.assert_allclose(out.o[:, 0].numpy(), np.asarray(rays.x), rtol=0, atol=REL)
    np.testing.assert_allclose(out.o[:, 1].numpy(), np.asarray(rays.y), rtol=0, atol=REL)
    np.testing.assert_allclose(out.d[:, 1].numpy(), np.asarray(rays.M), rtol=0, atol=REL)


@pytest.mark.parametrize("edit, msg", [
    (("SO    0.0 60.0", "SO    0.0 60.0\n  XDE 0.1"), "object surface (SO): a decentred or tilted object is not "
                                                        "supported"),  # surface decentres: test_codev_decentres.py
    (("NAO   0.08", "NA    0.2"), "image-space NA pupil (NA) is not supported"),
    (("YOB   0.0 1.0 2.0", "YIM   0.0 1.0 2.0"), "image-height field (YIM) is not supported"),
    (("  K   -0.9", "  K   -0.9\n  YTO"), "surface 2: toroid (y) (YTO) is not supported"),
    (("SO    0.0 60.0", "SO    0.0 1e10"), "NAO: an object-space NA needs an object at a finite distance"),
    # aperture decentres (ADX / ADY) are read since issue 44 (tests/test_codev_apertures.py); a rotation is not
    (("  K   -0.9", "  K   -0.9\n  ARO 10"), "surface 2: ARO 10: a rotated aperture is not supported"),
    (("  K   -0.9", "  K   -0.9\n  ELX 2"), "surface 2: elliptical aperture (ELX) is not supported"),
])
def test_unsupported_features_name_the_place(tmp_path, edit, msg):
    text = (DATA / "asphere_singlet_nao.seq").read_text()
    assert edit[0] in text
    p = tmp_path / "x.seq"
    p.write_text(text.replace(*edit))
    with pytest.raises(LensFileError) as e:
        read_lens_spec(p)
    assert msg in str(e.value) and str(e.value).startswith(str(p))


def test_curvature_mode_units_and_zero_decentres(tmp_path):
    text = (DATA / "cooke_triplet.seq").read_text()
    p = tmp_path / "c.seq"
    p.write_text(text.replace("DIM   M", "DIM   C").replace("S     -435.7604 6.007551", "S     -435.7604 6.007551\n"
                                                                                          "  XDE 0.0; ADE 0.0; ADX 0.0"))
    spec = read_lens_spec(p)
    assert spec["surfaces"][0]["radius"] == pytest.approx(220.1359) and spec["system_aperture"]["epd"] == 100.0
    lines = []
    for line in text.replace("RDM;LEN", "RDM N;LEN").splitlines():
        tok = line.split()
        if tok[:1] == ["S"] and float(tok[1]) != 0.0:
            tok[1] = repr(1.0 / float(tok[1]))
            line = " ".join(tok)
        lines.append(line)
    p.write_text("\n".join(lines) + "\n")
    curv = read_lens_spec(p)
    assert curv["surfaces"][0]["radius"] == pytest.approx(22.01359, rel=1e-14)
    with pytest.warns(Warning, match="ignored unknown CODE V commands: FOO"):
        p.write_text(text.replace("INI   'RWV'", "FOO 1"))
        read_lens_spec(p)
    assert math.isinf(lens_from_spec(spec).object_distance)


def test_cuy_and_rdy_set_the_surface_shape(tmp_path):
    """``CUY c`` / ``RDY r`` on a surface (or ``Sk``) replace the radius of its surface line (they were skipped, so
    a file that gives its curvatures this way lost them silently); bad values name the surface."""
    text = (DATA / "cooke_triplet.seq").read_text()
    ref = read_lens_spec(DATA / "cooke_triplet.seq")
    p = tmp_path / "c.seq"
    p.write_text(text.replace("S     -435.7604 6.007551", f"S     0 6.007551\n  CUY {1 / -435.7604!r}"))
    spec = read_lens_spec(p)
    assert spec["surfaces"][1]["radius"] == pytest.approx(ref["surfaces"][1]["radius"], rel=1e-14)
    p.write_text(text.replace("S     -435.7604 6.007551", "S     0 6.007551\n  RDY S1 99.5"))
    spec = read_lens_spec(p)
    assert spec["surfaces"][0]["radius"] == pytest.approx(99.5, rel=1e-14)
    assert spec["surfaces"][1]["radius"] == "inf"  # its own line says flat
    p.write_text(text.replace("S     -435.7604 6.007551", "S     -435.7604 6.007551\n  CUY"))
    with pytest.raises(LensFileError, match="surface 2: CUY"):
        read_lens_spec(p)
