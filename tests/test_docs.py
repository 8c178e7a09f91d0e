"""The README and the docs read the same in any clone: every relative link resolves inside the
repository (and its ``#anchor`` to a heading of the page it names), none points at the team's
handouts beside it (``../shared/*.md``), and every decision record the code and docs name exists.
Each decision record decides in under :data:`RECORD_LINES` lines (issue 51): its history is git log's."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

from fleetmap.parameters_doc import COMMAND, render

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
RECORDS = sorted((ROOT / "docs" / "decisions").glob("*.md"))
SOURCES = [
    ROOT / "README.md",
    *(
        p
        for folder in ("agents", "benchmarks", "docs", "merger", "scenarios", "shared", "src", "tests")
        for p in sorted((ROOT / folder).rglob("*"))
        if p.suffix in {".py", ".md", ".toml"}
    ),
]
"""Where a decision record may be named: code, docstrings, benchmarks, tests and docs."""
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$", re.MULTILINE)
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
RECORD_NAMED = re.compile(r"docs/decisions/(\d{3})([-a-z0-9]*\.md)?|\b[Rr]ecords? (\d{3})\b")
RECORD_LINES = 200


def anchors(doc: Path) -> set[str]:
    """The ``#anchors`` of a Markdown file's headings, as GitHub makes them: the heading's text
    (a link's text, no code or emphasis marks) lower-cased, punctuation but ``-`` and ``_``
    dropped, spaces as hyphens; a repeated one numbered ``-1``, ``-2``..."""
    seen: Counter[str] = Counter()
    out = set()
    for title in HEADING.findall(FENCE.sub("", doc.read_text(encoding="utf-8"))):
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title)
        slug = re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")
        out.add(f"{slug}-{seen[slug]}" if seen[slug] else slug)
        seen[slug] += 1
    return out


def broken_links(doc: Path, root: Path = ROOT) -> list[str]:
    """The relative link targets of a Markdown file that name no file or folder of the repository
    (``root``), or a heading its page does not have."""
    out = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue  # a URL
        name, _, anchor = target.partition("#")
        path = (doc.parent / name).resolve() if name else doc
        found = path.exists() and (not name or root in path.parents)
        if not found or (anchor and (path.suffix != ".md" or anchor not in anchors(path))):
            out.append(target)
    return out


def records_not_found(text: str) -> list[str]:
    """The decision records ``text`` names (``docs/decisions/NNN-title.md``, ``docs/decisions/NNN``,
    ``record NNN``) that are not in ``docs/decisions``."""
    names = {p.name for p in RECORDS}
    numbers = {name[:3] for name in names}
    out = []
    for m in RECORD_NAMED.finditer(text):
        number, title = m.group(1) or m.group(3), m.group(2)
        if number not in numbers or (title and number + title not in names):
            out.append(m.group(0))
    return out


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(ROOT)) for d in DOCS])
def test_every_relative_link_resolves_in_the_repository(doc: Path) -> None:
    assert not broken_links(doc)
    assert not re.findall(r"\.\./shared/[A-Za-z-]+\.md", doc.read_text(encoding="utf-8"))


def test_the_link_check_finds_a_link_out_of_the_repository(tmp_path: Path) -> None:
    doc = ROOT / "docs" / "formats.md"
    assert broken_links(doc) == []
    outside = tmp_path / "x.md"
    outside.write_text("[formats](docs/formats.md) and [contracts](../shared/CONTRACTS.md)")
    assert broken_links(outside) == ["docs/formats.md", "../shared/CONTRACTS.md"]


def test_the_link_check_finds_a_heading_that_is_not_there(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "other.md").write_text("# 013 — Input that looks legitimate\n## Clocks\n")
    page = tmp_path / "page.md"
    page.write_text(
        "# A `page`: of *notes*\n## Notes\n```\n# not a heading\n```\n## Notes\n"
        "[a](#a-page-of-notes) [b](#notes-1) [c](#notes-2) [d](#not-a-heading)\n"
        "[e](docs/other.md#013--input-that-looks-legitimate) [f](docs/other.md#clocks) [g](docs/other.md#keys)"
    )
    assert broken_links(page, tmp_path) == ["#notes-2", "#not-a-heading", "docs/other.md#keys"]


def test_every_decision_record_named_in_the_code_and_docs_exists() -> None:
    missing = {
        str(p.relative_to(ROOT)): found
        for p in SOURCES
        if p != Path(__file__).resolve() and (found := records_not_found(p.read_text(encoding="utf-8")))
    }
    assert not missing


def test_the_record_check_finds_a_record_that_is_not_there() -> None:
    first = RECORDS[0].name
    text = f"docs/decisions/{first}, docs/decisions/{first[:3]}, record {first[:3]}; "
    text += f"docs/decisions/{first[:3]}-gone.md and record 999"
    assert records_not_found(text) == [f"docs/decisions/{first[:3]}-gone.md", "record 999"]


@pytest.mark.parametrize("record", RECORDS, ids=[r.name for r in RECORDS])
def test_every_decision_record_decides_in_under_200_lines(record: Path) -> None:
    lines = len(record.read_text(encoding="utf-8").splitlines())
    assert lines < RECORD_LINES, f"{record.name}: {lines} lines; its history belongs in git log"


def test_the_parameter_reference_is_the_one_the_config_generates() -> None:
    # (under a second) a parameter added, retired or redocumented shows in docs/parameters.md
    assert (ROOT / "docs" / "parameters.md").read_text(encoding="utf-8") == render(), f"out of date: run {COMMAND}"
