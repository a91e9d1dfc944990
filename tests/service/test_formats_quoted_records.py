"""Double-quoted values in XYZ/CSV/TXT text (``service.formats.quoted_records``): a quoted value that runs over a line
break is refused before numpy reads it, found as numpy's reader finds it."""

from __future__ import annotations

import io
import random
import time
import warnings

import numpy as np
import pytest
from traced_peak import peak_bytes

from service.formats import PointCloudFormatError, read_cloud
from service.formats import quoted_records as quoted

LIMIT = 2_000_000  # the server's max_file_points
ROW = "1.000000,2.000000,3.000000\n"
# pieces of fields: numbers, quoted values (closed, open, over a line break, with "" and '#'), inch marks, comments,
# ASCII and Unicode whitespace, a carriage return
PIECES = ['1', '2.5', '"1"', '"1,2"', '"1\n2"', '1"', '"1"x', '""', '"a""b"', '"a""', '"', ' ', '#c', '# "', '\t',
          '"1 2"', 'x"y', '\u3000', '\xa0', '\x1c', '\r', '\r\n', ';', '"#"', '"\n"', '"""', '""""', 'é']


def test_an_unclosed_quote_is_refused_before_numpy_reads_the_rest_of_the_file_as_one_value() -> None:
    """numpy read the 24 MB after the quote as one value at about four bytes a character; a 240 MB file peaked at
    1,417 MiB, over the server's 1 GiB."""
    text = ("x,y,z\n1,2,3\n4,5,\"6\n" + ROW * 900_000).encode()

    def read() -> None:
        with pytest.raises(PointCloudFormatError, match=r"a double-quoted value opened on line 3 runs over a line "
                                                        r"break \(an unclosed quote\?\)"):
            read_cloud(text, "a.csv", max_points=LIMIT)

    assert len(text) > 24_000_000 and peak_bytes(read) < 48 << 20


@pytest.mark.parametrize(("text", "line"), [
    ('x,y,z,label\n1,2,3,"two\nlines"\n4,5,6,b\n', 2),  # a label over a line break: numpy joins the rows
    ('x y z label\n1 2 3 "a"\r\n4 5 6 "two\r\nlines"\r\n', 3),  # whitespace-separated, CRLF
    ('1,2,3\n4,5,6,"a ""quoted"" word\n', 2),  # an open quote on the last line
])
def test_a_quoted_value_over_a_line_break_names_the_line_it_opens_on(text: str, line: int) -> None:
    with pytest.raises(PointCloudFormatError, match=f"opened on line {line} runs over a line break"):
        read_cloud(text.encode(), "a.csv", max_points=LIMIT)


@pytest.mark.parametrize("text", [
    '"x","y","z","name"\n1.0,2.0,3.0,"bolt #1"\n4.0,5.0,6.0,"a ""b"" c"\n',  # '#' and "" inside quotes
    'x,y,z,label\n1,2,3,5" pipe\n4,5,6,"b"x"y\n',  # an inch mark; a quote after a closed value is literal
    'x,y,z\n1,2,3 # an odd " quote\n4,5,6\n',  # a quote in a comment
    'x,y,z,label\n1,2,3, "a\n4,5,6,b\n',  # a quote after a space opens nothing where commas separate values
    '1 2 3 x"y\n4 5 6\n',
])
def test_quotes_that_close_on_their_line_or_open_nothing_are_read(text: str) -> None:
    np.testing.assert_array_equal(read_cloud(text.encode(), "a.csv", max_points=LIMIT), [[1, 2, 3], [4, 5, 6]])


def test_the_line_named_counts_the_lines_of_every_block_before_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(quoted, "BLOCK_BYTES", 10)
    text = "x,y,z\n" + '1,2,"3"\n' * 20 + '1,2,"3\n' + "4,5,6\n" * 20
    with pytest.raises(PointCloudFormatError, match="opened on line 22 runs over"):
        read_cloud(text.encode(), "a.csv", max_points=LIMIT)


def numpy_joins_lines(text: str, separator: str | None) -> bool | None:
    """Whether numpy's reader makes a value of a line break (a quote carried over it), reading ``text`` as the text
    reader does; ``None`` where numpy refuses it (rows of different lengths)."""
    stream = io.TextIOWrapper(io.BytesIO(text.encode()), encoding="utf-8-sig", newline=None)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # no rows
            values = np.loadtxt(stream, dtype=str, comments="#", delimiter=separator, quotechar='"', ndmin=2)
    except ValueError:
        return None
    return any("\n" in value for value in values.ravel())


def check_joins_lines(text: str, separator: str | None) -> bool:
    return quoted.quote_over_a_line_break(io.BytesIO(text.encode()), separator) is not None


def random_text(rng: random.Random, separator: str | None) -> str:
    lines = []
    for _ in range(rng.randint(1, 4)):
        if rng.random() < 0.3:  # anything
            lines.append("".join(rng.choice([*PIECES, ",", "\n"]) for _ in range(rng.randint(1, 8))))
        else:  # fields and separators
            gap = separator or rng.choice([" ", "  ", "\t"])
            lines.append(gap.join(rng.choice(PIECES) for _ in range(rng.randint(1, 4))))
    return rng.choice(["", "", "\ufeff"]) + "\n".join(lines) + rng.choice(["", "\n", "\r\n"])


@pytest.mark.parametrize("block", [quoted.BLOCK_BYTES, 7])
def test_the_check_finds_the_records_numpy_carries_over_a_line_break(monkeypatch: pytest.MonkeyPatch, block: int
                                                                     ) -> None:
    """On random texts of quoted and unquoted fields, in blocks longer than the text and shorter than a line."""
    monkeypatch.setattr(quoted, "BLOCK_BYTES", block)
    rng, compared, joined, disagree = random.Random(0), 0, 0, []
    for _ in range(4_000):
        separator = rng.choice([",", ";", None])
        text = random_text(rng, separator)
        expected = numpy_joins_lines(text, separator)
        if expected is None:
            continue
        compared, joined = compared + 1, joined + expected
        if check_joins_lines(text, separator) != expected:
            disagree.append((separator, text, expected))
    assert compared > 1_000 and joined > 300 and not disagree[:5]


def test_a_block_of_line_breaks_is_searched_in_bounded_memory() -> None:
    """Index arrays of every line of a block: 4 MiB blocks of bare line breaks held 168 MiB at once."""
    text = b'x,y,z\n1,2,"3"\n' + b"\n" * 24_000_000 + b"4,5,6\n"
    assert peak_bytes(lambda: quoted.quote_over_a_line_break(io.BytesIO(text), ",")) < 64 << 20


def test_blank_and_comment_lines_among_the_rows_warn_nothing() -> None:
    """numpy's note that such a line does not count towards max_rows reached stderr (the server's log) per upload."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        points = read_cloud(b"x,y,z\n1,2,3\n\n# a comment\n4,5,6\n", "a.csv", max_points=LIMIT)
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])


def test_lines_that_look_like_open_quotes_but_are_not_cost_one_search_per_block() -> None:
    """Comment lines holding ',"' pass the vectorised look (the quote follows a separator); a Python step per such line
    took ~18x numpy's own read of the text (CPU time, one process), one search per block ~2-3x."""
    text = b"x,y,z\n1,2,3\n" + b'#,"\n' * 2_000_000 + b"4,5,6\n"
    begin = time.process_time()
    assert quoted.quote_over_a_line_break(io.BytesIO(text), ",") is None
    check = time.process_time() - begin
    begin = time.process_time()
    rows = np.loadtxt(io.StringIO(text.decode()), delimiter=",", skiprows=1, comments="#", quotechar='"')
    assert rows.shape == (2, 3) and check < 8 * (time.process_time() - begin)
