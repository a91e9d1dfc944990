"""Request and response models of the HTTP API (``/v1``) and of the Open Inference Protocol v2 (``/v2``).

Frames: every pose is ``src_to_tgt`` in the caller's units: ``target ~= source @ rotation.T + translation``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, WrapValidator
from pydantic_core import PydanticCustomError

from service.refine_modes import REFINE_POINTS_RANGE
from service.registrar import (
    AUTO_SEARCH_RELATIVE_RATIO,
    KEYPOINT_RANGE,
    MAX_ITERATIONS,
    MIN_POINTS,
)

FiniteFloat = Annotated[float, Field(allow_inf_nan=False, strict=True)]  # strict: no "1.5" or true for a number
Point = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
Cloud = Annotated[
    list[Point],
    Field(min_length=MIN_POINTS, description=f"Points [N, 3] (x, y, z), N >= {MIN_POINTS}, at most max_points."),
]
Row4 = Annotated[list[FiniteFloat], Field(min_length=4, max_length=4)]
Matrix4 = Annotated[list[Row4], Field(min_length=4, max_length=4)]
Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
# = service.refine_modes.REFINE_MODES (a test keeps them equal)
Refine = Literal["none", "icp", "icp-plane", "icp-plane-multistart"]
REFINE_DESCRIPTION = (
    "Optional refinement after the network: 'icp' = point-to-point ICP (mutual nearest neighbours), "
    "'icp-plane' = a wide robust symmetric point-to-plane stage, then point-to-plane ICP with target normals "
    "(closer and more often right for two independently sampled scans); 'icp-plane-multistart' = icp-plane, then "
    "12 turns of the pose (+-15 and +-30 deg about each axis) refined and compared by a two-way point-to-plane fit "
    "(more often right on sparse or ambiguous clouds, ~2x the refinement time). Default: the server's "
    "(MFGNET_DEFAULT_REFINE; icp-plane unless the operator changed it); 'none' = the network's pose alone."
)

DROP_ISOLATED_DESCRIPTION = (
    "Leave out isolated points (flying pixels, sparse clutter: mean distance to their 8 nearest others above 3x "
    "the cloud's median) before sampling the working clouds; false keeps every point a candidate."
)
RefinePoints = Annotated[int, Field(ge=REFINE_POINTS_RANGE[0], le=REFINE_POINTS_RANGE[1])]
REFINE_POINTS_DESCRIPTION = (
    "Points per cloud the refinement uses (all of them when fewer, else one per voxel); default: the network's "
    "working clouds (768). More points give a more precise pose on dense scans at a higher cost: 1536 independent "
    "points per cloud, median rotation error 0.162 -> 0.112 deg. Ignored with refine 'none'."
)

ROTATION_SEARCH_DESCRIPTION = (
    "Search over initial rotations covering SO(3), for any relative orientation (about 2-3x the time of a refined "
    "request, 10-20x without a refinement): true = always; "
    "'auto' = only when the plain result looks wrong (inlier ratio below "
    f"{AUTO_SEARCH_RELATIVE_RATIO} of what the target's point density allows; never on degenerate clouds), then "
    "the better of both is returned and timing_ms has a 'search' key; false = never. Default (null): the "
    "server's (MFGNET_DEFAULT_ROTATION_SEARCH; false unless the operator set 'auto' or true) when the request is "
    "refined, false with refine 'none'. 422 when the loaded pipeline does not support it."
)


def _one_rotation_search_error(value: Any, handler: Any) -> Any:
    """One clear message instead of one per member of the union."""
    try:
        return handler(value)
    except ValidationError:
        raise PydanticCustomError("rotation_search", "Input should be true, false or 'auto'") from None


RotationSearch = Annotated[bool | Literal["auto"], WrapValidator(_one_rotation_search_error)]

_EXAMPLE_SOURCE = [[0.1 * i, 0.05 * (i % 7), 0.02 * (i % 5)] for i in range(MIN_POINTS)]
_EXAMPLE_TARGET = [[x + 0.1, y, z] for x, y, z in _EXAMPLE_SOURCE]


class ErrorResponse(BaseModel):
    """Every error body: a sentence saying what is wrong (validation errors add ``detail``)."""

    error: str = Field(examples=["invalid request: source[5]: List should have at least 3 items after validation"])
    detail: list[dict[str, Any]] | None = Field(None, description="Per-field validation problems (loc, msg).")

    model_config = ConfigDict(extra="allow")


# -- /v1/register ------------------------------------------------------------------------------------
class RegisterOptions(BaseModel):
    """Options shared by the JSON body, the multipart form fields and each batch pair."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(None, max_length=128, description="Model name (GET /v1/models); default: the server's.")
    iterations: int | None = Field(
        None, ge=1, le=MAX_ITERATIONS, description="Network iterations; default: the model's."
    )
    keypoints: int | None = Field(
        None, ge=KEYPOINT_RANGE[0], le=KEYPOINT_RANGE[1], description="Keypoints per cloud; default: the model's."
    )
    refine: Refine | None = Field(None, description=REFINE_DESCRIPTION)
    refine_points: RefinePoints | None = Field(None, description=REFINE_POINTS_DESCRIPTION)
    drop_isolated: bool = Field(True, description=DROP_ISOLATED_DESCRIPTION)
    initial_transform: Matrix4 | None = Field(
        None, description="Rigid 4x4 src_to_tgt guess; the network starts from the source moved by it."
    )
    return_correspondences: bool = Field(True, description="Include the keypoint correspondences.")
    return_iterations: bool = Field(False, description="Include the cumulative pose after each iteration.")
    rotation_search: RotationSearch | None = Field(None, description=ROTATION_SEARCH_DESCRIPTION)


class RegisterRequest(RegisterOptions):
    """Register ``source`` onto ``target``."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"source": _EXAMPLE_SOURCE, "target": _EXAMPLE_TARGET, "iterations": 4}]},
    )

    source: Cloud
    target: Cloud


class Correspondence(BaseModel):
    source_index: int = Field(description="Row of the request's source array.")
    target_index: int = Field(description="Row of the request's target array (the keypoint it was matched to).")
    credibility: float = Field(ge=0, le=1, description="Predicted probability that the match is correct.")
    weight: float = Field(ge=0, description="Weight in the final SVD (weights sum to 1).")


class Quality(BaseModel):
    inlier_ratio: float = Field(description="Share of source points within the inlier distance after alignment.")
    residual_rms: float = Field(description="RMS distance of those inliers, caller's units.")
    reliable: bool = Field(
        description="False when the quality checks or degeneracy warnings flag the result: an inlier ratio below "
        "0.3 or below 0.6 of what the target's point density allows, identical / collinear points, a weakly "
        "constrained pose (stability below 0.01: a 'weakly constrained' warning), or (rotation search) a pose far "
        "from the returned one that fits almost as well (an 'ambiguous' warning)."
    )
    stability: float | None = Field(
        default=None,
        description="How firmly the geometry pins the pose down: the smallest eigenvalue of the point-to-plane "
        "information matrix per paired point (unitless: rotation arms in units of the target's RMS radius). "
        "Below 0.01 some motion -- a turn about an axis of symmetry, a slide along a flat overlap -- hardly "
        "changes the fit and the pose along it is a guess; null with too few paired points.",
    )


class ModelRef(BaseModel):
    name: str
    version: str
    sha256: str = Field(description="sha256 of the model's manifest.json.")


class IterationPoseOut(BaseModel):
    rotation: Matrix3
    translation: Vector3


class RegisterResponse(BaseModel):
    """The pose ``src_to_tgt`` and how it was found."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                    "translation": [0.1, 0, 0],
                    "transform": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                    "euler_zyx_deg": [0, 0, 0],
                    "correspondences": [{"source_index": 3, "target_index": 3, "credibility": 0.97, "weight": 0.02}],
                    "quality": {"inlier_ratio": 0.98, "residual_rms": 0.004, "reliable": True, "stability": 0.07},
                    "warnings": [],
                    "model": {"name": "clean", "version": "0.1.0", "sha256": "4752cd1a..."},
                    "iterations": 4,
                    "timing_ms": {"queue": 0.1, "preprocess": 30.2, "encoder": 35.0, "total": 110.5},
                }
            ]
        }
    )

    rotation: Matrix3 = Field(description="[3, 3] rotation src_to_tgt.")
    translation: Vector3 = Field(description="[3] translation, caller's units.")
    transform: list[list[float]] = Field(description="[4, 4] homogeneous src_to_tgt.")
    euler_zyx_deg: Vector3 = Field(description="Intrinsic z-y-x Euler angles of the rotation, degrees.")
    correspondences: list[Correspondence] | None = Field(
        None, description="Keypoint matches (when asked): one per source keypoint; after a refined rotation search "
        "with a model that searches a subsample (its manifest's 'search' section), those of the subsample."
    )
    quality: Quality
    warnings: list[str]
    model: ModelRef
    iterations: int
    timing_ms: dict[str, float] = Field(
        description="Pipeline stages in ms; 'total' is the pipeline, 'queue' the wait for a worker."
    )
    iteration_poses: list[IterationPoseOut] | None = Field(None, description="Pose after each iteration (when asked).")


class BatchRequest(BaseModel):
    """Several independent pairs, registered one after another in one worker."""

    model_config = ConfigDict(extra="forbid")

    pairs: list[RegisterRequest] = Field(min_length=1, description="At most max_batch pairs.")


class BatchResponse(BaseModel):
    results: list[RegisterResponse] = Field(description="One result per pair, in request order.")


# -- /v1/models -------------------------------------------------------------------------------------
class ModelInfo(BaseModel):
    name: str
    status: Literal["loading", "ready", "failed"]
    error: str | None = Field(None, description="Why a failed model is not served.")
    default: bool = False
    version: str | None = None
    sha256: str | None = None
    config: dict[str, Any] | None = None
    accuracy: dict[str, Any] | None = None
    load_seconds: float | None = None


class ModelList(BaseModel):
    default_model: str
    models: list[ModelInfo]


# -- health -----------------------------------------------------------------------------------------
class LiveResponse(BaseModel):
    live: bool = True


class ReadyResponse(BaseModel):
    ready: bool
    models: dict[str, str] = Field(description="Model name -> loading | ready | failed.")
    errors: dict[str, str] | None = Field(None, description="Failed model -> why it is not served (if any).")


# -- Open Inference Protocol v2 ---------------------------------------------------------------------
Parameters = dict[str, bool | int | float | str]


class ServerMetadata(BaseModel):
    name: str
    version: str
    extensions: list[str]


class TensorMetadata(BaseModel):
    name: str
    datatype: str
    shape: list[int]


class ModelMetadata(BaseModel):
    name: str
    versions: list[str]
    platform: str
    inputs: list[TensorMetadata]
    outputs: list[TensorMetadata]


class ModelReady(BaseModel):
    name: str
    ready: bool


class InferInputTensor(BaseModel):
    name: str = Field(description="SOURCE or TARGET.")
    shape: list[int] = Field(description="[N, 3] or [1, N, 3].")
    datatype: str = Field(description="FP32.")
    parameters: dict[str, Any] | None = None
    data: list[Any] = Field(description="Row-major numbers, flat or nested.")


class InferRequestedOutput(BaseModel):
    name: str
    parameters: dict[str, Any] | None = None


class InferRequest(BaseModel):
    """OIP v2 inference request; options go into ``parameters``: iterations, keypoints, refine, refine_points,
    rotation_search."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "pair-1",
                    "parameters": {"iterations": 4, "refine": "none"},
                    "inputs": [
                        {"name": "SOURCE", "shape": [MIN_POINTS, 3], "datatype": "FP32", "data": _EXAMPLE_SOURCE},
                        {"name": "TARGET", "shape": [MIN_POINTS, 3], "datatype": "FP32", "data": _EXAMPLE_TARGET},
                    ],
                }
            ]
        }
    )

    id: str | None = None
    parameters: dict[str, Any] | None = None
    inputs: list[InferInputTensor] = Field(min_length=1)
    outputs: list[InferRequestedOutput] | None = None


class InferParameters(BaseModel):
    """The request ``parameters`` this server understands (others are ignored, as OIP allows)."""

    iterations: int | None = Field(None, ge=1, le=MAX_ITERATIONS)
    keypoints: int | None = Field(None, ge=KEYPOINT_RANGE[0], le=KEYPOINT_RANGE[1])
    refine: Refine | None = Field(None, description=REFINE_DESCRIPTION)
    refine_points: RefinePoints | None = Field(None, description=REFINE_POINTS_DESCRIPTION)
    drop_isolated: bool = Field(True, description=DROP_ISOLATED_DESCRIPTION)
    rotation_search: RotationSearch | None = Field(None, description=ROTATION_SEARCH_DESCRIPTION)


class InferOutputTensor(BaseModel):
    name: str
    shape: list[int]
    datatype: str
    parameters: dict[str, Any] | None = None
    data: list[int | float]


class InferResponse(BaseModel):
    model_name: str
    model_version: str | None = None
    id: str | None = None
    parameters: Parameters | None = None
    outputs: list[InferOutputTensor]
