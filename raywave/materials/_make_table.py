"""Regenerate raywave/data/glasses/table.json from the refractiveindex.info database (CC0).

    python -m raywave.materials._make_table
"""

from __future__ import annotations

import json

from raywave.materials.catalog import TABLE_PATH
from raywave.materials.rii import database_root, read_rii_file

# (name, catalog, path in the database, aliases)
ENTRIES = [
    ("N-BK7", "SCHOTT", "specs/schott/optical/N-BK7.yml", []),
    ("N-SF11", "SCHOTT", "specs/schott/optical/N-SF11.yml", []),
    ("N-SF5", "SCHOTT", "specs/schott/optical/N-SF5.yml", []),
    ("N-SF6", "SCHOTT", "specs/schott/optical/N-SF6.yml", []),
    ("SF2", "SCHOTT", "specs/schott/optical/SF2.yml", []),
    ("N-LAK9", "SCHOTT", "specs/schott/optical/N-LAK9.yml", []),
    ("N-BAF10", "SCHOTT", "specs/schott/optical/N-BAF10.yml", []),
    ("N-SK16", "SCHOTT", "specs/schott/optical/N-SK16.yml", []),
    ("F2", "SCHOTT", "specs/schott/optical/F2.yml", []),
    ("H-K9L", "CDGM", "specs/cdgm/optical/H-K9L.yml", []),
    ("H-K51", "CDGM", "specs/cdgm/optical/H-K51.yml", []),
    ("H-ZF52", "CDGM", "specs/cdgm/optical/H-ZF52.yml", []),
    ("FUSED_SILICA", "MISC", "main/SiO2/nk/Malitson.yml", ["fused silica", "F_SILICA", "SILICA", "SIO2"]),
    ("PMMA", "MISC", "organic/(C5H8O2)n - poly(methyl methacrylate)/nk/Sultanova.yml", ["ACRYLIC"]),
    ("POLYCARB", "MISC", "organic/(C16H14O3)n - polycarbonate/nk/Sultanova.yml", ["POLYCARBONATE", "PC"]),
]

# Optical adhesives that OpticStudio keeps in its MISC catalog (Norland NOA 61: the database's "other" shelf).
ADHESIVE_ENTRIES = [
    ("NOA61", "MISC", "other/optical adhesives/NOA-61/nk/Norland.yml", ["NOA-61", "NORLAND_NOA61", "NOA_61"]),
]

# Obsolete SCHOTT glasses that OpticStudio's SCHOTT catalog still carries (flagged obsolete there) and old lens files
# name: (name, catalog nd, catalog vd, the data page of an equivalent glass in the CC0 database). The database has
# no page of the obsolete melts themselves; the equivalent is SCHOTT's own lead/arsenic-free successor (N-...) where
# its nd and vd are the obsolete glass's, else another maker's glass of the same nd and vd (the glass code).
# build() checks that the equivalent's nd and vd computed from its data agree with the catalog values to
# OBSOLETE_ND_TOL and OBSOLETE_VD_TOL. Catalog nd / vd: SCHOTT's catalog values of the obsolete glass (the
# six-digit glass code to 5 decimals; BK7's agree with the nd, vd OpticStudio writes into .zmx GLAS lines).
# Checked against an independent source by tests/test_glass_catalogs.py: the 18 (of these) that HIKARI or HOYA sell
# under the same name and glass code (their own data in the CC0 database) agree to 5e-5 in nd, 0.35 in vd, and the
# indices used to 2e-4 over 0.45-0.66 µm; BK7's nd / vd are those OpticStudio writes into the corpus's GLAS lines.
OBSOLETE_SCHOTT = [
    ("BK7", 1.51680, 64.17, "specs/schott/optical/N-BK7.yml"),
    ("K5", 1.52249, 59.48, "specs/schott/optical/N-K5.yml"),
    ("SK16", 1.62041, 60.33, "specs/schott/optical/N-SK16.yml"),
    ("SK4", 1.61272, 58.63, "specs/schott/optical/N-SK4.yml"),
    ("LAF2", 1.74400, 44.72, "specs/ohara/optical/S-LAM2.yml"),
    ("SSK4", 1.61765, 55.14, "specs/sumita/optical/K-SSK4.yml"),
    ("SSK4A", 1.61765, 55.14, "specs/sumita/optical/K-SSK4.yml"),
    ("FK5", 1.48749, 70.41, "specs/schott/optical/N-FK5.yml"),
    ("F1", 1.62588, 35.70, "specs/ohara/optical/PBM1.yml"),
    ("F4", 1.61659, 36.63, "specs/ohara/optical/PBM4.yml"),
    ("BAK1", 1.57250, 57.55, "specs/schott/optical/N-BAK1.yml"),
    ("BAK2", 1.53996, 59.71, "specs/schott/optical/N-BAK2.yml"),
    ("BAK4", 1.56883, 56.13, "specs/cdgm/optical/H-BAK7A.yml"),
    ("BALF4", 1.57956, 53.87, "specs/schott/optical/N-BALF4.yml"),
    ("BALF5", 1.54739, 53.63, "specs/schott/optical/N-BALF5.yml"),
    ("BAF3", 1.58267, 46.47, "specs/hikari/optical/BAF3.yml"),
    ("BASF2", 1.66446, 35.83, "specs/ohara/optical/BAH22.yml"),
    ("BK10", 1.49782, 66.95, "specs/schott/optical/N-BK10.yml"),
    ("FK51", 1.48656, 84.47, "specs/schott/optical/N-FK51.yml"),
    ("LAF3", 1.71700, 47.96, "specs/schott/optical/N-LAF3.yml"),
    ("LAK8", 1.71300, 53.83, "specs/schott/optical/N-LAK8.yml"),
    ("LAK9", 1.69100, 54.71, "specs/schott/optical/N-LAK9.yml"),
    ("LAK21", 1.64050, 60.10, "specs/schott/optical/N-LAK21.yml"),
    ("LASF9", 1.85025, 32.17, "specs/schott/optical/N-LASF9.yml"),
    ("PSK3", 1.55232, 63.46, "specs/schott/optical/N-PSK3.yml"),
    ("SF8", 1.68893, 31.18, "specs/cdgm/optical/ZF10.yml"),
    ("SK2", 1.60738, 56.65, "specs/schott/optical/N-SK2.yml"),
    ("SK5", 1.58913, 61.27, "specs/schott/optical/N-SK5.yml"),
    ("SK14", 1.60311, 60.60, "specs/schott/optical/N-SK14.yml"),
    ("SK15", 1.62296, 58.02, "specs/schott/optical/N-SK15.yml"),
    ("SK18", 1.63854, 55.42, "specs/hoya/optical/BACD18.yml"),
    ("SSK2", 1.62230, 53.17, "specs/ohara/optical/S-BSM22.yml"),
    ("SSKN5", 1.65844, 50.88, "specs/schott/optical/N-SSK5.yml"),
    ("LAKN7", 1.65160, 58.52, "specs/schott/optical/N-LAK7.yml"),
    ("LAKN22", 1.65113, 55.89, "specs/schott/optical/N-LAK22.yml"),
]
#: largest |nd| and |vd| differences between an obsolete glass's catalog values and its equivalent's data
OBSOLETE_ND_TOL, OBSOLETE_VD_TOL = 1e-4, 0.15

# The database holds Zeonex E48R (Zeon cyclo-olefin polymer) itself, under other/commercial polymers.
POLYMER_ENTRIES = [
    ("E48R", "MISC", "other/commercial polymers/ZeonexE48R/nk/Sultanova.yml",
     ["ZEONEX_E48R", "ZEONEXE48R", "E48R-LIKE", "COP"]),
]

AIR_ENTRY = {"name": "AIR", "aliases": [], "catalog": "MISC", "family": "constant", "formula": 0,
             "coefficients": [1.0], "wavelength_range": [0.0, 1.0e6], "source": None, "reference": None,
             "license": None, "provenance": "air: n = 1 by definition (catalog indices are relative to air)"}


def nd_vd(record: dict) -> tuple[float, float]:
    """(nd, vd) computed from a database record's data (d, F, C lines)."""
    from raywave.materials.glass import LINE_C, LINE_D, LINE_F, DispersiveGlass

    g = DispersiveGlass("x", record["family"], record["formula"], record["coefficients"], record["wavelength_range"])
    nd, nf, nc = (float(g.n(w)) for w in (LINE_D, LINE_F, LINE_C))
    return nd, (nd - 1.0) / (nf - nc)


def obsolete_entries(root) -> list:
    """The table's ``obsolete`` section: each obsolete SCHOTT glass with its equivalent's data, checked."""
    out = []
    for name, nd_cat, vd_cat, rel in OBSOLETE_SCHOTT:
        d = read_rii_file(str(root / rel))
        nd, vd = nd_vd(d)
        if abs(nd - nd_cat) > OBSOLETE_ND_TOL or abs(vd - vd_cat) > OBSOLETE_VD_TOL:
            raise ValueError(f"{name}: equivalent {rel} has nd {nd:.5f}, vd {vd:.2f}, not the catalog's "
                             f"{nd_cat:.5f}, {vd_cat:.2f}")
        equivalent = f"{rel.split('/')[1].upper()} {rel.rsplit('/', 1)[1][:-4]}"
        out.append({"name": name, "catalog": "SCHOTT", "status": "obsolete", "catalog_nd": nd_cat,
                    "catalog_vd": vd_cat, "equivalent": equivalent, "family": d["family"], "formula": d["formula"],
                    "coefficients": d["coefficients"], "wavelength_range": list(d["wavelength_range"]),
                    "source": f"refractiveindex.info database: data/{rel}", "reference": d["reference"],
                    "license": "CC0 1.0",
                    "provenance": f"obsolete SCHOTT {name} (catalog nd {nd_cat:.5f}, vd {vd_cat:.2f}): data of the "
                                  f"equivalent {equivalent} (nd {nd:.5f}, vd {vd:.2f}), refractiveindex.info "
                                  f"database (CC0 1.0), {rel}: {d['reference']}"})
    return out


def build() -> dict:
    root = database_root()
    glasses = []
    for name, catalog, rel, aliases in ENTRIES + ADHESIVE_ENTRIES + POLYMER_ENTRIES:
        d = read_rii_file(str(root / rel))
        glasses.append({"name": name, "aliases": aliases, "catalog": catalog, "family": d["family"],
                        "formula": d["formula"], "coefficients": d["coefficients"],
                        "wavelength_range": list(d["wavelength_range"]),
                        "source": f"refractiveindex.info database: data/{rel}", "reference": d["reference"],
                        "license": "CC0 1.0",
                        "provenance": f"refractiveindex.info database (CC0 1.0), {rel}: {d['reference']}"})
    glasses.append(AIR_ENTRY)
    return {"about": "raywave bundled glass table; regenerate with python -m raywave.materials._make_table. "
                     "Data: refractiveindex.info database (CC0 1.0) unless a glass's provenance says otherwise.",
            "glasses": glasses, "obsolete": obsolete_entries(root)}


if __name__ == "__main__":
    TABLE_PATH.parent.mkdir(parents=True, exist_ok=True)
    TABLE_PATH.write_text(json.dumps(build(), indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {TABLE_PATH}")
