"""Double-quoted values in delimited text, found as numpy's text reader (``loadtxt(quotechar='"')``) finds them.

A quote opens a value only as its field's first character (after leading whitespace where whitespace separates the
values); inside it, separators, ``#`` and line breaks are literal and ``""`` is one quote; the first other quote closes
it and the field runs on unquoted. So one unclosed quote makes the rest of the file one value, which numpy holds at
about four bytes a character. A point's row is one line: :func:`quote_over_a_line_break` finds the first line whose
quoted value runs over its end, in one pass of bounded memory, so that the reader refuses such text before numpy
reads it.
"""

from __future__ import annotations

import io
import re
from typing import BinaryIO

from service.formats.checks import BLOCK_BYTES

_IN_QUOTES = r'[^"\n]*+(?:""[^"\n]*+)*+'  # a quoted value's characters on its line: ``""`` is one quote


def _line_ending_in_quotes(separator: str | None) -> re.Pattern:
    """A line (matched from the line break before it) whose last field is a double quote still open at its end, for
    fields separated by ``separator`` (``None``: runs of whitespace, leading whitespace skipped)."""
    if separator is None:
        space = r"[^\S\n]"
        field = rf'(?:"{_IN_QUOTES}"[^\s#]*+|[^\s"#][^\s#]*+)'
        fields = rf"{space}*+(?:{field}{space}++)*+"
    else:
        sep = re.escape(separator)
        field = rf'(?:"{_IN_QUOTES}"[^{sep}#\n]*+|[^"{sep}#\n][^{sep}#\n]*+|)'
        fields = rf"(?:{field}{sep})*+"
    return re.compile(rf'\n(?=[^"\n]*+"){fields}"{_IN_QUOTES}(?=\n)')  # only lines holding a quote are tried


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


def quote_over_a_line_break(stream: io.TextIOBase, separator: str | None) -> int | None:
    """The first line (1-based) of ``stream`` (text with ``\\n`` line breaks, from its position) that ends inside a
    double-quoted value, as numpy reads values separated by ``separator`` (``None``: whitespace); ``None`` where no
    quoted value runs over a line break. Lines are searched whole, ``BLOCK_BYTES`` characters at a time."""
    pattern = _line_ending_in_quotes(separator)
    unfinished, lines_before = "", 0  # the last block's line without its line break yet; the lines before it
    while more := stream.read(BLOCK_BYTES):
        text = "\n" + unfinished + more  # from a line's start, after a line break
        cut = text.rfind("\n")  # the last line break: whole lines before it
        if text.find('"', 0, cut) >= 0 and (found := pattern.search(text, 0, cut + 1)) is not None:
            return lines_before + text.count("\n", 0, found.start() + 1)
        lines_before += text.count("\n", 1, cut + 1)
        unfinished = text[cut + 1:]
    return None
