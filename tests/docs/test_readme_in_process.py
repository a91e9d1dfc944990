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


def test_the_sequence_example_chains_frames_onto_the_truth_with_an_odometry_prior(capsys, monkeypatch, tmp_path):
    """README's "Sequences and odometry priors": frame i onto frame i-1 with odometry's prior, chained by matrix
    products, gives frame 3 in frame 0's coordinates; its printed quaternion is each step's 15 deg turn about z."""
    if not (bundled_models_dir() / "general" / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(section_example("Sequences and odometry priors"), str(README), "exec"), namespace)
    printed = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in printed[:3]] == [["1", "True"], ["2", "True"], ["3", "True"]], printed
    assert printed[0].split()[2:] == ["[0.", "0.", "0.1305", "0.9914]"], printed  # sin, cos of 7.5 deg
    world = namespace["T_world_sensor"]
    truth = np.linalg.inv(world[0]) @ world[-1]  # T_0_3
    np.testing.assert_allclose(namespace["T_0_i"], truth, atol=1e-5)
    np.testing.assert_allclose(truth, namespace["pose"](45, [0.9, 0.3, 0.0]), atol=1e-12)  # the comment's pose
    off = np.linalg.inv(np.linalg.inv(world[2]) @ world[3]) @ namespace["prior"]  # the last prior against its truth
    assert np.degrees(np.arctan2(off[1, 0], off[0, 0])) == pytest.approx(2.0)  # one frame's drift about z
    assert 0.01 < np.linalg.norm(off[:3, 3]) < 0.1, off
