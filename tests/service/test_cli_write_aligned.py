"""Specification of the aligned cloud as the user's own file, moved (``mfgnet register --write-aligned``,
``service.formats.moved.write_moved``): a PLY, PCD or LAS/LAZ source written in its own format keeps every other
field byte for byte (colours, intensity, faces, classification, VLRs), its points moved by ``R @ p + t`` within the
format's precision and its normals rotated; other combinations hold x, y, z and say what was not carried.

The files are written with the libraries users have (plyfile, pypcd4, laspy + lazrs)."""

from __future__ import annotations

import json
import os
import tracemalloc
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pypcd4
import pytest
from aligned_runs import FAST, pose, register, runner, sequence
from cli_support import synthetic_pair
from moved_files import PCD_NORMALS, PLY_NORMALS, coloured_ply, pcd_with_fields, survey_las, unit_normals
from scipy.spatial.transform import Rotation

from service.cancellation import Cancellation, RegistrationCancelledError, cancellable
from service.cli import app
from service.formats import PointCloudFormatError, moved_text
from service.formats.moved import write_moved
from service.pointcloud_io import read_points

SOURCE, TARGET = synthetic_pair()  # [600, 3] float32 each
R = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
T = np.array([1.5, -2.0, 0.3])
UTM = np.array([512_345.0, 4_123_456.0, 150.0])


def moved(xyz: np.ndarray, rotation: np.ndarray = R, translation: np.ndarray = T) -> np.ndarray:
    return np.asarray(xyz, dtype=np.float64) @ rotation.T + translation


def stacked(rows: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    return np.stack([np.asarray(rows[name], dtype=np.float64) for name in names], axis=1)


def write(source: Path, out: Path, rotation: np.ndarray = R, translation: np.ndarray = T) -> None:
    write_moved(
        source,
        out,
        rotation,
        translation,
        largest=float(np.abs(moved(read_points(source), rotation, translation)).max()),
    )


def traced_write(source: Path, out: Path) -> int:
    """:func:`write` of ``source`` to ``out``, and the most memory Python allocated during it (bytes)."""
    largest = float(np.abs(moved(read_points(source))).max())  # read first: the reader's memory is not the writer's
    tracemalloc.start()
    try:
        write_moved(source, out, R, T, largest=largest)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


# --------------------------------------------------------------------------------------------- PLY


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_ply_keeps_colours_and_faces_and_rotates_its_normals(tmp_path, text) -> None:
    source, out = tmp_path / "scan.ply", tmp_path / "aligned.ply"
    vertex = coloured_ply(source, SOURCE, text)
    write(source, out)
    written = plyfile.PlyData.read(str(out))
    assert written.text == text and written.comments == ["scanner X"]
    rows = written["vertex"].data
    assert rows.dtype == vertex.dtype  # float32 x, y, z kept: the moved points are within 1e4
    for name in ("red", "green", "blue", "quality"):
        assert rows[name].tobytes() == vertex[name].tobytes(), name
    np.testing.assert_allclose(stacked(rows, tuple("xyz")), moved(SOURCE), rtol=0, atol=1e-6)  # float32 steps
    np.testing.assert_allclose(stacked(rows, PLY_NORMALS), moved(stacked(vertex, PLY_NORMALS), R, 0), atol=1e-6)
    faces = plyfile.PlyData.read(str(source))["face"].data["vertex_indices"]
    assert [list(f) for f in written["face"].data["vertex_indices"]] == [list(f) for f in faces]
    if not text:  # the header and the faces' bytes are the source's
        before, after = source.read_bytes(), out.read_bytes()
        body = before.index(b"end_header\n") + len(b"end_header\n")
        rows_end = body + len(vertex) * vertex.dtype.itemsize
        assert after[:body] == before[:body] and after[rows_end:] == before[rows_end:]


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_ply_normals_named_as_pcl_names_them_are_rotated(tmp_path, text) -> None:
    """PCL's PLY writer names normals normal_x, normal_y, normal_z: they were copied unturned."""
    source, out = tmp_path / "pcl.ply", tmp_path / "aligned.ply"
    names = ("x", "y", "z", *PCD_NORMALS)
    vertex = np.empty(len(SOURCE), dtype=[(name, "<f4") for name in names])
    for name, column in zip(names, np.column_stack([SOURCE, unit_normals(len(SOURCE))]).T, strict=True):
        vertex[name] = column
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=text).write(str(source))
    write(source, out)
    rows = plyfile.PlyData.read(str(out))["vertex"].data
    np.testing.assert_allclose(stacked(rows, PCD_NORMALS), moved(stacked(vertex, PCD_NORMALS), R, 0), atol=1e-6)


def test_an_ascii_ply_mesh_is_moved_a_chunk_of_lines_at_a_time(tmp_path, monkeypatch) -> None:
    """plyfile read and wrote an ASCII PLY whole (26 s and 139 MB for 1,000 vertices and 200,000 faces; an aligned
    download past its deadline kept its slot): its vertex rows are moved as text rows are, the other lines copied,
    in memory that does not grow with the file."""
    monkeypatch.setattr(moved_text, "CHUNK_CHARS", 1 << 16)  # lines moved 64 KiB at a time
    source, out = tmp_path / "mesh.ply", tmp_path / "aligned.ply"
    rng = np.random.default_rng(0)
    faces = rng.integers(0, len(SOURCE), (100_000, 4))  # [F, 4]
    header = ["ply", "format ascii 1.0", "comment a scanner's mesh", f"element face {len(faces)}",
              "property list uchar int vertex_indices", f"element vertex {len(SOURCE)}", "property float x",
              "property float y", "property float z", *(f"property float {n}" for n in PCD_NORMALS), "end_header"]
    normals = unit_normals(len(SOURCE))
    rows = [" ".join(f"{v:.6f}" for v in row) for row in np.column_stack([SOURCE, normals])]
    lines = [*header, *(f"4 {a} {b} {c} {d}" for a, b, c, d in faces), *rows]
    source.write_text("\n".join(lines) + "\n")
    peak = traced_write(source, out)
    assert peak < 4 * 2**20, peak  # the file: 1.7 MB
    written = out.read_text().splitlines()
    assert written[: len(header) + len(faces)] == lines[: len(header) + len(faces)]  # header and faces as they were
    moved_rows = np.array([row.split() for row in written[len(header) + len(faces):]], dtype=np.float64)  # [N, 6]
    np.testing.assert_allclose(moved_rows[:, :3], moved(SOURCE), rtol=0, atol=1e-5)
    np.testing.assert_allclose(moved_rows[:, 3:], normals @ R.T, rtol=0, atol=1e-5)


def test_ply_moved_into_map_coordinates_holds_them_in_double(tmp_path) -> None:
    """float32 steps 0.25-0.5 m at UTM northings: x, y, z become double, every other property stays as it was."""
    source, out = tmp_path / "scan.ply", tmp_path / "aligned.ply"
    vertex = coloured_ply(source, SOURCE)
    write(source, out, R, UTM)
    rows = plyfile.PlyData.read(str(out))["vertex"].data
    assert [rows.dtype[a].str for a in "xyz"] == ["<f8"] * 3
    np.testing.assert_allclose(stacked(rows, tuple("xyz")), moved(SOURCE, R, UTM), rtol=0, atol=1e-9)
    assert all(rows[name].tobytes() == vertex[name].tobytes() for name in ("red", "green", "blue", "quality"))


def test_an_output_naming_its_source_is_written_from_the_whole_source(tmp_path) -> None:
    source = tmp_path / "scan.ply"
    coloured_ply(source, SOURCE)
    write(source, source)
    np.testing.assert_allclose(read_points(source), moved(SOURCE), atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["scan.ply"]  # no temporary file left


def test_the_written_file_gets_a_new_files_permissions_without_touching_the_process_umask(tmp_path, monkeypatch):
    """0o666 less the umask, as any file the user writes; reading the umask would set it process-wide for a moment,
    while a server's other threads create files (spooled uploads, logs)."""
    source, out = tmp_path / "scan.ply", tmp_path / "out.ply"
    coloured_ply(source, SOURCE)
    mask = os.umask(0o027)
    try:

        def umask_called(_: int) -> int:
            raise AssertionError("write_moved changed the process umask")

        monkeypatch.setattr(os, "umask", umask_called)
        write(source, out)
    finally:
        monkeypatch.undo()
        os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o640


# --------------------------------------------------------------------------------------------- PCD


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_keeps_intensity_and_colour_rotates_normals_and_moves_its_viewpoint(tmp_path, encoding) -> None:
    source, out = tmp_path / "scan.pcd", tmp_path / "aligned.pcd"
    records = pcd_with_fields(source, SOURCE, encoding)
    write(source, out)
    written = pypcd4.PointCloud.from_path(out)
    assert written.metadata.data.value == encoding and written.fields == (
        "x",
        "y",
        "z",
        "intensity",
        *PCD_NORMALS,
        "rgb",
    )
    rows = written.pc_data
    for name in ("intensity", "rgb"):  # the packed colour bit for bit, also through ASCII
        assert rows[name].tobytes() == records[name].tobytes(), name
    np.testing.assert_allclose(stacked(rows, tuple("xyz")), moved(SOURCE), rtol=0, atol=1e-6)
    np.testing.assert_allclose(stacked(rows, PCD_NORMALS), moved(stacked(records, PCD_NORMALS), R, 0), atol=1e-6)
    viewpoint = written.metadata.viewpoint  # tx ty tz qw qx qy qz: the sensor, at the origin before, moved too
    np.testing.assert_allclose(viewpoint[:3], T, atol=1e-12)
    w, x, y, z = viewpoint[3:]
    np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), R, atol=1e-12)


def test_an_ascii_pcd_is_moved_a_chunk_of_lines_at_a_time(tmp_path, monkeypatch) -> None:
    """Its rows were parsed whole into records of every field and written back by numpy (a 112 MB file took a server
    2 minutes past its deadline): they are moved as text rows are, every other value kept as it was written."""
    monkeypatch.setattr(moved_text, "CHUNK_CHARS", 1 << 16)  # lines moved 64 KiB at a time
    source, out = tmp_path / "scan.pcd", tmp_path / "aligned.pcd"
    normals = unit_normals(len(SOURCE))
    pad = np.random.default_rng(0).integers(0, 1000, (len(SOURCE), 40))  # [N, 40]: a field of COUNT 40
    rows = [" ".join([*(f"{v:.6f}" for v in xyz_n), *map(str, p)])
            for xyz_n, p in zip(np.column_stack([SOURCE, normals]), pad, strict=True)] * 20  # [20 N]
    header = ("VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z pad\nSIZE 4 4 4 4 4 4 4\nTYPE F F F F F F U\n"
              f"COUNT 1 1 1 1 1 1 40\nWIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\n"
              "DATA ascii\n")
    source.write_text(header + "\n".join(rows) + "\n")
    peak = traced_write(source, out)
    assert peak < 2 * 2**20, peak  # the file: 2.5 MB; its rows as records: 2.2 MB
    lines = out.read_text().splitlines()
    written = lines[next(k for k, line in enumerate(lines) if line.startswith("DATA")) + 1:]
    assert [line.split()[6:] for line in written] == [line.split()[6:] for line in rows]  # the pad as it was
    values = np.array([line.split()[:6] for line in written], dtype=np.float64)  # [20 N, 6]
    np.testing.assert_allclose(values[:, :3], np.tile(moved(SOURCE), (20, 1)), rtol=0, atol=1e-5)
    np.testing.assert_allclose(values[:, 3:], np.tile(normals @ R.T, (20, 1)), rtol=0, atol=1e-5)


def test_pcd_moved_into_map_coordinates_holds_them_in_8_byte_floats(tmp_path) -> None:
    source, out = tmp_path / "scan.pcd", tmp_path / "aligned.pcd"
    records = pcd_with_fields(source, SOURCE, "binary")
    write(source, out, R, UTM)
    written = pypcd4.PointCloud.from_path(out)
    assert written.metadata.size == (8, 8, 8, 4, 4, 4, 4, 4)
    np.testing.assert_allclose(read_points(out), moved(SOURCE, R, UTM), rtol=0, atol=1e-9)
    assert written.pc_data["rgb"].tobytes() == records["rgb"].tobytes()


def test_an_organized_pcd_keeps_its_grid_and_its_missing_returns(tmp_path) -> None:
    source, out = tmp_path / "depth.pcd", tmp_path / "aligned.pcd"
    grid = SOURCE[:600].astype(np.float32).copy()
    grid[::7] = np.nan  # pixels without a return
    cloud = pypcd4.PointCloud.from_points(grid, ("x", "y", "z"), (np.float32,) * 3)
    cloud.metadata = cloud.metadata.derive(width=30, height=20)
    cloud.save(source, encoding=pypcd4.Encoding.BINARY)
    write(source, out)
    written = pypcd4.PointCloud.from_path(out)
    assert (written.metadata.width, written.metadata.height, written.metadata.points) == (30, 20, 600)
    rows = stacked(written.pc_data, tuple("xyz"))
    assert np.isnan(rows[::7]).all() and not np.isnan(np.delete(rows, np.s_[::7], axis=0)).any()
    np.testing.assert_allclose(read_points(out), moved(np.delete(grid, np.s_[::7], axis=0)), atol=1e-6)


# ----------------------------------------------------------------------------------------- LAS/LAZ


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_points_of_many_extra_bytes_are_moved_as_las_and_refused_as_laz(tmp_path, suffix) -> None:
    """A LAZ file is decompressed whole to be moved, and its size does not bound its records (4,000 extra bytes a
    point that never change compress to almost nothing: 1.1 MB of LAZ held 800 MB)."""
    las = laspy.create(point_format=6, file_version="1.4")
    las.add_extra_dims([laspy.ExtraBytesParams(name=f"band_{k}", type="f8") for k in range(25)])  # 30 + 200 bytes
    las.header.scales = np.full(3, 1e-4)
    las.x, las.y, las.z = SOURCE[:, 0], SOURCE[:, 1], SOURCE[:, 2]
    source, out = tmp_path / f"wide{suffix}", tmp_path / f"aligned{suffix}"
    las.write(source)
    if suffix == ".las":
        write(source, out)
        np.testing.assert_allclose(read_points(out), moved(read_points(source)), rtol=0, atol=1e-4)
        return
    with pytest.raises(PointCloudFormatError, match=r"LAZ points of 2\d\d bytes each .* send it as LAS"):
        write(source, out)
    assert not out.exists()


@pytest.mark.parametrize(("suffix", "out_suffix"), [(".las", ".las"), (".laz", ".laz"), (".las", ".laz")])
def test_las_keeps_every_point_field_its_vlrs_and_its_scale(tmp_path, suffix, out_suffix) -> None:
    source, out = tmp_path / f"survey{suffix}", tmp_path / f"aligned{out_suffix}"
    original = survey_las(source, SOURCE.astype(np.float64) * 20 + UTM)
    write(source, out)
    written = laspy.read(str(out))
    assert written.header.are_points_compressed == (out_suffix == ".laz")
    assert written.header.point_format.id == 3 and written.header.version == original.header.version
    np.testing.assert_array_equal(written.header.scales, original.header.scales)
    np.testing.assert_array_equal(written.header.offsets, original.header.offsets)  # the moved points fit them
    assert [(v.record_id, v.record_data_bytes()) for v in written.header.vlrs if v.user_id != "laszip encoded"] == [
        (v.record_id, v.record_data_bytes()) for v in original.header.vlrs if v.user_id != "laszip encoded"
    ]
    for name in original.points.array.dtype.names:  # the raw records: return bits, flags, classification, ...
        if name not in ("X", "Y", "Z"):
            assert written.points.array[name].tobytes() == original.points.array[name].tobytes(), name
    np.testing.assert_allclose(written.xyz, moved(original.xyz), rtol=0, atol=0.0005 + 1e-9)  # half the scale
    np.testing.assert_allclose(written.header.mins, written.xyz.min(axis=0))
    np.testing.assert_allclose(written.header.maxs, written.xyz.max(axis=0))


def test_las_moved_from_a_local_frame_into_map_coordinates_gets_offsets_that_fit(tmp_path) -> None:
    """At millimetre scale 32-bit integers span +-2,147 km: a local scan (offsets 0) moved to a northing of 4,123 km
    needs a new offset there, the scale kept."""
    source, out = tmp_path / "local.las", tmp_path / "aligned.laz"
    original = survey_las(source, SOURCE.astype(np.float64) * 20, offsets=(0.0, 0.0, 0.0))
    write(source, out, R, UTM)
    written = laspy.read(str(out))
    np.testing.assert_array_equal(written.header.scales, original.header.scales)
    assert written.header.offsets[1] == pytest.approx(UTM[1], abs=100) and written.header.offsets[1] % 1 == 0
    np.testing.assert_allclose(written.xyz, moved(original.xyz, R, UTM), rtol=0, atol=0.0005 + 1e-9)


# ------------------------------------------------------------------------------------------- the CLI


def test_register_writes_the_coloured_ply_moved(tmp_path, model_dir) -> None:
    source, target, out, aligned = (tmp_path / n for n in ("scan.ply", "target.npy", "pose.json", "aligned.ply"))
    vertex = coloured_ply(source, SOURCE)
    np.save(target, TARGET)
    result = register(source, target, "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    rotation, translation = pose(out)
    rows = plyfile.PlyData.read(str(aligned))["vertex"].data
    assert all(rows[name].tobytes() == vertex[name].tobytes() for name in ("red", "green", "blue", "quality"))
    np.testing.assert_allclose(stacked(rows, tuple("xyz")), moved(SOURCE, rotation, translation), atol=1e-6)
    assert len(plyfile.PlyData.read(str(aligned))["face"].data) == 200 and "note" not in result.stderr


def test_register_writes_a_laz_survey_moved_at_its_scale(tmp_path, model_dir) -> None:
    source, target, out, aligned = (tmp_path / n for n in ("survey.laz", "target.npy", "pose.json", "aligned.laz"))
    original = survey_las(source, SOURCE.astype(np.float64) + UTM)
    np.save(target, TARGET.astype(np.float64) + UTM)
    result = register(source, target, "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    rotation, translation = pose(out)
    written = laspy.read(str(aligned))
    assert written.header.are_points_compressed
    assert [v.string for v in written.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)] == [
        'PROJCS["WGS 84 / UTM zone 32N"]'
    ]  # the CRS stays: the target's frame is the user's to know
    np.testing.assert_array_equal(written.classification, original.classification)
    np.testing.assert_allclose(written.xyz, moved(original.xyz, rotation, translation), rtol=0, atol=0.0005 + 1e-9)


def test_a_las_output_of_a_source_that_is_not_las_is_a_usage_error_before_anything_is_read(tmp_path, model_dir) -> None:
    source = tmp_path / "scan.ply"
    coloured_ply(source, SOURCE)
    result = register(
        source, tmp_path / "missing.npy", "--write-aligned", tmp_path / "aligned.laz", model_dir=model_dir
    )
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "aligned.laz" in result.stderr and "only from a LAS/LAZ source" in result.stderr
    assert "scan.ply is PLY" in result.stderr and not (tmp_path / "aligned.laz").exists()


def test_another_output_format_holds_x_y_z_and_says_which_fields_it_left(tmp_path, model_dir) -> None:
    source, target, out, aligned = (tmp_path / n for n in ("scan.pcd", "target.npy", "pose.json", "aligned.xyz"))
    pcd_with_fields(source, SOURCE, "binary")
    np.save(target, TARGET)
    result = register(source, target, "--out", out, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    np.testing.assert_allclose(read_points(aligned), moved(SOURCE, *pose(out)), atol=1e-5)
    assert "aligned.xyz holds x, y, z only" in result.stderr
    assert "intensity, normal_x, normal_y, normal_z, rgb" in result.stderr and ".pcd output" in result.stderr


@pytest.mark.parametrize(
    ("name", "text", "named"),
    [
        ("scan.csv", ",x,y,z,r,g,b\n", "(column 1, r, g, b)"),
        ("scan.xyz", "# no header\n", "(column 4, column 5)"),
        ("scan.pts", "600\n", "(intensity, red, green, blue)"),
    ],
    ids=["csv-header", "xyz-bare", "pts"],
)
def test_a_text_source_to_another_format_says_which_columns_it_left(tmp_path, model_dir, name, text, named) -> None:
    source, target, aligned = tmp_path / name, tmp_path / "target.npy", tmp_path / "aligned.ply"
    extra = {"scan.csv": 3, "scan.xyz": 2, "scan.pts": 4}[name]
    rows = [[*p, *range(extra)] for p in SOURCE.tolist()]
    if name == "scan.csv":
        rows = [[k, *row] for k, row in enumerate(rows)]  # pandas' index first
    separator = "," if name == "scan.csv" else " "
    source.write_text(text + "".join(separator.join(map(str, row)) + "\n" for row in rows))
    np.save(target, TARGET)
    result = register(source, target, "--write-aligned", aligned, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    assert "aligned.ply holds x, y, z only" in result.stderr and named in result.stderr


# ------------------------------------------------------------------------------------------ sequence


def test_sequence_writes_every_frame_moved_into_frame_0_with_its_fields(tmp_path, model_dir) -> None:
    frames, vertices = [], []
    for index in range(3):
        turn = Rotation.from_euler("z", -8.0 * index, degrees=True).as_matrix()
        (tmp_path / f"f{index}").mkdir()
        frames.append(tmp_path / f"f{index}" / f"frame_{index}.ply")
        vertices.append(coloured_ply(frames[-1], (SOURCE.astype(np.float64) @ turn.T).astype(np.float32)))
    folder, steps = tmp_path / "aligned", tmp_path / "steps.jsonl"
    folder.mkdir()
    result = sequence(frames, folder, model_dir, steps)
    assert result.exit_code == 0, result.output
    accumulated = [np.eye(4)] + [np.asarray(json.loads(line)["accumulated_transform"]) for line in
                                 steps.read_text().splitlines()]  # fmt: skip
    assert sorted(p.name for p in folder.iterdir()) == ["frame_0.ply", "frame_1.ply", "frame_2.ply"]
    for index, (vertex, T) in enumerate(zip(vertices, accumulated, strict=True)):
        written = plyfile.PlyData.read(str(folder / f"frame_{index}.ply"))
        rows = written["vertex"].data
        assert all(rows[name].tobytes() == vertex[name].tobytes() for name in ("red", "green", "blue", "quality"))
        expected = moved(stacked(vertex, tuple("xyz")), T[:3, :3], T[:3, 3])
        np.testing.assert_allclose(stacked(rows, tuple("xyz")), expected, atol=1e-5)
        assert len(written["face"].data) == 200


def test_sequence_aligned_folder_errors_come_before_any_registration(tmp_path, model_dir) -> None:
    frames = [tmp_path / "a" / "scan.ply", tmp_path / "b" / "scan.ply"]
    for frame in frames:
        frame.parent.mkdir()
        coloured_ply(frame, SOURCE)
    base = ["sequence", *map(str, frames), "--model-dir", str(model_dir), *FAST, "--write-aligned"]
    missing = runner.invoke(app, [*base, str(tmp_path / "nowhere")])
    assert missing.exit_code == 2 and "no such folder" in missing.stderr
    clash = runner.invoke(app, [*base, str(tmp_path)])
    assert clash.exit_code == 2 and "would both be written as scan.ply" in clash.stderr
    own = [tmp_path / "a" / "other.ply", frames[0]]
    coloured_ply(own[0], SOURCE)
    itself = runner.invoke(app, ["sequence", *map(str, own), "--write-aligned", str(tmp_path / "a")])
    assert itself.exit_code == 2 and "is one of the frames; it would be overwritten" in itself.stderr


@pytest.mark.parametrize("kind", ["xyz", "ply", "npy"])
def test_an_aligned_file_of_a_cancelled_request_stops_and_leaves_nothing(tmp_path, kind) -> None:
    """An aligned download past its deadline (504) wrote its file to the end, holding its worker: each block now
    looks at the request's cancellation first."""
    source, out = tmp_path / f"scan.{kind}", tmp_path / f"aligned.{kind}"
    if kind == "ply":
        coloured_ply(source, SOURCE)
    elif kind == "npy":
        np.save(source, SOURCE)
    else:
        np.savetxt(source, SOURCE)
    cancellation = Cancellation()
    cancellation.cancel()
    with cancellable(cancellation), pytest.raises(RegistrationCancelledError):
        write(source, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == [source.name]
