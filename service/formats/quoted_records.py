"""How far a double-quoted value runs in delimited text, as numpy's text reader (``loadtxt(quotechar='"')``) reads it.

A quote opens a value only as its field's first character (after leading whitespace where whitespace separates the
values); inside it, separators, ``#`` and line breaks are literal and ``""`` is one quote; the first other quote closes
it and the field runs on unquoted. So one unclosed quote makes the rest of the file one value: numpy keeps about four
bytes per character of it, past any line-length limit. :func:`check_quoted_records` refuses a record (the lines a
quoted value joins) longer than ``MAX_TEXT_LINE_BYTES`` characters, before numpy reads it.
"""

from __future__ import annotations

import io
import re
from typing import BinaryIO

from service.formats.checks import BLOCK_BYTES, MAX_TEXT_LINE_BYTES
from service.formats.errors import PointCloudFormatError

_IN_QUOTES = r'[^"\n]*+(?:""[^"\n]*+)*+'  # a quoted value's characters on its line: ``""`` is one quote
_QUOTED_TO_LINE_END = rf'"{_IN_QUOTES}(?=\n)'  # a quoted value still open where its line ends


def _grammar(separator: str | None) -> tuple[re.Pattern, re.Pattern, re.Pattern]:
    """Three patterns for fields separated by ``separator`` (``None``: whitespace): a line (matched from the line break
    before it) whose last field is a quote still open at its end; the rest of a line from a field's start that ends
    so; the unquoted rest of a field after its closing quote, with the separator that ends it, if one does."""
    if separator is None:
        space = r"[^\S\n]"
        field = rf'(?:"{_IN_QUOTES}"[^\s#]*+|[^\s"#][^\s#]*+)'
        rest = rf"{space}*+(?:{field}{space}++)*+{_QUOTED_TO_LINE_END}"
        tail = rf"[^\s#]*+({space})?"
    else:
        sep = re.escape(separator)
        field = rf'(?:"{_IN_QUOTES}"[^{sep}#\n]*+|[^"{sep}#\n][^{sep}#\n]*+|)'
        rest = rf"(?:{field}{sep})*+{_QUOTED_TO_LINE_END}"
        tail = rf"[^{sep}#\n]*+({sep})?"
    return re.compile(r"\n(?=[^\"\n]*+\")" + rest), re.compile(rest), re.compile(tail)  # lines holding a quote


# the rest of an open quoted value, line breaks included, and its closing quote
_QUOTED_BODY = re.compile(r'[^"]*+(?:""[^"]*+)*+"')


def holds_a_quote(f: BinaryIO) -> bool:
    """Whether the bytes from ``f``'s position to its end hold a double quote; ``f``'s position is kept."""
    start = f.tell()
    try:
        while block := f.read(BLOCK_BYTES):
            if b'"' in block:
                return True
        return False
    finally:
        f.seek(start)


def check_quoted_records(stream: io.TextIOBase, separator: str | None, what: str) -> None:
    """:class:`PointCloudFormatError` starting with ``what`` where a record that a quoted value carries over a line
    break (:func:`quoted_record_over`) is longer than ``MAX_TEXT_LINE_BYTES`` characters."""
    line = quoted_record_over(stream, separator, MAX_TEXT_LINE_BYTES)
    if line is not None:
        raise PointCloudFormatError(
            f"{what}: a double-quoted value opened on line {line} runs on for more than {MAX_TEXT_LINE_BYTES} "
            "characters (an unclosed quote?); a quote opening a value must close it")


def quoted_record_over(stream: io.TextIOBase, separator: str | None, limit: int) -> int | None:
    """One pass over ``stream`` (text with ``\n`` line breaks, from its position): the line (1-based) on which the
    first record begins that a quoted value carries over a line break (numpy's reading, values separated by
    ``separator`` or whitespace) and that is longer than ``limit`` characters; ``None`` where none is."""
    spans, rest, tail = _grammar(separator)
    buffer, lines_before, done = "\n", 0, False  # text from a line start, after a line break; lines dropped before it
    while not done:
        more = stream.read(BLOCK_BYTES)
        done = not more
        buffer += more
        cut = len(buffer) if done else buffer.rfind("\n")  # search whole lines only
        position = 0
        while buffer.find('"', position, cut) >= 0 and (found := spans.search(buffer, position, cut + 1)) is not None:
            start = found.start() + 1  # the record's first character
            while not done and len(buffer) - start <= limit:  # hold enough text to measure it
                more = stream.read(BLOCK_BYTES)
                done = not more
                buffer += more
            end = _record_end(buffer, found.end(), rest, tail)
            if end - start > limit:
                return lines_before + buffer.count("\n", 0, start)
            position = end
            cut = len(buffer) if done else buffer.rfind("\n")
        drop = max(cut, position)  # the line break that ends the lines searched
        lines_before += buffer.count("\n", 1, drop + 1)
        buffer = "\n" + buffer[drop + 1:]
    return None


def _record_end(buffer: str, open_at_line_end: int, rest: re.Pattern, tail: re.Pattern) -> int:
    """Where the record ends (its last line break, or the buffer's end) whose quoted value is open at
    ``open_at_line_end``."""
    position = open_at_line_end
    while True:
        closed = _QUOTED_BODY.match(buffer, position)
        if closed is None:
            return len(buffer)
        after = tail.match(buffer, closed.end())
        if after.group(1) is None or (reopened := rest.match(buffer, after.end())) is None:
            line_end = buffer.find("\n", after.end())
            return len(buffer) if line_end < 0 else line_end
        position = reopened.end()
