"""What a benchmark report's ``provenance`` (:func:`bench.report_io.provenance`) and a training run's record
(:func:`model.provenance.run_record`) must say of a run of this checkout."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def assert_made_by_this_checkout(made_by: dict, *models: str | Path) -> bool:
    """``made_by`` names a commit of this checkout's history, whether it had uncommitted changes, and ``models``
    (bundled names or folders; default ``general``), in order, with the versions their manifests give."""
    from service.manifest import load_manifest, model_folder

    assert_this_checkout(made_by)
    manifests = [load_manifest(model_folder(model)) for model in models or ("general",)]
    assert [(m["name"], m["version"]) for m in made_by["models"]] == [(m.name, m.version) for m in manifests]
    return True


def assert_this_checkout(made_by: dict) -> None:
    """``made_by`` (:func:`model.provenance.checkout`'s fields) names a commit of this checkout's history and whether
    it had uncommitted changes."""
    commit = made_by["commit"]  # HEAD when the run began, or before it: others may commit during the test
    assert isinstance(commit, str) and len(commit) == 40
    assert subprocess.run(["git", "merge-base", "--is-ancestor", commit, "HEAD"], cwd=ROOT).returncode == 0
    assert isinstance(made_by["uncommitted_changes"], bool)
