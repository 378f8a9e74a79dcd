"""Materials: catalog values against datasheets, formulas against optiland's independent evaluation,
AGF reading (UTF-8/16), catalog resolution order, errors and warnings, model glasses, dtypes."""

import math
import warnings

import numpy as np
import pytest
import torch

from raywave.materials import (AGFError, Air, Catalog, DispersiveGlass, GlassCatalogWarning, GlassLibrary,
                               GlassNotFoundError, ModelGlass, WavelengthRangeWarning, get_material, list_catalogs, list_glasses, read_agf)
from raywave.materials import formulas

D, F, C = 0.5875618, 0.4861327, 0.6562725
WL = torch.tensor([F, D, C], dtype=torch.float64)


def nd_vd(m):
    n = m.n(WL).detach()
    return float(n[1]), float((n[1] - 1) / (n[0] - n[2]))


@pytest.mark.parametrize("name, nd, vd", [
    ("N-BK7", 1.51680, 64.17), ("N-SF11", 1.78472, 25.68), ("N-SF5", 1.67271, 32.25), ("N-SF6", 1.80518, 25.36),
    ("SF2", 1.64769, 33.85), ("N-LAK9", 1.69100, 54.71), ("N-BAF10", 1.67003, 47.11), ("N-SK16", 1.62041, 60.32),
    ("F2", 1.62004, 36.37), ("H-K9L", 1.51680, 64.20), ("H-ZF52", 1.84666, 23.78), ("fused_silica", 1.45846, 67.8),
    ("PMMA", 1.4906, 53.2),
])
def test_bundled_glasses_match_datasheets(name, nd, vd):
    m = get_material(name)
    got_nd, got_vd = nd_vd(m)
    assert got_nd == pytest.approx(nd, abs=2e-4)
    assert got_vd == pytest.approx(vd, abs=0.3)
    assert m.provenance


def test_nbk7_nsf11_fused_silica_reference_values():
    nd, vd = nd_vd(get_material("N-BK7"))
    assert nd == pytest.approx(1.5168, abs=1e-4) and vd == pytest.approx(64.17, abs=0.1)
    assert nd_vd(get_material("N-SF11"))[0] == pytest.approx(1.78472, abs=1e-4)
    for alias in ["fused_silica", "FUSED SILICA", "SILICA", "F_SILICA", "SiO2"]:
        m = get_material(alias)
        assert m.name == "FUSED_SILICA" and "Malitson" in m.provenance
        assert float(m.n(0.5876)) == pytest.approx(1.458464, abs=5e-6)


def test_e48r_is_the_databases_zeonex_e48r():
    m = get_material("E48R")
    assert "ZeonexE48R" in m.provenance and "CC0" in m.provenance
    nd, vd = nd_vd(m)
    assert nd == pytest.approx(1.5310, abs=1e-3)  # Zeon datasheet nd; this single-term fit gives vd ≈ 51.8 (datasheet 56)
    assert 50 < vd < 57


def test_table_file_has_provenance_fields():
    import json

    from raywave.materials.catalog import TABLE_PATH

    data = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
    for g in data["glasses"]:
        assert g["provenance"]
        if g["family"] != "constant":
            assert g["source"].startswith("refractiveindex.info database: data/") and g["license"] == "CC0 1.0"


def test_every_bundled_glass_has_provenance_and_resolves():
    names = list_glasses("MISC")
    for required in ["N-BK7", "N-SF11", "N-SF5", "N-SF6", "SF2", "N-LAK9", "N-BAF10", "N-SK16", "F2", "H-K9L",
                     "H-K51", "H-ZF52", "FUSED_SILICA", "PMMA", "POLYCARB", "E48R", "AIR"]:
        assert required in names
    assert get_material("air").n(0.55) == 1.0
    for spec in [None, "", "AIR", "Air"]:
        assert isinstance(get_material(spec), Air)
    table_air = get_material({"name": "AIR", "catalog": "MISC"})
    assert table_air.is_air and table_air.to_spec() == "air"
    assert get_material("polycarbonate").name == "POLYCARB"


def test_database_shelves_main_organic_other():
    cats = list_catalogs()
    assert cats[:7] == ["MISC", "SCHOTT", "OHARA", "CDGM", "HOYA", "HIKARI", "SUMITA"]
    assert cats[-3:] == ["MAIN", "ORGANIC", "OTHER"]
    assert "CaF2" in list_glasses("MAIN")
    caf2 = get_material("CaF2", ["MAIN"])
    assert caf2.catalog == "MAIN" and float(caf2.n(0.5876)) == pytest.approx(1.4338, abs=2e-4)
    page = get_material("SiO2/Malitson")
    assert page.catalog == "MAIN" and float(page.n(0.5876)) == pytest.approx(1.458464, abs=5e-6)
    assert get_material("ZeonexE48R", ["OTHER"]).catalog == "OTHER"
    # A tabulated page: linear interpolation of the table, float32 in -> float32 out.
    gold = get_material("Au", ["MAIN"])
    assert gold.family == "tabulated"
    assert gold.n(torch.tensor([0.6], dtype=torch.float32)).dtype == torch.float32


@pytest.mark.parametrize("name, catalog", [("N-BK7", "SCHOTT"), ("S-BSL7", "OHARA"), ("H-ZLAF52A", "CDGM"),
                                           ("E-FD1", "HOYA"), ("J-BK7A", "HIKARI"), ("K-BK7", "SUMITA")])
def test_vendor_catalog_glasses_against_optiland(name, catalog):
    opt = pytest.importorskip("optiland.materials")
    warnings.filterwarnings("ignore")
    m = get_material({"name": name, "catalog": catalog})
    wl = np.array([0.45, 0.55, 0.65])
    ref = np.asarray(opt.Material(name, reference=catalog).n(wl), dtype=float)
    np.testing.assert_allclose(m.n(torch.tensor(wl)).numpy(), ref, atol=1e-9)


# ---------------------------------------------------------------- every formula against a direct numpy form
def _np_agf(k, w, a):
    l2 = w**2
    sell = lambda m: 1 + sum(a[2 * i] * l2 / (l2 - a[2 * i + 1]) for i in range(m))  # noqa: E731
    if k == 1:
        return np.sqrt(a[0] + a[1] * l2 + a[2] / l2 + a[3] / l2**2 + a[4] / l2**3 + a[5] / l2**4)
    if k == 2:
        return np.sqrt(sell(3))
    if k == 3:
        L = 1 / (l2 - 0.028)
        return a[0] + a[1] * L + a[2] * L**2 + a[3] * l2 + a[4] * l2**2 + a[5] * l2**3
    if k == 4:
        return np.sqrt(1 + a[0] + a[1] * l2 / (l2 - a[2]**2) + a[3] / (l2 - a[4]**2))
    if k == 5:
        return a[0] + a[1] / w + a[2] / w**3.5
    if k == 6:
        return np.sqrt(sell(4))
    if k == 7:
        return np.sqrt(a[0] + a[1] / (l2 - a[2]) - a[3] * l2)
    if k == 8:
        return np.sqrt(a[0] + a[1] * l2 / (l2 - a[2]) - a[3] * l2)
    if k == 9:
        return np.sqrt(a[0] + a[1] * l2 / (l2 - a[2]) + a[3] * l2 / (l2 - a[4]))
    if k == 10:
        return np.sqrt(a[0] + a[1] * l2 + sum(a[i] * w**(-2 * (i - 1)) for i in range(2, 8)))
    if k == 11:
        return np.sqrt(sell(5))
    if k == 12:
        return np.sqrt(a[0] + a[1] * l2 + a[2] / l2 + a[3] / l2**2 + a[4] / l2**3 + a[5] / l2**4
                       + a[6] * l2**2 + a[7] * l2**3)
    if k == 13:
        return np.sqrt(a[0] + a[1] * l2 + a[2] * l2**2 + sum(a[i] * w**(-2 * (i - 2)) for i in range(3, 9)))
    raise AssertionError(k)


SELL = [1.03961212, 0.00600069867, 0.231792344, 0.0200179144, 1.01046945, 103.560653]
AGF_COEFFS = {
    1: [2.2718929, -1.0108077e-2, 1.0592509e-2, 2.0816965e-4, -7.6472538e-6, 4.9240991e-7],
    2: SELL,
    3: [1.5, 0.005, 1e-4, -1e-3, 1e-5, -1e-7],
    4: [0.1, 1.1, 0.1, 0.002, 0.12],
    5: [1.5, 0.01, 1e-4],
    6: SELL + [0.01, 0.05],
    7: [2.3, 0.01, 0.02, 0.01],
    8: [1.3, 1.0, 0.01, 0.01],
    9: [1.2, 1.0, 0.01, 0.2, 100.0],
    10: [2.27, -0.01, 0.01, 2e-4, -7e-6, 5e-7, 1e-8, -1e-9],
    11: SELL + [0.01, 0.05, 0.001, 0.07],
    12: [2.27, -0.01, 0.01, 2e-4, -7e-6, 5e-7, 1e-4, -1e-5],
    13: [2.27, -0.01, 1e-4, 0.01, 2e-4, -7e-6, 5e-7, 1e-8, -1e-9],
}


def _np_rii(k, w, c):
    l2 = w**2
    pairs = lambda start: [(c[i], c[i + 1]) for i in range(start, len(c) - 1, 2)]  # noqa: E731
    if k == 1:
        return np.sqrt(1 + c[0] + sum(b * l2 / (l2 - d**2) for b, d in pairs(1)))
    if k == 2:
        return np.sqrt(1 + c[0] + sum(b * l2 / (l2 - d) for b, d in pairs(1)))
    if k == 3:
        return np.sqrt(c[0] + sum(b * w**e for b, e in pairs(1)))
    if k == 4:
        n2 = c[0] + c[1] * w**c[2] / (l2 - c[3]**c[4]) + c[5] * w**c[6] / (l2 - c[7]**c[8])
        return np.sqrt(n2 + sum(b * w**e for b, e in pairs(9)))
    if k == 5:
        return c[0] + sum(b * w**e for b, e in pairs(1))
    if k == 6:
        return 1 + c[0] + sum(b / (d - w**-2) for b, d in pairs(1))
    if k == 7:
        return c[0] + c[1] / (l2 - 0.028) + c[2] / (l2 - 0.028)**2 + c[3] * l2 + c[4] * l2**2 + c[5] * l2**3
    if k == 8:
        a = c[0] + c[1] * l2 / (l2 - c[2]) + c[3] * l2
        return np.sqrt((1 + 2 * a) / (1 - a))
    if k == 9:
        return np.sqrt(c[0] + c[1] / (l2 - c[2]) + c[3] * (w - c[4]) / ((w - c[4])**2 + c[5]))
    raise AssertionError(k)


RII_COEFFS = {
    1: [0.0, 0.6961663, 0.0684043, 0.4079426, 0.1162414, 0.8974794, 9.896161],   # fused silica, Malitson
    2: [0.0] + SELL,                                                             # N-BK7
    3: [2.28, -0.01, 2, 0.011, -2, 1e-4, -4],
    4: [2.3, 0.01, 2, 0.2, 2, 0.1, 2, 0.05, 2, -0.005, 2, 1e-4, -4],
    5: [1.5, 0.004, -2, 1e-4, -4],
    6: [0.0, 0.05792105, 238.0185, 0.00167917, 57.362],                          # air, Ciddor
    7: [1.4, 0.005, 1e-4, -1e-3, 1e-5, -1e-7],
    8: [0.25, 0.05, 0.01, -0.002],
    9: [2.3, 0.01, 0.02, 0.001, 3.0, 0.1],
}


@pytest.mark.parametrize("k", sorted(formulas.AGF_FORMULAS))
def test_each_agf_formula_matches_numpy(k):
    assert len(formulas.AGF_FORMULAS) == 13
    w = np.linspace(0.4, 1.0, 13)
    got = formulas.AGF_FORMULAS[k](torch.tensor(w), torch.tensor(AGF_COEFFS[k], dtype=torch.float64)).numpy()
    ref = _np_agf(k, w, AGF_COEFFS[k])
    assert np.isfinite(ref).all() and (ref > 1).all()
    np.testing.assert_allclose(got, ref, rtol=1e-13)


@pytest.mark.parametrize("k", sorted(formulas.RII_FORMULAS))
def test_each_rii_formula_matches_numpy(k):
    assert len(formulas.RII_FORMULAS) == 9
    w = np.linspace(0.4, 1.0, 13)
    got = formulas.RII_FORMULAS[k](torch.tensor(w), torch.tensor(RII_COEFFS[k], dtype=torch.float64)).numpy()
    ref = _np_rii(k, w, RII_COEFFS[k])
    assert np.isfinite(ref).all() and (ref >= 1).all()
    np.testing.assert_allclose(got, ref, rtol=1e-13)


def test_tabulated_matches_numpy_interp_and_is_differentiable():
    table = torch.tensor([[0.4, 1.53], [0.5, 1.52], [0.7, 1.512], [1.0, 1.507]], dtype=torch.float64)
    w = np.linspace(0.3, 1.1, 17)
    got = formulas.tabulated(torch.tensor(w), table).numpy()
    np.testing.assert_allclose(got, np.interp(w, table[:, 0].numpy(), table[:, 1].numpy()), rtol=1e-14)
    wl = torch.tensor([0.45, 0.61, 0.83], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda x: formulas.tabulated(x, table), (wl,))
    assert formulas.tabulated(torch.tensor([0.55], dtype=torch.float32), table.float()).dtype == torch.float32
    glass = DispersiveGlass("T", "tabulated", 0, table.tolist(), (0.4, 1.0))
    assert float(glass.n(0.6)) == pytest.approx(1.516)


def _numpy_sellmeier1(wl, K, L):
    l2 = wl**2
    return np.sqrt(1 + sum(k * l2 / (l2 - l) for k, l in zip(K, L)))


def test_agf_formulas_against_textbook_forms():
    wl = torch.linspace(0.4, 1.0, 7, dtype=torch.float64)
    w = wl.numpy()
    K, L = [1.03961212, 0.231792344, 1.01046945], [0.00600069867, 0.0200179144, 103.560653]
    c = torch.tensor([K[0], L[0], K[1], L[1], K[2], L[2]], dtype=torch.float64)
    np.testing.assert_allclose(formulas.sellmeier1(wl, c).numpy(), _numpy_sellmeier1(w, K, L), rtol=1e-14)
    # Schott formula for an old SCHOTT BK7 catalog entry
    a = [2.2718929, -1.0108077e-2, 1.0592509e-2, 2.0816965e-4, -7.6472538e-6, 4.9240991e-7]
    ref = np.sqrt(a[0] + a[1] * w**2 + a[2] * w**-2 + a[3] * w**-4 + a[4] * w**-6 + a[5] * w**-8)
    np.testing.assert_allclose(formulas.schott(wl, torch.tensor(a, dtype=torch.float64)).numpy(), ref, rtol=1e-14)
    assert float(formulas.schott(torch.tensor(D, dtype=torch.float64), torch.tensor(a, dtype=torch.float64))) == pytest.approx(1.5168, abs=2e-4)
    # Conrady, Herzberger: direct forms
    cc = torch.tensor([1.5, 0.01, 1e-4], dtype=torch.float64)
    np.testing.assert_allclose(formulas.conrady(wl, cc).numpy(), 1.5 + 0.01 / w + 1e-4 / w**3.5, rtol=1e-14)
    h = [1.5, 0.005, 1e-4, -1e-3, 1e-5, -1e-7]
    Lh = 1 / (w**2 - 0.028)
    np.testing.assert_allclose(formulas.herzberger(wl, torch.tensor(h, dtype=torch.float64)).numpy(),
                               h[0] + h[1] * Lh + h[2] * Lh**2 + h[3] * w**2 + h[4] * w**4 + h[5] * w**6, rtol=1e-14)
    # Every AGF formula gives finite, smooth values for a plausible coefficient set
    for k, fn in formulas.AGF_FORMULAS.items():
        out = fn(wl, torch.tensor([1.5, 0.01, 0.01, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9], dtype=torch.float64))
        assert torch.isfinite(out).all(), k


def test_dispersion_is_differentiable_and_normal():
    m = get_material("N-SF11")
    wl = torch.tensor([0.45, 0.55, 0.65], dtype=torch.float64, requires_grad=True)
    n = m.n(wl)
    (g,) = torch.autograd.grad(n.sum(), wl)
    assert (g < 0).all()  # normal dispersion in the visible
    c = m.coefficients.clone().requires_grad_(True)
    torch.autograd.gradcheck(lambda w, c: formulas.rii_sellmeier2(w, c), (wl, c))


AGF_TEXT = """CC Test catalog
NM MYBK7 2 517642 1.5168 64.17 0 0 0
GC comment
ED 7.1 -0.3 2.51 0.0009 0
CD 1.03961212 0.00600069867 0.231792344 0.0200179144 1.01046945 103.560653 0 0 0 0
TD 0 0 0 0 0 0 20
OD 1 1 1 1 1 1
LD 0.3 2.5
IT 0.3 0.5 25
NM MYF2 2 620364 1.62004 36.37 0 0 0
CD 1.34533359 0.00997743871 0.209073176 0.0470450767 0.937357162 111.886764 0 0 0 0
LD 0.32 2.5
"""


@pytest.mark.parametrize("encoding", ["utf-8", "utf-16"])
def test_agf_reader_utf8_and_utf16(tmp_path, encoding):
    p = tmp_path / "mycat.agf"
    p.write_bytes(AGF_TEXT.encode(encoding))
    cat = read_agf(p)
    assert cat.name == "MYCAT" and set(cat.names()) == {"MYBK7", "MYF2"}
    lib = GlassLibrary()
    lib.add_catalog(cat)
    mine = get_material("MYBK7", catalogs=["MYCAT"], library=lib)
    schott = get_material("N-BK7")
    assert torch.allclose(mine.n(WL), schott.n(WL), atol=1e-12)
    assert mine.wavelength_range == (0.3, 2.5)
    # against the published N-BK7 Sellmeier coefficients, evaluated directly
    w = np.array([F, D, C, 1.014])
    K, L = [1.03961212, 0.231792344, 1.01046945], [0.00600069867, 0.0200179144, 103.560653]
    np.testing.assert_allclose(cat["MYBK7"].n(torch.tensor(w)).numpy(), _numpy_sellmeier1(w, K, L), rtol=1e-14)
    assert float(mine.n(D)) == pytest.approx(1.5168, abs=1e-4)
    # Catalog is a read-only mapping name -> DispersiveGlass (case-insensitive)
    assert isinstance(cat, Catalog) and len(cat) == 2 and "mybk7" in cat and list(cat) == ["MYBK7", "MYF2"]
    assert isinstance(cat["myf2"], DispersiveGlass) and cat["MYF2"].formula == 2
    with pytest.raises(KeyError):
        cat["NOPE"]


def test_agf_utf16_without_bom_and_latin1(tmp_path):
    p = tmp_path / "nobom.agf"
    p.write_bytes(AGF_TEXT.encode("utf-16-le"))
    assert set(read_agf(p).names()) == {"MYBK7", "MYF2"}
    p = tmp_path / "latin.agf"
    p.write_bytes(("CC Glas für Tests \xb5m\n" + AGF_TEXT).encode("latin-1"))
    assert read_agf(p, name="Lat").name == "Lat"


def test_malformed_agf_names_file_and_line(tmp_path):
    p = tmp_path / "bad.agf"
    p.write_text("NM GOOD 2 0 1.5 60\nCD 1 0.01 0 0 0 0\nNM BAD 99 0 1.5 60\nCD 1\n")
    with pytest.raises(AGFError, match=r"bad.agf:3:.*formula"):
        read_agf(p)
    p.write_text("NM NOCD 2 0 1.5 60\nLD 0.4 0.7\n")
    with pytest.raises(AGFError, match=r"bad.agf:1:.*NOCD"):
        read_agf(p)
    p.write_text("NM G 2 0 1.5 60\nCD 1 0.01 x 0 0 0\n")
    with pytest.raises(AGFError, match=r"bad.agf:2:"):
        read_agf(p)
    assert issubclass(AGFError, ValueError)


def test_default_library_is_read_only():
    from raywave.materials import DEFAULT_LIBRARY

    with pytest.raises(RuntimeError, match="read-only"):
        DEFAULT_LIBRARY.add_catalog("x.agf")


def test_catalog_order_resolves_first_listed(tmp_path):
    lib = GlassLibrary()
    a, b = tmp_path / "first.agf", tmp_path / "second.agf"
    a.write_text("NM SAMEGLASS 5 0 1.5 60\nCD 1.5 0 0\n")
    b.write_text("NM SAMEGLASS 5 0 1.7 30\nCD 1.7 0 0\n")
    lib.add_catalog(a)
    lib.register_catalog(b)
    assert float(get_material("SAMEGLASS", ["FIRST", "SECOND"], lib).n(0.55)) == 1.5
    assert float(get_material("SAMEGLASS", ["SECOND", "FIRST"], lib).n(0.55)) == 1.7
    # A vendor glass present in two vendor catalogs: the listed catalog wins.
    assert get_material("N-BK7", ["SCHOTT"]).catalog == "SCHOTT"
    with pytest.raises(GlassNotFoundError, match="N-BK7.*OHARA"):
        get_material("N-BK7", ["OHARA"])


def test_unknown_glass_suggests_close_names():
    with pytest.raises(GlassNotFoundError) as err:
        get_material("N-BK77")
    assert "N-BK77" in str(err.value) and "N-BK7" in str(err.value) and "did you mean" in str(err.value)


def test_catalog_not_bundled_searches_the_rest_and_warns():
    """A GCAT catalog raywave does not bundle is skipped; a glass in none of the named catalogs it has is looked
    up everywhere else (with a warning naming the catalog used); a glass found nowhere is an error."""
    assert get_material("SF5", ["INFRARED", "SCHOTT"]).catalog == "SCHOTT"  # in a named catalog: no fallback
    with pytest.warns(GlassCatalogWarning, match="INFRARED is not bundled.*SF5 from SCHOTT"):
        assert get_material("SF5", ["INFRARED"]).catalog == "SCHOTT"
    with pytest.warns(GlassCatalogWarning, match="not in the named catalog.*OHARA"):
        get_material("N-BK7", ["NOSUCHVENDOR", "OHARA"])
    with pytest.raises(GlassNotFoundError, match="NOT-A-GLASS"):
        get_material("NOT-A-GLASS", ["INFRARED"])
    with pytest.raises(GlassNotFoundError, match="N-BK7.*OHARA"):  # every named catalog present: not searched on
        get_material("N-BK7", ["OHARA"])


def test_wavelength_out_of_range_warns():
    m = get_material("N-BK7")
    with pytest.warns(WavelengthRangeWarning, match=r"N-BK7.*0.25.*0.3"):
        m.n(torch.tensor([0.25, 0.5], dtype=torch.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m.n(torch.tensor([0.4, 0.7], dtype=torch.float64))


def test_model_glass_exact_and_differentiable():
    m = ModelGlass(1.6, 40.0)
    nd, vd = nd_vd(m)
    assert nd == pytest.approx(1.6, abs=1e-15) and vd == pytest.approx(40.0, rel=1e-12)
    m.n(torch.tensor(0.5, dtype=torch.float64)).backward()
    assert m.nd.grad is not None and m.vd.grad is not None
    assert get_material({"model": {"nd": 1.6, "vd": 40.0}}).to_spec() == {"model": {"nd": 1.6, "vd": 40.0}}


def test_dtype_follows_wavelength_and_module_protocol():
    m = get_material("N-BK7")
    assert m.n(0.55).dtype == torch.float64
    assert m.n(torch.tensor([0.55], dtype=torch.float32)).dtype == torch.float32
    sd = m.state_dict()
    assert "coefficients" in sd and sd["coefficients"].dtype == torch.float64
    m2 = get_material("N-BK7")
    m2.load_state_dict(sd)
    assert m.to("cpu") is m
    assert ModelGlass(1.5, 50).n(torch.tensor([0.55], dtype=torch.float32)).dtype == torch.float32
    m32 = get_material("N-BK7").to(torch.float32)
    assert m32.coefficients.dtype == torch.float32 and m32.n(torch.tensor([0.55])).dtype == torch.float32
    mg = ModelGlass(1.6, 40.0)
    mg2 = ModelGlass(1.5, 50.0)
    mg2.load_state_dict(mg.state_dict())
    assert float(mg2.nd.detach()) == 1.6 and float(mg2.vd.detach()) == 40.0
    assert get_material({"name": "N-BK7", "catalog": "SCHOTT"}).to_spec() == {"name": "N-BK7", "catalog": "SCHOTT"}
    assert get_material("N-BK7").to_spec() == "N-BK7"


def test_bad_material_spec():
    with pytest.raises(ValueError, match="not a glass name"):
        get_material({"nd": 1.5})
    with pytest.raises(ValueError, match="nd must be > 1"):
        get_material({"model": {"nd": 0.9, "vd": 40}})
    assert math.isclose(float(get_material({"index": 1.7}).n(0.5)), 1.7)
