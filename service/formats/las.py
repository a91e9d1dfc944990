"""LAS and LAZ with ``laspy`` (LAZ through its ``lazrs`` backend): scaled x, y, z in float64.

LAS stores integers with a scale and an offset, often UTM coordinates of millions of metres;
they are returned in float64, unrounded (the registrar centres each cloud before its float32 stages).

The counts of the header (VLRs, points, LAZ chunks) are checked against the file's size before
``laspy`` loops over them or ``lazrs`` allocates them (``lazrs`` aborts the process when an
allocation fails), and points are read in batches of at most :data:`BATCH_BYTES`. The LAZ VLR's items are
checked as LASzip checks them, each item of a fixed size (a point, a GPS time, a colour) of that size: ``lazrs``
panics on a shorter one, and Rust's panic hook prints ``thread ... panicked at ...`` on the server's stderr. LAZ is
decompressed by ``lazrs``'s sequential decompressor: the parallel one allocates a buffer of the LAZ VLR's chunk size
(points) at once, whatever the file holds.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from service.formats.checks import check_count, checked
from service.formats.deps import require
from service.formats.errors import MissingReaderError, PointCloudFormatError

if TYPE_CHECKING:
    from laspy import LasHeader, LasReader

VLR_HEADER_BYTES = 54
BATCH_BYTES = 16 * 2**20
# LAZ 1.4 layered items (type -> layers per chunk; Byte14: one per extra byte). A chunk starts with its first point
# raw, its point count and each layer's size (u32); Point14's first two layers are x/y (with returns, channel) and z.
POINT14, LAYERS = 10, {10: 9, 11: 1, 12: 2, 13: 1}
BYTE14 = 14
# LAZ item types of a fixed size (LASzip's), by type: name, bytes. Byte items (0, 14) are as long as they say.
ITEM_BYTES = {
    6: ("Point10", 20),
    7: ("GpsTime11", 8),
    8: ("RGB12", 6),
    9: ("Wavepacket13", 29),
    10: ("Point14", 30),
    11: ("RGB14", 6),
    12: ("RGBNIR14", 8),
    13: ("Wavepacket14", 29),
}


def read_las(f: BinaryIO, max_points: int | None) -> np.ndarray:
    laspy = require("laspy", "reading LAS/LAZ files")
    start = f.tell()
    size = f.seek(0, os.SEEK_END) - start
    f.seek(start)
    with _las_errors(), _open(laspy, f, size) as reader:
        header = reader.header
        count = int(header.point_count)
        check_count(count, max_points)
        if header.are_points_compressed:
            if not laspy.LazBackend.detect_available():
                raise MissingReaderError(
                    "reading LAZ files needs the 'lazrs' package, which is not installed: pip install 'mfgnet[formats]'"
                )
            _check_laz_items(header)
            _check_chunk_table(f, start + header.offset_to_point_data, start + size)
            _check_xyz_layers(f, header, start + header.offset_to_point_data)
        elif count * header.point_format.size > size - header.offset_to_point_data:
            raise PointCloudFormatError(
                f"LAS header declares {count} points of {header.point_format.size} bytes; the file holds "
                f"{max(0, size - header.offset_to_point_data)} bytes of points"
            )
        batches = _read_xyz(reader, count, max(1, BATCH_BYTES // header.point_format.size))
    read = sum(len(batch) for batch in batches)
    if read != count:
        raise PointCloudFormatError(f"LAS data holds {read} points; the header says {count}")
    return checked(np.concatenate(batches) if batches else np.empty((0, 3)))


def las_count(f: BinaryIO) -> int:
    """The points the LAS/LAZ header at ``f``'s position declares, read as :func:`read_las` reads it (the header and
    its VLRs, with the same errors); no points are read."""
    laspy = require("laspy", "reading LAS/LAZ files")
    start = f.tell()
    size = f.seek(0, os.SEEK_END) - start
    f.seek(start)
    with _las_errors(), _open(laspy, f, size) as reader:
        return int(reader.header.point_count)


def _open(laspy: ModuleType, f: BinaryIO, size: int) -> LasReader:
    """``laspy``'s reader of the file at ``f``'s position (``size`` bytes from there): its header and VLRs read, once
    their counts are checked against ``size`` (:func:`_check_header`); its points not yet."""
    _check_header(f, size)
    # read_evlrs=False: EVLRs are not used here, and laspy reads one per count, past the file's end; LAZ 1.4 layers
    # other than x, y, z are skipped unread (lazrs allocates each layer's declared size)
    xyz = laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z
    return laspy.open(
        f, closefd=False, read_evlrs=False, laz_backend=laspy.LazBackend.Lazrs, decompression_selection=xyz
    )


@contextmanager
def _las_errors() -> Iterator[None]:
    """What ``laspy`` and ``lazrs`` raise on bad data, as :class:`PointCloudFormatError`."""
    try:
        yield
    except PointCloudFormatError:
        raise
    except Exception as exc:  # laspy's LaspyException, or what numpy and the LAZ backend raise on bad data
        raise PointCloudFormatError(f"corrupt LAS/LAZ data ({type(exc).__name__}: {exc})") from None
    except BaseException as exc:
        if type(exc).__name__ != "PanicException":  # pyo3's, for a panic in lazrs: not an Exception
            raise
        raise PointCloudFormatError(f"corrupt LAS/LAZ data (lazrs panicked: {exc})") from None


def _read_xyz(reader: LasReader, count: int, batch: int) -> list[np.ndarray]:
    """float64 ``[n, 3]`` batches of scaled x, y, z, up to ``count`` points or the first short batch."""
    batches: list[np.ndarray] = []
    left = count
    while left > 0:
        wanted = min(batch, left)
        points = reader.read_points(wanted)
        if len(points):
            batches.append(np.stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)], axis=1))
        left -= len(points)
        if len(points) < wanted:
            break
    return batches


def _check_header(f: BinaryIO, size: int) -> None:
    """The VLR count and the offset to the points within the file (laspy reads a VLR per count, past the end)."""
    start = f.tell()
    head = f.read(227)  # the fixed part of a LAS 1.0-1.2 header, the start of every version's
    f.seek(start)
    if len(head) < 227:
        return  # laspy says what is missing
    offset, vlrs = struct.unpack_from("<II", head, 96)
    if offset > size:
        raise PointCloudFormatError(f"LAS header puts the points at byte {offset}; the file has {size} bytes")
    if vlrs * VLR_HEADER_BYTES > size:
        raise PointCloudFormatError(f"LAS header declares {vlrs} VLRs; the file of {size} bytes cannot hold them")


def _check_laz_items(header: LasHeader) -> None:
    """The LAZ VLR's items add up to the header's point size (lazrs sizes its buffers from the items), and each item
    of a fixed size has that size, as LASzip requires (lazrs slices an item's fixed size out of its declared bytes:
    fewer is a Rust panic, whose hook prints it on the server's stderr)."""
    found = header.vlrs.get("LasZipVlr")
    if not found:
        return  # laspy says that it is missing
    data = found[0].record_data
    items = struct.unpack_from("<H", data, 32)[0] if len(data) >= 34 else 0
    if len(data) < 34 + 6 * items:
        raise PointCloudFormatError(f"LAZ VLR cut short ({len(data)} bytes)")
    size = sum(size for _, size, _ in _laz_items(data))
    if size != header.point_format.size:
        raise PointCloudFormatError(
            f"LAZ VLR describes points of {size} bytes; the header says {header.point_format.size}"
        )
    for k, (kind, length, _) in enumerate(_laz_items(data)):
        name, fixed = ITEM_BYTES.get(kind, (None, length))
        if length != fixed:
            raise PointCloudFormatError(
                f"LAZ VLR's item {k} is a {name} of {length} bytes; a {name} item has {fixed} (the VLR is damaged)"
            )


def _check_chunk_table(f: BinaryIO, data: int, end: int) -> None:
    """The LAZ chunk table's count of chunks fits between the points' start and the table (lazrs allocates
    16 bytes per chunk before reading them, and aborts the process if that allocation fails)."""
    position = f.tell()
    try:
        f.seek(data)
        table = _int64(f.read(8))
        if table == -1:  # written to a stream: the table's offset is in the file's last 8 bytes
            f.seek(max(data, end - 8))
            table = _int64(f.read(8))
        if table is None or not 0 <= table <= end - 8:
            return  # lazrs finds no table there and says so
        f.seek(table)
        chunks = struct.unpack("<II", f.read(8))[1]
        room = max(0, table - data - 8)
        if chunks > room:
            raise PointCloudFormatError(
                f"LAZ chunk table at byte {table} declares {chunks} chunks; {room} bytes of compressed points "
                "cannot hold them"
            )
    finally:
        f.seek(position)


def _check_xyz_layers(f: BinaryIO, header: LasHeader, data: int) -> None:
    """In a LAZ 1.4 file of layered chunks, the x/y and z layer sizes of every chunk fit in the chunk (lazrs allocates
    them, zero-filled, before reading: 4 GB each from a damaged size). Other layers are skipped unread. Without a
    readable chunk table (lazrs reads on without one), each chunk is taken to end where its layer sizes say, as lazrs
    takes it, and its x, y and z layers must fit in the rest of the file."""
    lazrs = require("lazrs", "reading LAZ files")
    record = header.vlrs.get("LasZipVlr")[0].record_data
    items = _laz_items(record)
    if (
        not items
        or items[0][0] != POINT14
        or items[0][2] < 3
        or any(kind not in LAYERS and kind != BYTE14 for kind, _, _ in items)
    ):
        return  # not layered (LAZ 1.0-1.3 items are read point by point)
    layers = sum(LAYERS.get(kind, size) for kind, size, _ in items)  # Byte14: ``size`` layers
    point = header.point_format.size
    position = f.tell()
    try:
        end = f.seek(0, os.SEEK_END)
        f.seek(data)
        try:
            chunks = lazrs.read_chunk_table(f, lazrs.LazVlr(record))
        except BaseException as exc:  # no readable table (pyo3's PanicException is no Exception)
            if not isinstance(exc, Exception) and type(exc).__name__ != "PanicException":
                raise
            chunks = None
        chunks = chunks or None  # an empty table (a damaged count) is none
        at, k = data + 8, 0  # the chunks follow the chunk table's offset
        while chunks is None or k < len(chunks):
            f.seek(at + point + 4)  # after the first point and the point count
            raw = f.read(4 * layers)
            if len(raw) < 8:
                break  # lazrs says the chunk is cut short
            sizes = struct.unpack(f"<{len(raw) // 4}I", raw[: len(raw) // 4 * 4])
            xy, z = sizes[:2]
            length = chunks[k][1] if chunks is not None else point + 4 + 4 * layers + sum(sizes)
            room = min(length, end - at) - point - 4 - 4 * layers
            if xy + z > room:
                raise PointCloudFormatError(
                    f"LAZ chunk {k} declares x, y and z layers of {xy + z} bytes; it holds "
                    f"{max(0, room)} bytes of layers"
                )
            at, k = at + length, k + 1
            if chunks is None and at >= end:
                break
    finally:
        f.seek(position)


def _laz_items(record: bytes) -> list[tuple[int, int, int]]:
    """The LAZ VLR's items: (type, size, version) each (the VLR checked to hold them, :func:`_check_laz_items`)."""
    return [struct.unpack_from("<HHH", record, 34 + 6 * k) for k in range(struct.unpack_from("<H", record, 32)[0])]


def _int64(raw: bytes) -> int | None:
    return struct.unpack("<q", raw)[0] if len(raw) == 8 else None
