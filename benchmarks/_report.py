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
