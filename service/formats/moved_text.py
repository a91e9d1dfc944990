"""The text formats moved by a pose (:func:`service.formats.moved.write_moved`): the source's lines copied as they
are, only the numbers that place a point changed.

- XYZ/CSV/TXT: every line kept (comments, blank lines, the header line, separators, quotes, spacing, line endings)
  except that in each row the x, y, z values (the columns :mod:`service.formats.text` reads: those a header names
  ``x``, ``y``, ``z``, else the first three) are moved, and the normals a header names (``nx ny nz`` or
  ``normal_x normal_y normal_z``, any case) rotated. Without a header only the first three columns are known.
- PTS: the blocks' count lines kept, each row's first three values moved, the rest of the row kept.
- PTX: each scan's points stay in the scanner's frame and its header is composed with the pose: the registered
  scanner position moved, its axes rotated, the 4x4 (row-vector convention, :mod:`service.formats.leica`) becomes
  the pose after it; every row (the grid, ``0 0 0`` for no return) is copied as it is. The header's numbers are
  written as the shortest text that reads back as the same float64.

A moved value is written with as many decimals as the most any value of its columns (x, y, z; normals apart) carries
in the source, so that the file keeps its resolution without 17-digit noise (``1.5e-3`` counts 4 decimals), and at
least enough for :data:`MIN_SIGNIFICANT_DIGITS` significant digits of the largest coordinate (normals: at least
:data:`MIN_NORMAL_DECIMALS`), so that a file of whole numbers is not rounded to them once turned; where that is more
than :data:`FULL_PRECISION_DECIMALS` (a file of float64 values, as ``repr`` writes them) each value is its shortest
float64 text. The decimals come from a first pass over the file; rows are then moved
:data:`CHUNK_CHARS` at a time, so memory does not grow with the file.
"""

from __future__ import annotations

import io
import itertools
import operator
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, BinaryIO, Protocol

import numpy as np

from service.cancellation import stop_if_cancelled
from service.formats.errors import PointCloudFormatError
from service.formats.text import header_names, layout, xyz_columns

CHUNK_CHARS = 1 << 20  # lines are moved about this many characters at a time
PTX_BLOCK_ROWS = 1 << 16  # a PTX scan's rows are copied this many at a time
FULL_PRECISION_DECIMALS = 15  # more decimals than this in the source: each value as its shortest float64 text
# At least this many significant digits of the largest coordinate: a file of whole numbers (a hand-made cloud in
# metres) is not rounded to whole metres once turned; a scanner's file carries more than this already.
MIN_SIGNIFICANT_DIGITS = 4
MIN_NORMAL_DECIMALS = 6  # rotated normals: unit vectors written as whole numbers would point elsewhere
TEXT_NORMALS = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
UTF8_BOM = b"\xef\xbb\xbf"
_WHITESPACE = re.compile(r"(\s+)")
_CORE = re.compile(r'^(\s*"?)(.*?)("?\s*)$', re.DOTALL)  # a field's spacing and quotes around its value


def moved_text(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray) -> None:
    """XYZ/CSV/TXT ``src`` to ``dst``, its x, y, z moved by ``R [3, 3]``, ``t [3]`` and its named normals rotated."""
    with _text(src) as probe:
        skip, separator, header, _ = layout(probe)
    names = header_names(header, separator) if header is not None else []
    xyz = xyz_columns(header, separator)
    normals = next((tuple(names.index(n) for n in group) for group in TEXT_NORMALS if set(group) <= set(names)), ())

    _rewrite(src, dst, lambda: _TextRows(skip), separator, xyz, normals, R, t, "text")


def moved_rows(src: BinaryIO, dst: BinaryIO, start: int, before: int, count: int, xyz: tuple[int, ...],
               normals: tuple[int, ...], R: np.ndarray, t: np.ndarray, what: str) -> None:
    """``src``'s lines from byte ``start`` on to ``dst``: after ``before`` lines that are not blank, ``count`` rows of
    whitespace-separated values whose columns ``xyz`` are moved by ``R [3, 3]``, ``t [3]`` and ``normals`` rotated,
    every other line and character as it is (an ASCII PLY body: the vertex rows among the other elements' lines)."""
    _rewrite(src, dst, lambda: _CountedRows(before, count, what), None, xyz, normals, R, t, what, start)


def moved_pts(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray) -> None:
    """PTS ``src`` to ``dst``: every block's rows moved by ``R [3, 3]``, ``t [3]``, their other values kept."""
    _rewrite(src, dst, _PtsRows, None, (0, 1, 2), (), R, t, "PTS")


def moved_ptx(src: BinaryIO, dst: BinaryIO, R: np.ndarray, t: np.ndarray) -> None:
    """PTX ``src`` to ``dst``: every scan's header composed with ``R [3, 3]``, ``t [3]`` (its points, in the scanner's
    frame, are registered by the header), its rows copied."""
    with _text(src) as lines, _text_out(src, dst) as out:
        number, scan = 0, 0

        def header_line() -> str:
            nonlocal number
            for line in lines:
                number += 1
                if line.strip():
                    return line
                out.write(line)
            raise PointCloudFormatError(f"PTX scan {scan}: its header of 10 lines ends at line {number}")

        while True:
            first = next(lines, None)
            if first is None:
                return
            number += 1
            out.write(first)
            if not first.strip():
                continue
            scan += 1
            columns = _count(first, number)
            rows_line = header_line()
            out.write(rows_line)
            count = columns * _count(rows_line, number)
            position = header_line()  # the scanner's registered position, then its axes
            out.write(_replaced(position, _values(position, 3, number) @ R.T + t, repr))
            for _ in range(3):
                axis = header_line()
                out.write(_replaced(axis, _values(axis, 3, number) @ R.T, repr))
            matrix = [header_line() for _ in range(4)]  # [x' y' z' 1] = [x y z 1] @ M
            M = np.array([_values(line, 4, number) for line in matrix])  # [4, 4]
            M[:3, :3] = M[:3, :3] @ R.T  # p' = R (M3^T p + m) + t = (M3 R^T)^T p + (R m + t)
            M[3, :3] = R @ M[3, :3] + t
            for line, row in zip(matrix, M, strict=True):
                out.write(_replaced(line, row[:3], repr))
            copied = 0
            while copied < count and (rows := list(itertools.islice(lines, min(count - copied, PTX_BLOCK_ROWS)))):
                out.writelines(rows)
                copied += len(rows)
            if copied != count:
                raise PointCloudFormatError(f"PTX scan {scan}: {count} rows declared, {copied} follow its header")
            number += count


# ------------------------------------------------------------------------------------------ rows


def _rewrite(
    src: BinaryIO,
    dst: BinaryIO,
    layout: Callable[[], _Layout],
    separator: str | None,
    xyz: tuple[int, ...],
    normals: tuple[int, ...],
    R: np.ndarray,
    t: np.ndarray,
    what: str,
    start: int = 0,
) -> None:
    """``src``'s lines (from byte ``start``) to ``dst``: the rows ``layout`` finds with the values of columns ``xyz``
    moved and those of ``normals`` rotated, every other line and character as it is."""
    rows = _Rows(separator, (*xyz, *normals), what)
    with _text(src, start) as lines:
        decimals = np.zeros(len(rows.columns), dtype=np.int64)  # [C] the most any value of each column carries
        largest = 0.0  # the largest |x|, |y| or |z|
        for _, tokens in _pieces(lines, layout(), rows, values_only=True):
            if tokens is not None:
                decimals = np.maximum(decimals, _decimals(tokens))
                largest = max(largest, _largest(tokens[:, : len(xyz)], what))
    written = [_number_format(max(int(decimals[: len(xyz)].max()), _significant_decimals(largest)))] * 3
    if normals:
        written += [_number_format(max(int(decimals[len(xyz) :].max()), MIN_NORMAL_DECIMALS))] * 3
    with _text(src, start) as lines, _text_out(src, dst) as out:
        for split, tokens in _pieces(lines, layout(), rows):
            if tokens is None:
                out.writelines(split)
                continue
            try:
                values = tokens.astype(np.float64)  # [n, C]
            except ValueError as exc:
                raise PointCloudFormatError(f"{what}: a row changed since it was read ({exc})") from None
            values[:, :3] = values[:, :3] @ R.T + t  # [n, 3] x, y, z moved
            if normals:
                values[:, 3:] = values[:, 3:] @ R.T  # [n, 3] normals rotated
            out.write(rows.joined(split, [fmt(column) for fmt, column in zip(written, values.T, strict=True)]))


def _pieces(
    lines: io.TextIOWrapper, layout: _Layout, rows: _Rows, values_only: bool = False
) -> Iterator[tuple[Any, np.ndarray | None]]:
    """The lines in pieces, in order: ``(lines, None)`` for lines copied as they are, ``(split, tokens)`` for rows
    (:meth:`_Rows.split`; ``split`` may be ``None`` where ``values_only``), about :data:`CHUNK_CHARS` characters at a
    time."""
    number = 0  # lines taken
    while chunk := lines.readlines(CHUNK_CHARS):
        stop_if_cancelled()  # an aligned download past its deadline: its worker is free again
        first, number = number + 1, number + len(chunk)
        if layout.rows_ahead(first, len(chunk)) and (bare := rows.bare(chunk, values_only)) is not None:
            layout.took(len(chunk))
            yield bare
            continue
        numbered = [(first + k, line, layout.is_row(first + k, line)) for k, line in enumerate(chunk)]
        for is_row, group in itertools.groupby(numbered, key=operator.itemgetter(2)):
            run = list(group)
            yield rows.split(run) if is_row else ([line for _, line, _ in run], None)
    layout.end()


class _Layout(Protocol):
    """Which lines of a file are rows, as the format's reader finds them (lines numbered from 1)."""

    def rows_ahead(self, first: int, count: int) -> bool:
        """Whether the ``count`` lines from line ``first`` on may all be rows (then :meth:`took` or :meth:`is_row`)."""

    def took(self, count: int) -> None:
        """``count`` rows were taken as rows."""

    def is_row(self, number: int, line: str) -> bool:
        """Whether line ``number`` is a row; a :class:`PointCloudFormatError` where the format allows no such line."""

    def end(self) -> None:
        """The file ended: a :class:`PointCloudFormatError` where rows are missing."""


class _TextRows:
    """XYZ/CSV/TXT: after the first ``skip`` lines, every line that is not blank nor a ``#`` comment."""

    def __init__(self, skip: int):
        self.skip = skip

    def rows_ahead(self, first: int, count: int) -> bool:
        return first > self.skip

    def took(self, count: int) -> None:
        pass

    def is_row(self, number: int, line: str) -> bool:
        text = line.strip()
        return number > self.skip and bool(text) and not text.startswith("#")

    def end(self) -> None:
        pass


class _PtsRows:
    """PTS: a count line, then that many rows, again and again."""

    def __init__(self) -> None:
        self.left, self.at = 0, 0  # rows the last count line (line ``at``) declares that are still to come

    def rows_ahead(self, first: int, count: int) -> bool:
        return self.left >= count

    def took(self, count: int) -> None:
        self.left -= count

    def is_row(self, number: int, line: str) -> bool:
        text = line.strip()
        if self.left:
            if not text:
                raise PointCloudFormatError(f"PTS line {number}: a blank line among the rows of line {self.at}")
            self.left -= 1
            return True
        if text and not (text.isdigit() and text.isascii()):
            raise PointCloudFormatError(f"PTS line {number}: expected a point count, got {text[:60]!r}")
        if text:
            self.left, self.at = int(text), number
        return False

    def end(self) -> None:
        if self.left:
            raise PointCloudFormatError(f"PTS line {self.at}: fewer rows follow it than it declares")


class _CountedRows:
    """After ``before`` lines that are not blank (other elements' rows), ``count`` rows; blank lines are none, as the
    ASCII PLY reader skips them."""

    def __init__(self, before: int, count: int, what: str):
        self.before, self.left, self.what = before, count, what

    def rows_ahead(self, first: int, count: int) -> bool:
        return not self.before and self.left >= count

    def took(self, count: int) -> None:
        self.left -= count

    def is_row(self, number: int, line: str) -> bool:
        if not line.strip():
            return False
        if self.before:
            self.before -= 1
            return False
        if self.left:
            self.left -= 1
            return True
        return False

    def end(self) -> None:
        if self.left or self.before:
            raise PointCloudFormatError(f"{self.what}: fewer rows follow than the header declares")


class _Rows:
    """Finds the values of ``columns`` in a run of rows separated by ``separator`` (``None``: whitespace), as numpy's
    text reader separates them, and puts others in their place, every other character kept. Rows of bare values
    (no quotes, no ``#`` before the last column needed, lines ending in ``\\n`` or ``\\r\\n``) are split by one
    regular expression over the run; others one by one (a separator within double quotes is no separator)."""

    def __init__(self, separator: str | None, columns: tuple[int, ...], what: str):
        self.separator, self.columns, self.what = separator, columns, what
        self.need = max(columns) + 1
        space = r"[^\S\r\n]*"
        parts, values = [], []  # every character of a line is in a group: the groups joined are the line
        s = re.escape(separator) if separator else ""
        between = rf"{space}{s}{space}" if separator else r"[^\S\r\n]+"
        for column in range(self.need):
            parts.append(between if column else space)
            values.append(len(parts))
            parts.append(rf'[^{s}\s#"]+')
        parts.append(r"[^\r\n]*(?:\r\n|\r|\n)?")  # the rest of the line
        self.pattern = re.compile("^" + "".join(f"({p})" for p in parts), re.MULTILINE)
        self.groups = [values[c] for c in columns]  # the group of each column's value
        captured = sorted(set(columns))  # the values alone (for their text only): a group each of these columns
        self.values = re.compile(
            "^" + "".join(f"({p})" if k in values and values.index(k) in captured else f"(?:{p})"
                          for k, p in enumerate(parts[:-1])),
            re.MULTILINE,
        )  # fmt: skip
        self.order = [captured.index(c) for c in columns]
        self.quoted = re.compile(rf'(?:[^{re.escape(separator)}"]|"[^"]*")*') if separator else None

    def bare(self, lines: list[str], values_only: bool = False) -> tuple[tuple[bool, list] | None, np.ndarray] | None:
        """As :meth:`split` where every line is a row of bare values (without the pieces where ``values_only``), else
        ``None``."""
        if values_only:
            found = self.values.findall("".join(lines))
            return (None, np.array(found, dtype=str)[:, self.order]) if len(found) == len(lines) else None
        found = self.pattern.findall("".join(lines))
        if len(found) != len(lines):  # else a match a line, each the whole line
            return None
        groups = list(zip(*found, strict=True))  # [G] tuples of [n] pieces
        return (True, groups), np.array([groups[g] for g in self.groups], dtype=str).T

    def split(self, run: list[tuple[int, str, bool]]) -> tuple[tuple[bool, list], np.ndarray]:
        """The rows of ``run`` in pieces (for :meth:`joined`) and ``[n, C]`` the text of the columns' values."""
        bare = self.bare([line for _, line, _ in run])
        if bare is not None:
            return bare
        split = [self._fields(number, line) for number, line, _ in run]
        values = [[pieces[at].strip().strip('"').strip() for at in (positions[c] for c in self.columns)]
                  for pieces, positions in split]  # fmt: skip
        return (False, split), np.array(values, dtype=str).reshape(len(run), len(self.columns))

    def joined(self, split: tuple[bool, list], texts: list[list[str]]) -> str:
        """The rows :meth:`split` split, with ``texts`` (``[C]`` lists of ``[n]``) in place of their values."""
        bare, pieces = split
        if bare:
            for group, column in zip(self.groups, texts, strict=True):
                pieces[group] = column
            return "".join(map("".join, zip(*pieces, strict=True)))
        out = []
        for k, (row, positions) in enumerate(pieces):
            for column, values in zip(self.columns, texts, strict=True):
                core = _CORE.match(row[positions[column]])
                row[positions[column]] = core.group(1) + values[k] + core.group(3)
            out.append("".join(row))
        return "".join(out)

    def _fields(self, number: int, line: str) -> tuple[list[str], list[int]]:
        """Pieces that joined give ``line`` back (its ``#`` comment and line ending in the last) and the index of each
        column's piece."""
        body, tail = _body(line)
        if self.separator is None:
            pieces = _WHITESPACE.split(body)  # values at even indices, the spacing between them at odd ones
            positions = [k for k in range(0, len(pieces), 2) if pieces[k]]
        else:
            if '"' in body:
                values, at = [], 0
                while True:
                    match = self.quoted.match(body, at)
                    values.append(match.group())
                    at = match.end()
                    if at >= len(body) or body[at] != self.separator:
                        values[-1] += body[at:]  # an unclosed quote: the rest of the line
                        break
                    at += 1
            else:
                values = body.split(self.separator)
            pieces = [self.separator] * (2 * len(values) - 1)
            pieces[::2] = values
            positions = list(range(0, 2 * len(values), 2))
        if len(positions) < self.need:
            raise PointCloudFormatError(
                f"{self.what} line {number}: {len(positions)} values, expected at least {self.need} "
                "(changed since it was read?)"
            )
        pieces.append(tail)
        return pieces, positions


def _body(line: str) -> tuple[str, str]:
    """``line`` as its values and the rest: a ``#`` comment and the line ending."""
    end = len(line.rstrip("\r\n"))
    comment = line.find("#", 0, end)
    cut = end if comment < 0 else comment
    return line[:cut], line[cut:]


def _decimals(tokens: np.ndarray) -> np.ndarray:
    """``[C]``: the most decimals a value of each column of ``tokens [n, C]`` (numbers as text) carries; ``1.5e-3``
    carries 4, ``12e3`` none."""
    if not tokens.size:
        return np.zeros(tokens.shape[1], dtype=np.int64)
    lower = np.char.lower(tokens)
    exponent = np.char.find(lower, "e") >= 0  # [n, C]
    dot = np.char.find(tokens, ".")  # [n, C]
    most = np.where(~exponent & (dot >= 0), np.char.str_len(tokens) - dot - 1, 0).max(axis=0)  # [C]
    for row, column in zip(*np.nonzero(exponent), strict=True):
        mantissa, _, power = str(lower[row, column]).partition("e")
        if power.lstrip("+-").isdigit():  # else no number: the rows are parsed next
            most[column] = max(most[column], len(mantissa.partition(".")[2]) - int(power))
    return most


def _largest(tokens: np.ndarray, what: str) -> float:
    """The largest absolute value of ``tokens [n, 3]`` (numbers as text)."""
    try:
        values = np.abs(tokens.astype(np.float64))  # [n, 3]
    except ValueError as exc:
        raise PointCloudFormatError(f"{what}: a row changed since it was read ({exc})") from None
    return float(values[np.isfinite(values)].max(initial=0.0))  # an organized PCD's NaN rows stay NaN


def _significant_decimals(largest: float) -> int:
    """The decimals that give the largest coordinate ``largest`` :data:`MIN_SIGNIFICANT_DIGITS` significant digits."""
    if not np.isfinite(largest) or largest <= 0.0:
        return 0
    return max(0, MIN_SIGNIFICANT_DIGITS - 1 - int(np.floor(np.log10(largest))))


def _number_format(decimals: int) -> Callable[[np.ndarray], list[str]]:
    """How moved values ``[n]`` are written: with ``decimals`` decimals (no ``-0.00`` for a small negative), or each
    its shortest float64 text beyond :data:`FULL_PRECISION_DECIMALS`."""
    if decimals > FULL_PRECISION_DECIMALS:
        return lambda values: list(map(repr, values.tolist()))
    fixed = f"{{:.{max(decimals, 0)}f}}".format
    zero = 0.5 * 10.0**-decimals  # values within it are written as 0

    def written(values: np.ndarray) -> list[str]:
        values = np.where(np.abs(values) < zero, 0.0, values)
        return list(map(fixed, values.tolist()))

    return written


# ------------------------------------------------------------------------------------------- PTX


def _count(line: str, number: int) -> int:
    text = line.strip()
    if not (text.isdigit() and text.isascii()):
        raise PointCloudFormatError(f"PTX line {number}: expected a count, got {text[:60]!r}")
    return int(text)


def _values(line: str, count: int, number: int) -> np.ndarray:
    """The ``[count]`` numbers of a PTX header line."""
    try:
        values = np.array([float(v) for v in line.split()], dtype=np.float64)
    except ValueError:
        values = np.empty(0)
    if len(values) != count or not np.isfinite(values).all():
        raise PointCloudFormatError(f"PTX line {number}: expected {count} numbers, got {line.strip()[:80]!r}")
    return values


def _replaced(line: str, values: np.ndarray, written: Callable[[float], str]) -> str:
    """``line`` with its first ``len(values)`` whitespace-separated values replaced, its spacing kept."""
    body, tail = _body(line)
    pieces = _WHITESPACE.split(body)
    positions = [k for k in range(0, len(pieces), 2) if pieces[k]]
    for at, value in zip(positions, values.tolist(), strict=False):
        pieces[at] = written(float(value))
    return "".join(pieces) + tail


# ------------------------------------------------------------------------------------------ streams


@contextmanager
def _text(src: BinaryIO, start: int = 0) -> Iterator[io.TextIOWrapper]:
    """``src``'s lines from byte ``start``, decoded as the readers decode them (UTF-8, a byte-order mark left out,
    lines ending at ``\\n``, ``\\r\\n`` or ``\\r``) with their endings kept; ``src`` stays open."""
    src.seek(start)
    stream = io.TextIOWrapper(src, encoding="utf-8-sig", newline="")
    try:
        yield stream
    except UnicodeDecodeError as exc:  # the reader took it for UTF-8: it changed since
        raise PointCloudFormatError(f"not UTF-8 text ({exc.reason}); changed since it was read?") from None
    finally:
        stream.detach()


@contextmanager
def _text_out(src: BinaryIO, dst: BinaryIO) -> Iterator[io.TextIOWrapper]:
    """``dst`` as text, starting with a byte-order mark where ``src`` does; ``dst`` stays open."""
    at = src.tell()
    src.seek(0)
    if src.read(len(UTF8_BOM)) == UTF8_BOM:
        dst.write(UTF8_BOM)
    src.seek(at)
    stream = io.TextIOWrapper(dst, encoding="utf-8", newline="")
    try:
        yield stream
    finally:
        stream.flush()
        stream.detach()


__all__ = ["CHUNK_CHARS", "moved_pts", "moved_ptx", "moved_rows", "moved_text"]
