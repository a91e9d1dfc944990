"""``mfgnet`` in a real subprocess at ``COLUMNS=80``: ``models`` fits 100 columns and marks the default model;
every command's ``--help`` fits 80 columns with every flag name whole."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest
from cli_support import REPO_ROOT, snapshot_model

from service.manifest import bundled_models_dir

# Prints {command: {"help": its --help text, "flags": its option names, "texts": its own and its options' help
# texts as written, unwrapped}} for every `mfgnet` command.
EVERY_HELP = """
import contextlib, io, json, typer
from service.cli import app
group = typer.main.get_command(app)
out = {}
for name in ["", *group.list_commands(None)]:
    text = io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.suppress(SystemExit):
        app([name, "--help"] if name else ["--help"], prog_name="mfgnet")
    command = group.get_command(None, name) if name else group
    flags = [flag for p in command.params for flag in (*p.opts, *p.secondary_opts) if flag.startswith("-")]
    texts = [command.help or "", *(getattr(p, "help", None) or "" for p in command.params)]
    out[name or "mfgnet"] = {"help": text.getvalue(), "flags": flags, "texts": texts}
print(json.dumps(out))
"""


def mfgnet(*args: str, code: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "80", "PYTHONPATH": str(REPO_ROOT)}
    argv = ["-c", code] if code else ["-m", "service.cli", *args]
    return subprocess.run([sys.executable, *argv], env=env, capture_output=True, text=True, timeout=300,
                          cwd=REPO_ROOT)


@pytest.mark.skipif(not (bundled_models_dir() / "general" / "manifest.json").exists(), reason="no bundled 'general'")
def test_models_fits_100_columns_and_marks_the_default(tmp_path) -> None:
    deep = tmp_path.joinpath(*["a-rather-long-folder-name"] * 4)
    snapshot_model(deep, "clean")  # the only --model-dir model: what `mfgnet register` runs without --model
    run = mfgnet("models", "--model-dir", str(deep))
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert max(map(len, lines)) <= 100, run.stdout
    marked = [line for line in lines if line.startswith("*")]
    assert len(marked) == 2 and marked[0].split()[1] == "clean" and marked[1].startswith("* the default")
    assert marked[0].endswith("-folder-name/clean") and "..." in marked[0]  # the folder, elided
    assert "rmse" not in run.stdout and "mae" not in run.stdout and "recall" not in run.stdout
    bundled = mfgnet("models")
    assert bundled.returncode == 0 and max(map(len, bundled.stdout.splitlines())) <= 100
    marked = [line.split() for line in bundled.stdout.splitlines() if line.startswith("* ")]
    assert marked[0][:2] == ["*", "general"] and marked[0][-1] == "bundled"  # the bundled default


@pytest.fixture(scope="module")
def helps() -> dict:
    """What ``EVERY_HELP`` prints, from one subprocess at ``COLUMNS=80``."""
    run = mfgnet(code=EVERY_HELP)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_every_help_fits_80_columns_with_whole_flag_names(helps) -> None:
    assert {"mfgnet", "serve", "register", "models"} <= set(helps)
    for name, page in helps.items():
        widest = max(page["help"].splitlines(), key=len)
        assert len(widest) <= 80, f"{name}: {widest!r}"
        assert "…" not in page["help"], name
        for flag in page["flags"]:
            assert flag in page["help"].split() or f"{flag}," in page["help"], f"{name}: {flag} cut"
    assert "--rotation-search-mode" in helps["register"]["help"].split()
    for name, page in helps.items():  # nor cut where a help text names a flag (`--rotation-` / `search)`)
        cut = [line for line in page["help"].splitlines() if re.search(r"(?<![\w-])--[a-z][\w-]*-$", line)]
        assert not cut, f"{name}: {cut}"


def test_every_flag_a_help_names_is_one_of_its_commands(helps) -> None:
    """Option types are shared between commands (register and sequence): a help text names only flags of the command
    it is shown by. Another command's flags are named after that command (`register --json`, mfgnet evaluate
    --json)."""
    commands = "|".join(name for name in helps if name != "mfgnet")
    for name, page in helps.items():
        own = {*page["flags"], "--help"}
        for text in page["texts"]:
            text = re.sub(rf"\b(?:{commands})(?: --?[a-z][\w-]*)+", "", text)  # another command's flags
            named = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text))
            assert named <= own, f"{name}: {sorted(named - own)} in {text!r}"
