"""Specification of ``service.pointcloud_io``: every format round-trips, bad files fail clearly."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from service.pointcloud_io import (
    SUFFIXES,
    PointCloudFormatError,
    lzf_decompress,
    parse_points,
    read_points,
    write_points,
)


def cloud(n: int = 50, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).normal(size=(n, 3)) * 10).astype(np.float32)


def lzf_compress(data: bytes) -> bytes:
    """A tiny greedy LZF compressor (literal runs and back-references, overlapping ones included)."""
    out, literals, last_seen = bytearray(), bytearray(), {}

    def flush() -> None:
        for k in range(0, len(literals), 32):
            chunk = literals[k : k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        literals.clear()

    i = 0
    while i < len(data):
        key = data[i : i + 3]
        ref = last_seen.get(key) if len(key) == 3 else None
        if len(key) == 3:
            last_seen[key] = i
        if ref is not None and i - ref - 1 < 8192:
            length = 3
            while i + length < len(data) and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            distance, code = i - ref - 1, length - 2
            if code < 7:
                out.append((code << 5) | (distance >> 8))
            else:
                out += bytes([(7 << 5) | (distance >> 8), code - 7])
            out.append(distance & 0xFF)
            i += length
        else:
            literals.append(data[i])
            i += 1
    flush()
    return bytes(out)


def lzf_literals_only(data: bytes) -> bytes:
    """Valid LZF that only uses literal runs (no compression at all)."""
    return b"".join(bytes([len(data[k : k + 32]) - 1]) + data[k : k + 32] for k in range(0, len(data), 32))


# --------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix", [*SUFFIXES, ".PLY", ".Npz"])
def test_written_points_read_back_exactly(tmp_path: Path, suffix: str) -> None:
    points = cloud()
    path = tmp_path / f"cloud{suffix}"
    write_points(path, points)
    assert path.exists()
    back = read_points(path)
    assert back.dtype == np.float32 and back.shape == (50, 3)
    np.testing.assert_array_equal(back, points)


def test_float64_points_are_stored_as_float32(tmp_path: Path) -> None:
    points = cloud().astype(np.float64) / 3
    write_points(tmp_path / "a.ply", points)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), points.astype(np.float32))


def test_parse_points_reads_bytes(tmp_path: Path) -> None:
    write_points(tmp_path / "a.pcd", cloud())
    np.testing.assert_array_equal(parse_points((tmp_path / "a.pcd").read_bytes(), ".pcd"), cloud())


# ----------------------------------------------------------------------------------------------- PLY

PLY_XYZ = np.array([[1.0, 2.0, 3.0], [-4.5, 5.25, 6.0], [7.0, -8.0, 9.5]], dtype=np.float32)


def test_ply_ascii_with_extra_properties_and_faces(tmp_path: Path) -> None:
    text = (
        "ply\nformat ascii 1.0\ncomment hand made\nobj_info test\nelement vertex 3\n"
        "property float y\nproperty uchar red\nproperty float x\nproperty double z\nproperty float nx\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        + "".join(f"{y} 255 {x} {z} 0.5\n" for x, y, z in PLY_XYZ)
        + "3 0 1 2\n"
    )
    (tmp_path / "a.ply").write_text(text)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), PLY_XYZ)


def test_ply_ascii_with_a_list_element_before_the_vertices_and_crlf(tmp_path: Path) -> None:
    text = (
        "ply\r\nformat ascii 1.0\r\nelement face 2\r\nproperty list uchar int vertex_indices\r\n"
        "element vertex 3\r\nproperty float x\r\nproperty float y\r\nproperty float z\r\nend_header\r\n"
        "3 0 1 2\r\n4 0 1 2 0\r\n" + "".join(f"{x} {y} {z}\r\n" for x, y, z in PLY_XYZ)
    )
    (tmp_path / "a.ply").write_bytes(text.encode())
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), PLY_XYZ)


def test_ply_binary_big_endian_doubles_after_another_element(tmp_path: Path) -> None:
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement camera 2\nproperty float fx\nproperty short id\n"
        b"element vertex 3\nproperty double x\nproperty double y\nproperty double z\n"
        b"property uchar red\nproperty uchar green\nend_header\n"
    )
    camera = b"".join(struct.pack(">fh", 500.0, k) for k in range(2))
    vertices = b"".join(struct.pack(">dddBB", *p, 10, 20) for p in PLY_XYZ.astype(float))
    (tmp_path / "a.ply").write_bytes(header + camera + vertices)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), PLY_XYZ)


def test_ply_binary_little_endian_with_list_properties(tmp_path: Path) -> None:
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"element vertex 3\nproperty float x\nproperty list uint8 float extra\nproperty float y\n"
        b"property float z\nend_header\n"
    )
    face = struct.pack("<B3i", 3, 0, 1, 2)
    vertices = b"".join(
        struct.pack("<fB", p[0], k) + struct.pack(f"<{k}f", *range(k)) + struct.pack("<ff", p[1], p[2])
        for k, p in enumerate(PLY_XYZ.astype(float))
    )
    (tmp_path / "a.ply").write_bytes(header + face + vertices)
    np.testing.assert_array_equal(read_points(tmp_path / "a.ply"), PLY_XYZ)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"not a ply file\n", "magic"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
            "lacks",
        ),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vi\nend_header\n", "no vertex"),
        (b"ply\nformat weird 1.0\nelement vertex 1\nend_header\n", "format"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "not terminated"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + b"\x00" * 20,
            "too short",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n1 2 3\n",
            "ends inside",
        ),
    ],
)
def test_ply_corrupt_files_are_refused(tmp_path: Path, content: bytes, message: str) -> None:
    (tmp_path / "a.ply").write_bytes(content)
    with pytest.raises(PointCloudFormatError, match=message):
        read_points(tmp_path / "a.ply")


# ----------------------------------------------------------------------------------------------- PCD

PCD_FIELDS = "FIELDS j x y z rgb\nSIZE 4 4 4 4 4\nTYPE F F F F U\nCOUNT 2 1 1 1 1\n"


def pcd_header(n: int, data: str, fields: str = PCD_FIELDS) -> bytes:
    return (
        f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n{fields}WIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode()


def test_pcd_ascii_with_multi_count_fields(tmp_path: Path) -> None:
    points = cloud(7)
    body = "".join(f"0.5 0.25 {x!r} {y!r} {z!r} 4278190080\n" for x, y, z in points.tolist())
    (tmp_path / "a.pcd").write_bytes(pcd_header(7, "ascii") + body.encode())
    np.testing.assert_array_equal(read_points(tmp_path / "a.pcd"), points)


def test_pcd_binary_with_mixed_types(tmp_path: Path) -> None:
    points = cloud(9)
    fields = "FIELDS intensity x y z ring\nSIZE 1 8 8 8 2\nTYPE U F F F I\nCOUNT 1 1 1 1 1\n"
    body = b"".join(struct.pack("<Bdddh", 7, *p, -3) for p in points.astype(float))
    (tmp_path / "a.pcd").write_bytes(pcd_header(9, "binary", fields) + body)
    np.testing.assert_array_equal(read_points(tmp_path / "a.pcd"), points)


@pytest.mark.parametrize("compress", [lzf_literals_only, lzf_compress])
def test_pcd_binary_compressed(tmp_path: Path, compress) -> None:
    n = 40
    points = cloud(n)
    points[:, 2] = 1.5  # constant column: long (overlapping) back-references
    raw = (
        np.zeros((n, 2), "<f4").tobytes()  # field-major: all j, then all x, y, z, rgb
        + b"".join(points[:, k].astype("<f4").tobytes() for k in range(3))
        + np.full(n, 0xFF00FF, "<u4").tobytes()
    )
    compressed = compress(raw)
    assert lzf_decompress(compressed, len(raw)) == raw
    body = struct.pack("<II", len(compressed), len(raw)) + compressed
    (tmp_path / "a.pcd").write_bytes(pcd_header(n, "binary_compressed") + body)
    np.testing.assert_array_equal(read_points(tmp_path / "a.pcd"), points)


def test_lzf_decompresses_an_overlapping_back_reference() -> None:
    # literal "a", then copy 9 bytes from 1 byte back
    assert lzf_decompress(bytes([0x00, 0x61, 0xE0, 0x00, 0x00]), 10) == b"a" * 10
    assert lzf_decompress(bytes([0x01, 0x61, 0x62, 0x40, 0x01]), 6) == b"ababab"


@pytest.mark.parametrize(
    ("compressed", "size", "message"),
    [
        (bytes([0x05, 0x61]), 6, "literal run"),
        (bytes([0x00, 0x61, 0x20, 0x05]), 4, "before the start"),
        (bytes([0x00, 0x61, 0x20]), 4, "cut short"),
        (bytes([0x00, 0x61]), 2, "expected 2"),
        (bytes([0x00, 0x61, 0xE0, 0x00, 0x00]), 5, "beyond"),
    ],
)
def test_lzf_rejects_corrupt_data(compressed: bytes, size: int, message: str) -> None:
    with pytest.raises(PointCloudFormatError, match=message):
        lzf_decompress(compressed, size)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (pcd_header(3, "binary") + b"\x00" * 10, "expected"),
        (pcd_header(2, "ascii") + b"1 2 3 4 5 6\n", "values"),
        (pcd_header(1, "ascii", "FIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\n") + b"1 2\n", "lacks fields"),
        (pcd_header(1, "lzma") + b"", "DATA"),
        (pcd_header(2, "binary_compressed") + struct.pack("<II", 100, 48) + b"\x00" * 5, "cut short"),
        (b"VERSION 0.7\nFIELDS x y z\n", "not terminated"),
    ],
)
def test_pcd_corrupt_files_are_refused(tmp_path: Path, content: bytes, message: str) -> None:
    (tmp_path / "a.pcd").write_bytes(content)
    with pytest.raises(PointCloudFormatError, match=message):
        read_points(tmp_path / "a.pcd")


# ------------------------------------------------------------------------------------------ text


def test_csv_with_header_and_extra_columns(tmp_path: Path) -> None:
    (tmp_path / "a.csv").write_text("x,y,z,intensity\n1,2,3,0.5\n4, 5 ,6,0.1\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.csv"), [[1, 2, 3], [4, 5, 6]])


def test_xyz_with_tabs_comments_and_normals(tmp_path: Path) -> None:
    (tmp_path / "a.xyz").write_text("# scanner output\n1\t2\t3\t0 0 1\n\n-1e3 2.5 -0.125 0 1 0\n")
    np.testing.assert_array_equal(read_points(tmp_path / "a.xyz"), [[1, 2, 3], [-1000, 2.5, -0.125]])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2\n3 4\n", "column"),
        ("x y z\n1 2 3\n4 five 6\n", "corrupt"),
        ("", "empty"),
        ("x,y,z\n", "empty"),
        ("1 2 3\nnan 1 2\n", "NaN"),
        ("1 2 inf\n", "NaN/Inf"),
        ("1 2 1e39\n", "beyond float32"),
    ],
)
def test_text_errors(tmp_path: Path, text: str, message: str) -> None:
    (tmp_path / "a.txt").write_text(text)
    with pytest.raises(PointCloudFormatError, match=message):
        read_points(tmp_path / "a.txt")


# ------------------------------------------------------------------------------------------ numpy


@pytest.mark.parametrize(
    "array",
    [
        np.arange(12, dtype=np.float64).reshape(4, 3),
        np.arange(12, dtype=np.int32).reshape(4, 3),
        np.c_[np.arange(12.0).reshape(4, 3), np.ones((4, 3))],  # xyz + normals
    ],
)
def test_npy_numeric_arrays(tmp_path: Path, array: np.ndarray) -> None:
    np.save(tmp_path / "a.npy", array)
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), np.arange(12.0).reshape(4, 3))


def test_npy_structured_array_with_xyz_fields(tmp_path: Path) -> None:
    array = np.zeros(4, dtype=[("z", "f8"), ("x", "f4"), ("y", "f4"), ("rgb", "u4")])
    array["x"], array["y"], array["z"] = [0, 3, 6, 9], [1, 4, 7, 10], [2, 5, 8, 11]
    np.save(tmp_path / "a.npy", array)
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), np.arange(12.0).reshape(4, 3))


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.array([[1, 2, 3]], dtype=object), "object arrays"),
        (np.zeros((4, 2)), "3 columns"),
        (np.zeros(6), "3 columns"),
        (np.zeros((0, 3)), "empty"),
        (np.array([["a", "b", "c"]]), "numeric"),
    ],
)
def test_npy_errors(tmp_path: Path, array: np.ndarray, message: str) -> None:
    np.save(tmp_path / "a.npy", array, allow_pickle=True)
    with pytest.raises(PointCloudFormatError, match=message):
        read_points(tmp_path / "a.npy")


def test_npy_pickle_and_garbage_are_refused(tmp_path: Path) -> None:
    (tmp_path / "a.npy").write_bytes(b"\x80\x04garbage that looks like a pickle")
    with pytest.raises(PointCloudFormatError, match="pickled"):
        read_points(tmp_path / "a.npy")
    (tmp_path / "b.npy").write_bytes(b"\x93NUMPY\x01\x00{'descr': broken")
    with pytest.raises(PointCloudFormatError, match="corrupt"):
        read_points(tmp_path / "b.npy")


def test_npz_prefers_the_points_key(tmp_path: Path) -> None:
    np.savez(tmp_path / "a.npz", colors=np.zeros((4, 3)), points=np.ones((4, 3)))
    np.testing.assert_array_equal(read_points(tmp_path / "a.npz"), np.ones((4, 3)))


def test_npz_uses_its_only_array(tmp_path: Path) -> None:
    np.savez(tmp_path / "a.npz", cloud=np.ones((4, 3)))
    np.testing.assert_array_equal(read_points(tmp_path / "a.npz"), np.ones((4, 3)))


def test_npz_errors(tmp_path: Path) -> None:
    np.savez(tmp_path / "a.npz", a=np.ones((4, 3)), b=np.ones((4, 3)))
    with pytest.raises(PointCloudFormatError, match="several arrays"):
        read_points(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", points=np.array([[1, 2, 3]], dtype=object))
    with pytest.raises(PointCloudFormatError, match="object arrays"):
        read_points(tmp_path / "b.npz")
    np.save(tmp_path / "c.npy", np.ones((4, 3)))
    (tmp_path / "c.npz").write_bytes((tmp_path / "c.npy").read_bytes())
    with pytest.raises(PointCloudFormatError, match=r"not an \.npz"):
        read_points(tmp_path / "c.npz")


# ------------------------------------------------------------------------------------------ general


def test_unknown_extension_is_refused_before_reading(tmp_path: Path) -> None:
    with pytest.raises(PointCloudFormatError, match=r"unknown extension '\.obj'"):
        read_points(tmp_path / "missing.obj")
    with pytest.raises(PointCloudFormatError, match="unknown extension"):
        write_points(tmp_path / "a.las", cloud())


def test_missing_file_is_an_os_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_points(tmp_path / "missing.ply")


def test_empty_ply_is_refused(tmp_path: Path) -> None:
    (tmp_path / "a.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 0\n"
        b"property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with pytest.raises(PointCloudFormatError, match="empty"):
        read_points(tmp_path / "a.ply")


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.array([[0.0, np.nan, 1.0]]), "NaN"),
        (np.zeros((3, 2)), r"\(N, 3\)"),
        (np.zeros((0, 3)), "empty"),
    ],
)
def test_write_refuses_bad_points(tmp_path: Path, points: np.ndarray, message: str) -> None:
    with pytest.raises(PointCloudFormatError, match=message):
        write_points(tmp_path / "a.ply", points)
    assert not (tmp_path / "a.ply").exists()
