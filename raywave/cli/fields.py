"""The one field syntax of every command: ``--field Y`` or ``--field X,Y`` (repeatable) or the list form
``--fields Y|X,Y ...``.

    raywave psf hybrid_asphere --field 0,14            one field, X = 0, Y = 14
    raywave compare hybrid_asphere --field 0 --field 7 --field 0,14
    raywave spot cooke_triplet --fields 0 14 0,20      three fields (Y, Y, X,Y)

Values are the lens's field unit (degrees for angles, mm for object heights). The older forms stay accepted where
they are unambiguous: ``psf --field X Y`` (two plain numbers after one ``--field``: one field X, Y),
``compare --fields 0 7 0,14`` (the list form itself) and ``layout/spot --fields '0,10,14'`` (one token of three or
more comma-separated numbers: that many Y values). A single ``--fields A,B`` token is the field X = A, Y = B (the
documented syntax); the note printed then says how to ask for two fields instead.

A negative first value must be attached: ``--field=-5,0`` (argparse reads ``-5,0`` as an option otherwise).
"""

from __future__ import annotations

import sys

from raywave.cli.errors import CommandError, number_arg

__all__ = ["FIELD_HELP", "add_field_argument", "add_field_arguments", "check_angles", "field_points", "field_list", "parse_field_groups", "parse_field_list",
           "parse_field_token", "single_field"]

FIELD_HELP = ("field point: Y or X,Y in the lens's field unit (degrees for angles), repeatable "
              "(--field 0 --field 0,14); a negative first value as --field=-5,0")


def _numbers(text: str, flag: str) -> list[float]:
    parts = [p.strip() for p in str(text).split(",")]
    if any(p == "" for p in parts):
        raise CommandError(f"{flag}: {text!r} is not Y or X,Y (an empty value between commas)")
    return [number_arg(p, flag) for p in parts]


def parse_field_token(text: str, flag: str = "--field") -> tuple[float, float]:
    """``"Y"`` -> ``(0, Y)``; ``"X,Y"`` -> ``(X, Y)``; anything else a :class:`CommandError` naming ``flag``."""
    vals = _numbers(text, flag)
    if len(vals) == 1:
        return (0.0, vals[0])
    if len(vals) == 2:
        return (vals[0], vals[1])
    raise CommandError(f"{flag}: {text!r} is not Y or X,Y (give one field per --field, e.g. --field 0 --field 0,14)")


def _tokens(values) -> list[str]:
    """Whitespace inside a token splits it (``--fields "0 10 14"``)."""
    return [t for v in values for t in str(v).split()]


def parse_field_groups(groups, flag: str = "--field") -> list[tuple[float, float]]:
    """The fields of repeated ``--field`` options, each a list of tokens (``nargs="+"``): one token is Y or X,Y;
    two plain numbers are the old ``psf --field X Y``."""
    out = []
    for group in groups:
        toks = _tokens(group)
        if not toks:
            raise CommandError(f"{flag}: give Y or X,Y")
        if len(toks) == 2 and not any("," in t for t in toks):  # the old `psf --field X Y`
            out.append((number_arg(toks[0], flag), number_arg(toks[1], flag)))
        elif len(toks) == 1:
            out.append(parse_field_token(toks[0], flag))
        else:
            raise CommandError(f"{flag}: {' '.join(toks)!r}: give one field per --field, Y or X,Y (e.g. --field 0 "
                               "--field 0,14), or the list form --fields 0 0,14")
    return out


def parse_field_list(values, flag: str = "--fields", legacy_y_list: bool = False) -> list[tuple[float, float]]:
    """The fields of ``--fields`` tokens: each Y or X,Y; with ``legacy_y_list`` (layout, spot) a token of three or
    more comma-separated numbers is the old list of Y values, and one lone ``A,B`` token prints how it was read."""
    toks = _tokens(values)
    if not toks:
        raise CommandError(f"{flag}: no values given")
    out = []
    for t in toks:
        vals = _numbers(t, flag)
        if len(vals) == 1:
            out.append((0.0, vals[0]))
        elif len(vals) == 2:
            out.append((vals[0], vals[1]))
        elif legacy_y_list:
            out.extend((0.0, v) for v in vals)
        else:
            raise CommandError(f"{flag}: {t!r} is not Y or X,Y (separate fields by spaces: --fields 0 7 0,14)")
    if legacy_y_list and len(toks) == 1 and len(_numbers(toks[0], flag)) == 2:
        x, y = out[0]
        print(f"raywave: note: {flag} {toks[0]} is one field X = {x:g}, Y = {y:g}; for two fields give "
              f"--field {x:g} --field {y:g}", file=sys.stderr)
    return out


def add_field_arguments(p, default_help: str = "the lens's fields", legacy_y_list: bool = False) -> None:
    """``--field`` (repeatable, Y or X,Y) and ``--fields`` (the list form) on the sub-parser ``p``;
    ``legacy_y_list``: the command once took ``--fields '0,10,14'`` (read as Y values)."""
    p.add_argument("--field", action="append", nargs="+", default=None, metavar="Y|X,Y",
                   help=f"{FIELD_HELP} (default: {default_help})")
    p.add_argument("--fields", nargs="+", default=None, metavar="Y|X,Y",
                   help="the list form of --field: --fields 0 7 0,14" + (" (also the older '0,10,14': Y values)"
                                                                        if legacy_y_list else ""))
    p.set_defaults(_legacy_y_list=legacy_y_list)


def field_list(args, default=None) -> list[tuple[float, float]] | None:
    """Every field of ``--field`` and ``--fields`` (in that order) as ``(x, y)`` tuples, or ``default`` when
    neither is given."""
    groups = getattr(args, "field", None)
    lst = getattr(args, "fields", None)
    if not groups and not lst:
        return default
    out = parse_field_groups(groups) if groups else []
    if lst:
        out += parse_field_list(lst, legacy_y_list=getattr(args, "_legacy_y_list", False))
    return out


def single_field(args, default=(0.0, 0.0), command: str = "this command") -> tuple[float, float]:
    """The one field of a command that computes one (``psf``, ``doe report``): :func:`field_list`, refused when it
    holds more than one field."""
    fields = field_list(args)
    if fields is None:
        return tuple(default)
    if len(fields) != 1:
        raise CommandError(f"--field: {command} takes one field, got {len(fields)}: "
                           + ", ".join(f"({x:g}, {y:g})" for x, y in fields))
    return fields[0]


def check_angles(fields, flag: str = "--field") -> None:
    """Field angles (degrees) for the ray-wave engine (psf, compare, doe) must lie within (-90, 90): it samples the
    entrance-pupil plane. A :class:`CommandError` naming ``flag`` and saying where a wider field is traced otherwise
    (a fisheye's field beyond 90°, up to 180° for an object at infinity: the geometric analyses info, spot, layout)."""
    for f in fields:
        if any(abs(v) >= 90 for v in f):
            raise CommandError(f"{flag}: angles must lie within (-90, 90) degrees for the ray-wave engine, got "
                               f"({f[0]:g}, {f[1]:g}); a fisheye's field beyond 90° (object at infinity, below 180°) "
                               "is traced by the geometric analyses (info, spot, layout)")


def add_field_argument(parser, what: str = "field point") -> None:
    """``--field`` (repeatable) and ``--fields`` on an analysis command's parser (:func:`add_field_arguments`,
    defaulting to the lens's own fields along y)."""
    add_field_arguments(parser, default_help=f"{what}: the lens's fields along y")


def field_points(args, lens) -> list[tuple[float, float]]:
    """The field points of ``--field`` / ``--fields`` (:func:`field_list`), or the lens's own fields along y."""
    return field_list(args, default=[(0.0, float(f)) for f in lens.fields])
