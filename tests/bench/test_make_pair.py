"""bench.make_pair: a user's two clouds and ground-truth pose as a real-scan pair file, registered by
``bench.real_scans`` through a real server; success thresholds for sensors of no class (``--thresholds``, a pair
file's own); and their usage errors."""

import json
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from pypcd4 import PointCloud
from scipy.spatial.transform import Rotation
from shapes import lumpy_sphere

from bench import make_pair, real_scans
from bench.scan_pairs import derived_pairs, read_pair
from service.pointcloud_io import read_points

POINTS = 3000


def pose(degrees: tuple[float, float, float], shift: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_euler("zyx", degrees, degrees=True).as_matrix(), shift
    return T


TRUTH = pose((40, -20, 10), (0.3, -0.2, 0.5))  # T_target_source


def write_ply(path: Path, points: np.ndarray) -> Path:
    vertex = np.zeros(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    return path


def scans(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A source (.ply, plyfile) and a target (.pcd, pypcd4): the same lumpy sphere sampled twice, the target moved by
    :data:`TRUTH`; and the pose as ``np.savetxt`` writes it."""
    source = write_ply(tmp_path / "scan_1.ply", lumpy_sphere(POINTS, seed=1))
    target = tmp_path / "scan_0.pcd"
    PointCloud.from_xyz_points((lumpy_sphere(POINTS, seed=2) @ TRUTH[:3, :3].T + TRUTH[:3, 3]).astype(np.float32)).save(
        str(target)
    )
    transform = tmp_path / "T_0_1.txt"
    np.savetxt(transform, TRUTH)
    return source, target, transform


def test_pairs_made_from_real_files_register_over_http_with_their_thresholds(tmp_path, capsys):
    """Two pairs of a user's sensors of no class: one with its thresholds in the file, one given --thresholds."""
    source, target, transform = scans(tmp_path)
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    made = make_pair.main(
        [
            str(source),
            str(target),
            "--transform",
            str(transform),
            "--sensor",
            "lab-scanner",
            "--thresholds",
            "5,0.01",
            "--out",
            str(pairs / "lab_1_0.npz"),
        ]
    )
    assert made == pairs / "lab_1_0.npz" and "wrote" in capsys.readouterr().out
    with np.load(made) as data:  # the format the set's README and docs/REAL_SCANS.md give
        assert data["source"].dtype == np.float32 and data["source"].shape == (POINTS, 3)
        assert data["target"].dtype == np.float32 and data["transform"].dtype == np.float64
        np.testing.assert_allclose(data["transform"], TRUTH, atol=1e-12)
        assert str(data["sensor"]) == "lab-scanner"
        assert float(data["rotation_threshold_deg"]) == 5.0 and float(data["translation_threshold"]) == 0.01
    # the second from .npy clouds and the pose as mfgnet register --out writes one (JSON, 'transform')
    np.save(tmp_path / "a.npy", lumpy_sphere(POINTS, seed=3))
    np.save(tmp_path / "b.npy", lumpy_sphere(POINTS, seed=4) @ TRUTH[:3, :3].T + TRUTH[:3, 3])
    (tmp_path / "pose.json").write_text(json.dumps({"transform": TRUTH.tolist(), "rotation": "ignored"}))
    make_pair.main(
        [
            str(tmp_path / "a.npy"),
            str(tmp_path / "b.npy"),
            "--transform",
            str(tmp_path / "pose.json"),
            "--sensor",
            "robot-depth",
            "--out",
            str(pairs / "robot_a_b.npz"),
        ]
    )
    capsys.readouterr()

    report = real_scans.main(
        [
            str(pairs),
            "--no-fpfh",
            "--scales",
            "1",
            "1000",
            "--thresholds",
            "robot-depth=5,0.02",
            "--json",
            str(tmp_path / "report.json"),
        ]
    )
    printed = capsys.readouterr().out
    assert "success for lab-scanner: rotation error < 5 deg and translation error < 0.01" in printed
    assert "success for robot-depth: rotation error < 5 deg and translation error < 0.02" in printed
    assert "lab_1_0                scanned   x1000 |" in printed  # the scale, not a unit the files may not be in
    assert report["thresholds"] == {"robot-depth": [5.0, 0.02]}
    rows = {(r["pair"], r["variant"], r["scale"]): r for r in report["pairs"]}
    assert len(rows) == 8 and all(r["service"]["status"] == 200 for r in rows.values())
    for name, sensor, metres in (("lab_1_0", "lab-scanner", 0.01), ("robot_a_b", "robot-depth", 0.02)):
        for scale in (1.0, 1000.0):
            row = rows[(name, "scanned", scale)]
            assert row["sensor"] == sensor
            assert row["thresholds"] == {"rotation_deg": 5.0, "translation": pytest.approx(metres * scale)}
            assert row["service"]["success"], row  # the pose a user's pair states is the one measured against
    assert report["totals"]["x1"]["cases"] == 4 and report["totals"]["x1"]["service_successes"] >= 2


def test_thresholds_come_from_the_option_then_the_pair_file_then_the_class(tmp_path):
    cloud = lumpy_sphere(100).astype(np.float32)
    np.savez(
        tmp_path / "own.npz",
        source=cloud,
        target=cloud,
        transform=np.eye(4),
        sensor="lidar",
        rotation_threshold_deg=2.0,
        translation_threshold=0.1,
    )
    np.savez(tmp_path / "plain.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="lidar")
    np.savez(tmp_path / "other.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="tof-camera")

    def limits(**kwargs) -> dict[str, tuple[float, float]]:
        cases = real_scans.load_cases(tmp_path, scales=(1.0, 1000.0), **kwargs)
        return {(c.name, c.scale): real_scans.case_thresholds(c) for c in cases if c.variant == "scanned"}

    by_file = limits(names=["own", "plain"])
    assert by_file == {
        ("own", 1.0): (2.0, 0.1),
        ("own", 1000.0): (2.0, 100.0),  # the file's, scaled
        ("plain", 1.0): (5.0, 2.0),
        ("plain", 1000.0): (5.0, 2000.0),
    }  # the lidar class's
    by_option = limits(sensor_thresholds={"lidar": (10.0, 0.5), "tof-camera": (3.0, 0.004)})
    assert by_option[("own", 1.0)] == by_option[("plain", 1.0)] == (10.0, 0.5)  # before the file's and the class's
    assert by_option[("other", 1000.0)] == (3.0, 4.0)
    case = next(c for c in real_scans.load_cases(tmp_path, names=["own"], scales=(1.0,)) if c.variant == "scanned")
    turned_a_degree = Rotation.from_euler("z", 1, degrees=True).as_matrix()
    assert real_scans.judged(case, turned_a_degree, np.array([0.05, 0.0, 0.0]))["success"]
    assert not real_scans.judged(case, turned_a_degree, np.array([0.15, 0.0, 0.0]))["success"]  # class: 2 m


def test_derived_pairs_keep_thresholds_their_files_agree_on(tmp_path):
    blob = lumpy_sphere(200).astype(np.float32)
    for j, i in ((1, 0), (2, 1)):  # the same points for each scan: the files share scans 1
        np.savez(
            tmp_path / f"obj_{j}_{i}.npz",
            source=blob + j,
            target=blob + i,
            transform=np.eye(4),
            sensor="tof-camera",
            rotation_threshold_deg=4.0,
            translation_threshold=0.02,
        )
    (derived,) = derived_pairs(tmp_path)
    assert derived.name == "obj_2_0" and derived.limits == (4.0, 0.02)
    np.savez(
        tmp_path / "obj_2_1.npz",
        source=blob + 2,
        target=blob + 1,
        transform=np.eye(4),
        sensor="tof-camera",
        rotation_threshold_deg=4.0,
        translation_threshold=0.03,
    )
    assert derived_pairs(tmp_path)[0].limits is None  # the files disagree: none of theirs


def run_real_scans(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_info:
        real_scans.main([*argv, "--no-fpfh", "--url", "http://127.0.0.1:9"])  # nothing listens there
    assert exit_info.value.code == 2
    return capsys.readouterr().err


def test_a_sensor_of_no_class_is_refused_naming_the_option_that_gives_thresholds(tmp_path, capsys):
    cloud = lumpy_sphere(100).astype(np.float32)
    np.savez(tmp_path / "frames.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="velodyne-hdl64")
    err = run_real_scans([str(tmp_path)], capsys)
    assert "sensor 'velodyne-hdl64' is of no class with success thresholds" in err
    assert "--thresholds 'velodyne-hdl64=DEG,DIST'" in err and "rotation_threshold_deg" in err


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["--thresholds", "velodyne-hdl64"], "expected SENSOR=DEG,DIST"),
        (["--thresholds", "velodyne-hdl64=5"], "expected SENSOR=DEG,DIST"),
        (["--thresholds", "velodyne-hdl64=5,x"], "must be numbers"),
        (["--thresholds", "velodyne-hdl64=5,0"], "must be positive"),
        (["--thresholds", "velodyne-hdl64=nan,1"], "must be positive"),
        (["--thresholds", "=5,1"], "expected SENSOR=DEG,DIST"),
        (["--thresholds", "velodyne-hdl64=5,1", "--thresholds", "velodyne-hdl64=3,1"], "given twice"),
        (["--thresholds", "velodyne=5,1"], "no pair of the run has sensor 'velodyne' (there: velodyne-hdl64)"),
    ],
    ids=["no_values", "one_value", "word", "zero", "nan", "no_sensor", "twice", "misspelt"],
)
def test_bad_thresholds_are_usage_errors(tmp_path, capsys, argv, fragment):
    cloud = lumpy_sphere(100).astype(np.float32)
    np.savez(tmp_path / "frames.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="velodyne-hdl64")
    assert fragment in run_real_scans([str(tmp_path), *argv], capsys)


@pytest.mark.parametrize(
    ("fields", "fragment"),
    [
        ({"rotation_threshold_deg": 5.0}, "rotation_threshold_deg without translation_threshold"),
        ({"translation_threshold": 0.1}, "translation_threshold without rotation_threshold_deg"),
        (
            {"rotation_threshold_deg": 5.0, "translation_threshold": -0.1},
            "translation_threshold is float64 [] -0.1, not",
        ),
        ({"rotation_threshold_deg": [5.0, 1.0], "translation_threshold": 0.1}, "rotation_threshold_deg is float64 [2]"),
        ({"rotation_threshold_deg": "5", "translation_threshold": 0.1}, "not a positive number"),
    ],
    ids=["rotation_alone", "translation_alone", "negative", "array", "text"],
)
def test_a_pair_file_with_bad_thresholds_is_refused_naming_the_file(tmp_path, capsys, fields, fragment):
    cloud = lumpy_sphere(100).astype(np.float32)
    np.savez(tmp_path / "frames.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="tof", **fields)
    with pytest.raises(ValueError, match=r"frames\.npz: not a scan pair"):
        read_pair(tmp_path / "frames.npz")
    err = run_real_scans([str(tmp_path)], capsys)
    assert "frames.npz: not a scan pair" in err and fragment in err


def bad_cloud(tmp_path: Path) -> Path:
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n")
    return tmp_path / "bad.ply"


def few_points(tmp_path: Path) -> Path:
    np.save(tmp_path / "few.npy", lumpy_sphere(10))
    return tmp_path / "few.npy"


def written(name: str, content: str) -> object:
    def write(tmp_path: Path) -> Path:
        (tmp_path / name).write_text(content)
        return tmp_path / name

    return write


SCALED = "\n".join(" ".join(map(str, row)) for row in np.diag([1.01, 1.0, 1.0, 1.0]))


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"source": lambda p: p / "nowhere.ply"}, "nowhere.ply: cannot read it: No such file"),
        ({"target": lambda p: p}, "a folder, not a file"),
        ({"target": bad_cloud}, "TARGET: bad.ply"),
        ({"source": few_points}, "SOURCE few.npy: needs at least 32 points"),
        ({"transform": lambda p: p / "missing.txt"}, "--transform missing.txt: cannot read it"),
        ({"transform": lambda p: p}, "cannot read it: a folder, not a file"),
        (
            {"transform": written("T.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n")},
            "--transform T.txt: expected a 4x4 matrix, got [3, 4]",
        ),
        ({"transform": written("T.json", '{"rotation": []}')}, "--transform T.json: JSON object has no 'transform'"),
        ({"transform": written("T.yaml", "")}, "--transform T.yaml: expected a .json, .npy or .txt file"),
        (
            {"transform": written("T.txt", SCALED)},
            "--transform T.txt: not a rigid pose (must be rigid: its rotation must be orthonormal",
        ),
        ({"thresholds": "5"}, "expected DEG,DIST"),
        ({"thresholds": "5,-1"}, "must be positive"),
        ({"sensor": " "}, "--sensor must not be empty"),
        ({"out": lambda p: p / "pair.npy"}, "must end in .npz"),
        ({"out": lambda p: p / "absent" / "pair.npz"}, "folder"),
    ],
    ids=[
        "source_missing",
        "target_folder",
        "target_unreadable",
        "too_few_points",
        "transform_missing",
        "transform_folder",
        "transform_3x4",
        "json_without_transform",
        "transform_yaml",
        "transform_scaled",
        "thresholds_one",
        "thresholds_negative",
        "sensor_blank",
        "out_not_npz",
        "out_folder_absent",
    ],
)
def test_make_pair_usage_errors(tmp_path, capsys, change, fragment):
    source, target, transform = scans(tmp_path)
    given = {
        "source": source,
        "target": target,
        "transform": transform,
        "sensor": "lab",
        "thresholds": None,
        "out": tmp_path / "pair.npz",
    }
    given.update({key: value(tmp_path) if callable(value) else value for key, value in change.items()})
    argv = [
        str(given["source"]),
        str(given["target"]),
        "--transform",
        str(given["transform"]),
        "--sensor",
        given["sensor"],
        "--out",
        str(given["out"]),
    ] + (["--thresholds", given["thresholds"]] if given["thresholds"] else [])
    with pytest.raises(SystemExit) as exit_info:
        make_pair.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err
    assert not (tmp_path / "pair.npz").exists()


def test_make_pair_warns_of_a_pose_given_the_other_way_round(tmp_path, capsys):
    source, target, _ = scans(tmp_path)
    inverse = tmp_path / "T_1_0.npy"
    np.save(inverse, np.linalg.inv(TRUTH))
    make_pair.main(
        [str(source), str(target), "--transform", str(inverse), "--sensor", "lab", "--out", str(tmp_path / "pair.npz")]
    )
    assert "is it T_source_target? --transform takes T_target_source" in capsys.readouterr().err
    make_pair.main(
        [
            str(source),
            str(target),
            "--transform",
            str(tmp_path / "T_0_1.txt"),
            "--sensor",
            "lab",
            "--out",
            str(tmp_path / "pair.npz"),
        ]
    )
    assert "warning" not in capsys.readouterr().err


def test_make_pair_warns_where_float32_rounds_the_clouds_out_of_shape(tmp_path, capsys):
    """Clouds in UTM (float64 files): float32 rounds them by 0.25-0.5 m, most of a 1 m object; the pair is written and
    the warning says so and what to do. The same clouds near the origin get no warning (above)."""
    utm = np.array([512_345.0, 4_123_456.0, 87.0])
    source = tmp_path / "far_source.npy"
    target = tmp_path / "far_target.npy"
    np.save(source, lumpy_sphere(POINTS, seed=1) + utm)
    np.save(target, lumpy_sphere(POINTS, seed=2) + utm)
    np.savetxt(tmp_path / "T.txt", np.eye(4))
    make_pair.main([str(source), str(target), "--transform", str(tmp_path / "T.txt"), "--sensor", "lab",
                    "--out", str(tmp_path / "pair.npz")])
    err = capsys.readouterr().err
    assert "of the smaller cloud's RMS radius" in err and "move both clouds by one offset first" in err, err
    assert (tmp_path / "pair.npz").exists()


def test_make_pair_warns_where_clouds_were_moved_without_their_pose(tmp_path, capsys):
    """Both clouds moved by one offset with the pose kept as it was: the pose lays the source nowhere near the target,
    and the warning says how to move the pose with them."""
    source, target, _ = scans(tmp_path)
    offset = np.array([40.0, -25.0, 3.0])
    for name, path in (("moved_source.npy", source), ("moved_target.npy", target)):
        np.save(tmp_path / name, read_points(path).astype(np.float64) - offset)
    make_pair.main([str(tmp_path / "moved_source.npy"), str(tmp_path / "moved_target.npy"), "--transform",
                    str(tmp_path / "T_0_1.txt"), "--sensor", "lab", "--out", str(tmp_path / "pair.npz")])
    err = capsys.readouterr().err
    assert "nor its inverse lays the source onto the target" in err and "t' = t + R o - o" in err, err
