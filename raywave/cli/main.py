"""Entry point of the ``raywave`` command."""

from __future__ import annotations

import argparse
import os
import sys

from raywave.cli import analysis_commands, compare_commands, doe_commands, imaging_commands, lens_commands, psf_commands
from raywave.cli import train_commands
from raywave.cli.errors import CommandError
from raywave.utils.errors import MEMORY_LIMIT_ENV

__all__ = ["COMMAND_MODULES", "CommandError", "build_parser", "main"]

#: Modules that add sub-commands: each has ``register(subparsers)``.
COMMAND_MODULES = [lens_commands, analysis_commands, psf_commands, doe_commands, imaging_commands, compare_commands,
                   train_commands]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="raywave",
        description="End-to-end design of hybrid refractive-diffractive lenses (differentiable ray-wave model). "
        "Lengths in mm, wavelengths in µm.",
    )
    parser.add_argument("--traceback", action="store_true", help="show the full traceback on errors")
    parser.add_argument("--quiet", dest="quiet_global", action="store_true",
                        help="no progress bars (every command; also accepted after the command name)")
    parser.add_argument("--memory-limit", default=None, metavar="SIZE",
                        help="refuse work whose memory estimate exceeds SIZE (e.g. 8G, 512M; default: the memory "
                             f"available; also the environment variable {MEMORY_LIMIT_ENV})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    for p in _leaf_parsers(sub):
        if not any("--quiet" in a.option_strings for a in p._actions):
            p.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def _leaf_parsers(sub) -> list:
    """Every command's parser (nested sub-commands such as ``doe export`` included)."""
    out = []
    for p in dict.fromkeys(sub.choices.values()):
        nested = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        out += [q for n in nested for q in _leaf_parsers(n)] if nested else [p]
    return out


def _memory_limit(text):
    """Validate ``--memory-limit`` and return the environment change it needs (restored after the command)."""
    from raywave.utils.errors import parse_bytes

    try:
        return str(parse_bytes(text))
    except ValueError as e:
        raise CommandError(f"--memory-limit: {e}") from None


def main(argv=None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 user error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.quiet = bool(getattr(args, "quiet", False) or args.quiet_global)
    saved = os.environ.get(MEMORY_LIMIT_ENV)
    try:
        if args.memory_limit is not None:
            os.environ[MEMORY_LIMIT_ENV] = _memory_limit(args.memory_limit)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("raywave: interrupted", file=sys.stderr)
        return 130
    except (CommandError, ValueError, FileNotFoundError, LookupError, OSError) as err:
        if args.traceback:
            raise
        print(f"raywave: error: {err}", file=sys.stderr)
        return 2
    finally:
        if args.memory_limit is not None:  # one command's limit (main() may be called again in-process)
            if saved is None:
                os.environ.pop(MEMORY_LIMIT_ENV, None)
            else:
                os.environ[MEMORY_LIMIT_ENV] = saved


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
