"""A new user can run README's file examples as written: an earlier example makes every file that the upload
example, the "Command line" commands and ``mfgnet sequence`` read (``scan_a.npy``, ``scan_b.pcd``, the prior,
``frame_0.ply``, ...), and the in-process command lines then run in that order in an empty folder and exit 0.
The ``--server`` line reads the same files; the training-side lines read none of them."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from service.manifest import bundled_models_dir

README = Path(__file__).resolve().parents[2] / "README.md"
# `mfgnet ARGS` in this Python, as .venv/bin/mfgnet runs it
MFGNET = "import sys; sys.argv[0] = 'mfgnet'; from service.cli import main; main()"


def section(heading: str) -> str:
    return README.read_text().split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]


def blocks(heading: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", section(heading), flags=re.S)


def make_scan_files(folder: Path) -> None:
    """Runs the "Register over HTTP" shell line that writes the example files (``.venv/bin/python -c '...'``)."""
    made = [m.group(0) for b in blocks("Register over HTTP", "sh")
            for m in re.finditer(r"\.venv/bin/python -c '[^']*write_cloud[^']*'", b)]
    assert made, "README's 'Register over HTTP' shows no command that writes the example files"
    command = made[0].replace(".venv/bin/python", shlex.quote(sys.executable), 1)
    run = subprocess.run(["bash", "-c", command], cwd=folder, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr


def make_frames(folder: Path, monkeypatch) -> None:
    """Runs the "Sequences and odometry priors" Python example in ``folder``."""
    monkeypatch.chdir(folder)
    exec(compile(blocks("Sequences and odometry priors", "python")[0], str(README), "exec"), {})


def command_lines() -> list[list[str]]:
    """The "Command line" block's ``mfgnet register`` and ``mfgnet sequence`` lines (argv after ``mfgnet``), in
    order, without comments and ``&& ...``."""
    lines = []
    for line in blocks("Command line", "sh")[0].splitlines():
        line = re.sub(r"\s+#.*$", "", line).split("&&")[0]
        argv = shlex.split(line)
        if argv[:1] == [".venv/bin/mfgnet"] and argv[1] in ("register", "sequence"):
            lines.append(argv[1:])
    return lines


def test_the_readme_makes_every_file_its_examples_read_and_the_command_lines_run(tmp_path, monkeypatch) -> None:
    if not (bundled_models_dir() / "general" / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    make_scan_files(tmp_path)
    make_frames(tmp_path, monkeypatch)
    uploads = re.findall(r"-F \w+=@(\S+)", section("Register over HTTP"))
    assert uploads and all((tmp_path / name).is_file() for name in uploads), (uploads, sorted(tmp_path.iterdir()))
    lines = command_lines()
    assert len(lines) >= 6, lines
    for argv in lines:
        if "--server" in argv:
            assert all((tmp_path / arg).is_file() for arg in argv[1:3]), argv  # the files it uploads exist
            continue
        run = subprocess.run([sys.executable, "-c", MFGNET, *argv], cwd=tmp_path, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, (argv, run.stderr[-2000:])
