"""Files as the field's tools write them (pandas, Open3D, PCL, Leica PTS) read as those tools meant them.

Each input is written here byte for byte as the tool writes it (checked against the tool in a temporary environment:
pandas 3.1, Open3D 0.19/0.20, pypcd4 1.5), so that these tests need none of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.formats import read_cloud
from service.formats.errors import InvalidPointsError, PointCloudFormatError

XYZ = np.array([[0.5, -1.25, 2.0], [3.0, 4.5, -0.75], [1.0, 0.0, 0.25]])  # [N, 3]
RGB = np.array([[10, 20, 30], [40, 50, 60], [70, 80, 90]])  # [N, 3]


def rows(separator: str, table: np.ndarray, quote: str = "") -> str:
    return "".join(separator.join(f"{quote}{value:g}{quote}" for value in row) + "\n" for row in table)


def test_csv_reads_the_columns_its_header_names_x_y_z(tmp_path: Path) -> None:
    # pandas' to_csv writes its index first, under an empty name: taking the first three columns read index, x, y
    index = np.arange(len(XYZ))[:, None]
    (tmp_path / "pandas.csv").write_text(",x,y,z,r,g,b\n" + rows(",", np.hstack([index, XYZ, RGB])))
    np.testing.assert_array_equal(read_cloud(tmp_path / "pandas.csv"), XYZ)
    (tmp_path / "scan.txt").write_text("time intensity X Y Z\n" + rows(" ", np.hstack([index, index, XYZ])))
    np.testing.assert_array_equal(read_cloud(tmp_path / "scan.txt"), XYZ)


def test_a_header_without_x_y_z_names_keeps_the_first_three_columns(tmp_path: Path) -> None:
    (tmp_path / "cc.txt").write_text("//X,Y,Z,R,G,B\n" + rows(",", np.hstack([XYZ, RGB])))  # CloudCompare's export
    np.testing.assert_array_equal(read_cloud(tmp_path / "cc.txt"), XYZ)
    (tmp_path / "a.csv").write_text("east,north,height\n" + rows(",", XYZ))
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.csv"), XYZ)


@pytest.mark.parametrize("delimiter", [" ", ","])
def test_numpy_savetxt_column_names_in_a_comment_are_read(tmp_path: Path, delimiter: str) -> None:
    # np.savetxt(header=...) writes the names as a '#' comment: the first three columns were read (intensity, x, y)
    index = np.arange(len(XYZ))[:, None]
    np.savetxt(tmp_path / "a.txt", np.hstack([index, XYZ]), header=delimiter.join(["intensity", "x", "y", "z"]),
               delimiter=delimiter)
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.txt"), XYZ)
    np.savetxt(tmp_path / "b.txt", np.hstack([XYZ, index]), header="scanner A, 2 returns")  # names no columns
    np.testing.assert_array_equal(read_cloud(tmp_path / "b.txt"), XYZ)


@pytest.mark.parametrize("tail", [" ground", " 2024-05-01T10:00:00", " 0xff00ff", " # first return"])
def test_a_first_row_of_numbers_followed_by_a_label_is_a_row(tmp_path: Path, tail: str) -> None:
    # it was taken for a header line: the file's first point was lost, and every index after it shifted by one
    (tmp_path / "a.xyz").write_text("".join(" ".join(f"{v:g}" for v in row) + tail + "\n" for row in XYZ))
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.xyz"), XYZ)


@pytest.mark.parametrize("header", ["x;y;z;r;g;b\n", ""])
def test_semicolon_separated_text_reads(tmp_path: Path, header: str) -> None:
    (tmp_path / "a.csv").write_text(header + rows(";", np.hstack([XYZ, RGB])))  # pandas' sep=";", Excel's locales
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.csv"), XYZ)


@pytest.mark.parametrize("header", ['"x","y","z"\n', ""])
def test_quoted_csv_values_read(tmp_path: Path, header: str) -> None:
    (tmp_path / "a.csv").write_text(header + rows(",", XYZ, quote='"'))  # pandas' quoting=csv.QUOTE_ALL
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.csv"), XYZ)


def test_leica_pts_point_count_line_is_skipped(tmp_path: Path) -> None:
    # Open3D's write_point_cloud("a.pts"): the point count, then x y z intensity r g b
    intensity = np.zeros((len(XYZ), 1))
    (tmp_path / "a.pts").write_text(f"{len(XYZ)}\n" + rows(" ", np.hstack([XYZ, intensity, RGB])))
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.pts"), XYZ)


def test_npz_of_an_open3d_tensor_point_cloud_reads_its_positions(tmp_path: Path) -> None:
    # o3d.t.io.write_point_cloud("a.npz"): one array per attribute, the points under "positions"
    np.savez(tmp_path / "a.npz", colors=RGB / 255, normals=-XYZ, intensity=np.ones((len(XYZ), 1)), positions=XYZ)
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.npz"), XYZ)


@pytest.mark.parametrize("version", [".6", "0.6", ".5", "0.7", ".7"])
def test_pcd_of_an_older_version_reads(tmp_path: Path, version: str) -> None:
    # PCL's reader ignores VERSION; PCL 1.x wrote .5 and .6 headers (no VIEWPOINT) of the same layout
    header = (f"# .PCD v{version} - Point Cloud Data file format\nVERSION {version}\nFIELDS x y z\nSIZE 4 4 4\n"
              f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(XYZ)}\nHEIGHT 1\nPOINTS {len(XYZ)}\nDATA binary\n")
    (tmp_path / "a.pcd").write_bytes(header.encode() + XYZ.astype("<f4").tobytes())
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.pcd"), XYZ)


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-le", "utf-16-be"])  # with a byte-order mark, and without
def test_utf16_text_is_refused_naming_utf16(tmp_path: Path, encoding: str) -> None:
    # Windows PowerShell 5's Out-File and > write UTF-16 LE with a byte-order mark
    (tmp_path / "a.xyz").write_text(rows(" ", XYZ), encoding=encoding)
    with pytest.raises(PointCloudFormatError, match=r"UTF-16.*UTF-8"):
        read_cloud(tmp_path / "a.xyz")


def test_a_transposed_npy_is_refused_naming_the_shape_it_needs(tmp_path: Path) -> None:
    points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)  # [N, 3]
    np.save(tmp_path / "a.npy", np.ascontiguousarray(points.T))  # [3, N]: one row per axis
    with pytest.raises(InvalidPointsError, match=r"expected shape \[N, 3\], got \[3, 500\]: .*transposed"):
        read_cloud(tmp_path / "a.npy")


def test_a_homogeneous_npy_of_four_rows_is_refused_naming_the_rows_to_send(tmp_path: Path) -> None:
    """[4, N]: x, y, z and w rows; the row-size check had named 2,000 bytes per row instead."""
    points = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
    homogeneous = np.ascontiguousarray(np.vstack([points.T, np.ones((1, 500), np.float32)]))  # [4, N]
    np.save(tmp_path / "a.npy", homogeneous)
    with pytest.raises(InvalidPointsError, match=r"\[4, 500\].*homogeneous.*cloud\[:3\]\.T"):
        read_cloud(tmp_path / "a.npy")


@pytest.mark.parametrize(("shape", "dtype", "named"), [
    ((4, 40), np.int16, "homogeneous"), ((3, 40), np.int16, "transposed"), ((1, 4, 40), np.float64, "homogeneous"),
])
def test_narrow_rows_per_axis_are_named_as_wide_ones_are(tmp_path: Path, shape, dtype, named) -> None:
    """80-byte rows passed the row-size check and were read as 3 or 4 points ("needs at least 32 points")."""
    np.save(tmp_path / "a.npy", np.ones(shape, dtype))
    with pytest.raises(InvalidPointsError, match=rf"got \[{', '.join(map(str, shape))}\]: .*{named}"):
        read_cloud(tmp_path / "a.npy")
