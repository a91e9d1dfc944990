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

The header's count of points must be the count the data holds, or the file is refused (a header that declares fewer
points than the data holds too: reading that many would register part of the cloud without a word). Uncompressed
points fill the bytes from the offset to the points to the first EVLR or the waveform data, else to the file's end,
with less than a point left over. LAZ: before any point is decompressed, the counts that LAZ 1.4 layered chunks start
with, else the chunk table (all chunks but the last of the VLR's chunk size, or each chunk's count where they vary);
then, where the chunks are read point by point, the decompressor must stand at the chunk table once the header's
count is read (the chunks are read back to back, each to its exact end): a count within the last chunk but wrong
either stops short of it or decodes the table's bytes as points (a made-up point from a LAZ 1.2 file claiming one
point more than it holds).

LAZ of pointwise compression (the LAZ VLR's compressor 1, LASzip's only kind before chunks: one arithmetic-coded stream
of every point from the offset to the points, no chunk table nor its offset before the points) is read by ``lazrs``
as one chunk; none of the chunk table's checks apply (the first 8 bytes are a point's, not a table's offset), and
the decompressor must stand where the points end (the first EVLR or the waveform data, else the file's end) once
the header's count is read. ``lazrs`` takes a chunk size of 0 or 2**32 - 1 in the VLR for chunks of varying size and
panics without a chunk table: such a file is refused, as is one whose items are LAS 1.4 layered ones (only chunked).
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
# Most VLRs read: laspy makes Python objects of each, several times an empty 54-byte VLR's size; files carry a
# handful (projection, LAZ, extra bytes, classification names), and the header's count field would allow 4e9
MAX_VLRS = 65_535
BATCH_BYTES = 16 * 2**20
# LAZ 1.4 layered items (type -> layers per chunk; Byte14: one per extra byte). A chunk starts with its first point
# raw, its point count and each layer's size (u32); Point14's first two layers are x/y (with returns, channel) and z.
POINT14, LAYERS = 10, {10: 9, 11: 1, 12: 2, 13: 1}
BYTE14 = 14
POINTWISE = 1  # the LAZ VLR's compressor (u16 at byte 0): no chunks, no chunk table
VARIABLE_CHUNKS = (0, 2**32 - 1)  # the VLR's chunk sizes (u32 at byte 12) lazrs takes for chunks of varying size
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
            data = start + header.offset_to_point_data
            pointwise = _check_pointwise(header)
            if pointwise:
                table, chunks, in_layers = None, None, None
            else:
                table = _check_chunk_table(f, data, start + size)
                chunks = _chunk_table(f, header, data)
                in_layers = _check_xyz_layers(f, header, data, chunks)
                _check_laz_count(header, count, chunks, in_layers)
            try:
                batches = _read_xyz(reader, count, max(1, BATCH_BYTES // header.point_format.size))
            except Exception as exc:  # lazrs's LazrsError; "failed to fill whole buffer" at the end of the data
                if "fill whole buffer" not in str(exc):
                    raise
                kind = " (pointwise, without a chunk table)" if pointwise else ""
                raise PointCloudFormatError(
                    f"LAZ header declares {count} points; its compressed data{kind} ends before them "
                    f"({type(exc).__name__}: {exc})"
                ) from None
            if pointwise:
                _check_laz_end(reader, f, count, start + _points_end(header, size), start + size, pointwise=True)
            elif table is not None and chunks and in_layers is None:  # layered chunks say their counts
                _check_laz_end(reader, f, count, _chunks_end(chunks, table), start + size)
        else:
            _check_las_count(header, count, size)
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
    scales, offsets = struct.unpack_from("<3d", head, 131), struct.unpack_from("<3d", head, 155)
    if not all(np.isfinite(scale) and scale > 0 for scale in scales) or not np.isfinite(offsets).all():
        raise PointCloudFormatError(
            f"LAS header scales {list(scales)} and offsets {list(offsets)}: each scale must be a positive number and "
            "each offset finite (x = integer * scale + offset)"
        )
    if vlrs > MAX_VLRS:
        raise PointCloudFormatError(f"LAS header declares {vlrs} VLRs; at most {MAX_VLRS} are read")
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


def _check_pointwise(header: LasHeader) -> bool:
    """Whether the LAZ VLR says pointwise compression (no chunk table), or its refusal where ``lazrs`` cannot read
    it: a chunk size it takes for chunks of varying size (it panics: they need a table), LAS 1.4 layered items."""
    record = header.vlrs.get("LasZipVlr")[0].record_data  # checked to hold its items (_check_laz_items)
    compressor, chunk_size = struct.unpack_from("<H", record, 0)[0], struct.unpack_from("<I", record, 12)[0]
    if compressor != POINTWISE:
        return False
    if chunk_size in VARIABLE_CHUNKS:
        raise PointCloudFormatError(
            f"LAZ without a chunk table (pointwise compression) whose VLR gives a chunk size of {chunk_size}, which "
            "the LAZ reader takes for chunks of varying size: not supported; re-compress it with laszip or PDAL"
        )
    if any(kind in LAYERS or kind == BYTE14 for kind, _, _ in _laz_items(record)):
        raise PointCloudFormatError(
            "LAZ without a chunk table (pointwise compression) of LAS 1.4 layered items, which LASzip writes only in "
            "chunks: not supported (the VLR is damaged); re-compress it with laszip or PDAL"
        )
    return True


def _check_chunk_table(f: BinaryIO, data: int, end: int) -> int | None:
    """The LAZ chunk table's count of chunks fits between the points' start and the table (lazrs allocates
    16 bytes per chunk before reading them, and aborts the process if that allocation fails). Returns the table's
    offset, where the compressed points end; None where the file has no table there (lazrs says so, or reads on)."""
    position = f.tell()
    try:
        f.seek(data)
        table = _int64(f.read(8))
        if table == -1:  # written to a stream: the table's offset is in the file's last 8 bytes
            f.seek(max(data, end - 8))
            table = _int64(f.read(8))
        if table is None or not 0 <= table <= end - 8:
            return None  # lazrs finds no table there and says so
        f.seek(table)
        chunks = struct.unpack("<II", f.read(8))[1]
        room = max(0, table - data - 8)
        if chunks > room:
            raise PointCloudFormatError(
                f"LAZ chunk table at byte {table} declares {chunks} chunks; {room} bytes of compressed points "
                "cannot hold them"
            )
        return table
    finally:
        f.seek(position)


def _chunk_table(f: BinaryIO, header: LasHeader, data: int) -> list[tuple[int, int]] | None:
    """The LAZ chunk table as lazrs reads it: (points, bytes) a chunk (the points are the VLR's chunk size in a table of
    chunks of a fixed size); None where there is no readable table or it lists no chunks (a damaged count)."""
    lazrs = require("lazrs", "reading LAZ files")
    position = f.tell()
    try:
        f.seek(data)
        return lazrs.read_chunk_table(f, lazrs.LazVlr(header.vlrs.get("LasZipVlr")[0].record_data)) or None
    except BaseException as exc:  # no readable table (pyo3's PanicException is no Exception)
        if not isinstance(exc, Exception) and type(exc).__name__ != "PanicException":
            raise
        return None
    finally:
        f.seek(position)


def _check_xyz_layers(f: BinaryIO, header: LasHeader, data: int, chunks: list[tuple[int, int]] | None) -> int | None:
    """In a LAZ 1.4 file of layered chunks, the x/y and z layer sizes of every chunk fit in the chunk (lazrs allocates
    them, zero-filled, before reading: 4 GB each from a damaged size). Other layers are skipped unread. Without a
    readable chunk table (lazrs reads on without one), each chunk is taken to end where its layer sizes say, as lazrs
    takes it, and its x, y and z layers must fit in the rest of the file. Returns the points the chunks say they hold
    (each layered chunk starts with its count), None where the file is not layered or a chunk is cut short."""
    record = header.vlrs.get("LasZipVlr")[0].record_data
    items = _laz_items(record)
    if (
        not items
        or items[0][0] != POINT14
        or items[0][2] < 3
        or any(kind not in LAYERS and kind != BYTE14 for kind, _, _ in items)
    ):
        return None  # not layered (LAZ 1.0-1.3 items are read point by point)
    layers = sum(LAYERS.get(kind, size) for kind, size, _ in items)  # Byte14: ``size`` layers
    point = header.point_format.size
    position = f.tell()
    try:
        end = f.seek(0, os.SEEK_END)
        at, k, points = data + 8, 0, 0  # the chunks follow the chunk table's offset
        while chunks is None or k < len(chunks):
            if chunks is not None and not chunks[k][0]:  # a chunk of no points (lazrs never reads it)
                at, k = at + chunks[k][1], k + 1
                continue
            f.seek(at + point)  # after the first point
            raw = f.read(4 + 4 * layers)
            if len(raw) < 12:
                return None  # lazrs says the chunk is cut short
            count, *sizes = struct.unpack(f"<{len(raw) // 4}I", raw[: len(raw) // 4 * 4])
            xy, z = sizes[:2]
            length = chunks[k][1] if chunks is not None else point + 4 + 4 * layers + sum(sizes)
            room = min(length, end - at) - point - 4 - 4 * layers
            if xy + z > room:
                raise PointCloudFormatError(
                    f"LAZ chunk {k} declares x, y and z layers of {xy + z} bytes; it holds "
                    f"{max(0, room)} bytes of layers"
                )
            at, k, points = at + length, k + 1, points + count
            if chunks is None and at >= end:
                break
        return points
    finally:
        f.seek(position)


def _check_laz_count(
    header: LasHeader, count: int, chunks: list[tuple[int, int]] | None, in_layers: int | None
) -> None:
    """The header's count of points against what the LAZ data says it holds, before any point is decompressed: the
    counts that layered chunks start with, else the chunk table (its points a chunk where chunks vary in size; where
    they do not, all chunks but the last hold the VLR's chunk size, the last one to that size)."""
    if in_layers is not None:
        if in_layers != count:
            raise PointCloudFormatError(f"LAZ header declares {count} points; its chunks hold {in_layers}")
        return
    if not chunks:
        return
    if header.vlrs.get("LasZipVlr")[0].record_data[12:16] == b"\xff\xff\xff\xff":  # variable-size chunks
        held = sum(points for points, _ in chunks)
        if held != count:
            raise PointCloudFormatError(f"LAZ header declares {count} points; its chunk table lists {held}")
        return
    size = chunks[0][0]
    low, high = (len(chunks) - 1) * size + 1, len(chunks) * size
    if not low <= count <= high:
        raise PointCloudFormatError(
            f"LAZ header declares {count} points; its {len(chunks)} chunks of {size} points hold {low} to {high}"
        )


def _chunks_end(chunks: list[tuple[int, int]], table: int) -> int:
    """Where the compressed points end: at the chunk table, before any chunks of no points that end a table of chunks
    of varying sizes."""
    at = table
    for points, size in reversed(chunks):
        if points:
            break
        at -= size
    return at


def _check_laz_end(reader: LasReader, f: BinaryIO, count: int, at: int, end: int, pointwise: bool = False) -> None:
    """After the header's count of points, the decompressor stands at ``at``, where the compressed points end
    (:func:`_chunks_end`; a pointwise file's at the EVLRs or waveform data, else the file's end ``end``): lazrs reads
    the chunks back to back, each to its exact end. A header that declares fewer points than the last chunk holds
    leaves the decompressor inside it; one that declares more decodes the chunk table's bytes as points (a made-up
    point, without an error, from a LAZ 1.2 file that claims one point more than it holds). A ``pointwise`` stream has
    no table to end at, so bytes appended after its points are refused too. Two reads of at most 16 bytes (at the
    file's end: one byte, which must not be there); no point is decompressed."""
    length = min(16, end - at)
    try:  # before ``f`` is moved: lazrs reads on from its position
        after = reader.point_source.read_raw_bytes(length or 1)  # from where the decompressor stopped
    except Exception:  # lazrs's LazrsError: the decompressor has read to the file's end
        after = None
    position = f.tell()
    f.seek(at)
    expected = f.read(length) if length else None
    f.seek(position)
    if after == expected:
        return
    if pointwise:  # no table marks the points' end: appended bytes look the same as points the count leaves out
        where = f"after them its pointwise stream (no chunk table) does not reach byte {at}, where the points must end"
        causes = "the data is damaged, or bytes were appended after the points"
    else:
        where = f"its compressed points do not end after {count} (they end at byte {at})"
        causes = "or the data is damaged"
    raise PointCloudFormatError(
        f"LAZ header declares {count} points; {where}: the header's count does not match the data, {causes}"
    )


def _check_las_count(header: LasHeader, count: int, size: int) -> None:
    """The header's count of points fills the uncompressed points' room: from the offset to the points to the
    first EVLR or the waveform data that the header places after them (LAS 1.3-1.4), else to the file's end. A count
    beyond it would read those bytes, or past the file's end, as points; one that leaves room for another whole point
    or more would leave points unread."""
    offset, point = header.offset_to_point_data, header.point_format.size
    room = max(0, _points_end(header, size) - offset)
    if count * point > room:
        raise PointCloudFormatError(
            f"LAS header declares {count} points of {point} bytes; the file holds {room} bytes of points"
        )
    if room - count * point >= point:
        raise PointCloudFormatError(
            f"LAS header declares {count} points of {point} bytes; the file holds {room} bytes of points, "
            f"{room // point} points"
        )


def _points_end(header: LasHeader, size: int) -> int:
    """Where the points end (from the header's start; ``size`` bytes from there): at the first EVLR or the waveform
    data that the header places after them (LAS 1.3-1.4), else at the file's end."""
    offset = header.offset_to_point_data
    ends = [size]
    if header.version.minor >= 4 and header.number_of_evlrs:
        ends.append(header.start_of_first_evlr)
    if header.version.minor >= 3 and header.global_encoding.waveform_data_packets_internal:
        ends.append(header.start_of_waveform_data_packet_record)
    return min(at for at in ends if offset <= at <= size)


def _laz_items(record: bytes) -> list[tuple[int, int, int]]:
    """The LAZ VLR's items: (type, size, version) each (the VLR checked to hold them, :func:`_check_laz_items`)."""
    return [struct.unpack_from("<HHH", record, 34 + 6 * k) for k in range(struct.unpack_from("<H", record, 32)[0])]


def _int64(raw: bytes) -> int | None:
    return struct.unpack("<q", raw)[0] if len(raw) == 8 else None
