"""Entry point of the ``raywave`` command."""

from __future__ import annotations

import argparse
import sys

from raywave.cli import analysis_commands, compare_commands, doe_commands, imaging_commands, lens_commands, psf_commands
from raywave.cli import train_commands
from raywave.cli.errors import CommandError

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
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


def main(argv=None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 user error)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("raywave: interrupted", file=sys.stderr)
        return 130
    except (CommandError, ValueError, FileNotFoundError, LookupError, OSError) as err:
        if args.traceback:
            raise
        print(f"raywave: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
