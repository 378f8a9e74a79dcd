"""Lens-file io: raywave JSON (strict, exact), Zemax .zmx (read/write), DeepLens JSON (import)."""

import json
import math
import warnings

import pytest

from raywave.io import (LensFileError, LensFileWarning, canonical_spec, detect_format, read_deeplens,
                        read_json_spec, read_lens_spec, read_zmx, validate_spec, write_json_spec,
                        write_lens_spec, write_zmx)
from raywave.io.spec import radius_from_curvature

# ----------------------------------------------------------------------------------------- fixtures
COOKE_R = [22.01359, -435.7604, -22.21328, 20.29192, 79.68364, -18.3783]
COOKE_T = [3.25896, 6.007551, 0.9994, 4.750409, 2.952076, 42.20778]
COOKE_G = ["SK16", None, "F2", None, "SK16", None]


def cooke_spec():
    surfs = []
    for i, (r, t, g) in enumerate(zip(COOKE_R, COOKE_T, COOKE_G)):
        surfs.append({"type": "standard", "radius": r, "conic": 0.0, "thickness": t,
                      "material": g or "air", "aperture": None, "semi_diameter": 5.0, "stop": i == 3})
    return {
        "format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"},
        "name": "Cooke 40 degree field", "catalogs": ["SCHOTT"],
        "object": {"distance": "inf"}, "system_aperture": {"epd": 10.0},
        "fields": {"type": "angle", "values": [0.0, 14.0, 20.0]},
        "wavelengths": {"values": [0.4861327, 0.5875618, 0.6562725], "primary": 1},
        "surfaces": surfs,
    }


def cooke_zmx_text(extra_surface_lines=(), glass=("SK16", "F2")):
    """A Cooke triplet .zmx as OpticStudio writes it (abridged), curvatures as exact reciprocals."""
    lines = [
        "VERS 140404 277 24917", "MODE SEQ", "NAME Cooke 40 degree field", "PFIL 0 0 0", "LANG 0",
        "UNIT MM X W X CM MR CPMM", "ENPD 1.0E+1", "ENVD 2.0E+1 1 0", "GFAC 0 0", "GCAT SCHOTT",
        "RAIM 0 0 1 1 0 0 0 0 0", "PUSH 0 0 0 0 0 0", "SDMA 0 1 0", "FTYP 0 0 3 3 0 0 0", "ROPD 2", "PICB 1",
        "XFLN 0 0 0 0 0 0 0 0 0 0 0 0", "YFLN 0 1.4E+1 2.0E+1 0 0 0 0 0 0 0 0 0",
        "FWGN 1 1 1 1 1 1 1 1 1 1 1 1", "VDXN 0 0 0 0 0 0 0 0 0 0 0 0",
        "WAVM 1 0.4861327 1", "WAVM 2 0.5875618 1", "WAVM 3 0.6562725 1", "WAVM 4 0.55000000000000004 1",
        "PWAV 2", "POLS 1 0 1 0 0 1 0", "GLRS 1 0",
        "SURF 0", "  TYPE STANDARD", '  CURV 0.0 0 0 0 0 ""', "  HIDE 0 0 0 0 0 0 0 0 0 0", "  MIRR 2 0",
        "  SLAB 1", "  DISZ INFINITY", '  DIAM 0 0 0 0 1 ""', "  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0",
    ]
    glasses = {0: glass[0], 2: glass[1], 4: glass[0]}
    for i, (r, t) in enumerate(zip(COOKE_R, COOKE_T)):
        lines += [f"SURF {i + 1}"]
        if i == 3:
            lines.append("  STOP")
        lines += ["  TYPE STANDARD", f'  CURV {1.0 / r!r} 0 0 0 0 ""', "  HIDE 0 0 0 0 0 0 0 0 0 0",
                  "  MIRR 2 0", f"  SLAB {i + 2}", f"  DISZ {t}"]
        if i in glasses:
            lines.append(f"  GLAS {glasses[i]} 0 0 1.6 5.0E+1 0 0 0 0 0 0")
        lines.append('  DIAM 5 1 0 0 1 ""')
        if i == 1:
            lines += list(extra_surface_lines)
    lines += ["SURF 7", "  TYPE STANDARD", "  CURV 0.0", "  DISZ 0", '  DIAM 1.8E+1 0 0 0 1 ""',
              "TOL TOFF 0 0 0 0 0 0 0", "MNUM 1 1"]
    return "\r\n".join(lines) + "\r\n"


def write_bytes(tmp_path, name, text, encoding):
    p = tmp_path / name
    if encoding == "utf-16-bom":
        p.write_bytes(b"\xff\xfe" + text.encode("utf-16-le"))
    elif encoding == "utf-16-nobom":
        p.write_bytes(text.encode("utf-16-le"))
    else:
        p.write_bytes(text.encode(encoding))
    return p


def full_spec():
    """A spec using every feature the formats share (asphere, paraxial, model / index glass, apertures)."""
    return {
        "format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"},
        "name": "kitchen sink", "catalogs": ["SCHOTT", "OHARA"],
        "object": {"distance": 1000.0 / 3.0},
        "system_aperture": {"epd": 4.0},
        "fields": {"type": "object_height", "values": [0.0, 5.0, 10.0]},
        "wavelengths": {"values": [0.55, 0.4861327, 0.6562725], "primary": 0},
        "surfaces": [
            {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": 0.1, "material": "air",
             "aperture": {"shape": "circle", "radius": 1.0}, "stop": True, "comment": "stop"},
            {"type": "even_asphere", "radius": 4.7531, "conic": -1.2051,
             "aspheric": {"a2": 0.0, "a4": 5.33e-4, "a6": 1.12e-5, "a8": -3.75e-7, "a10": 0.0},
             "thickness": 7.5, "material": {"model": {"nd": 1.5168, "vd": 64.17}}, "aperture": None,
             "semi_diameter": 3.2, "stop": False},
            {"type": "standard", "curvature": 1.0 / 30.0, "conic": 0.0, "thickness": 2,
             "material": {"index": 1.5}, "aperture": {"shape": "square", "half_width": 2.5}, "stop": False},
            {"type": "standard", "radius": -15.65, "thickness": 5.0, "material": "N-BK7"},
            {"type": "paraxial", "focal_length": 25.0, "thickness": 25.0, "material": "air",
             "aperture": None, "stop": False},
        ],
    }


# ----------------------------------------------------------------------------------------- JSON
def test_json_round_trip_exact(tmp_path):
    spec = full_spec()
    spec["surfaces"][0]["thickness"] = 1.0 / 3.0
    spec["surfaces"][1]["radius"] = 22.01359
    spec["surfaces"][3]["thickness"] = 0.1 + 0.2
    spec["sensor"] = {"size": [36.0, 24.0], "resolution": [6000, 4000]}
    spec["description"] = "µm-exact round trip: ½"
    p = tmp_path / "lens.json"
    write_json_spec(spec, p)
    back = read_json_spec(p)
    assert back == spec
    assert back["surfaces"][0]["thickness"] == 1.0 / 3.0
    assert back["surfaces"][3]["thickness"] == 0.1 + 0.2
    assert isinstance(back["sensor"]["resolution"][0], int)
    assert '"inf"' in p.read_text(encoding="utf-8")
    # and through the dispatching reader / writer
    write_lens_spec(spec, tmp_path / "again.json")
    assert read_lens_spec(tmp_path / "again.json") == spec
    assert detect_format(p) == "raywave"


def test_json_header_added_when_missing(tmp_path):
    spec = {"surfaces": [{"radius": 10.0, "thickness": 2.0, "material": {"index": 1.5}},
                         {"radius": "inf", "thickness": 18.0}]}
    write_json_spec(spec, tmp_path / "bare.json")
    back = read_json_spec(tmp_path / "bare.json")
    assert back["format"] == "raywave-lens" and back["version"] == 1
    assert back["surfaces"] == spec["surfaces"]
    assert list(back)[:3] == ["format", "version", "units"]


def test_unknown_key_has_line_path_and_suggestion(tmp_path):
    spec = cooke_spec()
    spec["surfaces"][3]["radus"] = spec["surfaces"][3].pop("radius")
    p = tmp_path / "typo.json"
    text = json.dumps(spec, indent=2)
    p.write_text(text)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if '"radus"' in ln)
    with pytest.raises(LensFileError) as e:
        read_json_spec(p)
    msg = str(e.value)
    assert f"{p}:{line}: surfaces[3].radus: unknown key 'radus'" in msg
    assert "did you mean 'radius'?" in msg
    assert e.value.line == line and e.value.path == str(p)
    assert isinstance(e.value, ValueError)


def test_unknown_top_level_and_nested_keys(tmp_path):
    spec = cooke_spec()
    spec["wavelenghts"] = spec.pop("wavelengths")
    spec["system_aperture"]["epd_mm"] = 3
    with pytest.raises(LensFileError) as e:
        validate_spec(spec)
    msg = str(e.value)
    assert "<spec>: wavelenghts: unknown key 'wavelenghts' (did you mean 'wavelengths'?)" in msg
    assert "system_aperture.epd_mm: unknown key 'epd_mm' (did you mean 'epd'?)" in msg
    assert len(e.value.errors) == 2


def test_malformed_json_reports_line_and_column(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{\n  "format": "raywave-lens",\n  "surfaces": [\n    {"radius": 10.0 "thickness": 1}\n  ]\n}\n')
    with pytest.raises(LensFileError) as e:
        read_json_spec(p)
    assert str(e.value).startswith(f"{p}:4:")
    assert "invalid JSON" in str(e.value)
    assert e.value.line == 4


def test_json_nan_and_duplicate_keys_rejected(tmp_path):
    p = tmp_path / "nan.json"
    p.write_text('{"format": "raywave-lens",\n "surfaces": [{"thickness": NaN}]}')
    with pytest.raises(LensFileError, match=r"nan.json:2: invalid JSON"):
        read_json_spec(p)
    p.write_text('{"format": "raywave-lens",\n "surfaces": [{"thickness": 1,\n "thickness": 2}]}')
    with pytest.raises(LensFileError, match=r"nan.json:3: surfaces\[0\]\.thickness: duplicate key 'thickness'"):
        read_json_spec(p)


@pytest.mark.parametrize("mutate, expected", [
    (lambda s: s["surfaces"][0].update(radius=0), "surfaces[0].radius: radius 0 is not a surface"),
    (lambda s: s.update(surfaces=[]), "surfaces: the lens has no surfaces"),
    (lambda s: s["surfaces"][3].update(aperture={"shape": "circle", "radius": 0.0}),
     "surfaces[3].aperture.radius: empty aperture"),
    (lambda s: s["surfaces"][1].update(type="biconic"),
     "unknown surface type 'biconic'; known types: standard, even_asphere, odd_asphere, toroidal, paraxial"),
    (lambda s: s["surfaces"][2].update(curvature=0.05), "give either 'radius' or 'curvature', not both"),
    (lambda s: s["surfaces"][2].update(thickness="3 mm"), "surfaces[2].thickness: must be a number"),
    (lambda s: s["surfaces"][2].pop("thickness"), "surfaces[2]: missing 'thickness'"),
    (lambda s: s["surfaces"][2].update(aspheric={"a4": 1e-5}), "'aspheric' is not allowed on a 'standard'"),
    (lambda s: s["surfaces"][0].update(stop=True), "one aperture stop"),
    (lambda s: s["wavelengths"].update(values=[486.1, 587.6, 656.3]), "wavelengths are in µm, not nm"),
    (lambda s: s["wavelengths"].update(primary=3), "wavelengths.primary: index 3 out of range"),
    (lambda s: s.update(version=2), "newer than this raywave reads"),
    (lambda s: s["units"].update(length="in"), "units.length: must be 'mm'"),
    (lambda s: s["surfaces"][0].update(material={"model": {"nd": 1.5}}), "a model glass needs 'vd'"),
    (lambda s: s["surfaces"][0].update(material={"indx": 1.5}), "did you mean 'index'?"),
    (lambda s: s["object"].update(distance=-5.0), "object.distance: must be > 0"),
    (lambda s: s["object"].update(distance=math.inf), "write infinity as the string \"inf\""),
    (lambda s: s["fields"].update(type="angles"), "did you mean 'angle'?"),
    (lambda s: s["surfaces"][3].update(aperture={"shape": "circle", "half_width": 2}), "belongs to a 'square'"),
])
def test_schema_errors(mutate, expected):
    spec = cooke_spec()
    mutate(spec)
    with pytest.raises(LensFileError) as e:
        validate_spec(spec)
    assert expected in str(e.value)


def test_paraxial_needs_focal_length():
    spec = cooke_spec()
    spec["surfaces"][0] = {"type": "paraxial", "thickness": 10.0}
    with pytest.raises(LensFileError, match="needs 'focal_length'"):
        validate_spec(spec)
    spec["surfaces"][0] = {"type": "paraxial", "thickness": 10.0, "focal_length": 50.0, "radius": 3.0}
    with pytest.raises(LensFileError, match="'radius' is not allowed on a 'paraxial' surface"):
        validate_spec(spec)


def test_not_a_lens_file(tmp_path):
    p = tmp_path / "other.json"
    p.write_text('{"hello": 1}')
    with pytest.raises(LensFileError, match="not a lens file raywave knows"):
        read_lens_spec(p)
    with pytest.raises(LensFileError, match="missing \"format\""):
        read_json_spec(p)
    with pytest.raises(LensFileError, match="unknown lens file extension '.txt'"):
        read_lens_spec(p.rename(tmp_path / "other.txt"))
    with pytest.raises(LensFileError, match="cannot write lens files with extension '.seq'"):
        write_lens_spec(cooke_spec(), tmp_path / "x.seq")


# ----------------------------------------------------------------------------------------- .zmx
@pytest.mark.parametrize("encoding", ["utf-8", "utf-16-bom", "utf-16-nobom", "latin-1"])
def test_zmx_cooke_triplet(tmp_path, encoding):
    p = write_bytes(tmp_path, "cooke.zmx", cooke_zmx_text(), encoding)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean OpticStudio-style file reads without warnings
        spec = read_lens_spec(p)
    assert spec == cooke_spec()
    assert detect_format(p) == "zmx"


def test_zmx_glass_forms(tmp_path):
    text = cooke_zmx_text().replace("GLAS F2 0 0 1.6 5.0E+1", "GLAS ___BLANK 1 0 1.62004 36.37")
    text = text.replace("  GLAS SK16 0 0 1.6 5.0E+1 0 0 0 0 0 0\r\n  DIAM 5 1 0 0 1 \"\"\r\nSURF 6",
                        "  GLAS ___BLANK 1 0 1.5 0 0 0 0 0 0 0\r\n  DIAM 5 1 0 0 1 \"\"\r\nSURF 6")
    spec = read_zmx(write_bytes(tmp_path, "g.zmx", text, "utf-8"))
    mats = [s["material"] for s in spec["surfaces"]]
    assert mats == ["SK16", "air", {"model": {"nd": 1.62004, "vd": 36.37}}, "air", {"index": 1.5}, "air"]


def test_zmx_unsupported_surface_type_names_surface(tmp_path):
    text = cooke_zmx_text().replace("SURF 2\r\n  TYPE STANDARD", "SURF 2\r\n  TYPE SZERNSAG")
    p = write_bytes(tmp_path, "zernike.zmx", text, "utf-16-bom")
    line = text.split("\r\n").index("  TYPE SZERNSAG") + 1
    with pytest.raises(LensFileError) as e:
        read_zmx(p)
    assert str(e.value).startswith(f"{p}:{line}: surface 2: surface type SZERNSAG (Zernike standard sag) is not "
                                   "supported")
    assert "STANDARD, EVENASPH, ODDASPHE, TOROIDAL, PARAXIAL" in str(e.value)
    bad = cooke_zmx_text().replace("SURF 3\r\n  TYPE STANDARD", "SURF 3\r\n  TYPE BICONIC")
    with pytest.raises(LensFileError, match="surface 3: surface type BICONIC .biconic. is not supported"):
        read_zmx(write_bytes(tmp_path, "b.zmx", bad, "utf-8"))
    # a curved BINARY_2 inside the lens is read as a conformal DOE on that surface (issue 46)
    curved = cooke_zmx_text().replace("SURF 3\r\n  TYPE STANDARD", "SURF 3\r\n  TYPE BINARY_2")
    s3 = read_zmx(write_bytes(tmp_path, "c.zmx", curved, "utf-8"))["surfaces"][2]
    assert s3["doe"]["conformal"] is True and s3["radius"] != "inf"


@pytest.mark.parametrize("edit, expected", [
    (("SURF 3\r\n  TYPE STANDARD", "SURF 3\r\n  STOP\r\n  TYPE COORDBRK"),
     "surface 3: a coordinate break cannot be the stop"),
    (("ENPD 1.0E+1", "OBNA 0.1 0"), "OBNA: an object-space NA needs an object at a finite distance"),
    (("ENPD 1.0E+1", "FNUM 4 2"), "FNUM 4 2: unknown system aperture flag 2"),
    (("MODE SEQ", "MODE NSC"), "only sequential"),
    (("FTYP 0 0 3 3", "FTYP 7 0 3 3"), "FTYP 7: unknown field type"),
    (("UNIT MM", "UNIT FURLONG"), "UNIT FURLONG: unknown lens unit"),
    (("SURF 7\r\n  TYPE STANDARD\r\n  CURV 0.0", "SURF 7\r\n  TYPE EVENASPH\r\n  CURV 0.01"),
     "surface 7 (image): a non-standard image surface (type EVENASPH"),
])
def test_zmx_unsupported_features(tmp_path, edit, expected):
    text = cooke_zmx_text().replace(*edit, 1)
    assert text != cooke_zmx_text()
    with pytest.raises(LensFileError) as e:
        read_zmx(write_bytes(tmp_path, "x.zmx", text, "utf-8"))
    assert expected in str(e.value)
    assert str(e.value).startswith(str(tmp_path / "x.zmx"))


def test_zmx_apertures_and_unknown_keys(tmp_path):
    text = cooke_zmx_text(extra_surface_lines=["  CLAP 0 4.5 0", "  FOOB 1 2 3"])
    with pytest.warns(LensFileWarning, match=r"FOOB \(surface 2\) \(line \d+\)"):
        spec = read_zmx(write_bytes(tmp_path, "ap.zmx", text, "utf-8"))
    assert spec["surfaces"][1]["aperture"] == {"shape": "circle", "radius": 4.5}
    sq = cooke_zmx_text(extra_surface_lines=["  SQAP 2.0 2.0 0 0 0"])
    assert read_zmx(write_bytes(tmp_path, "sq.zmx", sq, "utf-8"))["surfaces"][1]["aperture"] == {
        "shape": "square", "half_width": 2.0}
    # rectangles (SQAP 2 3), annular obscurations (OBSC 1 2) and decentres (OBDC) are read since issue 44
    # (tests/test_apertures_files.py)
    for extra, msg in ((["  CLAP 0 0 0"], "empty aperture"), (["  CLAP 3 1 0"], "minimum radius")):
        bad = cooke_zmx_text(extra_surface_lines=extra)
        with pytest.raises(LensFileError, match=f"surface 2: .*{msg}"):
            read_zmx(write_bytes(tmp_path, "bad.zmx", bad, "utf-8"))


def test_zmx_float_by_stop_size_and_units(tmp_path):
    text = cooke_zmx_text().replace("ENPD 1.0E+1", "FLOA")
    spec = read_zmx(write_bytes(tmp_path, "floa.zmx", text, "utf-8"))
    assert "system_aperture" not in spec
    assert spec["surfaces"][3]["aperture"] == {"shape": "circle", "radius": 5.0}  # the stop's semi-diameter
    cm = cooke_zmx_text().replace("UNIT MM", "UNIT CM")
    spec_cm = read_zmx(write_bytes(tmp_path, "cm.zmx", cm, "utf-8"))
    assert spec_cm["system_aperture"]["epd"] == pytest.approx(100.0)
    assert spec_cm["surfaces"][0]["radius"] == pytest.approx(220.1359)
    assert spec_cm["surfaces"][0]["thickness"] == pytest.approx(32.5896)


@pytest.mark.parametrize("encoding", ["utf-16", "utf-8"])
def test_zmx_round_trip(tmp_path, encoding):
    spec = full_spec()
    p = tmp_path / "sink.zmx"
    write_zmx(spec, p, encoding=encoding)
    raw = p.read_bytes()
    assert raw.startswith(b"\xff\xfe") == (encoding == "utf-16")
    assert "\r\n" in raw.decode("utf-16" if encoding == "utf-16" else "utf-8")
    back = read_zmx(p)
    assert back == canonical_spec(spec)
    # twice round: stable
    write_lens_spec(back, tmp_path / "again.zmx")
    assert read_lens_spec(tmp_path / "again.zmx") == back


def test_zmx_round_trip_cooke_and_lossy_warning(tmp_path):
    spec = cooke_spec()
    write_zmx(spec, tmp_path / "c.zmx")
    assert read_zmx(tmp_path / "c.zmx") == spec
    spec["sensor"] = {"size": [36.0, 24.0], "resolution": [600, 400]}
    with pytest.warns(LensFileWarning, match="do not store sensor"):
        write_zmx(spec, tmp_path / "s.zmx")
    spec["surfaces"][1]["type"] = "even_asphere"
    spec["surfaces"][1]["aspheric"] = {"a20": 1e-20}
    del spec["sensor"]
    write_zmx(spec, tmp_path / "a20.zmx")  # more terms than EVENASPH holds: an extended asphere (XASPHERE)
    text = (tmp_path / "a20.zmx").read_bytes().decode("utf-16")
    assert "TYPE XASPHERE" in text and "XDAT 1 10.0" in text
    assert read_zmx(tmp_path / "a20.zmx")["surfaces"][1]["aspheric"]["a20"] == 1e-20


def test_radius_from_curvature_prefers_short_form():
    for r in COOKE_R + [1.0 / 3.0, 4.7531, -15.65, 1e-3, 123456.789]:
        back = radius_from_curvature(1.0 / r)
        assert 1.0 / back == 1.0 / r
        assert len(repr(back)) <= len(repr(r))
    assert radius_from_curvature(0.0) == "inf"


# ----------------------------------------------------------------------------------------- DeepLens
DEEPLENS_NEW = {
    "info": "US 2021/0263286 Example 1 (abridged)",
    "foclen": 49.565, "fnum": 1.8387, "r_sensor": 21.6, "(d_sensor)": 59.5344,
    "(sensor_size)": [30.547, 30.547], "sensor_res": [3000, 2000],
    "surfaces": [
        {"idx": 0, "type": "Spheric", "r": 15.0, "(c)": 0.0349, "roc": 28.621, "(d)": 0.0,
         "mat2": "1.83481/42.7", "d_next": 4.2},
        {"idx": 1, "type": "Spheric", "r": 14.24, "(c)": 0.0147, "roc": 68.136, "(d)": 4.2, "mat2": "air",
         "d_next": 5.27},
        {"idx": 2, "type": "Aperture", "r": 8.12, "(d)": 9.47, "mat2": "air", "is_square": False,
         "diffraction": False, "d_next": 6.2},
        {"idx": 3, "type": "Aspheric", "r": 7.76, "(c)": -0.04, "roc": -25.0, "d": 15.67, "k": 0.0,
         "ai": [0.0, -4.12032e-05, -2.90015e-07, -4.67119e-09, 7.90646e-11, -9.2847e-13],
         "mat2": "1.53110/55.9", "(ai2)": 0.0, "(ai4)": -4.12032e-05, "(ai6)": -2.90015e-07,
         "(ai8)": -4.67119e-09, "(ai10)": 7.90646e-11, "(ai12)": -9.2847e-13, "d_next": 2.95},
        {"idx": 4, "type": "Spheric", "r": 9.7, "(c)": -0.0544, "roc": -18.373, "(d)": 18.62, "mat2": "air",
         "d_next": 40.9144},
    ],
}

# the older layout: absolute "d", "c" without "roc" on some surfaces, "Stop", mat1, d_sensor
DEEPLENS_OLD = {
    "foclen": 49.8, "fnum": 4.0, "r_last": 18.175, "d_sensor": 60.439, "sensor_size": [25.7, 25.7],
    "surfaces": [
        {"type": "Spheric", "r": 7.5, "c": 0.0454, "d": 0.0, "mat1": "air", "mat2": "sk16"},
        {"type": "Spheric", "r": 7.5, "c": -0.0023, "roc": -434.78, "d": 3.259, "mat1": "sk16", "mat2": "air"},
        {"type": "Stop", "r": 5.0, "c": 0.0, "d": 12.385, "mat1": "air", "mat2": "occluder"},
        {"type": "Spheric", "r": 7.5, "c": -0.0544, "d": 18.087, "mat1": "occluder", "mat2": "1.6204/60.3"},
    ],
}


def test_deeplens_import(tmp_path):
    p = tmp_path / "rf50.json"
    p.write_text(json.dumps(DEEPLENS_NEW, indent=4))
    assert detect_format(p) == "deeplens"
    spec = read_lens_spec(p)
    assert spec["name"] == "rf50" and spec["description"].startswith("US 2021")
    s = spec["surfaces"]
    assert [x["type"] for x in s] == ["standard", "standard", "standard", "even_asphere", "standard"]
    assert s[0]["radius"] == 28.621 and s[0]["semi_diameter"] == 15.0
    assert s[0]["material"] == {"model": {"nd": 1.83481, "vd": 42.7}}
    assert [x["thickness"] for x in s] == [4.2, 5.27, 6.2, 2.95, 40.9144]
    assert s[2] == {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": 6.2, "material": "air",
                    "aperture": {"shape": "circle", "radius": 8.12}, "stop": True}
    assert [x["stop"] for x in s] == [False, False, True, False, False]
    # ai = [a2, a4, ...]: ai[i] multiplies r^(2i+2)
    assert s[3]["aspheric"] == {"a2": 0.0, "a4": -4.12032e-05, "a6": -2.90015e-07, "a8": -4.67119e-09,
                                "a10": 7.90646e-11, "a12": -9.2847e-13}
    assert s[3]["radius"] == -25.0 and s[3]["conic"] == 0.0
    w, h = spec["sensor"]["size"]
    assert math.hypot(w, h) == pytest.approx(2 * 21.6) and w / h == pytest.approx(1.5)
    assert spec["sensor"]["resolution"] == [3000, 2000]
    hfov = math.degrees(math.atan(21.6 / 49.565))
    assert spec["fields"]["values"] == pytest.approx([0.0, 0.7 * hfov, hfov])
    assert spec["object"] == {"distance": "inf"} and "system_aperture" not in spec
    # the import is a valid raywave spec that round-trips through both writers
    write_lens_spec(spec, tmp_path / "rf50_raywave.json")
    assert read_lens_spec(tmp_path / "rf50_raywave.json") == spec
    with pytest.warns(LensFileWarning, match="do not store sensor and description"):
        write_lens_spec(spec, tmp_path / "rf50.zmx")
    back = read_lens_spec(tmp_path / "rf50.zmx")
    assert back["surfaces"] == canonical_spec(spec)["surfaces"]


def test_deeplens_old_layout_absolute_positions(tmp_path):
    p = tmp_path / "cooke_dl.json"
    p.write_text(json.dumps(DEEPLENS_OLD))
    spec = read_deeplens(p)
    s = spec["surfaces"]
    assert [x["thickness"] for x in s] == pytest.approx([3.259, 12.385 - 3.259, 18.087 - 12.385, 60.439 - 18.087])
    assert s[0]["radius"] == radius_from_curvature(0.0454)
    assert s[1]["radius"] == -434.78
    assert s[0]["material"] == "sk16" and s[2]["material"] == "air" and s[2]["stop"]
    assert s[3]["material"] == {"model": {"nd": 1.6204, "vd": 60.3}}
    assert spec["sensor"] == {"size": [25.7, 25.7]}
    clipped = read_deeplens(p, clip_apertures=True)
    assert clipped["surfaces"][0]["aperture"] == {"shape": "circle", "radius": 7.5}


def test_deeplens_unsupported(tmp_path):
    bad = json.loads(json.dumps(DEEPLENS_NEW))
    bad["surfaces"][1]["type"] = "Cubic"
    p = tmp_path / "cubic.json"
    text = json.dumps(bad, indent=4)
    p.write_text(text)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if '"Cubic"' in ln)
    with pytest.raises(LensFileError) as e:
        read_lens_spec(p)
    assert str(e.value).startswith(f"{p}:{line}: surfaces[1]: DeepLens surface type 'Cubic' is not supported")
    hybrid = dict(DEEPLENS_NEW, DOE={"type": "binary2"})
    p.write_text(json.dumps(hybrid))
    with pytest.raises(LensFileError, match="DOE"):
        read_lens_spec(p)


# ----------------------------------------------------------------------------------------- building
def _materials():
    materials = pytest.importorskip("raywave.materials")
    if not hasattr(materials, "get_material"):
        pytest.skip("raywave.materials.get_material not available yet")
    return materials


def _build(spec):
    from raywave.lens.build import lens_from_spec

    return lens_from_spec(spec)


def test_build_from_json_zmx_and_deeplens(tmp_path):
    _materials()
    from raywave.lens.build import lens_to_spec

    # .zmx Cooke triplet with catalog glasses
    p = write_bytes(tmp_path, "cooke.zmx", cooke_zmx_text(glass=("N-SK16", "F2")), "utf-16-bom")
    lens = _build(read_lens_spec(p))
    efl = lens.paraxial().efl
    assert math.isfinite(efl) and 45 < efl < 55
    # JSON with model / index glasses, asphere, paraxial surface
    write_lens_spec(full_spec(), tmp_path / "sink.json")
    sink = _build(read_lens_spec(tmp_path / "sink.json"))
    assert math.isfinite(sink.paraxial().efl)
    # lens -> spec -> .zmx -> spec -> lens gives the same first-order optics
    write_lens_spec(lens_to_spec(lens), tmp_path / "again.zmx")
    again = _build(read_lens_spec(tmp_path / "again.zmx"))
    assert again.paraxial().efl == pytest.approx(efl, rel=1e-12)
    # DeepLens import (model glasses only)
    dl = tmp_path / "rf50.json"
    dl.write_text(json.dumps(DEEPLENS_NEW))
    assert math.isfinite(_build(read_lens_spec(dl)).paraxial().efl)


def test_zmx_unknown_glass_without_catalogs(tmp_path):
    materials = _materials()
    text = cooke_zmx_text(glass=("NOSUCHGLASS-42", "F2")).replace("GCAT SCHOTT\r\n", "")
    spec = read_lens_spec(write_bytes(tmp_path, "g.zmx", text, "utf-8"))
    assert "catalogs" not in spec
    with pytest.raises(materials.GlassNotFoundError) as e:
        _build(spec)
    assert "NOSUCHGLASS-42" in str(e.value)


# ----------------------------------------------------------------------------------------- bundled lenses
def _bundled():
    from pathlib import Path

    import raywave

    return sorted((Path(raywave.__file__).parent / "data" / "lenses").glob("*.json"))


@pytest.mark.parametrize("path", _bundled(), ids=lambda p: p.stem)
def test_bundled_lenses_read_and_round_trip(tmp_path, path):
    spec = read_lens_spec(path)
    write_json_spec(spec, tmp_path / "b.json")
    assert read_json_spec(tmp_path / "b.json") == spec
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LensFileWarning)  # sensor / description / doe are not stored in .zmx
        write_zmx(spec, tmp_path / "b.zmx")
    back = read_zmx(tmp_path / "b.zmx")
    expected = canonical_spec(spec)
    for k in ("sensor", "description", "doe"):
        expected.pop(k, None)
    assert back == expected
