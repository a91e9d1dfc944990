"""E57 (ASTM E2807) with ``e57`` (Rust, memory-safe): every scan in the file's frame, its points with a return.

A file holds one or more scans (``data3D``), each with its points in its own frame and a pose (a rotation
quaternion ``w, x, y, z`` and a translation) that takes them into the file's frame,
``p_file = R @ p_scan + t`` (no pose: the identity). ``e57.read_points`` reads each scan, moves it by its pose and
appends it in the file's order of scans, so a registered project of several scans reads as one cloud.

- Coordinates: ``cartesianX/Y/Z`` where a scan has them, else ``sphericalRange/Azimuth/Elevation``
  converted as the standard defines, ``x = r cos(elevation) cos(azimuth)``, ``y = r cos(elevation)
  sin(azimuth)``, ``z = r sin(elevation)`` (radians). Scaled-integer fields are scaled by the library.
- Points without a return are left out: those whose ``cartesianInvalidState`` (or, for spherical
  coordinates, ``sphericalInvalidState``) is not 0 (1: a direction only, 2: no measurement). The point
  limit counts every point the headers declare, invalid ones included, before any is read.
- Intensity, colour, row/column indices, timestamps and images are ignored (the library reads colour and intensity
  too: :data:`READ_BYTES_PER_POINT`).

``e57.read_points`` opens files by path only: a stream that is not a file on disk (an HTTP upload held in memory)
is copied to a temporary file, deleted after reading; the service's upload limit bounds its size.

The XML section is parsed by expat first (:func:`check_xml`), and the library reads only a file that passed. The
scans' record counts come from it: the library reserves its arrays from the first scan's count before it reads a
point, and aborts the process where that allocation fails (a declared 2,000,000,000 points), so the point limit, and
without one the memory (:func:`_check_memory`), are checked before it reads anything. Refused there: a DTD (E57 files
have none; the library refuses one too), an XML Schema instance attribute, an XML section beyond
:data:`MAX_XML_BYTES` or not in the file, more than :data:`MAX_XML_ELEMENTS` elements, nesting deeper than
:data:`MAX_XML_DEPTH` (100,000 levels overflowed the library's stack: SIGSEGV), a structure of more than
:data:`MAX_STRUCTURE_CHILDREN` children, and what would make the library read other counts or poses than those
checked: a ``data3D`` anywhere but under the root (the library reads the first one it meets), a record count that is
not a decimal integer (the library reads ``+5``), and a pose quaternion whose norm is not 1 within
:data:`MAX_QUATERNION_NORM_ERROR` (the library does not normalise it: the scan is scaled by the norm's square). So is a
prototype field's Float ``precision`` other than ``single`` and ``double`` (none is ``double``; the library refuses
another value too, case and spaces included), as the record counts are checked from each field's bits, and a Float
intensity or colour whose minimum is above its maximum (the library scales them by these limits, and panics), and a
comment or processing instruction inside a value element (:data:`VALUE_TYPES`: the library reads its text only up to
it), and a ``cartesianInvalidState`` or ``sphericalInvalidState`` field other than the standard's Integer of 0 to 2
(:func:`_check_invalid_state`: the library panics on a value outside 0 to 2, which wider bounds let the file hold;
the standard's own bounds take 2 bits, which can still store a 3: only the points' data shows it, and that panic is
left to the library).
Only the
``data3D`` children of type Structure are scans, as the library reads them (it skips another, and panics where none
is left). A scan of no points is refused too: the library cannot read a file holding one (it reads the empty scan's
section header at offset 0).

Every page's checksum is checked before the library reads the file (:func:`check_pages`): the library checks each page
as it reads it, but a mismatch in a scan's points is a Rust panic, and the panic hook prints it on stderr (a damaged
upload read as a crash in the server's logs). So is any error it meets in a scan's section, so each scan's ``points``
``fileOffset`` is checked to lead to one (:func:`check_sections`): inside the file, at a compressed-vector section
header (section ID 1, a length of whole 4-byte words) whose data offset is a data packet's. The section's data packets
are then walked as the library reads them, their headers only (:func:`_check_records`: 2.5 ms for a 24 MB file), and
refused where they hold fewer records than the scan's ``recordCount`` (the library reads on into what follows the last
packet: another section, the XML section), where a packet has another number of bytestreams than the prototype has
fields, where an index or ignored packet comes before the scan's records are all read (the library cannot read one
there: a panic), or where every field of the prototype takes 0 bits a record (the library makes records until its
memory runs out). A panic that still happens (``pyo3_runtime.PanicException``, a ``BaseException``: an XML section with
valid checksums that describes the binary sections in a way these checks leave to the library, such as a scan of more
than :data:`MAX_PACKETS` data packets whose last ones hold fewer records than its count) is a
:class:`PointCloudFormatError` here, its message still printed by the hook.
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
import shutil
import struct
import tempfile
import xml.parsers.expat
from collections.abc import Iterator
from typing import Any, BinaryIO, NamedTuple

import numpy as np

from service.formats.checks import check_count, checked
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError

# What e57.read_points holds for a declared point: x, y, z (float64), a colour (3 float32) and an intensity (float32);
# it reserves them from the first scan's record count before it reads a point
READ_BYTES_PER_POINT = 40
PAGE_BYTES, PAGE_DATA_BYTES = 1024, 1020  # E57 pages: 1,020 bytes of data, then a CRC-32C
PAGES_A_CHUNK = 1024  # pages read and checked at a time (1 MiB)
HEADER = struct.Struct("<8sIIQQQQ")  # signature, version major, minor, file length, XML offset, XML length, page size
SECTION = struct.Struct("<B7xQQQ")  # a compressed vector's section header: ID 1, logical length, data and index offsets
DATA_PACKET = 1  # a packet's first byte: 0 index, 1 data, 2 empty
PACKET = struct.Struct("<BBHH")  # a data packet's header: type 1, flags, logical length - 1, bytestream count
# Most data packets read to check a scan's record count (libE57Format wrote 489, of 49 KB, for 2,000,000 points in
# single precision, a 24 MB file; 65,536 such packets hold 3.2 GB); past it the count is left to the library. The walk
# takes about 15 microseconds a packet (2.9 s for 200,000 packets of one record each, which the library reads in 0.04 s)
MAX_PACKETS = 65_536
I64 = re.compile(r"[+-]?[0-9]+")  # an integer attribute as the library parses it (Rust's i64)
I64_MIN, I64_MAX = -(1 << 63), (1 << 63) - 1  # an Integer's minimum and maximum where the attribute is absent
# A Float attribute as the library parses it (Rust's f64 and f32: no spaces or underscores, as Python's float takes)
FLOAT = re.compile(r"[+-]?(inf|infinity|nan|([0-9]+\.?[0-9]*|\.[0-9]+)(e[+-]?[0-9]+)?)", re.IGNORECASE)
SCALED_FIELDS = ("intensity", "colorRed", "colorGreen", "colorBlue")  # the library scales them by their limits
MAX_XML_BYTES = 16 << 20  # a scan's XML is a few KB
MAX_XML_ELEMENTS = 100_000  # about 60 a scan (pye57's), 30 an image
MAX_XML_DEPTH = 64  # a scan's coordinate field is 6 deep
MAX_STRUCTURE_CHILDREN = 256  # a scan has about 20
XSI = "http://www.w3.org/2001/XMLSchema-instance"  # xsi:schemaLocation names a schema to load; E57 files have none
RECORD_COUNT = re.compile(r"[0-9]+")  # ASCII digits: str.isdigit() takes "²", which int() refuses
# Most a pose's quaternion norm may differ from 1: the library does not normalise it, and scales the scan by the
# norm's square (2e-4 at this bound, 2 cm at 100 m); a quaternion typed to 4 decimals (0.7071, 0, 0, 0.7071) is 1e-5 off
MAX_QUATERNION_NORM_ERROR = 1e-4
VALUE_TYPES = ("Float", "Integer", "ScaledInteger", "String")  # elements whose text is their value
POSE_ROTATION = ["data3D", "vectorChild", "pose", "rotation"]  # under the root: a scan's quaternion w, x, y, z
POSE_TRANSLATION = ["data3D", "vectorChild", "pose", "translation"]  # under the root: a scan's x, y, z shift
PROTOTYPE = ["data3D", "vectorChild", "points", "prototype"]  # under the root: a scan's fields, one bytestream each
COORDINATES = (("cartesianX", "cartesianY", "cartesianZ"), ("sphericalRange", "sphericalAzimuth", "sphericalElevation"))
FLOAT32_MAX = float(np.finfo(np.float32).max)  # a pose translation beyond it (or NaN) moves every point off the map
INVALID_STATES = ("cartesianInvalidState", "sphericalInvalidState")  # 0 a return, 1 a direction only, 2 none


class Section(NamedTuple):
    """A scan's ``points`` as the XML section gives them: the scan's number, its ``fileOffset`` (the attribute's
    text), its ``recordCount``, and the bits a record takes in each prototype field's bytestream, in the prototype's
    order (None: a type or bounds that the library refuses when it opens the file)."""

    scan: int
    offset: str
    count: int
    bits: list[int | None]


def read_e57(f: BinaryIO, max_points: int | None) -> np.ndarray:
    e57 = require("e57", "reading E57 files")
    with _on_disk(f) as path:
        sections: list[Section] = []
        scans = check_xml(path, sections)
        if not scans:
            raise InvalidPointsError("the E57 file holds no scans (its data3D is empty): no points to read")
        total = sum(scans)
        check_count(total, max_points)
        if total == 0:
            empty = f"none of the E57 file's {len(scans)} scan(s) declares a point"
            raise InvalidPointsError(f"the cloud is empty: {empty}")
        if 0 in scans:
            raise PointCloudFormatError(
                f"E57 scan {scans.index(0)} holds no points (its recordCount is 0); a file with an empty scan is not "
                "read (the e57 reader reads every scan's section, and an empty one has none): remove the empty scan"
            )
        _check_memory(total)
        check_pages(path)
        check_sections(path, sections)
        points = _read_points(e57, path)
    if len(points) == 0:
        raise InvalidPointsError(
            f"the cloud is empty: all {total} points of the E57 file are marked invalid (no return)"
        )
    return checked(points)


def _read_points(e57: Any, path: str) -> np.ndarray:
    """``e57.read_points``'s ``[N, 3]`` float64 points, its errors as :class:`PointCloudFormatError`: a
    ``RuntimeError`` (the header or XML section) or a Rust panic (``pyo3_runtime.PanicException``, a
    ``BaseException``: damaged point data, a checksum that does not match)."""
    try:
        return np.asarray(e57.read_points(path).points, dtype=np.float64)
    except BaseException as exc:
        if not isinstance(exc, Exception) and type(exc).__name__ != "PanicException":
            raise  # KeyboardInterrupt, SystemExit
        raise PointCloudFormatError(f"not a readable E57 file ({_reason(exc, path)})") from None


def check_pages(path: str) -> None:
    """:class:`PointCloudFormatError` naming the first page of the E57 file at ``path`` whose CRC-32C (its last 4
    bytes, big-endian) does not match its 1,020 bytes of data, or a file that is not whole pages. The library checks
    each page as it reads it, but a mismatch in a scan's points is a Rust panic, whose message the panic hook prints
    on the server's stderr before Python sees it: checked here first, so a damaged upload is refused without it
    (``google-crc32c``, in C: a few milliseconds for a 24 MB file)."""
    crc32c = require("google_crc32c", "reading E57 files")
    with open(path, "rb") as f:
        first = 0  # the number of the chunk's first page
        while chunk := f.read(PAGES_A_CHUNK * PAGE_BYTES):
            if len(chunk) % PAGE_BYTES:
                size = first * PAGE_BYTES + len(chunk)
                raise PointCloudFormatError(
                    f"not a readable E57 file (it has {size} bytes, not whole pages of {PAGE_BYTES}: cut short, or "
                    "bytes added)"
                )
            found = np.fromiter(
                (crc32c.value(chunk[k : k + PAGE_DATA_BYTES]) for k in range(0, len(chunk), PAGE_BYTES)),
                dtype=np.uint32,
                count=len(chunk) // PAGE_BYTES,
            )
            stored = np.frombuffer(chunk, dtype=">u4")[PAGE_DATA_BYTES // 4 :: PAGE_BYTES // 4]
            wrong = np.flatnonzero(found != stored)
            if len(wrong):
                page = first + int(wrong[0])
                raise PointCloudFormatError(
                    f"not a readable E57 file (invalid checksum for page {page}, bytes {page * PAGE_BYTES} to "
                    f"{page * PAGE_BYTES + PAGE_BYTES - 1}: the file is damaged)"
                )
            first += len(found)


def check_sections(path: str, sections: list[Section]) -> None:
    """:class:`PointCloudFormatError` where a scan's ``points`` (each :class:`Section` as the XML section gives them)
    do not lead to a compressed-vector section: past the file's end or at a page's checksum, a section header that is
    not one (section ID 1, a logical length of whole 4-byte words), or a data offset that is not a data packet's; or
    where the section's data packets hold fewer records than its ``recordCount`` (:func:`_check_records`). The library
    panics on each (its hook prints the panic on the server's stderr); this reads 33 bytes a scan, and a packet's
    header a packet, and decodes nothing. A ``fileOffset`` that is not a decimal integer is left to the library, which
    refuses it without a panic."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        for scan, text, count, bits in sections:
            if not RECORD_COUNT.fullmatch(text.removeprefix("+")):
                continue
            offset = int(text)
            where = f"the E57 file's XML section puts scan {scan}'s points at byte {offset}"
            header = _logical_bytes(f, offset, SECTION.size, size)
            if header is None:
                raise PointCloudFormatError(
                    f"{where}, {_outside(offset, size)}: the XML section does not describe the file (it is damaged)"
                )
            section, length, data, _ = SECTION.unpack(header)
            if section != 1 or length % 4:
                found = f"a first byte of {section}, not the section ID 1"
                if section == 1:
                    found = f"a length of {length} bytes, not a multiple of 4"
                raise PointCloudFormatError(
                    f"{where}, where there is no compressed-vector section ({found}): the XML section does not "
                    "describe the file (it is damaged)"
                )
            packet = _logical_bytes(f, data, 1, size)
            if packet != bytes([DATA_PACKET]):
                found = _outside(data, size) if packet is None else f"where there is none (a byte of {packet[0]})"
                raise PointCloudFormatError(
                    f"E57 scan {scan}'s section (at byte {offset}) puts its first data packet at byte {data}, {found}: "
                    "the file is damaged"
                )
            _check_records(f, Section(scan, text, count, bits), data, size)


def _check_records(f: BinaryIO, section: Section, data: int, size: int) -> None:
    """:class:`PointCloudFormatError` where the data packets of ``section`` (from the physical offset ``data`` on, in
    the E57 file ``f`` of ``size`` bytes) hold fewer records than its ``recordCount``: the library reads packet after
    packet until it has them all, and what follows the last one (another section, the XML section) is a Rust panic.
    The packets are walked as the library reads them, each header and its bytestreams' lengths only (a packet's bytes
    are not read): the records a packet adds are what each bytestream holds over its field's bits (32 a single, 64 a
    double, an Integer's or ScaledInteger's ``maximum - minimum`` in binary digits, 0 where they are equal), the
    fewest of them. Also refused: a packet of another number of bytestreams than the prototype has fields, an index
    or ignored packet before the records are all held (the library reads data packets only, and panics), and a
    prototype whose every field takes 0 bits (the library fills records without end: its memory). Left to the
    library (which refuses them when it opens the file, or reads them): a field of unknown bits, a packet that does
    not end where the library reads on (its bytestreams, up to the next multiple of 4 bytes in the file), and the
    packets past the first :data:`MAX_PACKETS` (each header's place follows from the one before, so the walk is a
    Python loop over the packets: see :data:`MAX_PACKETS`)."""
    scan, offset, count, bits = section
    if any(width is None for width in bits):
        return
    widths = [width for width in bits if width is not None]
    if not any(widths):
        fields = f"{len(widths)} field(s), each an integer whose minimum is its maximum (0 bits a record)"
        raise PointCloudFormatError(
            f"E57 scan {scan}'s prototype has {fields if widths else 'no field'}: the e57 reader cannot read its "
            f"{count} records"
        )
    held = [0] * len(widths)  # bytes of each bytestream so far
    logical = data // PAGE_BYTES * PAGE_DATA_BYTES + data % PAGE_BYTES
    end = size // PAGE_BYTES * PAGE_DATA_BYTES  # the file's logical bytes (whole pages: check_pages)
    for _ in range(MAX_PACKETS):
        records = min((held[k] * 8 // width for k, width in enumerate(widths) if width), default=0)
        if records >= count:
            return
        physical = logical // PAGE_DATA_BYTES * PAGE_BYTES + logical % PAGE_DATA_BYTES
        holds = (
            f"E57 scan {scan} declares {count} records (its recordCount), and its section (at byte {offset}) holds "
            f"{records} before byte {physical}"
        )
        header = _logical_bytes(f, physical, PACKET.size + 2 * len(widths), size)
        if header is None:
            raise PointCloudFormatError(
                f"{holds}, {_outside(physical, size)}: the XML section does not describe the file (it is damaged)"
            )
        kind, _, length, streams = PACKET.unpack_from(header)
        if kind in (0, 2):
            raise PointCloudFormatError(
                f"{holds}, where an {('index', '', 'ignored')[kind]} packet follows among its data packets: the e57 "
                "reader cannot read a scan whose data packets another packet interrupts (re-save the file with "
                "another E57 writer)"
            )
        if kind != DATA_PACKET or (length + 1) % 4:
            found = f"a byte of {kind}" if kind != DATA_PACKET else f"a length of {length + 1} bytes"
            raise PointCloudFormatError(
                f"{holds}, where no data packet follows ({found}): the XML section does not describe the file (it is "
                "damaged)"
            )
        if streams != len(widths):
            raise PointCloudFormatError(
                f"E57 scan {scan}'s prototype has {len(widths)} field(s), and its section (at byte {offset}) has a "
                f"data packet of {streams} bytestream(s) at byte {physical}: the XML section does not describe the "
                "file (it is damaged)"
            )
        lengths = struct.unpack_from(f"<{streams}H", header, PACKET.size)
        used = PACKET.size + 2 * streams + sum(lengths)
        # The library reads the bytestreams, then goes on at the next multiple of 4 bytes in the file (not of the
        # packet's own length: the two differ where a section does not begin at one). A packet laid out otherwise
        # than the library reads it is left to the library
        if -(-(logical + used) // 4) * 4 != logical + length + 1:
            return
        held = [total + more for total, more in zip(held, lengths, strict=True)]
        logical += length + 1
        if logical > end:
            raise PointCloudFormatError(
                f"E57 scan {scan}'s section (at byte {offset}) has a data packet at byte {physical} of {length + 1} "
                f"bytes, past the end of the file ({size} bytes): the file is cut short or damaged"
            )


def _outside(offset: int, size: int) -> str:
    """Why ``offset`` holds no section or packet of a file of ``size`` bytes."""
    if offset < size and offset % PAGE_BYTES >= PAGE_DATA_BYTES:
        return "a page's checksum"
    return f"at or past the end of the file ({size} bytes)"


def _logical_bytes(f: BinaryIO, offset: int, count: int, size: int, start: int = 0) -> bytes | None:
    """``count`` bytes of the E57 file ``f`` (beginning at ``start`` in ``f``) from its physical ``offset`` on, its
    pages' checksums left out; None where ``offset`` is a checksum's or the bytes run past the file's ``size``."""
    if offset % PAGE_BYTES >= PAGE_DATA_BYTES or offset >= size:
        return None
    f.seek(start + offset - offset % PAGE_BYTES)
    pages = f.read((offset % PAGE_BYTES + count) // PAGE_DATA_BYTES * PAGE_BYTES + PAGE_BYTES)
    data = b"".join(pages[k : k + PAGE_DATA_BYTES] for k in range(0, len(pages), PAGE_BYTES))
    found = data[offset % PAGE_BYTES :][:count]
    return found if len(found) == count else None


def _check_memory(total: int) -> None:
    """:class:`PointCloudFormatError` where the arrays ``e57.read_points`` reserves for ``total`` points are more
    than half the memory this process may have (physical memory, or a lower address-space limit): the library would
    abort the process where an allocation fails. Matters without a point limit (the CLI); the service's
    ``max_file_points`` is far below it."""
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        memory = min(memory, soft)
    if total * READ_BYTES_PER_POINT > memory // 2:
        raise PointCloudFormatError(
            f"the E57 file's scans declare {total} points; reading them takes {total * READ_BYTES_PER_POINT} bytes, "
            f"more than half of this machine's memory ({memory} bytes)"
        )


def check_xml(path: str, sections: list[Section] | None = None) -> list[int]:
    """The record count of each scan of the E57 file at ``path``, from its XML section: :class:`PointCloudFormatError`
    where it is not in the file, has a DTD, is not UTF-8, is not well formed or is beyond the limits above (parsed
    by expat, element by element, before the e57 library reads the file). Each scan's ``points`` are appended to
    ``sections`` where given."""
    with open(path, "rb") as f:
        text = _xml_section(f)
    return _parse_xml(text, sections)


def e57_count(f: BinaryIO) -> int:
    """The points the scans of the E57 file at ``f``'s position declare (the ``recordCount`` of each
    ``/data3D/*/points``), from its XML section as :func:`check_xml` parses it, with its errors; no point is read,
    and the e57 library is not used."""
    return sum(_parse_xml(_xml_section(f)))


def _xml_section(f: BinaryIO) -> bytes:
    """The XML section of the E57 file at ``f``'s position (its pages' CRCs left out); :class:`PointCloudFormatError`
    where the file is not an E57 file or does not hold it whole (a file cut short)."""
    start = f.tell()
    header = f.read(HEADER.size)
    if len(header) < HEADER.size or not header.startswith(b"ASTM-E57"):
        raise PointCloudFormatError("not an E57 file: its header (48 bytes from the signature ASTM-E57) is cut short")
    _, _, _, _, offset, length, _ = HEADER.unpack(header)
    if length > MAX_XML_BYTES:
        raise PointCloudFormatError(
            f"the E57 file's XML section has {length} bytes; at most {MAX_XML_BYTES} are read (a scan's takes a few KB)"
        )
    size = f.seek(0, os.SEEK_END) - start
    if offset % PAGE_BYTES >= PAGE_DATA_BYTES:  # no writer puts it among a page's CRC bytes
        raise PointCloudFormatError(f"the E57 file's header puts its XML section at byte {offset}, a page's checksum")
    text = _logical_bytes(f, offset, length, size, start) if length else b""
    if text is None:
        raise PointCloudFormatError(
            f"the E57 file is cut short: its header puts its XML section of {length} bytes at byte {offset}, and the "
            f"file has {size} bytes"
        )
    return text


def _parse_xml(text: bytes, sections: list[Section] | None = None) -> list[int]:
    """Parse the XML section ``text`` with expat, refusing a DTD, another encoding than UTF-8, the limits, a
    ``data3D`` elsewhere than under the root, a record count that is not a decimal integer and a prototype field's
    Float precision other than ``single`` and ``double``; the record count of each scan (a ``/data3D/vectorChild`` of
    type Structure with ``points``: the library skips another), and each ``points`` appended to ``sections`` where
    given (:class:`Section`)."""
    if b"\0" in text:  # UTF-16 or UTF-32, which the byte checks here would not read
        raise PointCloudFormatError("the E57 file's XML section is not UTF-8 text (it holds NUL bytes)")
    parser = xml.parsers.expat.ParserCreate(namespace_separator=" ")  # names as "namespace-URI local-name"
    children = [0]  # elements so far at each open level; [0]: the document's
    structures = [False]  # whether each open element is a Structure
    values = [False]  # whether each open element is a value the library reads from its text (Float, Integer, ...)
    names: list[str] = []  # the open elements' local names
    scans: list[int | None] = []  # each /data3D/vectorChild Structure's record count; None: no points element (yet)
    fields: list[set[str]] = []  # each such scan's prototype field names
    quaternion: dict[str, str] = {}  # the text of the open pose rotation's w, x, y, z
    shift: dict[str, str] = {}  # the text of the open pose translation's x, y, z
    elements = data3d = 0

    def refuse(reason: str) -> None:
        raise PointCloudFormatError(f"the E57 file's XML section {reason}")

    def declaration(version: str, encoding: str | None, standalone: int) -> None:
        if encoding is not None and encoding.lower().replace("_", "-") not in ("utf-8", "utf8"):
            refuse(f"declares the encoding {encoding[:40]!r}; E57 XML is UTF-8")

    def doctype(*_: Any) -> None:
        refuse(
            "has a document type declaration (<!DOCTYPE>), which E57 files do not have (its entities could expand "
            "without bound, or name files and URLs to read)"
        )

    def start(name: str, attributes: dict[str, str]) -> None:
        nonlocal elements, data3d
        elements += 1
        children[-1] += 1
        if elements > MAX_XML_ELEMENTS:
            refuse(f"has more than {MAX_XML_ELEMENTS} elements")
        if len(children) > MAX_XML_DEPTH:
            refuse(f"nests elements more than {MAX_XML_DEPTH} deep")
        if structures[-1] and children[-1] > MAX_STRUCTURE_CHILDREN:
            refuse(f"has a structure of more than {MAX_STRUCTURE_CHILDREN} children")
        schema = [key.split()[1] for key in attributes if key.startswith(f"{XSI} ")]
        if schema:
            refuse(f"has the XML Schema instance attribute {schema[0]!r}: schemas named there are not fetched")
        names.append(name.rsplit(" ", 1)[-1])
        if names[-1] == "data3D":
            data3d += 1
            if len(names) != 2 or data3d > 1:
                refuse("has a data3D element other than the root's (an E57 file has one, under its root)")
        if len(names) == 3 and names[1:] == ["data3D", "vectorChild"] and attributes.get("type") == "Structure":
            scans.append(None)  # the library skips a child of another type, or none
            fields.append(set())
        if len(names) == 4 and names[1:] == ["data3D", "vectorChild", "points"] and structures[3]:
            count = attributes.get("recordCount", "")
            if not RECORD_COUNT.fullmatch(count):
                refuse(f"gives scan {len(scans) - 1} the recordCount {count[:40]!r}, not a decimal integer")
            scans[-1] = (scans[-1] or 0) + int(count)
            if sections is not None:
                sections.append(Section(len(scans) - 1, attributes.get("fileOffset", ""), int(count), []))
        if len(names) == 6 and names[1:5] == PROTOTYPE and structures[3]:
            fields[-1].add(names[5])
            if names[5] in INVALID_STATES:
                _check_invalid_state(names[5], attributes, len(scans) - 1)
            width = _bits(names[5], attributes, len(scans) - 1)
            if sections:
                sections[-1].bits.append(width)
        if names[1:] == POSE_ROTATION and structures[3]:
            quaternion.clear()
        if names[1:] == POSE_TRANSLATION and structures[3]:
            shift.clear()
        children.append(0)
        structures.append(attributes.get("type") == "Structure")
        values.append(attributes.get("type") in VALUE_TYPES)

    def inside_value(what: str) -> None:
        if values[-1]:
            refuse(
                f"has {what} inside the value of <{names[-1]}>: the e57 library reads a value's text only up to it "
                "(other readers read all of it)"
            )

    def characters(data: str) -> None:
        if len(names) == 6 and names[1:5] == POSE_ROTATION and names[5] in ("w", "x", "y", "z"):
            quaternion[names[5]] = quaternion.get(names[5], "") + data
        if len(names) == 6 and names[1:5] == POSE_TRANSLATION and names[5] in ("x", "y", "z"):
            shift[names[5]] = shift.get(names[5], "") + data

    def end(name: str) -> None:
        if names[1:] == POSE_ROTATION and structures[3]:
            _check_quaternion(quaternion, len(scans) - 1)
        if names[1:] == POSE_TRANSLATION and structures[3]:
            try:
                finite = all(abs(float(shift.get(axis, "").strip() or 0)) <= FLOAT32_MAX for axis in "xyz")
            except ValueError:
                finite = True  # not a number: the library says so
            if not finite:
                refuse(f"gives scan {len(scans) - 1}'s pose the translation {dict(sorted(shift.items()))}, not finite "
                       "numbers within float32's range")
        children.pop()
        structures.pop()
        values.pop()
        names.pop()

    parser.XmlDeclHandler = declaration
    parser.StartDoctypeDeclHandler = doctype
    parser.StartElementHandler = start
    parser.CharacterDataHandler = characters
    parser.CommentHandler = lambda _: inside_value("a comment")
    parser.ProcessingInstructionHandler = lambda *_: inside_value("a processing instruction")
    parser.EndElementHandler = end
    try:
        parser.Parse(text, True)
    except xml.parsers.expat.ExpatError as exc:
        refuse(
            f"is not well-formed XML ({xml.parsers.expat.errors.messages[exc.code]} at line {exc.lineno}, "
            f"column {exc.offset})"
        )
    for scan, (count, names_) in enumerate(zip(scans, fields, strict=True)):
        if count is not None and not any(set(axes) <= names_ for axes in COORDINATES):
            have = sorted(names_ & {axis for axes in COORDINATES for axis in axes})
            refuse(f"gives scan {scan} no coordinates: its points' fields hold {have or 'none'} of cartesianX, "
                   "cartesianY, cartesianZ (or sphericalRange, sphericalAzimuth, sphericalElevation)")
    return [count for count in scans if count is not None]


def _bits(name: str, attributes: dict[str, str], scan: int) -> int | None:
    """The bits a record of scan ``scan``'s prototype field ``name`` (of these ``attributes``) takes in its
    bytestream, as the library reads it: a Float 32 (``precision="single"``) or 64 (``"double"``, or none), an Integer
    or ScaledInteger the binary digits of ``maximum - minimum`` (absent: those of a 64-bit integer); None for another
    type or bounds the library refuses. :class:`PointCloudFormatError` for a Float precision it does not know (it
    refuses one, case and spaces included), and for a Float intensity or colour whose minimum is above its maximum
    (the library scales them by these limits, and panics on such a pair)."""
    kind = attributes.get("type")
    if kind == "Float":
        precision = attributes.get("precision", "double")
        if precision not in ("single", "double"):
            raise PointCloudFormatError(
                f"the E57 file's XML section gives scan {scan}'s field {name[:40]!r} the Float precision "
                f"{precision[:40]!r}; the standard's are 'single' and 'double' (none: 'double')"
            )
        low, high = attributes.get("minimum", ""), attributes.get("maximum", "")
        if name in SCALED_FIELDS and FLOAT.fullmatch(low) and FLOAT.fullmatch(high):
            cast = np.float32 if precision == "single" else np.float64
            with np.errstate(over="ignore"):  # beyond the single range: infinite, as the library parses it
                above = cast(low) > cast(high)
            if above:
                raise PointCloudFormatError(
                    f"the E57 file's XML section gives scan {scan}'s field {name!r} the minimum {low[:40]!r}, above "
                    f"its maximum {high[:40]!r}"
                )
        return 32 if precision == "single" else 64
    if kind not in ("Integer", "ScaledInteger"):
        return None
    bounds = [attributes.get(key, default) for key, default in (("minimum", str(I64_MIN)), ("maximum", str(I64_MAX)))]
    if not all(I64.fullmatch(bound) and I64_MIN <= int(bound) <= I64_MAX for bound in bounds):
        return None
    low, high = map(int, bounds)
    return (high - low).bit_length() if high >= low else None


def _check_invalid_state(name: str, attributes: dict[str, str], scan: int) -> None:
    """:class:`PointCloudFormatError` where scan ``scan``'s prototype field ``name`` (``cartesianInvalidState`` or
    ``sphericalInvalidState``, of these ``attributes``) is not what the standard makes it, an Integer of ``minimum``
    0 or more and ``maximum`` 2 or less (absent bounds: those of a 64-bit integer): the library stops at a value
    outside 0 to 2 with a panic, so wider bounds, which let one be stored, are refused before it reads a point (a 3
    in the standard's own 2 bits shows only in the points' data: left to the library)."""
    kind = attributes.get("type")
    low, high = attributes.get("minimum", str(I64_MIN)), attributes.get("maximum", str(I64_MAX))
    if kind == "Integer" and I64.fullmatch(low) and I64.fullmatch(high) and int(low) >= 0 and int(high) <= 2:
        return
    found = f"the bounds {low[:40]} to {high[:40]}" if kind == "Integer" else f"the type {str(kind)[:40]!r}"
    raise PointCloudFormatError(
        f"the E57 file's XML section gives scan {scan}'s field {name!r} {found}; the standard's is an Integer of 0 to "
        "2 (0: a return, 1: a direction only, 2: no measurement), and the e57 reader cannot read a value outside them"
    )


def _check_quaternion(quaternion: dict[str, str], scan: int) -> None:
    """:class:`PointCloudFormatError` where scan ``scan``'s pose rotation (the text of its ``w, x, y, z``; an empty
    or missing one is 0, as the library reads it) is not a unit quaternion within
    :data:`MAX_QUATERNION_NORM_ERROR`."""
    try:
        norm = float(np.linalg.norm([float(quaternion.get(axis, "").strip() or 0) for axis in "wxyz"]))
    except ValueError:
        raise PointCloudFormatError(f"E57 scan {scan}'s pose has a rotation quaternion that is not numbers") from None
    if not abs(norm - 1.0) <= MAX_QUATERNION_NORM_ERROR:
        raise PointCloudFormatError(
            f"E57 scan {scan}'s pose has a rotation quaternion of norm {norm:.9g}; the standard's is a unit "
            f"quaternion (within {MAX_QUATERNION_NORM_ERROR:g} here), and another would scale the scan"
        )


@contextlib.contextmanager
def _on_disk(f: BinaryIO) -> Iterator[str]:
    """A path holding the bytes from ``f``'s position on: the file's own where ``f`` is a file on disk read from its
    start, else a temporary copy, deleted on exit."""
    name = getattr(f, "name", None)
    if isinstance(name, str) and f.tell() == 0 and os.path.isfile(name):
        yield name
        return
    descriptor, path = tempfile.mkstemp(suffix=".e57")
    try:
        with os.fdopen(descriptor, "wb") as copy:
            shutil.copyfileobj(f, copy)
        yield path
    finally:
        os.unlink(path)


def _reason(exc: BaseException, path: str) -> str:
    """The library's message without Rust's debug wrapping: ``Unable to read next point: Read { desc: "Failed to
    read data packet buffers", source: Some(Custom { kind: InvalidData, error: "Detected invalid checksum ..." }) }``
    reads ``Unable to read next point: Failed to read data packet buffers: Detected invalid checksum ...``; no path."""
    text = " ".join(str(exc).replace(path, "the file").split())
    quoted = re.findall(r'(?:desc|error): "((?:[^"\\]|\\.)*)"', text)
    if quoted:
        text = ": ".join([text.split(":", 1)[0], *quoted]) if ": " in text else ": ".join(quoted)
    return text[:300] or type(exc).__name__
