"""The JSON report every benchmark ends with: printed, and written to ``-o FILE`` when given."""

from __future__ import annotations

import json


def emit_json(obj, output: str | None = None, indent: int = 2) -> str:
    """Print ``obj`` as indented JSON and write it (with a final newline) to ``output`` if given; returns the text."""
    text = json.dumps(obj, indent=indent)
    print(text)
    if output:
        with open(output, "w") as fh:
            fh.write(text + "\n")
    return text


def emit_row(rows: list, row: dict, output: str | None = None) -> None:
    """A benchmark's streamed row: printed as one JSON line at once, appended to ``rows``, and all rows so far
    rewritten to ``output`` (indented JSON) if given, so an interrupted run keeps what it measured."""
    print(json.dumps(row), flush=True)
    rows.append(row)
    if output:
        with open(output, "w") as fh:
            fh.write(json.dumps(rows, indent=1))
