"""Which format a file holds, from its first bytes (magic numbers and headers), never from its name."""

from __future__ import annotations

import re

from service.formats.errors import PointCloudFormatError

HEAD_BYTES = 1024  # enough for every magic number and the first lines of a PCD header
MAX_HEAD_BYTES = 1 << 16  # how far comment lines may put off a PCD header's first keyword
FORMATS = ("ply", "pcd", "las", "e57", "npy", "npz", "pts", "ptx", "text")
_PCD_KEYS = (b"VERSION", b"FIELDS")
# text mesh formats whose numbers the XYZ reader would take for points: OFF's keyword (ModelNet40's files may run the
# counts on: 'OFF490 518 0'), OBJ's statements, ASCII STL's 'solid' before its facets
_OFF = re.compile(rb"(ST)?C?N?4?n?OFF(\d[\d ]*)?")
_OBJ_STATEMENTS = (b"v", b"vn", b"vt", b"o", b"g", b"f", b"mtllib", b"usemtl")


def detect(head: bytes) -> str:
    """One of :data:`FORMATS` for a file starting with ``head``, or :class:`PointCloudFormatError`.

    ``las`` covers LAZ (compressed LAS: the same ``LASF`` header). Text is UTF-8 without NUL bytes: ``ptx``
    where its first lines are two single integers (columns, rows) and a line of three numbers, ``pts`` where its
    first line is a single integer (the point count) and the next one a row of at least 3 numbers, else ``text``
    (XYZ, CSV, TXT); whether its rows are numbers is each reader's to say.
    """
    if not head:
        raise PointCloudFormatError("the file is empty (0 bytes)")
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if head.startswith(b"LASF"):
        return "las"
    if head.startswith(b"ASTM-E57"):
        return "e57"
    if head.startswith(b"ply") and head[3:4] in (b"\n", b"\r"):
        return "ply"
    if _pcd_header(head):
        return "pcd"
    if head and b"\0" not in head and _is_utf8(head):
        mesh = _text_mesh(head)
        if mesh:
            raise PointCloudFormatError(
                f"an {mesh} mesh, not a point cloud format read here: save its vertices as PLY (a mesh PLY is read as "
                "its vertices) or as XYZ rows")
        return _leica(head) or "text"
    if _utf16(head):
        raise PointCloudFormatError("text in UTF-16 (as Windows PowerShell writes it): save the file as UTF-8")
    if _single_byte_text(head):
        raise PointCloudFormatError("text that is not UTF-8 (Latin-1 or Windows-1252, as Excel may save a CSV): save "
                                    "the file as UTF-8")
    raise PointCloudFormatError(
        f"unrecognised content (starts with {head[:8]!r}): not a PLY, PCD, LAS/LAZ, E57, .npy, .npz or "
        "XYZ/CSV/TXT/PTS/PTX file"
    )


def _text_mesh(head: bytes) -> str | None:
    """``OFF``, ``OBJ`` or ``STL`` where text starts as that mesh format does (its first line that is not a ``#``
    comment), else ``None``: read as XYZ rows, their counts, face indices and vertices would all be points."""
    lines = [line.split() for line in head.splitlines() if line.strip() and not line.lstrip().startswith(b"#")]
    if not lines:
        return None
    first = lines[0]
    if _OFF.fullmatch(b" ".join(first)):
        return "OFF"
    vertex = any(line[0] == b"v" and len(line) >= 4 and _numbers(line[1:4]) for line in lines)  # v x y z
    if first[0] in _OBJ_STATEMENTS and vertex:
        return "OBJ"
    if first[0] == b"solid" and any(line[:1] == [b"facet"] for line in lines[1:]):
        return "STL"
    return None


def _leica(head: bytes) -> str | None:
    """``ptx`` or ``pts`` for text starting as Leica's ASCII formats do, else ``None``."""
    lines = [line.split() for line in head.splitlines()[:3]]
    if len(lines) < 2 or len(lines[0]) != 1 or not lines[0][0].isdigit():
        return None
    if len(lines[1]) == 1 and lines[1][0].isdigit() and len(lines) == 3 and len(lines[2]) == 3:
        return "ptx"
    return "pts" if len(lines[1]) >= 3 and _numbers(lines[1]) else None


def _numbers(tokens: list[bytes]) -> bool:
    try:
        [float(token) for token in tokens]
    except ValueError:
        return False
    return True


def _utf16(head: bytes) -> bool:
    """``head`` starts with a UTF-16 byte-order mark, or reads as ASCII text in UTF-16 (every other byte NUL)."""
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        return True
    pairs = head[: len(head) // 2 * 2]
    return len(pairs) >= 8 and any(pairs[k::2].count(0) == len(pairs) // 2 and pairs[1 - k::2].isascii()
                                   and 0 not in pairs[1 - k::2] for k in (0, 1))


def only_comments(head: bytes) -> bool:
    """``head`` holds nothing but ``#`` comment lines and blank ones: whether it is a PCD header or text comes later."""
    return all(not line.strip() or line.lstrip().startswith(b"#") for line in head.splitlines())


def _pcd_header(head: bytes) -> bool:
    """The first line that is not a ``#`` comment starts with a PCD header keyword."""
    for line in head.splitlines():
        line = line.strip()
        if line and not line.startswith(b"#"):
            return line.split()[0].upper() in _PCD_KEYS
    return False


def _single_byte_text(head: bytes) -> bool:
    """Text in a single-byte code page: no NUL, and every byte printable in Windows-1252 or a line break or tab, with
    at least nine in ten of them ASCII (a header's accented names, not binary data)."""
    if b"\0" in head or sum(byte < 128 for byte in head) < 0.9 * len(head):
        return False
    try:
        text = head.decode("cp1252")
    except UnicodeDecodeError:
        return False
    return all(c.isprintable() or c in "\r\n\t" for c in text)


def _is_utf8(head: bytes) -> bool:
    """UTF-8 text, allowing a multi-byte character cut at the end of ``head``."""
    for cut in range(4):
        try:
            head[: len(head) - cut].decode("utf-8")
            return True
        except UnicodeDecodeError:
            continue
    return False
