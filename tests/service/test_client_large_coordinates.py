"""The Python client with UTM-sized arrays: sent recentred as float32, the pose comes back in the caller's frame."""

from __future__ import annotations

import numpy as np
from api_server import main_server, modelnet_pair

from service.client import MfgnetClient, pose_from_response, recentred_transform, shared_offset

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
