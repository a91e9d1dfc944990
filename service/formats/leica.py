"""Leica's ASCII formats, as Cyclone (and Open3D, CloudCompare, LAStools) write them.

PTS: one or more blocks, each a line with its point count then that many rows ``x y z [intensity [r g b]]``.
Each block's count is checked against the point limit before its rows are read, and must match its rows.

PTX: one or more scans, each a header of 10 lines then ``columns * rows`` rows ``x y z intensity [r g b]``::

    columns
    rows
    st1 st2 st3       scanner position, registered
    sx1 sx2 sx3       scanner axis X, registered
    sy1 sy2 sy3       scanner axis Y, registered
    sz1 sz2 sz3       scanner axis Z, registered
    r11 r12 r13 0     4x4 transform, row-vector convention: the scan's points are in the scanner's frame and
    r21 r22 r23 0     [x' y' z' 1] = [x y z 1] @ M, i.e. p_registered = M[:3, :3].T @ p + M[3, :3]
    r31 r32 r33 0
    tr1 tr2 tr3 1

The 4x4 is applied to every point (as Cyclone's documentation says: "just apply to each point to get the
transformed coordinate"; CloudCompare and LAStools read it the same way); the four lines before it are checked
to hold three numbers each and not otherwise used. A row ``0 0 0`` (x, y and z all zero) is a direction with no
return and is left out; the point limit counts every row the headers declare, those included.

Rows are parsed by numpy's text reader (x, y and z only; further columns ignored), a block or scan at a time.
"""

from __future__ import annotations

import io
import itertools
import sys
from collections.abc import Callable
from typing import BinaryIO

import numpy as np

from service.formats.checks import check_count, check_text_lines, checked
from service.formats.errors import InvalidPointsError, PointCloudFormatError


def read_pts(f: BinaryIO, max_points: int | None) -> np.ndarray:
    return _as_text(f, "PTS file", max_points, _read_pts)


def read_ptx(f: BinaryIO, max_points: int | None) -> np.ndarray:
    return _as_text(f, "PTX file", max_points, _read_ptx)


def pts_count(f: BinaryIO) -> int:
    """The points the first block of the PTS file at ``f``'s position declares (its first line; later blocks' counts
    are checked as they are read), with :func:`read_pts`'s error for a line that is no count; no row is read."""
    line = _first_lines(f, 1)[0]
    return _integer(line, "PTS line 1", "a point count")


def ptx_count(f: BinaryIO) -> int:
    """The points (columns x rows) the first scan of the PTX file at ``f``'s position declares, with
    :func:`read_ptx`'s errors for lines that are no counts; no row is read."""
    columns, rows = _first_lines(f, 2)
    what = "PTX scan 1 (line 1) header"
    return _integer(columns, what, "the number of columns") * _integer(rows, what, "the number of rows")


def _first_lines(f: BinaryIO, count: int) -> list[str]:
    """The first ``count`` non-blank lines of the text at ``f``'s position (at most its first 64 KiB), stripped."""
    text = f.read(1 << 16).decode("utf-8-sig", errors="replace")
    lines = [line.strip() for line in text.splitlines() if line.strip()][:count]
    if len(lines) < count:
        raise PointCloudFormatError(f"fewer than {count} lines in the first 64 KiB")
    return lines


def _as_text(
    f: BinaryIO, what: str, max_points: int | None, read: Callable[[_Lines, int | None], np.ndarray]
) -> np.ndarray:
    check_text_lines(f, what)
    stream = io.TextIOWrapper(f, encoding="utf-8-sig", newline=None)
    try:
        return checked(read(_Lines(stream), max_points))
    except UnicodeDecodeError as exc:
        raise PointCloudFormatError(f"not UTF-8 text ({exc.reason} at byte {exc.start} of a block)") from None
    finally:
        stream.detach()  # leave the caller's file open


class _Lines:
    """The stream's lines, numbered from 1 as they are taken."""

    def __init__(self, stream: io.TextIOWrapper):
        self.stream = stream
        self.number = 0

    def next_nonblank(self) -> str | None:
        for line in self.stream:
            self.number += 1
            if line.strip():
                return line.strip()
        return None

    def rows(self, count: int, what: str) -> np.ndarray:
        """``[n, 3]`` float64 x, y, z of the next ``count`` lines (blank ones skipped by numpy, so counted short)."""
        if count == 0:
            return np.empty((0, 3), dtype=np.float64)
        lines = itertools.islice(self.stream, min(count, sys.maxsize))  # a count beyond it: the rows run short
        first = self.number + 1
        try:
            table = np.loadtxt(lines, dtype=np.float64, comments=None, usecols=(0, 1, 2), ndmin=2)  # [n, 3]
        except ValueError as exc:
            raise InvalidPointsError(f"{what}: not rows of at least 3 numbers from line {first} on: {exc}") from None
        self.number += count
        return table


def _read_pts(lines: _Lines, max_points: int | None) -> np.ndarray:
    blocks, total, at = [], 0, 0
    while (line := lines.next_nonblank()) is not None:
        if blocks and (len(line.split()) != 1 or not (line.isdigit() and line.isascii())):
            raise PointCloudFormatError(
                f"PTS line {at} declares {len(blocks[-1])} points; more rows follow them "
                f"(line {lines.number}: {line[:60]!r})"
            )
        at = lines.number
        count = _integer(line, f"PTS line {at}", "a point count")
        total += count
        check_count(total, max_points)
        block = lines.rows(count, f"PTS block of line {at}")
        if len(block) != count:
            raise PointCloudFormatError(f"PTS line {at} declares {count} points; {len(block)} rows follow it")
        blocks.append(block)
    if not blocks:
        raise InvalidPointsError("the cloud is empty: the PTS file has no lines")
    return np.concatenate(blocks) if len(blocks) > 1 else blocks[0]


def _read_ptx(lines: _Lines, max_points: int | None) -> np.ndarray:
    scans, total = [], 0
    while (line := lines.next_nonblank()) is not None:
        at = lines.number
        what = f"PTX scan {len(scans) + 1} (line {at})"
        columns = _integer(line, f"{what} header", "the number of columns")
        rows = _integer(_header_line(lines, what), f"{what} header", "the number of rows")
        for _ in range(4):  # the scanner's registered position and axes
            _numbers(_header_line(lines, what), 3, f"{what} header line {lines.number}")
        matrix = np.array(
            [_numbers(_header_line(lines, what), 4, f"{what} header line {lines.number}") for _ in range(4)]
        )  # [4, 4], row-vector convention
        if not np.allclose(matrix[:, 3], [0, 0, 0, 1], rtol=0, atol=1e-9):
            raise PointCloudFormatError(
                f"{what}: the 4x4 transform's last column is {matrix[:, 3].tolist()}, not 0 0 0 1: PTX puts the "
                "translation in the last row (a matrix written column by column, its translation in the last column, "
                "would be read without it)"
            )
        count = columns * rows
        total += count
        check_count(total, max_points)
        xyz = lines.rows(count, what)  # [n, 3]
        if len(xyz) != count:
            raise PointCloudFormatError(
                f"{what} declares {columns} x {rows} = {count} points; {len(xyz)} rows follow its header"
            )
        xyz = xyz[(xyz != 0).any(axis=1)]  # 0 0 0: no return
        scans.append(xyz @ matrix[:3, :3] + matrix[3, :3])
    if not scans:
        raise InvalidPointsError("the cloud is empty: the PTX file has no lines")
    return np.concatenate(scans) if len(scans) > 1 else scans[0]


def _header_line(lines: _Lines, what: str) -> str:
    line = lines.next_nonblank()
    if line is None:
        raise PointCloudFormatError(
            f"{what}: the header of 10 lines (columns, rows, scanner position and axes, "
            f"a 4x4 transform) ends at line {lines.number}"
        )
    return line


def _integer(line: str, where: str, meaning: str) -> int:
    tokens = line.split()
    if len(tokens) != 1 or not (tokens[0].isdigit() and tokens[0].isascii()):  # '²' is a digit int() refuses
        raise PointCloudFormatError(f"{where}: expected {meaning} (one integer), got {line[:60]!r}")
    return int(tokens[0])


def _numbers(line: str, count: int, where: str) -> list[float]:
    tokens = line.split()
    try:
        values = [float(token) for token in tokens]
    except ValueError:
        values = []
    if len(values) != count or not np.isfinite(values).all():
        raise PointCloudFormatError(f"{where}: expected {count} numbers, got {line[:80]!r}")
    return values
