"""LAZ of pointwise compression (the LAZ VLR's compressor 1: no chunks, no chunk table, the points one arithmetic-coded
stream from the offset to the points, as LASzip wrote before chunking), made here from real ``lazrs`` output: the
points compressed as one chunk (a chunk's bytes are the stream pointwise compression writes), the chunk table's offset
before them and the table after them left out, the VLR's compressor set to 1 (its chunk size kept: 50,000, what
LASzip writes). ``laspy`` with ``lazrs`` reads these files; ``service.formats.las`` reads them as it does, checks the
header's count against where the stream ends, and refuses, naming them, those ``lazrs`` cannot read."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import laspy
import lazrs
import numpy as np
import pytest
from api_server import MODEL, assert_error

from service.formats import PointCloudFormatError
from service.pointcloud_io import read_points

COMPRESSOR, CHUNK_SIZE = 0, 12  # the LAZ VLR record's compressor (u16) and chunk size (u32)


def laz_vlr_record(data: bytes | bytearray) -> int:
    """Where the LAZ VLR's record starts in the LAS file ``data`` (a LAS 1.2 or 1.4 header, its VLRs after it)."""
    at, count = struct.unpack_from("<H", data, 94)[0], struct.unpack_from("<I", data, 100)[0]
    for _ in range(count):
        user, record, length = data[at + 2 : at + 18].rstrip(b"\0"), *struct.unpack_from("<HH", data, at + 18)
        if (user, record) == (b"laszip encoded", 22204):
            return at + 54
        at += 54 + length
    raise AssertionError("no LAZ VLR")


def pointwise(xyz: np.ndarray, version: str = "1.2", point_format: int = 3) -> bytes:
    """A pointwise LAZ file of ``xyz [n, 3]`` (millimetre scale, intensities too)."""
    las = laspy.create(point_format=point_format, file_version=version)
    las.header.scales, las.header.offsets = [0.001] * 3, [0.0] * 3
    las.x, las.y, las.z = xyz.T
    las.intensity = np.arange(len(xyz)) % 65536
    plain, chunked = io.BytesIO(), io.BytesIO()
    las.write(plain)
    las.write(chunked, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    start = struct.unpack_from("<I", plain.getvalue(), 96)[0]
    records = plain.getvalue()[start : start + len(xyz) * las.header.point_format.size]
    data = bytearray(chunked.getvalue())
    offset, at = struct.unpack_from("<I", data, 96)[0], laz_vlr_record(data)
    record = bytearray(data[at : at + 34 + 6 * struct.unpack_from("<H", data, at + 32)[0]])
    struct.pack_into("<I", record, CHUNK_SIZE, 2**32 - 2)  # every point in one chunk
    stream = io.BytesIO()
    compressor = lazrs.LasZipCompressor(stream, lazrs.LazVlr(bytes(record)))
    compressor.compress_many(records)
    compressor.done()  # the table's offset, the chunk, the table
    compressed = stream.getvalue()
    struct.pack_into("<H", data, at + COMPRESSOR, 1)
    assert struct.unpack_from("<I", data, at + CHUNK_SIZE)[0] == 50_000
    return bytes(data[:offset]) + compressed[8 : struct.unpack_from("<q", compressed, 0)[0]]


def with_count(data: bytes, count: int) -> bytes:
    """``data`` (LAS 1.2) with the header's point count ``count``."""
    changed = bytearray(data)
    struct.pack_into("<I", changed, 107, count)
    return bytes(changed)


def with_chunk_size(data: bytes, size: int) -> bytes:
    changed = bytearray(data)
    struct.pack_into("<I", changed, laz_vlr_record(changed) + CHUNK_SIZE, size)
    return bytes(changed)


def laspy_xyz(path: Path) -> np.ndarray:
    las = laspy.read(path, laz_backend=laspy.LazBackend.Lazrs)
    return np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)


XYZ = np.random.default_rng(4).uniform(-50, 50, (60_000, 3))  # more points than the VLR's chunk size


@pytest.mark.parametrize("version", ["1.2", "1.4"])
def test_a_pointwise_file_reads_as_laspy_reads_it(tmp_path, version) -> None:
    (tmp_path / "scan.laz").write_bytes(pointwise(XYZ, version, 1))
    expected = laspy_xyz(tmp_path / "scan.laz")
    np.testing.assert_allclose(expected, XYZ, rtol=0, atol=5e-4)
    np.testing.assert_array_equal(read_points(tmp_path / "scan.laz"), expected)


def test_its_first_point_is_not_taken_for_a_chunk_tables_offset(tmp_path) -> None:
    """A pointwise file's first 8 bytes are its first point's, raw: x 0.1 and y 0 at a millimetre scale are the
    integers 100 and 0, which read as a chunk table's offset point at byte 100, inside the header. It was refused
    ("LAZ chunk table at byte 100 declares 3892322947 chunks"); laspy reads it."""
    xyz = XYZ[:1000].copy()
    xyz[0] = [0.1, 0.0, 1.0]
    (tmp_path / "origin.laz").write_bytes(pointwise(xyz))
    expected = laspy_xyz(tmp_path / "origin.laz")
    np.testing.assert_array_equal(read_points(tmp_path / "origin.laz"), expected)


def test_a_header_count_that_is_not_the_streams_is_refused(tmp_path) -> None:
    """Fewer points than the stream holds were read without a word (the rest left unread); more end the data early."""
    data = pointwise(XYZ[:5000])
    (tmp_path / "fewer.laz").write_bytes(with_count(data, 4999))
    (tmp_path / "more.laz").write_bytes(with_count(data, 5001))
    (tmp_path / "cut.laz").write_bytes(data[:-500])
    (tmp_path / "appended.laz").write_bytes(data + b"\0")
    for name, count in (("fewer.laz", 4999), ("appended.laz", 5000)):
        with pytest.raises(PointCloudFormatError, match=rf"declares {count} points; after them its pointwise stream "
                           r"\(no chunk table\) does not reach byte \d+, where the points must end: .* or bytes were "
                           "appended after the points"):
            read_points(tmp_path / name)
    for name, count in (("more.laz", 5001), ("cut.laz", 5000)):
        with pytest.raises(
            PointCloudFormatError,
            match=rf"declares {count} points; its compressed data \(pointwise, without a chunk table\) ends before",
        ):
            read_points(tmp_path / name)


@pytest.mark.parametrize("size", [0, 2**32 - 1])
def test_a_chunk_size_the_reader_takes_for_varying_chunks_is_refused_by_name(tmp_path, capfd, size) -> None:
    """lazrs takes these for chunks of varying size, which need a table, and panicked (Rust's hook printed it)."""
    (tmp_path / "varying.laz").write_bytes(with_chunk_size(pointwise(XYZ[:1000]), size))
    with pytest.raises(PointCloudFormatError, match=r"LAZ without a chunk table \(pointwise compression\)") as caught:
        read_points(tmp_path / "varying.laz")
    assert f"chunk size of {size}" in str(caught.value) and "re-compress it with laszip or PDAL" in str(caught.value)
    assert "panicked" not in capfd.readouterr().err


def test_las_1_4_layered_items_marked_pointwise_are_refused_by_name(tmp_path) -> None:
    """LASzip writes point formats 6-10 in layered chunks only; lazrs's layered reader would read on without one."""
    (tmp_path / "layered.laz").write_bytes(pointwise(XYZ[:1000], "1.4", 6))
    with pytest.raises(PointCloudFormatError, match=r"pointwise compression\) of LAS 1.4 layered items"):
        read_points(tmp_path / "layered.laz")


def test_the_server_refuses_one_with_a_400_naming_it(client, tmp_path) -> None:
    np.save(tmp_path / "target.npy", XYZ[:500])
    files = {
        "source": ("scan.laz", with_chunk_size(pointwise(XYZ[:500]), 0)),
        "target": ("target.npy", (tmp_path / "target.npy").read_bytes()),
    }
    answer = client.post("/v1/register", files=files, data={"model": MODEL, "rotation_search": "false"})
    assert_error(answer, 400, "source (scan.laz)", "LAZ without a chunk table (pointwise compression)")
