"""The ``raywave`` command line (argparse). Each command family lives in its own module and registers
its sub-commands in :func:`raywave.cli.main.build_parser`."""
