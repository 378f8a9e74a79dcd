"""Lens files <-> lens specs (plain dicts; torch only to read a DeepLens Pixel2D .pth map).

A *spec* is the dict form of a lens (docs/lens-format.md); :mod:`raywave.lens.build` turns it into a
:class:`~raywave.lens.lens.Lens` and back. Formats:

* ``.json`` — raywave's own format ("raywave-lens", version 1), read strictly and written exactly;
  a ``.json`` file without ``"format"`` that looks like a DeepLens lens file is imported from DeepLens.
* ``.zmx`` — Zemax OpticStudio sequential files (STANDARD, EVENASPH, ODDASPHE, TOROIDAL, PARAXIAL surfaces; every
  system aperture type), read and written.
* ``.seq`` — CODE V sequence files (spheres, conics, even aspheres; EPD / FNO / NAO), read.

Every problem is a :class:`LensFileError` (a ValueError) whose message starts with ``path:line:``.
"""

from __future__ import annotations

from pathlib import Path

from raywave.io.codev import read_seq
from raywave.io.deeplens import looks_like_deeplens, read_deeplens, read_deeplens_hybrid
from raywave.io.doe import DOEData, rebase_phase_path, resolve_doe
from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import (parse_json_text, read_json_spec, read_text, validate_spec,
                                    write_json_spec)
from raywave.io.spec import canonical_spec
from raywave.io.zmx import read_zmx, write_zmx

__all__ = [
    "DOEData",
    "LensFileError",
    "LensFileWarning",
    "canonical_spec",
    "detect_format",
    "read_deeplens",
    "read_deeplens_hybrid",
    "read_hybrid_spec",
    "read_json_spec",
    "read_lens_spec",
    "read_seq",
    "read_zmx",
    "rebase_phase_path",
    "resolve_doe",
    "validate_spec",
    "write_json_spec",
    "write_lens_spec",
    "write_zmx",
]

#: Extensions and the formats they hold.
READ_EXTENSIONS = {".json": "raywave JSON or DeepLens JSON", ".zmx": "Zemax OpticStudio", ".seq": "CODE V"}
WRITE_EXTENSIONS = {".json": "raywave JSON", ".zmx": "Zemax OpticStudio"}


def detect_format(path) -> str:
    """'raywave', 'deeplens', 'zmx' or 'codev' for a lens file, by extension and (for .json) content."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".zmx":
        return "zmx"
    if ext == ".seq":
        return "codev"
    if ext != ".json":
        raise LensFileError(f"unknown lens file extension {p.suffix or '(none)'!r}; raywave reads "
                            + ", ".join(f"{e} ({d})" for e, d in READ_EXTENSIONS.items()), p)
    data, _ = parse_json_text(read_text(p), str(p))
    if isinstance(data, dict) and "format" in data:
        return "raywave"
    if looks_like_deeplens(data):
        return "deeplens"
    raise LensFileError("not a lens file raywave knows: no \"format\": \"raywave-lens\" and not a DeepLens "
                        "lens file", p, 1)


def read_lens_spec(path, config: int | None = None) -> dict:
    """Read any lens file raywave knows into a validated spec (format chosen by :func:`detect_format`).

    ``config``: the configuration of a multi-configuration .zmx file (1-based, default 1); other formats have
    one configuration (``config`` > 1 is an error there)."""
    if not Path(path).exists():
        raise FileNotFoundError(f"lens file {str(path)!r} not found")
    fmt = detect_format(path)
    if fmt == "zmx":
        return read_zmx(path, config=config)
    if config is not None and int(config) != 1:
        raise ValueError(f"{path}: configuration {config} asked of a single-configuration lens file")
    if fmt == "codev":
        return read_seq(path)
    if fmt == "deeplens":
        return read_deeplens(path)
    return read_json_spec(path)


def read_hybrid_spec(path) -> tuple[dict, DOEData | None]:
    """Read a lens file and its DOE: ``(spec, doe)``, ``doe`` None when the file names no DOE.

    The DOE's phase map (``doe.phase``, relative to the lens file) is read in full and checked (2-D, finite,
    shape agreeing with ``shape`` / ``size`` and the pitch); errors are :class:`LensFileError` with the line of
    the key in the lens file. A DeepLens hybrid lens's ``"DOE"`` is read by :func:`read_deeplens_hybrid`."""
    if Path(path).exists() and detect_format(path) == "deeplens":
        return read_deeplens_hybrid(path)  # a Pixel2D map lives in a torch / numpy file the spec cannot name
    spec = read_lens_spec(path)
    if spec.get("doe") is None:
        return spec, None
    lines = None
    if detect_format(path) == "raywave":
        _, lines = parse_json_text(read_text(path), str(path))
    return spec, resolve_doe(spec, str(path), Path(path).parent, lines, load=True)


def write_lens_spec(spec: dict, path, **kwargs) -> None:
    """Write ``spec`` as raywave JSON (``.json``) or Zemax (``.zmx``; ``kwargs`` go to :func:`write_zmx`)."""
    ext = Path(path).suffix.lower()
    if ext == ".json":
        write_json_spec(spec, path)
    elif ext == ".zmx":
        write_zmx(spec, path, **kwargs)
    else:
        raise LensFileError(f"cannot write lens files with extension {Path(path).suffix or '(none)'!r}; use "
                            + " or ".join(WRITE_EXTENSIONS), path)
