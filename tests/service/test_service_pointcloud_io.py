"""Specification of the point-cloud reader (``service.formats`` behind ``service.pointcloud_io``): every format
reads by content, files written by the reference libraries read back exactly, bad files fail clearly."""

from __future__ import annotations

import subprocess
import sys
import tracemalloc
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pypcd4
import pytest

from service.formats import (
    InvalidPointsError,
    MissingReaderError,
    PointCloudFormatError,
    TooManyPointsError,
    read_cloud,
)
from service.formats import checks as format_checks
from service.formats import ply as ply_format
from service.pointcloud_io import SUFFIXES, parse_points, read_points, write_points

REPO = Path(__file__).resolve().parents[2]
UTM = np.array([512_345.0, 4_412_345.0, 230.0])  # metres: a UTM easting/northing and an elevation


def cloud(n: int = 500, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)  # [N, 3]


def write_ply_reference(path: Path, xyz: np.ndarray, text: bool, byte_order: str) -> None:
    """plyfile's writer, with colour properties and triangle faces besides x, y, z."""
    vertex = np.zeros(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("nx", "f4")])
    for axis, name in enumerate("xyz"):
        vertex[name] = xyz[:, axis]
    faces = np.zeros(2, dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = [[0, 1, 2], [1, 2, 3]]
    elements = [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")]
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))


def write_pcd_reference(path: Path, xyz: np.ndarray, encoding: pypcd4.Encoding) -> None:
    """pypcd4's writer, with an intensity field besides x, y, z."""
    pypcd4.PointCloud.from_xyzi_points(np.hstack([xyz, xyz[:, :1] * 0 + 7])).save(path, encoding=encoding)


def write_las_reference(path: Path, xyz: np.ndarray) -> None:
    """laspy's writer (LAZ through lazrs by the suffix), scale 2^-10 so that grid points stay exact."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [2.0**-10] * 3, np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.intensity = np.full(len(xyz), 9, dtype=np.uint16)
    las.write(str(path))


def on_las_grid(xyz: np.ndarray) -> np.ndarray:
    return np.round(xyz.astype(np.float64) * 1024) / 1024


@pytest.mark.parametrize("suffix", [*SUFFIXES, ".PLY", ".Npz"])
def test_every_written_format_reads_back(tmp_path: Path, suffix: str) -> None:
    points = cloud()
    write_points(tmp_path / f"a{suffix}", points)
    back = read_points(tmp_path / f"a{suffix}")
    assert back.dtype == np.float64 and back.shape == points.shape
    if suffix.lower() in (".xyz", ".txt", ".csv"):  # %.9g text: exact once rounded back to float32
        np.testing.assert_array_equal(back.astype(np.float32), points)
    else:
        np.testing.assert_array_equal(back, points)


@pytest.mark.parametrize("text, order", [(True, "="), (False, "<"), (False, ">")])
def test_ply_from_plyfile_ignores_extra_properties_and_faces(tmp_path: Path, text: bool, order: str) -> None:
    points = cloud()
    write_ply_reference(tmp_path / "a.ply", points, text, order)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), points)


@pytest.mark.parametrize("encoding", list(pypcd4.Encoding))
def test_pcd_from_pypcd4_every_encoding(tmp_path: Path, encoding: pypcd4.Encoding) -> None:
    points = cloud()
    write_pcd_reference(tmp_path / "a.pcd", points, encoding)
    back = read_points(tmp_path / "a.pcd")
    np.testing.assert_allclose(back, points, rtol=0, atol=1e-9)  # ascii: pypcd4 writes 10 decimals


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_keep_utm_coordinates_in_float64(tmp_path: Path, suffix: str) -> None:
    points = on_las_grid(cloud() * 20 + UTM)  # [N, 3] float32 would round these to 0.25-0.5 m
    write_las_reference(tmp_path / f"a{suffix}", points)
    np.testing.assert_array_equal(read_points(tmp_path / f"a{suffix}"), points)


def test_the_content_decides_not_the_name(tmp_path: Path) -> None:
    points = cloud()
    write_points(tmp_path / "a.ply", points)
    (tmp_path / "a.npy").write_bytes((tmp_path / "a.ply").read_bytes())  # a PLY named .npy
    (tmp_path / "scan.bin").write_bytes((tmp_path / "a.ply").read_bytes())
    for name in ("a.npy", "scan.bin"):
        np.testing.assert_array_equal(read_points(tmp_path / name), points)
    np.testing.assert_array_equal(parse_points((tmp_path / "a.ply").read_bytes(), ".xyz"), points)


def test_npy_takes_the_first_three_columns_of_any_numeric_dtype(tmp_path: Path) -> None:
    table = np.arange(40, dtype=np.int32).reshape(10, 4)
    np.save(tmp_path / "a.npy", table)
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), table[:, :3])
    np.save(tmp_path / "b.npy", np.asfortranarray(table[None].astype(np.float16)))
    np.testing.assert_array_equal(read_points(tmp_path / "b.npy"), table[:, :3])
    fields = np.zeros(4, dtype=[("x", "f8"), ("y", "f4"), ("z", "i2"), ("i", "u1")])
    fields["x"], fields["y"], fields["z"] = 1.5, 2.5, 3
    np.save(tmp_path / "c.npy", fields)
    np.testing.assert_array_equal(read_points(tmp_path / "c.npy"), [[1.5, 2.5, 3.0]] * 4)
    np.save(tmp_path / "d.npy", np.array([[1.0, 2.0, 3.0]] * 40, dtype=">f8"))  # big-endian: converted
    read = read_points(tmp_path / "d.npy")
    assert read.dtype == np.float64 and read.dtype.isnative and read.flags.writeable


@pytest.mark.parametrize(("dtype", "extra_mib"), [(np.float64, 10), (np.float32, 40)])
def test_a_full_resolution_npy_is_read_without_cloud_sized_temporaries(tmp_path: Path, dtype, extra_mib) -> None:
    """A 2,000,000-point file (the upload limit) peaks at most ``extra_mib`` above the 46 MiB float64 cloud returned:
    a float64 file is returned as read, a float32 one holds its 23 MiB raw array besides (and the checks take no
    copy of the cloud)."""
    points = np.random.default_rng(0).normal(size=(2_000_000, 3)).astype(dtype)
    np.save(tmp_path / "big.npy", points)
    tracemalloc.start()
    try:
        read = read_cloud(tmp_path / "big.npy")
        peak = tracemalloc.get_traced_memory()[1] - read.nbytes
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(read, points)
    assert peak < extra_mib * 2**20, f"{peak / 2**20:.0f} MiB above the cloud"


def test_an_ascii_ply_of_many_properties_is_read_keeping_only_x_y_z(tmp_path: Path, monkeypatch) -> None:
    """Its rows were parsed whole, every property a float64: a 210 MB file of 64 properties took 1 GB to read."""
    monkeypatch.setattr(ply_format, "ASCII_BLOCK_ROWS", 1_000)
    monkeypatch.setattr(format_checks, "BLOCK_BYTES", 1 << 16)  # the line check's pieces
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(20_000, 43)).round(4)  # [N, 43]: x, y, z and 40 more
    names = ["x", "y", "z", *(f"f{k}" for k in range(40))]
    header = f"ply\nformat ascii 1.0\nelement vertex {len(rows)}\n" + "".join(f"property float {n}\n" for n in names)
    (tmp_path / "wide.ply").write_text(header + "end_header\n" + "".join(" ".join(map(str, r)) + "\n" for r in rows))
    tracemalloc.start()
    try:
        read = read_cloud(tmp_path / "wide.ply")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(read, rows[:, :3].astype(np.float32))
    assert peak < 4 * 2**20, f"{peak / 2**20:.1f} MiB for {rows[:, :3].nbytes / 2**20:.1f} MiB of x, y, z"


def test_text_skips_comments_header_and_extra_columns(tmp_path: Path) -> None:
    (tmp_path / "a.csv").write_text("# scan\nx,y,z,intensity\n1,2,3,9\n4,5,6,9\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.csv"), [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "a.xyz").write_text("1 2 3\n\n-1e3\t2.5 -0.125 0 0 0\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.xyz"), [[1, 2, 3], [-1000, 2.5, -0.125]])


BAD_FILES = {
    "random_bytes": (bytes(range(256)) * 4, PointCloudFormatError, "unrecognised content"),
    "ply_truncated": (None, PointCloudFormatError, "PLY"),
    "ply_without_z": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
                      InvalidPointsError, "lacks properties ['z']"),
    "ply_bad_header": (b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n", PointCloudFormatError, "PLY header"),
    "pcd_no_fields": (b"VERSION 0.7\nPOINTS 1\nDATA ascii\n1 2 3\n", PointCloudFormatError, "PCD header"),
    "npy_pickle": (None, InvalidPointsError, "pickle"),
    "npy_two_columns": (None, InvalidPointsError, "[N, 3]"),
    "text_two_columns": (b"1 2\n3 4\n", InvalidPointsError, "at least 3 numbers"),
    "text_words": (b"1 2 3\n4 five 6\n", InvalidPointsError, "five"),
    "nan": (b"1 2 3\nnan 5 6\n", InvalidPointsError, "NaN/Inf"),
    "empty_text": (b"# nothing\n", InvalidPointsError, "empty"),
    "las_truncated": (None, PointCloudFormatError, "LAS"),
    "latin1_csv": ("x,y,z,intensité\n1,2,3,4\n5,6,7,8\n".encode("cp1252"), PointCloudFormatError,
                   "not UTF-8 (Latin-1 or Windows-1252"),  # it was "unrecognised content"
    # text meshes: their counts, face indices and vertices were read as points
    "off_mesh": (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", PointCloudFormatError, "an OFF mesh"),
    "off_as_modelnet40_writes_it": (b"OFF3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", PointCloudFormatError, "an OFF mesh"),
    "obj_mesh": (b"# exported\nmtllib a.mtl\no Cube\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", PointCloudFormatError,
                 "an OBJ mesh"),
    "stl_ascii": (b"solid part\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n", PointCloudFormatError,
                  "an STL mesh"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_fail_with_the_name_and_the_reason(tmp_path: Path, case: str) -> None:
    data, error, words = BAD_FILES[case]
    if case == "ply_truncated":
        write_points(tmp_path / "a.ply", cloud())
        data = (tmp_path / "a.ply").read_bytes()[:-100]
    elif case == "npy_pickle":
        np.save(tmp_path / "a.npy", np.array([{"x": 1}] * 4, dtype=object), allow_pickle=True)
        data = (tmp_path / "a.npy").read_bytes()
    elif case == "npy_two_columns":
        np.save(tmp_path / "a.npy", np.zeros((5, 2)))
        data = (tmp_path / "a.npy").read_bytes()
    elif case == "las_truncated":
        write_las_reference(tmp_path / "a.las", on_las_grid(cloud()))
        data = (tmp_path / "a.las").read_bytes()[:-50]
    with pytest.raises(error) as caught:
        read_cloud(data, name="scan.dat")
    assert str(caught.value).startswith("scan.dat: ") and words in str(caught.value)


@pytest.mark.parametrize("fmt", ["ply", "pcd", "npy", "las"])
def test_the_point_limit_is_checked_from_the_header_before_reading(tmp_path: Path, fmt: str) -> None:
    """A header announcing 10^12 points is refused as too many, not by running out of memory."""
    if fmt == "ply":
        data = b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\n" \
               b"property float z\nend_header\n1 2 3\n"
    elif fmt == "pcd":
        data = b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000000\nHEIGHT 1\n" \
               b"POINTS 1000000000000\nDATA binary_compressed\n\x00\x00\x00\x00"
    elif fmt == "npy":
        header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000, 3), }"
        data = b"\x93NUMPY\x01\x00" + (len(header) + 1).to_bytes(2, "little") + header + b"\n"
    else:
        write_las_reference(tmp_path / "a.las", on_las_grid(cloud()))
        data = bytearray((tmp_path / "a.las").read_bytes())
        data[107:111] = (4_000_000_000).to_bytes(4, "little")  # legacy point count of a LAS 1.2 header
    with pytest.raises(TooManyPointsError, match="the limit is 2000000"):
        read_cloud(bytes(data), name="big", max_points=2_000_000)


def test_text_point_limit() -> None:
    with pytest.raises(TooManyPointsError, match="more than 3 points"):
        read_cloud(b"1 2 3\n" * 4, max_points=3)
    assert read_cloud(b"1 2 3\n" * 3, max_points=3).shape == (3, 3)


BLOCKED_READER = """
import sys
sys.modules[{module!r}] = None  # as if the package were not installed: import raises ImportError
from service.formats import MissingReaderError, read_cloud
try:
    read_cloud(open(sys.argv[1], "rb").read(), name="scan")
except MissingReaderError as exc:
    print(exc.status, exc)
"""


@pytest.mark.parametrize("module, fmt", [("plyfile", "ply"), ("pypcd4", "pcd"), ("laspy", "las"), ("lazrs", "laz")])
def test_a_missing_reader_library_names_the_extra(tmp_path: Path, module: str, fmt: str) -> None:
    path = tmp_path / f"a.{fmt}"
    if fmt in ("las", "laz"):
        write_las_reference(path, on_las_grid(cloud()))
    else:
        write_points(path, cloud())
    script = BLOCKED_READER.format(module=module)
    out = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, timeout=120,
                         cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("415 scan: ") and f"'{module}'" in out.stdout and "mfgnet[formats]" in out.stdout
    assert MissingReaderError.status == 415


def test_write_refuses_bad_points(tmp_path: Path) -> None:
    with pytest.raises(PointCloudFormatError, match="unknown extension"):
        write_points(tmp_path / "a.las", cloud())
    with pytest.raises(PointCloudFormatError, match=r"\(N, 3\)"):
        write_points(tmp_path / "a.ply", np.zeros((4, 2)))
    with pytest.raises(PointCloudFormatError, match="NaN"):
        write_points(tmp_path / "a.ply", np.full((4, 3), np.nan))
