"""E57 (ASTM E2807) with ``pye57`` (libE57Format): every scan in the file's frame, its points with a return.

A file holds one or more scans (``data3D``), each with its points in its own frame and a pose (a rotation
quaternion ``w, x, y, z`` and a translation) that takes them into the file's frame,
``p_file = R @ p_scan + t`` (no pose: the identity). Each scan's points are read, moved by its pose and
appended in the file's order of scans, so a registered project of several scans reads as one cloud.

- Coordinates: ``cartesianX/Y/Z`` where a scan has them, else ``sphericalRange/Azimuth/Elevation``
  converted as the standard defines, ``x = r cos(elevation) cos(azimuth)``, ``y = r cos(elevation)
  sin(azimuth)``, ``z = r sin(elevation)`` (radians). Scaled-integer fields are scaled by libE57Format.
- Points without a return are left out: those whose ``cartesianInvalidState`` (or, for spherical
  coordinates, ``sphericalInvalidState``) is not 0 (1: a direction only, 2: no measurement). The point
  limit counts every point the headers declare, invalid ones included, before any is read.
- Intensity, colour, row/column indices, timestamps and images are ignored.

libE57Format opens files by path only: a stream that is not a file on disk (an HTTP upload held in memory)
is copied to a temporary file, deleted after reading; the service's upload limit bounds its size.

The XML section is checked before libE57Format's parser (Xerces-C) reads it (:func:`check_xml`). Refused: a DTD
(E57 files have none; Xerces expands the entities a DTD declares without a limit and fetches external ones, files
and URLs), an XML Schema instance attribute (Xerces fetches the schema an ``xsi:schemaLocation`` names), an XML
section beyond :data:`MAX_XML_BYTES`, more than :data:`MAX_XML_ELEMENTS` elements, nesting deeper than
:data:`MAX_XML_DEPTH`, and a structure of more than :data:`MAX_STRUCTURE_CHILDREN` children (libE57Format's tree
takes about 160 bytes an element, and a structure's children take time quadratic in their number: 100,000 children of
one structure took 136 s).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import struct
import tempfile
import xml.parsers.expat
from collections.abc import Iterator
from typing import Any, BinaryIO

import numpy as np

from service.formats.checks import check_count, checked
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError

BLOCK_POINTS = 1 << 18  # points read per call of libE57Format's reader (8 MiB of float64 x, y, z)
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
PAGE_BYTES, PAGE_DATA_BYTES = 1024, 1020  # libE57Format's pages: 1,020 bytes of data, then a CRC-32C
HEADER = struct.Struct("<8sIIQQQQ")  # signature, version major, minor, file length, XML offset, XML length, page size
MAX_XML_BYTES = 16 << 20  # a scan's XML is a few KB; 16 MiB of it took libE57Format 51 MiB
MAX_XML_ELEMENTS = 100_000  # about 60 a scan (pye57's), 30 an image
MAX_XML_DEPTH = 64  # a scan's coordinate field is 6 deep
MAX_STRUCTURE_CHILDREN = 256  # a scan has about 20
XSI = "http://www.w3.org/2001/XMLSchema-instance"  # xsi:schemaLocation: a URL or path Xerces loads a schema from


def read_e57(f: BinaryIO, max_points: int | None) -> np.ndarray:
    pye57 = require("pye57", "reading E57 files")
    libe57 = pye57.libe57
    with _on_disk(f) as path:
        check_xml(path)
        try:
            image = libe57.ImageFile(path, "r")
        except Exception as exc:  # libE57Format's E57Exception: a bad signature, length, checksum or XML section
            raise PointCloudFormatError(f"not a readable E57 file ({_reason(exc)})") from None
        try:
            return _read(libe57, image, max_points)
        except PointCloudFormatError:
            raise
        except Exception as exc:
            raise PointCloudFormatError(f"corrupt E57 data ({_reason(exc)})") from None
        finally:
            image.close()


def check_xml(path: str) -> None:
    """:class:`PointCloudFormatError` where the XML section of the E57 file at ``path`` has a DTD, is not UTF-8, is
    not well formed or is beyond the limits above (parsed by expat, element by element, before Xerces reads it)."""
    with open(path, "rb") as f:
        text = _xml_section(f)
    if text is not None:
        _parse_xml(text)


def e57_count(f: BinaryIO) -> int:
    """The points the scans of the E57 file at ``f``'s position declare (the ``recordCount`` of each
    ``/data3D/*/points``), from its XML section as :func:`check_xml` parses it, with its errors; no point is read,
    and libE57Format is not used. :class:`PointCloudFormatError` where the XML section cannot be found."""
    text = _xml_section(f)
    if text is None:
        raise PointCloudFormatError("the E57 file's XML section is not in the file")
    return _parse_xml(text)


def _xml_section(f: BinaryIO) -> bytes | None:
    """The XML section of the E57 file at ``f``'s position (its pages' CRCs left out), ``None`` where the file does
    not hold it (a file cut short: libE57Format, which reads no XML then, names the damage)."""
    start = f.tell()
    header = f.read(HEADER.size)
    if len(header) < HEADER.size or not header.startswith(b"ASTM-E57"):
        return None
    _, _, _, _, offset, length, _ = HEADER.unpack(header)
    if length > MAX_XML_BYTES:
        raise PointCloudFormatError(
            f"the E57 file's XML section has {length} bytes; at most {MAX_XML_BYTES} are read (a scan's takes a few KB)"
        )
    size = f.seek(0, os.SEEK_END) - start
    if offset >= size:
        return None  # beyond the file's end (the header's own page, checked by libE57Format first, is damaged)
    if offset % PAGE_BYTES >= PAGE_DATA_BYTES:  # no writer puts it among a page's CRC bytes
        raise PointCloudFormatError(f"the E57 file's header puts its XML section at byte {offset}, a page's checksum")
    f.seek(start + offset - offset % PAGE_BYTES)
    pages = f.read((length + offset % PAGE_BYTES) // PAGE_DATA_BYTES * PAGE_BYTES + 2 * PAGE_BYTES)
    data = b"".join(pages[k : k + PAGE_DATA_BYTES] for k in range(0, len(pages), PAGE_BYTES))  # the CRCs left out
    text = data[offset % PAGE_BYTES :][:length]
    return text if len(text) == length else None


def _parse_xml(text: bytes) -> int:
    """Parse the XML section ``text`` with expat, refusing a DTD, another encoding than UTF-8 and the limits; the
    sum of the scans' record counts (those that are integers: libE57Format judges the others)."""
    if b"\0" in text:  # UTF-16 or UTF-32, which Xerces would read and the byte checks here would not
        raise PointCloudFormatError("the E57 file's XML section is not UTF-8 text (it holds NUL bytes)")
    parser = xml.parsers.expat.ParserCreate(namespace_separator=" ")  # names as "namespace-URI local-name"
    children = [0]  # elements so far at each open level; [0]: the document's
    structures = [False]  # whether each open element is a Structure
    names: list[str] = []  # the open elements' local names
    elements = records = 0

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
        nonlocal elements, records
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
        count = attributes.get("recordCount", "")
        if len(names) == 4 and names[1:] == ["data3D", "vectorChild", "points"] and count.isdigit():
            records += int(count)
        children.append(0)
        structures.append(attributes.get("type") == "Structure")

    def end(name: str) -> None:
        children.pop()
        structures.pop()
        names.pop()

    parser.XmlDeclHandler = declaration
    parser.StartDoctypeDeclHandler = doctype
    parser.StartElementHandler = start
    parser.EndElementHandler = end
    try:
        parser.Parse(text, True)
    except xml.parsers.expat.ExpatError as exc:
        refuse(
            f"is not well-formed XML ({xml.parsers.expat.errors.messages[exc.code]} at line {exc.lineno}, "
            f"column {exc.offset})"
        )
    return records


def _read(libe57: Any, image: Any, max_points: int | None) -> np.ndarray:
    root = image.root()
    if not root.isDefined("data3D") or root["data3D"].childCount() == 0:
        raise InvalidPointsError("the E57 file holds no scans (its data3D is empty): no points to read")
    data3d = root["data3D"]
    scans = [data3d[k] for k in range(data3d.childCount())]
    plans = [_plan(libe57, scan, k) for k, scan in enumerate(scans)]
    total = sum(count for _, count, _ in plans)
    check_count(total, max_points)
    out = np.empty((total, 3), dtype=np.float64)  # [N, 3]: the valid points move up as they are read
    kept = 0
    for scan, (fields, count, invalid) in zip(scans, plans, strict=True):
        rotation, translation = _pose(scan)
        kept = _read_scan(libe57, image, scan, fields, invalid, count, rotation, translation, out, kept)
    if kept == 0:
        raise InvalidPointsError(
            f"the cloud is empty: all {total} points of the E57 file are marked invalid (no return)"
        )
    return checked(out[:kept])


def _plan(libe57: Any, scan: Any, index: int) -> tuple[tuple[str, str, str], int, str | None]:
    """The coordinate fields a scan is read from, its point count, and its invalid-state field (if any)."""
    if not scan.isDefined("points"):
        raise PointCloudFormatError(f"E57 scan {index} has no points node")
    points = scan["points"]
    prototype = libe57.StructureNode(points.prototype())
    names = {prototype.get(k).elementName() for k in range(prototype.childCount())}
    if set(CARTESIAN) <= names:
        fields, state = CARTESIAN, "cartesianInvalidState"
    elif set(SPHERICAL) <= names:
        fields, state = SPHERICAL, "sphericalInvalidState"
    else:
        raise PointCloudFormatError(
            f"E57 scan {index} has neither cartesianX/Y/Z nor sphericalRange/Azimuth/"
            f"Elevation fields (it has {', '.join(sorted(names))})"
        )
    return fields, int(points.childCount()), state if state in names else None


def _pose(scan: Any) -> tuple[np.ndarray, np.ndarray]:
    """``R [3, 3]`` and ``t [3]`` of the scan's pose (identity where absent); the quaternion normalised."""
    rotation, translation = np.eye(3), np.zeros(3)
    if not scan.isDefined("pose"):
        return rotation, translation
    pose = scan["pose"]
    if pose.isDefined("rotation"):
        q = np.array([_value(pose["rotation"], axis, 1.0 if axis == "w" else 0.0) for axis in "wxyz"])
        norm = float(np.linalg.norm(q))
        if not np.isfinite(norm) or norm < 1e-12:
            raise PointCloudFormatError(f"E57 scan pose has a rotation quaternion of norm {norm}")
        rotation = _rotation_matrix(q / norm)
    if pose.isDefined("translation"):
        translation = np.array([_value(pose["translation"], axis, 0.0) for axis in "xyz"])
        if not np.isfinite(translation).all():
            raise PointCloudFormatError(f"E57 scan pose has a translation of {translation.tolist()}")
    return rotation, translation


def _value(node: Any, name: str, default: float) -> float:
    return float(node[name].value()) if node.isDefined(name) else default


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    """The rotation of the unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _read_scan(
    libe57: Any,
    image: Any,
    scan: Any,
    fields: tuple[str, str, str],
    invalid: str | None,
    count: int,
    rotation: np.ndarray,
    translation: np.ndarray,
    out: np.ndarray,
    kept: int,
) -> int:
    """The scan's valid points, in the file's frame, written to ``out`` from row ``kept``; the rows then filled."""
    if count == 0:
        return kept
    capacity = min(count, BLOCK_POINTS)
    columns = {name: np.empty(capacity, dtype=np.float64) for name in fields}
    if invalid:
        columns[invalid] = np.empty(capacity, dtype=np.int8)
    buffers = libe57.VectorSourceDestBuffer()
    for name, column in columns.items():
        buffers.append(libe57.SourceDestBuffer(image, name, column, capacity, True, True))
    reader = scan["points"].reader(buffers)
    read = 0
    try:
        while read < count and (n := reader.read()) > 0:
            block = np.stack([columns[name][:n] for name in fields], axis=1)  # [n, 3]
            if invalid:
                block = block[columns[invalid][:n] == 0]
            if fields == SPHERICAL:
                block = _cartesian(block)
            out[kept : kept + len(block)] = block @ rotation.T + translation
            kept += len(block)
            read += n
    finally:
        reader.close()
    if read != count:
        raise PointCloudFormatError(f"E57 scan holds {read} points; its header says {count}")
    return kept


def _cartesian(rae: np.ndarray) -> np.ndarray:
    """``[n, 3]`` range, azimuth, elevation (radians) -> ``[n, 3]`` x, y, z (the E57 standard's convention)."""
    r, azimuth, elevation = rae.T
    flat = r * np.cos(elevation)
    return np.stack([flat * np.cos(azimuth), flat * np.sin(azimuth), r * np.sin(elevation)], axis=1)


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


def _reason(exc: Exception) -> str:
    """libE57Format's message and the context it gives (``header.filePhysicalLength=6144 file->length=3000``),
    without the temporary file's name and the library's source locations."""
    text = " ".join(str(exc).split())
    summary = text.split(" **** ")[0]
    context = re.search(r"context: (.*?)(?: sourceFunctionName:|$)", text)
    details = re.sub(r"fileName=\S*\s*", "", context.group(1)).strip() if context else ""
    return (f"{summary}: {details}" if details else summary)[:300] or type(exc).__name__
