"""The Python client with UTM-sized arrays: sent recentred as float32, the pose comes back in the caller's frame."""

from __future__ import annotations

import numpy as np
import pytest
from api_server import main_server, modelnet_pair

from service.client import MfgnetClient, MfgnetError, pose_from_response, recentred_transform, shared_offset

UTM = np.array([512_345.0, 4_123_456.0, 87.0])  # metres: float32 keeps only ~0.25-0.5 m here


def test_small_coordinates_are_sent_as_they_are():
    assert shared_offset(np.ones((5, 3)), np.zeros((5, 3))) is None


def test_recentred_transform_is_the_same_motion():
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
    T[:3, 3] = [1.0, 2.0, 3.0]
    points = rng.normal(size=(10, 3)) + UTM
    moved = np.asarray(recentred_transform(T, UTM))
    np.testing.assert_allclose((points - UTM) @ moved[:3, :3].T + moved[:3, 3],
                               points @ T[:3, :3].T + T[:3, 3] - UTM, atol=1e-6)


def test_utm_arrays_register_like_the_same_clouds_near_the_origin():
    pair = modelnet_pair(3)
    near = np.asarray(pair.source, np.float64), np.asarray(pair.target, np.float64)
    far = near[0] + UTM, near[1] + UTM  # the same scene in UTM coordinates
    with MfgnetClient(main_server().url, timeout=60) as client:
        R0, t0 = pose_from_response(client.register(*near, binary=True, rotation_search=False))
        R1, t1 = pose_from_response(client.register(*far, binary=True, rotation_search=False))
    angle = np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1))
    assert angle < 1e-6
    extent = np.ptp(near[0], axis=0).max()
    np.testing.assert_allclose(t1, t0 + UTM - R0 @ UTM, atol=1e-6 * extent + 1e-9 * np.abs(UTM).max())


def test_shared_offset_leaves_out_the_rows_the_server_refuses():
    points = np.random.default_rng(1).normal(size=(50, 3)) + UTM
    with_bad_rows = np.array(points)
    with_bad_rows[3, 0], with_bad_rows[9, 2], with_bad_rows[11, 1] = np.nan, -np.inf, 1e39
    kept = np.delete(with_bad_rows, [3, 9, 11], axis=0)
    np.testing.assert_array_equal(shared_offset(with_bad_rows, points), shared_offset(kept, points))
    np.testing.assert_array_equal(shared_offset(list(kept), kept.tolist()), np.round(kept.mean(0)))


def test_utm_array_with_a_nan_row_is_refused_naming_that_row():
    pair = modelnet_pair(3)
    far = np.asarray(pair.source, np.float64) + UTM
    far[3, 0] = np.nan
    with MfgnetClient(main_server().url, timeout=60) as client, pytest.raises(MfgnetError) as info:
        client.register(far, np.asarray(pair.target, np.float64) + UTM, binary=True)
    assert info.value.status == 422
    assert "1 point(s)" in info.value.message and "first at index 3" in info.value.message


def test_utm_arrays_with_a_fourth_column_register_on_their_first_three():
    pair = modelnet_pair(3)
    far = np.asarray(pair.source, np.float64) + UTM, np.asarray(pair.target, np.float64) + UTM
    with_intensity = tuple(np.c_[cloud, np.arange(len(cloud))] for cloud in far)  # [N, 4]: the server reads x, y, z
    with MfgnetClient(main_server().url, timeout=60) as client:
        expected = client.register(*far, binary=True, rotation_search=False)
        response = client.register(*with_intensity, binary=True, rotation_search=False)
    np.testing.assert_allclose(response["transform"], expected["transform"], atol=1e-9)
