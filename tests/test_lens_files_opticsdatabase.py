"""Real Zemax files as engineers have them (issue 44): one file per feature from the OpticExplorer Optics Database
(tests/data/opticsdatabase, MIT, attributed in its README), read by raywave with the warnings or named errors each
feature calls for, and checked against Optiland 0.6.3 where Optiland reads the file faithfully (EFL, BFL, F/#,
entrance and exit pupils, the real chief ray's image intercept at the largest field, to 1e-9 relative; the
comparison is benchmarks/_optiland_compare.py, which benchmarks/lens_files.py --optiland runs on the whole corpus).

Analytic checks beside Optiland: a real-image-height field's chief ray lands at its height and passes the stop
centre; a paraxial-image-height field (FTYP 2) lands there paraxially (Optiland's paraxial chief ray); an object in
water (immersion) against the thick-lens formulas; a curved image surface ends the real rays on the sphere.
"""

import functools
import math
import re
import sys
import warnings
from pathlib import Path

import pytest
import torch

import raywave
from raywave.io import LensFileError, LensFileWarning, read_lens_spec
from raywave.io.zmx import decode_zmx_bytes, read_zmx
from raywave.lens.build import lens_from_spec, lens_to_spec
from raywave.lens.lens import LensGeometryWarning
from raywave.lens.sources import chief_ray

HERE = Path(__file__).resolve().parent
DATA = HERE / "data" / "opticsdatabase"
sys.path.insert(0, str(HERE.parent / "benchmarks"))
REL = 1e-9


@functools.lru_cache(maxsize=None)
def _load(name, config=None):
    """(lens, warning messages) of a file of the subset, read once per test session (tests do not change it)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = raywave.load_lens(DATA / name, config=config)
    return lens, [str(w.message) for w in caught if issubclass(w.category, UserWarning)]


def _text(name) -> str:
    return decode_zmx_bytes((DATA / name).read_bytes())[0].replace("\r\n", "\n")


def test_subset_is_attributed():
    readme = (DATA / "README.md").read_text()
    assert "github.com/amegahed/OpticsDatabase" in readme and "fc0927a" in readme and "MIT" in readme
    assert (DATA / "LICENSE.md").exists()
    for f in DATA.glob("*.zmx"):
        assert f.name in readme, f.name


#: file -> (regexes every one of which some warning must match); read with finite paraxial data.
READS = {
    "Canon EF24-70mm f2.8L II USM.zmx": [r"multi-configuration file \(3 configurations, current 1\): configuration 1 "
                                         r"is read \(1 SDIA, 4 THIC applied\)"],
    "Nikon AF-S DX Nikkor 10-24mm f3.5-4.5G ED.zmx": [],
    "Nikon Nikkor Z 50mm f1.2 S.zmx": [r"surfaces 25 \(line \d+\), 26 \(line \d+\): XASPHERE with terms in PARM "
                                       r"1..8 and none in XDAT: read as EVENASPH terms"],
    "Nikon AF-S DX Zoom-Nikkor 18-55mm f3.5-5.6G ED II.zmx": [],
    "Canon EF15mm f2.8 Fisheye.zmx": [],  # its 90.015° field is read (tests/test_lens_files_fisheye.py)
    "Samsung 10mm F3.5 Fisheye.zmx": [],  # its 91.075° field (a YFIE operand) too
    "Nikon 400mm f8 Dodotto Tele.zmx": [r":6: the surfaces start at SURF 1 \(no object surface 0\): read as lens "
                                        r"surfaces with an object at infinity .* and an image plane 174.595 mm after "
                                        r"surface 7", r"no system aperture line"],
    "Nikon 120mm f4.5 Gugutto Macro.zmx": [r"surfaces are not numbered 0, 1, 2, ... \(1-4, 6-7\): read in file order"],
    "Djian 100mm F0.57.zmx": [r":\d+: SURF 5AS: read as a surface in file order \(the suffix 'AS' is ignored\)"],
    "Yongnuo YN40mm F2.8N.zmx": [r"numbers with a decimal comma read as decimals \(line 180\)"],
    "Nikon R-UW AF Fisheye-Nikkor 13mm f2.8.zmx": [],  # its 21.6 mm field solved (83.97°, tests/test_fields_wide.py)
    "Erfle USP1478704.zmx": [r"no system aperture line"],
    "Huygens.zmx": [r"no system aperture line"],
    "Apochromat Doublet.zmx": [r"surfaces 1 and 2 overlap at their edges"],
    "Canon Extender EF2X.zmx": [r"no system aperture line \(ENPD, FNUM, OBNA or FLOA\): the stop's semi-diameter"],
    "Microscope USP3893752.zmx": [],
    "Telescope Fraunhofer.zmx": [r"glass 'BK7' is obsolete in the SCHOTT catalog", r"surfaces 2 and 3 overlap"],
    "Canon New FD 500mm f8 Mirror.zmx": [r"surfaces 5 \(line 101\), 11 \(line 152\): model glass nd -1 read as a "
                                         r"mirror \(GLAS MIRROR\)"],
}


@pytest.mark.parametrize("name", sorted(READS))
def test_reads_with_the_expected_warnings(name):
    lens, warns = _load(name)
    p = lens.paraxial()
    assert all(math.isfinite(v) for v in (p.efl, p.bfl, p.epd, p.ep_z, p.xp_z, p.xpd)), name
    for pattern in READS[name]:
        assert any(re.search(pattern, w) for w in warns), (pattern, warns)
    # display-only keys (DBDT, OMMA, HYPR, FIMP, OEMA, merit function rows) are dropped silently
    assert not any("ignored .zmx keys" in w for w in warns), warns


#: file -> (error type, regex): what raywave refuses, and why, naming the line.
REFUSES = {
    "Canon EF24mm f1.4L II USM.zmx": (LensFileError, r":95: surface 4: PARM: '\?\?3.9223E-12' is not a number"),
    "Sony DT 16-50mm F2.8 SSM.zmx": (LensFileError, r":111: surface 6: PARM: '-6.03510E-08\?\?' is not a number"),
    "Nikon 90mm f4.8 Fuwatto Soft.zmx": (LensFileError, r":6: SURF needs a surface number, got '3.5'"),
    "Ricoh smc Pentax-FA 28-70mm F4 AL.zmx": (LensFileError, r":76: surface 2: GLAS vd: '\?' is not a number"),
    "Canon RF28-70mm F2 L USM.zmx": (LensFileError, r":274: surface 22: negative thickness DISZ -2.59 mm in air while "
                                     r"the light travels toward \+z: surface 23 lies 2.59 mm before it on the axis"),
}


@pytest.mark.parametrize("name", sorted(REFUSES))
def test_refuses_with_a_named_error(name):
    kind, pattern = REFUSES[name]
    with pytest.raises(kind, match=pattern), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        raywave.load_lens(DATA / name).paraxial()


def test_negative_index_mirrors_are_mirrors():
    """The Canon New FD 500mm f8 Mirror writes its two reflections as model glasses of index -1 (the Mangin primary's
    back surface, the secondary's): read as mirrors the catadioptric lens has its nominal focal length, 500 mm (a
    reading that is independent of the file: the lens's name); the light after the first mirror travels toward -z
    (negative thicknesses), after the second toward +z again."""
    lens, _ = _load("Canon New FD 500mm f8 Mirror.zmx")
    assert [i for i, s in enumerate(lens.surfaces) if s.interaction.kind == "reflection"] == [4, 10]
    assert lens.paraxial().efl == pytest.approx(500.0, rel=1e-4)
    signs = lens.direction_signs()
    assert signs[5] < 0 and signs[11] > 0
    # any other index <= 0 is still an error naming the line
    text = _text("Canon New FD 500mm f8 Mirror.zmx").replace("___BLANK 1 0 -1  0", "___BLANK 1 0 -1.5  0", 1)
    with pytest.raises(LensFileError, match=r":101: surface 5: model glass index nd -1.5 is not supported"):
        read_lens_spec_text(text)


def read_lens_spec_text(text: str):
    """read_zmx on ``text`` written to a temporary .zmx file."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.zmx"
        p.write_text(text)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return read_zmx(p)


def test_unsupported_features_are_named(tmp_path):
    """One edit per unsupported feature of the Canon zoom: each gives its named error or warning."""
    base = _text("Canon EF24-70mm f2.8L II USM.zmx")
    cases = [
        (("FTYP 3 0 3", "FTYP 7 0 3"), LensFileError, r"FTYP 7: unknown field type"),
        (("SURF 2\n  TYPE STANDARD", "SURF 2\n  TYPE SZERNSAG"), LensFileError,
         r"surface 2: surface type SZERNSAG \(Zernike standard sag\) is not supported"),
        (("SURF 2\n  TYPE STANDARD", "SURF 2\n  TYPE IRREGULA"), LensFileError, r"IRREGULA \(irregular\)"),
        (("MNUM 3 1", "MNUM 3 1\nGLSS   2   1 \"N-BK7\" 0 0 0 1 1 0 0 0"), LensFileWarning,
         r"multi-configuration operands of configuration 1 that change the optics are not modelled and were "
         r"ignored: GLSS \(line \d+\)"),
        (("MODE SEQ", "MODE SEQ\nFOOB 1 2"), LensFileWarning, r"ignored .zmx keys that may change the optics .*FOOB"),
    ]
    for (old, new), kind, pattern in cases:
        text = base.replace(old, new, 1)
        assert text != base, old
        p = tmp_path / "x.zmx"
        p.write_text(text)
        if issubclass(kind, Warning):
            with pytest.warns(kind, match=pattern):
                read_zmx(p)
        else:
            with pytest.raises(kind, match=pattern), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read_zmx(p)


@pytest.mark.parametrize("name", sorted(n for n in READS if n not in ("Erfle USP1478704.zmx", "Huygens.zmx")))
def test_agrees_with_optiland_where_it_reads_the_file(name):
    from _optiland_compare import NotFaithful, compare

    pytest.importorskip("optiland")
    lens, _ = _load(name)
    try:
        diffs = compare(str(DATA / name), lens)
    except NotFaithful as why:
        # Optiland 0.6.3 refuses extended aspheres and files with no aperture line; zooms whose thicknesses are
        # not configuration 1's, an object in a medium, a working F/# read as image-space
        assert re.search(r"refuses|thicknesses differ|medium|working F/#|surfaces, raywave", str(why)), str(why)
        pytest.skip(str(why))
    for q, v in diffs.items():
        assert v < REL, (q, v)


def test_optiland_compares_the_camera_lenses():
    """The comparison above is not vacuous: the FTYP 3 zoom, the decimal-comma lens and the microscope are
    compared."""
    from _optiland_compare import compare

    pytest.importorskip("optiland")
    for name in ("Canon EF24-70mm f2.8L II USM.zmx", "Yongnuo YN40mm F2.8N.zmx", "Microscope USP3893752.zmx"):
        lens, _ = _load(name)
        assert max(compare(str(DATA / name), lens).values()) < REL, name


def test_real_image_height_chief_rays_land_at_their_heights():
    lens, _ = _load("Canon EF24-70mm f2.8L II USM.zmx")
    assert lens.field_definition == {"type": "real_image_height", "values": [0.0, 15.148, 21.64]}
    assert lens.field_type == "angle" and lens.fields[0] == 0.0
    assert lens.fields[2] == pytest.approx(42.0809, abs=1e-3)
    with torch.no_grad():
        rays = chief_ray(lens, [[0.0, f] for f in lens.fields], [lens.primary_wavelength])
        out, rec = lens.trace_to_image(rays, record=True)
    assert out.o[:, 0, 0, 1].tolist() == pytest.approx([0.0, 15.148, 21.64], abs=1e-11)
    assert rec.points[lens.stop_index + 1][1].abs().max() < 1e-10  # through the centre of the stop
    # the spec keeps the file's definition: a round trip solves the same angles
    again = lens_from_spec(lens_to_spec(lens))
    assert again.fields == pytest.approx(lens.fields, abs=1e-12)


def test_theodolite_angles(tmp_path):
    """FTYP 4 (azimuth x, elevation y): the field angle from the axis is acos(cos x cos y); y alone is the angle."""
    text = _text("Yongnuo YN40mm F2.8N.zmx").replace("1,5168", "1.5168")
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith("FTYP"))
    lines[i] = "FTYP 4" + lines[i][6:]
    j = next(k for k, ln in enumerate(lines) if ln.startswith("XFLN"))
    k = next(k for k, ln in enumerate(lines) if ln.startswith("YFLN"))
    lines[j], lines[k] = "XFLN 0 0 10", "YFLN 0 15 20"
    p = tmp_path / "theo.zmx"
    p.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = read_zmx(p)
    expect = math.degrees(math.acos(math.cos(math.radians(10)) * math.cos(math.radians(20))))
    assert spec["fields"] == {"type": "angle", "values": [0.0, pytest.approx(15.0, abs=1e-12),
                                                          pytest.approx(expect, abs=1e-12)]}


def test_finite_object_image_heights():
    """FTYP 3 with a finite object: object heights are solved (negative for an inverted image)."""
    spec = read_lens_spec(DATA / "Microscope USP3893752.zmx")
    spec["fields"] = {"type": "real_image_height", "values": [0.0, 1.0]}
    lens = lens_from_spec(spec)
    assert lens.field_type == "object_height" and lens.fields[1] < 0
    with torch.no_grad():
        out = lens.trace_to_image(chief_ray(lens, [[0.0, f] for f in lens.fields], [lens.primary_wavelength]))
    assert float(out.o[1, 0, 0, 1]) == pytest.approx(1.0, abs=1e-11)


def test_paraxial_image_height_fields_against_optiland(tmp_path):
    """FTYP 2: the solved angle's paraxial chief ray (Optiland's paraxial trace) lands at the height."""
    pytest.importorskip("optiland")
    from optiland.fileio.zemax.reader.converter import ZemaxToOpticConverter
    from optiland.fileio.zemax.reader.parser import ZemaxDataParser

    text = _text("Yongnuo YN40mm F2.8N.zmx")
    ftyp = next(ln for ln in text.splitlines() if ln.startswith("FTYP"))
    p = tmp_path / "ftyp2.zmx"
    p.write_text(text.replace(ftyp, "FTYP 2" + ftyp[6:], 1).replace("1,5168", "1.5168"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = raywave.load_lens(p)
        o = ZemaxToOpticConverter(ZemaxDataParser(str(p)).parse()).convert()
    assert lens.field_definition["type"] == "paraxial_image_height"
    h = lens.field_definition["values"][-1]
    theta = lens.fields[-1]
    o.fields.set_type("angle")
    o.fields.fields = []
    o.add_field(y=0.0)
    o.add_field(y=theta)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        y, _ = o.paraxial.chief_ray()
    # Optiland's paraxial chief ray has the slope tan θ of the largest field; its height on the image surface
    assert float(abs(y[-1]).ravel()[0]) == pytest.approx(h, rel=REL)


def test_immersion_against_the_thick_lens_formulas(tmp_path):
    """An object in water (n0 = 1.333): a plano-convex glass plate whose curved face meets the water; EFL = 1/φ1
    with φ1 = (n - n0)/R (the flat face has no power), BFL = 1/φ1 - t/n."""
    n0, n, R, t = 1.333, 1.5, 50.0, 5.0
    text = "\n".join([
        "VERS 1", "MODE SEQ", "UNIT MM", "ENPD 10", "FTYP 0 0 1 1", "YFLN 0", "WAVM 1 0.5876 1", "PWAV 1",
        "SURF 0", "  DISZ INFINITY", f"  GLAS ___BLANK 1 0 {n0} 0",
        "SURF 1", "  STOP", f"  CURV {1 / R}", f"  DISZ {t}", f"  GLAS ___BLANK 1 0 {n} 0", "  DIAM 10",
        "SURF 2", "  CURV 0", "  DISZ 290", "  DIAM 10",
        "SURF 3", "  CURV 0", "  DISZ 0"]) + "\n"
    f = tmp_path / "water.zmx"
    f.write_text(text)
    spec = read_zmx(f)
    assert spec["object"]["material"] == {"index": n0}
    lens = lens_from_spec(spec)
    p = lens.paraxial()
    phi = (n - n0) / R
    assert p.efl == pytest.approx(1 / phi, rel=1e-12)
    assert p.bfl == pytest.approx(1 / phi - t / n, rel=1e-12)
    assert lens_to_spec(lens)["object"]["material"] == {"index": n0}
    # a real ray parallel to the axis in the water, near the axis, crosses it at the paraxial focus
    from raywave.rays.bundle import RayBundle

    rays = RayBundle.create(torch.tensor([[0.0, 1e-3, -1.0]], dtype=torch.float64),
                            torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), 0.5876)
    out = lens.trace(rays)
    o_, d_ = out.o.detach(), out.d.detach()
    z_cross = float(o_[0, 2] - o_[0, 1] * d_[0, 2] / d_[0, 1])
    assert z_cross - t == pytest.approx(p.bfl, rel=1e-6)


def test_curved_image_surface():
    """Huygens eyepiece: the last surface of the file is curved; real rays end on the sphere, the ray-wave engine
    refuses it with the reason."""
    lens, _ = _load("Huygens.zmx")
    c = lens.image_curvature
    assert c != 0.0
    from raywave.rays.bundle import RayBundle

    rays = RayBundle.create(torch.tensor([[0.0, 2.0, -1.0], [1.0, -3.0, -1.0]], dtype=torch.float64),
                            torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 0.5876)
    with torch.no_grad():
        out = lens.trace_to_image(rays)
    assert bool(out.valid.all())
    x, y, z = out.o.unbind(-1)
    r2 = x * x + y * y
    sag = c * r2 / (1 + torch.sqrt(1 - c * c * r2))
    assert torch.allclose(z - lens.total_track(), sag, atol=1e-12, rtol=0)
    assert "needs a planar sensor" in lens.wave_support_problem()


def test_curved_object_surface_places_the_object_points():
    lens, _ = _load("Erfle USP1478704.zmx")
    assert lens.object_curvature != 0.0 and not lens.object_material.is_air
    from raywave.lens.sources import point_source_rays

    rays = point_source_rays(lens, [[0.0, 5.0]], [lens.primary_wavelength], pupil=("grid", 3), field_type="object_height",
                             aim="paraxial")
    c = lens.object_curvature
    sag = c * 25.0 / (1 + math.sqrt(1 - c * c * 25.0))
    assert float(rays.o[0, 0, 0, 2]) == pytest.approx(-lens.object_distance + sag, abs=1e-12)


def test_multi_configuration_choice():
    text = _text("Canon EF24-70mm f2.8L II USM.zmx")
    thic = {}
    for ln in text.splitlines():
        tok = ln.split()
        if tok[:1] == ["THIC"] and tok[2] == "3":
            thic[int(tok[1])] = float(tok[3])
    lens3, warns = _load("Canon EF24-70mm f2.8L II USM.zmx", config=3)
    assert any("configuration 3 is read" in w and "choose another" not in w for w in warns), warns
    for surf, value in thic.items():
        if surf > 0:
            assert float(lens3.surfaces[surf - 1].thickness) == value
    lens1, _ = _load("Canon EF24-70mm f2.8L II USM.zmx")
    assert lens3.paraxial().efl > 2 * lens1.paraxial().efl  # the long end of the zoom
    with pytest.raises(LensFileError, match="configuration 4 does not exist: the file has 3 configurations"):
        raywave.load_lens(DATA / "Canon EF24-70mm f2.8L II USM.zmx", config=4)


def test_extended_aspheres_against_their_definition():
    """XOSPHERE: sag = conic + sum B_i (r/R)^i from XDAT; XASPHERE (XDAT): sum A_i (r/R)^(2i)."""
    for name, surf_no, odd in (("Nikon AF-S DX Zoom-Nikkor 18-55mm f3.5-5.6G ED II.zmx", 3, True),
                               ("Nikon AF-S DX Nikkor 10-24mm f3.5-4.5G ED.zmx", None, False)):
        text = _text(name)
        blocks = text.split("SURF ")
        typ = "XOSPHERE" if odd else "XASPHERE"
        block = next(b for b in blocks if f"TYPE {typ}" in b and (surf_no is None or b.startswith(f"{surf_no}\n")
                                                                   or b.startswith(f"{surf_no}\r")))
        number = int(block.split()[0])
        xdat = {int(ln.split()[1]): float(ln.split()[2]) for ln in block.splitlines() if ln.split()[:1] == ["XDAT"]}
        curv = float(next(ln.split()[1] for ln in block.splitlines() if ln.split()[:1] == ["CURV"]))
        coni = float(next((ln.split()[1] for ln in block.splitlines() if ln.split()[:1] == ["CONI"]), 0.0))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lens = raywave.load_lens(DATA / name)
        g = lens.surfaces[number - 1].geometry
        n_terms, rn = int(xdat[1]), xdat[2]
        for r in (0.5, 2.0, 4.0):
            expect = curv * r * r / (1 + math.sqrt(1 - (1 + coni) * curv * curv * r * r))
            expect += sum(xdat.get(2 + i, 0.0) * (r / rn) ** (i if odd else 2 * i) for i in range(1, n_terms + 1))
            got = float(g.sag(torch.tensor(r, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)))
            assert got == pytest.approx(expect, rel=1e-13, abs=1e-15)


def test_cli_info_prints_the_field_table(capsys):
    """`raywave info` on a real-image-height zoom: the field table in degrees and in image height; --config."""
    from raywave.cli.main import main

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["info", str(DATA / "Canon EF24-70mm f2.8L II USM.zmx")]) == 0
    out = capsys.readouterr().out
    assert "Fields (defined by real image height (file)" in out
    assert "angle (deg)" in out and "real image h (mm)" in out and "paraxial image h (mm)" in out
    row = next(ln for ln in out.splitlines() if ln.strip().startswith("3 "))
    angle, real_h = (float(v) for v in row.split()[1:3])
    assert angle == pytest.approx(42.0809, abs=1e-3) and real_h == pytest.approx(21.64, abs=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["info", str(DATA / "Canon EF24-70mm f2.8L II USM.zmx"), "--config", "3"]) == 0
    long_end = capsys.readouterr().out
    efl = float(next(ln for ln in long_end.splitlines() if "Effective focal length (paraxial)" in ln).split()[-2])
    assert efl > 60.0


@pytest.mark.slow
def test_cli_psf_with_the_default_blank_doe(tmp_path):
    """`raywave psf` on the real-image-height Canon zoom works with the default blank DOE (end to end)."""
    import json

    from raywave.cli.main import main

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["psf", str(DATA / "Canon EF24-70mm f2.8L II USM.zmx"), "--field", "0", "20", "--ks", "32",
                     "-o", str(tmp_path / "psf.npy"), "--json"]) == 0
    import numpy as np

    psf = np.load(tmp_path / "psf.npy")
    assert psf.shape == (32, 32) and abs(psf.sum() - 1.0) < 1e-9
