"""CODE V sequence files (.seq, sequential subset) -> lens specs.

What is read (docs/lens-format.md, "CODE V .seq"): ``RDM`` (radius mode; ``RDM N``: curvatures), ``TITLE``,
``DIM`` (M / C / I), the pupil (``EPD``, ``FNO`` = image-space F/#, ``NAO`` = object-space NA), ``WL`` (nm),
``REF``, fields ``XAN`` / ``YAN`` (degrees) or ``XOB`` / ``YOB`` (object heights), and the surfaces ``SO`` (object:
its thickness is the object distance, ≥ 1e10 = infinity), ``S`` (radius, thickness, glass), ``STO`` (the stop:
as a surface line, or alone after one), ``SI`` (image; its thickness is a defocus: the image plane sits that far
beyond the last surface's thickness, as CODE V and rayoptics read it), with the qualifiers ``K`` (conic), ``A`` … ``J`` (aspheric
terms on r⁴ … r²⁰), ``CUY`` / ``RDY`` (curvature / radius, replacing the surface line's), ``SLB`` (label → comment) and the apertures (:func:`_aperture_command`; ``Sk`` addresses surface k): ``CIR r``
(clear aperture → semi-diameter), ``CIR OBS r`` (a circular obscuration; with ``CIR HOL r0`` inside it an annular
obscuration), ``REX`` / ``REY`` (a rectangular clear aperture, a real aperture; with ``OBS`` a rectangular
obscuration), ``ADX`` / ``ADY`` (the clear aperture's decentre, a decentred CIR becoming a real aperture; with
``OBS`` the obscuration's). Glasses:
``NAME_CATALOG`` (CODE V writes vendor names without hyphens: NBK7_SCHOTT is N-BK7, resolved when the lens is
built), a bare name, ``nd:vd`` and glass codes ``NNNVVV``, ``NNNVVV.DDD``, ``NNNNNN.VVVVVV`` (model glasses, :func:`_glass_code`). A mirror is ``REFL`` as the glass (the
medium after it is the one before it; CODE V, like OpticStudio, writes the thicknesses after it negative).
Surface decentres and tilts (``XDE`` / ``YDE`` / ``ZDE`` lens units, ``ADE`` / ``BDE`` / ``CDE`` degrees, optional
``Sk``) with CODE V's basic decentre or ``DAR`` / ``BEN`` / ``REV`` become coordinate breaks around the surface
(:func:`_breaks`; a decentred image surface tilts the image plane). Everything raywave cannot model (a decentred
object surface, ``REV`` on the image surface, toroids ``YTO`` / ``XTO``, special surfaces ``SPS``, diffractive
surfaces ``DIF``, image-space ``NA``, image-height fields, a curved object or image) is a :class:`LensFileError`
naming the surface and line. Commands that do not change the prescription (weights, vignetting factors, solves and
variable flags, ``INI``, ``GO``, ...) are skipped; other unknown commands give one :class:`LensFileWarning`.

Lines: ``!`` starts a comment, ``&`` at the end continues a line, ``;`` separates commands.
"""

from __future__ import annotations

import math
import re
from decimal import Decimal, InvalidOperation
import warnings
from pathlib import Path

from raywave.io.errors import LensFileError, LensFileWarning
from raywave.io.json_format import FORMAT_NAME, FORMAT_VERSION, UNITS, validate_spec
from raywave.io.spec import DEFAULT_WAVELENGTHS, aspheric_canonical, shape_entry

#: Lens units (DIM) -> mm.
DIM_SCALE = {"M": 1.0, "C": 10.0, "I": 25.4}
#: Aspheric qualifiers and the power of r they multiply.
ASPHERIC_LETTERS = {"A": 4, "B": 6, "C": 8, "D": 10, "E": 12, "F": 14, "G": 16, "H": 18, "J": 20}
#: Object distances at or beyond this (lens units) are infinite (CODE V writes 1e10 or 1e13 for infinity).
INFINITE_DISTANCE = 1e10
#: Commands skipped on purpose (weights, vignetting, solves, variables, bookkeeping).
IGNORED = {"LEN", "INI", "WTW", "WTF", "VUX", "VLX", "VUY", "VLY", "VCX", "VCY", "TEM", "PRE", "GO", "CWL", "DDM",
           "DES", "CCY", "THC", "GLC", "PIM", "SPH", "CON", "ASP", "RSU", "EDG", "SELECT", "END", "PRV", "PWL", "DEL",
           "AFO", "RMD", "HOT", "ZOO", "PWR", "CCA", "CCB", "CCC", "CCD", "CCE", "CCK",
           "CCF", "CCG", "CCH", "CCJ", "TLE", "DNP", "NAM", "LNG", "XRI", "YRI", "HWL", "HOR", "HCT",
           "HCO", "OBS"}
#: Commands raywave cannot model, and what they are.
UNSUPPORTED = {
    "YTO": "toroid (y)",
    "XTO": "toroid (x)", "SPS": "special surface", "NA": "image-space NA pupil", "XIM": "image-height field",
    "YIM": "image-height field", "XRI": "real image-height field", "YRI": "real image-height field",
    "UDS": "user-defined surface", "HOE": "holographic surface", "GRT": "grating",
    "DIF": "diffractive surface",  # its HWL / HOR / HCT / HCO data mean nothing without it (skipped)
    "ELX": "elliptical aperture", "ELY": "elliptical aperture", "POL": "polygon aperture",
}
#: Commands that take effect only when non-zero.
_ZERO_OK: set = set()
#: Surface decentre values (XDE, YDE, ZDE in lens units; ADE, BDE, CDE in degrees) and decentre types.
DECENTRE_VALUES = {"XDE": "x", "YDE": "y", "ZDE": "z", "ADE": "a", "BDE": "b", "CDE": "c"}
DECENTRE_TYPES = {"DAR": "decentre and return", "BEN": "bend", "REV": "reverse decentre"}
_SURFACE_STARTS = ("SO", "S", "STO", "SI")


#: CODE V aperture commands (a qualifier of a surface, or of surface k with ``Sk``): the shape or decentre and,
#: after an optional ``OBS`` / ``HOL`` / ``EDG`` keyword, the value. ``EDG`` (a mechanical edge) is read past.
APERTURE_COMMANDS = ("CIR", "REX", "REY", "ADX", "ADY", "ARO")
_APERTURE_KINDS = {"OBS": "obs", "HOL": "hol", "EDG": "edg"}


def _aperture_command(surfs: list, cur: dict, where: str, cmd: str, args: list, ln: int, err) -> None:
    """A ``CIR`` / ``REX`` / ``REY`` / ``ADX`` / ``ADY`` / ``ARO`` qualifier ``cmd [Sk] [OBS|HOL|EDG] value`` of
    surface k (``Sk``) or of the current surface. Kept on the surface record: ``cir`` (a clear circle: the
    semi-diameter), ``obs`` / ``hol`` (a circular obscuration, and a hole in it: an annular obscuration),
    ``rect`` / ``rect_obs`` (``{"x": half width, "y": ...}`` of a clear / obscuring rectangle), ``dec`` / ``dec_obs``
    (the clear aperture's / the obscuration's decentre [x, y]); the line in ``ap_line``."""
    target, where, rest = _addressed(surfs, cur, where, cmd, args, ln, err)
    vals = [float(a) for a in rest if _number(a)]
    words = [a.upper() for a in rest if not _number(a)]
    kind = next((_APERTURE_KINDS[w] for w in words if w in _APERTURE_KINDS), "clear")
    bad = [w for w in words if w not in _APERTURE_KINDS]
    if bad or len(vals) != 1 or not math.isfinite(vals[0]):
        raise err(f"{where}: {cmd} {' '.join(args)}: needs one finite number (after an optional OBS, HOL or EDG)",
                  ln)
    v = vals[0]
    target.setdefault("ap_line", ln)
    if kind == "edg":
        return  # the mechanical edge: drawing only
    if cmd == "ARO":
        if v != 0.0:
            raise err(f"{where}: ARO {' '.join(args)}: a rotated aperture is not supported by raywave", ln)
        return
    if cmd in ("ADX", "ADY"):
        dec = target.setdefault("dec_obs" if kind in ("obs", "hol") else "dec_ap", [0.0, 0.0])
        dec[0 if cmd == "ADX" else 1] = v
        return
    if not v > 0:
        raise err(f"{where}: {cmd} {' '.join(args)}: the aperture size must be > 0", ln)
    if cmd == "CIR":
        target["cir" if kind == "clear" else kind] = v
    else:
        target.setdefault("rect" if kind == "clear" else f"rect_{kind}", {})[cmd[-1].lower()] = v


def _addressed(surfs: list, cur: dict, where: str, cmd: str, args: list, ln: int, err):
    """``(surface record, its name, the other arguments)`` of a qualifier that addresses the current surface or,
    with ``Sk`` among its arguments, surface k."""
    target, rest = cur, []
    for a in args:
        if re.fullmatch(r"[Ss]\d+", a):
            k = int(a[1:])
            if not 0 <= k < len(surfs):
                raise err(f"{where}: {cmd} {' '.join(args)}: no surface {k}", ln)
            target, where = surfs[k], f"surface {k}"
        else:
            rest.append(a)
    return target, where, rest


def _decentre(surfs: list, cur: dict, where: str, cmd: str, args: list, ln: int, err) -> None:
    """A decentre qualifier of the current surface or of surface k (``Sk``): a value (``XDE`` / ``YDE`` / ``ZDE``
    in lens units, ``ADE`` / ``BDE`` / ``CDE`` in degrees) or a decentre type (``DAR`` / ``BEN`` / ``REV``; none:
    CODE V's basic decentre), kept in the surface's ``"dec"`` record (converted to coordinate breaks later)."""
    target, where, rest = _addressed(surfs, cur, where, cmd, args, ln, err)
    dec = target.setdefault("dec", {"x": 0.0, "y": 0.0, "z": 0.0, "a": 0.0, "b": 0.0, "c": 0.0, "type": None,
                                    "line": ln})
    if cmd in DECENTRE_TYPES:
        if rest:
            raise err(f"{where}: {cmd} {' '.join(rest)}: the decentre type takes no value", ln)
        if dec["type"] not in (None, cmd):
            raise err(f"{where}: two decentre types on one surface ({dec['type']} and {cmd})", ln)
        dec["type"] = cmd
        return
    if len(rest) != 1 or not _number(rest[0]) or not math.isfinite(float(rest[0])):
        raise err(f"{where}: {cmd} {' '.join(args)}: needs one finite number "
                  f"({'degrees' if cmd in ('ADE', 'BDE', 'CDE') else 'lens units'})", ln)
    dec[DECENTRE_VALUES[cmd]] = float(rest[0])
    dec["line"] = ln


def _shape(surfs: list, cur: dict, where: str, cmd: str, args: list, ln: int, err) -> None:
    """``CUY [Sk] c`` (curvature, 1 / lens unit) or ``RDY [Sk] r`` (radius, lens units; 0: flat) of the current
    surface or of surface k: it replaces the value the surface line gave, whatever ``RDM`` / ``CUM`` says."""
    target, where, rest = _addressed(surfs, cur, where, cmd, args, ln, err)
    if len(rest) != 1 or not _number(rest[0]) or not math.isfinite(float(rest[0])):
        raise err(f"{where}: {cmd} {' '.join(args)}: needs one finite number "
                  f"({'curvature, 1/lens unit' if cmd == 'CUY' else 'radius, lens units'})", ln)
    v = float(rest[0])
    target["curvature"] = v if cmd == "CUY" else (0.0 if v == 0.0 else 1.0 / v)


def _moves(dec) -> bool:
    """Whether a surface's decentre record moves or turns anything."""
    return bool(dec) and any(dec[k] != 0.0 for k in ("x", "y", "z", "a", "b", "c"))


def _cb(decenter, tilt, thickness: float, order: int, comment: str) -> dict:
    return {"type": "coordinate_break", "decenter": list(decenter), "tilt": list(tilt), "order": order,
            "thickness": thickness, "comment": comment}


def _breaks(dec, thickness: float, scale: float, label: str):
    """``(breaks before, the surface's own thickness, breaks after)``: a CODE V surface decentre as OpticStudio
    coordinate breaks (the spec's ``"coordinate_break"``; ``thickness`` mm is the CODE V surface's, ``scale`` lens
    unit -> mm).

    CODE V (``T``: the translation (XDE, YDE, ZDE), then ``R``: the tilts ADE about x, BDE about the new y, CDE
    about the new z; ADE and BDE are left-handed, CDE right-handed, so that ADE, BDE, CDE are OpticStudio's
    tilts about x, y, z of −ADE, −BDE, +CDE, whose tilts are all right-handed):

    * basic decentre: ``T R`` before the surface; the surfaces after it stay in the new frame (its thickness runs
      along the new z);
    * ``DAR``: ``T R`` before the surface, ``(T R)⁻¹`` after it (back to the frame before the decentre, whose z
      carries the thickness);
    * ``BEN``: ``T R`` before the surface and ``R`` again after it (a fold mirror: the axis follows the reflected
      light);
    * ``REV``: nothing before the surface, ``(T R)⁻¹ = R⁻¹ T⁻¹`` after it.

    ``T R`` is a break of order 0 (decentre x, y, then tilts; a ZDE adds a first break that carries it as its
    thickness, along the z before the tilts); ``(T R)⁻¹`` is a break of order 1 with every value negated whose
    thickness is the surface's minus ZDE (the inverse tilts end on the axes before the decentre)."""
    if not _moves(dec):
        return [], thickness, []
    kind = dec["type"]
    x, y, z = dec["x"] * scale, dec["y"] * scale, dec["z"] * scale
    tilt = [-dec["a"] if dec["a"] else 0.0, -dec["b"] if dec["b"] else 0.0, dec["c"]]  # OpticStudio's signs
    name = {None: "decentre", "DAR": "decentre and return (DAR)", "BEN": "bend (BEN)",
            "REV": "reverse decentre (REV)"}[kind]
    note = f"CODE V {label} {name}"
    before = []
    if kind != "REV":
        if z != 0.0:
            before.append(_cb([x, y], [0.0, 0.0, 0.0], z, 0, note))
            if any(tilt):
                before.append(_cb([0.0, 0.0], tilt, 0.0, 0, note))
        else:
            before.append(_cb([x, y], tilt, 0.0, 0, note))
    if kind is None:
        return before, thickness, []
    if kind == "BEN":
        return before, 0.0, [_cb([0.0, 0.0], tilt, thickness, 0, note)]
    back = _cb([-x if x else 0.0, -y if y else 0.0], [-v if v else 0.0 for v in tilt], thickness - z, 1, note)
    return before, 0.0, [back]


def _number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


#: A quoted string (kept whole, with its quotes), a command separator, or a plain token.
_TOKEN = re.compile(r"'[^']*'|\"[^\"]*\"|;|[^\s;]+")


def _commands(text: str):
    """[(line, [tokens])]: comments dropped, continuations joined, ';' separated (quoted strings kept whole)."""
    out = []
    pending, start = "", None
    for ln, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("!", 1)[0].rstrip()
        if line.endswith("&"):
            pending += " " + line[:-1]
            start = start or ln
            continue
        line = (pending + " " + line).strip()
        first, pending, start = start or ln, "", None
        toks: list[str] = []
        for m in _TOKEN.finditer(line):
            if m.group(0) == ";":
                if toks:
                    out.append((first, toks))
                toks = []
            else:
                toks.append(m.group(0))
        if toks:
            out.append((first, toks))
    return out


def _nm_to_um(tok: str, path, ln) -> float:
    """A wavelength token in nm -> µm, decimally exact (587.5618 -> 0.5875618, not 0.5875617999999999)."""
    try:
        return float(Decimal(tok).scaleb(-3))
    except InvalidOperation:
        raise LensFileError(f"WL: {tok!r} is not a number", path, ln) from None


def _glass_code(t: str, where: str, path, ln) -> tuple[float, float] | None:
    """``(nd, vd)`` of a glass code, or None when ``t`` is not one: ``NNNVVV`` (nd 1.NNN, vd VV.V), SCHOTT's
    ``NNNVVV.DDD`` (DDD: the density, ignored) and CODE V's fine code ``NNNNNN.VVVVVV`` (six digits after the point:
    nd 1.NNNNNN, vd VV.VVVV; ``517000.520000`` is nd 1.517, vd 52). The same rules as
    :func:`raywave.materials.codes.parse_glass_code` (io may not import materials). Never vd = 0: a code whose Abbe
    digits are zero is an error naming it."""
    m = re.fullmatch(r"(\d{3})(\d{3})(?:\.\d{3})?", t)
    if m:
        nd, vd = 1.0 + int(m.group(1)) / 1000.0, int(m.group(2)) / 10.0
    else:
        m = re.fullmatch(r"(\d{6})\.(\d{4,})", t)
        if not m:
            return None
        nd, vd = 1.0 + int(m.group(1)) / 1e6, float("0." + m.group(2)) * 100.0
    if not vd > 0:
        raise LensFileError(f"{where}: glass code {t!r} has Abbe number vd = 0 (NNNVVV, NNNVVV.DDD or CODE V's "
                            "NNNNNN.VVVVVV: nd 1.NNNNNN, vd VV.VVVV)", path, ln)
    return nd, vd


def _glass(tok: str, where: str, path, ln):
    """A CODE V glass token -> spec material."""
    t = tok.strip("'\"")
    up = t.upper()
    if up in ("", "AIR"):
        return "air"
    if up == "REFL":
        return "mirror"  # as OpticStudio's GLAS MIRROR: thicknesses after it are negative in CODE V too
    m = re.fullmatch(r"(\d+\.\d+):(\d+\.?\d*)", t)
    if m:
        return {"model": {"nd": float(m.group(1)), "vd": float(m.group(2))}}
    code = _glass_code(t, where, path, ln)
    if code is not None:
        return {"model": {"nd": code[0], "vd": code[1]}}
    if "_" in t:
        name, cat = t.rsplit("_", 1)
        if name and cat:
            return {"name": name, "catalog": cat.upper()}
    return t


def read_seq(path) -> dict:
    """Read a CODE V .seq file into a validated lens spec (see the module docstring for what is read)."""
    path = str(path)
    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    spec = _interpret(_commands(text), path)
    return validate_spec(spec, path)


class _Seq:
    """What the commands of a .seq file set, in lens units as written (converted to mm when the spec is made)."""

    def __init__(self, path):
        self.path = path
        self.radius_mode = True  # RDM (radii) or CUM / RDM N (curvatures)
        self.scale = 1.0  # lens unit -> mm (DIM)
        self.name = ""
        self.pupil = None  # (EPD / FNO / NAO, value, line)
        self.wls: list[float] = []  # µm
        self.ref = None  # (REF, 1-based, line)
        self.fields: dict[str, list[float]] = {}  # "X" / "Y" -> values
        self.field_type = None
        # raw surfaces: kind (SO / S / SI), r, t, glass, line, stop, conic, asph, label, cir
        self.surfs: list[dict] = []
        self.unknown: dict[str, int] = {}  # unknown command -> its first line
        self.in_private = False  # inside a PRV ... END private catalog
        self.sto_label = None  # (k, line) of a ``STO Sk``

    def err(self, msg, ln):
        """A :class:`LensFileError` at line ``ln`` of the file."""
        return LensFileError(msg, self.path, ln)


def _num(tok, what, ln, err) -> float:
    """``tok`` as a float; else the error ``what: 'tok' is not a number`` (``err(msg, ln)`` makes it)."""
    try:
        return float(tok)
    except ValueError:
        raise err(f"{what}: {tok!r} is not a number", ln) from None


def _first_num(args: list, what, ln, err) -> float:
    """The command's first argument as a float; a command given without one is the error ``what: a value is
    missing``."""
    if not args:
        raise err(f"{what}: a value is missing", ln)
    return _num(args[0], what, ln, err)


def _index(args: list, what, ln, err) -> int:
    """The command's first argument as a whole number (a 1-based index); anything else is an error naming it."""
    v = _first_num(args, what, ln, err)
    if not (math.isfinite(v) and v == int(v)):
        raise err(f"{what}: {args[0]!r} is not a whole number", ln)
    return int(v)


def _interpret(cmds, path) -> dict:
    """The lens spec (not yet validated; lengths in mm) of the .seq commands ``cmds`` (from :func:`_commands`);
    ``path`` names the file in errors and warnings."""
    st = _Seq(path)
    _read_commands(st, cmds)
    obj, img, lens = _check_prescription(st)

    spec: dict = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "units": dict(UNITS)}
    if st.name:
        spec["name"] = st.name
    distance = _object_distance(obj, st)
    spec["object"] = {"distance": distance}
    if st.pupil is not None:
        spec["system_aperture"] = _system_aperture(st.pupil, distance, st.scale, st.err)
    spec["fields"] = _fields(st)
    spec["wavelengths"] = _wavelengths(st)
    spec["surfaces"] = _surfaces(lens, img, st)
    if st.unknown:
        listed = ", ".join(f"{k} (line {ln})" for k, ln in sorted(st.unknown.items(), key=lambda kv: kv[1]))
        warnings.warn(LensFileWarning(f"{path}: ignored unknown CODE V commands: {listed}"), stacklevel=3)
    return spec


def _read_commands(st: _Seq, cmds) -> None:
    """Read the commands ``[(line, [tokens])]`` into ``st``: surfaces with their qualifiers, system settings."""
    for ln, toks in cmds:
        cmd = toks[0].upper()
        args = toks[1:]
        if st.in_private:
            st.in_private = cmd != "END"
            continue
        if cmd == "PRV":
            st.in_private = True
            # stacklevel 4: the caller of read_seq (_read_commands <- _interpret <- read_seq), as before the split
            warnings.warn(LensFileWarning(f"{st.path}:{ln}: private glass catalog (PRV) skipped: its glasses must "
                                          "be in raywave's catalogs"), stacklevel=4)
            continue
        cur = st.surfs[-1] if st.surfs else None
        if _surface_line(st, cmd, args, ln) or _stop_command(st, cur, cmd, args, ln):
            continue
        if cur is not None and _qualifier(st, cur, cmd, args, ln):
            continue
        _setting(st, cmd, args, ln)


def _surface_line(st: _Seq, cmd: str, args: list, ln: int) -> bool:
    """Whether ``cmd args`` is a surface line (``SO`` / ``S`` / ``STO r t`` / ``SI``: radius, thickness in lens
    units, glass); if so its raw surface is appended to ``st.surfs`` (after an implicit object surface when the
    file has no ``SO``)."""
    if not (cmd in ("SO", "S", "SI") or (cmd == "STO" and args and _number(args[0]))):
        return False
    surfs = st.surfs
    if cmd != "SO" and not surfs:
        surfs.append({"kind": "SO", "r": 0.0, "t": math.inf, "glass": "air", "line": ln, "stop": False,
                      "conic": 0.0, "asph": {}, "label": "", "cir": None, "implicit": True})
    vals = [_num(a, f"{cmd} radius/thickness", ln, st.err) for a in args[:2] if _number(a)]
    r = vals[0] if vals else 0.0
    t = vals[1] if len(vals) > 1 else 0.0
    rest = [a for a in args[len(vals):]]
    glass = "air"
    if rest:
        glass = _glass(rest[0], f"surface {len(surfs)}", st.path, ln)
    surfs.append({"kind": "S" if cmd == "STO" else cmd, "r": r, "t": t, "glass": glass, "line": ln,
                  "stop": cmd == "STO", "conic": 0.0, "asph": {}, "label": "", "cir": None})
    return True


def _stop_command(st: _Seq, cur, cmd: str, args: list, ln: int) -> bool:
    """Whether ``cmd`` is a ``STO`` without a surface line (``STO Sk``: surface k is the stop; ``STO`` alone: the
    current surface ``cur``); if so it is recorded in ``st``."""
    if cmd != "STO":
        return False
    if args and re.fullmatch(r"[Ss]\d+", args[0]):
        st.sto_label = (int(args[0][1:]), ln)
    elif cur is not None:
        cur["stop"] = True
    return True


def _qualifier(st: _Seq, cur: dict, cmd: str, args: list, ln: int) -> bool:
    """Whether ``cmd args`` is a qualifier of the current surface ``cur`` (or of the surface ``Sk`` it names):
    conic, aspheric term, label, clear aperture, decentre, curvature; if so it is stored on that surface. An
    unsupported surface qualifier is a :class:`LensFileError`."""
    where = f"surface {len(st.surfs) - 1}"
    if cmd == "K":
        cur["conic"] = _first_num(args, f"{where}: K", ln, st.err)
        return True
    if cmd in ASPHERIC_LETTERS and args and _number(args[0]):
        cur["asph"][ASPHERIC_LETTERS[cmd]] = _num(args[0], f"{where}: {cmd}", ln, st.err)
        return True
    if cmd == "SLB":
        cur["label"] = " ".join(args).strip("'\"")
        return True
    if cmd in APERTURE_COMMANDS:
        _aperture_command(st.surfs, cur, where, cmd, args, ln, st.err)
        return True
    if cmd in DECENTRE_VALUES or cmd in DECENTRE_TYPES:
        _decentre(st.surfs, cur, where, cmd, args, ln, st.err)
        return True
    if cmd in ("CUY", "RDY"):
        _shape(st.surfs, cur, where, cmd, args, ln, st.err)
        return True
    if cmd in UNSUPPORTED:
        if cmd in _ZERO_OK and args and _number(args[0]) and float(args[0]) == 0.0:
            return True
        raise st.err(f"{where}: {UNSUPPORTED[cmd]} ({cmd}) is not supported by raywave", ln)
    return False


def _setting(st: _Seq, cmd: str, args: list, ln: int) -> None:
    """A command that is not about one surface (radius mode, title, lens units, pupil, wavelengths, fields) into
    ``st``; skipped commands pass, unknown ones are recorded in ``st.unknown``."""
    if cmd in ("RDM", "CUM"):
        st.radius_mode = cmd == "RDM" and not (args and args[0].upper() in ("N", "NO"))
    elif cmd in ("TITLE", "TIT"):
        st.name = " ".join(args).strip().strip("'\"")
    elif cmd == "DIM":
        u = args[0].upper() if args else "M"
        if u not in DIM_SCALE:
            raise st.err(f"DIM {u}: unknown lens unit (known: M, C, I)", ln)
        st.scale = DIM_SCALE[u]
    elif cmd in ("EPD", "FNO", "NAO"):
        st.pupil = _pupil_command(st.pupil, cmd, args, ln, st.err)
    elif cmd == "WL":
        st.wls = [_nm_to_um(a, st.path, ln) for a in args]
    elif cmd == "REF":
        st.ref = (_index(args, "REF", ln, st.err), ln)
    elif cmd in ("XAN", "YAN", "XOB", "YOB"):
        kind = "angle" if cmd.endswith("AN") else "object_height"
        if st.field_type is not None and st.field_type != kind:
            raise st.err(f"{cmd}: fields of two types (angles and object heights)", ln)
        st.field_type = kind
        st.fields[cmd[0]] = [_num(a, cmd, ln, st.err) for a in args]
    elif cmd in UNSUPPORTED:
        raise st.err(f"{UNSUPPORTED[cmd]} ({cmd}) is not supported by raywave", ln)
    elif cmd in DECENTRE_VALUES or cmd in DECENTRE_TYPES:
        raise st.err(f"{cmd}: a decentre before the first surface (it qualifies the surface before it)", ln)
    elif cmd in APERTURE_COMMANDS:
        raise st.err(f"{cmd}: an aperture before the first surface (it qualifies the surface before it)", ln)
    elif cmd in IGNORED or cmd in ("K", "SLB") or cmd in ASPHERIC_LETTERS:
        pass
    else:
        st.unknown.setdefault(cmd, ln)


def _pupil_command(pupil, cmd: str, args: list, ln: int, err) -> tuple:
    """``(cmd, value, line)`` of a pupil command (``EPD`` lens units, ``FNO``, ``NAO``); ``pupil``: the one read
    before (None), which must be of the same kind."""
    v = _num(args[0], cmd, ln, err) if args else None
    if v is None or not v > 0:
        raise err(f"{cmd}: the pupil value must be > 0", ln)
    if pupil is not None and pupil[0] != cmd:
        raise err(f"{cmd}: a second pupil specification (line {pupil[2]} gives {pupil[0]})", ln)
    return (cmd, v, ln)


def _check_prescription(st: _Seq):
    """``(object, image, [lens surfaces])`` of the raw surfaces, after the checks of what raywave can model (the
    object and image surfaces, the stop); ``STO Sk`` is applied here."""
    surfs, err = st.surfs, st.err
    if len(surfs) < 3 or surfs[0]["kind"] != "SO" or surfs[-1]["kind"] != "SI":
        raise err("a lens needs an object surface (SO), at least one surface (S) and an image surface (SI)",
                  surfs[-1]["line"] if surfs else None)
    obj, img, lens = surfs[0], surfs[-1], surfs[1:-1]
    if img.get("obs") or img.get("rect_obs") or img.get("hol"):
        raise err("image surface: an obscuration (CIR OBS, REX / REY OBS) on the image surface is not supported",
                  img.get("ap_line", img["line"]))
    if img.get("rect") or any(img.get("dec_ap") or ()):
        raise err("image surface: a rectangular or decentred aperture (REX / REY, ADX / ADY) on the image surface "
                  "is not supported (the sensor is the image plane)", img.get("ap_line", img["line"]))
    if _moves(obj.get("dec")):
        raise err("object surface (SO): a decentred or tilted object is not supported (decentre surface 1 "
                  "instead)", obj["dec"]["line"])
    if _moves(img.get("dec")) and img["dec"]["type"] == "REV":
        raise err("image surface (SI): a reverse decentre (REV) acts after its surface, i.e. after the image: "
                  "not supported (put the tilt on the image surface without REV)", img["dec"]["line"])
    if st.sto_label is not None:
        k, ln = st.sto_label
        if not 1 <= k <= len(lens):
            raise err(f"STO S{k}: no such surface (1..{len(lens)})", ln)
        for s in lens:
            s["stop"] = False
        lens[k - 1]["stop"] = True
    for s, what in ((obj, "object"), (img, "image")):
        if s["r"] != 0.0:
            raise err(f"{what} surface ({'SO' if what == 'object' else 'SI'}): a curved {what} is not supported",
                      s["line"])
    if obj["glass"] != "air":
        raise err("object surface (SO): the object space must be air", obj["line"])
    stops = [i for i, s in enumerate(lens) if s["stop"]]
    if len(stops) > 1:
        raise err(f"surfaces {[i + 1 for i in stops]} are all marked as the stop", lens[stops[1]]["line"])
    return obj, img, lens


def _object_distance(obj: dict, st: _Seq):
    """The spec's object distance: mm, or "inf" (``SO`` thickness ≥ :data:`INFINITE_DISTANCE` lens units)."""
    dist = obj["t"]
    distance = "inf" if (math.isinf(dist) or abs(dist) >= INFINITE_DISTANCE) else dist * st.scale
    if distance != "inf" and not distance > 0:
        raise st.err(f"object surface (SO): object distance {dist!r} must be > 0", obj["line"])
    return distance


def _system_aperture(pupil: tuple, distance, scale: float, err) -> dict:
    """The spec's ``"system_aperture"`` of ``(EPD / FNO / NAO, value, line)`` (EPD lens units -> mm)."""
    cmd, v, ln = pupil
    if cmd == "EPD":
        return {"epd": v * scale}
    if cmd == "FNO":
        return {"f_number": v}
    if distance == "inf":
        raise err("NAO: an object-space NA needs an object at a finite distance", ln)
    if not v < 1.0:
        raise err(f"NAO {v!r}: must be < 1 (NA in air)", ln)
    return {"object_na": v}


def _fields(st: _Seq) -> dict:
    """The spec's ``"fields"``: radial values (degrees, or object heights in mm); x components are folded in."""
    ys = st.fields.get("Y", [])
    xs = st.fields.get("X", [])
    n = max(len(xs), len(ys), 1)
    xs, ys = xs + [0.0] * (n - len(xs)), ys + [0.0] * (n - len(ys))
    if any(xs):
        # stacklevel 4: the caller of read_seq (_fields <- _interpret <- read_seq), as before the split
        warnings.warn(LensFileWarning(f"{st.path}: fields with an x component are folded to radial fields "
                                      "sqrt(x² + y²) (raywave lenses are rotationally symmetric)"), stacklevel=4)
    values = [math.hypot(x, y) if x else y for x, y in zip(xs, ys)]
    if st.field_type == "object_height":
        values = [v * st.scale for v in values]
    return {"type": st.field_type or "angle", "values": values}


def _wavelengths(st: _Seq) -> dict:
    """The spec's ``"wavelengths"`` (µm, 0-based primary from ``REF``; none given: the defaults)."""
    if not st.wls:
        return dict(DEFAULT_WAVELENGTHS)
    ref = st.ref
    primary = (ref[0] - 1) if ref else 0
    if not 0 <= primary < len(st.wls):
        raise st.err(f"REF {ref[0]}: reference wavelength out of range 1..{len(st.wls)}", ref[1])
    return {"values": st.wls, "primary": primary}


def _surfaces(lens: list, img: dict, st: _Seq) -> list:
    """The spec's ``"surfaces"``: each lens surface between the coordinate breaks of its decentre, then the breaks
    of a decentred / tilted image plane."""
    surfaces = []
    for i, s in enumerate(lens, start=1):
        out = _surface_entry(s, i, st)
        before, out["thickness"], after = _breaks(s.get("dec"), out["thickness"], st.scale, f"S{i}")
        surfaces += before + [out] + after
    if img["t"] != 0.0:  # the image surface's thickness: a defocus, as CODE V and rayoptics read it
        if not math.isfinite(img["t"]):
            raise st.err("image surface (SI): its thickness (a defocus) must be finite", img["line"])
        surfaces[-1]["thickness"] += img["t"] * st.scale
    if _moves(img.get("dec")):  # a tilted / decentred image plane: the breaks before it (the image is no entry)
        before, _, _ = _breaks(dict(img["dec"], type=None), 0.0, st.scale, "SI")
        surfaces += before
    return surfaces


def _surface_entry(s: dict, i: int, st: _Seq) -> dict:
    """The spec entry (mm) of raw lens surface ``s`` (surface ``i``, 1-based), without its decentre."""
    r = s["r"]
    c = 0.0 if r == 0.0 else ((1.0 / r) if st.radius_mode else r)
    if s.get("curvature") is not None:  # CUY / RDY
        c = s["curvature"]
    c /= st.scale
    out: dict = {"type": "even_asphere" if any(s["asph"].values()) else "standard"}
    out.update(shape_entry(c))
    out["conic"] = s["conic"]
    if out["type"] == "even_asphere":
        out["aspheric"] = aspheric_canonical({f"a{p}": v * st.scale ** (1 - p) for p, v in s["asph"].items()})
    if not math.isfinite(s["t"]):
        raise st.err(f"surface {i}: thickness must be finite", s["line"])
    out["thickness"] = s["t"] * st.scale
    out["material"] = s["glass"]
    out["aperture"] = _aperture(s, i, st.scale, st.err)
    if s["cir"]:
        out["semi_diameter"] = s["cir"] * st.scale
    out["stop"] = bool(s["stop"])
    if s["label"]:
        out["comment"] = s["label"]
    return out


def _aperture(s: dict, i: int, scale: float, err):
    """The spec ``"aperture"`` of raw surface ``s`` (mm): None; a clear rectangle (``REX`` / ``REY``) or a decentred
    circle (``CIR`` with ``ADX`` / ``ADY``) as a real aperture; an obscuration (``CIR OBS``, an annulus with
    ``CIR HOL`` inside it, or ``REX`` / ``REY OBS``), decentred by ``ADX`` / ``ADY OBS``. A clear ``CIR`` alone stays
    the semi-diameter (it does not clip), as before."""
    ln = s.get("ap_line", s["line"])
    obs = _obscuration(s, i, scale, err, ln)
    dec = [v * scale for v in s.get("dec_ap", [0.0, 0.0])]
    clear = None
    if s.get("rect"):
        r = s["rect"]
        if set(r) != {"x", "y"}:
            raise err(f"surface {i}: a rectangular aperture needs both REX and REY (got only "
                      f"{'REX' if 'x' in r else 'REY'})", ln)
        clear = {"shape": "rectangle", "half_width_x": r["x"] * scale, "half_width_y": r["y"] * scale}
    elif any(dec) or (obs is not None and s["stop"]):
        if not s["cir"]:
            what = "has an obscuration (CIR OBS)" if not any(dec) else "has a decentred aperture (ADX / ADY)"
            raise err(f"surface {i}: {'the stop' if s['stop'] else 'the surface'} {what} but no clear aperture "
                      "(CIR r)", ln)
        clear = {"shape": "circle", "radius": s["cir"] * scale}
    if clear is None:
        return None if obs is None else {"shape": "none", "obscuration": obs}
    if any(dec):
        clear["decenter"] = dec
    if obs is not None:
        clear["obscuration"] = obs
    return clear


def _obscuration(s: dict, i: int, scale: float, err, ln):
    """The spec obscuration of raw surface ``s`` (mm), or None: ``CIR OBS r`` (a disc; with ``CIR HOL r0`` inside it,
    the ring r0 <= r <= r: an annular obscuration) or ``REX`` / ``REY OBS`` (a rectangle), decentred by ``ADX`` /
    ``ADY OBS``."""
    obs = None
    if s.get("obs"):
        obs = {"shape": "circle", "radius": s["obs"] * scale}
        if s.get("hol"):
            if not s["hol"] < s["obs"]:
                raise err(f"surface {i}: the hole (CIR HOL {s['hol']:g}) must lie inside the obscuration "
                          f"(CIR OBS {s['obs']:g})", ln)
            obs = {"shape": "annulus", "inner_radius": s["hol"] * scale, "radius": s["obs"] * scale}
    elif s.get("rect_obs"):
        r = s["rect_obs"]
        if set(r) != {"x", "y"}:
            raise err(f"surface {i}: a rectangular obscuration needs both REX OBS and REY OBS", ln)
        obs = {"shape": "rectangle", "half_width_x": r["x"] * scale, "half_width_y": r["y"] * scale}
    elif s.get("hol"):
        raise err(f"surface {i}: a hole (CIR HOL) without an obscuration (CIR OBS) around it", ln)
    d = [v * scale for v in s.get("dec_obs", [0.0, 0.0])]
    if obs is not None and any(d):
        obs["decenter"] = d
    elif any(d):
        raise err(f"surface {i}: an obscuration decentre (ADX / ADY OBS) without an obscuration", ln)
    return obs
