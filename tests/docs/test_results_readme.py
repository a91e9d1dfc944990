"""``results/README.md`` has one row for every file under ``results/`` and names no file that is not there; every
``results/...`` path that the docs (``README.md``, ``docs/*.md``, ``results/README.md``) name exists."""

from __future__ import annotations

import re
from pathlib import Path

from test_doc_commands import DOCS, ROOT

RESULTS = ROOT / "results"
INDEX = RESULTS / "README.md"
# a results path as a doc writes it: up to the end of the code span, the sentence or the table cell
RESULTS_PATH = re.compile(r"(?<![\w/.-])results/[^\s`'\"(),;|]*")
PATTERN_MARKS = ("<", "{", "*", "$", "...")  # `results/<model>-<version>/`, `.../{dense,sparse}_it{I}...`: not a file


def stored_files() -> set[str]:
    """Every file under ``results/`` but its README, relative to ``results/``."""
    return {p.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("*") if p.is_file() and p != INDEX}


def index_rows() -> list[tuple[int, str]]:
    """(line, path relative to ``results/``) of every file named in the first cell of a table row of
    ``results/README.md``, under the folder of the ``## <folder>/`` heading above it."""
    rows, folder = [], None
    for number, line in enumerate(INDEX.read_text().split("\n"), 1):
        if line.startswith("## "):
            folder = line[3:].strip().strip("`").rstrip("/")
        elif line.startswith("|") and folder is not None:
            first = line.strip("|").split("|")[0]
            rows += [(number, f"{folder}/{name}") for name in re.findall(r"`([^`]+)`", first)]
    return rows


def named_results_paths(path: Path) -> list[tuple[int, str]]:
    """(line, path) of every concrete ``results/...`` path that ``path`` names (patterns and elisions left out)."""
    found = []
    for number, line in enumerate(path.read_text().split("\n"), 1):
        for match in RESULTS_PATH.findall(line):
            if not any(mark in match for mark in PATTERN_MARKS):
                found.append((number, match.rstrip(".:")))
    return found


def test_every_results_file_has_a_row_in_the_results_readme() -> None:
    listed = {name for _, name in index_rows()}
    assert listed, "results/README.md lists no file: the table pattern is wrong"
    missing = sorted(stored_files() - listed)
    assert not missing, f"results/README.md has no row for {missing}"


def test_the_results_readme_lists_only_files_that_exist_and_each_once() -> None:
    rows = index_rows()
    absent = [f"results/README.md:{number}: {name}" for number, name in rows if name not in stored_files()]
    assert not absent, f"results/README.md names files that do not exist: {absent}"
    names = [name for _, name in rows]
    assert len(names) == len(set(names)), sorted({name for name in names if names.count(name) > 1})


def test_every_results_path_a_doc_names_exists() -> None:
    named = [(f"{doc.relative_to(ROOT)}:{number}", path) for doc in [*DOCS, INDEX]
             for number, path in named_results_paths(doc)]
    assert len(named) > 50, "the docs name few results paths: the pattern is wrong"
    missing = [f"{where}: {path}" for where, path in named if not (ROOT / path).exists()]
    assert not missing, f"docs name results paths that do not exist: {missing}"
