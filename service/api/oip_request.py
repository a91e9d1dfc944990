"""OIP v2 ``infer`` request bodies -> a validated :class:`InferCall`: JSON tensors and the binary tensor data
extension.

A binary request is a JSON header of ``Inference-Header-Content-Length`` bytes followed by the raw tensor
bytes (little-endian, row-major, no padding) of every input whose ``parameters`` carry ``binary_data_size``,
in the order of ``inputs``. Every size is checked before a byte is converted: the header length against the
body, each ``binary_data_size`` against ``shape`` x the datatype's size, their sum against what follows the
header (exactly), and both clouds' declared point counts against ``max_points`` before either cloud's data. A binary
input is read in place (``np.frombuffer``): the body plus one float64 copy per cloud is all the memory a request holds.
:func:`check_infer_head` runs the checks a short JSON header allows once the body is read, before the request waits for
a worker.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from itertools import chain

import numpy as np
from pydantic import ValidationError
from starlette.requests import Request

from service.api.bodies import (
    JSON,
    Pair,
    check_json_values,
    load_json,
    media_type,
    require_identity_encoding,
    too_many_points,
    two_clouds,
)
from service.api.errors import APIError, from_pydantic
from service.api.schemas import InferInputTensor, InferParameters, InferRequest, RegisterOptions

HEADER_LENGTH = "Inference-Header-Content-Length"
OCTET_STREAM = "application/octet-stream"
OIP_INPUTS = {"SOURCE": "source", "TARGET": "target"}
GUESS_INPUT = "INITIAL_TRANSFORM"  # optional: FP32 [4, 4], the /v1/register option initial_transform
OIP_OUTPUTS = ("TRANSFORM", "SOURCE_INDEX", "TARGET_INDEX", "CREDIBILITY")
FP32_WIRE = np.dtype("<f4")  # binary FP32: little-endian float32
# Triton extensions a client may ask for in a tensor's parameters that this server does not implement (GET /v2
# lists binary_tensor_data only): refused by name, since answering with plain data would leave the client reading
# its shared memory region or expecting class labels
SHARED_MEMORY = ("shared_memory_region", "shared_memory_byte_size", "shared_memory_offset")
MAX_HEADER_DIGITS = 19  # any int64; more digits cannot be a header length
# A JSON header up to this long is parsed before the request waits for a worker (check_infer_head): one of binary
# tensor data names its tensors in a few hundred bytes
HEAD_PRECHECK_BYTES = 64 * 1024


@dataclass
class InferCall:
    """One ``infer`` request: its id, the pair to register, the outputs asked for and which of them go binary."""

    request_id: str | None
    pair: Pair
    outputs: list[str]
    binary_outputs: set[str]


def check_media_type(request: Request) -> str:
    """The request's media type (``""`` when none); 415 unless the body is JSON as OIP clients send it: no
    ``Content-Type`` (``tritonclient.http``), ``application/json`` (or ``+json``), or ``application/octet-stream``
    (clients sending binary tensors); and unless it is not compressed (``Content-Encoding``)."""
    kind = media_type(request)
    if kind and kind not in (JSON, OCTET_STREAM) and not (kind.startswith("application/") and kind.endswith("+json")):
        raise APIError(415, f"unsupported content type {kind[:80]!r}; use {JSON}, {OCTET_STREAM} or none")
    require_identity_encoding(request)
    return kind


def header_length(request: Request) -> int | None:
    """The ``Inference-Header-Content-Length`` header as an int, ``None`` when absent, 400 when not a length."""
    value = request.headers.get(HEADER_LENGTH)
    if value is None:
        return None
    text = value.strip()
    if not text.isdigit() or not text.isascii() or len(text) > MAX_HEADER_DIGITS:
        raise APIError(400, f"{HEADER_LENGTH} must be a non-negative integer, got {value[:40]!r}")
    return int(text)


# -- tensors ------------------------------------------------------------------------------------------
def _rows_before_conversion(data: list) -> int:
    """Rows in flat (``3N``), nested (``N x 3``) or batched (``1 x N x 3``) data, without converting it."""
    if data and isinstance(data[0], list):
        if data[0] and isinstance(data[0][0], list):
            return sum(len(block) if isinstance(block, list) else 1 for block in data)
        return len(data)
    return len(data) // 3


def _scalar_types(data: list, depth: int = 3) -> set[type]:
    """Types of the non-list values in flat, nested or batched ``data`` (down to ``depth`` levels of lists)."""
    types: set[type] = set()
    level = data
    for _ in range(depth):
        kinds = set(map(type, level))
        types |= kinds - {list}
        if list not in kinds:
            return types
        rows = level if kinds == {list} else [x for x in level if type(x) is list]
        level = list(chain.from_iterable(rows))
    return types | (set(map(type, level)) - {list})


def _numbers_only(tensor: InferInputTensor) -> None:
    """422 unless the JSON ``data`` holds numbers only: checked before numpy, which would quietly turn true into 1.0."""
    odd = sorted(t.__name__ for t in _scalar_types(tensor.data) - {int, float})
    if odd:
        raise APIError(422, f"invalid request: {tensor.name}: data must be numbers only, got {', '.join(odd)}")


def _point_count(tensor: InferInputTensor, max_points: int) -> int:
    """N of an FP32 ``[N, 3]`` or ``[1, N, 3]`` tensor (422 otherwise, 413 above ``max_points``)."""
    name = tensor.name
    if tensor.datatype != "FP32":
        raise APIError(422, f"invalid request: {name}: datatype must be FP32, got {tensor.datatype!r}")
    shape = list(tensor.shape)
    if len(shape) == 3 and shape[0] == 1:
        shape = shape[1:]
    if len(shape) != 2 or shape[1] != 3 or shape[0] < 0:
        raise APIError(422, f"invalid request: {name}: shape must be [N, 3] or [1, N, 3], got {list(tensor.shape)}")
    if shape[0] > max_points:
        raise too_many_points(name, shape[0], max_points)
    return shape[0]


def _finite_float64(array: np.ndarray, name: str) -> np.ndarray:
    """float32 ``[N, 3]`` -> float64 ``[N, 3]``; 422 naming the first row with NaN or infinity."""
    finite = np.isfinite(array).all(axis=1)  # [N]
    if not finite.all():
        first = int(np.argmin(finite))
        raise APIError(422, f"invalid request: {name}: data contains NaN or infinite values (first at row {first})")
    return array.astype(np.float64)


def _decode_json_tensor(tensor: InferInputTensor, max_points: int) -> np.ndarray:
    name, n = tensor.name, _point_count(tensor, max_points)
    data = tensor.data
    if data is None:
        raise APIError(422, f"invalid request: {name}: give the values in data or as binary data (binary_data_size)")
    if _rows_before_conversion(data) > max_points:
        raise too_many_points(name, _rows_before_conversion(data), max_points)
    _numbers_only(tensor)
    try:
        array = np.asarray(data)
    except ValueError:
        raise APIError(422, f"invalid request: {name}: data is ragged (rows of different lengths)") from None
    if array.dtype == object:  # numbers only (checked above), so integers beyond int64 / uint64: 2**64 and more
        try:
            array = array.astype(np.float64)
        except OverflowError:  # beyond float64 (10**400), so beyond FP32 too
            raise APIError(422, f"invalid request: {name}: data holds a number beyond the FP32 range") from None
    if array.dtype.kind not in "fiu":
        raise APIError(422, f"invalid request: {name}: data must be numbers only")
    # flat (row-major) or nested as the declared shape: a [3, N] nesting declared [N, 3], or lists nested deeper than
    # the shape (below the depth the numbers check reads, where numpy turned a true into 1.0), were reshaped silently
    if array.ndim != 1 and list(array.shape) != list(tensor.shape):
        raise APIError(422, f"invalid request: {name}: data is nested as {list(array.shape)}; give it flat "
                            f"(row-major) or nested as the shape {list(tensor.shape)}")
    if array.size != 3 * n:
        raise APIError(
            422, f"invalid request: {name}: data has {array.size} values; shape {tensor.shape} needs {3 * n}"
        )
    array = array.reshape(n, 3)
    with np.errstate(over="ignore"):
        wire = array.astype(np.float32)  # FP32 is the declared datatype
    beyond = (np.isinf(wire) & np.isfinite(array)).any(axis=1)  # [N] finite numbers FP32 cannot hold (1e39)
    if beyond.any():
        raise APIError(422, f"invalid request: {name}: data holds a number beyond the FP32 range (first at row "
                            f"{int(np.argmax(beyond))})")
    return _finite_float64(wire, name)


def _decode_transform(tensor: InferInputTensor, raw: memoryview | None) -> list[list[float]]:
    """The ``INITIAL_TRANSFORM`` input, FP32 ``[4, 4]`` or ``[1, 4, 4]`` as JSON ``data`` or 64 binary bytes, as the
    ``initial_transform`` option (4 rows of 4 finite numbers; 422 naming the problem). Whether it is rigid is checked
    where every request's guess is (:func:`service.checks.check_transform`)."""
    name = tensor.name
    if tensor.datatype != "FP32":
        raise APIError(422, f"invalid request: {name}: datatype must be FP32, got {tensor.datatype!r}")
    if list(tensor.shape) not in ([4, 4], [1, 4, 4]):
        raise APIError(422, f"invalid request: {name}: shape must be [4, 4] or [1, 4, 4], got {list(tensor.shape)}")
    if raw is not None:
        if len(raw) != 16 * FP32_WIRE.itemsize:
            raise APIError(422, f"invalid request: {name}: binary_data_size is {len(raw)} bytes; [4, 4] of FP32 "
                                f"needs {16 * FP32_WIRE.itemsize}")
        array = np.frombuffer(raw, dtype=FP32_WIRE)
    else:
        if tensor.data is None:
            raise APIError(422, f"invalid request: {name}: give the values in data or as binary data")
        _numbers_only(tensor)
        try:
            array = np.asarray(tensor.data, dtype=np.float64).reshape(-1)
        except ValueError:
            raise APIError(422, f"invalid request: {name}: data must be 16 numbers, row-major") from None
        except OverflowError:  # a JSON integer beyond float64 (10**400)
            raise APIError(422, f"invalid request: {name}: data holds a number beyond float64's range") from None
        if array.size != 16:
            raise APIError(422, f"invalid request: {name}: data has {array.size} values; [4, 4] needs 16")
        with np.errstate(over="ignore"):
            array = array.astype(np.float32)  # FP32 is the declared datatype
    if not np.isfinite(array).all():
        raise APIError(422, f"invalid request: {name}: data contains NaN or infinite values")
    return array.astype(np.float64).reshape(4, 4).tolist()


def binary_data_size(tensor: InferInputTensor) -> int | None:
    """The input's ``parameters.binary_data_size`` (bytes), ``None`` when it has none; 422 when not an int >= 0."""
    size = (tensor.parameters or {}).get("binary_data_size")
    if size is None:
        return None
    if type(size) is not int or size < 0:
        raise APIError(422, f"invalid request: {tensor.name}: parameters.binary_data_size must be an integer >= 0")
    if tensor.data is not None:
        raise APIError(422, f"invalid request: {tensor.name}: give data or binary_data_size, not both")
    return size


def _decode_binary_tensor(tensor: InferInputTensor, raw: memoryview, max_points: int) -> np.ndarray:
    name, n = tensor.name, _point_count(tensor, max_points)
    needed = 3 * n * FP32_WIRE.itemsize
    if len(raw) != needed:
        raise APIError(
            422, f"invalid request: {name}: binary_data_size is {len(raw)} bytes; shape {tensor.shape} of FP32 "
            f"needs {needed}"
        )
    array = np.frombuffer(raw, dtype=FP32_WIRE).reshape(n, 3)  # [N, 3], a view of the body
    return _finite_float64(array, name)


def _binary_parts(inputs: list[InferInputTensor], tail: memoryview | None) -> dict[str, memoryview]:
    """Each binary input's bytes, cut from ``tail`` (what follows the JSON header; ``None`` without the
    header) in input order."""
    parts, at = {}, 0
    sizes = [(tensor.name, binary_data_size(tensor)) for tensor in inputs]
    binary = [name for name, size in sizes if size is not None]
    if tail is None:
        if binary:
            raise APIError(400, f"{binary[0]}: binary_data_size needs the {HEADER_LENGTH} header")
        return parts
    total = sum(size for _, size in sizes if size is not None)
    if total != len(tail):
        raise APIError(
            400, f"binary data: the inputs' binary_data_size add up to {total} bytes but {len(tail)} bytes follow "
            f"the JSON header ({HEADER_LENGTH})"
        )
    for name, size in sizes:
        if size is not None:
            parts[name] = tail[at : at + size]
            at += size
    return parts


# -- the request --------------------------------------------------------------------------------------
def _split(body: bytes | bytearray, length: int | None) -> tuple[bytes | bytearray, memoryview | None]:
    """The JSON header and the binary tail of ``body``; no tail without a header length."""
    if length is None:
        return body, None
    if length > len(body):
        raise APIError(400, f"{HEADER_LENGTH} is {length} bytes but the body has only {len(body)}")
    if length == 0:
        raise APIError(400, f"{HEADER_LENGTH} is 0: the body must start with the JSON inference request")
    view = memoryview(body)
    return bytes(view[:length]), view[length:]


def refuse_extensions(where: str, parameters: dict | None, send: str) -> None:
    """422 when a tensor's ``parameters`` ask for an extension this server does not implement (shared memory,
    classification), naming the parameter and ``send``: what to do instead."""
    parameters = parameters or {}
    for key in (*SHARED_MEMORY, "classification"):
        if key in parameters:
            extension = "classification" if key == "classification" else "shared memory"
            raise APIError(
                422,
                f"invalid request: {where}: parameters.{key}: the {extension} extension is not supported (GET /v2 "
                f"lists the extensions served); {send}",
            )


def _outputs(req: InferRequest, binary_default: bool) -> tuple[list[str], set[str]]:
    """Names of the outputs to return (all when none are named) and those to send as binary data."""
    if not req.outputs:
        names = list(OIP_OUTPUTS)
        return names, set(names) if binary_default else set()
    names, binary = [], set()
    for output in req.outputs:
        if output.name not in OIP_OUTPUTS:
            raise APIError(
                422, f"invalid request: outputs: unknown output {output.name!r}; expected some of {list(OIP_OUTPUTS)}"
            )
        if output.name in names:
            raise APIError(422, f"invalid request: outputs: {output.name} asked for more than once")
        refuse_extensions(
            f"outputs: {output.name}",
            output.parameters,
            "ask for the output as data or as binary data (parameters.binary_data)",
        )
        flag = (output.parameters or {}).get("binary_data", binary_default)
        if type(flag) is not bool:
            raise APIError(
                422, f"invalid request: outputs: {output.name}: parameters.binary_data must be true or false"
            )
        names.append(output.name)
        if flag:
            binary.add(output.name)
    return names, binary


def _json_then_more(body: bytes | bytearray) -> bool:
    """Whether ``body``, which is no JSON, starts as a JSON object and has more after it: not UTF-8 text (binary
    data), or one whole JSON object and then something."""
    if bytes(body[:64]).lstrip()[:1] != b"{":
        return False
    try:
        text = bytes(body).decode()
    except UnicodeDecodeError:
        return True
    try:
        json.JSONDecoder().raw_decode(text.lstrip())
    except (ValueError, RecursionError):  # RecursionError: nested too deep, as load_json's 400 said
        return False  # malformed JSON, no whole object
    return True  # a whole object, which json.loads refused as a body: something follows it


def _load_head(head: bytes | bytearray, length: int | None, octet_stream: bool) -> object:
    """The parsed JSON header; a 400 about a body sent as binary but without its header length says so."""
    try:
        return load_json(head)
    except APIError as exc:
        if length is None and (octet_stream or _json_then_more(head)):
            raise APIError(exc.status, f"{exc.message}; a JSON inference request followed by binary tensor data needs "
                                       f"the {HEADER_LENGTH} header (the JSON's length in bytes)") from None
        raise


@dataclass
class _Head:
    """An ``infer`` body's JSON header, checked up to the clouds' data: the request, its parameters, the inputs by name,
    the outputs, the binary inputs' bytes."""

    req: InferRequest
    params: InferParameters
    by_name: dict[str, InferInputTensor]
    outputs: list[str]
    binary_outputs: set[str]
    parts: dict[str, memoryview]


def _infer_head(body: bytes | bytearray, length: int | None, max_points: int, octet_stream: bool,
                values_checked: bool) -> _Head:
    """Every check of :func:`infer_call` before the clouds' data is read, the clouds' declared shapes last (their 413
    above ``max_points``, SOURCE's then TARGET's)."""
    head, tail = _split(body, length)
    if not values_checked:
        check_json_values(head, 2 * max_points, two_clouds(max_points))
    obj = _load_head(head, length, octet_stream)
    if not isinstance(obj, dict):
        raise APIError(422, f"invalid request: the body must be a JSON object, got {type(obj).__name__}")
    try:
        req = InferRequest.model_validate(obj)
        params = InferParameters.model_validate(req.parameters or {}, strict=True)
    except ValidationError as exc:
        raise from_pydantic(exc) from None
    if (req.parameters or {}).get("initial_transform") is not None:  # /v1's option name, else ignored: a guess unused
        raise APIError(422, f"invalid request: parameters.initial_transform: the guess goes in the {GUESS_INPUT} input "
                            "(FP32, shape [4, 4]), not in parameters")
    by_name: dict[str, InferInputTensor] = {}
    for tensor in req.inputs:
        if tensor.name not in OIP_INPUTS and tensor.name != GUESS_INPUT:
            raise APIError(422, f"invalid request: inputs: unknown input {tensor.name!r}; expected SOURCE and TARGET "
                                f"(and optionally {GUESS_INPUT})")
        if tensor.name in by_name:
            raise APIError(422, f"invalid request: inputs: {tensor.name} given more than once")
        refuse_extensions(
            tensor.name, tensor.parameters, "send the values in data or as binary data (binary_data_size)"
        )
        by_name[tensor.name] = tensor
    missing = [name for name in OIP_INPUTS if name not in by_name]
    if missing:
        raise APIError(422, f"invalid request: inputs: missing {', '.join(missing)}")
    outputs, binary_outputs = _outputs(req, params.binary_data_output)
    parts = _binary_parts(req.inputs, tail)
    for name in OIP_INPUTS:  # both clouds' declared sizes before either cloud's data
        _point_count(by_name[name], max_points)
    return _Head(req, params, by_name, outputs, binary_outputs, parts)


def check_infer_head(body: bytes | bytearray, max_points: int, length: int | None, octet_stream: bool) -> None:
    """What :func:`infer_call` refuses before reading the clouds' data, where that is cheap: the JSON header's value
    count (bytes counted, no parse, as :func:`service.api.bodies.check_json_values` for ``/v1/register``), and, for a
    JSON header of at most :data:`HEAD_PRECHECK_BYTES` (binary tensor data, the values after it), every check up to
    the clouds' declared shapes (their 413 above ``max_points``). Its error is the one :func:`infer_call` gives
    first (the same checks in the same order), so a request answered from here gets an idle server's answer without
    waiting for a worker; :func:`infer_call` then skips the count (``values_checked``)."""
    head, _ = _split(body, length)
    check_json_values(head, 2 * max_points, two_clouds(max_points))
    if length is not None and length <= HEAD_PRECHECK_BYTES:
        _infer_head(body, length, max_points, octet_stream, values_checked=True)


def infer_call(body: bytes | bytearray, length: int | None, max_points: int, octet_stream: bool = False,
               values_checked: bool = False) -> InferCall:
    """Decode an ``infer`` body whose JSON header is ``length`` bytes long (``None``: the whole body);
    ``octet_stream``: it was sent as ``application/octet-stream`` (a hint for the error when it is no JSON);
    ``values_checked``: :func:`check_infer_head` has passed the body already (its values not counted twice)."""
    checked = _infer_head(body, length, max_points, octet_stream, values_checked)
    by_name, parts = checked.by_name, checked.parts
    clouds: list[np.ndarray] = []
    for name in OIP_INPUTS:
        tensor = by_name[name]
        part = parts.get(name)
        clouds.append(
            _decode_json_tensor(tensor, max_points) if part is None else _decode_binary_tensor(tensor, part, max_points)
        )
    guess = by_name.get(GUESS_INPUT)
    params = checked.params
    options = RegisterOptions(
        iterations=params.iterations, keypoints=params.keypoints, refine=params.refine,
        refine_points=params.refine_points, drop_isolated=params.drop_isolated, rotation_search=params.rotation_search,
        initial_transform=None if guess is None else _decode_transform(guess, parts.get(GUESS_INPUT)),
        return_correspondences=True,
    )
    pair = Pair(options, clouds[0], clouds[1], names=("SOURCE", "TARGET", GUESS_INPUT))  # a 422 names the input
    return InferCall(checked.req.id, pair, checked.outputs, checked.binary_outputs)
