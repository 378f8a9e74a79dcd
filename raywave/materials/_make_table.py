"""Regenerate raywave/data/glasses/table.json from the refractiveindex.info database (CC0).

    python -m raywave.materials._make_table
"""

from __future__ import annotations

import json

from raywave.materials.catalog import TABLE_PATH
from raywave.materials.glass import LINE_C, LINE_D, LINE_F
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

# Zeonex E48R is not in the database: a Cauchy model n = A + B/λ² through the maker's nd = 1.5310 and
# νd = 56.0 (Zeon datasheet values), labelled "E48R-like" (a model, not measured dispersion).
E48R_ND, E48R_VD = 1.5310, 56.0


def _e48r_entry() -> dict:
    b = (E48R_ND - 1) / E48R_VD / (1 / LINE_F**2 - 1 / LINE_C**2)
    a = E48R_ND - b / LINE_D**2
    return {"name": "E48R", "aliases": ["E48R-LIKE", "COP", "ZEONEX_E48R"], "catalog": "MISC", "family": "rii",
            "formula": 5, "coefficients": [a, b, -2.0], "wavelength_range": [0.4, 1.1],
            "provenance": "E48R-like cyclo-olefin polymer: Cauchy model n = A + B/λ² through nd = 1.5310, "
                          "νd = 56.0 (Zeon Zeonex E48R datasheet values); not measured dispersion data"}


def build() -> dict:
    root = database_root()
    glasses = []
    for name, catalog, rel, aliases in ENTRIES:
        d = read_rii_file(str(root / rel))
        glasses.append({"name": name, "aliases": aliases, "catalog": catalog, "family": d["family"],
                        "formula": d["formula"], "coefficients": d["coefficients"],
                        "wavelength_range": list(d["wavelength_range"]),
                        "provenance": f"refractiveindex.info database (CC0 1.0), {rel}: {d['reference']}"})
    glasses.append(_e48r_entry())
    return {"about": "raywave bundled glass table; regenerate with python -m raywave.materials._make_table. "
                     "Data: refractiveindex.info database (CC0 1.0) unless a glass's provenance says otherwise.",
            "glasses": glasses}


if __name__ == "__main__":
    TABLE_PATH.parent.mkdir(parents=True, exist_ok=True)
    TABLE_PATH.write_text(json.dumps(build(), indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {TABLE_PATH}")
