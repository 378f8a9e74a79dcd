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

# The database holds Zeonex E48R (Zeon cyclo-olefin polymer) itself, under other/commercial polymers.
POLYMER_ENTRIES = [
    ("E48R", "MISC", "other/commercial polymers/ZeonexE48R/nk/Sultanova.yml",
     ["ZEONEX_E48R", "ZEONEXE48R", "E48R-LIKE", "COP"]),
]

AIR_ENTRY = {"name": "AIR", "aliases": [], "catalog": "MISC", "family": "constant", "formula": 0,
             "coefficients": [1.0], "wavelength_range": [0.0, 1.0e6], "source": None, "reference": None,
             "license": None, "provenance": "air: n = 1 by definition (catalog indices are relative to air)"}


def build() -> dict:
    root = database_root()
    glasses = []
    for name, catalog, rel, aliases in ENTRIES + POLYMER_ENTRIES:
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
            "glasses": glasses}


if __name__ == "__main__":
    TABLE_PATH.parent.mkdir(parents=True, exist_ok=True)
    TABLE_PATH.write_text(json.dumps(build(), indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {TABLE_PATH}")
