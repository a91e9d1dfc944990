"""``POST /v1/register/aligned`` against the main uvicorn server: a PLY, PCD or LAS/LAZ upload comes back as the
user's file moved (the bytes ``service.formats.moved.write_moved`` writes, as ``mfgnet register --write-aligned``
does), named ``<stem>_aligned.<its extension>`` with its media type; a file that cannot hold its moved points is a
422 naming why."""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pypcd4
from api_server import assert_error
from moved_files import coloured_ply, pcd_with_fields, survey_las
from scipy.spatial.transform import Rotation

from service.formats.detect import FORMATS
from service.formats.moved import KEPT_FORMATS, write_moved
from service.pointcloud_io import read_points

R = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
T = np.array([1.5, -2.0, 0.3])
UTM = np.array([512_345.0, 4_123_456.0, 150.0])
XYZ = np.random.default_rng(11).normal(size=(500, 3)).astype(np.float32)  # [500, 3]


def test_every_format_the_reader_finds_comes_back_as_itself():
    """The download has no fallback format: a format the reader learns must learn to be written moved too."""
    assert set(KEPT_FORMATS) == set(FORMATS)


def transform(rotation: np.ndarray = R, translation: np.ndarray = T) -> str:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    return json.dumps(matrix.tolist())


def written_moved(source: Path, out: Path, rotation: np.ndarray = R, translation: np.ndarray = T) -> bytes:
    """What ``--write-aligned`` writes for ``source`` moved: the answer must be these bytes."""
    largest = float(np.abs(read_points(source).astype(np.float64) @ rotation.T + translation).max())
    write_moved(source, out, rotation, translation, largest)
    return out.read_bytes()


def post(client, path: Path, name: str | None = None, matrix: str | None = None):
    return client.post(
        "/v1/register/aligned",
        files={"source": (name or path.name, path.read_bytes())},
        data={"transform": matrix or transform()},
    )


def plyfile_input(tmp_path: Path, content: bytes) -> str:
    path = tmp_path / "answer.ply"
    path.write_bytes(content)
    return str(path)


def test_a_coloured_ply_mesh_comes_back_as_itself_moved(client, tmp_path) -> None:
    source = tmp_path / "scan.ply"
    vertex = coloured_ply(source, XYZ)
    answer = post(client, source, "mesh scan.ply")
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"] == "application/octet-stream"
    assert answer.headers["content-disposition"] == 'attachment; filename="mesh_scan_aligned.ply"'
    assert answer.content == written_moved(source, tmp_path / "cli.ply")  # the CLI's file, byte for byte
    written = plyfile.PlyData.read(plyfile_input(tmp_path, answer.content))
    rows = written["vertex"].data
    for name in ("red", "green", "blue", "quality"):
        assert rows[name].tobytes() == vertex[name].tobytes(), name
    assert len(written["face"].data) == 200 and written.comments == ["scanner X"]
    moved = np.stack([rows[a].astype(np.float64) for a in "xyz"], axis=1)
    np.testing.assert_allclose(moved, XYZ.astype(np.float64) @ R.T + T, rtol=0, atol=1e-6)


def test_a_las_survey_keeps_its_crs_and_records_and_a_laz_stays_compressed(client, tmp_path) -> None:
    for suffix, media in ((".las", "application/vnd.las"), (".laz", "application/vnd.laszip")):
        source = tmp_path / f"survey{suffix}"
        original = survey_las(source, XYZ.astype(np.float64) * 20 + UTM)
        answer = post(client, source)
        assert answer.status_code == 200, answer.text
        assert answer.headers["content-type"] == media
        assert answer.headers["content-disposition"] == f'attachment; filename="survey_aligned{suffix}"'
        assert int(answer.headers["content-length"]) == len(answer.content)
        assert answer.content == written_moved(source, tmp_path / f"cli{suffix}")
        (tmp_path / f"answer{suffix}").write_bytes(answer.content)
        written = laspy.read(str(tmp_path / f"answer{suffix}"))
        assert written.header.are_points_compressed == (suffix == ".laz")
        assert [v.string for v in written.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)] == [
            'PROJCS["WGS 84 / UTM zone 32N"]'
        ]
        np.testing.assert_array_equal(written.header.scales, original.header.scales)
        for name in original.points.array.dtype.names:
            if name not in ("X", "Y", "Z"):
                assert written.points.array[name].tobytes() == original.points.array[name].tobytes(), name
        np.testing.assert_allclose(written.xyz, original.xyz @ R.T + T, rtol=0, atol=0.0005 + 1e-9)
        renamed = post(client, source, "survey.data")  # named otherwise: .las or .laz as its header says
        assert renamed.headers["content-disposition"] == f'attachment; filename="survey_aligned{suffix}"'
        assert renamed.content == answer.content


def test_an_ascii_pcd_and_a_ply_named_otherwise_come_back_in_their_own_format(client, tmp_path) -> None:
    source = tmp_path / "scan.pcd"
    records = pcd_with_fields(source, XYZ, "ascii")
    answer = post(client, source)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-disposition"] == 'attachment; filename="scan_aligned.pcd"'
    assert answer.content == written_moved(source, tmp_path / "cli.pcd")
    (tmp_path / "answer.pcd").write_bytes(answer.content)
    written = pypcd4.PointCloud.from_path(tmp_path / "answer.pcd")
    assert written.metadata.data.value == "ascii"
    assert written.pc_data["rgb"].tobytes() == records["rgb"].tobytes()

    mesh = tmp_path / "mesh.ply"
    coloured_ply(mesh, XYZ)
    answer = post(client, mesh, "mesh.bin")  # the format is the content's, the extension its own
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-disposition"] == 'attachment; filename="mesh_aligned.ply"'
    assert answer.content == written_moved(mesh, tmp_path / "cli.ply")


def test_a_las_file_whose_moved_points_leave_its_integers_is_a_422_naming_it(client, tmp_path) -> None:
    """At millimetre scale a LAS file's 32-bit integers span +-2,147 km: a square of +-2,000 km turned by 45 deg
    about z reaches +-2,828 km."""
    source = tmp_path / "wide.las"
    corners = np.array([[x, y, 0.0] for x in np.linspace(-2e6, 2e6, 20) for y in np.linspace(-2e6, 2e6, 20)])
    survey_las(source, corners, offsets=(0.0, 0.0, 0.0))
    turn = Rotation.from_euler("z", 45.0, degrees=True).as_matrix()
    answer = post(client, source, matrix=transform(turn, np.zeros(3)))
    assert_error(answer, 422, "wide.las", "32-bit integers", "scale 0.001")


def test_a_csv_whose_quoted_label_runs_over_a_line_break_is_a_400_naming_the_line(client, tmp_path) -> None:
    """numpy's reader joins the two lines into one row; the moved copy, a row per line, then failed as "a row changed
    since it was read"."""
    source = tmp_path / "labelled.csv"
    rows = "".join(f"{x:.4f},{y:.4f},{z:.4f},plain\n" for x, y, z in XYZ[1:])
    source.write_text(f'x,y,z,label\n{XYZ[0, 0]:.4f},{XYZ[0, 1]:.4f},{XYZ[0, 2]:.4f},"two\nlines"\n' + rows)
    answer = post(client, source)
    assert_error(answer, 400, "labelled.csv", "a double-quoted value opened on line 2 runs over a line break")
