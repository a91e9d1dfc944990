"""Double-quoted values in delimited text, found as numpy's text reader (``loadtxt(quotechar='"')``) finds them.

A quote opens a value only as its field's first character (after leading whitespace where whitespace separates the
values); inside it, separators, ``#`` and line breaks are literal and ``""`` is one quote; the first other quote closes
it and the field runs on unquoted. So one unclosed quote makes the rest of the file one value, which numpy holds at
about four bytes a character. A point's row is one line: :func:`quote_over_a_line_break` finds the first line whose
quoted value runs over its end, in one pass of bounded memory, so that the reader refuses such text before numpy
reads it.
"""

from __future__ import annotations

import re
from typing import BinaryIO

import numpy as np

# Bytes searched at a time: a block of line breaks alone holds ~40 bytes of index arrays per byte while it is searched
BLOCK_BYTES = 1 << 20
UTF8_BOM = b"\xef\xbb\xbf"
_ASCII_SPACES = np.array([9, 11, 12, 28, 29, 30, 31, 32], dtype=np.uint8)  # str.isspace, line breaks aside
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


def quote_over_a_line_break(f: BinaryIO, separator: str | None) -> int | None:
    """The first line (1-based, ``\\r\\n``, ``\\r`` and ``\\n`` each ending one) of the UTF-8 text from ``f``'s
    position whose last value is a double quote still open at its end, as numpy reads values separated by
    ``separator`` (``None``: whitespace); ``None`` where no quoted value runs over a line break.

    The text is read ``BLOCK_BYTES`` at a time, whole lines searched. A line can end inside quotes only where its last
    run of an odd number of quotes (the opening quote and the ``""`` after it; every run after it is ``""`` pairs)
    starts a field: those lines (:func:`_candidate_lines`, vectorised) are read as numpy reads them (the pattern of
    :func:`_line_ending_in_quotes`). ``UnicodeDecodeError`` where such a line is not UTF-8."""
    pattern = _line_ending_in_quotes(separator)
    unfinished, lines_before, after_cr = b"", 0, False  # the last block's line without its break; lines before it
    head = f.read(len(UTF8_BOM))
    data = (b"" if head == UTF8_BOM else head) + f.read(BLOCK_BYTES)  # a byte-order mark is no character of a line
    while data:
        cut = max(data.rfind(b"\n"), data.rfind(b"\r")) + 1  # whole lines before it
        whole, unfinished = data[:cut], data[cut:]
        if b'"' in whole:
            for begin, end in _candidate_lines(whole, separator):
                if pattern.match("\n" + whole[begin:end].decode("utf-8") + "\n"):
                    return lines_before + _line_breaks(whole[:begin], after_cr) + 1
        lines_before += _line_breaks(whole, after_cr)
        after_cr = whole.endswith(b"\r") or (after_cr and not whole)
        data = (more := f.read(BLOCK_BYTES)) and unfinished + more
    return None


def _line_breaks(text: bytes, after_cr: bool) -> int:
    """Line breaks in ``text`` (``\\r\\n`` one; a leading ``\\n`` none where the text before ended in ``\\r``)."""
    return text.count(b"\n") + text.count(b"\r") - text.count(b"\r\n") - (after_cr and text.startswith(b"\n"))


def _candidate_lines(text: bytes, separator: str | None) -> list[tuple[int, int]]:
    """``(begin, end)`` byte offsets, in order, of the lines of ``text`` (whole lines) whose last run of an odd number
    of double quotes starts a field: at the line's start or after ``separator`` (``None``: after whitespace, or any
    byte of a character that is not ASCII, which may be whitespace)."""
    data = np.frombuffer(text, dtype=np.uint8)  # [B]
    quote = (data == 34).view(np.int8)  # [B]
    edges = np.flatnonzero(np.diff(quote, prepend=np.int8(0), append=np.int8(0)))  # [2R] each run's first byte, end
    first, after = edges[0::2], edges[1::2]  # [R] each
    odd = first[((after - first) & 1).astype(bool)]  # [O] the runs of an odd number of quotes
    ends = np.flatnonzero((data == 10) | (data == 13))  # [L] each line's break
    begins = np.concatenate(([0], ends[:-1] + 1))  # [L] each line's first byte
    last = odd[np.maximum(np.searchsorted(odd, ends) - 1, 0)] if len(odd) else np.zeros(len(ends), np.int64)  # [L]
    before = data[np.maximum(last - 1, 0)]  # [L] the byte before each line's last odd run
    starts = (last == begins) | (before == (32 if separator is None else ord(separator)))
    if separator is None:
        starts |= np.isin(before, _ASCII_SPACES) | (before >= 0x80)
    lines = np.flatnonzero(starts & (last >= begins) & (last < ends)) if len(odd) else []  # [C] lines holding it
    return [(int(begins[k]), int(ends[k])) for k in lines]
