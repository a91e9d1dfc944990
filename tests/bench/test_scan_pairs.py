"""bench.scan_pairs: pairs derived from the set's by chaining ground truth through shared scans; and
``bench.real_scans --derived`` registering them through a real server."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

from bench import real_scans
from bench.scan_pairs import derived_pairs, read_pairs

DATA = real_scans.data_dir()
needs_data = pytest.mark.skipif(not (DATA / "dragon_24_0.npz").exists(),
                                reason=f"real-scan set absent ({DATA}; set MFGNET_REAL_DATA)")


def pose(degrees: tuple[float, float, float], shift: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_euler("zyx", degrees, degrees=True).as_matrix(), shift
    return T


def moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return (points @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


# scan k of the object "blob" is the blob moved by WORLD[k] (scan -> world); the set pairs 1 -> 0 and 2 -> 1
WORLD = {0: np.eye(4), 1: pose((30, 5, -10), (0.1, 0.2, 0.0)), 2: pose((-25, 10, 5), (0.0, -0.3, 0.4))}


def write_set(directory: Path, points: int = 400) -> dict[int, np.ndarray]:
    blob = asymmetric_blob(points)
    scans = {k: moved(blob, np.linalg.inv(T)) for k, T in WORLD.items()}  # world -> scan k
    for j, i in ((1, 0), (2, 1)):
        np.savez(directory / f"blob_{j}_{i}.npz", source=scans[j], target=scans[i],
                 transform=np.linalg.inv(WORLD[i]) @ WORLD[j], sensor="cyberware-range")
    return scans


def test_the_unpaired_scans_are_paired_with_the_chained_ground_truth(tmp_path):
    scans = write_set(tmp_path)
    derived = derived_pairs(tmp_path)
    assert [p.name for p in derived] == ["blob_2_0"]
    pair = derived[0]
    assert np.array_equal(pair.source, scans[2]) and np.array_equal(pair.target, scans[0])
    np.testing.assert_allclose(pair.src_to_tgt, np.linalg.inv(WORLD[0]) @ WORLD[2], atol=1e-9)
    np.testing.assert_allclose(moved(pair.source, pair.src_to_tgt), pair.target, atol=1e-5)
    assert pair.sensor == "cyberware-range"


def test_a_label_reused_with_other_points_is_another_scan(tmp_path):
    write_set(tmp_path)
    with np.load(tmp_path / "blob_2_1.npz") as data:
        target = data["target"] + np.float32(0.001)  # "scan 1" again, but not the points blob_1_0 holds
        np.savez(tmp_path / "blob_2_1.npz", source=data["source"], target=target, transform=data["transform"],
                 sensor=data["sensor"])
    assert derived_pairs(tmp_path) == []


def test_pairs_named_otherwise_or_already_held_are_not_derived(tmp_path):
    scans = write_set(tmp_path)
    np.savez(tmp_path / "blob_0_2.npz", source=scans[0], target=scans[2], transform=np.linalg.inv(WORLD[2]),
             sensor="cyberware-range")  # the set holds 0 -> 2: 2 -> 0 is no longer derived
    np.savez(tmp_path / "other.npz", source=scans[0], target=scans[1], transform=np.eye(4), sensor="lidar")
    assert derived_pairs(tmp_path) == []
    assert [p.name for p in read_pairs(tmp_path)] == ["blob_0_2", "blob_1_0", "blob_2_1", "other"]


def test_derived_cases_are_turned_and_scaled_like_the_sets(tmp_path):
    write_set(tmp_path)
    cases = real_scans.load_cases(tmp_path, seed=0, scales=(1.0, 1000.0), derived=True)
    assert [(c.name, c.variant, c.scale) for c in cases] == [
        ("blob_2_0", v, s) for s in (1.0, 1000.0) for v in ("scanned", "turned")]
    for case in cases:
        np.testing.assert_allclose(moved(case.source, case.src_to_tgt), case.target, atol=1e-5 * case.scale)


def test_derived_pairs_register_through_a_real_server(tmp_path):
    write_set(tmp_path, points=2000)
    report = real_scans.main([str(tmp_path), "--derived", "--no-fpfh", "--scales", "1"])
    assert report["derived"] and [(r["pair"], r["variant"]) for r in report["pairs"]] == [
        ("blob_2_0", "scanned"), ("blob_2_0", "turned")]
    assert all(r["service"]["status"] == 200 for r in report["pairs"])
    assert report["pairs"][0]["service"]["success"]  # the same blob about 28 deg turned: the service finds it


def test_a_set_without_derived_pairs_is_refused(tmp_path, capsys):
    np.savez(tmp_path / "solo_1_0.npz", source=np.zeros((40, 3), np.float32), target=np.ones((40, 3), np.float32),
             transform=np.eye(4), sensor="lidar")
    with pytest.raises(SystemExit):
        real_scans.main([str(tmp_path), "--derived", "--no-fpfh"])
    assert "no derived pairs to register" in capsys.readouterr().err


@needs_data
def test_the_dragon_scans_give_the_wider_turntable_pairs():
    derived = derived_pairs(DATA)
    held = {p.name for p in read_pairs(DATA)}
    names = [p.name for p in derived]
    assert len(names) == 15 and not held & set(names)
    gaps = {int(n.split("_")[1]) - int(n.split("_")[2]) for n in names}
    assert gaps == {72, 96, 120, 144, 168}  # the set's own dragon pairs are 24 and 48 deg apart
    by_name = {p.name: p.src_to_tgt for p in read_pairs(DATA)}
    chained = by_name["dragon_24_0"] @ by_name["dragon_48_24"] @ by_name["dragon_72_48"]  # another chain, 72 -> 0
    np.testing.assert_allclose(next(p for p in derived if p.name == "dragon_72_0").src_to_tgt, chained, atol=1e-9)


@pytest.mark.parametrize(("arrays", "problem"), [
    ({"source": np.ones((5, 2))}, "source is float64 [5, 2], not [N, 3] numbers"),
    ({"target": np.ones((0, 3))}, "target is float64 [0, 3], not [N, 3] numbers"),
    ({"source": np.array([["a", "b", "c"]])}, "not [N, 3] numbers"),
    ({"target": np.array([[0, 0, 0], [np.nan, 0, 0]])}, "target has 1 rows that are not finite"),
    ({"transform": np.eye(3)}, "transform is float64 [3, 3], not a finite [4, 4]"),
    ({"sensor": np.array(3)}, "sensor is int64 [], not a string"),
    # a scaled rotation judged a pose 0 deg off, a last row of 0 0 0 2 passed: the ground truth must be a rigid pose
    ({"transform": np.diag([2.0, 2.0, 2.0, 1.0])}, "transform is not a rigid pose (must be rigid: its rotation"),
    ({"transform": np.diag([1.0, 1.0, 1.0, 2.0])}, "its last row must be 0 0 0 1"),
    # finite as float64, infinite as the float32 the benchmark uploads: every case was a silent 422 miss
    ({"source": np.full((5, 3), 1e39)}, "source has 5 rows that are not finite as float32"),
], ids=["2d source", "empty target", "text points", "nan", "3x3 pose", "sensor number", "scaled rotation",
        "last row", "beyond float32"])
def test_a_file_that_is_no_pair_is_refused_naming_it_and_the_problem(arrays, problem, tmp_path):
    pair = {"source": np.ones((5, 3)), "target": np.ones((5, 3)), "transform": np.eye(4), "sensor": "lidar", **arrays}
    np.savez(tmp_path / "a_1_0.npz", **pair)
    with pytest.raises(ValueError, match=r"a_1_0\.npz: not a scan pair") as refused:
        read_pairs(tmp_path)
    assert problem in str(refused.value)
