"""The source file itself, its points moved by a pose: ``p' = R @ p + t`` in float64, every other field kept.

Written where the output's format is the source's (:data:`KEPT_FORMATS`; the source's format from its content, the
output's from its extension): PLY, PCD, LAS/LAZ, XYZ/CSV/TXT (any of ``.txt``, ``.xyz``, ``.csv``), PTS, PTX, NPY,
NPZ and E57.
Normals (PLY ``nx ny nz``, PCD ``normal_x normal_y normal_z``, where all three are floats; text columns a header names
so) are rotated, not translated; every other per-point field is copied as the file holds it.

- PLY (``plyfile`` parses the header): binary files are copied a block of rows at a time, the vertex rows' x, y, z
  and normals replaced, the bytes of every other element (faces, edges, ...) and the header copied as they are; ASCII
  files' lines are copied a chunk at a time, the vertex rows' x, y, z moved and normals rotated as the text formats'
  are (:func:`service.formats.moved_text.moved_rows`: the decimals the source's coordinates carry).
- PCD (``pypcd4`` parses and composes the header): binary records are copied a block at a time, ``binary_compressed``
  read and written whole by ``pypcd4``, ASCII rows moved as text rows are, a chunk of lines at a time (as ASCII PLY's;
  not ``pypcd4``'s ``%.10f``, which loses small values and colours packed in a float). The header is composed by
  ``pypcd4`` (``VERSION 0.7``, comments dropped); ``VIEWPOINT``, the sensor's pose in the file's frame, is moved with
  the points.
- LAS/LAZ (``laspy``, ``lazrs``): the points, VLRs (a CRS among them), EVLRs and point format kept; x, y, z at the
  file's scales, its offsets kept where the moved coordinates fit its 32-bit integers, else the moved bounds' centre
  rounded to a whole unit; ``laspy`` writes the header's bounds. ``.las`` or ``.laz`` from the output's extension.
- XYZ/CSV/TXT, PTS and PTX (:mod:`service.formats.moved_text`): every line copied as it is but for the numbers that
  place a point: a row's x, y, z (normals) written with the decimals the source's coordinates carry, a PTX scan's
  header composed with the pose (its rows, in the scanner's frame, copied).
- E57 (:mod:`service.formats.moved_e57`): every scan's and image's pose composed with the pose in the XML section;
  the points, images and every other binary section copied as they are, a chunk of pages at a time.
- NPY and NPZ (:mod:`service.formats.moved_arrays`): the array's shape, order and dtype kept (float32 widened for
  map coordinates, integers written as float64), its first three columns or fields x, y, z moved, a structured
  array's normals and an archive's ``normals`` array rotated, every other column, field and archive member copied.

x, y, z stored as 4-byte floats become 8-byte ones where a moved coordinate is beyond ``FLOAT32_EXACT_ENOUGH`` (as
:func:`service.formats.write.write_cloud` writes them). The output is written to a temporary file beside it and
renamed into place, so an output naming the source is written from the whole source. The source may be a path or
an open, seekable binary file (an HTTP upload, spooled): it is read from its start and left open.
"""

from __future__ import annotations

import io
import itertools
import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, BinaryIO

import numpy as np
from scipy.spatial.transform import Rotation

from service.cancellation import stop_if_cancelled
from service.formats import pcd as pcd_format
from service.formats import ply as ply_format
from service.formats import text as text_format
from service.formats.checks import BLOCK_BYTES, MAX_ROW_BYTES
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError
from service.formats.moved_arrays import check_moved_npy, check_moved_npz, moved_npy, moved_npz
from service.formats.moved_arrays import other_fields as array_fields
from service.formats.moved_e57 import check_moved_e57, moved_e57
from service.formats.moved_e57 import other_fields as e57_fields
from service.formats.moved_text import moved_pts, moved_ptx, moved_rows, moved_text
from service.formats.read import detect_at as detect_format
from service.formats.read import read_cloud
from service.formats.write import FLOAT32_EXACT_ENOUGH

if TYPE_CHECKING:
    from plyfile import PlyData

# source format (service.formats.detect) -> the output extensions that keep its content (the first: a name's default)
KEPT_FORMATS = {
    "ply": (".ply",),
    "pcd": (".pcd",),
    "las": (".las", ".laz"),
    "text": (".txt", ".xyz", ".csv"),
    "pts": (".pts",),
    "ptx": (".ptx",),
    "e57": (".e57",),
    "npy": (".npy",),
    "npz": (".npz",),
}
# The extensions written only from a source of their format (no writer of x, y, z alone is named by them)
OWN_FORMAT_ONLY = {".las": "las", ".laz": "las", ".pts": "pts", ".ptx": "ptx", ".e57": "e57"}
LEICA_COLUMNS = ("intensity", "red", "green", "blue")  # a PTS or PTX row's values after x, y, z
# the normals each format's rows may carry, rotated (the first triple a record holds whole, as floats): PLY's
# nx ny nz (Open3D, CloudCompare, MeshLab) or normal_x normal_y normal_z (PCL's PLY writer), PCD's normal_x ...
PCL_NORMALS = ("normal_x", "normal_y", "normal_z")
NORMALS = {"ply": (("nx", "ny", "nz"), PCL_NORMALS), "pcd": (PCL_NORMALS,)}
FORMAT_NAMES = {
    "ply": "PLY",
    "pcd": "PCD",
    "las": "LAS/LAZ",
    "e57": "E57",
    "npy": "NPY",
    "npz": "NPZ",
    "pts": "PTS",
    "ptx": "PTX",
    "text": "XYZ/CSV/TXT",
}
INT32_MAX = 2**31 - 1
_TEXT_WRITERS = {"text": moved_text, "pts": moved_pts, "ptx": moved_ptx}
_CHECKS = {"e57": check_moved_e57, "npy": check_moved_npy, "npz": check_moved_npz}  # what a header decides
Source = str | os.PathLike[str] | BinaryIO  # a path, or an open seekable binary file (read from its start, left open)


@contextmanager
def _opened(source: Source) -> Iterator[BinaryIO]:
    """``source`` at its first byte: a path opened (closed afterwards), or an open file seeked to its start."""
    if hasattr(source, "read"):
        source.seek(0)  # type: ignore[union-attr]
        yield source  # type: ignore[misc]
    else:
        with open(source, "rb") as f:  # type: ignore[arg-type]
            yield f


def source_format(path: Source) -> str | None:
    """The format of the file at ``path`` (or of an open file) as :func:`service.formats.read_cloud` finds it, from its
    first bytes; ``None`` where it cannot be opened or read as a point cloud (the reader says why)."""
    try:
        with _opened(path) as f:
            return detect_format(f)
    except (OSError, PointCloudFormatError):
        return None


def own_suffix(source: Source, kind: str, name: str) -> str:
    """The extension of the moved copy of a ``kind`` source (:data:`KEPT_FORMATS`) named ``name``: its own where it is
    one of its format's (``.las`` or ``.laz`` as named), else ``.ply``, ``.pcd``, or for LAS/LAZ ``.laz`` where its
    header marks the points compressed."""
    suffix = Path(name).suffix.lower()
    if suffix in KEPT_FORMATS[kind]:
        return suffix
    if kind != "las":
        return KEPT_FORMATS[kind][0]
    laspy = require("laspy", "reading LAS/LAZ files")
    with _opened(source) as f, laspy.open(f, closefd=False, read_evlrs=False) as reader:
        return ".laz" if reader.header.are_points_compressed else ".las"


def keeps_content(kind: str | None, out: str | os.PathLike[str]) -> bool:
    """Whether an output named ``out`` is written as the source file of format ``kind``, moved."""
    return Path(out).suffix.lower() in KEPT_FORMATS.get(kind or "", ())


def check_moved(source: Source, kind: str | None) -> None:
    """:class:`PointCloudFormatError` where the ``kind`` file ``source`` (:func:`source_format`; a path or an open
    file) cannot be written moved as itself, as far as its header decides, before anything is registered or written:
    an E57 file whose poses cannot be rewritten (:func:`service.formats.moved_e57.check_moved_e57`), an array whose
    rows would be too long written, an ``.npz`` archive whose other members are too large or cannot be opened, an
    array of 8-byte integers holding one beyond 2**53 in a column copied as float64 (its data read a block at a time:
    :func:`service.formats.moved_arrays.check_moved_npy`, ``check_moved_npz``), with the writers' own checks.
    Nothing for other formats: their writers' refusals need the data. Nothing either where the reader refuses the file
    (these checks parse what the reader parses: a truncated ``.npy`` file, an archive that is no zip file, an E57 file
    cut short): it is no writing problem, and reading the source says why, as it does for every other format.

    Raises:
        OSError: ``source`` unreadable.
    """
    check = _CHECKS.get(kind or "")
    if check is not None:
        with _opened(source) as f:
            try:
                check(f)
            except PointCloudFormatError:
                if _read_by_the_reader(f):
                    raise


def _read_by_the_reader(f: BinaryIO) -> bool:
    """Whether :func:`service.formats.read_cloud` reads the file ``f`` (from its start; left there): run only once a
    check has refused it, to tell the file the writer refuses from the file the reader refuses (its points read once
    more, on this path only)."""
    f.seek(0)
    try:
        read_cloud(f)
    except PointCloudFormatError:
        return False
    finally:
        f.seek(0)
    return True


def other_fields(path: str | os.PathLike[str], kind: str | None) -> list[str]:
    """What a file holds besides x, y, z, from its header or first row: the vertex properties and the other elements
    of a PLY file, the fields of a PCD file, the point dimensions of a LAS/LAZ file, the other columns of a text file
    (named by its header, else numbered from 1) and of a PTS or PTX file (intensity, red, green, blue), an array's
    other fields or columns and an archive's other arrays (:func:`service.formats.moved_arrays.other_fields`), an E57
    file's other point fields and its images (:func:`service.formats.moved_e57.other_fields`). Empty where the file
    cannot be read."""
    try:
        with open(path, "rb") as f:
            if kind in ("text", "pts", "ptx"):
                return _other_columns(f, kind)
            if kind in ("npy", "npz"):
                return array_fields(f, kind)
            if kind == "e57":
                return e57_fields(f)
            if kind == "ply":
                header, _ = ply_format.read_header(require("plyfile", "reading PLY files"), f)
                names = [prop.name for prop in header["vertex"].properties]
                return [n for n in names if n not in ("x", "y", "z")] + [
                    element.name for element in header.elements if element.name != "vertex"
                ]
            if kind == "pcd":
                return [
                    n
                    for n in pcd_format.read_metadata(require("pypcd4", "reading PCD files"), f).fields
                    if n not in ("x", "y", "z")
                ]
            if kind == "las":
                laspy = require("laspy", "reading LAS/LAZ files")
                with laspy.open(f, closefd=False, read_evlrs=False) as reader:
                    return [n for n in reader.header.point_format.dimension_names if n not in ("X", "Y", "Z")]
    except Exception:  # a note only: the reader has already read the file
        return []
    return []


def _other_columns(f: BinaryIO, kind: str) -> list[str]:
    """The columns of the text, PTS or PTX file ``f`` besides x, y, z, from its header line or its first row."""
    stream = io.TextIOWrapper(f, encoding="utf-8-sig", newline=None)
    if kind == "text":
        skip, separator, header, _ = text_format.layout(stream)
        if header is not None:
            xyz = text_format.xyz_columns(header, separator)
            names = text_format.header_names(header, separator)
            return [n or f"column {k + 1}" for k, n in enumerate(names) if k not in xyz]
        stream.seek(0)
        rows = (line.strip() for line in itertools.islice(stream, skip, None))
        first = next((line for line in rows if line and not line.startswith("#")), "")
        return [f"column {k + 1}" for k in range(3, len(first.split(separator)))]
    header_lines = 1 if kind == "pts" else 10  # a PTS block's count line; a PTX scan's header
    rows = (line.strip() for line in itertools.islice(stream, header_lines, None))
    first = next((line for line in rows if line), "")
    return list(LEICA_COLUMNS[: max(0, len(first.split()) - 3)])


def write_moved(
    source: Source,
    out: str | os.PathLike[str],
    rotation: np.ndarray,
    translation: np.ndarray,
    largest: float,
) -> None:
    """Write the PLY, PCD, LAS/LAZ, XYZ/CSV/TXT, PTS, PTX, NPY, NPZ or E57 file ``source`` (a path or an open file) to
    ``out`` (:func:`keeps_content`) with its points moved by ``rotation [3, 3]`` and ``translation [3]`` and its
    normals rotated, every other field and element kept; an E57 file with every scan's and image's pose composed.
    ``largest``: the largest absolute moved coordinate (the caller has moved the points it registered): beyond
    ``FLOAT32_EXACT_ENOUGH`` float32 x, y, z are written as float64.

    Raises:
        PointCloudFormatError: a source this cannot copy, or moved coordinates its LAS scale cannot hold.
        OSError: ``source`` unreadable or ``out`` unwritable.
    """
    out = Path(out)
    kind = source_format(source)
    if not keeps_content(kind, out):
        raise PointCloudFormatError(
            f"{out.name}: a {FORMAT_NAMES.get(kind or '', 'such')} source is not written as "
            f"{out.suffix!r} with its other fields"
        )
    R = np.asarray(rotation, dtype=np.float64)  # [3, 3]
    t = np.asarray(translation, dtype=np.float64)  # [3]
    widen = bool(largest > FLOAT32_EXACT_ENOUGH)
    handle, temporary = _new_file_beside(out)
    try:
        with _opened(source) as src, os.fdopen(handle, "wb") as dst:
            if kind == "ply":
                _moved_ply(src, dst, R, t, widen)
            elif kind == "pcd":
                _moved_pcd(src, dst, R, t, widen)
            elif kind == "las":
                _moved_las(src, dst, R, t, out.suffix.lower() == ".laz")
            elif kind in ("npy", "npz"):
                (moved_npy if kind == "npy" else moved_npz)(src, dst, R, t, widen)
            elif kind == "e57":
                moved_e57(src, dst, R, t)
            else:
                _TEXT_WRITERS[kind](src, dst, R, t)
        os.replace(temporary, out)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


# ------------------------------------------------------------------------------------------ records


def _widened(record: np.dtype, widen: bool) -> np.dtype:
    """``record`` with x, y, z as they are written: floats of 8 bytes or more stay, others become 8-byte floats where
    ``widen``, else 4-byte ones (integer and 2-byte coordinates too: moved, they are no longer whole numbers); byte
    order kept. ``record`` itself (its offsets, padding and titles) where no field changes."""

    def kept(field: np.dtype) -> np.dtype:
        if field.kind == "f" and (field.itemsize >= 8 or (field.itemsize == 4 and not widen)):
            return field
        return np.dtype((field.str[0] if field.str[0] in "<>" else "=") + ("f8" if widen else "f4"))

    if all(kept(record[name]) == record[name] for name in ("x", "y", "z")):
        return record
    return np.dtype([(name, kept(record[name]) if name in ("x", "y", "z") else record[name]) for name in record.names])


def _move_rows(rows: np.ndarray, written: np.ndarray, R: np.ndarray, t: np.ndarray,
               normals: tuple[tuple[str, ...], ...]) -> None:
    """``written [n]`` (records of ``rows``' fields, perhaps ``rows`` itself): x, y, z of ``rows [n]`` moved, its
    float normals rotated, every other field copied."""
    if written is not rows:
        for name in rows.dtype.names:
            written[name] = rows[name]
    xyz = np.stack([rows[a].astype(np.float64) for a in "xyz"], axis=1)  # [n, 3]
    moved = xyz @ R.T + t  # [n, 3]
    for axis, name in enumerate("xyz"):
        written[name] = moved[:, axis]
    triple = next((names for names in normals
                   if all(n in rows.dtype.names and rows.dtype[n].kind == "f" for n in names)), None)
    if triple is not None:
        turned = np.stack([rows[n].astype(np.float64) for n in triple], axis=1) @ R.T  # [n, 3]
        for axis, name in enumerate(triple):
            written[name] = turned[:, axis]


def _moved_blocks(
    src: BinaryIO,
    dst: BinaryIO,
    record: np.dtype,
    written: np.dtype,
    count: int,
    R: np.ndarray,
    t: np.ndarray,
    normals: tuple[tuple[str, ...], ...],
    what: str,
) -> None:
    """The ``count`` binary rows of ``record`` at ``src``'s position, moved, to ``dst`` as rows of ``written``: a
    block of ``BLOCK_BYTES`` at a time."""
    per_block = max(1, BLOCK_BYTES // record.itemsize)
    for begin in range(0, count, per_block):
        stop_if_cancelled()  # an aligned download past its deadline: its worker is free again
        n = min(per_block, count - begin)
        data = bytearray(n * record.itemsize)
        if src.readinto(data) != len(data):
            raise PointCloudFormatError(f"{what} cut short: fewer than {count} rows follow")
        rows = np.frombuffer(data, dtype=record)  # [n], writable: moved in place where the record is kept
        out = rows if written == record else np.empty(n, dtype=written)
        _move_rows(rows, out, R, t, normals)
        dst.write(out.tobytes())


# ---------------------------------------------------------------------------------------------- PLY


def _moved_ply(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray, widen: bool) -> None:
    plyfile = require("plyfile", "writing PLY files")
    header, body = ply_format.read_header(plyfile, src)
    vertex = header["vertex"]
    if any(isinstance(prop, plyfile.PlyListProperty) for prop in vertex.properties):
        raise InvalidPointsError("PLY vertex element with list properties")
    at = [element.name for element in header.elements].index("vertex")
    if header.text:
        _moved_ply_text(plyfile, src, dst, header, body, at, R, t, widen)
        return
    before = header.elements[:at]
    if any(isinstance(prop, plyfile.PlyListProperty) for element in before for prop in element.properties):
        raise InvalidPointsError("binary PLY whose vertex element follows an element of lists")
    record = ply_format.row_record(vertex, header.byte_order)
    written = _widened(record, widen)
    src.seek(0)
    if written == record:
        _copy(src, dst, body, "PLY header")
    else:
        dst.write(_ply_header(plyfile, header, at, written).encode("ascii") + b"\n")
        src.seek(body)
    _copy(src, dst, sum(e.count * ply_format.row_record(e, header.byte_order).itemsize for e in before), "PLY data")
    _moved_blocks(src, dst, record, written, vertex.count, R, t, NORMALS["ply"], "PLY vertex rows")
    shutil.copyfileobj(src, dst)  # the elements after the vertices, as they are


def _ply_header(plyfile: ModuleType, header: PlyData, at: int, written: np.dtype) -> str:
    """``plyfile``'s header text for ``header`` with the vertex element's x, y, z declared as ``written`` holds them."""
    vertex = header.elements[at]
    properties = [
        plyfile.PlyProperty(p.name, "double" if written[p.name].itemsize == 8 else "float")
        if p.name in ("x", "y", "z")
        else p
        for p in vertex.properties
    ]
    elements = list(header.elements)
    elements[at] = plyfile.PlyElement(vertex.name, properties, vertex.count, vertex.comments)
    return plyfile.PlyData(
        elements, text=header.text, byte_order=header.byte_order, comments=header.comments, obj_info=header.obj_info
    ).header


def _moved_ply_text(plyfile: ModuleType, src: BinaryIO, dst: BinaryIO, header: PlyData, body: int, at: int,
                    R: np.ndarray, t: np.ndarray, widen: bool) -> None:
    """ASCII PLY: the header copied (rewritten where x, y, z change type), then the body's lines, one an element's row,
    as they are but the vertex rows (``header.elements[at]``), whose x, y, z are moved and normals rotated as the text
    formats' are (:func:`service.formats.moved_text.moved_rows`): a chunk of lines at a time, so that time and memory
    stay those of reading the file (plyfile read and wrote it whole: minutes and gigabytes for a mesh of millions of
    faces)."""
    vertex = header.elements[at]
    record = ply_format.row_record(vertex, "=")
    written = _widened(record, widen)
    names = list(record.names)
    triple = next((group for group in NORMALS["ply"] if all(n in names and record[n].kind == "f" for n in group)), ())
    src.seek(0)
    if written == record:
        _copy(src, dst, body, "PLY header")
    else:
        dst.write(_ply_header(plyfile, header, at, written).encode("ascii") + b"\n")
    before = sum(element.count for element in header.elements[:at])
    moved_rows(src, dst, body, before, vertex.count, tuple(names.index(a) for a in "xyz"),
               tuple(names.index(n) for n in triple), R, t, "PLY vertex rows")


# ---------------------------------------------------------------------------------------------- PCD


def _moved_pcd(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray, widen: bool) -> None:
    pypcd4 = require("pypcd4", "writing PCD files")
    meta = pcd_format.read_metadata(pypcd4, src)  # src now at the data
    record = pcd_format.point_record(meta)
    written = _widened(record, widen)
    xyz = [name in ("x", "y", "z") for name in meta.fields]
    sizes = tuple(
        written[name].itemsize if is_xyz else size
        for name, size, is_xyz in zip(meta.fields, meta.size, xyz, strict=True)
    )
    types = tuple("F" if is_xyz else kind for kind, is_xyz in zip(meta.type, xyz, strict=True))
    encoding = pypcd4.Encoding.BINARY_COMPRESSED if meta.data == pypcd4.Encoding.BINARYSCOMPRESSED else meta.data
    moved_meta = meta.derive(size=sizes, type=types, viewpoint=_moved_viewpoint(meta.viewpoint, R, t), data=encoding)
    if meta.data == pypcd4.Encoding.BINARY:
        dst.write(moved_meta.compose_header().encode("ascii"))
        _moved_blocks(src, dst, record, written, meta.points, R, t, NORMALS["pcd"], "PCD binary data")
        return
    if meta.data == pypcd4.Encoding.ASCII:  # rows moved as text rows are, a chunk of lines at a time
        data = src.tell()
        dst.write(moved_meta.compose_header().encode("ascii"))
        first = dict(zip(meta.fields, np.cumsum((0, *meta.count)).tolist(), strict=False))  # each field's column
        triple = next((group for group in NORMALS["pcd"] if all(n in first and record[n].kind == "f" for n in group)),
                      ())
        moved_rows(src, dst, data, 0, meta.points, tuple(first[a] for a in "xyz"), tuple(first[n] for n in triple),
                   R, t, "PCD ASCII data")
        return
    rows = pypcd4.pypcd4._parse_pc_data(src, meta)
    if len(rows) != meta.points:
        raise PointCloudFormatError(f"PCD data holds {len(rows)} points; the header says {meta.points}")
    out = rows if written == record and rows.flags.writeable else np.empty(len(rows), dtype=written)
    _move_rows(rows, out, R, t, NORMALS["pcd"])
    pypcd4.PointCloud(moved_meta, out).save(dst, encoding=encoding)


def _moved_viewpoint(viewpoint: tuple[float, ...], R: np.ndarray, t: np.ndarray) -> tuple[float, ...]:
    """PCD's ``VIEWPOINT tx ty tz qw qx qy qz`` (the sensor's pose in the file's frame) moved by ``R``, ``t``."""
    origin, (qw, qx, qy, qz) = np.asarray(viewpoint[:3], dtype=np.float64), viewpoint[3:]
    turn = Rotation.from_matrix(R) * Rotation.from_quat([qx, qy, qz, qw])
    x, y, z, w = turn.as_quat(canonical=True)
    return (*(float(v) for v in R @ origin + t), float(w), float(x), float(y), float(z))


# ------------------------------------------------------------------------------------------ LAS/LAZ


def _moved_las(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray, compress: bool) -> None:
    laspy = require("laspy", "writing LAS/LAZ files")
    start = src.tell()
    try:
        with laspy.open(src, closefd=False) as reader:
            size, packed = reader.header.point_format.size, reader.header.are_points_compressed
    except Exception as exc:  # laspy's LaspyException
        raise PointCloudFormatError(f"corrupt LAS/LAZ data ({type(exc).__name__}: {exc})") from None
    if packed and size > MAX_ROW_BYTES:  # its records are read whole below; a LAZ file's size does not bound them
        raise PointCloudFormatError(
            f"LAZ points of {size} bytes each (extra bytes included): a LAZ file is decompressed whole to be moved, "
            f"so its points may take at most {MAX_ROW_BYTES} bytes each; send it as LAS")
    src.seek(start)
    try:
        las = laspy.read(src, closefd=False, laz_backend=laspy.LazBackend.Lazrs)
    except Exception as exc:  # laspy's LaspyException, what the LAZ backend raises
        raise PointCloudFormatError(f"corrupt LAS/LAZ data ({type(exc).__name__}: {exc})") from None
    moved = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1) @ R.T + t  # [N, 3]
    offsets = _las_offsets(moved, np.asarray(las.header.scales), np.asarray(las.header.offsets))
    las.header.offsets = offsets
    las.points.offsets = offsets
    for axis, name in enumerate("xyz"):
        setattr(las, name, moved[:, axis])
    if compress and not laspy.LazBackend.Lazrs.is_available():
        raise PointCloudFormatError("writing LAZ needs the 'lazrs' package: pip install 'mfgnet[formats]'")
    las.write(dst, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)


def _las_offsets(moved: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``[3]`` offsets that put ``moved [N, 3]`` within the 32-bit integers at ``scales``: ``offsets`` where they do,
    else the moved bounds' centre rounded to a whole unit (a multiple of a scale above 1)."""
    if not len(moved):
        return offsets
    low, high = moved.min(axis=0), moved.max(axis=0)  # [3]
    fits = (np.abs(low - offsets) / scales < INT32_MAX) & (np.abs(high - offsets) / scales < INT32_MAX)
    step = np.maximum(scales, 1.0)
    centred = np.round((low + high) / 2 / step) * step
    wide = (high - centred) / scales >= INT32_MAX
    if (~fits & wide).any():
        k = int(np.flatnonzero(~fits & wide)[0])
        raise PointCloudFormatError(
            f"the moved {'xyz'[k]} coordinates span {high[k] - low[k]:.6g}: more than the LAS "
            f"file's 32-bit integers hold at its scale {scales[k]:g}"
        )
    return np.where(fits, offsets, centred)


# --------------------------------------------------------------------------------------------- glue


def _copy(src: BinaryIO, dst: BinaryIO, size: int, what: str) -> None:
    """``size`` bytes from ``src`` to ``dst``."""
    left = size
    while left > 0:
        data = src.read(min(left, BLOCK_BYTES))
        if not data:
            raise PointCloudFormatError(f"{what} cut short")
        dst.write(data)
        left -= len(data)


def _new_file_beside(out: Path) -> tuple[int, Path]:
    """A new hidden file in ``out``'s folder, open for writing, with the permissions any new file gets there (0o666
    less the umask, applied by the kernel: reading the umask would set it process-wide for a moment, and a server's
    other threads create files too)."""
    while True:
        path = out.parent / f".{out.name}.{secrets.token_hex(6)}"
        try:
            return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666), path
        except FileExistsError:
            continue
