"""The README's set-up commands as ``make`` runs them: ``make test`` installs torch's CPU build.

PyPI's Linux ``torch`` wheel is the CUDA build (its metadata requires ``cuda-toolkit`` and ``nvidia-*`` packages),
so ``pip install -e ".[train,dev]"`` alone installs CUDA torch on a clean Linux machine. The Makefile
installs the pinned torch from PyTorch's CPU index first; the extras then find it installed. ``make -n`` prints the
commands without running them. A doc that installs an extra holding torch (``train``, ``bench``) does it after
``make install-dev``, so that the extra finds the CPU build installed.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]  # not docs/decisions/: historical records
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def make_commands(target: str, venv: Path) -> list[list[str]]:
    """The commands ``make TARGET`` would run for a venv that does not exist yet (continuations joined)."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    printed = subprocess.run(["make", "-n", "-C", str(ROOT), target, f"VENV={venv}"], capture_output=True,
                             text=True, timeout=60, check=True).stdout
    return [shlex.split(line) for line in printed.replace("\\\n", " ").splitlines() if line.strip()]


def pinned_torch() -> str:
    """The ``train`` extra's torch requirement in ``pyproject.toml`` (``torch==X.Y.Z``)."""
    pins = re.findall(r'^\s*"(torch==[^"]+)"', (ROOT / "pyproject.toml").read_text(), flags=re.M)
    assert len(pins) == 1, pins
    return pins[0]


def installs(commands: list[list[str]]) -> list[int]:
    """The indices of ``commands`` that install packages: ``pip install`` or ``uv pip install``."""
    return [i for i, argv in enumerate(commands)
            if (argv[0].endswith("/pip") and argv[1] == "install") or (argv[0].endswith("/uv") and argv[1:3] == [
                "pip", "install"])]


def test_make_test_installs_the_pinned_torch_from_the_cpu_index_before_the_extras(tmp_path) -> None:
    commands = make_commands("install-dev", tmp_path / "venv")
    pip = installs(commands)
    torch = [i for i in pip if pinned_torch() in commands[i]]
    extras = [i for i in pip if any(arg.startswith(".[train") for arg in commands[i])]
    assert torch and extras, commands
    assert commands[torch[0]][0].endswith("/pip"), commands  # pip: it reads the machine's find-links (Makefile)
    argv = commands[torch[0]]
    assert argv[argv.index("--index-url") + 1] == CPU_INDEX, argv  # not PyPI's CUDA build
    assert "--no-deps" in argv, argv  # torch's own dependencies come from PyPI with the extras
    assert torch[0] < extras[0], commands  # else the extras' resolver takes torch from PyPI


def test_uv_that_installs_the_extras_is_pinned_and_installed_into_the_venv_first(tmp_path) -> None:
    venv = tmp_path / "venv"
    commands = make_commands("install-dev", venv)
    uv = [i for i, argv in enumerate(commands) if argv[0].endswith("/uv")]
    bootstrap = [i for i in installs(commands) if any(re.fullmatch(r"uv==[\d.]+", arg) for arg in commands[i])]
    assert uv and bootstrap and bootstrap[0] < uv[0], commands
    for i in uv:  # into the venv's own interpreter, not whichever python uv finds first
        assert commands[i][commands[i].index("--python") + 1] == str(venv / "bin" / "python"), commands[i]


def test_uv_compiles_what_it_installs_to_bytecode(tmp_path) -> None:
    for target in ("install-dev", "install-serve"):
        commands = make_commands(target, tmp_path / "venv")
        uv = [commands[i] for i in installs(commands) if commands[i][0].endswith("/uv")]
        assert uv and all("--compile-bytecode" in argv for argv in uv), (target, uv)  # pip compiles by default


def test_the_test_runs_may_write_bytecode_whatever_the_environment_says(tmp_path) -> None:
    for target in ("test", "test-all"):
        runs = [argv for argv in make_commands(target, tmp_path / "venv") if "pytest" in argv]
        assert len(runs) == 2 and all(argv[0] == "PYTHONDONTWRITEBYTECODE=" for argv in runs), (target, runs)


def test_docs_install_the_torch_extras_after_make_install_dev() -> None:
    bare = [f"{doc.name}:{number}: {line.strip()}" for doc in DOCS
            for number, line in enumerate(doc.read_text().splitlines(), 1)
            if re.search(r"pip install .*\[[^\]]*\b(train|bench)\b", line) and "make install-dev" not in line]
    assert not bare, bare


def marks_serial(path: Path) -> bool:
    """Whether the test file marks tests ``serial`` anywhere (a decorator, ``pytestmark``, a param's marks)."""
    import ast

    return any(isinstance(node, ast.Attribute) and node.attr == "serial" and isinstance(node.value, ast.Attribute)
               and node.value.attr == "mark" for node in ast.walk(ast.parse(path.read_text())))


def test_the_serial_run_collects_every_file_that_marks_serial_tests(tmp_path) -> None:
    (serial,) = [argv for argv in make_commands("test", tmp_path / "venv")
                 if "pytest" in argv and "serial and not slow" in argv]
    named = {ROOT / arg for arg in serial[serial.index("serial and not slow") + 1:]}
    marking = {path for path in (ROOT / "tests").rglob("test_*.py") if marks_serial(path)}
    assert marking and named == marking, sorted(named ^ marking)
    hooks = [*(ROOT / "tests").rglob("conftest.py"), *(ROOT / "tests" / "helpers").glob("*.py")]
    adding = [path for path in hooks if "add_marker(" in path.read_text()]
    assert not adding, adding  # a marker added at collection would escape the files named
