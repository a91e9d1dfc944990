"""The checks every reader applies: the point-count limit (before reading) and usable coordinates (after)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import BinaryIO

import numpy as np

from service.checks import LEAVE_NAN_ROWS_OUT, max_abs
from service.formats.errors import InvalidPointsError, PointCloudFormatError, TooManyPointsError

FLOAT32_MAX = float(np.finfo(np.float32).max)
# Most bytes per point of an array or a compressed record (16 float64 values: x, y, z and 13 more columns). It bounds
# what an .npz member or a binary_compressed PCD, whose compressed size says nothing of it, may expand to: 2,000,000
# points of 128 bytes are 256 MiB, the upload limit.
MAX_ROW_BYTES = 128
# Longest line of a text body (XYZ / CSV / TXT, ASCII PLY and PCD). numpy's text reader keeps about 32 bytes per value
# of a line, so a 256 MiB upload of one line would take several GB; a row of 4,096 values of 16 characters (PCD's
# MAX_VALUES_PER_POINT) is 64 KiB.
MAX_TEXT_LINE_BYTES = 1 << 20
BLOCK_BYTES = 1 << 22  # bodies are scanned, and binary rows wider than x, y, z read, this many bytes at a time
COUNT_BLOCK_BYTES = BLOCK_BYTES // 16  # text bodies are checked in pieces this long: counting holds ~8 bytes per byte


def check_count(count: int, max_points: int | None) -> None:
    """:class:`TooManyPointsError` when a header announces more than ``max_points`` points."""
    if max_points is not None and count > max_points:
        raise TooManyPointsError(f"has {count} points; the limit is {max_points} per cloud", count, max_points)


def check_text_lines(f: BinaryIO, what: str, rows: int = 0, values: int = 0, rows_what: str = "") -> None:
    """One pass over the text from ``f``'s position to its end, before a text reader holds a line; ``f``'s position is
    kept. :class:`PointCloudFormatError` starting with ``what`` where a line (split at ``\\n`` or ``\\r``) is longer
    than ``MAX_TEXT_LINE_BYTES``; else, starting with ``rows_what``, where one of the first ``rows`` non-blank rows
    holds other than ``values`` values split on whitespace, counted without parsing a number (so a reader may parse
    only the columns it keeps)."""
    start = f.tell()
    line_start = position = start  # where the current line began; bytes scanned so far
    too_long_at = None
    seen, wrong = 0, None  # non-blank rows checked; the error of the first row of another count
    open_values, in_value = 0, False  # values of the row the last piece ended in; whether it ended inside one
    for data in _pieces(f):  # [B] bytes
        breaks = (data == 10) | (data == 13)  # [B]
        ends = np.flatnonzero(breaks)  # [E] offsets of the line breaks in the piece
        if seen < rows and not wrong:
            gap = breaks | (data == 32) | (data == 9)  # [B] separators and line breaks
            begins = ~gap & np.concatenate(([not in_value], gap[:-1]))  # [B] the first byte of each value
            before = np.cumsum(begins, dtype=np.int32)  # [B] values begun up to each byte
            per_row = np.diff(before[ends], prepend=0)  # [E] values of each row that ends in this piece
            if len(ends):
                per_row[0] += open_values
                open_values = int(before[-1] - before[ends[-1]])
            else:
                open_values += int(before[-1])
            in_value = not gap[-1]
            seen, wrong = _check_counts(per_row[per_row > 0], seen, rows, values, rows_what)
        if len(ends):
            lengths = np.diff(ends, prepend=line_start - position - 1) - 1  # [E] each line's bytes, its break left out
            too_long = np.flatnonzero(lengths > MAX_TEXT_LINE_BYTES)  # [L] which of them are too long
            if len(too_long):
                too_long_at = position + int(ends[too_long[0]] - lengths[too_long[0]])
            line_start = position + int(ends[-1]) + 1
        position += len(data)
        if too_long_at is None and position - line_start > MAX_TEXT_LINE_BYTES:
            too_long_at = line_start
        if too_long_at is not None:
            break
    f.seek(start)
    if too_long_at is not None:
        raise PointCloudFormatError(f"{what}: a line longer than {MAX_TEXT_LINE_BYTES} bytes (from byte "
                                    f"{too_long_at}); rows of numbers are far shorter")
    if seen < rows and not wrong and open_values:  # a last row without a line break
        seen, wrong = _check_counts(np.array([open_values]), seen, rows, values, rows_what)
    if wrong:
        raise PointCloudFormatError(wrong)


def _pieces(f: BinaryIO) -> Iterator[np.ndarray]:
    """The bytes from ``f``'s position to its end as views of ``COUNT_BLOCK_BYTES``, read ``BLOCK_BYTES`` at a time
    (read a piece at a time, a fresh process's heap faulted in new pages for every piece's arrays)."""
    while block := f.read(BLOCK_BYTES):
        data = np.frombuffer(block, dtype=np.uint8)  # [BLOCK_BYTES or fewer]
        for begin in range(0, len(data), COUNT_BLOCK_BYTES):
            yield data[begin:begin + COUNT_BLOCK_BYTES]


def _check_counts(per_row: np.ndarray, seen: int, rows: int, values: int, what: str) -> tuple[int, str | None]:
    """Rows checked after ``per_row`` (values of each non-blank row, following ``seen`` rows), at most ``rows``, and
    the error of the first of them that holds other than ``values`` values, if one does."""
    per_row = per_row[:rows - seen]
    wrong = np.flatnonzero(per_row != values)
    if len(wrong):
        row = seen + int(wrong[0]) + 1
        return row, f"{what}: row {row} holds {int(per_row[wrong[0]])} values; the header declares {values} per row"
    return seen + len(per_row), None


def xyz_in_blocks(f: BinaryIO, record: np.dtype, count: int, short: str) -> np.ndarray:
    """``[N, 3]`` float64 x, y, z of the ``count`` binary rows of ``record`` at ``f``'s position, read ``BLOCK_BYTES``
    at a time so that no more than the output and one block are held: a structured ``record``'s fields ``x``, ``y``,
    ``z``, or the first three values of a plain one of shape ``(C,)``. A short read is a format error starting with
    ``short``."""
    out = np.empty((count, 3), dtype=np.float64)  # [N, 3]
    per_block = max(1, BLOCK_BYTES // record.itemsize)
    for begin in range(0, count, per_block):
        n = min(per_block, count - begin)
        data = f.read(n * record.itemsize)
        if len(data) != n * record.itemsize:
            raise PointCloudFormatError(f"{short}: {begin + len(data) // record.itemsize} of {count} rows follow")
        rows = np.frombuffer(data, dtype=record, count=n)  # [n] records, or [n, C] values
        if record.names is None:
            out[begin:begin + n] = rows[:, :3]
        else:
            for axis, name in enumerate("xyz"):
                out[begin:begin + n, axis] = rows[name]
    return out


def as_declared(column: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """``column [N]`` (float64, parsed from text) cast to its declared type; an integer field must hold integers in its
    range, as a typed parse would read them (a cast would turn NaN into a number). Floats beyond float32 become inf,
    refused later (:func:`checked`). ``what`` names the column in the error: ``"PLY vertex x"``."""
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        if not (np.isfinite(column).all() and (column == np.round(column)).all()
                and column.min(initial=info.min) >= info.min and column.max(initial=info.max) <= info.max):
            raise PointCloudFormatError(f"corrupt data: {what} values that are not {dtype} integers")
    with np.errstate(over="ignore"):
        return column.astype(dtype)


def xyz_columns(columns: list[np.ndarray]) -> np.ndarray:
    """Three coordinate columns (any numeric dtype) -> checked float64 ``[N, 3]``."""
    return checked(stacked_xyz(columns))


def stacked_xyz(columns: list[np.ndarray]) -> np.ndarray:
    """Three coordinate columns (any numeric dtype) -> a fresh float64 ``[N, 3]``, its values not yet checked."""
    for column in columns:
        if column.dtype.kind not in "fiu":
            raise InvalidPointsError(f"coordinates must be real numbers, got dtype {column.dtype}")
    xyz = np.empty((len(columns[0]), 3), dtype=np.float64)  # [N, 3]
    for axis, column in enumerate(columns):
        xyz[:, axis] = column
    return xyz


def checked(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` float64 ``[N, 3]`` if it has points, all finite and within float32's range."""
    if xyz.shape[0] == 0:
        raise InvalidPointsError("the cloud is empty")
    if np.isfinite(xyz).all() and max_abs(xyz) <= FLOAT32_MAX:
        return xyz
    bad = ~(np.abs(xyz) <= FLOAT32_MAX).all(axis=1)  # NaN compares false
    if bad.any():
        raise InvalidPointsError(
            f"{int(bad.sum())} point(s) with NaN/Inf coordinates or beyond the float32 range, "
            f"first at index {int(np.argmax(bad))}; {LEAVE_NAN_ROWS_OUT}"
        )
    return xyz
