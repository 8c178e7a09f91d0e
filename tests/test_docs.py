"""The README and the docs read the same in any clone: every relative link resolves inside the
repository, and none points at the team's handouts beside it (``../shared/*.md``)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from fleetmap.parameters_doc import COMMAND, render

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def broken_links(doc: Path) -> list[str]:
    """The relative link targets of a Markdown file that name no file or folder of the repository."""
    out = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL, or a heading of the same page
        path = (doc.parent / target.split("#")[0]).resolve()
        if not path.exists() or ROOT not in path.parents:
            out.append(target)
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


def test_the_parameter_reference_is_the_one_the_config_generates() -> None:
    # (under a second) a parameter added, retired or redocumented shows in docs/parameters.md
    assert (ROOT / "docs" / "parameters.md").read_text(encoding="utf-8") == render(), f"out of date: run {COMMAND}"
