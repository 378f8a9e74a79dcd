"""Glass catalogs as OpticStudio ships them (issue 44): obsolete SCHOTT glasses (with the data of an equivalent
glass of the same nd and vd, and a warning saying so), optical adhesives of the MISC catalog (Norland NOA 61),
glass codes (never vd = 0), and unknown glasses named with their file line."""

import json
import warnings

import pytest
import torch

from raywave.materials import (GlassNotFoundError, ModelGlass, ObsoleteGlassWarning, get_material, list_glasses,
                               parse_glass_code)
from raywave.materials.catalog import TABLE_PATH
from raywave.materials.glass import LINE_C, LINE_D, LINE_F


def nd_vd(material) -> tuple[float, float]:
    """nd and vd of a material from its indices at the d, F and C lines (the definition of vd)."""
    wl = torch.tensor([LINE_D, LINE_F, LINE_C], dtype=torch.float64)
    nd, nf, nc = (float(v) for v in material.n(wl).detach())
    return nd, (nd - 1.0) / (nf - nc)


# SCHOTT catalog nd of obsolete glasses (glass codes 517642, 522595, 620603)
@pytest.mark.parametrize("name, nd", [("BK7", 1.51680), ("K5", 1.52249), ("SK16", 1.62041), ("SK4", 1.61272),
                                      ("LAF2", 1.74400), ("SSK4", 1.61765), ("FK5", 1.48749)])
def test_obsolete_schott_glasses_resolve_in_the_schott_catalog_with_a_warning(name, nd):
    with pytest.warns(ObsoleteGlassWarning, match=rf"'{name}' is obsolete in the SCHOTT catalog.*equivalent"):
        glass = get_material(name, catalogs=["SCHOTT"])
    assert glass.catalog == "SCHOTT" and "obsolete SCHOTT" in glass.provenance
    got_nd, _ = nd_vd(glass)
    assert abs(got_nd - nd) < 1e-4
    assert name in list_glasses("SCHOTT")


def test_bk7_matches_the_nd_vd_opticstudio_writes_for_it():
    """OpticStudio writes the catalog glass's nd and vd into a .zmx GLAS line: the OpticsDatabase (MIT) file
    Astronomy/Objectives/Telescope Gauss.zmx has ``GLAS BK7 0 0 1.516800034501 6.41673362375E+1`` (GCAT SCHOTT)."""
    with pytest.warns(ObsoleteGlassWarning):
        nd, vd = nd_vd(get_material("BK7", catalogs=["SCHOTT"]))
    assert abs(nd - 1.516800034501) < 2e-6 and abs(vd - 64.1673362375) < 0.01


def test_every_obsolete_entry_reproduces_its_catalog_nd_vd_and_records_provenance():
    data = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
    assert len(data["obsolete"]) >= 30
    for g in data["obsolete"]:
        assert g["status"] == "obsolete" and g["license"] == "CC0 1.0"
        assert g["source"].startswith("refractiveindex.info database: data/specs/") and g["equivalent"]
        with pytest.warns(ObsoleteGlassWarning):
            nd, vd = nd_vd(get_material({"name": g["name"], "catalog": g["catalog"]}))
        assert abs(nd - g["catalog_nd"]) < 1e-4 and abs(vd - g["catalog_vd"]) < 0.15, g["name"]


def _same_named_glasses():
    """(obsolete SCHOTT name, page) for every obsolete SCHOTT glass that HIKARI or HOYA sell under the same name (the
    old SCHOTT names of their equivalents), in the refractiveindex.info database (CC0): the makers' own data, an
    independent check of the values raywave's table was written with."""
    from raywave.materials.rii import database_root

    root = database_root() / "specs"
    data = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
    return [(g["name"], root / maker / "optical" / f"{g['name']}.yml") for g in data["obsolete"]
            for maker in ("hikari", "hoya") if (root / maker / "optical" / f"{g['name']}.yml").exists()]


def test_obsolete_glass_data_agree_with_the_same_named_glasses_of_other_makers():
    """The table's catalog nd and vd of an obsolete SCHOTT glass (K5, SK16, SK4, LAF2, ...), and the indices raywave
    uses for it (its equivalent's data), against HIKARI's and HOYA's glasses of the same name and glass code: nd to
    5e-5, vd to 0.35 (makers' melts of one glass code differ in vd's decimal), n(λ) over 0.45-0.66 µm to 2e-4."""
    from raywave.materials.glass import DispersiveGlass
    from raywave.materials.rii import read_rii_file

    pairs = _same_named_glasses()
    assert {"K5", "SK16", "SK4", "LAF2"} <= {n for n, _ in pairs} and len(pairs) >= 15
    table = {g["name"]: g for g in json.loads(TABLE_PATH.read_text(encoding="utf-8"))["obsolete"]}
    wl = torch.tensor([0.45, LINE_F, 0.55, LINE_D, 0.62, LINE_C], dtype=torch.float64)
    for name, page in pairs:
        d = read_rii_file(str(page))
        other = DispersiveGlass(name, d["family"], d["formula"], d["coefficients"], d["wavelength_range"])
        nd_o, vd_o = nd_vd(other)
        assert abs(table[name]["catalog_nd"] - nd_o) < 5e-5, (name, page)
        assert abs(table[name]["catalog_vd"] - vd_o) < 0.35, (name, page)
        with pytest.warns(ObsoleteGlassWarning):
            ours = get_material(name, catalogs=["SCHOTT"])
        assert float((ours.n(wl) - other.n(wl)).abs().max()) < 2e-4, (name, page)


def test_a_current_schott_glass_gives_no_obsolete_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", ObsoleteGlassWarning)
        assert get_material("N-BK7", catalogs=["SCHOTT"]).name == "N-BK7"


def test_norland_noa61_adhesive_is_in_misc():
    """Norland NOA 61 (cured): n = 1.56 at the d line (Norland's data sheet; refractiveindex.info's page)."""
    glass = get_material("NOA61", catalogs=["SCHOTT", "OHARA", "MISC"])
    nd, _ = nd_vd(glass)
    assert abs(nd - 1.56) < 1e-3
    assert "NOA-61" in glass.provenance


@pytest.mark.parametrize("code, nd, vd", [("517642", 1.517, 64.2), ("517642.251", 1.517, 64.2),
                                          ("517000.520000", 1.517, 52.0), ("620041.603200", 1.620041, 60.32),
                                          ("'755276'", 1.755, 27.6)])
def test_glass_codes(code, nd, vd):
    assert parse_glass_code(code) == pytest.approx((nd, vd), abs=1e-12)
    m = get_material(code.strip("'"))
    assert isinstance(m, ModelGlass)
    got_nd, got_vd = nd_vd(m)
    assert got_nd == pytest.approx(nd, abs=1e-12) and got_vd == pytest.approx(vd, rel=1e-12)


def test_glass_code_never_gives_vd_zero():
    assert parse_glass_code("N-BK7") is None and parse_glass_code("51764") is None
    with pytest.raises(ValueError, match="vd = 0"):
        parse_glass_code("517000.000000")


def test_unknown_glass_names_the_glass_and_the_file_line(tmp_path):
    from raywave import load_lens

    text = "\n".join(["VERS 190513 80 123457", "MODE SEQ", "UNIT MM X W X CM MR CPMM", "ENPD 10", "GCAT SCHOTT",
                      "WAVM 1 0.5875618 1", "SURF 0", "  DISZ INFINITY", "SURF 1", "  CURV 0.02", "  DISZ 4",
                      "  GLAS NOSUCHGLASS 0 0 1.5 40 0 0 0 0 0 0", "  DIAM 8", "SURF 2", "  STOP", "  CURV -0.01",
                      "  DISZ 45", "  DIAM 8", "SURF 3", "  DISZ 0", ""])
    p = tmp_path / "unknown_glass.zmx"
    p.write_text(text)
    with pytest.raises(GlassNotFoundError, match=r"unknown_glass\.zmx:12: surfaces\[0\]: unknown glass 'NOSUCHGLASS'"):
        load_lens(p)
