"""README's "In process (Python)" example runs as shown and registers its pair."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from service.manifest import bundled_models_dir

README = Path(__file__).resolve().parents[2] / "README.md"


def section_example(heading: str) -> str:
    """The first ```python block under ``## heading`` of the README."""
    section = README.read_text().split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, f"README's {heading!r} section has no python example"
    return blocks[0]


def test_the_in_process_example_runs_and_finds_the_turn(capsys, monkeypatch, tmp_path):
    if not (bundled_models_dir() / "general" / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(section_example("In process (Python)"), str(README), "exec"), namespace)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].split() == ["[[", "0.866", "-0.5", "0.", "0.1", "]"], printed  # the 30 deg turn and the shift
    assert printed[4].startswith("True []"), printed  # reliable, no warnings, then the time
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    first = namespace["registrar"].register(namespace["src"], namespace["tgt"])
    np.testing.assert_allclose(first.rotation, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(first.translation, [0.1, 0.0, 0.0], atol=1e-6)
    assert namespace["result"].reliable  # the last call, with options
