"""Reader for Zemax AGF glass catalogs (UTF-8, Latin-1 or UTF-16, as users bring them)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from raywave.materials.base import Air, ConstantIndex, Material
from raywave.materials.glass import DispersiveGlass


class AGFError(ValueError):
    """A malformed AGF file (the message names the file and line)."""


@dataclass
class GlassRecord:
    """The data of one glass: enough to build a :class:`~raywave.materials.glass.DispersiveGlass`."""

    name: str
    family: str
    formula: int
    coefficients: list
    wavelength_range: tuple
    catalog: str
    provenance: str
    nd: float | None = None
    vd: float | None = None
    #: for an obsolete catalog glass whose data come from an equivalent glass: the note a warning gives
    obsolete: str | None = None

    def to_material(self, explicit_catalog: bool = False) -> Material:
        """A fresh material module for this record (family "constant": a :class:`ConstantIndex` / :class:`Air`)."""
        if self.family == "constant":
            index = float(self.coefficients[0])
            return Air() if index == 1.0 and self.name.lower() == "air" else ConstantIndex(index, name=self.name)
        return DispersiveGlass(self.name, self.family, self.formula, self.coefficients, self.wavelength_range,
                               catalog=self.catalog, provenance=self.provenance, explicit_catalog=explicit_catalog)


@dataclass(eq=False)
class Catalog(Mapping):
    """A named glass catalog (one AGF file, or the bundled table): a read-only mapping glass name ->
    :class:`~raywave.materials.glass.DispersiveGlass` (a fresh module per lookup; names case-insensitive).

    ``records`` holds the raw data (upper-case name or alias -> :class:`GlassRecord`).
    """

    name: str
    records: dict = field(default_factory=dict)  # upper-case name -> GlassRecord

    def names(self) -> list[str]:
        """Glass names (aliases not repeated), in file order."""
        return list(dict.fromkeys(r.name for r in self.records.values()))

    def record(self, name: str) -> GlassRecord | None:
        return self.records.get(str(name).upper())

    def __getitem__(self, name: str) -> Material:
        rec = self.record(name)
        if rec is None:
            raise KeyError(name)
        return rec.to_material()

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and name.upper() in self.records

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Catalog({self.name!r}, {len(self)} glasses)"


def decode_text(raw: bytes) -> str:
    """Decode catalog or lens-file bytes: UTF-16 (BOM or NUL bytes), else UTF-8, else Latin-1."""
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16")
    if raw[:200].count(b"\x00") > 10:
        return raw.decode("utf-16-le" if raw[1:2] == b"\x00" else "utf-16-be")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def read_agf(path, name: str | None = None) -> Catalog:
    """Read an AGF catalog file into a :class:`Catalog` named ``name`` (default: the file stem, upper case).

    Lines used: ``NM name formula MIL nd vd ...``, ``CD c0 c1 ...`` (coefficients), ``LD lo hi``
    (wavelength range, µm). Other lines (CC, GC, ED, TD, OD, IT) are read past.
    """
    p = Path(path)
    text = decode_text(p.read_bytes())
    cat = Catalog(name or p.stem.upper())
    cur: dict | None = None

    def finish():
        if cur is None:
            return
        if cur.get("coefficients") is None:
            raise AGFError(f"{p}:{cur['line']}: glass {cur['name']!r} has no CD (coefficient) line")
        cat.records[cur["name"].upper()] = GlassRecord(
            cur["name"], "agf", cur["formula"], cur["coefficients"], cur.get("range", (0.0, float("inf"))),
            cat.name, f"AGF catalog {p.name}", cur.get("nd"), cur.get("vd"))

    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0].upper()
        try:
            if key == "NM":
                finish()
                if len(parts) < 3:
                    raise ValueError("NM needs a name and a formula number")
                formula = int(float(parts[2]))
                if not 1 <= formula <= 13:
                    raise ValueError(f"unknown dispersion formula number {formula} (AGF knows 1–13)")
                cur = {"name": parts[1], "formula": formula, "line": lineno,
                       "nd": float(parts[4]) if len(parts) > 4 else None,
                       "vd": float(parts[5]) if len(parts) > 5 else None, "coefficients": None}
            elif key == "CD":
                if cur is None:
                    raise ValueError("CD line before any NM line")
                cur["coefficients"] = [float(v) for v in parts[1:]]
            elif key == "LD":
                if cur is None:
                    raise ValueError("LD line before any NM line")
                cur["range"] = (float(parts[1]), float(parts[2]))
        except (ValueError, IndexError) as err:
            raise AGFError(f"{p}:{lineno}: {err} (line: {line.strip()!r})") from None
    finish()
    if not cat.records:
        raise AGFError(f"{p}: no glasses found (no NM lines); is this an AGF catalog?")
    return cat
