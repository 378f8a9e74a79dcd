"""Glass lookup: the bundled table, the vendor catalogs of the refractiveindex.info database, and AGF
catalogs users bring — resolved as OpticStudio does (exact name, in the listed catalogs, in order)."""

from __future__ import annotations

import difflib
import json
import warnings
from functools import cached_property
from pathlib import Path

from raywave.materials.agf import Catalog, GlassRecord, read_agf
from raywave.materials.base import Air, ConstantIndex, Material
from raywave.materials.codes import parse_glass_code
from raywave.materials.glass import ModelGlass
from raywave.materials.rii import book_index, database_root, read_rii_file

TABLE_PATH = Path(__file__).resolve().parent.parent / "data" / "glasses" / "table.json"
#: Vendor catalogs searched (in this order) when a lens names no catalogs.
VENDOR_ORDER = ["SCHOTT", "OHARA", "CDGM", "HOYA", "HIKARI", "SUMITA"]
#: The bundled table answers to this catalog name too (OpticStudio keeps fused silica, plastics in MISC).
TABLE_CATALOG = "MISC"
#: Research-data shelves of the database, searched last: a book id (e.g. "CaF2", "SiO2", "ZeonexE48R")
#: gives the book's first page with index data; "BOOK/PAGE" (e.g. "SiO2/Malitson") a given page.
BOOK_ORDER = ["MAIN", "ORGANIC", "OTHER"]


class GlassNotFoundError(ValueError):
    """A glass name that no searched catalog holds (``glass``: the name, when known)."""

    def __init__(self, message: str, glass: str | None = None):
        super().__init__(message)
        self.glass = glass


class GlassCatalogWarning(UserWarning):
    """A glass taken from a catalog the lens does not name, because a catalog it names is not bundled."""


class ObsoleteGlassWarning(UserWarning):
    """An obsolete catalog glass (e.g. SCHOTT BK7, K5, SK16): its data come from an equivalent glass."""


def _vendor_index() -> dict[str, dict[str, Path]]:
    """{CATALOG: {NAME: yml path}} over specs/<vendor>/** of the database (optical/ wins duplicates)."""
    root = database_root() / "specs"
    out: dict[str, dict[str, Path]] = {}
    for vendor in sorted(p for p in root.iterdir() if p.is_dir()):
        files = sorted(vendor.rglob("*.yml"), key=lambda f: (f.parent.name != "optical", str(f)))
        idx: dict[str, Path] = {}
        for f in files:
            if f.name != "about.yml":
                idx.setdefault(f.stem.upper(), f)
        if idx:
            out[vendor.name.upper()] = idx
    return out


class GlassLibrary:
    """Where glasses come from: the bundled table, the vendor database and user catalogs.

    The module's default library (``DEFAULT_LIBRARY``) is read-only; make your own to add AGF catalogs::

        lib = GlassLibrary()
        lib.add_catalog("my_vendor.agf")
        glass = get_material("MYGLASS", catalogs=["MY_VENDOR"], library=lib)
    """

    def __init__(self, read_only: bool = False):
        self._user: dict[str, Catalog] = {}
        self._read_only = read_only

    # ------------------------------------------------------------------ sources
    @cached_property
    def table(self) -> Catalog:
        """The bundled glass table (raywave/data/glasses/table.json), with aliases."""
        data = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
        cat = Catalog(TABLE_CATALOG)
        for g in data["glasses"]:
            rec = GlassRecord(g["name"], g["family"], g.get("formula", 0), g["coefficients"],
                              tuple(g["wavelength_range"]), g.get("catalog", TABLE_CATALOG), g["provenance"])
            for key in [g["name"]] + g.get("aliases", []):
                cat.records[key.upper()] = rec
        return cat

    @cached_property
    def obsolete(self) -> dict[str, dict[str, GlassRecord]]:
        """{CATALOG: {NAME: record}} of the bundled table's obsolete glasses (the data of an equivalent glass)."""
        data = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
        out: dict[str, dict[str, GlassRecord]] = {}
        for g in data.get("obsolete", []):
            note = (f"glass {g['name']!r} is obsolete in the {g['catalog']} catalog (nd {g['catalog_nd']:.5f}, "
                    f"vd {g['catalog_vd']:.2f}); raywave uses the dispersion data of the equivalent "
                    f"{g['equivalent']} (same nd and vd to {1e-4:g} / 0.15; the CC0 database has no data of the "
                    "obsolete melt)")
            out.setdefault(g["catalog"].upper(), {})[g["name"].upper()] = GlassRecord(
                g["name"], g["family"], g.get("formula", 0), g["coefficients"], tuple(g["wavelength_range"]),
                g["catalog"], g["provenance"], g["catalog_nd"], g["catalog_vd"], obsolete=note)
        return out

    @cached_property
    def vendor_index(self) -> dict[str, dict[str, Path]]:
        """Lazy: built on the first lookup that needs the vendor database."""
        return _vendor_index()

    @cached_property
    def book_lookup(self) -> dict[str, dict[str, tuple[str, list]]]:
        """Lazy: {SHELF: {BOOK upper: (book id, [(page, path), ...])}} of the main/organic/other shelves."""
        return {shelf: {b.upper(): (b, pages) for b, pages in books.items()}
                for shelf, books in book_index().items()}

    def add_catalog(self, catalog, name: str | None = None) -> Catalog:
        """Add a user catalog (an AGF path or a :class:`Catalog`); it is searched before the others."""
        if self._read_only:
            raise RuntimeError("the default glass library is read-only: create GlassLibrary() and add catalogs to it")
        cat = catalog if isinstance(catalog, Catalog) else read_agf(catalog, name)
        self._user[cat.name.upper()] = cat
        return cat

    register_catalog = add_catalog

    @property
    def read_only(self) -> bool:
        return self._read_only

    def catalogs(self) -> list[str]:
        """Every catalog name this library knows."""
        return list(self._user) + [TABLE_CATALOG] + [c for c in VENDOR_ORDER if c in self.vendor_index] + \
            [c for c in self.vendor_index if c not in VENDOR_ORDER] + \
            [c for c in BOOK_ORDER if c in self.book_lookup]

    def glasses(self, catalog: str) -> list[str]:
        """Glass names in ``catalog``."""
        c = catalog.upper()
        if c in self._user:
            return self._user[c].names()
        if c == TABLE_CATALOG:
            return sorted({r.name for r in self.table.records.values()})
        if c in self.vendor_index:
            return sorted({p.stem for p in self.vendor_index[c].values()} |
                          {r.name for r in self.obsolete.get(c, {}).values()})
        if c in self.book_lookup:
            return sorted(book for book, _ in self.book_lookup[c].values())
        raise GlassNotFoundError(f"unknown glass catalog {catalog!r}; known: {', '.join(self.catalogs())}")

    # ------------------------------------------------------------------ lookup
    def _find_in(self, catalog: str, name: str) -> GlassRecord | None:
        c, key = catalog.upper(), name.upper()
        if c in self._user:
            return self._user[c].record(key)
        if c == TABLE_CATALOG:
            return self.table.record(key)
        if c in BOOK_ORDER:
            return self._find_in_books(c, name)
        path = self.vendor_index.get(c, {}).get(key)
        if path is None:
            return self.obsolete.get(c, {}).get(key)  # an obsolete glass the catalog still lists
        d = read_rii_file(str(path))
        rel = path.relative_to(database_root())
        return GlassRecord(path.stem, d["family"], d["formula"], d["coefficients"], d["wavelength_range"], c,
                           f"refractiveindex.info database (CC0), {rel}: {d['reference']}")

    def _find_unhyphenated(self, catalog: str, name: str) -> GlassRecord | None:
        """The glass of ``catalog`` whose name without hyphens and spaces is ``name``'s (CODE V's form of vendor
        names: NBK7 for N-BK7), when exactly one glass matches; vendor catalogs and user catalogs only."""
        key = name.upper().replace("-", "").replace(" ", "")
        if catalog.upper() in BOOK_ORDER:
            return None
        try:
            names = self.glasses(catalog)
        except GlassNotFoundError:
            return None
        hits = [g for g in names if g.upper().replace("-", "").replace(" ", "") == key]
        return self._find_in(catalog, hits[0]) if len(hits) == 1 else None

    def _find_in_books(self, shelf: str, name: str) -> GlassRecord | None:
        book_key, _, page_key = name.partition("/")
        hit = self.book_lookup.get(shelf, {}).get(book_key.strip().upper())
        if hit is None:
            return None
        book, pages = hit
        if page_key:
            pages = [(p, rel) for p, rel in pages if p.upper() == page_key.strip().upper()]
        root = database_root()
        for page, rel in pages:
            try:
                d = read_rii_file(str(root / rel))
            except (ValueError, KeyError, OSError):
                continue  # a page with extinction data only, or unreadable: try the next one
            return GlassRecord(f"{book}/{page}" if page_key else book, d["family"], d["formula"], d["coefficients"],
                               d["wavelength_range"], shelf,
                               f"refractiveindex.info database (CC0), {rel}: {d['reference']}")
        return None

    def find(self, name: str, catalogs=None) -> GlassRecord:
        """The record of glass ``name`` (see :meth:`_find`); an obsolete glass gives an :class:`ObsoleteGlassWarning`
        naming the equivalent whose data are used."""
        rec = self._find(name, catalogs)
        if rec.obsolete:
            warnings.warn(ObsoleteGlassWarning(rec.obsolete), stacklevel=3)
        return rec

    def _find(self, name: str, catalogs=None) -> GlassRecord:
        """The record of glass ``name``: in ``catalogs`` (in order) if given, else in the user catalogs, the
        bundled table (MISC), the vendor catalogs (SCHOTT, OHARA, CDGM, HOYA, HIKARI, SUMITA, then the
        database's other vendors), then the database's MAIN, ORGANIC and OTHER shelves.

        Named catalogs that this library does not have are skipped; when the glass is in none of the named
        catalogs it has, and one of them was skipped, every other catalog is searched (in the order above) and
        a :class:`GlassCatalogWarning` names the catalog used. Only a glass found nowhere is an error (or,
        when every named catalog is present, a glass not in them: OpticStudio's rule)."""
        missing: list[str] = []
        if catalogs:
            known = self.catalogs()
            named = list(dict.fromkeys(c.upper() for c in catalogs))
            missing = [c for c in named if c not in known]
            order = [c for c in named if c in known]
        else:
            order = self.catalogs()
        for c in order:
            rec = self._find_in(c, name)
            if rec is not None:
                return rec
        for c in order:  # CODE V writes vendor names without hyphens (NBK7_SCHOTT for N-BK7)
            rec = self._find_unhyphenated(c, name)
            if rec is not None:
                return rec
        if missing:
            # A named catalog raywave does not have may hold the glass: look in every other catalog, and say where
            # the glass came from (OpticStudio would have searched the missing catalog first).
            rest = [c for c in self.catalogs() if c not in order]
            for c in rest:
                rec = self._find_in(c, name)
                if rec is not None:
                    warnings.warn(GlassCatalogWarning(
                        f"glass {name!r}: not in the named catalog(s) {', '.join(order) or '(none bundled)'}, and "
                        f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} not bundled with raywave; "
                        f"using {rec.name} from {c}"), stacklevel=5)
                    return rec
            order = order + rest
            if not order:
                raise GlassNotFoundError(f"glass {name!r}: unknown glass catalog(s) {', '.join(missing)}; "
                                         f"known: {', '.join(self.catalogs())}", name)
        pool = sorted({g for c in order for g in self.glasses(c)})
        close = difflib.get_close_matches(name.upper(), [g.upper() for g in pool], n=5, cutoff=0.6)
        by_upper = {g.upper(): g for g in pool}
        hint = f"; did you mean {', '.join(by_upper[c] for c in close)}?" if close else ""
        raise GlassNotFoundError(f"unknown glass {name!r} (searched catalogs: {', '.join(order)}){hint}", name)

    def material(self, name: str, catalogs=None, catalog: str | None = None) -> Material:
        """A fresh material module (a :class:`DispersiveGlass`, or air) for glass ``name``."""
        rec = self.find(name, [catalog] if catalog else catalogs)
        return rec.to_material(explicit_catalog=catalog is not None)


DEFAULT_LIBRARY = GlassLibrary(read_only=True)


def get_material(spec, catalogs=None, library: GlassLibrary | None = None) -> Material:
    """A material from its lens-file form (docs/lens-format.md).

    ``spec``: a :class:`Material` (returned as is); ``"air"`` (or None / ""); a glass name (or a glass code
    no catalog names, e.g. ``"517642"`` or CODE V's ``"517000.520000"``: a model glass, :mod:`raywave.materials.codes`); ``{"index": n}``
    (constant index); ``{"model": {"nd": .., "vd": ..}}`` (model glass); ``{"name": .., "catalog": ..}``.
    ``catalogs``: the catalog search order (a .zmx GCAT line), default: see :meth:`GlassLibrary.find`.
    Raises :class:`GlassNotFoundError` (naming the glass and suggesting close names) or ValueError.
    """
    lib = library or DEFAULT_LIBRARY
    if isinstance(spec, Material):
        return spec
    if spec is None or (isinstance(spec, str) and spec.strip().lower() in ("", "air")):
        return Air()
    if isinstance(spec, str):
        try:
            return lib.material(spec.strip(), catalogs)
        except GlassNotFoundError:
            code = parse_glass_code(spec)  # a glass code no catalog names: a model glass (nd, vd)
            if code is None:
                raise
            return ModelGlass(*code, name=spec.strip())
    if isinstance(spec, dict):
        if set(spec) == {"index"}:
            return ConstantIndex(float(spec["index"]))
        if set(spec) == {"model"} and isinstance(spec["model"], dict) and set(spec["model"]) == {"nd", "vd"}:
            return ModelGlass(float(spec["model"]["nd"]), float(spec["model"]["vd"]))
        if set(spec) == {"name", "catalog"}:
            return lib.material(str(spec["name"]), catalog=str(spec["catalog"]))
    raise ValueError(f"material {spec!r} is not a glass name, 'air', {{'index': n}}, {{'model': {{'nd', 'vd'}}}} "
                     "or {'name', 'catalog'}")


def list_catalogs(library: GlassLibrary | None = None) -> list[str]:
    return (library or DEFAULT_LIBRARY).catalogs()


def list_glasses(catalog: str, library: GlassLibrary | None = None) -> list[str]:
    return (library or DEFAULT_LIBRARY).glasses(catalog)
