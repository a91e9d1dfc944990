"""How the ``python -m export.*`` experiments hand back their report: printed, and saved when asked."""

from __future__ import annotations

import json
from pathlib import Path


def emit_report(report: dict, json_path: Path | None) -> None:
    """Print ``report`` as indented JSON and, with ``json_path``, write the same text there."""
    text = json.dumps(report, indent=2)
    print(text)
    if json_path:
        json_path.write_text(text + "\n")
