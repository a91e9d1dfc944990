"""``service.core.logging``: every line the server writes to stderr is one JSON object."""

from __future__ import annotations

import json
import subprocess
import sys

WARNING_SCRIPT = """
import logging
import numpy as np
from service.core.logging import configure_logging
configure_logging("info")
logging.getLogger("mfgnet.api").info("before")
np.ones(3, dtype=np.float32) / np.zeros(3, dtype=np.float32)  # RuntimeWarning: divide by zero
logging.getLogger("mfgnet.api").info("after")
"""


def test_python_warnings_are_json_lines_too() -> None:
    """A numerical warning in the server process is a ``py.warnings`` JSON line, not plain text."""
    done = subprocess.run([sys.executable, "-W", "default", "-c", WARNING_SCRIPT], capture_output=True, text=True,
                          timeout=60, check=True)
    entries = [json.loads(line) for line in done.stderr.splitlines()]  # fails on any plain-text line
    assert [e["msg"] for e in entries if e["logger"] == "mfgnet.api"] == ["before", "after"]
    warning = [e for e in entries if e["logger"] == "py.warnings"]
    assert len(warning) == 1 and warning[0]["level"] == "warning" and "divide by zero" in warning[0]["msg"]


LIBRARY_SCRIPT = """
import logging
from service.core.logging import configure_logging
configure_logging("info")
logging.getLogger("python_multipart.multipart").warning("Found invalid character %r in header at %d", 13, 75)
logging.getLogger("python_multipart.multipart").info("parsing a part")  # below the libraries' level: not shown
logging.getLogger("mfgnet.api").info("served")
"""


def test_other_libraries_warnings_are_json_lines_and_their_chatter_is_left_out() -> None:
    """A warning of a library the server does not configure by name (python-multipart on a malformed upload)."""
    done = subprocess.run([sys.executable, "-c", LIBRARY_SCRIPT], capture_output=True, text=True, timeout=60,
                          check=True)
    entries = [json.loads(line) for line in done.stderr.splitlines()]  # fails on any plain-text line
    assert [(e["logger"], e["level"], e["msg"]) for e in entries] == [
        ("python_multipart.multipart", "warning", "Found invalid character 13 in header at 75"),
        ("mfgnet.api", "info", "served"),
    ]
