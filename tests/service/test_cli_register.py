"""Specification of ``mfgnet register`` in-process: every readable format, the JSON record, the aligned
cloud, initial transforms, and clear exit-code-2 errors for bad input.

Accuracy is not asserted (the bundled model may be early in training): only that the pose is a proper
rigid transform and that every file format yields the same pose as the ``.npy`` reference."""

from __future__ import annotations

import json
import os
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from cli_support import snapshot_model, synthetic_pair
from scipy.spatial.transform import Rotation
from shapes import smooth_blob
from typer.testing import CliRunner

from service.cli import app
from service.pointcloud_io import read_points, write_points

runner = CliRunner()
FAST = ("--iterations", "1", "--keypoints", "32")  # one small matcher pass: the tests check plumbing, not accuracy
RECORD_KEYS = {"rotation", "translation", "transform", "euler_zyx_deg", "yaw_pitch_roll_deg", "quaternion_xyzw",
               "quality", "warnings", "model", "iterations", "timing_ms"}
SOURCE, TARGET = synthetic_pair()


# ------------------------------------------------------------------------- hand-made file writers


def write_ply_ascii(path: Path, xyz: np.ndarray) -> None:
    header = (f"ply\nformat ascii 1.0\ncomment hand-made\nelement vertex {len(xyz)}\nproperty float x\n"
              "property float y\nproperty float z\nproperty uchar red\nend_header\n")
    body = "".join(f"{x:.9g} {y:.9g} {z:.9g} 200\n" for x, y, z in xyz)
    path.write_text(header + body)


def write_ply_big_endian(path: Path, xyz: np.ndarray) -> None:
    header = (f"ply\nformat binary_big_endian 1.0\nelement vertex {len(xyz)}\nproperty float x\n"
              "property float y\nproperty float z\nend_header\n")
    path.write_bytes(header.encode() + xyz.astype(">f4").tobytes())


def pcd_header(n: int, data: str) -> bytes:
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()


def write_pcd_ascii(path: Path, xyz: np.ndarray) -> None:
    path.write_bytes(pcd_header(len(xyz), "ascii") + "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in xyz).encode())


def write_pcd_binary_compressed(path: Path, xyz: np.ndarray) -> None:
    raw = np.ascontiguousarray(xyz.astype("<f4").T).tobytes()  # field-major: all x, all y, all z
    compressed = b"".join(bytes([len(raw[i : i + 32]) - 1]) + raw[i : i + 32] for i in range(0, len(raw), 32))
    path.write_bytes(pcd_header(len(xyz), "binary_compressed") + struct.pack("<II", len(compressed), len(raw))
                     + compressed)


# format id -> (file suffix, writer)
FORMATS = {
    "ply-binary": (".ply", write_points),
    "ply-ascii": (".ply", write_ply_ascii),
    "ply-binary-big-endian": (".ply", write_ply_big_endian),
    "pcd-binary": (".pcd", write_points),
    "pcd-ascii": (".pcd", write_pcd_ascii),
    "pcd-binary-compressed": (".pcd", write_pcd_binary_compressed),
    "xyz": (".xyz", write_points),
    "txt": (".txt", write_points),
    "csv": (".csv", write_points),
    "npy": (".npy", write_points),
    "npz": (".npz", write_points),
}


def write_pair(folder: Path, fmt: str) -> tuple[Path, Path]:
    suffix, writer = FORMATS[fmt]
    src, tgt = folder / f"source{suffix}", folder / f"target{suffix}"
    writer(src, SOURCE)
    writer(tgt, TARGET)
    return src, tgt


def assert_proper_pose_record(record: dict) -> None:
    """The JSON record is complete and its pose is a proper rigid transform."""
    assert set(record) == RECORD_KEYS
    R, t, T = (np.asarray(record[k], dtype=np.float64) for k in ("rotation", "translation", "transform"))
    assert R.shape == (3, 3) and t.shape == (3,) and T.shape == (4, 4)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(T[:3, :3], R) and np.allclose(T[:3, 3], t) and np.array_equal(T[3], [0, 0, 0, 1])
    euler = np.asarray(record["euler_zyx_deg"])
    assert euler.shape == (3,) and np.allclose(Rotation.from_euler("zyx", euler, degrees=True).as_matrix(), R)
    quality = record["quality"]
    assert set(quality) == {"inlier_ratio", "residual_rms", "reliable", "stability"}
    assert 0.0 <= quality["inlier_ratio"] <= 1.0 and quality["residual_rms"] >= 0.0
    assert isinstance(quality["reliable"], bool) and isinstance(record["warnings"], list)
    assert record["model"]["name"] == "clean" and len(record["model"]["sha256"]) == 64
    assert record["iterations"] >= 1 and record["timing_ms"]["total"] > 0


def assert_clean_failure(result, *fragments: str) -> None:
    """Exit code 2, the message on stderr, no traceback."""
    assert result.exit_code == 2, result.output
    assert not isinstance(result.exception, Exception), result.exception  # SystemExit only
    assert "Traceback" not in result.output
    for fragment in fragments:
        assert fragment in result.stderr, result.stderr


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return snapshot_model(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module", autouse=True)
def shared_registrars():
    """One loaded ``Registrar`` per model folder for the whole module (loading costs more than a small run), where
    ``LocalRegistrar`` builds one. (Patched in ``service.registrar`` alone, it took effect only where this module
    imported ``service.in_process`` first, and then broke ``Registrar.option_names``: the file failed run alone.)"""
    import service.in_process
    import service.registrar

    loaded: dict[tuple[str, int | None], service.registrar.Registrar] = {}
    real = service.registrar.Registrar

    def cached(directory, threads=None, warmup=True):
        key = (str(Path(directory).resolve()), threads)
        if key not in loaded:
            loaded[key] = real(directory, threads=threads, warmup=warmup)
        return loaded[key]

    cached.option_names = real.option_names  # what LocalRegistrar.register checks keywords against
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(service.in_process, "Registrar", cached)
        yield


@pytest.fixture(scope="module")
def reference(tmp_path_factory, model_dir) -> dict:
    """The record of the ``.npy`` pair, written with ``--out``."""
    folder = tmp_path_factory.mktemp("reference")
    src, tgt = write_pair(folder, "npy")
    out = folder / "pose.json"
    result = register(src, tgt, "--out", out, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    return json.loads(out.read_text())


def register(*args, model_dir: Path, fast: bool = True):
    """``mfgnet register ARGS --model-dir MODEL_DIR`` (plus ``FAST`` options unless ``fast=False``)."""
    return runner.invoke(app, ["register", *map(str, args), "--model-dir", str(model_dir), *(FAST if fast else ())])


# ---------------------------------------------------------------------------------------- formats


def test_reference_record_is_well_formed_and_proper(reference) -> None:
    assert_proper_pose_record(reference)


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_round_trips_to_the_same_pose_and_aligned_cloud(tmp_path, model_dir, reference, fmt) -> None:
    src, tgt = write_pair(tmp_path, fmt)
    out, aligned = tmp_path / "pose.json", tmp_path / f"aligned{FORMATS[fmt][0]}"
    result = register(src, tgt, "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads(out.read_text())
    assert_proper_pose_record(record)
    assert np.allclose(record["transform"], reference["transform"], atol=1e-5)  # same points read from every format
    R, t = np.asarray(record["rotation"]), np.asarray(record["translation"])
    assert np.allclose(read_points(aligned), SOURCE.astype(np.float64) @ R.T + t, atol=1e-5)


# ----------------------------------------------------------------------------------------- output


def test_summary_prints_the_matrix_model_quality_and_time(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--out", tmp_path / "pose.json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads((tmp_path / "pose.json").read_text())
    out = result.stdout
    assert out.startswith("transform (source -> target):")
    rows = [[float(v) for v in line.strip(" []").split()] for line in out.splitlines()[1:5]]
    assert np.allclose(rows, record["transform"], atol=1e-6)
    for label in ("model        clean 0", "inlier ratio", "reliable", "warnings", "total"):
        assert label in out
    assert "wrote" in result.stderr and "wrote" not in out


def test_the_summary_prints_one_warning_per_line(tmp_path, model_dir) -> None:
    """A warning's own text may hold '; ' (the separator before): the summary's list is read line by line."""
    rng = np.random.default_rng(4)
    np.save(tmp_path / "src.npy", rng.normal(size=(300, 3)))
    np.save(tmp_path / "tgt.npy", rng.normal(size=(300, 3)) * [1, 1, 0.01])  # flat: coplanar, weakly constrained
    result = register(tmp_path / "src.npy", tmp_path / "tgt.npy", "--out", tmp_path / "pose.json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    warnings = json.loads((tmp_path / "pose.json").read_text())["warnings"]
    assert len(warnings) >= 2 and any("; " in warning for warning in warnings), warnings
    lines = result.stdout.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("warnings"))
    assert [line[13:] for line in lines[first:first + len(warnings)]] == warnings
    assert lines[first + len(warnings)].startswith("total")


def test_the_printed_translation_of_clouds_small_in_their_unit_is_not_rounded_to_zero(tmp_path, model_dir) -> None:
    """Clouds a micrometre across in their unit: a translation of about 1e-7 printed as 0.000000."""
    np.save(tmp_path / "src.npy", SOURCE.astype(np.float64) * 1e-6)
    np.save(tmp_path / "tgt.npy", TARGET.astype(np.float64) * 1e-6)
    result = register(tmp_path / "src.npy", tmp_path / "tgt.npy", "--out", tmp_path / "pose.json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    printed = np.array([[float(v) for v in line.strip(" []").split()] for line in result.stdout.splitlines()[1:5]])
    record = np.asarray(json.loads((tmp_path / "pose.json").read_text())["transform"])
    assert 0 < np.abs(record[:3, 3]).max() < 1e-3
    np.testing.assert_allclose(printed[:3, 3], record[:3, 3], rtol=0.01, atol=1e-3 * np.abs(record[:3, 3]).max())


def test_a_cloud_onto_itself_prints_six_decimals_not_its_rounding_noise(tmp_path, model_dir) -> None:
    """A translation of 1e-15 (rounding noise) printed 17 decimals: the digits follow the clouds' size."""
    np.save(tmp_path / "src.npy", SOURCE.astype(np.float64))
    result = register(tmp_path / "src.npy", tmp_path / "src.npy", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    values = " ".join(result.stdout.splitlines()[1:5]).replace("[", " ").replace("]", " ").split()
    assert {len(v.split(".")[1]) for v in values} == {6}, result.stdout


def test_the_printed_matrix_places_map_coordinates_as_the_record_does(tmp_path, model_dir) -> None:
    offset = np.array([512345.25, 4000000.5, 120.0])  # a UTM easting and northing
    np.save(tmp_path / "src.npy", SOURCE.astype(np.float64) + offset)
    np.save(tmp_path / "tgt.npy", TARGET.astype(np.float64) + offset)
    result = register(tmp_path / "src.npy", tmp_path / "tgt.npy", "--out", tmp_path / "pose.json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    printed = np.array([[float(v) for v in line.strip(" []").split()] for line in result.stdout.splitlines()[1:5]])
    record = np.asarray(json.loads((tmp_path / "pose.json").read_text())["transform"])
    source = SOURCE.astype(np.float64) + offset
    moved = source @ printed[:3, :3].T + printed[:3, 3]  # as a user applies the printed pose
    assert np.abs(moved - (source @ record[:3, :3].T + record[:3, 3])).max() < 1e-4  # 6 decimals: metres off


def test_json_flag_prints_only_the_record(tmp_path, model_dir, reference) -> None:
    src, tgt = write_pair(tmp_path, "npz")
    result = register(src, tgt, "--json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert_proper_pose_record(record)
    assert np.allclose(record["transform"], reference["transform"], atol=1e-5)


@pytest.mark.parametrize("kind", ["json-list", "npy", "txt", "txt-commented-csv", "previous-out-file"])
def test_initial_transform_is_read_from_json_npy_txt_or_a_previous_out_file(tmp_path, model_dir, reference, kind):
    src, tgt = write_pair(tmp_path, "npy")
    if kind == "json-list":
        init = tmp_path / "init.json"
        init.write_text(json.dumps(np.eye(4).tolist()))
    elif kind == "npy":
        init = tmp_path / "init.npy"
        np.save(init, np.eye(4))
    elif kind == "txt":  # a pose as np.savetxt and other registration tools write it
        init = tmp_path / "T_target_source.txt"
        np.savetxt(init, np.eye(4))
    elif kind == "txt-commented-csv":
        init = tmp_path / "init.txt"
        init.write_text("# T_target_source\n" + "".join(", ".join(map(str, row)) + "\n" for row in np.eye(4)))
    else:
        init = tmp_path / "pose.json"
        init.write_text(json.dumps(reference))
    result = register(src, tgt, "--initial-transform", init, "--json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert_proper_pose_record(record)
    if kind != "previous-out-file":  # the identity guess changes nothing
        assert np.allclose(record["transform"], reference["transform"], atol=1e-5)


def test_icp_refinement_reports_its_time(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--refine", "icp", "--iterations", "2", "--keypoints", "64", "--json",
                      model_dir=model_dir, fast=False)
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert_proper_pose_record(record)
    assert record["iterations"] == 2 and "refine" in record["timing_ms"]


def test_point_to_plane_refinement_gives_the_in_process_pose(tmp_path, model_dir) -> None:
    import service.registrar

    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--refine", "icp-plane", "--json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert_proper_pose_record(record)
    assert "refine" in record["timing_ms"]
    registrar = service.registrar.Registrar(model_dir, threads=None, warmup=False)  # the module's shared one
    expected = registrar.register(SOURCE, TARGET, iterations=1, keypoints=32, refine="icp-plane")
    np.testing.assert_allclose(record["transform"], expected.transform, rtol=0, atol=1e-12)
    other = registrar.register(SOURCE, TARGET, iterations=1, keypoints=32, refine="icp")
    assert not np.allclose(record["transform"], other.transform, rtol=0, atol=1e-12)  # not point-to-point


def test_no_refine_option_means_icp_plane_and_refine_none_the_network_alone(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    records = {}
    for name, extra in (("default", ()), ("plane", ("--refine", "icp-plane")), ("none", ("--refine", "none"))):
        result = register(src, tgt, *extra, "--json", model_dir=model_dir)
        assert result.exit_code == 0, result.output
        records[name] = json.loads(result.stdout)
    assert records["default"]["transform"] == records["plane"]["transform"]
    assert "refine" in records["default"]["timing_ms"] and "refine" not in records["none"]["timing_ms"]
    assert records["none"]["transform"] != records["plane"]["transform"]


def test_refine_points_option_sets_the_refinement_clouds(tmp_path, model_dir, monkeypatch) -> None:
    import service.stages.refine as refine_stage

    sizes, real = [], refine_stage.refine_plane

    def spy(src_r, tgt_r, *args, **kwargs):
        sizes.append((len(src_r), len(tgt_r)))
        return real(src_r, tgt_r, *args, **kwargs)

    monkeypatch.setattr(refine_stage, "refine_plane", spy)
    source = smooth_blob(1200, seed=3)
    R = Rotation.from_euler("zyx", [8.0, -4.0, 3.0], degrees=True).as_matrix()
    np.save(tmp_path / "s.npy", source)
    np.save(tmp_path / "t.npy", (smooth_blob(1200, seed=4) @ R.T).astype(np.float32))  # another sampling
    for extra in ((), ("--refine-points", "1200")):
        result = register(tmp_path / "s.npy", tmp_path / "t.npy", *extra, "--rotation-search-mode", "off", "--json",
                          model_dir=model_dir)
        assert result.exit_code == 0, result.output
    assert sizes == [(768, 768), (1200, 1200)]
    for value in ("16", "9000"):
        result = register(tmp_path / "s.npy", tmp_path / "t.npy", "--refine-points", value, model_dir=model_dir)
        assert result.exit_code == 2 and "refine-points" in result.output


def test_rejects_an_unknown_refine_mode(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--refine", "plane", model_dir=model_dir)
    assert result.exit_code == 2 and "icp-plane" in result.output


# ------------------------------------------------------------------------------------- bad input


def test_rejects_content_that_is_no_point_cloud(tmp_path, model_dir) -> None:
    """The content decides, not the extension: an OBJ mesh is named as one, and bytes of no format are unrecognised."""
    bad = tmp_path / "cloud.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nf 1 2 1\n")
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(bad, tgt, model_dir=model_dir), "cloud.obj", "an OBJ mesh")
    bad.write_bytes(bytes(range(256)))
    assert_clean_failure(register(bad, tgt, model_dir=model_dir), "cloud.obj", "unrecognised content")


def test_rejects_rows_with_too_few_columns(tmp_path, model_dir) -> None:
    bad = tmp_path / "flat.xyz"
    bad.write_text("1 2\n3 4\n")
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(tgt, bad, model_dir=model_dir), "flat.xyz", "column")


def test_rejects_an_empty_cloud(tmp_path, model_dir) -> None:
    bad = tmp_path / "empty.csv"
    bad.write_text("x,y,z\n")
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(bad, tgt, model_dir=model_dir), "empty.csv", "empty")


def test_rejects_nan_points(tmp_path, model_dir) -> None:
    bad = tmp_path / "nan.npy"
    points = SOURCE.copy()
    points[7, 1] = np.nan
    np.save(bad, points)
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(bad, tgt, model_dir=model_dir), "nan.npy", "NaN", "index 7")


def test_rejects_a_ply_without_xyz(tmp_path, model_dir) -> None:
    bad = tmp_path / "broken.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n")
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(bad, tgt, model_dir=model_dir), "broken.ply", "lacks properties")


def test_rejects_a_missing_file(tmp_path, model_dir) -> None:
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(tmp_path / "nowhere.ply", tgt, model_dir=model_dir), "nowhere.ply",
                         "No such file")


def test_rejects_too_few_points(tmp_path, model_dir) -> None:
    small = tmp_path / "small.npy"
    np.save(small, SOURCE[:10])
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(small, tgt, model_dir=model_dir), "at least 32 points")


@pytest.mark.parametrize(("matrix", "fragment"), [
    (np.diag([1.0, 1.0, -1.0, 1.0]), "--initial-transform init.json: must be rigid"),  # the pipeline's check
    (np.eye(3), "--initial-transform init.json: expected a 4x4 matrix"),  # the file reader's
])
def test_rejects_a_bad_initial_transform(tmp_path, model_dir, matrix, fragment) -> None:
    init = tmp_path / "init.json"
    init.write_text(json.dumps(matrix.tolist()))
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--initial-transform", init, model_dir=model_dir), fragment)


def _npy_header(shape: str) -> bytes:
    header = f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}".encode()
    header += b" " * (63 - len(header)) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


@pytest.mark.parametrize(("name", "content", "fragment"), [
    ("init.npy", lambda path: np.savez(path.with_suffix(".npz"), a=np.eye(4)) or path.with_suffix(".npz").read_bytes(),
     "4x4"),  # an .npz named .npy: np.load gave an NpzFile (AttributeError)
    ("init.json", lambda path: ("[" * 100_000 + "]" * 100_000).encode(), "not a 4x4 matrix"),  # RecursionError
    ("init.json", lambda path: json.dumps([[10 ** 400, 0, 0, 0], *np.eye(4)[1:].tolist()]).encode(),
     "not a 4x4 matrix"),  # OverflowError
    ("init.npy", lambda path: _npy_header("(4, 1000000000000)"), "4x4"),  # np.load allocated 29 TiB (MemoryError)
    ("init.json", lambda path: json.dumps({"rotation": np.eye(3).tolist(), "translation": [0, 0, 0]}).encode(),
     "an object with 'transform'"),  # said only "JSON object has no 'transform'"
    ("init.txt", lambda path: b"1 0 0 0\n0 1 0 0\n0 0 1 0\n", "got [3, 4]"),
    ("init.txt", lambda path: b"1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n", "not a 4x4 matrix"),  # a short row
    ("init.txt", lambda path: b"a b c d\n" * 4, "not a 4x4 matrix"),
    ("init.txt", lambda path: b"#" * (1 << 17), "not a 4x4 matrix"),  # over 64 KiB: not read
], ids=["npz_as_npy", "deep_json", "int_beyond_float", "npy_huge_shape", "json_without_transform", "txt_3x4",
        "txt_short_row", "txt_words", "txt_huge"])
def test_an_unreadable_initial_transform_is_a_usage_error(tmp_path, model_dir, name, content, fragment) -> None:
    init = tmp_path / name
    init.write_bytes(content(init))
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--initial-transform", init, model_dir=model_dir), fragment)


def test_a_fifo_is_refused_not_waited_on(tmp_path, model_dir) -> None:
    """open() of a FIFO with no writer blocked for ever."""
    fifo = tmp_path / "cloud.npy"
    os.mkfifo(fifo)
    _, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(fifo, tgt, model_dir=model_dir), "not a regular file")


def test_a_fifo_as_initial_transform_is_refused_not_waited_on(tmp_path, model_dir) -> None:
    fifo = tmp_path / "init.json"
    os.mkfifo(fifo)
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--initial-transform", fifo, model_dir=model_dir), "not a regular file")


def test_threads_are_bounded(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--threads", "100000", model_dir=model_dir)
    assert result.exit_code == 2 and "threads" in result.output


def test_rejects_out_of_range_options(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--keypoints", "4", model_dir=model_dir, fast=False), "keypoints")


@pytest.mark.parametrize("name", ["nope", ""])  # "" named the working directory
def test_rejects_an_unknown_model_and_lists_the_available_ones(tmp_path, model_dir, name) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--model", name, model_dir=model_dir), f"'{name}' not found", "clean")


def test_rejects_an_unwritable_aligned_format_before_registering(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--write-aligned", tmp_path / "aligned.obj", model_dir=model_dir)
    assert_clean_failure(result, "aligned.obj", "unknown extension")


@pytest.mark.parametrize("option", ["--out", "--write-aligned"])
def test_rejects_an_output_in_a_folder_or_a_missing_one_before_registering(tmp_path, model_dir, option) -> None:
    """--out to a folder failed only after the registration had run."""
    src, tgt = write_pair(tmp_path, "npy")
    (tmp_path / "folder.ply").mkdir()
    assert_clean_failure(register(src, tgt, option, tmp_path / "folder.ply", model_dir=model_dir), "a folder")
    missing = tmp_path / "nowhere" / "x.ply"
    assert_clean_failure(register(src, tgt, option, missing, model_dir=model_dir), "does not exist")


@pytest.mark.parametrize("option", ["--out", "--write-aligned"])
@pytest.mark.parametrize("victim", ["SOURCE", "TARGET", "--initial-transform"])
def test_an_output_that_names_an_input_is_refused_and_the_input_kept(tmp_path, model_dir, option, victim) -> None:
    """--out or --write-aligned onto SOURCE, TARGET or the --initial-transform file (named another way too) replaced
    the user's file; now a usage error before any registration, the file as it was."""
    src, tgt = write_pair(tmp_path, "npy")
    prior = tmp_path / "prior.npy"
    np.save(prior, np.eye(4))
    named = {"SOURCE": src, "TARGET": tgt, "--initial-transform": prior}[victim]
    before = named.read_bytes()
    (tmp_path / "sub").mkdir()
    os.link(named, tmp_path / f"hard_link{named.suffix}")
    for other_name in (tmp_path / "sub" / ".." / named.name, tmp_path / f"hard_link{named.suffix}"):  # other paths
        result = register(src, tgt, "--initial-transform", prior, option, other_name, model_dir=model_dir)
        assert_clean_failure(result, f"is the {victim} file; it would be overwritten")
        assert named.read_bytes() == before


def test_out_and_write_aligned_may_not_name_one_file(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    result = register(src, tgt, "--out", tmp_path / "both.ply", "--write-aligned", tmp_path / "both.ply",
                      model_dir=model_dir)
    assert_clean_failure(result, "--out and --write-aligned are the same file")
    assert not (tmp_path / "both.ply").exists()


def test_a_corrupted_model_fails_with_exit_code_1(tmp_path, model_dir) -> None:
    broken = tmp_path / "clean"
    shutil.copytree(model_dir, broken)
    (broken / "matcher_1.onnx").write_bytes(b"not a graph")
    src, tgt = write_pair(tmp_path, "npy")
    result = runner.invoke(app, ["register", str(src), str(tgt), "--model", str(broken), *FAST])
    assert result.exit_code == 1
    assert "sha256 of matcher_1.onnx does not match" in result.stderr and "Traceback" not in result.output


def test_a_model_name_wins_over_a_folder_of_that_name_in_the_working_directory(tmp_path, model_dir,
                                                                             monkeypatch) -> None:
    """A training run's folder named like a model (``train --out clean``) beside the clouds was taken for the model
    (``manifest.json is missing``); a path written as one (``./clean``) still names the folder."""
    src, tgt = write_pair(tmp_path, "npy")
    (tmp_path / "clean").mkdir()
    monkeypatch.chdir(tmp_path)
    result = register(src, tgt, "--model", "clean", "--json", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["model"]["name"] == "clean"
    assert register(src, tgt, "--model", "./clean", model_dir=model_dir).exit_code == 1  # the empty folder


def test_require_reliable_exits_3_on_an_unreliable_result_and_still_writes_it(tmp_path, model_dir) -> None:
    """A script gating on the exit status could not tell an unreliable pose from a reliable one (both 0)."""
    line = np.linspace(0.0, 1.0, 200)[:, None] * np.array([[1.0, 2.0, 3.0]])  # collinear: never reliable
    src, tgt = tmp_path / "s.npy", tmp_path / "t.npy"
    np.save(src, line)
    np.save(tgt, line + 0.01)
    out = tmp_path / "pose.json"
    assert register(src, tgt, model_dir=model_dir).exit_code == 0
    result = register(src, tgt, "--require-reliable", "--out", out, model_dir=model_dir)
    assert result.exit_code == 3 and "not reliable" in result.stderr, result.output
    assert json.loads(out.read_text())["quality"]["reliable"] is False
    src_ok, tgt_ok = write_pair(tmp_path, "npy")
    reliable = register(src_ok, tgt_ok, "--json", model_dir=model_dir, fast=False)
    expected = 0 if json.loads(reliable.stdout)["quality"]["reliable"] else 3
    assert register(src_ok, tgt_ok, "--require-reliable", model_dir=model_dir, fast=False).exit_code == expected


@pytest.mark.parametrize("fmt", ["ply", "pcd", "xyz", "csv", "npy", "npz"])
def test_aligned_map_coordinates_are_written_in_float64_and_others_in_float32(tmp_path, model_dir, fmt) -> None:
    """Every format was written as float32: a scan in UTM coordinates came back moved in steps of up to 0.125 m."""
    offset = np.array([512_345.0, 4_123_456.0, 150.0])
    src, tgt = tmp_path / "s.npy", tmp_path / "t.npy"
    np.save(src, SOURCE.astype(np.float64) + offset)
    np.save(tgt, TARGET.astype(np.float64) + offset)
    aligned, out = tmp_path / f"aligned.{fmt}", tmp_path / "pose.json"
    assert register(src, tgt, "--out", out, "--write-aligned", aligned, model_dir=model_dir).exit_code == 0
    record = json.loads(out.read_text())
    expected = np.load(src) @ np.asarray(record["rotation"]).T + np.asarray(record["translation"])
    np.testing.assert_allclose(read_points(aligned), expected, rtol=0, atol=1e-6)
    near = tmp_path / f"near.{fmt}"
    write_points(near, SOURCE.astype(np.float64))
    far_size, near_size = aligned.stat().st_size, near.stat().st_size
    assert near_size < far_size  # float32 where it keeps the points: the file of the same points is smaller


def test_out_dash_prints_only_the_record_and_writes_no_file(tmp_path, model_dir, monkeypatch) -> None:
    """``--out -`` made a file named ``-``."""
    src, tgt = write_pair(tmp_path, "npy")
    monkeypatch.chdir(tmp_path)
    result = register(src, tgt, "--out", "-", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    assert set(json.loads(result.stdout)) == RECORD_KEYS and not (tmp_path / "-").exists()


def test_rejects_options_that_the_chosen_run_would_ignore(tmp_path, model_dir) -> None:
    src, tgt = write_pair(tmp_path, "npy")
    assert_clean_failure(register(src, tgt, "--refine", "none", "--refine-points", "512", model_dir=model_dir),
                         "--refine-points", "--refine none")
    result = runner.invoke(app, ["register", str(src), str(tgt), "--server", "http://127.0.0.1:1", "--threads", "2"])
    assert_clean_failure(result, "--threads", "MFGNET_THREADS")
