"""The LiDAR variants: each one's truth maps its source onto the target's frame, the crops hold what they say, the
set is seeded, and the odometry guesses lie as far off the truth as asked."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout
from scipy.spatial.transform import Rotation

import bench.lidar_variants
from bench.lidar_variants import PAIR, RADII, load_pair, main, odometry_guesses, seen_from, variants
from bench.real_scans import data_dir
from service.registrar import default_threads
from service.rotation_search import rotation_between_deg

needs_pair = pytest.mark.skipif(not (data_dir() / f"{PAIR}.npz").exists(),
                                reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")


@pytest.fixture(scope="module")
def pair():
    return load_pair(data_dir())


@needs_pair
def test_the_truth_takes_the_source_back_to_the_target_frame_and_the_crops_hold(pair):
    source_in_target, target = pair
    src, tgt, truth = seen_from(source_in_target, target, 20.0, 0.7, 130.0, 20.0)
    back = src.astype(np.float64) @ truth[:3, :3].T + truth[:3, 3]  # [N, 3] in the target's frame
    sensor = truth[:3, 3]
    assert np.isclose(np.linalg.norm(sensor), 20.0) and np.isclose(sensor[2], 0.0)
    assert np.linalg.norm(back[:, :2] - sensor[:2], axis=1).max() < 20.0 + 1e-3
    assert np.linalg.norm(tgt[:, :2], axis=1).max() < 20.0 + 1e-3  # float32
    kept = np.linalg.norm(source_in_target[:, :2] - sensor[:2], axis=1) < 20.0
    assert np.abs(back - source_in_target[kept]).max() < 1e-3  # float32 rounding of ~20 m coordinates


@needs_pair
def test_the_variants_are_seeded_and_turned_ones_keep_their_truth():
    first, again = list(variants(data_dir())), list(variants(data_dir()))
    assert len(first) == len(RADII) * 4 * 3 * 2
    for (label, src, _, truth), (label2, src2, _, truth2) in zip(first, again, strict=True):
        assert label == label2 and np.array_equal(src, src2) and np.array_equal(truth, truth2)
    (_, level, _, truth), (_, turned_src, _, truth_t) = first[0], first[1]
    moved = [c.astype(np.float64) @ T[:3, :3].T + T[:3, 3] for c, T in ((level, truth), (turned_src, truth_t))]
    assert np.abs(moved[0] - moved[1]).max() < 1e-3  # both variants land on the same points of the target's frame


def test_odometry_guesses_lie_as_far_off_the_truth_as_asked_and_are_seeded():
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix(), [12.0, -3.0, 0.4]
    guesses, again = odometry_guesses(5.0, 1.0), odometry_guesses(5.0, 1.0)
    first = [guesses(truth) for _ in range(4)]
    for guess in first:
        assert np.isclose(rotation_between_deg(guess[:3, :3], truth[:3, :3]), 5.0)
        assert np.isclose(np.linalg.norm(guess[:3, 3] - truth[:3, 3]), 1.0)  # the source's origin moved 1 m
    assert not np.allclose(first[0], first[1])  # a new axis and direction per case
    assert all(np.array_equal(a, again(truth)) for a in first)


@needs_pair
def test_the_report_names_the_machine_and_what_made_it(tmp_path, monkeypatch):
    monkeypatch.setattr(bench.lidar_variants, "registered", lambda cases, **_: [])  # no registration: the report only
    out = tmp_path / "lidar.json"
    main([str(data_dir()), "--no-fpfh", "--json", str(out)])
    written = json.loads(out.read_text())
    assert (written["machine"]["cpus"], written["machine"]["threads"]) == (os.cpu_count(), default_threads())
    assert "fpfh_threads" not in written["machine"]  # FPFH + RANSAC + ICP did not run
    assert_made_by_this_checkout(written["provenance"])
