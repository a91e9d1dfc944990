"""``docs/decisions/``: the index lists every record once, and every reference to a record names one that exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DECISIONS = ROOT / "docs" / "decisions"
RECORD_NAME = re.compile(r"\b\d{4}-[a-z0-9-]+\.md\b")
TEXT_DIRS = ("docs", "service", "model", "export", "bench", "scripts", "tests", "deploy")


def records() -> list[str]:
    return sorted(p.name for p in DECISIONS.glob("[0-9][0-9][0-9][0-9]-*.md"))


def test_the_index_links_every_record_once_and_nothing_else() -> None:
    index = (DECISIONS / "README.md").read_text()
    linked = re.findall(r"\]\(([^)]+)\)", index)
    assert sorted(linked) == records()


def test_every_named_record_exists() -> None:
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md"]
    for folder in TEXT_DIRS:
        files += [p for p in (ROOT / folder).rglob("*") if p.suffix in (".md", ".py") and p.is_file()]
    named = {(path.relative_to(ROOT).as_posix(), name) for path in files
             for name in RECORD_NAME.findall(path.read_text(errors="replace"))}
    assert named, "no file names a decision record: the pattern is wrong"
    missing = sorted((where, name) for where, name in named if not (DECISIONS / name).is_file())
    assert not missing


RELATION = re.compile(r"(?:Amends|Amended by|Supersedes in part|Superseded in part by|Supersedes|Superseded by)"
                      r"\s+`?(\d{4})")


def related(name: str) -> set[str]:
    """The numbers of the records that ``name``'s header (the lines before its first section) says it amends or
    supersedes, or is amended or superseded by."""
    header = (DECISIONS / name).read_text().split("\n## ")[0]
    return set(RELATION.findall(header))


def test_an_amendment_is_named_by_both_records() -> None:
    """A record whose header says it amends or supersedes another (or is amended or superseded by one) is named in
    that one's header too: a reader of either finds the other."""
    numbers = {name[:4]: name for name in records()}
    relations = {(name[:4], other) for name in records() for other in related(name)}
    assert relations, "no header names an amendment: the pattern is wrong"
    for number, other in sorted(relations):
        assert other in numbers, f"{numbers[number]} names a record {other} that does not exist"
        assert number in related(numbers[other]), f"{numbers[number]} names {numbers[other]}, which does not name it"
