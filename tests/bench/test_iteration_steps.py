"""``python -m bench.iteration_steps``: the angle each network iteration still turns the pose, and the error left."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import ellipsoid_surface

from bench.iteration_steps import main, step_rows
from model.data import PairProtocol, make_pairs, save_pairs
from service.manifest import bundled_models_dir


def test_each_step_is_the_angle_from_the_iteration_before_and_the_error_is_against_the_truth() -> None:
    angles = np.array([[0.0, 10.0, 15.0, 16.0], [0.0, -20.0, -20.0, -22.0]])  # [P, I] degrees about z
    rotations = Rotation.from_euler("z", angles.reshape(-1, 1), degrees=True).as_matrix().reshape(2, 4, 3, 3)
    truth = Rotation.from_euler("z", [[16.0], [-21.0]], degrees=True).as_matrix()
    rows = step_rows(rotations, truth)
    assert [row["iteration"] for row in rows] == [1, 2, 3, 4] and "step_deg_median" not in rows[0]
    np.testing.assert_allclose([row["step_deg_median"] for row in rows[1:]], [15.0, 2.5, 1.5])
    np.testing.assert_allclose([row["rotation_error_deg_median"] for row in rows], [18.5, 3.5, 1.0, 0.5])


@pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")
def test_a_report_has_a_row_per_iteration_of_the_network(tmp_path) -> None:
    rng = np.random.default_rng(0)
    save_pairs(tmp_path / "p.npz", make_pairs(ellipsoid_surface(rng, (2, 1024)).astype(np.float32), PairProtocol(),
                                              rng))
    out = tmp_path / "steps.json"
    main(["--pairs", str(tmp_path / "p.npz"), "--iterations", "3", "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["n"] == 2 and [row["iteration"] for row in report["per_iteration"]] == [1, 2, 3]
    assert all(row["step_deg_p90"] >= row["step_deg_median"] >= 0 for row in report["per_iteration"][1:])


def test_more_iterations_than_the_service_runs_is_a_usage_error(tmp_path) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--pairs", str(tmp_path / "p.npz"), "--iterations", "9"])
    assert exit_.value.code == 2
