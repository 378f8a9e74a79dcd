"""The raywave JSON lens format ("raywave-lens", version 1): strict reading, validation, exact writing.

Everything here works on plain dicts ("specs", see docs/lens-format.md) and never imports torch.
:func:`validate_spec` checks a spec against the schema and reports *every* problem at once, each with
its key path (``surfaces[3].radus``) and, for a file, its line number.
"""

from __future__ import annotations

import bisect
import json
import math
import re
from json.decoder import scanstring
from json.scanner import NUMBER_RE
from pathlib import Path

from raywave.io.doe import check_doe_files, validate_doe
from raywave.io.surface_doe import validate_surface_doe
from raywave.io.errors import LensFileError, suggestion
from raywave.utils.checks import MAX_FIELD_ANGLE, MAX_WAVELENGTH_UM, MAX_WIDE_FIELD_ANGLE, wavelength_problem as _wavelength_problem

FORMAT_NAME = "raywave-lens"
FORMAT_VERSION = 1
UNITS = {"length": "mm", "wavelength": "um"}

TOP_KEYS = ("format", "version", "units", "name", "description", "catalogs", "object", "system_aperture",
            "fields", "wavelengths", "sensor", "surfaces", "doe", "image")
SURFACE_TYPES = ("standard", "even_asphere", "odd_asphere", "toroidal", "paraxial", "coordinate_break")
#: The keys of a coordinate break (it has no shape, medium, aperture or stop).
COORDINATE_BREAK_KEYS = ("type", "thickness", "decenter", "tilt", "order", "comment")
#: The material string of a reflecting surface (Zemax GLAS MIRROR): the medium after it is the one before it.
MIRROR = "mirror"
COMMON_SURFACE_KEYS = ("type", "thickness", "material", "aperture", "semi_diameter", "stop", "comment", "doe")
TYPE_KEYS = {
    "standard": ("radius", "curvature", "conic"),
    "even_asphere": ("radius", "curvature", "conic", "aspheric"),
    "odd_asphere": ("radius", "curvature", "conic", "aspheric"),
    "toroidal": ("radius", "curvature", "conic", "radius_of_rotation", "aspheric"),
    "paraxial": ("focal_length",),
    "coordinate_break": ("decenter", "tilt", "order"),
}
ALL_SURFACE_KEYS = tuple(dict.fromkeys(COMMON_SURFACE_KEYS + sum(TYPE_KEYS.values(), ())))
ASPHERIC_KEYS = tuple(f"a{p}" for p in range(2, 21, 2))
#: The "aspheric" keys of each surface type: a_p multiplies r^p (toroidal: y^p, on the y–z curve).
ASPHERIC_KEYS_BY_TYPE = {  # up to the 240 terms of an OpticStudio extended asphere (XASPHERE / XOSPHERE)
    "even_asphere": tuple(f"a{p}" for p in range(2, 481, 2)),
    "odd_asphere": tuple(f"a{p}" for p in range(1, 241)),
    "toroidal": tuple(f"a{p}" for p in range(2, 15, 2)),
}
FIELD_TYPES = ("angle", "object_height", "paraxial_image_height", "real_image_height")
APERTURE_SHAPES = {"circle": "radius", "square": "half_width", "rectangle": ("half_width_x", "half_width_y")}
#: Central obscuration shapes (an aperture's "obscuration" entry) and their size keys (mm).
OBSCURATION_SHAPES = {"circle": ("radius",), "rectangle": ("half_width_x", "half_width_y"),
                      "annulus": ("inner_radius", "radius")}
#: System aperture types (one per lens; the key of the "system_aperture" object) and what their value is.
SYSTEM_APERTURE_TYPES = {
    "epd": "entrance pupil diameter, mm",
    "f_number": "image-space F/#: |EFL| / EPD",
    "working_f_number": "paraxial working F/#: 1 / (2 n' |u'|) of the paraxial marginal ray in image space",
    "object_na": "object-space NA n sin(theta) of the marginal ray (finite object)",
    "object_cone_angle": "object-space marginal ray half-angle theta in degrees (finite object)",
    "float_by_stop_size": "true: the stop's own aperture sets the pupil",
}


# --------------------------------------------------------------------------------------- locating keys
_WS = re.compile(r"[ \t\n\r]*")
_LITERALS = ("true", "false", "null", "NaN", "Infinity", "-Infinity")


def locate_keys(text: str) -> tuple[dict, list]:
    """Line numbers of every key and array element of a JSON text that ``json.loads`` accepts.

    Returns ``(lines, duplicates)``: ``lines`` maps a key path (tuple of str keys and int indices) to the
    1-based line where that key (or array element) starts; ``duplicates`` lists ``(path, line)`` of keys
    that occur twice in the same object.
    """
    loc = _KeyLocator(text)
    loc.value(0, ())
    return loc.lines, loc.dups


class _KeyLocator:
    """A walk over a JSON text that ``json.loads`` accepted, noting where each key and array element starts
    (``lines``: key path -> 1-based line) and the keys that repeat in one object (``dups``: ``(path, line)``)."""

    def __init__(self, text: str):
        self.text = text
        self.starts = [0] + [m.end() for m in re.finditer("\n", text)]
        self.lines: dict = {}
        self.dups: list = []

    def line_of(self, pos) -> int:
        """The 1-based line of character offset ``pos``."""
        return bisect.bisect_right(self.starts, pos)

    def ws(self, i) -> int:
        """The offset of the first non-whitespace character at or after ``i``."""
        return _WS.match(self.text, i).end()

    def value(self, i, path) -> int:
        """Walk the value at offset ``i`` (key path ``path``); return the offset just after it.

        One Python frame per nesting level, as :func:`json.loads` allows (the helpers return before recursing)."""
        text = self.text
        i = self.ws(i)
        self.lines.setdefault(path, self.line_of(i))
        c = text[i]
        if c == "{":
            i = self.ws(i + 1)
            if text[i] == "}":
                return i + 1
            seen: set = set()
            while True:
                kpath, i = self._key(i, path, seen)
                i = self.ws(i)  # the ':'
                i = self.value(i + 1, kpath)
                i = self.ws(i)
                if text[i] == ",":
                    i += 1
                    continue
                return i + 1
        if c == "[":
            i = self.ws(i + 1)
            if text[i] == "]":
                return i + 1
            k = 0
            while True:
                i = self.value(i, path + (k,))
                k += 1
                i = self.ws(i)
                if text[i] == ",":
                    i += 1
                    continue
                return i + 1
        return self._scalar(i)

    def _key(self, i, path, seen: set) -> tuple:
        """Read the object key at (or after whitespace at) offset ``i`` of the object at ``path``, noting its line
        (or, when ``seen`` already holds it, a duplicate); return ``(its key path, the offset after it)``."""
        i = self.ws(i)
        key_line = self.line_of(i)
        key, i = scanstring(self.text, i + 1)
        kpath = path + (key,)
        if key in seen:
            self.dups.append((kpath, key_line))
        else:
            self.lines[kpath] = key_line
        seen.add(key)
        return kpath, i

    def _scalar(self, i) -> int:
        """The offset just after the string, number or literal at offset ``i``."""
        text = self.text
        c = text[i]
        if c == '"':
            return scanstring(text, i + 1)[1]
        m = NUMBER_RE.match(text, i)
        if m:
            return m.end()
        for lit in _LITERALS:
            if text.startswith(lit, i):
                return i + len(lit)
        raise ValueError(f"unexpected character {c!r} at offset {i}")  # json.loads accepted it: cannot happen


def key_path(path) -> str:
    """('surfaces', 3, 'radius') -> 'surfaces[3].radius'."""
    out = ""
    for p in path:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out or "(top level)"


# --------------------------------------------------------------------------------------- validation
def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _typename(x) -> str:
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "a boolean"
    if isinstance(x, (int, float)):
        return f"the number {x!r}"
    if isinstance(x, str):
        return f"the string {x!r}"
    if isinstance(x, list):
        return "a list"
    if isinstance(x, dict):
        return "an object"
    return type(x).__name__


class _Validator:
    def __init__(self, source, lines: dict | None):
        self.source = source
        self.lines = lines or {}
        self.errors: list[tuple[int | None, str]] = []

    def line(self, path):
        path = tuple(path)
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return None

    def err(self, path, msg):
        where = key_path(path)
        self.errors.append((self.line(path), f"{where}: {msg}" if path else msg))

    # ----- generic checks
    def keys(self, obj, path, allowed, misplaced: dict | None = None):
        for k in obj:
            if k in allowed:
                continue
            if misplaced and k in misplaced:
                self.err(tuple(path) + (k,), misplaced[k])
            else:
                self.err(tuple(path) + (k,), f"unknown key {k!r}{suggestion(str(k), allowed)}")

    def obj(self, x, path, what="an object") -> bool:
        if not isinstance(x, dict):
            self.err(path, f"must be {what}, got {_typename(x)}")
            return False
        return True

    def number(self, x, path, positive=False, nonzero=False, nonneg=False) -> bool:
        if not _is_number(x):
            extra = " (write infinity as the string \"inf\")" if isinstance(x, float) and math.isinf(x) else ""
            self.err(path, f"must be a number, got {_typename(x)}{extra}")
            return False
        if positive and not x > 0:
            self.err(path, f"must be > 0, got {x!r}")
            return False
        if nonneg and x < 0:
            self.err(path, f"must be >= 0, got {x!r}")
            return False
        if nonzero and x == 0:
            self.err(path, "must not be 0")
            return False
        return True

    def string(self, x, path, nonempty=False) -> bool:
        if not isinstance(x, str):
            self.err(path, f"must be a string, got {_typename(x)}")
            return False
        if nonempty and not x.strip():
            self.err(path, "must not be empty")
            return False
        return True

    def number_list(self, x, path, n=None, positive=False, integer=False) -> bool:
        if not isinstance(x, list):
            self.err(path, f"must be a list, got {_typename(x)}")
            return False
        if n is not None and len(x) != n:
            self.err(path, f"must have {n} entries, got {len(x)}")
            return False
        if n is None and not x:
            self.err(path, "must not be empty")
            return False
        ok = True
        for i, v in enumerate(x):
            p = tuple(path) + (i,)
            if integer:
                if not _is_int(v) or (positive and v <= 0):
                    self.err(p, f"must be a {'positive ' if positive else ''}integer, got {_typename(v)}")
                    ok = False
            else:
                ok = self.number(v, p, positive=positive) and ok
        return ok

    # ----- the schema
    def spec(self, spec):
        """Check a whole spec: the top-level entries in order, then every surface."""
        if not self.obj(spec, ()):
            return
        self.keys(spec, (), TOP_KEYS)
        self._header(spec)
        for k in ("name", "description"):
            if k in spec:
                self.string(spec[k], (k,))
        if "catalogs" in spec:
            self._catalogs(spec["catalogs"])
        if "object" in spec and self.obj(spec["object"], ("object",)):
            self._object(spec["object"])
        if "system_aperture" in spec and self.obj(spec["system_aperture"], ("system_aperture",)):
            self.system_aperture(spec["system_aperture"], spec)
        if "fields" in spec and self.obj(spec["fields"], ("fields",)):
            obj = spec.get("object") if isinstance(spec.get("object"), dict) else {}
            self._fields(spec["fields"], distant=obj.get("distance", "inf") == "inf")
        if "wavelengths" in spec and self.obj(spec["wavelengths"], ("wavelengths",)):
            self._wavelengths(spec["wavelengths"])
        if "sensor" in spec and self.obj(spec["sensor"], ("sensor",)):
            self._sensor(spec["sensor"])
        if "doe" in spec and spec["doe"] is not None:
            validate_doe(self, spec["doe"], spec)
        if "image" in spec and self.obj(spec["image"], ("image",)):
            self.keys(spec["image"], ("image",), ("curvature",))
            if "curvature" in spec["image"]:
                self.number(spec["image"]["curvature"], ("image", "curvature"))
        self._surfaces(spec)

    def _header(self, spec):
        """Check "format", "version" and "units" (when present) of a spec (a dict)."""
        if "format" in spec and spec["format"] != FORMAT_NAME:
            self.err(("format",), f"must be {FORMAT_NAME!r}, got {_typename(spec['format'])}")
        if "version" in spec:
            v = spec["version"]
            if not _is_int(v):
                self.err(("version",), f"must be an integer, got {_typename(v)}")
            elif v > FORMAT_VERSION:
                self.err(("version",), f"format version {v} is newer than this raywave reads "
                                       f"(version {FORMAT_VERSION}); upgrade raywave")
            elif v < 1:
                self.err(("version",), f"must be >= 1, got {v}")
        if "units" in spec and self.obj(spec["units"], ("units",)):
            u = spec["units"]
            self.keys(u, ("units",), tuple(UNITS))
            for k, want in UNITS.items():
                if k in u and u[k] != want:
                    self.err(("units", k), f"must be {want!r} (the only {k} unit of format version 1), "
                                           f"got {_typename(u[k])}")

    def _catalogs(self, c):
        """Check "catalogs": a list of non-empty catalog names."""
        if not isinstance(c, list):
            self.err(("catalogs",), f"must be a list of catalog names, got {_typename(c)}")
        else:
            for i, name in enumerate(c):
                self.string(name, ("catalogs", i), nonempty=True)

    def _object(self, o):
        """Check "object" (a dict): its "distance", mm > 0 or "inf"; its medium "material" (default air) and the
        "curvature" (1/mm) of a curved object surface."""
        self.keys(o, ("object",), ("distance", "material", "curvature"))
        if "material" in o:
            self.material(o["material"], ("object", "material"))
        if "curvature" in o:
            self.number(o["curvature"], ("object", "curvature"))
        if "distance" in o:
            d = o["distance"]
            if d != "inf":
                if isinstance(d, str):
                    self.err(("object", "distance"), f"must be a number or \"inf\", got {_typename(d)}")
                else:
                    self.number(d, ("object", "distance"), positive=True)

    def _fields(self, f, distant: bool = True):
        """Check "fields" (a dict): its type and values (angles in degrees within ±MAX_FIELD_ANGLE, or within ±180°
        for an object at infinity (``distant``): a fisheye's field seen from behind the first vertex)."""
        self.keys(f, ("fields",), ("type", "values"))
        if "type" in f and f["type"] not in FIELD_TYPES:
            self.err(("fields", "type"), f"must be one of {', '.join(map(repr, FIELD_TYPES))}, got "
                                         f"{_typename(f['type'])}"
                     + (suggestion(f["type"], FIELD_TYPES) if isinstance(f["type"], str) else ""))
        if "values" not in f:
            self.err(("fields",), "missing 'values'")
        elif self.number_list(f["values"], ("fields", "values")) and f.get("type", "angle") == "angle":
            limit = MAX_WIDE_FIELD_ANGLE if distant else MAX_FIELD_ANGLE
            for i, v in enumerate(f["values"]):
                if not abs(v) < limit:
                    self.err(("fields", "values", i), f"field angle {v!r}° must lie between -{limit:g}° and "
                                                      f"{limit:g}°" + ("" if distant else
                                                                       " (beyond 90° only for an object at infinity)"))

    def _wavelengths(self, w):
        """Check "wavelengths" (a dict): values in µm (not nm) and the 0-based "primary" index."""
        self.keys(w, ("wavelengths",), ("values", "primary"))
        if "values" not in w:
            self.err(("wavelengths",), "missing 'values' (µm)")
        elif self.number_list(w["values"], ("wavelengths", "values"), positive=True):
            for i, v in enumerate(w["values"]):
                if v > MAX_WAVELENGTH_UM:  # the one wavelength check's message (nm named)
                    self.err(("wavelengths", "values", i), _wavelength_problem(v))
            if "primary" in w:
                p = w["primary"]
                if not _is_int(p):
                    self.err(("wavelengths", "primary"), f"must be an integer index, got {_typename(p)}")
                elif not 0 <= p < len(w["values"]):
                    self.err(("wavelengths", "primary"),
                             f"index {p} out of range for {len(w['values'])} wavelengths (0-based)")

    def _sensor(self, s):
        """Check "sensor" (a dict): "size" [width, height] mm and the optional pixel "resolution"."""
        self.keys(s, ("sensor",), ("size", "resolution"))
        if "size" not in s:
            self.err(("sensor",), "missing 'size' ([width, height] mm)")
        else:
            self.number_list(s["size"], ("sensor", "size"), n=2, positive=True)
        if "resolution" in s:
            self.number_list(s["resolution"], ("sensor", "resolution"), n=2, positive=True, integer=True)

    def _surfaces(self, spec):
        """Check "surfaces" of a spec (a dict): a non-empty list of surfaces with at most one stop."""
        if "surfaces" not in spec:
            self.err((), "missing 'surfaces' (the list of surfaces)")
            return
        surfs = spec["surfaces"]
        if not isinstance(surfs, list):
            self.err(("surfaces",), f"must be a list, got {_typename(surfs)}")
            return
        if not surfs:
            self.err(("surfaces",), "the lens has no surfaces (empty list)")
            return
        stops = []
        for i, s in enumerate(surfs):
            self.surface(s, ("surfaces", i))
            if isinstance(s, dict) and s.get("stop") is True:
                stops.append(i)
        if len(stops) > 1:
            for i in stops[1:]:
                self.err(("surfaces", i, "stop"), f"a lens has one aperture stop; surfaces {stops} are all "
                                                  "marked as stop")

    def system_aperture(self, a, spec):
        path = ("system_aperture",)
        self.keys(a, path, tuple(SYSTEM_APERTURE_TYPES))
        given = [k for k in SYSTEM_APERTURE_TYPES if k in a]
        if not given:
            self.err(path, "needs one of " + ", ".join(f"{k!r} ({v})" for k, v in SYSTEM_APERTURE_TYPES.items()))
            return
        if len(given) > 1:
            self.err(path, f"give exactly one system aperture type, got {', '.join(map(repr, given))}")
            return
        key = given[0]
        v = a[key]
        if key == "float_by_stop_size":
            if v is not True:
                self.err(path + (key,), f"must be true (the stop's own aperture sets the pupil), got {_typename(v)}")
            return
        if not self.number(v, path + (key,), positive=True):
            return
        if key == "object_na" and not v < 1.0:
            self.err(path + (key,), f"an object-space NA in air must be < 1, got {v!r}")
        if key == "object_cone_angle" and not v < 90.0:
            self.err(path + (key,), f"the object cone half-angle must be < 90 degrees, got {v!r}")
        if key in ("object_na", "object_cone_angle"):
            d = (spec.get("object") or {}).get("distance", "inf") if isinstance(spec.get("object"), dict) else "inf"
            if d == "inf":
                self.err(path + (key,), f"{key!r} needs an object at a finite distance (object.distance), got "
                                        "\"inf\" (use 'epd' or 'f_number' for a distant object)")

    def surface(self, s, path):
        """Check one entry of "surfaces" (a surface or a coordinate break) at key path ``path``."""
        if not self.obj(s, path):
            return
        kind = s.get("type", "standard")
        if kind not in SURFACE_TYPES:
            hint = suggestion(kind, SURFACE_TYPES) if isinstance(kind, str) else ""
            self.err(path + ("type",), f"unknown surface type {kind!r}{hint}; known types: "
                                       f"{', '.join(SURFACE_TYPES)}")
            self.keys(s, path, ALL_SURFACE_KEYS)
            return
        if kind == "coordinate_break":
            self.coordinate_break(s, path)
            return
        allowed = COMMON_SURFACE_KEYS + TYPE_KEYS[kind]
        misplaced = {k: f"{k!r} is not allowed on a {kind!r} surface (it belongs to "
                        f"{' / '.join(t for t, ks in TYPE_KEYS.items() if k in ks)} surfaces)"
                     for k in ALL_SURFACE_KEYS if k not in allowed}
        self.keys(s, path, allowed, misplaced)
        if "thickness" not in s:
            self.err(path, "missing 'thickness' (mm to the next surface, or to the image for the last one)")
        else:
            self.number(s["thickness"], path + ("thickness",))
        self._surface_shape(s, path, kind)
        self._surface_medium(s, path, kind)
        if "doe" in s:  # a DOE plane inside the lens (issue 46)
            validate_surface_doe(self, s, path)

    def _surface_shape(self, s, path, kind):
        """Check the shape keys of a (non-break) surface ``s`` of type ``kind``: radius or curvature, radius of
        rotation, conic, aspheric terms, paraxial focal length (mm)."""
        if "radius" in s and "curvature" in s:
            self.err(path + ("curvature",), "give either 'radius' or 'curvature', not both")
        if "radius" in s:
            r = s["radius"]
            if r != "inf":
                if isinstance(r, str):
                    self.err(path + ("radius",), f"must be a number or \"inf\", got {_typename(r)}")
                elif self.number(r, path + ("radius",)) and r == 0:
                    self.err(path + ("radius",), "radius 0 is not a surface; write \"inf\" for a flat surface")
        if "curvature" in s:
            self.number(s["curvature"], path + ("curvature",))
        if "radius_of_rotation" in s:
            r = s["radius_of_rotation"]
            if r != "inf":
                if isinstance(r, str):
                    self.err(path + ("radius_of_rotation",), f"must be a number or \"inf\", got {_typename(r)}")
                elif self.number(r, path + ("radius_of_rotation",)) and r == 0:
                    self.err(path + ("radius_of_rotation",), "0 is not a radius; write \"inf\" for a cylinder (no "
                                                             "power in x)")
        if "conic" in s:
            self.number(s["conic"], path + ("conic",))
        if "aspheric" in s and self.obj(s["aspheric"], path + ("aspheric",)):
            a = s["aspheric"]
            keys = ASPHERIC_KEYS_BY_TYPE.get(kind, ASPHERIC_KEYS)
            self.keys(a, path + ("aspheric",), keys)
            for k in keys:
                if k in a:
                    self.number(a[k], path + ("aspheric", k))
        if kind == "paraxial":
            if "focal_length" not in s:
                self.err(path, "a paraxial surface needs 'focal_length' (mm)")
            else:
                self.number(s["focal_length"], path + ("focal_length",), nonzero=True)

    def _surface_medium(self, s, path, kind):
        """Check the rest of a (non-break) surface ``s`` of type ``kind``: material, aperture, semi-diameter
        (mm), stop flag, comment."""
        if "material" in s:
            self.material(s["material"], path + ("material",))
            if kind == "paraxial" and isinstance(s["material"], str) and s["material"].lower() == MIRROR:
                self.err(path + ("material",), "a paraxial (ideal lens) surface cannot be a mirror")
        if "aperture" in s:
            self.aperture(s["aperture"], path + ("aperture",))
            if s.get("stop") is True and isinstance(s["aperture"], dict) and s["aperture"].get("shape") == "none":
                self.err(path + ("aperture", "shape"), "the stop needs a clear aperture ('circle' or 'square', "
                                                       "with the obscuration), not 'none'")
        if "semi_diameter" in s and s["semi_diameter"] is not None:
            self.number(s["semi_diameter"], path + ("semi_diameter",), positive=True)
        if "stop" in s and not isinstance(s["stop"], bool):
            self.err(path + ("stop",), f"must be true or false, got {_typename(s['stop'])}")
        if "comment" in s:
            self.string(s["comment"], path + ("comment",))

    def coordinate_break(self, s, path):
        misplaced = {k: f"{k!r} is not allowed on a coordinate break (it has no shape, medium, aperture or stop)"
                     for k in ALL_SURFACE_KEYS if k not in COORDINATE_BREAK_KEYS}
        self.keys(s, path, COORDINATE_BREAK_KEYS, misplaced)
        if "thickness" not in s:
            self.err(path, "missing 'thickness' (mm along the new local z to the next surface)")
        else:
            self.number(s["thickness"], path + ("thickness",))
        if "decenter" in s:
            self.number_list(s["decenter"], path + ("decenter",), n=2)
        if "tilt" in s:
            self.number_list(s["tilt"], path + ("tilt",), n=3)
        if "order" in s and s["order"] not in (0, 1):
            self.err(path + ("order",), f"must be 0 (decentre, then tilt x, y, z) or 1 (tilt z, y, x, then "
                                        f"decentre), got {s['order']!r}")
        if "comment" in s:
            self.string(s["comment"], path + ("comment",))

    def material(self, m, path):
        if isinstance(m, str):
            self.string(m, path, nonempty=True)
            return
        if not isinstance(m, dict):
            self.err(path, f"must be a glass name or an object ({{\"index\": n}}, {{\"model\": {{\"nd\": .., "
                           f"\"vd\": ..}}}} or {{\"name\": .., \"catalog\": ..}}), got {_typename(m)}")
            return
        forms = (("index",), ("model",), ("name", "catalog"), ("name",))
        if "index" in m:
            self.keys(m, path, ("index",))
            self.number(m["index"], path + ("index",), positive=True)
        elif "model" in m:
            self.keys(m, path, ("model",))
            if self.obj(m["model"], path + ("model",)):
                md = m["model"]
                self.keys(md, path + ("model",), ("nd", "vd"))
                for k in ("nd", "vd"):
                    if k not in md:
                        self.err(path + ("model",), f"a model glass needs {k!r}")
                if "nd" in md:
                    self.number(md["nd"], path + ("model", "nd"), positive=True)
                if "vd" in md:
                    self.number(md["vd"], path + ("model", "vd"), positive=True)
        elif "name" in m:
            self.keys(m, path, ("name", "catalog"))
            self.string(m["name"], path + ("name",), nonempty=True)
            if "catalog" in m:
                self.string(m["catalog"], path + ("catalog",), nonempty=True)
        else:
            allowed = sorted({k for f in forms for k in f})
            if not m:
                self.err(path, "empty material object; expected \"index\", \"model\" or \"name\"")
            self.keys(m, path, allowed)

    def aperture(self, a, path):
        if a is None:
            return
        if not self.obj(a, path, what="null or an object {\"shape\": ...}"):
            return
        shape = a.get("shape")
        shapes = tuple(APERTURE_SHAPES) + ("none",)
        if not isinstance(shape, str) or shape not in shapes:
            hint = suggestion(shape, shapes) if isinstance(shape, str) else ""
            self.err(path + ("shape",) if "shape" in a else path,
                     f"aperture shape must be 'circle', 'square', 'rectangle' or 'none' (an obscuration alone), "
                     f"got {_typename(shape)}{hint}")
            return
        if shape == "none":
            misplaced = {k: f"{k!r} belongs to a {s!r} aperture; a 'none' aperture has only an obscuration"
                         for s, ks in APERTURE_SHAPES.items() for k in _size_keys(ks)}
            misplaced["decenter"] = "a 'none' aperture has no centre: give the decenter to its obscuration"
            self.keys(a, path, ("shape", "obscuration"), misplaced)
            if a.get("obscuration") is None:
                self.err(path, "a 'none' aperture needs an \"obscuration\" (else write the aperture as null)")
            else:
                self.obscuration(a["obscuration"], path + ("obscuration",), None)
            return
        size_keys = _size_keys(APERTURE_SHAPES[shape])
        misplaced = {k: f"{k!r} belongs to a {s!r} aperture, not a {shape!r} one"
                     for s, ks in APERTURE_SHAPES.items() if s != shape for k in _size_keys(ks) if k not in size_keys}
        if shape != "circle":
            misplaced["fixed"] = "'fixed' belongs to a 'circle' aperture (a stop's own clear aperture)"
        self.keys(a, path, ("shape", "decenter", "obscuration") + size_keys + (("fixed",) if shape == "circle" else ()),
                  misplaced)
        if "fixed" in a and not isinstance(a["fixed"], bool):
            self.err(path + ("fixed",), f"'fixed' must be true or false, got {_typename(a['fixed'])}")
        v = None
        for size_key in size_keys:
            if size_key not in a:
                self.err(path, f"a {shape} aperture needs {size_key!r} (mm)")
                return
            v = a[size_key]
            if self.number(v, path + (size_key,)) and not v > 0:
                self.err(path + (size_key,), f"empty aperture: {size_key} must be > 0 mm, got {v!r}")
                return
        if "decenter" in a and not self.number_list(a["decenter"], path + ("decenter",), n=2):
            return
        if a.get("obscuration") is not None:
            self.obscuration(a["obscuration"], path + ("obscuration",),
                             v if shape == "circle" and _is_number(v) else None)

    def obscuration(self, o, path, clear_radius):
        """An obscuration: {"shape": "circle", "radius": r}, {"shape": "rectangle", "half_width_x": ..,
        "half_width_y": ..} or {"shape": "annulus", "inner_radius": .., "radius": ..} (a ring), each with an
        optional "decenter": [dx, dy] (mm, about the aperture's centre)."""
        if not self.obj(o, path, what="an object {\"shape\": \"circle\", \"radius\": r} or a rectangle"):
            return
        shape = o.get("shape", "circle")
        if not isinstance(shape, str) or shape not in OBSCURATION_SHAPES:
            hint = suggestion(shape, OBSCURATION_SHAPES) if isinstance(shape, str) else ""
            self.err(path + ("shape",), f"obscuration shape must be 'circle', 'rectangle' or 'annulus', got "
                                        f"{_typename(shape)}{hint}")
            return
        size_keys = OBSCURATION_SHAPES[shape]
        misplaced: dict = {}
        for s, ks in OBSCURATION_SHAPES.items():  # a key of two shapes (radius) is named by the first
            for k in ks:
                if s != shape and k not in size_keys:
                    misplaced.setdefault(k, f"{k!r} belongs to a {s!r} obscuration, not a {shape!r} one")
        self.keys(o, path, ("shape", "decenter") + size_keys, misplaced)
        ok = True
        for k in size_keys:
            if k not in o:
                self.err(path, f"a {shape} obscuration needs {k!r} (mm)")
                ok = False
            elif not self.number(o[k], path + (k,), positive=True):
                ok = False
        if "decenter" in o and not self.number_list(o["decenter"], path + ("decenter",), n=2):
            ok = False
        if ok and shape == "annulus" and not o["inner_radius"] < o["radius"]:
            self.err(path + ("inner_radius",), f"an annular obscuration's inner_radius ({o['inner_radius']!r} mm) "
                                               f"must be < its radius ({o['radius']!r} mm)")
        if ok and shape == "circle" and clear_radius is not None:
            d = o.get("decenter", [0.0, 0.0])
            if not any(d) and o["radius"] >= clear_radius:
                self.err(path + ("radius",), f"the obscuration (radius {o['radius']!r} mm) covers the whole "
                                             f"clear aperture (radius {clear_radius!r} mm)")


def _size_keys(keys) -> tuple:
    """An aperture shape's size key(s) as a tuple."""
    return (keys,) if isinstance(keys, str) else tuple(keys)


def validate_spec(spec, source="<spec>", lines: dict | None = None) -> dict:
    """Check ``spec`` against the lens format (docs/lens-format.md); return it unchanged.

    Raises :class:`LensFileError` listing every problem, each as ``source:line: key.path: message``
    (the line only when ``lines``, a map from key path to line as made by :func:`locate_keys`, is given).
    """
    v = _Validator(source, lines)
    v.spec(spec)
    if v.errors:
        raise LensFileError.collect(v.errors, source)
    return spec


# --------------------------------------------------------------------------------------- read / write
def _reject_constant(name):
    raise ValueError(f"{name} is not a valid JSON number (write infinity as the string \"inf\")")


def parse_json_text(text: str, source) -> tuple[object, dict]:
    """Parse JSON text -> (data, key lines); syntax errors become :class:`LensFileError` with line/column."""
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as e:
        raise LensFileError(f"invalid JSON: {e.msg}", source, e.lineno, e.colno) from None
    except ValueError as e:  # NaN / Infinity
        m = re.search(r"(?<![\w\"])(-?Infinity|NaN)(?![\w\"])", text)
        line = text.count("\n", 0, m.start()) + 1 if m else None
        raise LensFileError(f"invalid JSON: {e}", source, line) from None
    lines, dups = locate_keys(text)
    if dups:
        raise LensFileError.collect([(ln, f"{key_path(p)}: duplicate key {p[-1]!r}") for p, ln in dups], source)
    return data, lines


def read_text(path) -> str:
    """A text file as str (UTF-8, with or without BOM); decoding errors become :class:`LensFileError`."""
    raw = Path(path).read_bytes()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise LensFileError(f"not UTF-8 text ({e.reason} at byte {e.start})", path, line) from None


def read_json_spec(path) -> dict:
    """Read and strictly validate a raywave JSON lens file; return its spec dict.

    Raises :class:`LensFileError` (``path:line: message``) on invalid JSON, on a file that is not a
    raywave lens file, and on any schema violation (unknown keys, with a suggestion; wrong types; ranges).
    """
    path = str(path)
    data, lines = parse_json_text(read_text(path), path)
    if not isinstance(data, dict):
        raise LensFileError(f"a lens file must hold a JSON object, got {_typename(data)}", path, 1)
    if "format" not in data:
        raise LensFileError(f"missing \"format\": {FORMAT_NAME!r} (not a raywave lens file; DeepLens files "
                            "are read by raywave.io.read_lens_spec / read_deeplens)", path, 1)
    validate_spec(data, path, lines)
    check_doe_files(data, path, lines)  # the phase map file: exists, 2-D, shape (read in full when built)
    return data


def with_header(spec: dict) -> dict:
    """``spec`` with "format", "version" and "units" first (added when missing)."""
    out = {"format": spec.get("format", FORMAT_NAME), "version": spec.get("version", FORMAT_VERSION),
           "units": spec.get("units", dict(UNITS))}
    out.update((k, v) for k, v in spec.items() if k not in out)
    return out


def dumps_spec(spec: dict) -> str:
    """The JSON text :func:`write_json_spec` writes (floats by repr, so they read back identical)."""
    return json.dumps(with_header(spec), indent=2, ensure_ascii=False, allow_nan=False) + "\n"


def write_json_spec(spec: dict, path) -> None:
    """Validate ``spec`` and write it as indented UTF-8 JSON that :func:`read_json_spec` reads back equal.

    "format", "version" and "units" are added in front when missing. Floats are written with ``repr``
    (shortest exact form), so every number round-trips bit for bit; infinity stays the string "inf".
    """
    validate_spec(spec, str(path))
    text = dumps_spec(spec)
    Path(path).write_text(text, encoding="utf-8")
