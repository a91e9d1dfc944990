"""An E57 file moved by a pose (:func:`service.formats.moved.write_moved`): its poses composed, its data copied.

Each scan (``/data3D/*``) and image (``/images2D/*``) has a pose (a rotation quaternion ``w, x, y, z`` and a
translation) that maps its own coordinates into the file's frame, ``p_file = R_i @ p + t_i`` (no pose: the identity;
:mod:`service.formats.e57`). Moving the file by ``R``, ``t`` composes each: ``R_i' = R @ R_i``, ``t_i' = R @ t_i + t``,
and an element without a pose gains one. The points, images and every other binary section stay as they are, in the
scans' own frames; so do bounds (``cartesianBounds``, ``sphericalBounds``: in the scan's frame).

- The XML section is rewritten by splicing: each pose's ``w x y z`` and translation ``x y z`` elements are replaced
  where they are (found at expat's byte positions), as ``<w type="Float">`` with the value's shortest float64 text
  (``repr``), and a missing pose, rotation, translation or component is inserted before its parent's end tag; every
  other byte of the XML (declaration, namespaces, extensions, element order, whitespace, CDATA) is kept. Only elements
  of the root's namespace are composed; an element of another namespace named as one of those the pose is looked up
  by (a scan's ``pose``, its ``rotation``, its ``w``, ...) is refused where the pose is looked up, since the e57 library
  reads the first element of that local name whatever its namespace (one deeper in an extension is not looked at).
- Each quaternion is written of unit norm, its sign the one with ``w >= 0``. A scan's or image's quaternion must be of
  norm 1 within :data:`service.formats.e57.MAX_QUATERNION_NORM_ERROR` (what the reader allows); it is normalised
  before it is composed.
- The file: where the old XML section is the last thing in it (it ends in the last page, and no ``fileOffset`` lies
  beyond its start), the new one is written in its place and the file ends after it; else the new one is appended on
  a page of its own after the last page, and the old one is left unreferenced. The header's ``filePhysicalLength``,
  ``xmlPhysicalOffset`` and ``xmlLogicalLength`` are updated. Pages are copied as they are, with their CRC-32C, a chunk
  at a time (the file is never held whole); the rewritten pages (the header's, and those of the XML) get new ones
  (``google-crc32c``, as the reader checks them).

Refused (:class:`PointCloudFormatError`, before anything is written): what the reader refuses of the XML section
(:func:`service.formats.e57.check_xml`'s checks), another page size than 1,024 bytes, a file of partial pages, a pose
element repeated or one of its names in another namespace, a pose whose numbers are not finite numbers or whose
quaternion is not a unit one, and an XML section that the poses added would take beyond the reader's limits.
"""

from __future__ import annotations

import os
import re
import xml.parsers.expat
from dataclasses import dataclass, field
from types import ModuleType
from typing import BinaryIO

import numpy as np
from scipy.spatial.transform import Rotation

from service.formats import e57 as e57_format
from service.formats.deps import require
from service.formats.errors import PointCloudFormatError

PAGE_BYTES, PAGE_DATA_BYTES = e57_format.PAGE_BYTES, e57_format.PAGE_DATA_BYTES
HEADER = e57_format.HEADER
COPY_BYTES = e57_format.PAGES_A_CHUNK * PAGE_BYTES  # pages copied at a time (1 MiB)
ELEMENTS = ("data3D", "images2D")  # the root's vectors whose Structure children have poses
ROTATION, TRANSLATION = ("w", "x", "y", "z"), ("x", "y", "z")
COORDINATES = {f"cartesian{a}" for a in "XYZ"} | {f"spherical{a}" for a in ("Range", "Azimuth", "Elevation")}
WHITESPACE = b" \t\n\r\x0b\x0c"  # what bytes.rstrip() strips
START_TAG = re.compile(rb"""<(?:[^>"']|"[^"]*"|'[^']*')*>""")  # a start tag: '>' may be in an attribute's value
LONGEST_FLOAT = len("-1.2345678901234567e-300")  # the longest text repr() gives a float64 (24 characters)


@dataclass
class _Element:
    """An element of the XML section: its local name, namespace, ``type`` attribute, byte span ``[start, end)``, where
    its content ends (its end tag's first byte; ``None``: an empty-element tag ``<a/>``), its children, its text."""

    name: str
    namespace: str
    kind: str | None
    start: int
    open_end: int
    end: int = -1
    content_end: int | None = None
    children: list[_Element] = field(default_factory=list)
    text: list[str] = field(default_factory=list)


def moved_e57(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray) -> None:
    """The E57 file ``src`` (seekable, read from its start) written to ``dst`` moved by ``R [3, 3]``, ``t [3]``:
    every scan's and image's pose composed with it, everything else kept (module docstring)."""
    crc32c = require("google_crc32c", "writing E57 files")
    signature, major, minor, offset, size, xml = _layout(src)
    text, file_offsets = _moved_xml(xml, R, t)
    pages = size // PAGE_BYTES
    logical = offset // PAGE_BYTES * PAGE_DATA_BYTES + offset % PAGE_BYTES  # the old XML's first logical byte
    last_page = (logical + max(len(xml), 1) - 1) // PAGE_DATA_BYTES
    if last_page == pages - 1 and all(o is not None and o < offset for o in file_offsets):
        first, new_offset = offset // PAGE_BYTES, offset  # written in the old one's place, from its first page on
        src.seek(first * PAGE_BYTES)
        tail = bytearray(src.read(PAGE_DATA_BYTES)[: offset % PAGE_BYTES])  # that page's bytes before the XML
    else:
        first, new_offset, tail = pages, size, bytearray()  # appended on pages of its own
    tail += text
    tail += bytes(-len(tail) % PAGE_DATA_BYTES)
    length = (first + len(tail) // PAGE_DATA_BYTES) * PAGE_BYTES
    header = HEADER.pack(signature, major, minor, length, new_offset, len(text), PAGE_BYTES)
    if first == 0:
        tail[: HEADER.size] = header
    else:
        src.seek(0)
        page = bytearray(src.read(PAGE_DATA_BYTES))
        page[: HEADER.size] = header
        dst.write(_paged(crc32c, bytes(page)))
        src.seek(PAGE_BYTES)
        left = (first - 1) * PAGE_BYTES
        while left > 0:
            chunk = src.read(min(left, COPY_BYTES))
            if not chunk:
                raise PointCloudFormatError("the E57 file is cut short (it changed while it was copied)")
            dst.write(chunk)
            left -= len(chunk)
    dst.write(_paged(crc32c, bytes(tail)))


def check_moved_e57(f: BinaryIO) -> None:
    """:class:`PointCloudFormatError` where the E57 file ``f`` (seekable, read from its start) cannot be written
    moved (:func:`moved_e57`'s refusals), before anything is registered or written; ``f`` is left at its start. The
    pose is not known yet: the identity is composed, each number written padded with zeros to the longest a float64's
    text can be (:data:`LONGEST_FLOAT` characters), so that no registration's pose takes the XML section beyond the
    reader's byte limit once this has passed it."""
    try:
        _, _, _, _, _, xml = _layout(f)
        _moved_xml(xml, np.eye(3), np.zeros(3), longest=True)
    finally:
        f.seek(0)


def other_fields(f: BinaryIO) -> list[str]:
    """What the E57 file ``f`` holds besides the points' coordinates: its scans' prototype fields other than
    ``cartesianX/Y/Z`` and ``sphericalRange/Azimuth/Elevation`` (in order, each once), and ``images`` where
    ``images2D`` holds any."""
    root = _tree(e57_format._xml_section(f))
    names: dict[str, None] = {}
    for scan in _posed(root, "data3D"):
        for points in _named(scan, root, "points"):
            for prototype in _named(points, root, "prototype"):
                names.update((c.name, None) for c in prototype.children if c.name not in COORDINATES)
    images = ["images"] if _posed(root, "images2D") else []
    return [*names, *images]


# ------------------------------------------------------------------------------------------------------ the file


def _layout(f: BinaryIO) -> tuple[bytes, int, int, int, int, bytes]:
    """The E57 file ``f``'s signature, version, XML section's physical offset, its size and the XML section's text,
    with the reader's checks of them (:func:`service.formats.e57.check_xml`)."""
    f.seek(0)
    head = f.read(HEADER.size)
    if len(head) < HEADER.size or not head.startswith(b"ASTM-E57"):
        raise PointCloudFormatError("not an E57 file: its header (48 bytes from the signature ASTM-E57) is cut short")
    signature, major, minor, _, offset, _, page = HEADER.unpack(head)
    if page != PAGE_BYTES:
        raise PointCloudFormatError(f"the E57 file's header gives a page size of {page} bytes; E57's is {PAGE_BYTES}")
    if offset < HEADER.size:
        raise PointCloudFormatError(f"the E57 file's header puts its XML section at byte {offset}, inside the header")
    size = f.seek(0, os.SEEK_END)
    if size % PAGE_BYTES:
        raise PointCloudFormatError(
            f"not a readable E57 file (it has {size} bytes, not whole pages of {PAGE_BYTES}: cut short, or bytes added)"
        )
    f.seek(0)
    xml = e57_format._xml_section(f)
    e57_format._parse_xml(xml)  # the reader's checks: DTD, encoding, limits, quaternions of the scans, ...
    return signature, major, minor, offset, size, xml


def _paged(crc32c: ModuleType, logical: bytes) -> bytes:
    """``logical`` (whole pages of data) as E57 pages: each 1,020 bytes followed by their CRC-32C, big-endian."""
    out = bytearray()
    for k in range(0, len(logical), PAGE_DATA_BYTES):
        data = logical[k : k + PAGE_DATA_BYTES]
        out += data
        out += crc32c.value(data).to_bytes(4, "big")
    return bytes(out)


# ------------------------------------------------------------------------------------------------------- the XML


def _tree(text: bytes, offsets: list[str] | None = None) -> _Element:
    """The XML section ``text``'s elements with their byte spans (expat's positions; ``text`` passed the reader's
    checks, :func:`_layout`); each ``fileOffset`` attribute's value appended to ``offsets`` where given."""
    parser = xml.parsers.expat.ParserCreate(namespace_separator=" ")  # names as "namespace-URI local-name"
    document = _Element("", "", None, 0, 0)
    stack = [document]

    def start(name: str, attributes: dict[str, str]) -> None:
        at = parser.CurrentByteIndex
        tag = START_TAG.match(text, at)
        namespace, _, local = name.rpartition(" ")
        element = _Element(local, namespace, attributes.get("type"), at, tag.end() if tag else at)
        if offsets is not None and "fileOffset" in attributes:
            offsets.append(attributes["fileOffset"])
        stack[-1].children.append(element)
        stack.append(element)

    def end(name: str) -> None:
        element = stack.pop()
        if text[element.open_end - 2 : element.open_end] == b"/>":  # <a/>: expat is past it
            element.end = element.open_end
        else:
            element.content_end = parser.CurrentByteIndex
            element.end = text.index(b">", element.content_end) + 1

    def characters(data: str) -> None:
        stack[-1].text.append(data)

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = characters
    parser.Parse(text, True)  # well formed: _layout parsed it
    return document.children[0]


def _named(parent: _Element, root: _Element, name: str) -> list[_Element]:
    """``parent``'s children named ``name`` in the root's namespace."""
    return [c for c in parent.children if c.name == name and c.namespace == root.namespace]


def _posed(root: _Element, vector: str) -> list[_Element]:
    """The Structure children of the root's ``vector`` (``data3D``, ``images2D``): the scans or images."""
    return [c for v in _named(root, root, vector) for c in v.children if c.kind == "Structure"]


def _moved_xml(text: bytes, R: np.ndarray, t: np.ndarray, longest: bool = False) -> tuple[bytes, list[int | None]]:
    """The XML section ``text`` with every scan's and image's pose composed with ``R``, ``t`` (spliced: every other
    byte kept), and the ``fileOffset`` of each binary section it names (``None``: not a decimal integer).
    ``longest``: each pose number padded to :data:`LONGEST_FLOAT` characters (:func:`check_moved_e57`)."""
    offsets: list[str] = []
    root = _tree(text, offsets)
    edits: list[tuple[int, int, bytes]] = []
    matrix = np.asarray(R, dtype=np.float64)
    turn = Rotation.from_matrix(matrix)  # once: each scan's or image's rotation is composed with it
    for vector in ELEMENTS:
        if len(_named(root, root, vector)) > 1:
            raise PointCloudFormatError(f"the E57 file's XML section has more than one {vector} element")
        for number, owner in enumerate(_posed(root, vector)):
            what = f"E57 {'scan' if vector == 'data3D' else 'image'} {number}"
            edits += _pose_edits(text, root, owner, what, matrix, turn, np.asarray(t, dtype=np.float64), longest)
    out, at = bytearray(), 0
    for begin, finish, piece in sorted(edits, key=lambda edit: edit[0]):  # stable: insertions keep their order
        out += text[at:begin] + piece
        at = finish
    out += text[at:]
    _check_readable(bytes(out))
    return bytes(out), [int(value) if e57_format.RECORD_COUNT.fullmatch(value) else None for value in offsets]


def _check_readable(text: bytes) -> None:
    """:class:`PointCloudFormatError` where the reader would refuse the moved XML section ``text``: the poses added
    (10 elements, about 340 bytes, each) may take it beyond :data:`service.formats.e57.MAX_XML_ELEMENTS` or
    :data:`service.formats.e57.MAX_XML_BYTES`."""
    reason = None
    if len(text) > e57_format.MAX_XML_BYTES:
        reason = f"it would have {len(text)} bytes; at most {e57_format.MAX_XML_BYTES} are read"
    else:
        try:
            e57_format._parse_xml(text)
        except PointCloudFormatError as exc:
            reason = str(exc).removeprefix("the E57 file's XML section ")
    if reason is not None:
        raise PointCloudFormatError(
            f"the E57 file's XML section with its poses composed would not be read back: {reason}"
        )


def _pose_edits(
    text: bytes,
    root: _Element,
    owner: _Element,
    what: str,
    R: np.ndarray,
    turn: Rotation,
    t: np.ndarray,
    longest: bool = False,
) -> list[tuple[int, int, bytes]]:
    """The splices that give ``owner`` (a scan or image) its pose composed with ``R [3, 3]``, ``t [3]`` (``turn``:
    ``R``); ``longest``: each number padded to :data:`LONGEST_FLOAT` characters."""
    pose = _unique(owner, root, "pose", what)
    rotation = _unique(pose, root, "rotation", what) if _open(pose) else None
    translation = _unique(pose, root, "translation", what) if _open(pose) else None
    q = _numbers(rotation, root, ROTATION, what) if _open(rotation) else np.array([1.0, 0.0, 0.0, 0.0])  # [4] w x y z
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) <= e57_format.MAX_QUATERNION_NORM_ERROR:
        raise PointCloudFormatError(
            f"{what}'s pose has a rotation quaternion of norm {norm:.9g}; the standard's is a unit quaternion (within "
            f"{e57_format.MAX_QUATERNION_NORM_ERROR:g} here)"
        )
    turned = turn * Rotation.from_quat(q[[1, 2, 3, 0]] / norm)  # R @ R_i (scipy's quaternions: x, y, z, w)
    x, y, z, w = turned.as_quat(canonical=True)  # w >= 0
    offset = _numbers(translation, root, TRANSLATION, what) if _open(translation) else np.zeros(3)  # [3] t_i
    values = {
        "rotation": dict(zip(ROTATION, np.array([w, x, y, z]) / np.linalg.norm([w, x, y, z]), strict=True)),
        "translation": dict(zip(TRANSLATION, R @ offset + t, strict=True)),
    }
    prefix = _prefix(text, owner)
    if not _open(pose):
        return _put(text, owner, pose, _structure(prefix, "pose", values, longest))
    edits: list[tuple[int, int, bytes]] = []
    for name, child in (("rotation", rotation), ("translation", translation)):
        if not _open(child):
            edits += _put(text, pose, child, _structure(prefix, name, values[name], longest))
            continue
        for axis, value in values[name].items():
            edits += _put(text, child, _unique(child, root, axis, what), _structure(prefix, axis, value, longest))
    return edits


def _open(element: _Element | None) -> bool:
    """Whether ``element`` is a Structure with an end tag (children are spliced into it, not it replaced)."""
    return element is not None and element.kind == "Structure" and element.content_end is not None


def _unique(parent: _Element | None, root: _Element, name: str, what: str) -> _Element | None:
    """``parent``'s child ``name`` (the root's namespace), ``None`` where it has none; refused where it has two, or
    one of that local name in another namespace (the e57 library reads a scan's first child of the local name
    ``pose``, whatever its namespace: that one would be read as the pose, not the one composed)."""
    found = [c for c in parent.children if c.name == name] if parent is not None else []
    foreign = next((c for c in found if c.namespace != root.namespace), None)
    if foreign is not None:
        raise PointCloudFormatError(
            f"{what}'s pose cannot be rewritten: the E57 file's XML section gives it a {name!r} element of another "
            f"namespace ({foreign.namespace[:80]!r}), and the e57 reader reads the first {name!r}, whatever its "
            "namespace"
        )
    if len(found) > 1:
        raise PointCloudFormatError(
            f"{what}'s pose cannot be rewritten: the E57 file's XML section gives it {len(found)} {name!r} elements"
        )
    return found[0] if found else None


def _numbers(parent: _Element, root: _Element, axes: tuple[str, ...], what: str) -> np.ndarray:
    """The values of ``parent``'s children ``axes`` (a missing or empty one is 0, as the reader reads it)."""
    values = []
    for axis in axes:
        leaf = _unique(parent, root, axis, what)
        word = "".join(leaf.text).strip() if leaf is not None else ""
        try:
            value = float(word or 0)
        except ValueError:
            value = float("nan")
        if not np.isfinite(value):
            raise PointCloudFormatError(
                f"{what}'s pose cannot be rewritten: its {parent.name} {axis} is {word[:40]!r}, not a finite number"
            )
        values.append(value)
    return np.array(values)


def _prefix(text: bytes, element: _Element) -> str:
    """The namespace prefix (``e57:`` or none) of ``element``'s tag, for the elements written into it."""
    qname = re.match(rb"<([^\s/>]+)", text[element.start : element.open_end]).group(1).decode("utf-8")
    return qname.rpartition(":")[0] + ":" if ":" in qname else ""


def _structure(prefix: str, name: str, value: float | dict, longest: bool = False) -> bytes:
    """The element ``name``: a Float of ``value``'s shortest float64 text (``longest``: padded with zeros to
    :data:`LONGEST_FLOAT` characters, the same number), or a Structure of ``value``'s items."""
    if isinstance(value, dict):
        inner = "".join(_structure(prefix, key, item, longest).decode("utf-8") for key, item in value.items())
        return f'<{prefix}{name} type="Structure">{inner}</{prefix}{name}>'.encode()
    number = repr(float(value))
    if longest:
        mantissa, e, exponent = number.partition("e")  # "1e-05": no point
        mantissa += "" if "." in mantissa else "."
        number = mantissa + "0" * (LONGEST_FLOAT - len(mantissa) - len(e) - len(exponent)) + e + exponent
    return f'<{prefix}{name} type="Float">{number}</{prefix}{name}>'.encode()


def _put(text: bytes, parent: _Element, old: _Element | None, piece: bytes) -> list[tuple[int, int, bytes]]:
    """The splice that puts ``piece`` in place of ``old``, or where ``parent`` has none, last among its children
    (indented as its other children where its end tag is on a line of its own)."""
    if old is not None:
        return [(old.start, old.end, piece)]
    if parent.content_end is None:  # <a .../>: opened, given the piece, closed
        opening = text[parent.start : parent.open_end][:-2].rstrip()
        qname = re.match(rb"<([^\s/>]+)", opening).group(1)
        return [(parent.start, parent.end, opening + b">" + piece + b"</" + qname + b">")]
    start = parent.content_end  # the white space before the end tag, found without copying the text before it
    while start > 0 and text[start - 1] in WHITESPACE:
        start -= 1
    space = text[start : parent.content_end]
    if b"\n" in space:
        indent = space.rpartition(b"\n")[2]
        piece = b"  " + piece + b"\n" + indent
    return [(parent.content_end, parent.content_end, piece)]
