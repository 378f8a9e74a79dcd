"""Every ```python snippet in README.md and docs/*.md runs (issue 17): the docs show the public API as it is.

The snippets of one file run in order in one namespace (a later snippet may use an earlier one's names), in a
temporary working directory. A snippet whose first line is a marker comment is treated specially:

* ``# snippet: skip (reason)`` — never run (a fragment of a larger program, or it needs data or a GPU);
* ``# snippet: slow (reason)`` — run only in the slow suite (``pytest -m slow``).

An unmarked snippet that fails is a doc bug (or an API break)."""

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MARKER = re.compile(r"^#\s*snippet:\s*(skip|slow)\b(.*)$")


def snippets(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, code, marker) of every ```python block of ``path``."""
    out, block, start = [], None, 0
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if block is None and line.strip() == "```python":
            block, start = [], i + 1
        elif block is not None and line.strip() == "```":
            code = "\n".join(block)
            first = block[0].strip() if block else ""
            m = MARKER.match(first)
            out.append((start, code, m.group(1) if m else None))
            block = None
        elif block is not None:
            block.append(line)
    return out


def _params():
    """(file, with the slow snippets): the default suite runs a file's fast snippets, the slow suite all of them."""
    for path in FILES:
        marks = [m for _, _, m in snippets(path)]
        if None in marks:
            yield pytest.param(path, False, id=path.name)
        if "slow" in marks:
            yield pytest.param(path, True, id=f"{path.name}-slow", marks=pytest.mark.slow)


def test_the_snippet_reader_finds_the_docs_snippets():
    assert len(snippets(ROOT / "README.md")) >= 2
    assert sum(len(snippets(p)) for p in FILES) >= 8


@pytest.mark.parametrize("path, run_slow", list(_params()))
def test_doc_snippets_run(path, run_slow, tmp_path, monkeypatch):
    """Run the file's snippets in order (the slow ones only in the slow suite; skipped ones never)."""
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"snippets_of_{path.stem}"}
    for line, code, marker in snippets(path):
        if marker == "skip" or (marker == "slow" and not run_slow):
            continue
        try:
            exec(compile(code, f"{path.name}:{line}", "exec"), namespace)
        except Exception as err:  # noqa: BLE001 - report where in the docs it failed
            raise AssertionError(f"{path.relative_to(ROOT)}, snippet at line {line}: "
                                 f"{type(err).__name__}: {err}") from err
    assert os.getcwd() == str(tmp_path)
