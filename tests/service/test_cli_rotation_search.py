"""``mfgnet register --rotation-search`` recovers a relative rotation far outside the trained range."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import bumpy_ellipsoid
from typer.testing import CliRunner

from service.cli import app
from service.manifest import bundled_models_dir
from service.pointcloud_io import write_points

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").exists(),
                                reason="bundled model 'clean' absent")


def test_register_with_rotation_search_recovers_150_degrees(tmp_path):
    src = bumpy_ellipsoid(800)
    R_true = Rotation.from_euler("z", 150, degrees=True).as_matrix()
    write_points(tmp_path / "a.npy", src)
    write_points(tmp_path / "b.npy", src @ R_true.T + [0.2, 0.0, -0.1])
    result = CliRunner().invoke(
        app, ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--rotation-search", "--refine", "icp",
              "--json"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    R = np.asarray(record["rotation"])
    error_deg = np.degrees(2 * np.arcsin(min(1.0, np.linalg.norm(R - R_true) / (2 * np.sqrt(2)))))
    assert error_deg < 2.0 and "search" in record["timing_ms"]
