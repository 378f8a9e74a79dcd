"""``write_zmx`` writes the DOEs inside the lens (issue 46): a surface DOE with a ``binary_2`` phase model as a
BINARY_2 surface, a ``grating`` (at ±90°) or a blank one as a DGRATING, on the surface itself (a plane with the DOE
0 mm after it, or conformal on a sphere / conic) or on a plane of its own in the gap; what a .zmx cannot hold is
named in the :class:`LensFileWarning`.

Checked: the repo's .zmx fixtures with mid-system BINARY_2 / DGRATING surfaces (tests/test_midsystem_zmx.py; in mm
and in cm) read → written → read to the same spec and the same text; hand-written specs → .zmx → spec; and,
independently of the reader and writer, real rays through the read-back lens and the original (the DOEs as
analytic phase surfaces of their phase models, and as the engine's pixel-map phase surfaces) agree to 1e-12, and a
written DGRATING bends a ray by OpticStudio's grating equation with the file's own PARM 1 / PARM 2."""

import copy
import math
import re
import warnings

import pytest
import torch

from test_midsystem_zmx import CURVED, DGRATING, DOUBLET, WL

from raywave.assembly.midsystem import does_lens, lens_with_doe
from raywave.hybrid import SamplingWarning
from raywave.hybrid.midsystem import insert_doe
from raywave.io import LensFileWarning, read_lens_spec
from raywave.io.zmx import write_zmx, zmx_text
from raywave.io.zmx.surface_doe_writer import grating_lines_per_um
from raywave.rays.bundle import RayBundle

CURVED_DGRATING = DGRATING.replace("  TYPE DGRATING\n  CURV 0.0\n", "  TYPE DGRATING\n  CURV -0.01\n  CONI -0.5\n")
FIXTURES = {"binary2": DOUBLET, "dgrating": DGRATING, "curved_binary2": CURVED, "curved_dgrating": CURVED_DGRATING,
            "binary2_cm": DOUBLET.replace("UNIT MM", "UNIT CM")}


def _read_text(tmp_path, text, name="in.zmx"):
    path = tmp_path / name
    path.write_text(text)
    return read_lens_spec(path)


def _write_read(tmp_path, spec, name="out.zmx"):
    """``spec`` → .zmx (no warning allowed) → spec."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_zmx(spec, tmp_path / name)
    return read_lens_spec(tmp_path / name)


def _doublet(tmp_path):
    """The doublet of tests/test_midsystem_zmx.py without its DOE (lens 1, R 50 mm / plane, n 1.5; lens 2, R 60 /
    −80 mm, n 1.6), in the reader's form."""
    spec = _read_text(tmp_path, DOUBLET, "doublet.zmx")
    del spec["surfaces"][1]["doe"]
    return spec


B2 = {"type": "binary_2", "order": 1.0, "norm_radius": 5.0, "coefficients": [-300.0, 10.0]}


# ------------------------------------------------------------------------------------------ the repo's fixtures
@pytest.mark.parametrize("name", list(FIXTURES))
def test_fixtures_with_doe_surfaces_round_trip(tmp_path, name):
    """file → spec → .zmx → spec: the same spec (the DOE on the same surface, same coefficients, thicknesses,
    glasses), without a warning; writing the read-back spec gives the same text, the DOE surface of the same type
    at the same SURF number."""
    text = FIXTURES[name]
    spec = _read_text(tmp_path, text)
    back = _write_read(tmp_path, spec)
    assert back == spec
    assert zmx_text(back) == zmx_text(spec)
    typ = "DGRATING" if "DGRATING" in text else "BINARY_2"
    assert re.search(rf"SURF 2\r\n  TYPE {typ}\r\n", zmx_text(spec))
    if name == "binary2_cm":  # read in cm, written in mm: the same lens (R = 5 cm = 50 mm)
        assert spec["surfaces"][1]["doe"]["phase_model"]["norm_radius"] == 50.0
        assert spec["surfaces"][1]["thickness"] == 20.0


def test_curved_dgrating_keeps_its_conic(tmp_path):
    """A conformal DOE's substrate is the surface's sphere and conic (OpticStudio's DGRATING / BINARY_2 sag): the
    reader keeps CONI (it used to drop it), the writer writes it back."""
    spec = _read_text(tmp_path, CURVED_DGRATING)
    s = spec["surfaces"][1]
    assert s["radius"] == -100.0 and s["conic"] == -0.5 and s["doe"]["conformal"] is True
    assert s["doe"]["phase_model"] == {"type": "grating", "period": 0.02, "angle": -90.0}
    block = zmx_text(spec).split("SURF 2\r\n")[1].split("SURF 3")[0]
    assert "TYPE DGRATING" in block and "CURV -0.01" in block and "CONI -0.5" in block
    assert "PARM 1 0.05" in block and "PARM 2 -1.0" in block


# ------------------------------------------------------------------------------------------ hand-written specs
def _cases(tmp_path) -> dict:
    """Specs with DOEs inside the doublet (reader form), by case."""
    base = _doublet(tmp_path)
    out = {}

    s = copy.deepcopy(base)  # the plane back face of lens 1 carries the DOE (its own CLAP is the DOE's size)
    s["surfaces"][1].update(aperture={"shape": "circle", "radius": 5.0},
                            doe={"distance": 0.0, "aperture": "circle", "size": [10.0, 10.0], "phase": None,
                                 "phase_model": B2})
    out["on_the_plane"] = s

    s = copy.deepcopy(base)  # in the air gap, 1.25 mm after the plane: a plane of its own
    s["surfaces"][1]["doe"] = {"distance": 1.25, "aperture": "circle", "size": [9.0, 9.0], "phase": None,
                               "phase_model": B2}
    out["in_the_air_gap"] = s

    s = copy.deepcopy(base)  # inside lens 1's glass, and a blank one in the air gap
    s["surfaces"][0]["doe"] = {"distance": 1.5, "aperture": "square", "size": [6.0, 6.0], "phase": None,
                               "phase_model": {"type": "grating", "period": 0.02, "angle": -90.0}}
    s["surfaces"][1]["doe"] = {"distance": 0.5, "aperture": "square", "phase": None}
    out["in_the_glass_and_blank"] = s

    s = copy.deepcopy(base)  # two on lens 2's curved back face: at its vertex (a plane there) and 5 mm after it
    s["surfaces"][3]["doe"] = [
        {"distance": 5.0, "aperture": "circle", "size": [8.0, 8.0], "phase": None,
         "phase_model": {"type": "grating", "period": 0.05, "angle": 90.0}},
        {"distance": 0.0, "aperture": "square", "size": [8.0, 8.0], "phase": None,
         "phase_model": {"type": "binary_2", "order": -2.0, "norm_radius": 4.0, "coefficients": [50.0, -1.0 / 3]}}]
    out["two_on_a_curved_face"] = s

    s = copy.deepcopy(base)  # conformal: a BINARY_2 on lens 2's front (a conic), a grating on its back face
    s["surfaces"][2].update(conic=-0.7, doe={"conformal": True, "aperture": "square", "phase": None,
                                             "phase_model": B2})
    s["surfaces"][3].update(semi_diameter=6.0,
                            doe={"conformal": True, "aperture": "circle", "size": [12.0, 12.0], "phase": None,
                                 "phase_model": {"type": "grating", "period": 0.05, "angle": 90.0}})
    out["conformal"] = s
    return out


CASES = ["on_the_plane", "in_the_air_gap", "in_the_glass_and_blank", "two_on_a_curved_face", "conformal"]
#: surfaces the read-back spec has more than the original: a plane per DOE written on its own plane, and a plain
#: plane half way to the image after a DOE on (or after) the last surface (else read as the DOE before the sensor)
EXTRA = {"on_the_plane": 0, "in_the_air_gap": 1, "in_the_glass_and_blank": 2, "two_on_a_curved_face": 3,
         "conformal": 1}


@pytest.mark.parametrize("case", CASES)
def test_spec_zmx_spec(tmp_path, case):
    """spec → .zmx → spec, without a warning: a DOE the reader gives back on its surface is the same spec; one in a
    gap (or at a curved face's vertex, or not sized by the surface's aperture) comes back on a plane surface of its
    own there (0 mm after it: the surface's thickness split at the DOE, the plane's glass the gap's, its CLAP /
    SQAP the DOE's size); a DOE on or after the last surface gets a plain plane half way to the image after it;
    once more round, the same text."""
    spec = _cases(tmp_path)[case]
    back = _write_read(tmp_path, spec)
    assert zmx_text(back) == zmx_text(spec)
    assert len(back["surfaces"]) == len(spec["surfaces"]) + EXTRA[case]
    if case == "on_the_plane":
        assert back == spec
    if case == "in_the_air_gap":
        s0, s1, plane, s2, s3 = back["surfaces"]
        assert [s0, s2, s3] == [spec["surfaces"][k] for k in (0, 2, 3)]
        assert s1 == {k: v for k, v in spec["surfaces"][1].items() if k != "doe"} | {"thickness": 1.25}
        assert plane == {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": 2.0 - 1.25,
                         "material": "air", "aperture": {"shape": "circle", "radius": 4.5}, "stop": False,
                         "doe": dict(spec["surfaces"][1]["doe"], distance=0.0)}
    if case == "in_the_glass_and_blank":
        s0, plane, s1, blank = back["surfaces"][:4]
        assert s0["thickness"] == 1.5 and plane["thickness"] == 2.5 and plane["material"] == {"index": 1.5}
        assert plane["doe"] == dict(spec["surfaces"][0]["doe"], distance=0.0)
        assert plane["aperture"] == {"shape": "square", "half_width": 3.0}
        assert "doe" not in s1 and s1["thickness"] == 0.5 and blank["thickness"] == 1.5
        assert blank["doe"] == {"distance": 0.0, "aperture": "square", "phase": None} and blank["aperture"] is None
    if case == "two_on_a_curved_face":
        s3, p0, p5, plain = back["surfaces"][3:]
        assert s3["thickness"] == 0.0 and p0["thickness"] == 5.0 and p5["thickness"] == 17.5
        assert plain == {"type": "standard", "radius": "inf", "conic": 0.0, "thickness": 17.5, "material": "air",
                         "aperture": None, "stop": False}
        assert p0["doe"]["phase_model"] == spec["surfaces"][3]["doe"][1]["phase_model"]
        assert p5["doe"]["phase_model"] == spec["surfaces"][3]["doe"][0]["phase_model"]
    if case == "conformal":
        assert back["surfaces"][:3] == spec["surfaces"][:3]
        assert back["surfaces"][3] == dict(spec["surfaces"][3], thickness=20.0)
        assert back["surfaces"][4]["thickness"] == 20.0 and "doe" not in back["surfaces"][4]
    assert "doe" not in back  # never read as the DOE before the sensor


def test_conformal_doe_on_a_plane_comes_back_0_mm_after_it(tmp_path):
    """A .zmx plane diffractive surface inside the lens is read as a DOE 0 mm after the plane: a conformal DOE on a
    plane comes back so (the same ray bending: both add the phase's gradient to n·d's tangential part)."""
    spec = _doublet(tmp_path)
    grid = {"aperture": "circle", "size": [10.0, 10.0]}  # the plane's CLAP 0 5
    spec["surfaces"][1]["doe"] = {"conformal": True, "phase": None, "phase_model": B2} | grid
    back = _write_read(tmp_path, spec)
    assert back["surfaces"][1]["doe"] == {"distance": 0.0, "phase": None, "phase_model": B2} | grid
    _assert_same_rays(spec, back)


# ------------------------------------------------------------------------------------------ rays, independently
def _analytic_phase(model):
    """The phase (rad) and gradient (rad/mm) of a phase model, written out here: BINARY_2 (OpticStudio)
    φ = M Σ A_i (r/R)^(2i); a grating 2π (x cos θ + y sin θ) / period; blank 0."""
    if model is None:
        return lambda x, y, wl: (0 * x, 0 * x, 0 * x)
    if model["type"] == "grating":
        t = math.radians(model["angle"])
        kx, ky = 2 * math.pi * math.cos(t) / model["period"], 2 * math.pi * math.sin(t) / model["period"]
        return lambda x, y, wl: (kx * x + ky * y, kx + 0 * x, ky + 0 * x)
    m, r, a = model["order"], model["norm_radius"], model["coefficients"]

    def phase(x, y, wl):
        u = (x * x + y * y) / r ** 2
        phi = sum(m * c * u ** (i + 1) for i, c in enumerate(a))
        g = sum(m * c * (i + 1) * u ** i for i, c in enumerate(a)) * 2 / r ** 2  # dφ/du · du/d(r²) · 2
        return phi, g * x, g * y
    return phase


def _rays(lens):
    """A fan of collimated rays at 0°, 1.5° and −2.5° (in y) and 1° in x over a 3.6 mm disc, at three
    wavelengths."""
    g = torch.linspace(-1.8, 1.8, 9, dtype=torch.float64)
    x, y = torch.meshgrid(g, g, indexing="xy")
    keep = x * x + y * y <= 1.8 ** 2
    pts = torch.stack([x[keep], y[keep], torch.full_like(x[keep], -1.0)], -1)
    dirs = [(0.0, 0.0), (0.0, 1.5), (0.0, -2.5), (1.0, 0.0)]
    o, d, w = [], [], []
    for ax, ay in dirs:
        for wl in (0.48, WL, 0.65):
            o.append(pts)
            d.append(torch.tensor([math.tan(math.radians(ax)), math.tan(math.radians(ay)), 1.0],
                                  dtype=torch.float64).expand_as(pts))
            w.append(torch.full((len(pts),), wl, dtype=torch.float64))
    return RayBundle.create(torch.cat(o), torch.cat(d), torch.cat(w))


def _traced(spec, engine: bool):
    """Rays through ``spec``'s lens at the image plane, its surface DOEs as analytic phase surfaces (or, with
    ``engine``, as the engine's pixel-map phase surfaces of its DOEs, 2 µm pixels)."""
    lens, does, afters, distances = does_lens(spec, doe_pitch=0.002)
    if engine:
        traced = lens_with_doe(lens, does, afters, distances)
    else:
        models = [d.get("phase_model") for s in spec["surfaces"] for d in
                  (s["doe"] if isinstance(s.get("doe"), list) else [s["doe"]] if s.get("doe") else [])]
        traced = lens
        # insert from the back (and the farther of a surface's DOEs first): the indices in front stay valid
        order = sorted(range(len(afters)), key=lambda k: (afters[k], -1 if distances[k] is None else distances[k]),
                       reverse=True)
        for k in order:
            traced = insert_doe(traced, afters[k], distances[k], _analytic_phase(models[k]), 1.0)
    with torch.no_grad():
        out = traced.trace_to_image(_rays(traced))
    return out


def _assert_same_rays(spec, back):
    for engine in (False, True):
        a, b = _traced(spec, engine), _traced(back, engine)
        assert bool(a.valid.all()) and torch.equal(a.valid, b.valid)
        assert float((a.o - b.o).abs().max()) < 1e-12
        assert float((a.d - b.d).abs().max()) < 1e-12
        assert float((a.opl - b.opl).abs().max()) < 1e-12


@pytest.mark.parametrize("case", CASES)
def test_read_back_lens_traces_the_same_rays(tmp_path, case):
    """Real rays (4 directions, 3 wavelengths, a 3.6 mm disc) through the original spec's lens and the read-back
    one, with the DOEs as analytic phase surfaces and as the engine's pixel-map phase surfaces: the same points,
    directions and optical paths at the image within 1e-12; and the DOEs matter (without them the rays differ by
    more than 0.01 mm)."""
    spec = _cases(tmp_path)[case]
    back = _write_read(tmp_path, spec)
    _assert_same_rays(spec, back)
    lens = does_lens(spec, doe_pitch=0.002)[0]
    with torch.no_grad():
        bare = lens.trace_to_image(_rays(lens))
    assert float((bare.o - _traced(spec, False).o).abs().max()) > 0.01


def test_read_back_lens_gives_the_same_psf(tmp_path):
    """The orders engine (MidSystemLens: both DOEs conformal, the grating's orders) on the original and the read-back
    lens, the sensor at the paraxial focus (32.16 mm after the last vertex) and the engine's plane near it at the same
    place (6 mm after the read-back's plain plane, 22.08 mm after the original's last vertex): the same PSF within
    1e-9 of its peak. (Its default plane, at most half the last gap before the sensor, moves with the plain plane:
    give final_distance to compare.)"""
    from raywave.assembly.midsystem import midsystem_from_spec

    spec = _cases(tmp_path)["conformal"]
    spec["surfaces"][3]["thickness"] = 32.16
    back = _write_read(tmp_path, spec)
    assert back["surfaces"][-1]["thickness"] == 16.08
    psfs = []
    for sp, final in ((spec, 22.08), (back, 6.0)):
        with warnings.catch_warnings():  # the DOE's 4 µm pixels' flat steps (the same in both)
            warnings.filterwarnings("ignore", message=".*pixels' flat steps", category=SamplingWarning)
            ml = midsystem_from_spec(sp, doe_pitch=0.004, sensor_pitch=0.002, final_distance=final, stop_edge="doe")
            with torch.no_grad():
                psfs.append(ml.psf((0.0, 0.0), WL, ks=32))
    peak = float(psfs[0].max())
    assert peak > 20 / 32 ** 2  # a focused spot, not a blur over the crop
    assert float((psfs[0] - psfs[1]).abs().max()) < 1e-9 * peak


def test_written_dgrating_obeys_the_grating_equation(tmp_path):
    """The DGRATING written for a grating of period 0.02 mm at −90° (inside lens 1's glass, n 1.5): the file's own
    PARM 1 (T, lines per µm) and PARM 2 (M) give OpticStudio's n' sinθ' − n sinθ = M T λ along y, which the
    original lens's ray (the analytic grating) obeys within 1e-12."""
    spec = _cases(tmp_path)["in_the_glass_and_blank"]
    text = zmx_text(spec)
    block = text.split("TYPE DGRATING")[1].split("SURF")[0]
    t = float(re.search(r"PARM 1 (\S+)", block).group(1))
    m = float(re.search(r"PARM 2 (\S+)", block).group(1))
    assert (t, m) == (0.05, -1.0)
    lens, _, afters, distances = does_lens(spec, doe_pitch=0.002)
    grating = insert_doe(lens, afters[0], distances[0], _analytic_phase(spec["surfaces"][0]["doe"]["phase_model"]))
    rays = RayBundle.create(torch.tensor([[0.0, 0.7, -1.0]], dtype=torch.float64),
                            torch.tensor([[0.0, 0.02, 1.0]], dtype=torch.float64),
                            torch.tensor([WL], dtype=torch.float64))
    with torch.no_grad():
        before = grating.trace(rays, stop=1)  # in the glass after lens 1's front face
        after = grating.trace(rays, stop=2)  # and after the grating 1.5 mm behind it (still in the glass)
    n = 1.5
    sin_in, sin_out = float(before.d[0, 1]), float(after.d[0, 1])
    assert abs(n * sin_out - n * sin_in - m * t * WL) < 1e-12
    assert abs(float(after.d[0, 0])) < 1e-15  # along y only (cos(−90°) ≈ 6e-17 in the analytic phase)


def test_grating_period_inverts_exactly():
    """PARM 1 = T such that the reader's ``1 / |T · M · 1e3|`` (M = ±1) is the period again: bit for bit for every
    period the reader gives (2000 random DGRATINGs, orders −3..3, read by the reader itself), within an ulp for any
    other (not every float period is 1 / (T · 1e3) of a float T: ~14 % of random ones are not)."""
    import random

    from raywave.io.zmx.diffractive import _grating_phase

    rng = random.Random(46)
    for _ in range(2000):
        t0, m0 = 10 ** rng.uniform(-4, 1), rng.choice([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0])
        model = _grating_phase({"parms": {1: (t0, 1), 2: (m0, 2)}}, "surface 1", "x.zmx", 1.0, 1)
        t = grating_lines_per_um(model["period"])
        assert 1.0 / abs(t * 1e3) == model["period"]
    for period in [0.02, 0.05, 1.0 / 3.0, 7.3e-3, 0.123456789, 2.5e-4, 1.7] + \
            [10 ** rng.uniform(-5, 1) for _ in range(2000)]:
        t = grating_lines_per_um(period)
        assert abs(1.0 / (t * 1e3) - period) <= math.ulp(period)


# ------------------------------------------------------------------------------------------ what is left out
def test_what_a_zmx_cannot_hold_is_named(tmp_path):
    """One LensFileWarning names each DOE left out (with why and where) and each written DOE's keys that are not
    stored; what is written reads back."""
    spec = _doublet(tmp_path)
    spec["surfaces"][0]["doe"] = {"distance": 1.0, "aperture": "square", "size": [4.0, 4.0], "phase": None,
                                  "phase_model": {"type": "zernike", "coefficients": [0.0, 1.0]}}
    spec["surfaces"][1]["doe"] = [
        {"distance": 0.5, "aperture": "circle", "size": [8.0, 8.0], "phase": None, "pitch": 0.002, "levels": 8,
         "design_wavelength": 0.55, "phase_model": B2},
        {"distance": 1.0, "aperture": "square", "size": [8.0, 8.0], "phase": None,
         "phase_model": {"type": "grating", "period": 0.02, "angle": 30.0}},
        {"distance": 0.5, "aperture": "square", "size": [8.0, 8.0], "phase": None,
         "phase_model": {"type": "grating", "period": 0.02}}]
    spec["surfaces"][3]["doe"] = {"distance": 1.0, "aperture": "square", "phase": "map.npy", "pitch": 0.01,
                                  "shape": [100, 100]}
    with pytest.warns(LensFileWarning) as rec:
        write_zmx(spec, tmp_path / "lossy.zmx")
    msgs = [str(r.message) for r in rec if issubclass(r.category, LensFileWarning)]
    assert len(msgs) == 1
    msg = msgs[0]
    assert "surfaces[0].doe (a zernike phase model: only binary_2 (BINARY_2) and grating (DGRATING)" in msg
    assert "surfaces[1].doe[1] (a grating at 30°: a DGRATING's rulings run along its x axis" in msg
    assert "surfaces[1].doe[2] (a grating at 0°" in msg
    assert "surfaces[1].doe[0]'s pitch, design_wavelength, levels" in msg
    assert "surfaces[3].doe (a phase map" in msg
    assert "DOEs inside the lens" not in msg
    back = read_lens_spec(tmp_path / "lossy.zmx")
    does = [(i, s["doe"]) for i, s in enumerate(back["surfaces"]) if s.get("doe")]
    assert len(does) == 1 and does[0][1]["phase_model"] == B2 and back["surfaces"][does[0][0] - 1]["thickness"] == 0.5


@pytest.mark.parametrize("edit, expected", [
    (lambda s: s["surfaces"][1].update(doe=[{"distance": 0.5, "aperture": "square", "phase": None},
                                            {"distance": 0.5, "aperture": "square", "phase": None}]),
     r"surfaces\[1\].doe\[1\] \(at the same place as another DOE of the surface\)"),
    (lambda s: s["surfaces"][2].update(type="even_asphere", aspheric={"a4": 1e-6},
                                       doe={"conformal": True, "aperture": "square", "phase": None,
                                            "phase_model": B2}),
     r"surfaces\[2\].doe \(conformal on a even_asphere surface"),
    (lambda s: s["surfaces"][2].update(semi_diameter=7.0, doe={"conformal": True, "aperture": "circle",
                                                               "size": [10.0, 10.0], "phase": None,
                                                               "phase_model": B2}),
     r"surfaces\[2\].doe's size and aperture \(read back as the surface's: circle, \[14.0, 14.0\] mm\)"),
])
def test_surface_does_a_zmx_cannot_place(tmp_path, edit, expected):
    spec = _doublet(tmp_path)
    edit(spec)
    with pytest.warns(LensFileWarning, match=expected):
        write_zmx(spec, tmp_path / "x.zmx")
    read_lens_spec(tmp_path / "x.zmx")  # what is written reads
