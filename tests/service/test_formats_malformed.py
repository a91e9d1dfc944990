"""Malformed point-cloud files found by fuzzing the readers (``service.formats``): each gets the readers' own
error (a 4xx over HTTP) naming the problem, never another exception (a 500), a hang, an allocation of what a
header declares before the body is known to hold it, or an abort of the process (``lazrs``, in Rust, aborts
when an allocation fails, so those files are read in a subprocess here)."""

from __future__ import annotations

import io
import re
import struct
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pypcd4
import pytest
from api_server import MODEL, assert_error
from traced_peak import peak_bytes
from typer.testing import CliRunner

from service.cli import app
from service.formats import InvalidPointsError, PointCloudFormatError, checks, read_cloud, write_cloud

REPO = Path(__file__).resolve().parents[2]
LIMIT = 2_000_000  # the server's max_file_points
LAS_VLR_HEADER = 54
LAS12_HEADER, LAS14_HEADER = 227, 375


def cloud(n: int = 24) -> np.ndarray:
    return np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)  # [N, 3]


def read_in_subprocess(path: Path, memory_mib: int = 3000) -> subprocess.CompletedProcess:
    """read_cloud(path) in a fresh interpreter limited to ``memory_mib`` of address space: prints the shape or the
    error; a Rust allocation failure aborts it (return code -6)."""
    script = (
        "import resource, sys\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({memory_mib} << 20, {memory_mib} << 20))\n"
        "from service.formats import PointCloudFormatError, read_cloud\n"
        "try:\n"
        f"    print('points', read_cloud(sys.argv[1], max_points={LIMIT}).shape)\n"
        "except PointCloudFormatError as exc:\n"
        "    print('error', exc)\n"
    )
    return subprocess.run(
        [sys.executable, "-c", script, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"},
    )


# --- PLY ---------------------------------------------------------------------------------------------------------


def ply_bytes(xyz: np.ndarray, text: bool, extra: int = 0) -> bytes:
    fields = [(axis, "f8") for axis in "xyz"] + [(f"p{i}", "f8") for i in range(extra)]
    vertex = np.zeros(len(xyz), dtype=fields)
    for axis, name in enumerate("xyz"):
        vertex[name] = xyz[:, axis]
    out = io.BytesIO()
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=text).write(out)
    return out.getvalue()


def test_ply_count_beyond_int64_is_a_format_error(tmp_path: Path) -> None:
    """plyfile raised OverflowError (its element's len() cannot be that large)."""
    write_cloud(tmp_path / "a.ply", cloud())
    data = (tmp_path / "a.ply").read_bytes().replace(b"element vertex 24", f"element vertex {2**63}".encode())
    (tmp_path / "big.ply").write_bytes(data)
    with pytest.raises(PointCloudFormatError, match=f"declares {2**63} 'vertex' rows"):
        read_cloud(tmp_path / "big.ply")


def test_ply_huge_count_of_another_element_is_refused_before_allocating(tmp_path: Path) -> None:
    """Only the vertex count was checked against max_points: an ASCII face count made plyfile allocate an array
    of that many rows (MemoryError, a 500)."""
    data = ply_bytes(cloud().astype(np.float64), text=True)
    data = data.replace(
        b"end_header", b"element face 1000000000000000\nproperty list uchar int vertex_indices\nend_header"
    )
    (tmp_path / "a.ply").write_bytes(data)
    with pytest.raises(PointCloudFormatError, match="declares 1000000000000000 'face' rows") as caught:
        read_cloud(tmp_path / "a.ply", max_points=LIMIT)
    assert str(caught.value).startswith("a.ply: ")


def test_ply_vertex_count_within_the_limit_is_checked_against_the_body(tmp_path: Path) -> None:
    """1,999,999 vertices of 13 doubles announced, 24 written: plyfile allocated the 208 MB before reading."""
    data = ply_bytes(cloud().astype(np.float64), text=True, extra=10)
    (tmp_path / "a.ply").write_bytes(data.replace(b"element vertex 24", b"element vertex 1999999"))

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match="declares 1999999 'vertex' rows"):
            read_cloud(tmp_path / "a.ply", max_points=LIMIT)

    assert peak_bytes(read) < 16 << 20


def test_ply_header_without_end_header_is_refused_after_its_first_256_kib(tmp_path: Path) -> None:
    """plyfile parses a header a byte at a time: a 256 MiB upload of comment lines kept a worker busy for minutes."""
    (tmp_path / "a.ply").write_bytes(b"ply\nformat ascii 1.0\n" + b"comment more\n" * 400_000)
    with pytest.raises(PointCloudFormatError, match="no end_header in its first 262144 bytes"):
        read_cloud(tmp_path / "a.ply")


# --- PCD ---------------------------------------------------------------------------------------------------------

PCD_HEADER = (
    "VERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {type}\nCOUNT {count}\nWIDTH {points}\nHEIGHT 1\n"
    "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
)


def pcd_header(
    points: int = 24,
    data: str = "ascii",
    fields: str = "x y z",
    size: str = "4 4 4",
    type: str = "F F F",
    count: str = "1 1 1",
) -> bytes:
    return PCD_HEADER.format(fields=fields, size=size, type=type, count=count, points=points, data=data).encode()


def test_pcd_after_many_comment_lines_is_read_as_pcd(tmp_path: Path) -> None:
    """Comment lines filling the first KiB made the file text, and over 64 lines of them left no room for the header."""
    comments = b"".join(b"# scanner export, line %d of a long provenance note\n" % i for i in range(300))
    header = pcd_header(points=2).replace(b"SIZE", b"# between entries\n" * 100 + b"SIZE")
    (tmp_path / "a.pcd").write_bytes(comments + header + b"1 2 3\n4 5 6\n")
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.pcd"), [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "a.xyz").write_bytes(comments + b"1 2 3\n4 5 6\n")  # text after as many comments is still text
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.xyz"), [[1, 2, 3], [4, 5, 6]])


def test_pcd_without_points_is_an_empty_cloud(tmp_path: Path) -> None:
    """POINTS 0 raised numpy's ValueError (reshape of an empty table)."""
    (tmp_path / "a.pcd").write_bytes(pcd_header(points=0))
    with pytest.raises(InvalidPointsError, match="empty"):
        read_cloud(tmp_path / "a.pcd")


def test_pcd_xyz_with_count_above_one_is_refused(tmp_path: Path) -> None:
    """COUNT 2 for x raised numpy's ValueError (pypcd4 names the values x__0000, x__0001)."""
    rows = b"".join(b"%g %g %g %g\n" % (x, x, y, z) for x, y, z in cloud())
    (tmp_path / "a.pcd").write_bytes(pcd_header(count="2 1 1") + rows)
    with pytest.raises(InvalidPointsError, match=r"\['x'\] have COUNT > 1"):
        read_cloud(tmp_path / "a.pcd")


@pytest.mark.parametrize(
    "entries",
    [
        {"size": "2 2 2"},  # no 2-byte float: KeyError
        {"size": "4 4"},  # fewer sizes than fields: IndexError
        {"fields": "x y z x", "size": "4 4 4 4", "type": "F F F F", "count": "1 1 1 1"},  # numpy's ValueError
    ],
    ids=["float16", "short_size", "field_twice"],
)
def test_pcd_fields_without_a_record_type_are_a_header_error(tmp_path: Path, entries: dict) -> None:
    """The binary_compressed size check built pypcd4's record type outside any error handling."""
    (tmp_path / "a.pcd").write_bytes(pcd_header(data="binary_compressed", **entries) + bytes(8))
    with pytest.raises(PointCloudFormatError, match="invalid PCD header"):
        read_cloud(tmp_path / "a.pcd")


@pytest.mark.parametrize(
    "header,message",
    [
        (lambda: pcd_header().replace(b"DATA ascii\n", b""), "no DATA line"),
        (lambda: pcd_header().replace(b"DATA ascii", b"DATA"), "DATA must be one of"),
        (lambda: pcd_header().replace(b"DATA ascii", b"DATA text"), "DATA must be one of"),
        (lambda: pcd_header(fields="x y z " + " ".join(f"f{i}" for i in range(1000))), "a line longer than 4096 bytes"),
        (lambda: pcd_header().replace(b"WIDTH 24", b"WIDTH many"), "invalid PCD header"),
        (lambda: pcd_header().replace(b"WIDTH 24", b"WIDTH 12"), "WIDTH 12 x HEIGHT 1 = 12 points, but POINTS says 24"),
        (lambda: pcd_header().replace(b"HEIGHT 1", b"HEIGHT 2"), "WIDTH 24 x HEIGHT 2 = 48 points, but POINTS says 24"),
    ],
    ids=["no_data_line", "bare_data", "unknown_data", "long_line", "width_not_a_number", "width_short_of_points",
         "grid_beyond_points"],
)
def test_pcd_header_errors_name_the_problem(tmp_path: Path, header, message: str) -> None:
    """pypcd4 took a missing or bare DATA line for binary_compressed ("data cut short", "declares 825637174 bytes"),
    a header line beyond 4,096 bytes was split silently, and pydantic's text and URL reached the message."""
    (tmp_path / "a.pcd").write_bytes(header() + b"1 2 3\n" * 24)
    with pytest.raises(PointCloudFormatError, match=message) as caught:
        read_cloud(tmp_path / "a.pcd")
    assert "pydantic" not in str(caught.value) and "binary_compressed data" not in str(caught.value)


def test_pcd_count_is_bounded_before_pypcd4_names_every_value(tmp_path: Path) -> None:
    """pypcd4 makes a record field per value: COUNT 1 1 100000000 took minutes and gigabytes."""
    (tmp_path / "a.pcd").write_bytes(pcd_header(count="1 1 300000") + b"1 2 3\n")
    with pytest.raises(PointCloudFormatError, match="COUNT adds up to 300002 values per point"):
        read_cloud(tmp_path / "a.pcd")


def test_pcd_header_of_eleven_entries_reads(tmp_path: Path) -> None:
    """pypcd4 stops at ten header lines: an eleventh (a repeated VERSION) left its DATA unread, the binary points
    were taken for a compressed block and a 1 GB read was allocated."""
    write_cloud(tmp_path / "a.pcd", cloud())
    data = (tmp_path / "a.pcd").read_bytes().replace(b"VERSION 0.7\n", b"VERSION 0.7\nVERSION 0.7\n", 1)
    (tmp_path / "b.pcd").write_bytes(data)
    np.testing.assert_array_equal(read_cloud(tmp_path / "b.pcd"), cloud())


def test_pcd_binary_points_beyond_the_body_are_refused_before_reading(tmp_path: Path) -> None:
    """POINTS 100,000,000 over 24 points of data: the file read allocated 1.2 GB first."""
    write_cloud(tmp_path / "a.pcd", cloud())
    data = (tmp_path / "a.pcd").read_bytes()
    data = data.replace(b"WIDTH 24", b"WIDTH 100000000").replace(b"POINTS 24", b"POINTS 100000000")
    (tmp_path / "b.pcd").write_bytes(data)

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match="PCD binary data holds 288 bytes"):
            read_cloud(tmp_path / "b.pcd")

    assert peak_bytes(read) < 64 << 20


def test_pcd_compressed_block_that_cannot_expand_to_its_size_is_refused(tmp_path: Path) -> None:
    """A 120 MB block declared by a 400-byte file (4 GB, the largest a block can declare, before blocks above
    MAX_COMPRESSED_BLOCK_BYTES were refused): lzf allocated its declared size before decompressing."""
    path = tmp_path / "a.pcd"
    points = np.ones((24, 3), dtype=np.float32)  # compressible: pypcd4 writes binary where LZF gains nothing
    pypcd4.PointCloud.from_xyz_points(points).save(path, encoding=pypcd4.Encoding.BINARY_COMPRESSED)
    data = path.read_bytes()
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed = struct.unpack_from("<I", data, start)[0]
    points = 10_000_000  # 12 bytes each
    header = data[:start].replace(b"WIDTH 24", b"WIDTH %d" % points).replace(b"POINTS 24", b"POINTS %d" % points)
    path.write_bytes(header + struct.pack("<II", compressed, points * 12) + data[start + 8 :])
    with pytest.raises(PointCloudFormatError, match="cannot expand to the 120000000 bytes"):
        read_cloud(path)


def compressed_pcd(points: int, extra_values: int) -> bytes:
    """A binary_compressed PCD of ``points`` records of x, y, z and ``extra_values`` more float32 values, all zeros: an
    LZF stream of one literal byte and back references of 264 bytes, about 88 times smaller than what it expands to."""
    raw = points * (12 + 4 * extra_values)
    full, rest = divmod(raw - 1, 264)
    stream = (
        b"\x00\x00"
        + b"\xe0\xff\x00" * full
        + (bytes([0xE0, rest - 9, 0]) if rest >= 9 else bytes([(rest - 2) << 5, 0]) if rest else b"")
    )
    header = (
        f"VERSION 0.7\nFIELDS x y z p\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 {extra_values}\n"
        f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA binary_compressed\n"
    )
    return header.encode() + struct.pack("<II", len(stream), raw) + stream


@pytest.mark.parametrize(
    ("points", "extra", "expands"), [(2_000_000, 131, 1_072_000_000), (2_000_000, 29, 256_000_000)]
)
def test_pcd_compressed_blocks_above_128_mib_are_refused_before_decompressing(
    tmp_path: Path, points: int, extra: int, expands: int
) -> None:
    """2,000,000 records of 536 bytes in a 12 MB file: a 1 GB block that pypcd4 decompressed, zeroed and copied
    (2.4 GiB of server memory for one upload); of 128 bytes, 256 MB expanded took 472 MiB above idle."""
    path = tmp_path / "a.pcd"
    path.write_bytes(compressed_pcd(points, extra))

    def read() -> None:
        with pytest.raises(InvalidPointsError, match=f"expands to {expands} bytes, at most 134217728"):
            read_cloud(path)

    assert peak_bytes(read) < 64 << 20


@pytest.mark.parametrize(("points", "extra"), [(1000, 29), (200_000, 33)])  # 128 bytes; FPFH33 beside x, y, z
def test_pcd_compressed_records_of_any_width_read_within_the_block_limit(
    tmp_path: Path, points: int, extra: int
) -> None:
    path = tmp_path / "a.pcd"
    path.write_bytes(compressed_pcd(points, extra))
    assert read_cloud(path).shape == (points, 3)


def test_pcd_compressed_block_is_expanded_once_and_only_x_y_z_kept(tmp_path: Path) -> None:
    """pypcd4 held the expanded block and a zeroed record array of every field: twice the block's 64 MB here."""
    path = tmp_path / "a.pcd"
    path.write_bytes(compressed_pcd(500_000, 29))  # 128-byte records
    points = {}

    def read() -> None:
        points["xyz"] = read_cloud(path)

    assert peak_bytes(read) < 96 << 20
    assert points["xyz"].shape == (500_000, 3)


def test_pcd_ascii_reads_x_y_z_of_the_rows_the_header_declares(tmp_path: Path) -> None:
    """pypcd4 parsed every field of every row: 6,000,000 rows under a header of 10 points (36 MB) were all read."""
    path = tmp_path / "a.pcd"
    path.write_bytes(pcd_header(points=10).replace(b"SIZE 4 4 4", b"SIZE 8 8 8") + b"1 2 3\n" * 6_000_000)
    points = {}

    def read() -> None:
        points["xyz"] = read_cloud(path)

    assert peak_bytes(read) < 32 << 20
    np.testing.assert_array_equal(points["xyz"], np.tile([1.0, 2.0, 3.0], (10, 1)))


def test_pcd_ascii_integer_fields_hold_integers(tmp_path: Path) -> None:
    path = tmp_path / "a.pcd"
    path.write_bytes(pcd_header(points=2, type="I I I") + b"1 2 3\n4 5.5 6\n")
    with pytest.raises(PointCloudFormatError, match="PCD field y values that are not int32 integers"):
        read_cloud(path)


FOUR_FIELDS = {"fields": "x y z intensity", "size": "4 4 4 4", "type": "F F F F", "count": "1 1 1 1"}


@pytest.mark.parametrize(
    ("rows", "row", "values"),
    [
        (b"1 2 3 4\n1 2 3\n1 2 3 4\n", 2, 3),
        (b"1 2 3 4\r\n\r\n1 2 3 4 5\r\n1 2 3 4\r\n", 2, 5),  # CRLF and a blank line
        (b"1 2 3 4\n" * 700_000 + b"1\t2 3\n" + b"1 2 3 4\n", 700_001, 3),  # past the first 4 MiB block
        (b"1 2 3 4\n" * 2 + b"1 2  3", 3, 3),  # a last row without a line break
    ],
)
def test_pcd_ascii_rows_hold_one_value_per_field(tmp_path: Path, rows: bytes, row: int, values: int) -> None:
    """Only x, y and z are parsed; a row of more or fewer values than the fields is still refused, as pypcd4's typed
    parse of every field refused it."""
    path = tmp_path / "a.pcd"
    path.write_bytes(pcd_header(points=rows.count(b"1 "), **FOUR_FIELDS) + rows)
    with pytest.raises(PointCloudFormatError, match=f"row {row} holds {values} values; the header declares 4"):
        read_cloud(path)


@pytest.mark.parametrize(
    "rows", [b"1 2 3 4\n\n 5 6 7 8 \n\t9 10 11 12", b"1 2 3 4\r\n5 6 7 8\r\n9 10 11 12\r\n" + b"1 2\n" * 5]
)  # rows past POINTS are not read
def test_pcd_ascii_rows_of_the_declared_values_are_read(tmp_path: Path, rows: bytes) -> None:
    path = tmp_path / "a.pcd"
    path.write_bytes(pcd_header(points=3, **FOUR_FIELDS) + rows)
    np.testing.assert_array_equal(read_cloud(path), [[1, 2, 3], [5, 6, 7], [9, 10, 11]])


def ply_of(elements: list, text: bool = False, byte_order: str = "<") -> bytes:
    out = io.BytesIO()
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(out)
    return out.getvalue()


def vertices(n: int = 1000) -> tuple[np.ndarray, plyfile.PlyElement]:
    xyz = cloud(n)
    rows = np.zeros(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1")])
    rows["x"], rows["y"], rows["z"] = xyz.T
    return xyz.astype(np.float64), plyfile.PlyElement.describe(rows, "vertex")


def lists(name: str, n: int, length: int) -> plyfile.PlyElement:
    rows = np.empty(n, dtype=[("vertex_indices", "O")])
    rows["vertex_indices"] = [np.arange(length, dtype=np.int32)] * n
    return plyfile.PlyElement.describe(rows, name, val_types={"vertex_indices": "i4"})


def test_ply_faces_after_the_vertices_are_never_read(tmp_path: Path) -> None:
    """300,000 quads after the vertices: plyfile read faces that are not triangles row by row in Python (3,000,000 took
    23 s and 0.9 GB of server memory); only the vertex rows are read now."""
    xyz, vertex = vertices()
    (tmp_path / "a.ply").write_bytes(ply_of([vertex, lists("face", 300_000, 4)]))

    def read() -> None:
        np.testing.assert_array_equal(read_cloud(tmp_path / "a.ply"), xyz)

    assert peak_bytes(read) < 8 << 20


@pytest.mark.parametrize("length", [2, 0], ids=["edges", "empty_lists"])
def test_ply_of_short_list_rows_reads(tmp_path: Path, length: int) -> None:
    """Rows of lists shorter than a triangle's: plyfile's pre-check called the valid file cut short."""
    xyz, vertex = vertices()
    (tmp_path / "a.ply").write_bytes(ply_of([vertex, lists("edge", 5000, length)]))
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.ply"), xyz)


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_vertices_after_other_elements_read(tmp_path: Path, text: bool, byte_order: str) -> None:
    xyz, vertex = vertices()
    camera = np.zeros(2, dtype=[("k1", "f8"), ("k2", "i2")])
    before = [plyfile.PlyElement.describe(camera, "camera")] + ([lists("face", 30, 3)] if text else [])
    (tmp_path / "a.ply").write_bytes(ply_of([*before, vertex], text=text, byte_order=byte_order))
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.ply"), xyz)


ASCII_PLY_HEAD = (
    "ply\nformat ascii 1.0\n{before}element vertex {count}\nproperty float x\nproperty float y\n"
    "property float z\n{after}end_header\n"
)
FACES = "element face 10\nproperty list uchar int vertex_indices\n"


@pytest.mark.parametrize(
    "head,rows",
    [
        (
            ASCII_PLY_HEAD.format(
                before="", count=110, after=FACES
            ),  # 100 vertex rows: the faces were read as vertices
            "".join(f"{i} {i} {i}\n" for i in range(100)) + "".join(f"3 {i} {i + 1} {i + 2}\n" for i in range(10)),
        ),
        (
            ASCII_PLY_HEAD.format(before=FACES, count=100, after=""),  # a blank line: one face row was read as a vertex
            "\n"
            + "".join(f"3 {i} {i + 1} {i + 2}\n" for i in range(10))
            + "".join(f"{i} {i} {i}\n" for i in range(100)),
        ),
    ],
    ids=["vertex_count_past_its_rows", "blank_line_before_the_faces"],
)
def test_ascii_ply_rows_are_not_taken_for_vertices(tmp_path: Path, head: str, rows: str) -> None:
    (tmp_path / "a.ply").write_text(head + rows)
    try:
        xyz = read_cloud(tmp_path / "a.ply")
    except PointCloudFormatError as exc:
        assert "corrupt PLY data" in str(exc)
    else:
        np.testing.assert_array_equal(xyz, np.repeat(np.arange(100.0)[:, None], 3, axis=1))


def test_binary_pcd_holds_only_x_y_z_while_read(tmp_path: Path) -> None:
    """pypcd4 read the body whole: 250,000 records of 256 bytes (64 MB) held at once."""
    n = 250_000
    records = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "<f4", (61,))])
    records["x"] = np.arange(n)
    header = pcd_header(points=n, data="binary", fields="x y z pad", size="4 4 4 4", type="F F F F", count="1 1 1 61")
    (tmp_path / "a.pcd").write_bytes(header + records.tobytes())
    points = {}

    def read() -> None:
        points["xyz"] = read_cloud(tmp_path / "a.pcd")

    assert peak_bytes(read) < 16 << 20  # the output is 6 MB
    np.testing.assert_array_equal(points["xyz"][:, 0], np.arange(n))


def test_binary_ply_whose_vertices_follow_lists_is_refused(tmp_path: Path) -> None:
    vertex = vertices()[1]
    (tmp_path / "a.ply").write_bytes(ply_of([lists("face", 30, 3), vertex]))
    with pytest.raises(InvalidPointsError, match="follows an element of lists"):
        read_cloud(tmp_path / "a.ply")


# --- text lines ---------------------------------------------------------------------------------------------------

LONG_ROW = " ".join(["1"] * 1_500_000)  # 3 MB: numpy's text reader kept about 32 bytes per value of a line


@pytest.mark.parametrize(
    "name,text",
    [
        ("a.xyz", LONG_ROW + "\n"),
        ("a.xyz", "x y z\n" + "1 2 3\n" * 40 + LONG_ROW + "\n1 2 3\n"),
        (
            "a.ply",
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            "end_header\n" + LONG_ROW + "\n1 2 3\n",
        ),
        (
            "a.pcd",
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
            "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n" + LONG_ROW + "\n1 2 3\n",
        ),
        (
            "a.pcd",
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
            "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 3\r\n" + LONG_ROW,
        ),  # no line break after it
    ],
    ids=["xyz_one_line", "xyz_after_rows", "ply_ascii", "pcd_ascii", "pcd_ascii_last_line"],
)
def test_a_text_line_beyond_a_mebibyte_is_refused_before_parsing(tmp_path: Path, name: str, text: str) -> None:
    """One line of a 256 MiB upload took several GB of server memory to parse (or to split, for the header probe)."""
    (tmp_path / name).write_text(text)

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match="a line longer than 1048576 bytes"):
            read_cloud(tmp_path / name)

    assert peak_bytes(read) < 32 << 20


@pytest.mark.parametrize(
    "text,words",
    [
        ("hello\n", "no rows of numbers after its first line 'hello'"),  # a .ply of anything else: read as text
        ("x,y,z\n", "no rows of numbers after its first line 'x,y,z'"),  # a header and no rows
        ("# exported\n\n# nothing\n", "only comments or blank lines"),
    ],
    ids=["a_word", "header_only", "comments_only"],
)
def test_text_without_rows_of_numbers_names_what_it_holds_and_warns_nothing(
    tmp_path: Path, text: str, words: str
) -> None:
    """numpy's "loadtxt: input contained no data" UserWarning reached stderr (the CLI's, the server's log), and the
    error said only "the cloud is empty", of a file that was not read as the format its name says."""
    (tmp_path / "scan.ply").write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidPointsError, match=re.escape(words)) as caught:
            read_cloud(tmp_path / "scan.ply")
    assert "read as XYZ/CSV/TXT text" in str(caught.value)


def test_an_empty_file_says_so(tmp_path: Path) -> None:
    (tmp_path / "scan.ply").write_bytes(b"")
    with pytest.raises(PointCloudFormatError, match=r"the file is empty \(0 bytes\)"):
        read_cloud(tmp_path / "scan.ply")


def test_pcd_ascii_line_too_long_is_refused_before_a_row_of_other_values(tmp_path: Path) -> None:
    """Lines and values are checked in one pass; a line too long anywhere is still the error given, as when every line
    was checked before the rows."""
    (tmp_path / "a.pcd").write_bytes(pcd_header(points=3) + b"1 2\n" + LONG_ROW.encode() + b"\n1 2 3\n")
    with pytest.raises(PointCloudFormatError, match="PCD ascii data: a line longer than 1048576 bytes"):
        read_cloud(tmp_path / "a.pcd")


def text_lines_error(body: bytes, start: int, rows: int, values: int, limit: int) -> str | None:
    """The error :func:`checks.check_text_lines` gives for ``body`` (at byte ``start`` of its file), found line by
    line: the first line longer than ``limit``, else the first of the first ``rows`` non-blank rows of other than
    ``values`` values."""
    lines = re.split(rb"[\r\n]", body)
    for line, offset in zip(lines, np.cumsum([start] + [len(line) + 1 for line in lines[:-1]]), strict=True):
        if len(line) > limit:
            return f"L: a line longer than {limit} bytes (from byte {offset}); rows of numbers are far shorter"
    counts = [len(line.split()) for line in lines if line.split()][:rows]
    wrong = [row for row, count in enumerate(counts) if count != values]
    if wrong:
        return f"R: row {wrong[0] + 1} holds {counts[wrong[0]]} values; the header declares {values} per row"
    return None


@pytest.mark.parametrize("seed", range(4))
def test_text_lines_check_agrees_with_reading_line_by_line(monkeypatch: pytest.MonkeyPatch, seed: int) -> None:
    """Blocks and pieces of a few bytes, so that lines, values, CR LF pairs and blank rows straddle them; bodies with
    and without a last line break, lines too long, rows of too few and too many values, rows past those counted."""
    rng = np.random.default_rng(seed)
    monkeypatch.setattr(checks, "MAX_TEXT_LINE_BYTES", 24)
    for _ in range(300):
        monkeypatch.setattr(checks, "BLOCK_BYTES", int(rng.integers(1, 40)))
        monkeypatch.setattr(checks, "COUNT_BLOCK_BYTES", int(rng.integers(1, 40)))
        lines = [
            b"".join(rng.choice([b" ", b"\t", b"  "]) + rng.choice([b"1", b"-2.5"]) for _ in range(values))
            + rng.choice([b"\n", b"\r\n", b"\r", b" \n"])
            for values in rng.choice([0, 3, 4, 4, 5, 9], size=rng.integers(0, 10))
        ]  # 9 values: often too long
        body = b"".join(lines).rstrip(b"\r\n") if rng.random() < 0.3 else b"".join(lines)
        rows = int(rng.integers(0, 12))
        f = io.BytesIO(b"DATA ascii\n" + body)
        f.seek(11)
        try:
            checks.check_text_lines(f, "L", rows, 4, "R")
            found = None
        except PointCloudFormatError as exc:
            found = str(exc)
        assert found == text_lines_error(body, 11, rows, 4, 24), (body, rows)
        assert f.tell() == 11


def test_text_rows_of_a_thousand_values_read(tmp_path: Path) -> None:
    rows = "\n".join(" ".join(f"{v:.6f}" for v in row) for row in np.random.default_rng(0).normal(size=(40, 1000)))
    (tmp_path / "a.txt").write_text(rows + "\n")
    assert read_cloud(tmp_path / "a.txt").shape == (40, 3)


# --- LAS / LAZ ---------------------------------------------------------------------------------------------------


def las_bytes(version: str, point_format: int, compressed: bool, n: int = 24) -> bytearray:
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales, header.offsets = [2.0**-10] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud(n).astype(np.float64).T
    out = io.BytesIO()
    las.write(out, do_compress=compressed)
    return bytearray(out.getvalue())


def on_grid(xyz: np.ndarray) -> np.ndarray:
    return np.round(xyz.astype(np.float64) * 1024) / 1024


def test_las_vlr_count_beyond_the_file_is_refused(tmp_path: Path) -> None:
    """laspy reads one VLR per count, past the end of the file: 4,294,967,295 of them took hours."""
    data = las_bytes("1.2", 0, compressed=False)
    struct.pack_into("<I", data, 100, 300_000)
    (tmp_path / "a.las").write_bytes(data)
    with pytest.raises(PointCloudFormatError, match="declares 300000 VLRs"):
        read_cloud(tmp_path / "a.las")


@pytest.mark.parametrize("compressed", [False, True], ids=["las", "laz"])
def test_las14_evlr_count_is_not_read(tmp_path: Path, compressed: bool) -> None:
    """The EVLRs (never used here) were read from their count and offset: one at offset 0 read the header as an
    EVLR and allocated its length (MemoryError)."""
    data = las_bytes("1.4", 6, compressed)
    struct.pack_into("<I", data, 243, 1)  # number of EVLRs; the start of the first stays 0
    (tmp_path / "a.las").write_bytes(data)
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.las"), on_grid(cloud()))


def test_las_point_count_beyond_the_body_is_refused_before_reading(tmp_path: Path) -> None:
    """1,900,000 points (within max_points) announced over 24: laspy allocated 65 MB before reading."""
    data = las_bytes("1.2", 3, compressed=False)
    struct.pack_into("<I", data, 107, 1_900_000)  # legacy point count
    (tmp_path / "a.las").write_bytes(data)

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match="declares 1900000 points of 34 bytes"):
            read_cloud(tmp_path / "a.las", max_points=LIMIT)

    assert peak_bytes(read) < 16 << 20


def test_laz_chunk_table_count_beyond_the_file_does_not_abort(tmp_path: Path) -> None:
    """lazrs allocated 16 bytes per declared chunk: 4,294,967,295 chunks aborted the process (a server down)."""
    data = las_bytes("1.2", 1, compressed=True)
    points_at = struct.unpack_from("<I", data, 96)[0]
    table = struct.unpack_from("<q", data, points_at)[0]
    struct.pack_into("<I", data, table + 4, 0xFFFFFFFF)
    (tmp_path / "a.laz").write_bytes(data)
    out = read_in_subprocess(tmp_path / "a.laz")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("error a.laz: LAZ chunk table") and "4294967295 chunks" in out.stdout


def test_laz_vlr_chunk_size_does_not_abort(tmp_path: Path) -> None:
    """lazrs's parallel decompressor allocated the LAZ VLR's chunk size in points at once: 4,294,967,280 aborted
    the process. The sequential one reads the 24 points."""
    data = las_bytes("1.2", 1, compressed=True)
    struct.pack_into("<I", data, LAS12_HEADER + LAS_VLR_HEADER + 12, 0xFFFFFFF0)
    (tmp_path / "a.laz").write_bytes(data)
    out = read_in_subprocess(tmp_path / "a.laz")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("points (24, 3)")


def test_laz14_damage_in_a_layer_other_than_xyz_is_skipped(tmp_path: Path) -> None:
    """A LAZ 1.4 chunk declares each layer's size: a 4 GB intensity layer was allocated (an abort under a memory
    limit). Only the x, y and z layers are decompressed now."""
    data = las_bytes("1.4", 6, compressed=True)
    chunk = struct.unpack_from("<I", data, 96)[0] + 8  # after the chunk table's offset
    struct.pack_into("<I", data, chunk + 30 + 4 + 4 * 4, 0xF0000000)  # first point, count, 4 layer sizes before
    (tmp_path / "a.laz").write_bytes(data)
    out = read_in_subprocess(tmp_path / "a.laz")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("points (24, 3)")


def test_laz_vlr_items_must_make_the_header_point_size(tmp_path: Path) -> None:
    """lazrs sizes its buffer from the VLR's items (up to 4 GB a point): 120,000 points with a damaged item
    size allocated 3.7 GB."""
    data = las_bytes("1.2", 1, compressed=True)
    struct.pack_into("<H", data, LAS12_HEADER + LAS_VLR_HEADER + 34 + 2, 60_000)  # first item's size (was 20)
    (tmp_path / "a.laz").write_bytes(data)
    with pytest.raises(PointCloudFormatError, match="LAZ VLR describes points of 60008 bytes; the header says 28"):
        read_cloud(tmp_path / "a.laz")


@pytest.mark.parametrize(
    ("version", "point_format", "item", "value", "message"),
    [
        ("1.2", 1, 1, (6, 8), "item 1 is a Point10 of 8 bytes; a Point10 item has 20"),  # GPS time typed as a point
        ("1.2", 3, 2, (7, 6), "item 2 is a GpsTime11 of 6 bytes; a GpsTime11 item has 8"),  # a colour typed as a time
        ("1.4", 7, 1, (13, 6), "item 1 is a Wavepacket14 of 6 bytes; a Wavepacket14 item has 29"),
    ],
)
def test_laz_item_of_another_size_than_its_type_is_refused_before_lazrs_panics(
    tmp_path: Path, version: str, point_format: int, item: int, value: tuple[int, int], message: str
) -> None:
    """An item shorter than its type made lazrs panic (pyo3's PanicException, its message printed on stderr by
    Rust's panic hook); each item of a fixed size must have that size, as LASzip requires."""
    data = las_bytes(version, point_format, compressed=True)
    header = LAS12_HEADER if version == "1.2" else LAS14_HEADER
    struct.pack_into("<HH", data, header + LAS_VLR_HEADER + 34 + 6 * item, *value)
    (tmp_path / "a.laz").write_bytes(data)
    with pytest.raises(PointCloudFormatError, match=re.escape(message)):
        read_cloud(tmp_path / "a.laz")


def test_a_laz_item_of_the_wrong_size_is_a_400_and_no_rust_panic_on_the_servers_stderr(server, client) -> None:
    """The GPS-time item typed as a point, uploaded: a 400 before as after, but lazrs's panic was printed on the
    server's stderr by Rust's panic hook (``thread '<unnamed>' panicked at ...``), which reads as a crash in an
    operator's logs."""
    data = las_bytes("1.2", 1, compressed=True, n=64)
    struct.pack_into("<H", data, LAS12_HEADER + LAS_VLR_HEADER + 34 + 6, 6)  # second item's type: 7 -> 6
    target = io.BytesIO()
    np.save(target, cloud(64))
    files = {"source": ("bad.laz", bytes(data)), "target": ("t.npy", target.getvalue())}
    response = client.post("/v1/register", files=files, data={"model": MODEL, "rotation_search": "false"})
    log = server.log_path.read_text(errors="replace")  # the server subprocess's stdout and stderr
    assert "panicked" not in log and "RUST_BACKTRACE" not in log, log[-2000:]
    assert_error(response, 400, "source (bad.laz)", "item 1 is a Point10 of 8 bytes", "damaged")


def set_point_count(data: bytearray, version: str, count: int) -> None:
    """The header's count of points: the legacy 32-bit one (0 in LAS 1.4's point formats 6-10) and LAS 1.4's 64-bit
    one."""
    struct.pack_into("<I", data, 107, count if version != "1.4" or data[104] & 0x3F < 6 else 0)
    if version == "1.4":
        struct.pack_into("<Q", data, 247, count)


LAS_FORMATS = [(version, point_format) for version in ("1.2", "1.3", "1.4") for point_format in range(4)] + [
    ("1.4", point_format) for point_format in (6, 7, 8)
]


@pytest.mark.parametrize(("version", "point_format"), LAS_FORMATS, ids=lambda value: str(value))
@pytest.mark.parametrize("compressed", [False, True], ids=["las", "laz"])
def test_a_header_count_its_data_does_not_hold_is_refused(version: str, point_format: int, compressed: bool) -> None:
    """24 points under a header claiming 25 read a made-up 25th point from a LAZ file of point format 0, 2 or 3 (the
    chunk table's bytes decoded as a point); a header claiming fewer read that many from LAS and LAZ alike, the rest
    of the points left unread. Each count is refused now, naming what the header declares."""
    data = las_bytes(version, point_format, compressed)
    kind = "LAZ" if compressed else "LAS"
    for declared in (25, 23, 26, 1, 1000):
        set_point_count(data, version, declared)
        with pytest.raises(PointCloudFormatError, match=f"^a.{kind.lower()}: {kind} header declares {declared} points"):
            read_cloud(bytes(data), f"a.{kind.lower()}")


def test_a_laz_count_beyond_its_chunks_is_refused_before_any_point_is_decompressed(tmp_path: Path) -> None:
    """The chunk table (chunks of 50,000 points but the last) bounds the count: 50,001 points claimed as 50,000 were
    read without the last chunk, and as 100,001 decompressed 50,001 points before lazrs ran out of data."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(1).normal(size=(50_001, 3)).T
    las.write(tmp_path / "a.laz", do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    data = bytearray((tmp_path / "a.laz").read_bytes())
    for declared in (50_000, 100_001):
        set_point_count(data, "1.2", declared)
        (tmp_path / "a.laz").write_bytes(data)

        def read(declared: int = declared) -> None:
            with pytest.raises(
                PointCloudFormatError,
                match=f"declares {declared} points; its 2 chunks of 50000 points hold 50001 to 100000",
            ):
                read_cloud(tmp_path / "a.laz")

        assert peak_bytes(read) < 1 << 20  # nothing decompressed: 50,000 points are 1.4 MB


@pytest.mark.parametrize("points", [1, 50_000, 50_001])
@pytest.mark.parametrize("version_format", [("1.2", 1), ("1.3", 3), ("1.4", 3)], ids=lambda value: str(value))
def test_laz_files_ending_at_a_chunk_edge_read_as_laspy_reads_them(tmp_path: Path, points: int, version_format) -> None:
    """The checks of the count against the data pass LAZ files of a full last chunk and of a last chunk of one point
    (its first point stored raw, then the decoder's first bytes)."""
    version, point_format = version_format
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales, header.offsets = [0.001] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(points).normal(scale=100.0, size=(points, 3)).T
    las.gps_time = np.random.default_rng(0).uniform(0, 1e5, points)
    las.write(tmp_path / "a.laz", do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    back = laspy.read(tmp_path / "a.laz")
    np.testing.assert_array_equal(
        read_cloud(tmp_path / "a.laz"), np.stack([np.asarray(back.x), np.asarray(back.y), np.asarray(back.z)], axis=1)
    )


@pytest.mark.parametrize("compressed", [False, True], ids=["las", "laz"])
def test_las14_points_before_an_evlr_are_counted_to_the_evlr(tmp_path: Path, compressed: bool) -> None:
    """An EVLR follows the points of a LAS 1.4 file: a header claiming one point more read the EVLR's first bytes as a
    made-up point. The file as written reads."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [2.0**-10] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud().astype(np.float64).T
    las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("mfgnet", 1, "padding", bytes(200))])
    out = io.BytesIO()
    las.write(out, do_compress=compressed)
    data = bytearray(out.getvalue())
    np.testing.assert_array_equal(read_cloud(bytes(data), "a.las"), on_grid(cloud()))
    set_point_count(data, "1.4", 25)
    with pytest.raises(PointCloudFormatError, match="header declares 25 points"):
        read_cloud(bytes(data), "a.las")


def test_a_laz_header_claiming_a_point_more_is_a_400_naming_the_count(client) -> None:
    data = las_bytes("1.2", 3, compressed=True, n=64)
    set_point_count(data, "1.2", 65)
    target = io.BytesIO()
    np.save(target, cloud(64))
    files = {"source": ("scan.laz", bytes(data)), "target": ("t.npy", target.getvalue())}
    response = client.post("/v1/register", files=files, data={"model": MODEL, "rotation_search": "false"})
    assert_error(response, 400, "source (scan.laz)", "LAZ header declares 65 points")


def test_a_laz_header_claiming_a_point_more_is_a_usage_error_of_register(tmp_path: Path, model_dir: Path) -> None:
    data = las_bytes("1.2", 3, compressed=True, n=64)
    set_point_count(data, "1.2", 65)
    (tmp_path / "scan.laz").write_bytes(data)
    np.save(tmp_path / "t.npy", cloud(64))
    result = CliRunner().invoke(
        app, ["register", str(tmp_path / "scan.laz"), str(tmp_path / "t.npy"), "--model-dir", str(model_dir)]
    )
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    assert "scan.laz: LAZ header declares 65 points" in " ".join(result.stderr.split())


# --- NPY / NPZ ---------------------------------------------------------------------------------------------------


def npy_bytes(header: str, body: bytes = bytes(48)) -> bytes:
    text = header.encode("latin1") + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + body


@pytest.mark.parametrize(
    "header",
    [
        "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 3, }",  # tokenize.TokenError
        "{[]: 1}",  # TypeError: unhashable
        "{'descr': '<f4', 'fortran_order': False, 'shape': (4, 3), 1: 1}",  # TypeError: keys sorted for the message
        "{'descr': '<f4', 'fortran_order': False, 'shape': (True, 3)}",  # a bool passes numpy's check of the shape
    ],
    ids=["unclosed", "list_key", "int_key", "bool_dim"],
)
def test_npy_unreadable_header_is_a_format_error(tmp_path: Path, header: str) -> None:
    (tmp_path / "a.npy").write_bytes(npy_bytes(header))
    with pytest.raises(PointCloudFormatError, match=r"not a valid \.npy file"):
        read_cloud(tmp_path / "a.npy")


def test_npy_header_length_beyond_numpys_limit_is_refused_before_reading(tmp_path: Path) -> None:
    """A version 2.0 header's length (4 bytes) of 4 GiB: numpy read that much before checking its 10,000-byte limit."""
    (tmp_path / "a.npy").write_bytes(b"\x93NUMPY\x02\x00" + struct.pack("<I", 0xFFFFFFFF) + b"{}")

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match="a header of 4294967295 bytes"):
            read_cloud(tmp_path / "a.npy")

    assert peak_bytes(read) < 64 << 20


def in_container(npy: bytes, container: str) -> bytes:
    """``npy`` as it is (``"npy"``) or as the member ``points.npy`` of an ``.npz`` archive (``"npz"``)."""
    if container == "npy":
        return npy
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        archive.writestr("points.npy", npy)
    return out.getvalue()


@pytest.mark.parametrize(
    "shape",
    [
        (2**62, 4),  # numpy's product of the shape wrapped to 0: ValueError from reshape
        (1, 2**63 - 1),  # OverflowError
        (5, 10**9),  # 5 rows: 40 GB allocated (MemoryError)
    ],
    ids=["wraps", "overflows", "wide"],
)
@pytest.mark.parametrize("container", ["npy", "npz"])
def test_npy_shape_beyond_the_file_is_refused_before_reading(tmp_path: Path, shape: tuple, container: str) -> None:
    data = npy_bytes(f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}")
    (tmp_path / f"a.{container}").write_bytes(in_container(data, container))
    with pytest.raises(PointCloudFormatError, match=r"truncated \.npy file: shape .* needs"):
        read_cloud(tmp_path / f"a.{container}")  # no max_points (the CLI): 2**62 rows are not refused as too many


@pytest.mark.parametrize("shape", [(0, 2**63), (0, 2**62), (1, 0, 2**63)], ids=["beyond_intp", "too_big", "three_dims"])
@pytest.mark.parametrize("container", ["npy", "npz"])
def test_npy_empty_shape_beyond_any_array_is_a_format_error(tmp_path: Path, shape: tuple, container: str) -> None:
    """A shape with a zero holds no data, so it passes the check against the file, but numpy cannot make an array of
    its other dimensions (its reshape raised outside the reader's errors: a 500)."""
    data = npy_bytes(f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}", body=b"")
    (tmp_path / f"a.{container}").write_bytes(in_container(data, container))
    with pytest.raises(PointCloudFormatError, match=r"not a valid \.npy file \(shape .* beyond any array's size"):
        read_cloud(tmp_path / f"a.{container}")


@pytest.mark.parametrize(
    "header",
    [
        "{'descr': '<f8', 'fortran_order': False, 'shape': (0, 268435456), }",
        "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 0, 536870912), }",
    ],
)
def test_npy_of_no_rows_however_wide_is_the_empty_cloud(tmp_path: Path, header: str) -> None:
    """Rows of 2 GiB are no numpy dtype: the block reader's dtype raised (a 500) where the cloud is empty."""
    (tmp_path / "a.npy").write_bytes(npy_bytes(header, body=b""))
    with pytest.raises(InvalidPointsError, match="empty"):
        read_cloud(tmp_path / "a.npy")


@pytest.mark.parametrize("shapes", [((2,), (), ()), ((0,), (0,), (0,))], ids=["x_pair", "empty_fields"])
def test_npy_structured_fields_must_be_single_numbers(tmp_path: Path, shapes: tuple) -> None:
    """Array fields raised numpy's broadcast ValueError, or ZeroDivisionError for a record of 0 bytes."""
    fields = [(axis, "<f4", shape) for axis, shape in zip("xyz", shapes, strict=True)]
    np.save(tmp_path / "a.npy", np.zeros(5, dtype=fields))
    for source in (tmp_path / "a.npy", (tmp_path / "a.npy").read_bytes()):
        with pytest.raises(InvalidPointsError, match="x, y and z must be single numbers"):
            read_cloud(source)


def npz_member_bytes(compress: int) -> bytearray:
    array = io.BytesIO()
    np.save(array, cloud())
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compress) as archive:
        archive.writestr("points.npy", array.getvalue())
    return bytearray(out.getvalue())


def corrupt_npz(case: str) -> bytes:
    data = npz_member_bytes(zipfile.ZIP_DEFLATED if case == "bad_deflate" else zipfile.ZIP_STORED)
    central = data.rindex(b"PK\x01\x02")
    if case == "bad_deflate":  # the first block of the member's deflate stream of the reserved type 3
        name, extra = struct.unpack_from("<HH", data, 26)
        data[30 + name + extra] = 0xFF
    elif case == "unknown_method":  # NotImplementedError
        struct.pack_into("<H", data, 8, 99)
        struct.pack_into("<H", data, central + 10, 99)
    elif case == "encrypted":  # RuntimeError: password required
        struct.pack_into("<H", data, 6, 1)
        struct.pack_into("<H", data, central + 8, 1)
    else:  # the central directory's offset beyond the archive: ValueError, negative seek
        struct.pack_into("<I", data, data.rindex(b"PK\x05\x06") + 16, 0xFFFFFFFF)
    return bytes(data)


@pytest.mark.parametrize("case", ["bad_deflate", "unknown_method", "encrypted", "directory_offset"])
def test_npz_corrupt_or_unsupported_member_is_a_format_error(tmp_path: Path, case: str) -> None:
    (tmp_path / "a.npz").write_bytes(corrupt_npz(case))
    with pytest.raises(PointCloudFormatError, match=r"\.npz archive") as caught:
        read_cloud((tmp_path / "a.npz").read_bytes(), name="a.npz")
    assert str(caught.value).startswith("a.npz: ")


def test_npz_of_wide_rows_is_refused_before_decompressing(tmp_path: Path) -> None:
    """An archive under 1 MiB of zeros shaped (5, 4,000,000), 160 MB decompressed: the point limit bounds rows only."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        member = io.BytesIO()
        np.save(member, np.zeros((5, 4_000_000)))
        archive.writestr("points.npy", member.getvalue())
    (tmp_path / "a.npz").write_bytes(out.getvalue())
    assert (tmp_path / "a.npz").stat().st_size < 1 << 20

    def read() -> None:
        with pytest.raises(InvalidPointsError, match="at most 128 bytes per point"):
            read_cloud(tmp_path / "a.npz", max_points=LIMIT)

    assert peak_bytes(read) < 8 << 20


def test_rows_up_to_16_float64_columns_are_read(tmp_path: Path) -> None:
    table = np.random.default_rng(1).normal(size=(50, 16))  # x, y, z and 13 more columns
    np.savez_compressed(tmp_path / "a.npz", points=table)
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.npz"), table[:, :3])


@pytest.mark.parametrize("container", ["npy", "npz"])
@pytest.mark.parametrize("order", ["C", "F"])
def test_wide_rows_hold_only_x_y_z_while_read(tmp_path: Path, container: str, order: str) -> None:
    """500,000 rows of 16 float64 columns (64 MB): an .npz member was read whole, then joined (two copies), and every
    array whole before its first three columns were taken; now only the [N, 3] output and one block are held."""
    table = (
        np.asfortranarray(np.random.default_rng(2).normal(size=(500_000, 16)))
        if order == "F"
        else np.random.default_rng(2).normal(size=(500_000, 16))
    )
    if container == "npz":
        np.savez(tmp_path / "a.npz", points=table)
    else:
        np.save(tmp_path / "a.npy", table)
    points = {}

    def read() -> None:
        points["xyz"] = read_cloud(tmp_path / f"a.{container}")

    assert peak_bytes(read) < 24 << 20  # the output is 12 MB
    np.testing.assert_array_equal(points["xyz"], table[:, :3])


def test_laz14_xyz_layer_sizes_beyond_the_chunk_are_refused(tmp_path: Path) -> None:
    """A LAZ 1.4 chunk declares its x/y and z layers' sizes: lazrs allocated and zero-filled a damaged 4 GB one
    (seconds and gigabytes of memory) before finding the file short."""
    data = las_bytes("1.4", 6, compressed=True)
    chunk = struct.unpack_from("<I", data, 96)[0] + 8  # after the chunk table's offset
    struct.pack_into("<I", data, chunk + 30 + 4, 0xF0000000)  # the first point, the count, then the x/y layer
    (tmp_path / "a.laz").write_bytes(data)
    out = read_in_subprocess(tmp_path / "a.laz", memory_mib=1000)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("error a.laz: LAZ chunk 0 declares x, y and z layers of"), out.stdout


@pytest.mark.parametrize("point_format", [6, 7, 8])
def test_laz14_of_several_chunks_reads_as_laspy_reads_it(tmp_path: Path, point_format: int) -> None:
    points = np.random.default_rng(point_format).normal(scale=100.0, size=(120_000, 3))
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales, header.offsets = [0.001] * 3, [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.write(tmp_path / "a.laz", do_compress=True, laz_backend=laspy.LazBackend.Lazrs)  # chunks of 50,000 points
    back = laspy.read(tmp_path / "a.laz")
    np.testing.assert_array_equal(
        read_cloud(tmp_path / "a.laz"), np.stack([np.asarray(back.x), np.asarray(back.y), np.asarray(back.z)], axis=1)
    )


def test_laz14_xyz_layer_sizes_are_checked_under_a_chunk_table_of_no_chunks(tmp_path: Path) -> None:
    """Found by fuzzing (a LAZ 1.4 file with 411 of its own bytes inserted in its first chunk, so that its chunk table's
    offset pointed at a table of no chunks): the x/y and z layer sizes went unchecked, and lazrs, which reads on
    without chunk entries, allocated and zero-filled a 4 GB z layer (4.2 GB of RSS from a 1,352-byte file; an abort
    under a memory limit)."""
    data = las_bytes("1.4", 6, compressed=True)
    start = struct.unpack_from("<I", data, 96)[0]  # the points: the chunk table's offset, then the first chunk
    struct.pack_into("<q", data, start, len(data))  # a table of version 0 and no chunks, appended
    data += bytes(8)
    struct.pack_into("<I", data, start + 8 + 30 + 4 + 4, 0xF0000000)  # the first point, the count, x/y's size, z's
    (tmp_path / "a.laz").write_bytes(data)
    out = read_in_subprocess(tmp_path / "a.laz", memory_mib=1000)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("error a.laz: LAZ chunk 0 declares x, y and z layers of"), out.stdout


@pytest.mark.parametrize(("before", "bad", "message"), [
    ("", "1 x 3", "could not convert 'x' to a number at line 1001, column 2"),
    ("x y z\n# a note\n\n", "1 x 3", "could not convert 'x' to a number at line 1004, column 2"),
    ("", "1 2", "line 1001 has 2 columns, fewer than the x, y and z columns need"),
    ("x y z\n\n", "1 2", "line 1003 has 2 columns, fewer than the x, y and z columns need"),
])
def test_a_bad_text_row_is_named_by_its_line_in_the_file(tmp_path: Path, before: str, bad: str, message: str) -> None:
    """numpy named a value it could not convert by its row of data from 0 and a short row by its row from 1, both
    without the header, comments and blank lines: the error names the line as an editor numbers it."""
    rows = ["1 2 3"] * 1200
    rows[1000] = bad
    (tmp_path / "a.xyz").write_text(before + "\n".join(rows) + "\n")
    with pytest.raises(InvalidPointsError) as caught:
        read_cloud(tmp_path / "a.xyz")
    assert message in str(caught.value)
    lines = (tmp_path / "a.xyz").read_text().splitlines()
    line = int(message.split("line ")[1].split()[0].rstrip(","))
    assert lines[line - 1] == bad  # the named line is the bad one


def test_a_decimal_comma_is_named_in_the_error(tmp_path: Path) -> None:
    """A semicolon CSV as a spreadsheet of a comma-decimal locale saves it: the error says what the numbers lack."""
    (tmp_path / "eu.csv").write_text("x;y;z\n0,125;-1,5;2,0\n1,0;2,0;3,0\n")
    with pytest.raises(InvalidPointsError, match=r"'0,125'.*a decimal comma\? numbers need a decimal point"):
        read_cloud(tmp_path / "eu.csv")
    (tmp_path / "word.csv").write_text("x;y;z\nabc;1;2\n")
    with pytest.raises(InvalidPointsError) as word:
        read_cloud(tmp_path / "word.csv")
    assert "decimal comma" not in str(word.value)


def test_an_npz_directory_listing_too_many_members_is_refused_before_zipfile_parses_it(tmp_path):
    """zipfile makes an object of every entry: an archive listing 1,000,000 members took 494 MiB to open."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        array = io.BytesIO()
        np.save(array, cloud())
        archive.writestr("points.npy", array.getvalue())
        for k in range(20_000):  # 20,000 x 56-byte entries: a directory over MAX_DIRECTORY_BYTES
            archive.writestr(f"member_{k:08d}_padding_padding.npy", b"")
    with pytest.raises(PointCloudFormatError, match="its directory of members takes") as caught:
        read_cloud(buffer.getvalue(), "a.npz", max_points=LIMIT)
    assert caught.value.status == 400


def test_an_npz_error_lists_at_most_20_of_its_arrays():
    buffer = io.BytesIO()
    np.savez(buffer, **{f"a{k}": cloud() for k in range(50)})
    with pytest.raises(PointCloudFormatError) as caught:
        read_cloud(buffer.getvalue(), "a.npz", max_points=LIMIT)
    assert "and 30 more" in str(caught.value) and "a49" not in str(caught.value)


@pytest.mark.parametrize("text", [
    b'"x","y","z","name"\n1.0,2.0,3.0,"bolt #1"\n4.0,5.0,6.0,"bolt #2"\n',  # pandas QUOTE_NONNUMERIC: '#' quoted
    b'x,y,z,label\n1,2,3,5" pipe\n4,5,6,b\n',  # an unquoted inch mark: a quote only opens a field
])
def test_legal_quotes_are_read_as_numpy_reads_them(text):
    np.testing.assert_array_equal(read_cloud(text, "a.csv", max_points=LIMIT), [[1, 2, 3], [4, 5, 6]])


def test_quotes_in_comments_and_closed_quotes_across_reads_are_kept():
    rows = "".join(f'"{k}","{k + 1}","{k + 2}"\n' for k in range(200_000))  # quoted values, pieces cut mid-line
    text = ('# a comment with an odd " quote\nx,y,z\n' + rows).encode()
    np.testing.assert_array_equal(read_cloud(text, "a.csv", max_points=LIMIT)[-1], [199_999, 200_000, 200_001])
    assert len(text) > checks.COUNT_BLOCK_BYTES


def test_wide_ascii_ply_vertices_are_parsed_a_bounded_number_of_values_at_a_time(monkeypatch):
    """Every property of a block is parsed as float64 before x, y, z are kept: a vertex of 2,000 properties is parsed in
    blocks of fewer rows."""
    from service.formats import ply as ply_reader

    names = ["x", "y", "z", *(f"p{k}" for k in range(2_000))]
    header = "ply\nformat ascii 1.0\nelement vertex 40\n" + "".join(f"property float {n}\n" for n in names)
    body = "".join(" ".join(["1", "2", "3", *["0"] * 2_000]) + "\n" for _ in range(40))
    calls, original = [], np.loadtxt

    def counted(rows, *args, **kwargs):
        calls.append(len(rows))
        return original(rows, *args, **kwargs)

    monkeypatch.setattr(ply_reader.np, "loadtxt", counted)
    monkeypatch.setattr(ply_reader, "ASCII_BLOCK_VALUES", 20_000)
    points = read_cloud((header + "end_header\n" + body).encode(), "a.ply", max_points=LIMIT)
    assert points.shape == (40, 3) and max(calls) <= 9  # 20,000 values // 2,003 properties


@pytest.mark.parametrize(("field", "value", "words"), [
    (131, struct.pack("<d", -0.001), "each scale must be a positive number"),
    (131, struct.pack("<d", 0.0), "each scale must be a positive number"),
    (139, struct.pack("<d", float("nan")), "each scale must be a positive number"),
    (155, struct.pack("<d", float("inf")), "each offset finite"),
])
def test_a_las_header_scale_or_offset_that_places_no_point_is_refused(field, value, words):
    """A negative scale read, then failed as a 500 when written moved; 0 put every point on the offset; NaN blamed
    the points."""
    data = bytearray(las_bytes("1.2", 0, False))
    data[field:field + 8] = value
    with pytest.raises(PointCloudFormatError, match=words) as caught:
        read_cloud(bytes(data), "a.las", max_points=LIMIT)
    assert caught.value.status == 400


def test_a_las_header_declaring_more_than_65535_vlrs_is_refused():
    data = bytearray(las_bytes("1.2", 0, False))
    data[100:104] = struct.pack("<I", 70_000)
    with pytest.raises(PointCloudFormatError, match="declares 70000 VLRs; at most 65535"):
        read_cloud(bytes(data), "a.las", max_points=LIMIT)


@pytest.mark.parametrize(("text", "name"), [
    (b"2\n0 0 0\n1 1 1\n\xc2\xb2\n2 2 2\n", "a.pts"),  # a superscript 2 as a later block's count
    (b"1\n1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n1 2 3 0.5\n"
     b"\xc2\xb2\n1\n", "a.ptx"),  # ... as a later scan's column count
])
def test_a_unicode_digit_as_a_leica_count_is_refused_not_a_500(text, name):
    with pytest.raises(PointCloudFormatError) as caught:
        read_cloud(text, name, max_points=LIMIT)
    assert caught.value.status == 400


def test_a_ptx_transform_with_its_translation_in_the_last_column_is_refused():
    """It was read without the translation: PTX puts it in the last row."""
    header = b"1\n1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
    column_major = b"1 0 0 100\n0 1 0 200\n0 0 1 300\n0 0 0 1\n"
    with pytest.raises(PointCloudFormatError, match="last column is"):
        read_cloud(header + column_major + b"1 2 3 0.5\n", "a.ptx", max_points=LIMIT)
    row_major = b"1 0 0 0\n0 1 0 0\n0 0 1 0\n100 200 300 1\n"
    np.testing.assert_allclose(read_cloud(header + row_major + b"1 2 3 0.5\n", "a.ptx", max_points=LIMIT),
                               [[101, 202, 303]])


def test_an_npz_whose_zip64_locator_names_several_disks_is_a_format_error():
    """zipfile raises BadZipFile reading its end record: the directory check let it out as a 500."""
    buffer = io.BytesIO()
    np.savez(buffer, points=cloud())
    good = buffer.getvalue()
    end = good.rfind(b"PK\x05\x06")
    multi_disk = good[:end] + struct.pack("<4sIQI", b"PK\x06\x07", 0, 0, 2) + good[end:]
    with pytest.raises(PointCloudFormatError) as caught:
        read_cloud(multi_disk, "a.npz", max_points=LIMIT)
    assert caught.value.status == 400
