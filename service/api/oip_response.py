"""OIP v2 ``infer`` responses: output tensors as JSON ``data`` or, with the binary tensor data extension, as raw
little-endian bytes after the JSON header (``Inference-Header-Content-Length``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from starlette.responses import Response

from service.api.errors import APIError
from service.api.oip_request import HEADER_LENGTH, OCTET_STREAM
from service.api.responses import RenderedJSON, render_json
from service.registrar import RegistrationResult

WIRE_TYPES = {"FP32": np.dtype("<f4"), "INT64": np.dtype("<i8")}  # OIP datatype -> little-endian dtype
FP32_MAX = float(np.finfo(np.float32).max)  # 3.4028235e38


def output_array(result: RegistrationResult, name: str) -> tuple[str, np.ndarray]:
    """The output ``name`` as ``(datatype, array)`` in its wire dtype and shape.

    ``ValueError`` (a 500) if it holds NaN or infinity (JSON has none); :class:`APIError` 422 if a finite value
    is beyond the FP32 range (clouds near FP32's limits can be further apart than FP32 can hold)."""
    if name == "TRANSFORM":
        return "FP32", fp32_wire(name, result.transform)  # [4, 4] src_to_tgt
    if name == "CREDIBILITY":
        return "FP32", fp32_wire(name, result.credibility)  # [K]
    index = {"SOURCE_INDEX": result.source_index, "TARGET_INDEX": result.target_index}[name]  # [K]
    return "INT64", index.astype(WIRE_TYPES["INT64"])


def fp32_wire(name: str, values: np.ndarray) -> np.ndarray:
    """float64 ``values`` as little-endian float32; 422 naming the output (for TRANSFORM, the part) that does not
    fit."""
    if not np.isfinite(values).all():  # a 500, as before
        raise ValueError("the registration result has numbers the response schema does not allow")
    with np.errstate(over="ignore"):
        wire = values.astype(WIRE_TYPES["FP32"])
    beyond = ~np.isfinite(wire)
    if beyond.any():
        part = name
        if name == "TRANSFORM" and not beyond[:, :3].any():
            part = "TRANSFORM's translation"
        raise APIError(
            422, f"{part} is beyond the FP32 range ({float(np.abs(values[beyond]).max()):.3g}; FP32 holds magnitudes "
            f"up to {FP32_MAX:.4g}); send clouds nearer the origin, or use POST /v1/register, whose JSON numbers are "
            "float64"
        )
    return wire


def infer_parameters(result: RegistrationResult) -> dict[str, Any]:
    """The response ``parameters``; ``stability`` only when there is one, ``search_ms`` only when the rotation
    search ran (``timing_ms["search"]``)."""
    parameters = {
        "iterations": int(result.iterations),
        "inlier_ratio": float(result.inlier_ratio),
        "residual_rms": float(result.residual_rms),
        "reliable": bool(result.reliable),
        "warnings": "\n".join(result.warnings),  # a warning's own text holds "; "
        "total_ms": float(result.timing_ms["total"]),
    }
    if result.stability is not None:  # OIP parameter values cannot be null
        parameters["stability"] = float(result.stability)
    if "search" in result.timing_ms:
        parameters["search_ms"] = float(result.timing_ms["search"])
    return parameters


def infer_response(head: dict[str, Any], result: RegistrationResult, names: list[str], binary: set[str]) -> Response:
    """``head`` (model_name, model_version, id) plus ``parameters`` and the ``names`` outputs; those in
    ``binary`` as raw bytes after the JSON header, in output order."""
    outputs, chunks = [], []
    for name in names:
        datatype, array = output_array(result, name)
        tensor: dict[str, Any] = {"name": name, "datatype": datatype, "shape": list(array.shape)}
        if name in binary:
            chunk = array.tobytes(order="C")
            tensor["parameters"] = {"binary_data_size": len(chunk)}
            chunks.append(chunk)
        else:
            tensor["data"] = array.ravel().tolist()
        outputs.append(tensor)
    header = render_json({**head, "parameters": infer_parameters(result), "outputs": outputs})
    if not chunks:
        return RenderedJSON(header)
    return Response(
        b"".join([header, *chunks]), media_type=OCTET_STREAM, headers={HEADER_LENGTH: str(len(header))}
    )
