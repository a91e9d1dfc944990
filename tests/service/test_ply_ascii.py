"""ASCII PLY: the vertex rows of a file that starts with its vertex element are parsed by numpy.loadtxt, with every
value cast to its declared type as plyfile casts it; the result is plyfile's own, and other layouts still read."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import plyfile
import pytest

from service.formats import InvalidPointsError, PointCloudFormatError, read_cloud

HEADER = """ply
format ascii 1.0
comment written by a scanner
element vertex {n}
property float x
property double y
property int z
property float nx
property uchar red
element face {faces}
property list uchar int vertex_indices
end_header
"""


def scan_ply(path: Path, n: int = 200, faces: int = 3, rows: int | None = None, crlf: bool = False) -> None:
    rng = np.random.default_rng(0)
    xyz = rng.normal(scale=50.0, size=(n, 3))
    lines = [f"{x:.9f} {y:.12f} {int(z)} {rng.random():.3f} {rng.integers(0, 256)}" for x, y, z in xyz]
    lines = lines[:rows] if rows is not None else lines + [f"3 {i} {i + 1} {i + 2}" for i in range(faces)]
    text = HEADER.format(n=n, faces=faces) + "\n".join(lines) + "\n"
    path.write_bytes(text.replace("\n", "\r\n").encode() if crlf else text.encode())


def plyfile_xyz(path: Path) -> np.ndarray:
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    return np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)


@pytest.mark.parametrize("crlf", [False, True], ids=["lf", "crlf"])
def test_vertex_rows_read_as_plyfile_reads_them(tmp_path: Path, crlf: bool) -> None:
    scan_ply(tmp_path / "a.ply", crlf=crlf)
    points = read_cloud(tmp_path / "a.ply")
    np.testing.assert_array_equal(points, plyfile_xyz(tmp_path / "a.ply"))  # float32 x, float64 y, int z
    assert points[:, 0].astype(np.float32).astype(np.float64).tolist() == points[:, 0].tolist()
    assert np.array_equal(points[:, 2], np.round(points[:, 2]))


def test_fewer_vertex_rows_than_declared_are_refused(tmp_path: Path) -> None:
    scan_ply(tmp_path / "a.ply", n=200, faces=0, rows=150)
    with pytest.raises(PointCloudFormatError, match="150 vertex rows, the header says 200"):
        read_cloud(tmp_path / "a.ply")


def test_a_row_that_is_not_numbers_is_refused(tmp_path: Path) -> None:
    scan_ply(tmp_path / "a.ply", n=20, faces=0)
    text = (tmp_path / "a.ply").read_text().replace("end_header\n", "end_header\n1.0 two 3 0.5 7\n", 1)
    (tmp_path / "a.ply").write_text(text.replace("element vertex 20", "element vertex 21"))
    with pytest.raises(PointCloudFormatError, match="corrupt PLY data"):
        read_cloud(tmp_path / "a.ply")


def test_a_file_whose_first_element_is_not_the_vertices_still_reads(tmp_path: Path) -> None:
    scan_ply(tmp_path / "a.ply", n=30, faces=0)
    text = (tmp_path / "a.ply").read_text().replace(
        "element vertex 30", "element camera 1\nproperty float view_x\nelement vertex 30", 1)
    (tmp_path / "b.ply").write_text(text.replace("end_header\n", "end_header\n0.5\n", 1))
    np.testing.assert_array_equal(read_cloud(tmp_path / "b.ply"), read_cloud(tmp_path / "a.ply"))


def test_blank_lines_are_skipped_and_no_rows_is_an_empty_cloud_without_warnings(tmp_path: Path) -> None:
    head = ("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
            "end_header\n")
    (tmp_path / "a.ply").write_text(head.format(n=2) + "1 2 3\n\n4 5 6\n")
    (tmp_path / "b.ply").write_text(head.format(n=0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's loadtxt warns of both by default
        np.testing.assert_array_equal(read_cloud(tmp_path / "a.ply"), [[1, 2, 3], [4, 5, 6]])
        with pytest.raises(InvalidPointsError, match="the cloud is empty"):
            read_cloud(tmp_path / "b.ply")


@pytest.mark.parametrize(("kind", "z"), [("int", "nan"), ("int", "1.5"), ("uchar", "300")])
def test_an_integer_property_must_hold_integers_of_its_type(tmp_path: Path, kind: str, z: str) -> None:
    """A cast of the parsed value would have made NaN, 1.5 or 300 some integer and read it as a coordinate."""
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                    f"property {kind} z\nend_header\n1 2 {z}\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(PointCloudFormatError, match="vertex z values that are not"):
            read_cloud(tmp_path / "a.ply")
