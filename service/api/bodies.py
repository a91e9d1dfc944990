"""Request bodies -> validated :class:`Pair` objects: JSON and multipart point-cloud file uploads
(OIP v2 tensors: ``oip_request.py``).

Point counts are checked (413) before any conversion: from the JSON lists' lengths, the file's
header (``service.formats``; text files while reading), or the OIP tensor ``shape``. Files are read
with the CLI's reader, so a file gives the same array and the same error everywhere. Decoding runs
in a worker thread (see ``runner.py``), never on the event loop.

JSON bodies take a fast path that only ever accepts what the reference path accepts, with the same
values: ``/v1/register`` reads its two clouds piece by piece straight into numpy
(``json_clouds.py``), ``/v1/register/batch`` parses with orjson and converts each cloud with a few
vectorised checks; pydantic then validates only the small options. Whenever anything is unusual
the body goes through the reference path: ``json`` plus ``RegisterRequest`` validation, whose answer
(value, or status and message) is the API contract. For a 100k-point pair that path holds 43 MiB of
``json`` objects plus 74 MiB for pydantic's validated copy (docs/BENCHMARKS.md, "HTTP overhead").
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np
import orjson
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.formparsers import parse_options_header
from starlette.requests import Request
from starlette.types import Message

from service.api.body_budget import BodyBudget, BodyHold
from service.api.errors import APIError, TempStorageError, from_pydantic
from service.api.json_clouds import rows_array, split_register_body
from service.api.json_shapes import check_cloud_shapes
from service.api.schemas import (
    BatchRequest,
    RegisterOptions,
    RegisterRequest,
)
from service.formats import PointCloudFormatError, read_cloud
from service.formats.read import check_declared_count
from service.registrar import MIN_POINTS

JSON = "application/json"
MULTIPART = "multipart/form-data"
CLOUD_FIELDS = ("source", "target")
MAX_FORM_FIELD_BYTES = 64 * 1024
EXACT_FLOAT_LIMIT = 2.0**63  # orjson reads integer literals beyond 64 bits as floats; json keeps them ints
# JSON values a body may hold beyond four per point (a point's list and its three numbers): the options, a batch's
# pairs. A parsed value takes 24-64 bytes however short its text ("{}", "1.5"), so a 64 MiB body of them took 1-3.6 GB
# to parse, whatever field held them.
VALUES_PER_POINT = 4
EXTRA_JSON_VALUES = 4096
# Strings of a body (keys and text values: field names, options, model names, an OIP id): a batch of 16 pairs holds a
# few hundred of a few bytes each.
MAX_JSON_STRINGS = 4096
MAX_JSON_TEXT_BYTES = 64 * 1024
# the bytes a JSON value begins with: json's NaN and Infinity literals among them, and UTF-8, 16 and 32 byte order
# marks (the parse says what is wrong with those)
JSON_VALUE_STARTS = frozenset(b'{["-0123456789tfnNI\xef\xff\xfe\x00')


@dataclass
class Pair:
    """One registration to run: options plus the two clouds as float64 ``[N, 3]``, ``[M, 3]``; ``names``: what a 422
    calls the source, the target and the initial transform (OIP's input names there)."""

    options: RegisterOptions
    source: np.ndarray
    target: np.ndarray
    names: tuple[str, str, str] = ("source", "target", "initial_transform")


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";", 1)[0].strip().lower()


def require_media_type(request: Request, *allowed: str) -> str:
    """The request's media type if it is one of ``allowed`` (``application/*+json`` counts as JSON), else 415."""
    kind = media_type(request)
    if JSON in allowed and kind.startswith("application/") and kind.endswith("+json"):
        kind = JSON
    if kind not in allowed:
        shown = repr(kind[:80]) if kind else "none"
        raise APIError(415, f"unsupported content type {shown}; use {' or '.join(allowed)}")
    require_identity_encoding(request)
    return kind


def require_identity_encoding(request: Request) -> None:
    """415 for a compressed body (``Content-Encoding: gzip``...), naming the one coding read (RFC 7694): its bytes
    were read as JSON or multipart, a 400 "not UTF-8 text" or a form parse error."""
    codings = [part.strip().lower() for line in request.headers.getlist("content-encoding") for part in line.split(",")]
    encoding = ", ".join(coding for coding in codings if coding not in ("", "identity"))  # every header line counts
    if encoding:
        raise APIError(415, f"unsupported Content-Encoding {encoding[:40]!r}; send the body uncompressed",
                       headers={"Accept-Encoding": "identity"})


def too_many_points(name: str, count: int, max_points: int) -> APIError:
    return APIError(413, f"{name} has {count} points; the limit is {max_points} per cloud (MFGNET_MAX_POINTS)")


# -- JSON -------------------------------------------------------------------------------------------
class HeldBody:
    """A request body read within the :class:`BodyBudget`: ``take()`` it once to decode it, then ``release()`` its
    bytes (from the worker; ``with held:`` releases them in any case)."""

    def __init__(self, data: bytearray, hold: BodyHold):
        self._data: bytearray | None = data
        self._hold = hold

    def __enter__(self) -> HeldBody:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def peek(self) -> bytearray:
        """The body, not taken (for a check before it is decoded)."""
        if self._data is None:
            raise RuntimeError("the body was taken")
        return self._data

    def take(self) -> bytearray:
        data, self._data = self._data, None
        if data is None:
            raise RuntimeError("a body is taken once")
        return data

    def release(self) -> None:
        self._data = None
        self._hold.release()


async def read_body(request: Request, budget: BodyBudget, max_body_bytes: int,
                    wait_s: float | None = None) -> HeldBody:
    """The request body, read into one growing buffer once the budget holds its Content-Length (or
    ``max_body_bytes``, which the middleware enforces, when it has none).

    Unlike ``await request.body()`` this keeps no list of chunks beside the joined copy and does
    not cache the body on the request, so it can be freed as soon as it is parsed.
    """
    # a chunked body's Content-Length says nothing of its size (h11 frames it by the chunks): counted at the limit
    declared = "" if "transfer-encoding" in request.headers else request.headers.get("content-length", "")
    try:  # a wait for the budget is bounded as a wait for a worker is (MFGNET_TIMEOUT_S): then 503, the slot freed
        async with asyncio.timeout(wait_s):
            hold = await budget.hold(int(declared) if declared.isdigit() else max_body_bytes)
    except TimeoutError:
        raise APIError(503, f"server is busy: the bodies of earlier requests fill the memory for request bodies "
                            f"(MFGNET_MAX_BUFFERED_BYTES) until they are decoded, and this one waited {wait_s:g} s "
                            "(MFGNET_TIMEOUT_S) unread; retry later", headers={"Retry-After": "1"}) from None
    try:
        body = bytearray()
        async for chunk in request.stream():
            body += chunk
    except BaseException:
        hold.release()
        raise
    return HeldBody(body, hold)


def check_json_values(body: bytes | bytearray, points: int, clouds: str) -> None:
    """413 where ``body`` holds more JSON values (counted from its ``,``, ``[`` and ``{`` bytes, before any parse: at
    least one per value but the last of each array or object) than ``points`` points of ``clouds`` (what the message
    calls them, :data:`VALUES_PER_POINT` each) and :data:`EXTRA_JSON_VALUES` more need, or more strings (keys and
    text values) than :data:`MAX_JSON_STRINGS` or more bytes of them than :data:`MAX_JSON_TEXT_BYTES`."""
    allowed = VALUES_PER_POINT * points + EXTRA_JSON_VALUES
    _check_json_text(body)
    if len(body) <= 2 * allowed:  # each takes two bytes at least (a value and its comma, or "[]"): no need to count
        return
    count = body.count(b",") + body.count(b"[") + body.count(b"{")
    if count > allowed:
        raise APIError(413, f"the JSON body holds {count} values, arrays and objects; {clouds} need at most {allowed}")


def check_json_start(body: bytes | bytearray, hint: str) -> None:
    """400 where ``body`` cannot begin a JSON value (a file, or a multipart body, sent as ``application/json``), with
    ``hint`` (what the route takes): said before its bytes are counted as JSON's, which would call it too large. Only
    its first 4 KiB are looked at; a body of whitespace alone there passes (the parse answers it)."""
    head = bytes(body[:4096]).lstrip(b" \t\r\n")
    # "-" begins a number or -Infinity; a multipart body's boundary line begins with "--"
    if head and (head[0] not in JSON_VALUE_STARTS or (head[:1] == b"-" and head[1:2] not in b"0123456789I")):
        raise APIError(400, f"malformed JSON: the body begins with {head[:12]!r}, which begins no JSON value; {hint}")


def _check_json_text(body: bytes | bytearray) -> None:
    """413 where ``body``'s strings are more or longer than any request's keys and option values need: 4,000 unique
    keys of 16 KB in a 64 MiB body took 250 MiB to parse, and their 422 named every one."""
    quotes = body.count(b'"')
    if quotes > 2 * MAX_JSON_STRINGS:
        raise APIError(413, f"the JSON body holds {quotes // 2} strings; requests need at most {MAX_JSON_STRINGS} "
                            "(coordinates are JSON numbers, not strings)")
    text, start, position = 0, -1, body.find(b'"')
    while position >= 0:
        before = position
        while before > 0 and body[before - 1] == 0x5C:  # a run of backslashes: an odd one escapes the quote
            before -= 1
        if (position - before) % 2 == 0:
            if start < 0:
                start = position
            else:
                text, start = text + position - start - 1, -1
        position = body.find(b'"', position + 1)
    if text > MAX_JSON_TEXT_BYTES:
        raise APIError(413, f"the JSON body holds {text} bytes of strings (keys and text values); requests need at "
                            f"most {MAX_JSON_TEXT_BYTES}")


def two_clouds(max_points: int) -> str:
    """The clouds of one pair, as :func:`check_json_values` names them."""
    return f"two clouds of at most {max_points} points (MFGNET_MAX_POINTS)"


def load_json(body: bytes | bytearray, fast: bool = False) -> Any:
    """The parsed body, or 400 saying what is wrong with it (the standard library's diagnosis).

    ``fast``: try orjson first; it refuses what it cannot read exactly as ``json`` does (NaN and
    Infinity literals, lone surrogates, a BOM, numbers beyond float64), which then goes to ``json``.
    """
    if not body:
        raise APIError(400, "empty request body; expected a JSON object")
    if fast:
        try:
            return orjson.loads(body)
        except orjson.JSONDecodeError:
            pass
    try:
        return json.loads(body)
    except UnicodeDecodeError:
        raise APIError(400, "malformed JSON: the body is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise APIError(400, f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except RecursionError:
        raise APIError(400, "malformed JSON: nested too deeply") from None
    except ValueError:  # e.g. an integer literal longer than Python's int conversion limit (4300 digits)
        raise APIError(400, "malformed JSON: a number has too many digits") from None


def _require_object(obj: Any, what: str = "the body") -> dict:
    if not isinstance(obj, dict):
        raise APIError(422, f"invalid request: {what} must be a JSON object, got {type(obj).__name__}")
    return obj


def _count_clouds(obj: dict, max_points: int, prefix: str = "") -> None:
    check_cloud_shapes(obj, prefix)  # a flat list of numbers holds a third as many points: named by its shape
    for name in CLOUD_FIELDS:
        value = obj.get(name)
        if isinstance(value, list) and len(value) > max_points:
            raise too_many_points(prefix + name, len(value), max_points)


def _pair_from_request(req: RegisterRequest) -> Pair:
    options = RegisterOptions.model_validate(req.model_dump(exclude=set(CLOUD_FIELDS)))
    return Pair(options, np.asarray(req.source, dtype=np.float64), np.asarray(req.target, dtype=np.float64))


def cloud_array(value: Any) -> np.ndarray | None:
    """float64 ``[N, 3]`` if ``value`` is a cloud ``RegisterRequest`` accepts (a list of at least
    ``MIN_POINTS`` lists of exactly three finite numbers, ints or floats, no bools), else ``None``."""
    if type(value) is not list or len(value) < MIN_POINTS:
        return None
    return rows_array(value)


def _exact(value: Any) -> bool:
    """False if ``value`` holds a float orjson may have read from a 64-bit-overflowing integer literal."""
    if type(value) is float:
        return abs(value) < EXACT_FLOAT_LIMIT
    if type(value) is list:
        return all(map(_exact, value))
    if type(value) is dict:
        return all(map(_exact, value.values()))
    return True


def _fast_pair(obj: Any) -> Pair | None:
    """The :class:`Pair` the reference path would build from ``obj``, or ``None`` to let it decide."""
    if type(obj) is not dict or not all(name in obj for name in CLOUD_FIELDS):
        return None
    options = {key: value for key, value in obj.items() if key not in CLOUD_FIELDS}
    if not _exact(options):
        return None
    clouds = [cloud_array(obj[name]) for name in CLOUD_FIELDS]
    if clouds[0] is None or clouds[1] is None:
        return None
    try:
        parsed = RegisterOptions.model_validate(options, strict=True)
    except ValidationError:
        return None
    return Pair(parsed, clouds[0], clouds[1])


def _split_pair(body: bytes | bytearray, max_points: int) -> Pair | None:
    """The register fast path (see ``json_clouds.py``): a :class:`Pair`, a 413, or ``None``."""
    split = split_register_body(body, max_points)
    if split is None:
        return None
    for name in CLOUD_FIELDS:  # the body is valid JSON with these lists: the reference path says the same
        if split.counts[name] > max_points:
            raise too_many_points(name, split.counts[name], max_points)
    source, target = (split.clouds[name] for name in CLOUD_FIELDS)
    if source is None or target is None or min(len(source), len(target)) < MIN_POINTS:
        return None
    if not _exact(split.options):
        return None
    try:
        options = RegisterOptions.model_validate(split.options, strict=True)
    except ValidationError:
        return None
    return Pair(options, source, target)


def check_register_values(body: bytes | bytearray, max_points: int) -> None:
    """:func:`check_json_start` and :func:`check_json_values` for a ``/v1/register`` body: two clouds of at most
    ``max_points``."""
    check_json_start(body, "send point-cloud files as multipart/form-data (file fields source and target)")
    check_json_values(body, 2 * max_points, two_clouds(max_points))


def check_batch_values(body: bytes | bytearray, max_points: int) -> None:
    """:func:`check_json_start` and :func:`check_json_values` for a ``/v1/register/batch`` body: at most
    ``2 * max_points`` points in all."""
    check_json_start(body, 'a batch is a JSON object {"pairs": [...]}')
    check_json_values(body, 2 * max_points, f"a batch's clouds, at most {2 * max_points} points in all "
                                            "(2 x MFGNET_MAX_POINTS),")


async def refuse_too_many_values(held: HeldBody, check: Callable[[bytes | bytearray, int], None],
                                 max_points: int) -> None:
    """The 400 of a body that begins no JSON value and the 413 the decoder answers first for a JSON body of more
    values than ``max_points`` allow (``check``: :func:`check_register_values` or :func:`check_batch_values`), before
    the request waits for a worker (where a deadline passing in the queue would make it a 504), as
    :func:`refuse_oversized_uploads` does for files. It counts bytes only (no parse), in a thread (off the event loop):
    a cloud of 1,000,000 points where 200,000 are allowed is refused here; a body within the count but with a cloud
    over ``max_points`` is refused by the decoder's parse."""
    await run_in_threadpool(check, held.peek(), max_points)


def register_pair_from_json(body: bytes | bytearray, max_points: int, values_checked: bool = False) -> Pair:
    """``values_checked``: :func:`check_register_values` has passed the body already (not counted twice)."""
    if not values_checked:
        check_register_values(body, max_points)
    pair = _split_pair(body, max_points)
    if pair is not None:
        return pair
    obj = _require_object(load_json(body))  # the reference path: json's parse and RegisterRequest's verdict
    _count_clouds(obj, max_points)  # and their shapes
    try:
        req = RegisterRequest.model_validate(obj, strict=True)  # JSON has types: no "1.5" or true for numbers
    except ValidationError as exc:
        raise from_pydantic(exc) from None
    return _pair_from_request(req)


def _fast_batch(obj: Any, max_points: int, max_batch: int) -> list[Pair] | None:
    """The batch's :class:`Pair` objects from orjson's parse ``obj`` where each is plain, else ``None`` (413 where the
    batch or a cloud is too large)."""
    if type(obj) is not dict:
        return None
    _count_batch(obj, max_points, max_batch)
    items = obj.get("pairs")
    if type(items) is not list or not items or set(obj) != {"pairs"}:
        return None
    pairs = [_fast_pair(item) for item in items]
    return pairs if all(pair is not None for pair in pairs) else None  # type: ignore[return-value]


def _count_batch(obj: dict, max_points: int, max_batch: int) -> None:
    """413 where the batch has more than ``max_batch`` pairs, a cloud more than ``max_points`` points, or its clouds
    more than ``2 * max_points`` points in all (what one pair may hold: the batch's memory is bounded as a pair's)."""
    pairs = obj.get("pairs")
    if isinstance(pairs, list):
        if len(pairs) > max_batch:
            raise APIError(413, f"pairs has {len(pairs)} entries; the limit is {max_batch} per batch "
                                "(MFGNET_MAX_BATCH)")
        total = 0
        for i, pair in enumerate(pairs):
            if isinstance(pair, dict):
                _count_clouds(pair, max_points, prefix=f"pairs[{i}].")
                total += sum(len(pair[name]) for name in CLOUD_FIELDS if isinstance(pair.get(name), list))
        if total > 2 * max_points:
            raise APIError(413, f"pairs hold {total} points in all; the limit is {2 * max_points} per batch "
                                "(2 x MFGNET_MAX_POINTS)")


def batch_pairs_from_json(body: bytes | bytearray, max_points: int, max_batch: int,
                          values_checked: bool = False) -> list[Pair]:
    """``values_checked``: :func:`check_batch_values` has passed the body already (not counted twice)."""
    if not values_checked:
        check_batch_values(body, max_points)
    pairs = _fast_batch(load_json(body, fast=True), max_points, max_batch)
    if pairs is not None:
        return pairs
    obj = _require_object(load_json(body))  # the fast path's parse is freed: one parse of the body at a time
    _count_batch(obj, max_points, max_batch)  # and each pair's clouds' shapes
    try:
        batch = BatchRequest.model_validate(obj, strict=True)
    except ValidationError as exc:
        raise from_pydantic(exc) from None
    return [_pair_from_request(req) for req in batch.pairs]


# -- multipart/form-data with point-cloud files ----------------------------------------------------
@dataclass
class Upload:
    """One uploaded cloud: the form field, the client's file name, and the spooled file (not yet read)."""

    field: str
    filename: str
    file: BinaryIO

    @property
    def label(self) -> str:
        return f"{self.field} ({self.filename})" if self.filename else self.field


@dataclass
class RegisterForm:
    fields: dict[str, str]
    files: dict[str, Upload]  # "source" / "target"; closed by register_pair_from_form

    def close(self) -> None:
        for upload in self.files.values():
            upload.file.close()


async def read_register_form(request: Request, file_fields: tuple[str, ...] = CLOUD_FIELDS) -> RegisterForm:
    """Read the upload (bounded by max_upload_bytes upstream): ``file_fields`` as point-cloud files (all required),
    the rest as short text fields. The files stay spooled (on disk past 1 MiB) and are decoded later, off the loop
    (:func:`register_pair_from_form`, or :func:`decode_upload` and :meth:`RegisterForm.close`)."""
    params = parse_options_header(request.headers.get("content-type", ""))[1]
    charset = params.get(b"charset", b"utf-8").decode("latin-1")
    if charset.lower() not in ("utf-8", "utf8", "us-ascii", "ascii"):  # part headers and fields are read as UTF-8
        raise APIError(415, f"multipart/form-data with charset={charset[:40]!r}: send it as UTF-8")
    boundary = params.get(b"boundary", b"")
    closing = b"\r\n--" + boundary + b"--"  # the close delimiter, as the parser reads it (an epilogue may follow)
    seen = [False]
    carry = bytearray(b"\r\n")  # the end of the body so far (at first, as if a line ended: a body of no parts)

    async def receive() -> Message:
        message = await request.receive()
        if message["type"] == "http.request" and not seen[0]:
            carry.extend(message.get("body", b""))
            seen[0] = closing in carry
            del carry[:-(len(closing) - 1)]
        return message

    try:
        form = await Request(request.scope, receive).form(max_files=len(file_fields), max_fields=32,
                                                          max_part_size=MAX_FORM_FIELD_BYTES)
    except OSError as exc:  # a file past 1 MiB is spooled to the temporary folder
        raise TempStorageError(exc, "the upload") from None
    except StarletteHTTPException as exc:
        if str(exc.detail).startswith("Part exceeded maximum size"):  # a cloud sent as a text field (curl -F 'x=<f')
            raise APIError(400, f"a text field is over {MAX_FORM_FIELD_BYTES // 1024} KiB: send "
                                f"{' and '.join(file_fields)} as file uploads (curl -F {file_fields[0]}=@FILE; a "
                                "Content-Disposition with filename=), the options as text fields") from None
        if not str(exc.detail).startswith("Too many files"):
            raise
        each = "one file" if len(file_fields) == 1 else "one file each"
        raise APIError(400, f"more file uploads than {' and '.join(file_fields)} ({each}): a file field given twice, "
                            "or an option sent as a file; every other field (the options) is a text field, not a "
                            "file") from None
    if not seen[0]:  # python-multipart takes a body cut short for a whole one, less its last part
        await form.close()
        raise APIError(400, f"multipart body ends before its closing boundary {closing.strip().decode('latin-1')!r}: "
                            "the upload was cut short")
    fields: dict[str, str] = {}
    files: dict[str, Upload] = {}
    try:
        for key, value in form.multi_items():
            if key in fields or key in files:
                raise APIError(422, f"invalid request: {key}: given more than once")
            if key in file_fields:
                if not isinstance(value, UploadFile):  # no filename parameter
                    raise APIError(422, f"invalid request: {key}: expected a point-cloud file upload, got a text field "
                                        "(a file's Content-Disposition names it with filename=...; filename* alone "
                                        "marks no file in multipart/form-data, RFC 7578)")
                _check_transfer_encoding(key, value)
                files[key] = Upload(key, (value.filename or "")[:200], value.file)
            elif isinstance(value, UploadFile):
                raise APIError(422, f"invalid request: {key}: unexpected file; only {' and '.join(file_fields)} "
                               f"{'are files' if len(file_fields) > 1 else 'is a file'}")
            else:
                if "\x00" in value:  # the parser reads fields as UTF-8 (else Latin-1): UTF-16 text keeps its NULs
                    raise APIError(400, f"{key}: the field's value holds a NUL byte; form fields are read as UTF-8 "
                                        "text (was it sent as UTF-16?)")
                fields[key] = value
        missing = [name for name in file_fields if name not in files]
        if missing:
            raise APIError(422, f"invalid request: {', '.join(missing)}: missing point-cloud file upload")
    except BaseException:
        await form.close()
        raise
    return RegisterForm(fields, {name: files[name] for name in file_fields})  # in order: the first is refused first


def _check_transfer_encoding(key: str, upload: UploadFile) -> None:
    """415 for a file part sent in a ``Content-Transfer-Encoding`` (base64, quoted-printable): RFC 7578 deprecates it,
    and its bytes were read as the file's (a base64 ``.npy`` came back "the cloud is empty")."""
    encoding = upload.headers.get("content-transfer-encoding", "binary").strip().lower()
    if encoding not in ("binary", "8bit", "7bit"):
        raise APIError(415, f"{key}: Content-Transfer-Encoding {encoding[:40]!r} is not read (RFC 7578 deprecates "
                            "it); send the file's own bytes")


def decode_upload(upload: Upload, max_points: int) -> np.ndarray:
    """A point-cloud file (any format of :mod:`service.formats`, found from its content) -> float64 ``[N, 3]``.

    Errors name the field and the file: 400 unreadable, 413 over ``max_points`` (from the header, before the
    points are read), 415 a reader library not installed, 422 unusable points.
    """
    try:
        upload.file.seek(0)
        return read_cloud(upload.file, upload.label, max_points)
    except PointCloudFormatError as exc:
        raise _upload_error(exc) from None
    except OSError as exc:  # a small upload copied to a real file (binary PLY, E57): the temporary folder
        raise TempStorageError(exc, "a copy of the upload") from None


def _upload_error(exc: PointCloudFormatError) -> APIError:
    message = str(exc)
    if exc.status == 422:
        message = f"invalid request: {message}"
    elif exc.status == 413:
        message = f"{message} (MFGNET_MAX_FILE_POINTS)"
    return APIError(exc.status, message)


async def refuse_oversized_uploads(form: RegisterForm, max_points: int) -> None:
    """The 413 :func:`decode_upload` would answer for an upload whose header declares more than ``max_points``
    points (PLY, PCD, LAS/LAZ, E57, PTS, PTX, .npy, .npz: :func:`service.formats.read.check_declared_count`), before
    the request waits for a worker (where a deadline passing in the queue would make it a 504), the form then closed.
    It reads the headers only, in a thread (off the event loop); the decoder stays the authority (text formats, and a
    header that declares fewer points than its data holds, are refused there)."""
    try:
        await run_in_threadpool(_check_declared_counts, form, max_points)
    except BaseException:
        form.close()
        raise


def _check_declared_counts(form: RegisterForm, max_points: int) -> None:
    for upload in form.files.values():
        try:
            upload.file.seek(0)
            check_declared_count(upload.file, upload.label, max_points)
        except PointCloudFormatError as exc:
            raise _upload_error(exc) from None


def register_pair_from_form(form: RegisterForm, max_points: int) -> Pair:
    """Options and the two decoded files; ``max_points`` is the per-file limit (max_file_points)."""
    try:
        fields: dict[str, Any] = dict(form.fields)
        if "initial_transform" in fields:
            try:
                fields["initial_transform"] = json.loads(fields["initial_transform"])
            except (ValueError, RecursionError):  # bad JSON, an integer literal too long, or nested too deep
                raise APIError(422, "invalid request: initial_transform: expected a JSON 4x4 array") from None
        try:
            options = RegisterOptions.model_validate(fields)
        except ValidationError as exc:
            raise from_pydantic(exc) from None
        source, target = (decode_upload(form.files[name], max_points) for name in CLOUD_FIELDS)
        return Pair(options, source, target)
    finally:
        form.close()

