"""``.npy`` and ``.npz`` files moved by a pose (:func:`service.formats.moved.write_moved`): the user's array, its
shape, order and other columns kept.

- ``.npy``: the points (:func:`service.formats.arrays.read_npy`'s: the first three columns of an ``[N, C]`` or
  ``[1, N, C]`` array, or the fields x, y, z) become ``R @ p + t`` in float64, stored in the array's dtype; the
  fields ``nx ny nz`` or ``normal_x normal_y normal_z`` of a structured array (all three floats) are rotated; every
  other column and field is copied as it was (a plain array's columns after the third have no names: copied). The
  header is copied as it was where the dtype is kept, else composed by numpy. Rows are read and written a block of
  ``BLOCK_BYTES`` at a time; a Fortran-order array's x, y, z columns are held whole (they follow one another), the
  rest is streamed.
- The dtype: float64 is kept; float32 is kept unless a moved coordinate is beyond ``FLOAT32_EXACT_ENOUGH``, when the
  coordinates become float64 (a plain array: the whole array, each other value exactly as it was); a plain array of
  2-byte floats becomes float32 (float64 beyond it), one of integers float64 (an 8-byte integer beyond 2**53, which
  float64 would round, is refused, and so is a plain array whose rows would be longer than ``MAX_WRITTEN_ROW_BYTES``
  as float64, whether or not the pose widens them: only the pose tells, and the check before registering refuses
  what the writer refuses). A structured
  array's x, y, z fields are written as a PLY file's are (8-byte floats kept, 4-byte ones kept or widened, others
  4-byte floats, 8-byte ones beyond it; ``np.longdouble`` ones kept); its other fields keep their types, and where
  x, y, z keep theirs the dtype is the file's own (its padding, offsets and titles).
- ``.npz``: every member copied as it was, in its place, with its name, date, attributes (and the system that made
  them) and compression (stored or deflated), the archive's comment too; the member
  :func:`service.formats.arrays.read_npz` reads (``points``, else ``positions``, else the only array) moved as an
  ``.npy`` file, and a plain float ``normals`` array of its rows and 3 columns (Open3D's ``o3d.t.io`` layout, or
  ours) rotated; of two members of one name, the last (numpy's) is the one moved or rotated, the other one of those
  copied. Members are decompressed and compressed a block at a time; those not moved may expand to at most
  ``OTHER_BYTES_PER_POINT`` per point of the cloud (plus ``OTHER_BYTES_EXTRA``), so that a small archive cannot ask
  for gigabytes of work.

:func:`check_moved_npy` and :func:`check_moved_npz` refuse, before anything is registered, what the header (an
archive's directory and its members' headers) decides, with the writer's own checks: rows too long written, other
members too large, a member zipfile cannot open. A plain array of 8-byte integers of more than three columns is the one
whose data they read (a block of ``BLOCK_BYTES`` at a time, as the writer reads it): a value beyond 2**53 in a column
the writer copies as float64 is refused by them with the writer's words.
"""

from __future__ import annotations

import shutil
import zipfile
from typing import BinaryIO, NamedTuple

import numpy as np

from service.cancellation import stop_if_cancelled
from service.formats.arrays import cloud_member, npy_layout, opened_archive
from service.formats.checks import BLOCK_BYTES, MAX_ROW_BYTES
from service.formats.errors import PointCloudFormatError

NORMAL_FIELDS = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))  # a structured array's, rotated
NORMALS_MEMBER = "normals.npy"  # an .npz array of the cloud's rows and 3 float columns, rotated
OTHER_BYTES_PER_POINT = MAX_ROW_BYTES  # what an .npz's members not moved may expand to, per point of its cloud ...
OTHER_BYTES_EXTRA = 1 << 20  # ... and this much more (small arrays: a pose, a name, a grid's size)
EXACT_INTEGERS = 2**53  # the largest integers float64 holds exactly
MAX_WRITTEN_ROW_BYTES = 2 * MAX_ROW_BYTES  # a plain array's rows as float64 (integers; floats widened): at most this


def moved_npy(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray, widen: bool) -> None:
    """The ``.npy`` file ``src`` (at its start) moved into ``dst`` (module docstring); ``widen``: a moved coordinate
    is beyond ``FLOAT32_EXACT_ENOUGH``."""
    _moved_array(src, dst, R, t, widen)


def moved_npz(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray, widen: bool) -> None:
    """The ``.npz`` archive ``src`` (at its start) moved into ``dst``: its cloud member moved, a ``normals`` member
    rotated, every other member copied (module docstring)."""
    with opened_archive(src) as archive:
        member, normals = _archive_plan(archive)
        with zipfile.ZipFile(dst, "w", allowZip64=True) as out:
            out.comment = archive.comment
            for info in archive.infolist():
                copy = zipfile.ZipInfo(info.filename, info.date_time)
                copy.compress_type, copy.create_system, copy.external_attr, copy.comment = (
                    info.compress_type,
                    info.create_system,  # the system the attributes are read by (MS-DOS, Unix)
                    info.external_attr,
                    info.comment,
                )
                copy.file_size = info.file_size  # zipfile's ZIP64 choice; a moved member grows at most 8-fold
                if info.is_dir():
                    out.writestr(copy, b"")
                    continue
                wider = info is member and info.file_size * 8 > zipfile.ZIP64_LIMIT
                with archive.open(info) as stream, out.open(copy, "w", force_zip64=wider) as written:
                    if info is member:
                        _moved_array(stream, written, R, t, widen, info.file_size)
                    elif info is normals:
                        _moved_array(stream, written, R, np.zeros(3), False, info.file_size, rotate=True)
                    else:
                        shutil.copyfileobj(stream, written, BLOCK_BYTES)


def check_moved_npy(f: BinaryIO) -> None:
    """:class:`PointCloudFormatError` where the ``.npy`` file ``f`` (seekable, read from its start) cannot be written
    moved as far as its header decides (:func:`moved_npy`'s refusals that need no data: :func:`_array_plan`'s), and an
    8-byte integer beyond ``EXACT_INTEGERS`` in a column copied as float64 (:func:`_check_integers`: the data of such
    an array alone is read), before anything is registered or written; ``f`` is left at its start."""
    try:
        _check_integers(f, _array_plan(f, False))  # its refusals are those of x, y, z widened or not
    finally:
        f.seek(0)


def check_moved_npz(f: BinaryIO) -> None:
    """:class:`PointCloudFormatError` where the ``.npz`` archive ``f`` (seekable, read from its start) cannot be
    written moved as far as its directory and its members' headers decide (:func:`_archive_plan`, which
    :func:`moved_npz` runs first), and its cloud member's 8-byte integers (:func:`_check_integers`), before anything
    is registered or written; ``f`` is left at its start."""
    try:
        with opened_archive(f) as archive:
            member, _ = _archive_plan(archive)
            with archive.open(member) as stream:
                _check_integers(stream, _array_plan(stream, False, member.file_size))
    finally:
        f.seek(0)


def other_fields(f: BinaryIO, kind: str) -> list[str]:
    """What an ``.npy`` file (``kind`` ``npy``) or an ``.npz`` archive (``npz``) holds besides x, y, z: a structured
    array's other fields, a plain array's other columns (``column 4``, ...), an archive's other arrays."""
    if kind == "npy":
        return _other_columns(f, None)
    with opened_archive(f) as archive:
        member = cloud_member(archive)
        with archive.open(member) as stream:
            fields = _other_columns(stream, archive.getinfo(member).file_size)
        return fields + [name.removesuffix(".npy") for name in archive.namelist() if name != member]


def _other_columns(f: BinaryIO, size: int | None) -> list[str]:
    shape, _, dtype, _ = npy_layout(f, None, size)
    if dtype.names is not None:
        return [name for name in dtype.names if name not in ("x", "y", "z")]
    return [f"column {k + 1}" for k in range(3, shape[-1])]


def _are_normals(archive: zipfile.ZipFile, rows: int) -> bool:
    """Whether ``archive`` holds a ``normals`` member of ``rows`` rows of 3 floats."""
    if NORMALS_MEMBER not in archive.namelist():
        return False
    try:
        with archive.open(NORMALS_MEMBER) as stream:
            shape, _, dtype, count = npy_layout(stream, None, archive.getinfo(NORMALS_MEMBER).file_size)
    except PointCloudFormatError:  # not an array of points: copied as it is
        return False
    return dtype.names is None and dtype.kind == "f" and count == rows and shape[-1] == 3


def _archive_plan(archive: zipfile.ZipFile) -> tuple[zipfile.ZipInfo, zipfile.ZipInfo | None]:
    """The member of ``archive`` moved (the cloud: of two of one name, the last, as numpy reads) and the ``normals``
    member rotated (``None``: none), with the refusals that the directory and these members' headers decide: the
    cloud member's (:func:`_array_plan`, x, y, z not widened), the other members expanding beyond
    ``OTHER_BYTES_PER_POINT`` per point, and a member zipfile cannot open (encrypted, a compression it lacks, a
    local header that is not the directory's). No member's data is read."""
    member = archive.getinfo(cloud_member(archive))
    with archive.open(member) as stream:
        rows = _array_plan(stream, False, member.file_size).rows
    normals = archive.getinfo(NORMALS_MEMBER) if _are_normals(archive, rows) else None
    normals = None if normals is member else normals
    others = sum(info.file_size for info in archive.infolist() if info is not member and info is not normals)
    allowed = rows * OTHER_BYTES_PER_POINT + OTHER_BYTES_EXTRA
    if others > allowed:
        raise PointCloudFormatError(
            f".npz archive whose other arrays expand to {others} bytes: at most {allowed} are copied "
            f"({OTHER_BYTES_PER_POINT} bytes per point of its {rows}, and {OTHER_BYTES_EXTRA} more)"
        )
    for info in archive.infolist():
        if info.is_dir():  # a folder's entry is written anew, never opened
            continue
        if info.flag_bits & 0x1:  # zipfile's own test: it asks for a password
            raise PointCloudFormatError(f".npz member {info.filename!r} is encrypted: it cannot be read or copied")
        try:
            archive.open(info).close()  # the local header read and a decompressor picked: no data
        except NotImplementedError as exc:  # a compression this Python's zipfile lacks
            raise PointCloudFormatError(f".npz member {info.filename!r} cannot be read or copied: {exc}") from None
    return member, normals


# ------------------------------------------------------------------------------------------- arrays


class _Plan(NamedTuple):
    """An ``.npy`` array as :func:`_moved_array` writes it."""

    start: int  # where its header begins
    header: int  # the header's bytes
    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype
    rows: int
    written: np.dtype  # the dtype it is written in


def _array_plan(src: BinaryIO, widen: bool, size: int | None = None, rotate: bool = False) -> _Plan:
    """The ``.npy`` header at ``src``'s position (``size`` bytes: an archive's member; else to the file's end),
    ``src`` left at its data, as it is written (:func:`_moved_array`'s arguments), or its refusal: a plain array
    whose rows would be longer than ``MAX_WRITTEN_ROW_BYTES`` as float64 (its dtype widened, as map coordinates
    widen it: the same refusal whatever ``widen``, so that the check before registering refuses what this does)."""
    start = src.tell()
    shape, fortran, dtype, rows = npy_layout(src, None, size)
    header = src.tell() - start
    if dtype.names is not None:
        from service.formats.moved import _widened

        return _Plan(start, header, shape, fortran, dtype, rows, _widened(dtype, widen))
    written = dtype if rotate else _plain_written(dtype, widen)
    widest = dtype if rotate else _plain_written(dtype, True)
    if shape[-1] * widest.itemsize > MAX_WRITTEN_ROW_BYTES:  # 128 int8 columns would be 1 KiB a row
        raise PointCloudFormatError(
            f"rows of {shape[-1]} {dtype} values would be {shape[-1] * widest.itemsize} bytes as {widest}: "
            f"at most {MAX_WRITTEN_ROW_BYTES} are written (save the array as floats, or write another format)"
        )
    return _Plan(start, header, shape, fortran, dtype, rows, written)


def _moved_array(
    src: BinaryIO,
    dst: BinaryIO,
    R: np.ndarray,
    t: np.ndarray,
    widen: bool,
    size: int | None = None,
    rotate: bool = False,
) -> None:
    """The ``.npy`` bytes at ``src``'s position (``size`` of them: an archive's member; else to the file's end)
    moved into ``dst``; ``rotate``: the array is a plain float one of normals, rotated, its dtype kept."""
    start, header, shape, fortran, dtype, rows, written = _array_plan(src, widen, size, rotate)
    _header(src, dst, start, header, shape, fortran, dtype, written)
    if dtype.names is not None:
        from service.formats.moved import _moved_blocks

        _moved_blocks(src, dst, dtype, written, rows, R, t, NORMAL_FIELDS, ".npy records")  # the first float triple
    elif fortran:
        _moved_columns(src, dst, dtype, written, rows, shape[-1], R, t)
    else:
        _moved_rows(src, dst, dtype, written, rows, shape[-1], R, t)
    shutil.copyfileobj(src, dst, BLOCK_BYTES)  # what follows the array, as it was


def _plain_written(dtype: np.dtype, widen: bool) -> np.dtype:
    """The dtype a plain array of ``dtype`` is written in (module docstring)."""
    if dtype.kind == "f" and (dtype.itemsize >= 8 or (dtype.itemsize == 4 and not widen)):
        return dtype
    order = dtype.str[0] if dtype.str[0] in "<>" else "="
    return np.dtype(order + ("f8" if widen or dtype.kind in "iu" else "f4"))


def _header(
    src: BinaryIO,
    dst: BinaryIO,
    start: int,
    length: int,
    shape: tuple[int, ...],
    fortran: bool,
    dtype: np.dtype,
    written: np.dtype,
) -> None:
    """The ``.npy`` header: the source's ``length`` bytes from ``start`` where the dtype is kept, else numpy's."""
    if written != dtype:
        header = {"descr": np.lib.format.dtype_to_descr(written), "fortran_order": fortran, "shape": shape}
        np.lib.format.write_array_header_1_0(dst, header)
        return
    src.seek(start)
    dst.write(src.read(length))


def _moved_rows(
    src: BinaryIO,
    dst: BinaryIO,
    dtype: np.dtype,
    written: np.dtype,
    rows: int,
    columns: int,
    R: np.ndarray,
    t: np.ndarray,
) -> None:
    """The ``rows`` C-order rows of ``columns`` values at ``src``'s position, their first three moved, to ``dst``
    as ``written``: a block of ``BLOCK_BYTES`` at a time."""
    row_bytes = columns * dtype.itemsize
    per_block = max(1, BLOCK_BYTES // row_bytes)
    for begin in range(0, rows, per_block):
        n = min(per_block, rows - begin)
        block = np.frombuffer(_read(src, n * row_bytes, rows), dtype=dtype).reshape(n, columns)  # [n, C]
        out = block if written == dtype else _cast(block, written, 3)  # [n, C]
        out[:, :3] = block[:, :3].astype(np.float64) @ R.T + t
        dst.write(out.data)


def _moved_columns(
    src: BinaryIO,
    dst: BinaryIO,
    dtype: np.dtype,
    written: np.dtype,
    rows: int,
    columns: int,
    R: np.ndarray,
    t: np.ndarray,
) -> None:
    """The Fortran-order ``[rows, columns]`` values at ``src``'s position (column after column) to ``dst`` as
    ``written``: the x, y, z columns held whole and moved, the others copied a block at a time."""
    xyz = np.frombuffer(_read(src, 3 * rows * dtype.itemsize, rows), dtype=dtype).reshape(3, rows)  # [3, N]
    out = xyz if written == dtype else np.empty((3, rows), dtype=written)  # [3, N]
    per_block = max(1, BLOCK_BYTES // (3 * dtype.itemsize))
    for begin in range(0, rows, per_block):
        end = min(rows, begin + per_block)
        out[:, begin:end] = R @ xyz[:, begin:end].astype(np.float64) + t[:, None]
    dst.write(out.data)
    left = (columns - 3) * rows
    per_block = max(1, BLOCK_BYTES // dtype.itemsize)
    for begin in range(0, left, per_block):
        n = min(per_block, left - begin)
        values = np.frombuffer(_read(src, n * dtype.itemsize, rows), dtype=dtype)  # [n]
        dst.write(values.data if written == dtype else _cast(values[:, None], written, 0).data)


def _check_integers(src: BinaryIO, plan: _Plan) -> None:
    """The refusal :func:`_cast` makes while writing, made before: an 8-byte integer beyond ``EXACT_INTEGERS`` in a
    column of the plain array ``plan`` (``src`` at its data) that is copied as float64 (every column but x, y, z).
    Only such an array's data is read, a block of ``BLOCK_BYTES`` at a time (a Fortran-order array's x, y, z columns
    skipped); ``src`` is left where it stops."""
    dtype, rows, columns = plan.dtype, plan.rows, plan.shape[-1]
    if dtype.names is not None or dtype.kind not in "iu" or dtype.itemsize != 8 or columns <= 3:
        return
    if plan.fortran:
        _skip(src, 3 * rows * dtype.itemsize, rows)  # x, y, z: moved, not copied
        values, width, skip = (columns - 3) * rows, 1, 0
    else:
        values, width, skip = rows, columns, 3
    per_block = max(1, BLOCK_BYTES // (width * dtype.itemsize))
    for begin in range(0, values, per_block):
        n = min(per_block, values - begin)
        block = np.frombuffer(_read(src, n * width * dtype.itemsize, rows), dtype=dtype).reshape(n, width)  # [n, W]
        _check_exact(block, skip)


def _check_exact(values: np.ndarray, skip: int) -> None:
    """An error where ``values [n, C]``, 8-byte integers, hold one beyond ``EXACT_INTEGERS`` in a column from
    ``skip`` on (float64 would round it)."""
    if values.dtype.kind in "iu" and values.dtype.itemsize == 8 and values.shape[1] > skip:
        kept = values[:, skip:]
        if ((kept > EXACT_INTEGERS) | (kept < -EXACT_INTEGERS)).any():
            raise PointCloudFormatError(
                f"an array of {values.dtype} holds integers beyond 2**53, which float64 cannot hold exactly; its "
                "moved coordinates need floats (save the array as float64, or write another format)"
            )


def _cast(values: np.ndarray, written: np.dtype, skip: int) -> np.ndarray:
    """``values [n, C]`` as ``written``; an 8-byte integer beyond ``EXACT_INTEGERS`` in a column from ``skip`` on
    (float64 would round it) is an error (:func:`_check_exact`)."""
    _check_exact(values, skip)
    return values.astype(written)


def _skip(src: BinaryIO, size: int, rows: int) -> None:
    """``size`` bytes of ``src`` passed over (read a block at a time where ``src`` cannot seek: a deflated member),
    or a format error where fewer follow."""
    while size > 0:
        got = len(src.read(min(size, BLOCK_BYTES)))
        if not got:
            raise PointCloudFormatError(f"truncated .npy file: its {rows} rows do not follow")
        size -= got


def _read(src: BinaryIO, size: int, rows: int) -> bytearray:
    """``size`` bytes of ``src`` in a writable buffer, or a format error."""
    stop_if_cancelled()  # an aligned download past its deadline: its worker is free again
    data = bytearray(size)
    view, done = memoryview(data), 0
    while done < size:
        got = src.readinto(view[done:])
        if not got:
            raise PointCloudFormatError(f"truncated .npy file: its {rows} rows do not follow")
        done += got
    return data
