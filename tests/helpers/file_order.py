"""Test files in the order of their recorded cost, heaviest first, so that two workers finish together.

``make test`` hands files to its two workers in collection order (``--dist loadfile --no-loadscope-reorder``); with
the heaviest first, the last files handed out are short ones and neither worker waits long for the other at the end
(docs/decisions/0099). ``tests/file_durations.json`` holds each file's summed test durations (seconds) from a run of
``make test-durations``; files it does not name go first, their cost unknown. ``--record-file-durations PATH`` writes
such a record from the run it is given to (under xdist, from the controller, which sees every worker's reports).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import pytest

DURATIONS = Path(__file__).resolve().parents[1] / "file_durations.json"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--file-durations", metavar="PATH", type=Path, default=DURATIONS,
                     help="the record of each test file's durations that orders them (default: %(default)s)")
    parser.addoption("--record-file-durations", metavar="PATH", type=Path, default=None,
                     help="write each test file's summed test durations (seconds) to PATH as JSON")


def recorded_durations(path: Path) -> dict[str, float]:
    """Seconds per test file (its path as in test ids), or nothing where no record exists."""
    return json.loads(path.read_text()) if path.is_file() else {}


def file_of(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Heaviest recorded files first; unrecorded files before them; each file's own order kept (a stable sort)."""
    seconds = recorded_durations(config.getoption("--file-durations"))
    items.sort(key=lambda item: -seconds.get(file_of(item.nodeid), math.inf))


class DurationRecorder:
    """Sums each file's setup, call and teardown durations and writes them when the session ends."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.seconds: dict[str, float] = defaultdict(float)

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        self.seconds[file_of(report.nodeid)] += report.duration

    def pytest_sessionfinish(self) -> None:
        ordered = sorted(self.seconds.items(), key=lambda kv: (-kv[1], kv[0]))
        self.out.write_text(json.dumps({name: round(value, 1) for name, value in ordered}, indent=1) + "\n")


def pytest_configure(config: pytest.Config) -> None:
    out = config.getoption("--record-file-durations")
    if out and not hasattr(config, "workerinput"):  # the controller or a run without workers, not each worker
        config.pluginmanager.register(DurationRecorder(out), "file_durations_recorder")
