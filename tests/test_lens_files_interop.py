"""Toroidal and odd-asphere surfaces (sag and normal against Optiland's geometries, intersection gradients against
finite differences), system aperture types (conversion to the EPD, JSON and .zmx round trips), and the errors
for what raywave does not model (other surface types, malformed coordinate breaks, a mirror on an ideal lens)."""

import math
import warnings

import numpy as np
import pytest
import torch

from raywave.io import LensFileError, canonical_spec, read_lens_spec, validate_spec, write_lens_spec
from raywave.io.zmx import read_zmx, write_zmx
from raywave.lens.build import lens_from_spec, lens_to_spec
from raywave.surfaces.geometry import OddAsphere, Toroidal

optiland = pytest.importorskip("optiland")
from optiland.coordinate_system import CoordinateSystem  # noqa: E402
from optiland.geometries import OddAsphere as OlOddAsphere  # noqa: E402
from optiland.geometries import ToroidalGeometry  # noqa: E402

T = dict(dtype=torch.float64)


def _grid(r, n=9):
    v = np.linspace(-r, r, n)
    x, y = np.meshgrid(v, v)
    return x.ravel(), y.ravel()


@pytest.mark.parametrize("rot", [60.0, -45.0, math.inf])
def test_toroidal_sag_and_normal_match_optiland(rot):
    c, k, a = 1 / 40.0, -0.6, [1e-4, -2e-6, 1e-9]
    ours = Toroidal(c, k, 0.0 if math.isinf(rot) else 1 / rot, a)
    theirs = ToroidalGeometry(CoordinateSystem(), radius_x=rot, radius_y=40.0, conic=k, coeffs_poly_y=a)
    x, y = _grid(8.0)
    with torch.no_grad():
        tx, ty = torch.tensor(x, **T), torch.tensor(y, **T)
        z = ours.sag(tx, ty)
        n = ours.normal(tx, ty, z)
    np.testing.assert_allclose(z.numpy(), np.asarray(theirs.sag(x, y)), rtol=0, atol=1e-14)
    nx, ny, nz = theirs._surface_normal(x, y)  # Optiland's normal points toward -z
    np.testing.assert_allclose(np.stack([t.numpy() for t in n]), -np.stack([nx, ny, nz]), rtol=0, atol=1e-14)
    assert not ours.rotationally_symmetric
    assert float(ours.paraxial_curvature().detach()) == pytest.approx(c + 2 * a[0], rel=1e-15)


def test_odd_asphere_sag_and_normal_match_optiland():
    coeffs = [1e-3, 2e-3, -4e-4, 3e-5, -1e-6, 0.0, 2e-9, 0.0]
    ours = OddAsphere(1 / 12.0, -1.3, coeffs)
    theirs = OlOddAsphere(CoordinateSystem(), radius=12.0, conic=-1.3, coefficients=coeffs)
    x, y = _grid(4.0, 8)  # even count: no sample on the cone point
    with torch.no_grad():
        tx, ty = torch.tensor(x, **T), torch.tensor(y, **T)
        z = ours.sag(tx, ty)
        n = ours.normal(tx, ty, z)
    np.testing.assert_allclose(z.numpy(), np.asarray(theirs.sag(x, y)), rtol=0, atol=1e-14)
    nx, ny, nz = theirs._surface_normal(x, y)
    np.testing.assert_allclose(np.stack([t.numpy() for t in n]), -np.stack([nx, ny, nz]), rtol=0, atol=1e-13)
    assert float(ours.paraxial_curvature().detach()) == pytest.approx(1 / 12.0 + 2 * 2e-3, rel=1e-15)
    with torch.no_grad():  # the cone point: finite, normal along the axis
        g = ours.normal(torch.zeros(1, **T), torch.zeros(1, **T), torch.zeros(1, **T))
    assert [float(v) for v in g] == [0.0, 0.0, 1.0]


@pytest.mark.parametrize("geom", [Toroidal(1 / 40.0, -0.6, 1 / 60.0, [1e-4, -2e-6]),
                                  OddAsphere(1 / 12.0, -1.3, [0.0, 2e-3, -4e-4, 3e-5])])
def test_intersection_is_exact_and_differentiable(geom):
    """The Newton intersection lands on the surface, and the gradient of the hit point with respect to the ray and
    the surface parameters (one differentiable Newton step) equals finite differences."""
    o = torch.tensor([[0.7, -1.1, -3.0], [1.5, 0.4, -2.0]], **T)
    d = torch.tensor([[0.05, 0.08, 1.0], [-0.1, 0.02, 1.0]], **T)
    d = d / d.norm(dim=-1, keepdim=True)

    def hit(o, d):
        t, ok = geom.intersect(*o.unbind(-1), *d.unbind(-1))
        assert bool(ok.all())
        return o + t[:, None] * d

    p = hit(o, d)
    with torch.no_grad():
        assert float((p[:, 2] - geom.sag(p[:, 0], p[:, 1])).abs().max()) < 1e-12
    o.requires_grad_(True)
    params = [geom.curvature, geom.coefficients]
    out = hit(o, d)[:, 2].sum()
    grads = torch.autograd.grad(out, [o] + params)
    h = 1e-7
    with torch.no_grad():
        for j in range(2):  # d/d(origin x, y)
            e = torch.zeros_like(o)
            e[:, j] = h
            fd = (hit(o + e, d)[:, 2].sum() - hit(o - e, d)[:, 2].sum()) / (2 * h)
            assert float(grads[0][:, j].sum()) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
        for prm, g in zip(params, grads[1:]):
            flat = prm.view(-1)
            for i in range(flat.numel()):
                old = float(flat[i])
                flat[i] = old + h
                up = hit(o, d)[:, 2].sum()
                flat[i] = old - h
                dn = hit(o, d)[:, 2].sum()
                flat[i] = old
                assert float(g.view(-1)[i]) == pytest.approx(float((up - dn) / (2 * h)), rel=1e-5, abs=1e-7)


def _spec(surfaces, ap, distance="inf"):
    return {"format": "raywave-lens", "version": 1, "units": {"length": "mm", "wavelength": "um"}, "object": {"distance": distance}, "system_aperture": ap,
            "fields": {"type": "angle", "values": [0.0, 3.0]},
            "wavelengths": {"values": [0.5875618], "primary": 0}, "surfaces": surfaces}


TORIC = [{"type": "toroidal", "radius": 40.0, "conic": -0.5, "radius_of_rotation": 60.0,
          "aspheric": {"a2": 0.0, "a4": -2e-6, "a6": 1e-9}, "thickness": 4.0, "material": "N-BK7", "stop": True},
         {"type": "odd_asphere", "radius": -120.0, "aspheric": {"a1": 0.0, "a2": 0.0, "a3": 1e-5, "a4": -3e-7},
          "thickness": 55.0},
         {"type": "toroidal", "radius": "inf", "radius_of_rotation": "inf", "thickness": 1.0, "material": "N-BK7"},
         {"type": "standard", "radius": "inf", "thickness": 1.5}]
APERTURES = [{"epd": 7.5}, {"f_number": 8.0}, {"working_f_number": 7.0}, {"object_na": 0.004},
             {"object_cone_angle": 0.25}, {"float_by_stop_size": True}]


@pytest.mark.parametrize("ap", APERTURES, ids=lambda a: next(iter(a)))
def test_system_aperture_round_trips(tmp_path, ap):
    """JSON: write -> read gives the same spec and the same lens; .zmx: the canonical spec (float-by-stop-size is
    the absence of a system aperture there); the stop is sized to the EPD the aperture type defines."""
    finite = "object_na" in ap or "object_cone_angle" in ap
    surfaces = [dict(s) for s in TORIC]
    if "float_by_stop_size" in ap:
        surfaces[0]["aperture"] = {"shape": "circle", "radius": 3.2}
    spec = validate_spec(_spec(surfaces, ap, 800.0 if finite else "inf"))
    write_lens_spec(spec, tmp_path / "l.json")
    back = read_lens_spec(tmp_path / "l.json")
    assert back == spec
    lens = lens_from_spec(back)
    assert lens_to_spec(lens).get("system_aperture") == canonical_spec(spec).get("system_aperture")
    again = lens_from_spec(lens_to_spec(lens))
    assert again.paraxial().epd == pytest.approx(lens.paraxial().epd, rel=1e-15)
    write_zmx(spec, tmp_path / "l.zmx")
    assert read_zmx(tmp_path / "l.zmx") == canonical_spec(spec)
    p = lens.paraxial()
    assert p.section == "y-z"
    kind, value = next(iter(ap.items()))
    if kind == "epd":
        assert p.epd == pytest.approx(value, rel=1e-14)
    elif kind == "f_number":
        assert p.fnum == pytest.approx(value, rel=1e-14)
    elif kind == "working_f_number":
        assert p.working_fnum == pytest.approx(value, rel=1e-14)
    elif kind in ("object_na", "object_cone_angle"):
        theta = math.asin(value) if kind == "object_na" else math.radians(value)
        assert p.epd == pytest.approx(2 * (800.0 + p.ep_z) * math.tan(theta), rel=1e-14)
    else:
        assert lens.surfaces[0].aperture.extent == pytest.approx(3.2)


@pytest.mark.parametrize("ap, msg", [
    ({"f_number": 4, "epd": 3}, "exactly one system aperture type"),
    ({"object_na": 0.1}, "needs an object at a finite distance"),
    ({"object_na": 1.2}, "must be < 1"),
    ({"float_by_stop_size": 1}, "must be true"),
    ({"fnumber": 4}, "unknown key 'fnumber' (did you mean 'f_number'?)"),
    ({}, "needs one of"),
])
def test_system_aperture_errors(ap, msg):
    with pytest.raises(LensFileError) as e:
        validate_spec(_spec(TORIC, ap))
    assert msg in str(e.value)


def test_toroidal_spec_errors():
    bad = [dict(TORIC[0], radius_of_rotation=0)] + TORIC[1:]
    with pytest.raises(LensFileError, match=r"radius_of_rotation: 0 is not a radius"):
        validate_spec(_spec(bad, {"epd": 5.0}))
    bad = [dict(TORIC[0], aspheric={"a16": 1.0})] + TORIC[1:]
    with pytest.raises(LensFileError, match=r"aspheric.a16: unknown key"):
        validate_spec(_spec(bad, {"epd": 5.0}))


def _zmx(tmp_path, surf_lines, head=("ENPD 10",)):
    lines = ["VERS 190513 80 123457", "MODE SEQ", "UNIT MM X W X CM MR CPMM", *head, "GCAT SCHOTT",
             "SURF 0", "  TYPE STANDARD", "  CURV 0.0", "  DISZ INFINITY",
             "SURF 1", "  STOP", "  TYPE STANDARD", "  CURV 0.02", "  DISZ 5", "  GLAS N-BK7 0 0 1.5168 64.17",
             "SURF 2", *surf_lines, "  DISZ 90",
             "SURF 3", "  TYPE STANDARD", "  CURV 0.0", "  DISZ 0"]
    p = tmp_path / "x.zmx"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("lines, msg", [
    (["  TYPE COORDBRK", "  PARM 7 0.5"], "surface 2: COORDBRK PARM 7 is not a coordinate-break parameter"),
    (["  TYPE PARAXIAL", "  PARM 1 50", "  GLAS MIRROR"], "surface 2: a PARAXIAL surface cannot be a mirror"),
    (["  TYPE BICONIC"], "surface 2: surface type BICONIC (biconic) is not supported"),
    (["  TYPE TOROIDAL", "  CURV 0.01", "  PARM 13 4"], "surface 2: Zernike sag terms on a TOROIDAL surface"),
    (["  TYPE ODDASPHE", "  PARM 9 1e-3"], "surface 2: ODDASPHE PARM 9 is not an odd-asphere coefficient"),
])
def test_unsupported_zmx_surfaces_name_the_surface(tmp_path, lines, msg):
    with pytest.raises(LensFileError) as e:
        read_zmx(_zmx(tmp_path, lines))
    assert msg in str(e.value)


def test_zmx_toroidal_and_odd_asphere_units(tmp_path):
    """Lens units scale the radius of rotation and the polynomial terms (a_p · s^(1-p))."""
    lines = ["  TYPE TOROIDAL", "  CURV -0.01", "  PARM 1 6.0", "  PARM 2 1e-3", "  PARM 3 2e-5"]
    p = _zmx(tmp_path, lines)
    cm = p.read_text().replace("UNIT MM", "UNIT CM")
    p.write_text(cm)
    s = read_zmx(p)["surfaces"][1]
    assert s["radius_of_rotation"] == pytest.approx(60.0)
    assert s["aspheric"]["a2"] == pytest.approx(1e-4) and s["aspheric"]["a4"] == pytest.approx(2e-8)
    p.write_text(cm.replace("TYPE TOROIDAL", "TYPE ODDASPHE").replace("  PARM 1 6.0\n", ""))
    s = read_zmx(p)["surfaces"][1]
    assert s["type"] == "odd_asphere"
    assert s["aspheric"]["a2"] == pytest.approx(1e-4) and s["aspheric"]["a3"] == pytest.approx(2e-7)


def test_zmx_two_system_apertures_is_an_error(tmp_path):
    with pytest.raises(LensFileError, match="a second system aperture"):
        read_zmx(_zmx(tmp_path, ["  TYPE STANDARD"], head=("ENPD 10", "FNUM 4 0")))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        spec = read_zmx(_zmx(tmp_path, ["  TYPE STANDARD"], head=("FNUM 4 0", "FLOA")))
    assert spec["system_aperture"] == {"f_number": 4.0}
    assert any("f_number" in str(x.message) and "FLOA" in str(x.message) for x in w)


def test_unbundled_catalog_warns_once_per_lens():
    """GCAT naming only a catalog raywave lacks: each glass is looked up everywhere, with one warning per glass and
    lens, however many surfaces use it."""
    from raywave.materials import GlassCatalogWarning

    surfaces = [{"radius": 50.0, "thickness": 4.0, "material": "SF5", "stop": True},
                {"radius": -50.0, "thickness": 1.0},
                {"radius": 50.0, "thickness": 4.0, "material": "SF5"},
                {"radius": -50.0, "thickness": 40.0}]
    spec = dict(_spec(surfaces, {"epd": 10.0}), catalogs=["INFRARED"])
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        lens = lens_from_spec(validate_spec(spec))
    msgs = [str(x.message) for x in w if issubclass(x.category, GlassCatalogWarning)]
    assert msgs == ["glass 'SF5': not in the named catalog(s) (none bundled), and INFRARED is not bundled with "
                    "raywave; using SF5 from SCHOTT"]
    assert lens.surfaces[0].material.catalog == lens.surfaces[2].material.catalog == "SCHOTT"
