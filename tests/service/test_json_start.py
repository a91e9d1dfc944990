"""``bodies.check_json_start``: a body that begins no JSON value (a file or a multipart body sent as
``application/json``) is a 400 naming its first bytes before its bytes are counted as JSON's; every body that may begin
a JSON text passes to the parse, which answers it as before."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.api.bodies import check_json_start
from service.api.errors import APIError

VALID = {
    "object": b'{"source": []}',
    "array": b"[1, 2]",
    "string": b'"x"',
    "number": b"12",
    "negative": b"-1",
    "minus_infinity": b"-Infinity",
    "nan": b"NaN",
    "literals": b"true",
    "null": b"null",
    "whitespace_first": b" \t\r\n" * 30 + b"{}",
    "whitespace_then_minus_at_the_window": b" " * 4095 + b"-1",
    "minus_whose_digit_is_cut_off": b" " * 63 + b"-1"[:1],
    "utf8_bom": b"\xef\xbb\xbf{}",
    "utf16_le_bom": "\ufeff{}".encode("utf-16-le"),
    "utf16_be": "{}".encode("utf-16-be"),
    "utf32_le_bom": "\ufeff{}".encode("utf-32-le"),
    "empty": b"",
    "whitespace_only": b"   ",
}


@pytest.mark.parametrize("body", VALID.values(), ids=VALID.keys())
def test_whatever_may_begin_a_json_text_passes(body: bytes) -> None:
    check_json_start(body, "hint")


def npy_bytes() -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, np.zeros((4, 3), np.float32))
    return buffer.getvalue()


@pytest.mark.parametrize("body,first", [(npy_bytes(), b"\x93NUMPY"), (b"--boundary\r\nContent-Disposition", b"--b"),
                                        (b"ply\nformat ascii 1.0\n", b"ply"), (b"  # .PCD v0.7\n", b"# .PCD"),
                                        (b"-x", b"-x")])
def test_a_body_that_begins_no_json_value_is_a_400_naming_its_first_bytes(body: bytes, first: bytes) -> None:
    with pytest.raises(APIError) as caught:
        check_json_start(body, "send files as multipart/form-data")
    assert caught.value.status == 400
    assert caught.value.message.startswith("malformed JSON: the body begins with ")
    assert repr(first)[2:-1] in caught.value.message and "send files as multipart/form-data" in caught.value.message
    with pytest.raises(ValueError):
        json.loads(body)  # the rule refuses only what no JSON parse would read
