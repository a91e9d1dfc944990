"""Every command that ``README.md`` and ``docs/*.md`` show (``python -m bench.X``, ``mfgnet ...``, ``make ...``,
``scripts/*.py``) names a module, command or target that exists, and its options are accepted by that command's
parser. Nothing is run: an argparse module's ``main`` stops right after ``parse_args``, and a ``mfgnet`` command's
options are parsed by its click command without invoking it.

A span without options (``python -m bench.vs_fpfh`` in a sentence) only has to name something that exists. Shell loop
variables take the loop's first value, ``<...>`` and the placeholders below a plausible value, and a span holding
``...`` is left out (it is elided on purpose).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "PACKAGE.md", *sorted((ROOT / "docs").glob("*.md"))]  # not docs/decisions/
COMMAND = re.compile(r"^(?:python3? -m bench\.\w+|mfgnet [a-z]|make [a-z]"
                     r"|(?:python3? )?(?:scripts|tests/helpers)/\w+\.py\b)")
PLACEHOLDERS = {"S": "0", "I": "4", "K": "128", "M": "clean", "N": "1",  # --seed S, --iterations I, ...
                "DEG,DIST": "5,0.01"}  # bench.make_pair --thresholds DEG,DIST


def _spans(text: str) -> list[tuple[int, str]]:
    """(line, text) of every command-like piece: each code-block line (continuations joined) and inline code span."""
    spans: list[tuple[int, str]] = []
    loops: dict[str, str] = {}
    block: list[str] = []
    prose: list[tuple[int, str]] = []
    in_block = False
    for number, line in enumerate(text.split("\n"), 1):
        if line.lstrip().startswith("```"):
            in_block = not in_block
            continue
        if in_block:
            block.append(line.strip())
            if not line.rstrip().endswith("\\"):
                joined = " ".join(part.rstrip("\\").strip() for part in block)
                for var, first in re.findall(r"\bfor (\w+) in (\S+)", joined):
                    loops[var] = first
                spans.append((number, joined))
                block = []
        else:
            prose.append((number, line))
    # inline spans may wrap: join each paragraph, bullet or table row before looking for backticks
    paragraph: list[str] = []
    start = 0
    for number, line in [*prose, (0, "")]:
        new_item = not line.strip() or line.startswith("|") or re.match(r"^\s*(- |\d+\. )", line)
        if new_item and paragraph:
            spans += [(start, span) for span in re.findall(r"`([^`]+)`", " ".join(paragraph))]
            paragraph = []
        if line.strip():
            if not paragraph:
                start = number
            paragraph.append(line.strip())
    return [(number, _substitute(span, loops)) for number, span in spans]


def _substitute(span: str, loops: dict[str, str]) -> str:
    span = re.sub(r"\$\{?(\w+)\}?", lambda m: loops.get(m.group(1), "x"), span)
    return re.sub(r"<[^>]+>", "x", span)


def doc_commands() -> list[tuple[str, str]]:
    found = []
    for path in DOCS:
        for number, span in _spans(path.read_text()):
            span = re.sub(r"(^|\s+)#.*$", "", re.sub(r"(^|\s)\.venv/bin/", r"\1", span.strip()))  # comments
            span = re.sub(r"^.*?\bdo\s+", "", span)
            span = re.sub(r";\s*done\b.*$", "", span)
            for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", span):
                part = re.sub(r"^(?:[A-Z_]+=\S+\s+)+", "", part.strip())  # VAR=value prefixes
                part = re.sub(r"\[([^\[\]]+)\]", r"\1", part)  # optional [--flag value]: checked with it
                if COMMAND.match(part) and "..." not in part.split():
                    found.append((f"{path.relative_to(ROOT)}:{number}", part))
    return sorted(set(found))


class _ParsedError(Exception):
    """Raised right after a parser has accepted the arguments."""


@pytest.fixture
def parse_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """argparse parsers stop after parsing: a ``main`` that parses first then does no work."""
    original = argparse.ArgumentParser.parse_args

    def parse_args(self, args=None, namespace=None):
        _optional_everywhere(self, monkeypatch)
        original(self, args, namespace)
        raise _ParsedError

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_args)


def _optional_everywhere(parser: argparse.ArgumentParser, monkeypatch: pytest.MonkeyPatch) -> None:
    """Required options made optional (in sub-commands too): a fragment may leave out an input, not add a wrong one."""
    for action in parser._actions:
        if action.option_strings and action.required:
            monkeypatch.setattr(action, "required", False)
        for sub in (action.choices or {}).values() if isinstance(action, argparse._SubParsersAction) else ():
            _optional_everywhere(sub, monkeypatch)


def _argparse_main(main, argv: list[str], monkeypatch: pytest.MonkeyPatch,
                   capsys: pytest.CaptureFixture) -> str | None:
    monkeypatch.setattr(sys, "argv", ["prog", *argv])
    try:
        main(argv) if main.__code__.co_argcount else main()
    except _ParsedError:
        return None
    except SystemExit as exc:
        return f"exit {exc.code}: {capsys.readouterr().err.strip()}"
    return "main() ran past parse_args"


def _check_mfgnet(argv: list[str], options_given: bool) -> str | None:
    import typer

    from service.cli import app

    group = typer.main.get_command(app)
    parent = group.make_context("mfgnet", [], resilient_parsing=True)
    if not argv or argv[0].startswith("-"):
        return None
    command = group.get_command(parent, argv[0])
    if command is None:
        return f"no mfgnet command {argv[0]!r}"
    if not options_given:
        return None
    try:
        command.make_context(argv[0], argv[1:], parent=parent)
    except Exception as exc:  # click's usage errors (typer vendors click, so match by name)
        if type(exc).__name__ in ("Exit", "MissingParameter"):  # a fragment may leave out a required input
            return None
        if type(exc).__name__ == "BadOptionUsage" and "requires an argument" in str(exc) and argv[-1].startswith("-"):
            return None  # a sentence naming an option: `mfgnet evaluate --checkpoint`
        if hasattr(exc, "format_message"):
            return f"{type(exc).__name__}: {exc.format_message()}"
        raise
    return None


def _check(command: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> str | None:
    argv = [PLACEHOLDERS.get(token, token) for token in shlex.split(command)]
    if argv[0] == "make":
        targets = set(re.findall(r"^([a-z][\w-]*):", (ROOT / "Makefile").read_text(), re.M))
        missing = [a for a in argv[1:] if "=" not in a and a not in targets]
        return f"no make target {missing}" if missing else None
    if argv[0] == "mfgnet":
        return _check_mfgnet(argv[1:], options_given=len(argv) > 2)
    if argv[0].startswith("python") and argv[1] == "-m":
        name, args = argv[2], argv[3:]
        if importlib.util.find_spec(name) is None:
            return f"no module {name}"
        module = importlib.import_module(name)
    else:
        script, args = (argv[1], argv[2:]) if argv[0].startswith("python") else (argv[0], argv[1:])
        if not (ROOT / script).is_file():
            return f"no file {script}"
        spec = importlib.util.spec_from_file_location(f"_doc_script_{Path(script).stem}", ROOT / script)
        module = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, spec.name, module)
        spec.loader.exec_module(module)
    main = getattr(module, "main", None)
    if not args or main is None:  # a mention, or a module that parses its own way (bench.plot: two paths)
        return None
    return _argparse_main(main, args, monkeypatch, capsys)


COMMANDS = doc_commands()


def test_the_docs_show_commands() -> None:
    assert len(COMMANDS) > 50, "the extraction found few commands: the pattern is wrong"


@pytest.mark.parametrize(("where", "command"), COMMANDS, ids=[f"{w} {c[:60]}" for w, c in COMMANDS])
def test_every_doc_command_parses(where: str, command: str, parse_only: None, monkeypatch: pytest.MonkeyPatch,
                                  capsys: pytest.CaptureFixture) -> None:
    problem = _check(command, monkeypatch, capsys)
    assert problem is None, f"{where}: `{command}`: {problem}"
