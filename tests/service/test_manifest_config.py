"""A model folder's manifest ``config`` is checked when the model loads: a hand-edited or damaged value the runtime
cannot run is a :class:`ModelIntegrityError` naming it, not a traceback at the first registration."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest
from service.registrar import Registrar

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


def edited(tmp_path: Path, **config) -> Path:
    """A copy of the bundled ``general`` whose manifest's config has ``config``'s values."""
    folder = tmp_path / "general"
    shutil.copytree(bundled_models_dir() / "general", folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["config"].update(config)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


@pytest.mark.parametrize(("config", "named"), [
    ({"centroid": "weightex"}, "centroid 'weightex'"),  # a ValueError at the first registration
    ({"iterations": 0}, "iterations 0"),
    ({"keypoints": 100_000}, "keypoints 100000"),  # every request refused: "keypoints must be in 16..512"
    ({"knn": "12"}, "knn '12'"),
])
def test_a_config_value_the_runtime_cannot_run_is_named_when_the_model_loads(tmp_path, config, named) -> None:
    with pytest.raises(ModelIntegrityError, match=f"model 'general': malformed config in manifest.json: {named}"):
        load_manifest(edited(tmp_path, **config))


def test_a_neighbour_count_other_than_the_encoders_is_named(tmp_path) -> None:
    """ONNX Runtime's InvalidArgument ("Got: 13 Expected: 12") at the first registration."""
    with pytest.raises(ModelIntegrityError, match="config knn 13, but its encoder graph takes 12 neighbours per point"):
        Registrar(edited(tmp_path, knn=13))
