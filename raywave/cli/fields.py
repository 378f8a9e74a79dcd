"""One field syntax for the analysis commands: ``--field`` repeated, each ``Y`` or ``X,Y`` (degrees, or mm of
object height, as the lens's fields), e.g. ``--field 0 --field 0,14``; without any, the lens's own fields along y."""

from __future__ import annotations

from raywave.cli.errors import CommandError, number_arg


def parse_field(text: str, flag: str = "--field") -> tuple[float, float]:
    """``"Y"`` → (0, Y); ``"X,Y"`` (or ``"X Y"``) → (X, Y); anything else a one-line :class:`CommandError`."""
    parts = str(text).replace(",", " ").split()
    if len(parts) == 1:
        return 0.0, number_arg(parts[0], flag)
    if len(parts) == 2:
        return number_arg(parts[0], flag), number_arg(parts[1], flag)
    raise CommandError(f"{flag}: {text!r} is not a field point: give Y or X,Y (e.g. {flag} 14 or {flag} 0,14)")


def field_points(values, lens, flag: str = "--field") -> list[tuple[float, float]]:
    """The field points of repeated ``flag`` values (a list of strings, or None: the lens's fields along y)."""
    if not values:
        return [(0.0, float(f)) for f in lens.fields]
    return [parse_field(v, flag) for v in values]


def add_field_argument(parser, what: str = "field point") -> None:
    """``--field`` (repeatable) on ``parser``."""
    parser.add_argument("--field", action="append", default=None, metavar="[X,]Y",
                        help=f"{what}: Y or X,Y (degrees, or mm of object height, as the lens's fields); repeat for "
                             "several (default: the lens's fields along y)")
