"""XYZ, CSV and TXT: rows of numbers separated by whitespace, commas or semicolons (numpy's C text reader).

The first three columns are x, y, z, or the columns a header line names ``x``, ``y`` and ``z`` (pandas'
``to_csv`` puts its index first: ``,x,y,z``); further columns (intensity, colours, normals) are ignored.
``#`` comments and blank lines are skipped, and so is one header line: a first row whose first three values are not
numbers (``x,y,z``, CloudCompare's ``//X,Y,Z``; a row of numbers followed by a label is a row), or a single number (a
point count before rows that are not whitespace-separated; a count before such rows is Leica PTS, read and checked by
:mod:`service.formats.leica`). Without one, the last ``#`` comment before the rows names the columns where it names
x, y, z among as many names as the first row has values (numpy's ``savetxt(header=...)``). Values may be in double
quotes (pandas' ``QUOTE_ALL``), each closed on its line (:mod:`service.formats.quoted_records`).
"""

from __future__ import annotations

import io
import re
import warnings
from typing import BinaryIO

import numpy as np

from service.formats.checks import check_text_lines, checked
from service.formats.errors import InvalidPointsError, PointCloudFormatError, TooManyPointsError
from service.formats.quoted_records import quote_over_a_line_break

PROBE_LINES = 64  # lines read to find the header and the separator
_DECIMAL_COMMA = re.compile(r"convert string '[-+]?\d+,\d+' ")  # numpy's error for a number such as 0,125
# numpy's errors for a value it cannot convert and for a row with fewer columns than asked for
_CANNOT_CONVERT = re.compile(
    r"could not convert string (?P<value>.+) to float64 at row (?P<row>\d+), column (?P<column>\d+)")
_SHORT_ROW = re.compile(r"invalid column index \d+ at row (?P<row>\d+) with (?P<columns>\d+) columns")


def read_text(f: BinaryIO, max_points: int | None) -> np.ndarray:
    check_text_lines(f, "text file")
    stream = io.TextIOWrapper(f, encoding="utf-8-sig", newline=None)
    try:
        return _read(stream, max_points)
    except UnicodeDecodeError as exc:
        raise PointCloudFormatError(f"not UTF-8 text ({exc.reason} at byte {exc.start} of a block)") from None
    finally:
        stream.detach()  # leave the caller's file open


def layout(stream: io.TextIOWrapper) -> tuple[int, str | None, str | None, bool]:
    """How the text at ``stream``'s start is laid out, from its first :data:`PROBE_LINES` lines: the lines before the
    rows (the header line and the comments before it; 0 without a header), the separator (``;``, ``,`` or ``None``:
    whitespace), the header line or the ``#`` comment's text that names the columns (``None`` without either), and
    whether rows of numbers may follow."""
    skip, separator, header, comment = 0, None, None, None
    for number, line in enumerate(stream):
        if number >= PROBE_LINES:
            return skip, separator, header, True  # not known yet: loadtxt reads on
        text = line.strip()
        if text.startswith("#"):
            comment = text.lstrip("#").strip()
        if not text or text.startswith("#"):
            continue
        separator = _separator(text)  # from the first data line
        if header is None and _is_header(text, separator):
            skip, header = number + 1, text  # one header line: skip it and the comments before it
            continue
        if header is None and comment is not None and _names_the_columns(comment, text, separator):
            header = comment  # numpy's savetxt(header=...): the names as a comment before the rows
        return skip, separator, header, True
    return skip, separator, header, False


def _names_the_columns(comment: str, row: str, separator: str | None) -> bool:
    """Whether ``comment`` (a ``#`` line's text) names the columns of ``row``: x, y and z among as many names."""
    names = header_names(comment, separator)
    return {"x", "y", "z"} <= set(names) and len(names) == len([v for v in row.split(separator) if v.strip()])


def _read(stream: io.TextIOWrapper, max_points: int | None) -> np.ndarray:
    skip, separator, header, rows_follow = layout(stream)
    if not rows_follow:  # checked here: numpy's loadtxt would warn on stderr, then return no rows
        raise InvalidPointsError(_no_rows(header))
    stream.seek(0)  # the bytes from the start (the wrapper's state reset): read below, then again as text
    if (line := quote_over_a_line_break(stream.buffer, separator)) is not None:
        raise PointCloudFormatError(f"text file: a double-quoted value opened on line {line} runs over a line break "
                                    "(an unclosed quote?); each point's row must be one line")
    stream.seek(0)
    try:
        with warnings.catch_warnings():  # a blank or comment line among the rows: numpy's note on max_rows, to stderr
            warnings.filterwarnings("ignore", message=r"Input line \d+ contained no data", category=UserWarning)
            table = np.loadtxt(
                stream,
                dtype=np.float64,
                comments="#",
                delimiter=separator,
                skiprows=skip,
                quotechar='"',
                usecols=xyz_columns(header, separator),
                ndmin=2,
                max_rows=None if max_points is None else max_points + 1,
            )  # [N, 3]
    except ValueError as exc:
        comma = " (a decimal comma? numbers need a decimal point)" if _DECIMAL_COMMA.search(str(exc)) else ""
        raise InvalidPointsError(f"not rows of at least 3 numbers: {_on_its_line(stream, skip, str(exc))}{comma}"
                                 ) from None
    if len(table) == 0:
        raise InvalidPointsError(_no_rows(header))
    if max_points is not None and len(table) > max_points:
        raise TooManyPointsError(
            f"has more than {max_points} points; the limit is {max_points} per cloud", len(table), max_points
        )
    return checked(table)


def _on_its_line(stream: io.TextIOWrapper, skip: int, message: str) -> str:
    """numpy's ``message`` with the row it names as the file's line (1-based): numpy counts rows of data from 0 in a
    value it cannot convert and from 1 in a row short of columns, both without the ``skip`` lines, comments and blank
    lines; else ``message`` as it is."""
    convert, short = _CANNOT_CONVERT.search(message), _SHORT_ROW.search(message)
    if convert is None and short is None:
        return message
    data_row = int(convert["row"]) if convert else int(short["row"]) - 1  # 0-based among the rows of data
    line = _data_line(stream, skip, data_row)
    if line is None:
        return message
    if convert:
        return f"could not convert {convert['value']} to a number at line {line}, column {convert['column']}"
    return f"line {line} has {short['columns']} columns, fewer than the x, y and z columns need"


def _data_line(stream: io.TextIOWrapper, skip: int, data_row: int) -> int | None:
    """The 1-based line number of the ``data_row``-th (0-based) row of data after the first ``skip`` lines, comments
    and blank lines not counted, as numpy's ``loadtxt`` counts them."""
    stream.seek(0)
    rows = -1
    for number, line in enumerate(stream, start=1):
        if number <= skip or not line.split("#", 1)[0].strip():
            continue
        rows += 1
        if rows == data_row:
            return number
    return None


def _no_rows(header: str | None) -> str:
    """The error for text with no rows of numbers; ``header``: its one non-comment line, if any."""
    what = (
        "only comments or blank lines" if header is None else f"no rows of numbers after its first line {header[:40]!r}"
    )
    return (
        f"the cloud is empty: read as XYZ/CSV/TXT text (it starts with no PLY, PCD, LAS/LAZ, .npy or .npz header), "
        f"it has {what}; expected rows of x y z"
    )


def _separator(line: str) -> str | None:
    return ";" if ";" in line else "," if "," in line else None  # else whitespace


def xyz_columns(header: str | None, separator: str | None) -> tuple[int, int, int]:
    """The columns a header line names x, y and z (any case, quoted or not, CloudCompare's ``//`` before the first),
    else the first three."""
    names = header_names(header, separator)
    return tuple(names.index(axis) for axis in "xyz") if {"x", "y", "z"} <= set(names) else (0, 1, 2)


def header_names(header: str | None, separator: str | None) -> list[str]:
    """The names a header line gives its columns: lower case, quotes and CloudCompare's ``//`` taken off."""
    return [token.strip().strip('"').removeprefix("//").lower() for token in (header or "").split(separator)]


def _is_header(line: str, separator: str | None) -> bool:
    """Whether ``line``, the first line of a file that is not a comment, is its header: one value (a point count), or
    first three values (a trailing ``#`` comment left out, as numpy leaves it) that are not all numbers. A row of
    numbers followed by a label, a timestamp or a hex colour is a row: taken for a header, it lost the file's first
    point."""
    values = [token.strip().strip('"') for token in line.split("#", 1)[0].split(separator) if token.strip()]
    try:
        [float(value) for value in values[:3]]
    except ValueError:
        return True
    return len(values) == 1
