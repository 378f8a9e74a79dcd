"""Every relative link in the user docs resolves (issue 45, "docs as a product").

README.md, CHANGELOG.md, docs/*.md and docs/notes/*.md are read; for each Markdown link ``[text](target)`` outside
code blocks and code spans whose target is not a URL, the file must exist (relative to the linking file) and an
``#anchor`` must name a heading of the target, slugged as GitHub does. Plain-text mentions of ``docs/….md`` files
must name files that exist. Pure text processing: well under a second."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FILES = [p for p in [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md")),
                     *sorted((ROOT / "docs" / "notes").glob("*.md"))] if p.exists()]
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
MENTION = re.compile(r"(?<![\w/.-])(docs/[\w./-]+\.md)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")


def prose_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the lines outside fenced code blocks, with inline code spans blanked."""
    out, fence = [], None
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        s = line.lstrip()
        if fence is None and (s.startswith("```") or s.startswith("~~~")):
            fence = s[:3]
            continue
        if fence is not None:
            if s.startswith(fence):
                fence = None
            continue
        out.append((i, CODE_SPAN.sub(lambda m: " " * len(m.group(0)), line)))
    return out


def prose_lines_raw(path: Path) -> list[tuple[int, str]]:
    """Lines outside fenced code blocks, code spans kept (headings keep their `code`)."""
    out, fence = [], None
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        s = line.lstrip()
        if fence is None and (s.startswith("```") or s.startswith("~~~")):
            fence = s[:3]
            continue
        if fence is not None:
            if s.startswith(fence):
                fence = None
            continue
        out.append((i, line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: lower case, markup and punctuation dropped (letters, digits, ``-``
    and ``_`` kept, any script), spaces to hyphens."""
    text = re.sub(r"`([^`]*)`", r"\1", heading.strip())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = text.lower()
    text = "".join(ch for ch in text if ch.isalnum() or ch in " -_")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file (duplicates numbered -1, -2, ... as GitHub does)."""
    seen: dict[str, int] = {}
    out = set()
    for _, line in prose_lines_raw(path):
        m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(2))
        n = seen.get(s, 0)
        out.add(s if n == 0 else f"{s}-{n}")
        seen[s] = n + 1
    return out


def links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every Markdown link of ``path`` outside code."""
    return [(i, m.group(1)) for i, line in prose_lines(path) for m in LINK.finditer(line)]


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """Descriptions of the links of ``path`` that do not resolve (paths shown relative to ``root``)."""
    bad = []
    for line, target in links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:, ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = path if not file_part else (path.parent / file_part).resolve()
        where = f"{path.relative_to(root)}:{line}: {target}"
        if not dest.exists():
            bad.append(f"{where} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{where} (no heading #{anchor} in {dest.relative_to(root)})")
    return bad


def test_the_checker_reads_links_and_anchors(tmp_path):
    """The checker itself: a good and a bad file link, a good and a bad anchor, links inside code ignored."""
    (tmp_path / "b.md").write_text("# Top\n\n## Where the stop's edge diffracts (`HybridLens(stop_edge=...)`)\n\n"
                                   "## Top\n", encoding="utf-8")
    a = tmp_path / "a.md"
    a.write_text("[ok](b.md) [ok](b.md#top-1) [ok](b.md#where-the-stops-edge-diffracts-hybridlensstop_edge)\n"
                 "[bad](c.md) [bad](b.md#nowhere) [web](https://example.org/x#y) `[code](d.md)`\n"
                 "```\n[block](e.md)\n```\n", encoding="utf-8")
    found = [t for _, t in links(a)]
    assert found == ["b.md", "b.md#top-1", "b.md#where-the-stops-edge-diffracts-hybridlensstop_edge", "c.md",
                     "b.md#nowhere", "https://example.org/x#y"]
    bad = broken_links(a, root=tmp_path)
    assert len(bad) == 2 and "c.md" in bad[0] and "#nowhere" in bad[1]


def test_the_doc_files_are_found():
    names = {p.name for p in FILES}
    assert {"README.md", "ray-wave.md", "training.md"} <= names


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_and_anchors_resolve(path):
    assert broken_links(path) == []


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_mentioned_doc_files_exist(path):
    """A plain-text ``docs/x.md`` (e.g. "see docs/imaging.md") names a file of the repository."""
    missing = [f"{path.relative_to(ROOT)}:{i}: {m.group(1)}" for i, line in prose_lines_raw(path)
               for m in MENTION.finditer(line) if not (ROOT / m.group(1)).exists()]
    assert missing == []
