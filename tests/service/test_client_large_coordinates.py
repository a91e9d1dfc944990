"""The Python client with UTM-sized arrays: each cloud sent recentred as float32, the pose comes back in the caller's
frame, also for a local scan registered into a map in UTM."""

from __future__ import annotations

import numpy as np
import pytest
from api_server import main_server, modelnet_pair

from service.client import MfgnetClient, MfgnetError, cloud_offsets, pose_from_response, recentred_transform

UTM = np.array([512_345.0, 4_123_456.0, 87.0])  # metres: float32 keeps only ~0.25-0.5 m here


def test_small_coordinates_are_sent_as_they_are():
    assert cloud_offsets(np.ones((5, 3)), np.zeros((5, 3))) is None


def test_recentred_transform_is_the_same_motion():
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
    T[:3, 3] = [1.0, 2.0, 3.0]
    points = rng.normal(size=(10, 3)) + UTM
    for source_offset, target_offset in ((UTM, UTM), (UTM, np.zeros(3)), (np.zeros(3), UTM)):
        moved = np.asarray(recentred_transform(T, source_offset, target_offset))
        np.testing.assert_allclose((points - source_offset) @ moved[:3, :3].T + moved[:3, 3],
                                   points @ T[:3, :3].T + T[:3, 3] - target_offset, atol=1e-6)


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


def test_a_small_object_far_from_the_origin_is_recentred_too():
    """A ModelNet40 pair scaled to 6 cm across and 6 km from the origin: within ``LARGE_COORDINATE``, yet float32's step
    there (0.5 mm) is coarse for the object; sent as it was, the server warned `float32 rounding` and asked for float64
    coordinates, which the caller had sent."""
    pair = modelnet_pair(3)
    near = np.asarray(pair.source, np.float64) * 0.06, np.asarray(pair.target, np.float64) * 0.06
    offset = np.array([6_000.0, -2_500.0, 40.0])
    far = near[0] + offset, near[1] + offset
    assert cloud_offsets(*far) is not None and cloud_offsets(*near) is None
    with MfgnetClient(main_server().url, timeout=60) as client:
        R0, t0 = pose_from_response(client.register(*near, binary=True, rotation_search=False))
        response = client.register(*far, binary=True, rotation_search=False)
    R1, t1 = pose_from_response(response)
    assert not any(w.startswith("float32 rounding") for w in response["warnings"]), response["warnings"]
    assert np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1)) < 1e-6
    np.testing.assert_allclose(t1, t0 + offset - R0 @ offset, atol=1e-6)


def test_a_small_object_beside_one_at_the_origin_gets_its_own_offset():
    """One offset for both would move the object at the origin 3 km out (the far one's centroid), or leave the far one
    where it is (an offset rounding to zero): each is moved by its own."""
    near = np.asarray(modelnet_pair(3).source, np.float64) * 0.06  # [N, 3] 6 cm across
    far = near + np.array([3_000.123, 0.3, 0.2])
    source_offset, target_offset = cloud_offsets(far, near)
    np.testing.assert_array_equal(source_offset, [3_000.0, 0.0, 0.0])
    np.testing.assert_array_equal(target_offset, np.zeros(3))
    source_offset, target_offset = cloud_offsets(near, far)
    np.testing.assert_array_equal(source_offset, np.zeros(3))
    np.testing.assert_array_equal(target_offset, [3_000.0, 0.0, 0.0])


def test_cloud_offsets_leave_out_the_rows_the_server_refuses():
    points = np.random.default_rng(1).normal(size=(50, 3)) + UTM
    with_bad_rows = np.array(points)
    with_bad_rows[3, 0], with_bad_rows[9, 2], with_bad_rows[11, 1] = np.nan, -np.inf, 1e39
    kept = np.delete(with_bad_rows, [3, 9, 11], axis=0)
    np.testing.assert_array_equal(cloud_offsets(with_bad_rows, points), cloud_offsets(kept, points))
    np.testing.assert_array_equal(cloud_offsets(list(kept), kept.tolist())[0], np.round(kept.mean(0)))


def test_each_cloud_gets_its_own_offset_and_a_local_one_none():
    local = np.random.default_rng(2).normal(size=(50, 3))
    far = local + UTM
    source_offset, target_offset = cloud_offsets(local, far)
    np.testing.assert_array_equal(source_offset, np.zeros(3))
    np.testing.assert_array_equal(target_offset, np.round(far.mean(0)))


def test_a_far_cloud_of_float32_values_is_not_moved():
    local = np.random.default_rng(2).normal(size=(50, 3))
    far = local + UTM
    as_float32 = far.astype(np.float32)
    assert cloud_offsets(as_float32, as_float32.astype(np.float64)) is None  # nothing to round: sent as they are
    source_offset, target_offset = cloud_offsets(as_float32, far)  # no shared offset: the float64 map moves alone
    np.testing.assert_array_equal(source_offset, np.zeros(3))
    np.testing.assert_array_equal(target_offset, np.round(far.mean(0)))


@pytest.mark.parametrize("far", ["target", "source"])
def test_a_local_scan_and_a_map_in_utm_register_as_in_process(far):
    """A local scan registered into a map in UTM (or the map onto the scan): the far cloud is recentred on its own, so
    float32 keeps its shape, and the pose is the one of the same clouds near each other (it was 60-150 deg off: the
    far cloud had been moved by the local one's centroid, which left it in UTM)."""
    pair = modelnet_pair(3)
    source, target = np.asarray(pair.source, np.float64), np.asarray(pair.target, np.float64)
    moved = (source, target + UTM) if far == "target" else (source + UTM, target)
    with MfgnetClient(main_server().url, timeout=60) as client:
        R0, t0 = pose_from_response(client.register(source, target, binary=True, rotation_search=False))
        R1, t1 = pose_from_response(client.register(*moved, binary=True, rotation_search=False))
    angle = np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1))
    assert angle < 1e-6
    expected = t0 + UTM if far == "target" else t0 - R0 @ UTM  # target = R source + t, in the moved frames
    extent = np.ptp(source, axis=0).max()
    np.testing.assert_allclose(t1, expected, atol=1e-6 * extent + 1e-9 * np.abs(UTM).max())


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


def test_a_prior_given_the_wrong_way_round_is_named_for_a_local_scan_onto_a_utm_map():
    """Each cloud moved by its own offset would conjugate the prior differently on either side, and the server could no
    longer see an inverted prior as the result's inverse: such clouds go unmoved, as float64."""
    pair = modelnet_pair(3)
    source, target = np.asarray(pair.source, np.float64), np.asarray(pair.target, np.float64) + UTM
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = pair.rotation, pair.translation + UTM
    with MfgnetClient(main_server().url, timeout=60) as client:
        response = client.register(source, target, binary=True, initial_transform=np.linalg.inv(truth))
    R, t = pose_from_response(response)
    assert np.abs(source @ R.T + t - (source @ truth[:3, :3].T + truth[:3, 3])).max() < 0.05
    assert any("looks given target-to-source" in warning for warning in response["warnings"]), response["warnings"]


def test_an_array_beside_a_file_keeps_its_utm_coordinates(tmp_path):
    pair = modelnet_pair(3)
    source, target = np.asarray(pair.source, np.float64) + UTM, np.asarray(pair.target, np.float64) + UTM
    np.save(tmp_path / "target.npy", target)
    with MfgnetClient(main_server().url, timeout=60) as client:
        both_arrays = client.register(source, target, binary=True, rotation_search=False)
        beside_a_file = client.register(source, tmp_path / "target.npy", binary=True, rotation_search=False)
    R0, t0 = pose_from_response(both_arrays)
    R1, t1 = pose_from_response(beside_a_file)
    moved = source @ R1.T + t1 - (source @ R0.T + t0)  # float32 of the array alone: 0.25-0.5 m steps, poses cm apart
    assert np.abs(moved).max() < 1e-3
