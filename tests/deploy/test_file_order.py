"""The test files' order: recorded durations, heaviest first (tests/helpers/file_order.py, docs/decisions/0099)."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HELPERS = ROOT / "tests" / "helpers"
SLOW = "import time\n\ndef test_slow():\n    time.sleep(0.4)\n"
QUICK = "def test_one():\n    pass\n\ndef test_two():\n    pass\n"


def run_pytest(folder: Path, *args: str) -> subprocess.CompletedProcess:
    """pytest in ``folder`` (its own rootdir) with the ordering plugin and xdist only (no other plugin's start-up)."""
    (folder / "pytest.ini").write_text("[pytest]\n")
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "file_order", "-p", "xdist.plugin", "-p",
                           "no:cacheprovider", *args], cwd=folder, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(HELPERS), "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"})


def collected(result: subprocess.CompletedProcess) -> list[str]:
    assert result.returncode == 0, result.stdout + result.stderr
    return [line for line in result.stdout.splitlines() if "::" in line]


def test_files_run_heaviest_recorded_first_and_unrecorded_ones_before_them(tmp_path) -> None:
    for name in ("test_a.py", "test_b.py", "test_c.py"):
        (tmp_path / name).write_text(QUICK)
    record = tmp_path / "durations.json"
    record.write_text(json.dumps({"test_a.py": 1.0, "test_b.py": 5.0}))
    ids = collected(run_pytest(tmp_path, "--collect-only", "-q", "--file-durations", str(record)))
    assert ids == [f"test_{f}.py::test_{t}" for f in "cba" for t in ("one", "two")]  # each file's own order kept


def test_without_a_record_the_collection_order_is_kept(tmp_path) -> None:
    for name in ("test_a.py", "test_b.py"):
        (tmp_path / name).write_text(QUICK)
    ids = collected(run_pytest(tmp_path, "--collect-only", "-q", "--file-durations", str(tmp_path / "none.json")))
    assert ids == [f"test_{f}.py::test_{t}" for f in "ab" for t in ("one", "two")]


@pytest.mark.parametrize("workers", [[], ["-n", "2", "--dist", "loadfile", "--no-loadscope-reorder"]],
                         ids=["one process", "two workers"])
def test_a_run_records_each_files_summed_durations(tmp_path, workers) -> None:
    (tmp_path / "test_slow.py").write_text(SLOW)
    (tmp_path / "test_quick.py").write_text(QUICK)
    out = tmp_path / "out.json"
    result = run_pytest(tmp_path, "-q", *workers, "--record-file-durations", str(out))
    assert result.returncode == 0, result.stdout + result.stderr
    seconds = json.loads(out.read_text())
    assert list(seconds) == ["test_slow.py", "test_quick.py"], seconds  # heaviest first
    assert 0.4 <= seconds["test_slow.py"] < 5 and 0 <= seconds["test_quick.py"] < 0.4, seconds


def test_the_suite_loads_the_plugin() -> None:
    addopts = shlex.split(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"][
        "addopts"])
    assert addopts[addopts.index("-p") + 1] == "file_order", addopts


def test_the_committed_record_names_only_test_files_that_exist() -> None:
    seconds = json.loads((ROOT / "tests" / "file_durations.json").read_text())
    missing = [name for name in seconds if not (ROOT / name).is_file()]
    assert seconds and not missing, missing
