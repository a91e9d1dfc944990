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


def quote_over_a_line_break(f: BinaryIO, separator: str | None) -> int | None:
    """The first line (1-based, ``\\r\\n``, ``\\r`` and ``\\n`` each ending one) of the UTF-8 text from ``f``'s
    position whose last value is a double quote still open at its end, as numpy reads values separated by
    ``separator`` (``None``: whitespace); ``None`` where no quoted value runs over a line break.

    The text is read ``BLOCK_BYTES`` at a time, whole lines searched, blocks without a quote skipped. A line can end
    inside quotes only where its last run of an odd number of quotes (the opening quote and the ``""`` after it;
    every run after it is ``""`` pairs) starts a field: from the first such line of a block
    (:func:`_first_candidate_line`, vectorised) the block is read as numpy reads it (the pattern of
    :func:`_line_ending_in_quotes`). ``UnicodeDecodeError`` where that part is not UTF-8."""
    pattern = _line_ending_in_quotes(separator)
    head = f.read(len(UTF8_BOM))
    text_start = f.tell() - len(head) + (len(UTF8_BOM) if head == UTF8_BOM else 0)  # a byte-order mark: no character
    f.seek(text_start)
    offset, unfinished = text_start, b""  # where ``data`` starts in ``f``; the last block's line without its break
    while more := f.read(BLOCK_BYTES):
        data = unfinished + more
        cut = max(data.rfind(b"\n"), data.rfind(b"\r")) + 1  # whole lines before it
        if data.find(b'"', 0, cut) >= 0 and (begin := _first_candidate_line(data[:cut], separator)) is not None:
            # one search in C from there on: a Python step per candidate line cost ~10x on lines such as '# "'
            text = "\n" + data[begin:cut].decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")
            if (found := pattern.search(text)) is not None:
                return _line_breaks_before(f, text_start, offset + begin) + text.count("\n", 0, found.start() + 1)
        offset, unfinished = offset + cut, data[cut:]
    return None


def _line_breaks_before(f: BinaryIO, start: int, stop: int) -> int:
    """Line breaks (``\\r\\n`` one) in ``f``'s bytes from ``start`` to ``stop``."""
    f.seek(start)
    breaks, left, after_cr = 0, stop - start, False
    while left > 0 and (block := f.read(min(BLOCK_BYTES, left))):
        left -= len(block)
        breaks += block.count(b"\n") + block.count(b"\r") - block.count(b"\r\n") - (after_cr and block[:1] == b"\n")
        after_cr = block.endswith(b"\r")
    return breaks


def _first_candidate_line(text: bytes, separator: str | None) -> int | None:
    """The byte offset of the first line of ``text`` (whole lines) whose last run of an odd number of double quotes
    starts a field: at the line's start or after ``separator`` (``None``: after whitespace, or any byte of a character
    that is not ASCII, which may be whitespace); ``None`` where no line's does."""
    data = np.frombuffer(text, dtype=np.uint8)  # [B]
    quote = (data == 34).view(np.int8)  # [B]
    edges = np.flatnonzero(np.diff(quote, prepend=np.int8(0), append=np.int8(0)))  # [2R] each run's first byte, end
    first, after = edges[0::2], edges[1::2]  # [R] each
    odd = first[((after - first) & 1).astype(bool)]  # [O] the runs of an odd number of quotes
    if not len(odd):
        return None
    ends = np.flatnonzero((data == 10) | (data == 13))  # [L] each line's break
    begins = np.concatenate(([0], ends[:-1] + 1))  # [L] each line's first byte
    last = odd[np.maximum(np.searchsorted(odd, ends) - 1, 0)]  # [L] the last odd run before each line's break
    before = data[np.maximum(last - 1, 0)]  # [L] the byte before it (a line's start: below)
    starts = (last == begins) | (before == (32 if separator is None else ord(separator)))
    if separator is None:
        starts |= np.isin(before, _ASCII_SPACES) | (before >= 0x80)
    lines = np.flatnonzero(starts & (last >= begins) & (last < ends))  # [C] the lines it starts a field of
    return int(begins[lines[0]]) if len(lines) else None
