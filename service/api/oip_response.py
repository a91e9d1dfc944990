"""OIP v2 ``infer`` responses: output tensors as JSON ``data`` or, with the binary tensor data extension, as raw
little-endian bytes after the JSON header (``Inference-Header-Content-Length``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from starlette.responses import Response

from service.api.oip_request import HEADER_LENGTH, OCTET_STREAM
from service.api.responses import RenderedJSON, render_json
from service.registrar import RegistrationResult

WIRE_TYPES = {"FP32": np.dtype("<f4"), "INT64": np.dtype("<i8")}  # OIP datatype -> little-endian dtype


def output_arrays(result: RegistrationResult) -> dict[str, tuple[str, np.ndarray]]:
    """Every output by name: ``(datatype, array)`` in its wire dtype and shape."""
    return {
        "TRANSFORM": ("FP32", result.transform.astype(WIRE_TYPES["FP32"])),  # [4, 4] src_to_tgt
        "SOURCE_INDEX": ("INT64", result.source_index.astype(WIRE_TYPES["INT64"])),  # [K]
        "TARGET_INDEX": ("INT64", result.target_index.astype(WIRE_TYPES["INT64"])),  # [K]
        "CREDIBILITY": ("FP32", result.credibility.astype(WIRE_TYPES["FP32"])),  # [K]
    }


def infer_parameters(result: RegistrationResult) -> dict[str, Any]:
    """The response ``parameters``; ``stability`` only when there is one, ``search_ms`` only when the rotation
    search ran (``timing_ms["search"]``)."""
    parameters = {
        "iterations": int(result.iterations),
        "inlier_ratio": float(result.inlier_ratio),
        "residual_rms": float(result.residual_rms),
        "reliable": bool(result.reliable),
        "warnings": "; ".join(result.warnings),
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
    arrays = output_arrays(result)
    if not all(np.isfinite(array).all() for _, array in arrays.values()):  # JSON has no NaN; a 500, as before
        raise ValueError("the registration result has numbers the response schema does not allow")
    outputs, chunks = [], []
    for name in names:
        datatype, array = arrays[name]
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
