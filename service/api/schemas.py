"""Request and response models of the HTTP API (``/v1``) and of the Open Inference Protocol v2 (``/v2``).

Frames: every pose is ``src_to_tgt`` in the caller's units: ``target ~= source @ rotation.T + translation``.
Every response field says its frame and units in its description (a test walks the OpenAPI document).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictInt,
    ValidationError,
    WrapValidator,
)
from pydantic_core import PydanticCustomError

from service.refine_modes import REFINE_POINTS_RANGE
from service.registrar import (
    AUTO_SEARCH_RELATIVE_RATIO,
    KEYPOINT_RANGE,
    MAX_ITERATIONS,
    MIN_POINTS,
)

FiniteFloat = Annotated[float, Field(allow_inf_nan=False, strict=True)]  # strict: no "1.5" or true for a number


def _whole_float_as_int(value: Any) -> Any:
    """``4.0`` as ``4``: JSON Schema's integer takes a number with no fractional part, and serializers that write
    doubles (nlohmann::json, Jackson, JavaScript's own numbers) send one; strict validation then refuses the rest."""
    return int(value) if type(value) is float and value.is_integer() else value


# strict: no "4" or true, but 4.0 (the bounds before the validator, so that the JSON schema carries them)
Iterations = Annotated[int, Field(ge=1, le=MAX_ITERATIONS), BeforeValidator(_whole_float_as_int)]
Keypoints = Annotated[int, Field(ge=KEYPOINT_RANGE[0], le=KEYPOINT_RANGE[1]), BeforeValidator(_whole_float_as_int)]
Point = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
Cloud = Annotated[
    list[Point],
    Field(
        min_length=MIN_POINTS,
        description=f"Points [N, 3] (x, y, z), N >= {MIN_POINTS}, at most the server's MFGNET_MAX_POINTS.",
    ),
]


def _writable_text(value: str) -> str:
    """``value`` if UTF-8 can encode it: a JSON string escape of a lone surrogate (``"\\ud800"``) parses to a str that
    no JSON response can hold; pydantic's own error for it, as the length-limited string fields give."""
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise PydanticCustomError(
            "string_unicode", "Input should be a valid string, unable to parse raw data as a unicode string"
        ) from None
    return value


UnicodeText = Annotated[str, AfterValidator(_writable_text)]
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
    "(more often right on sparse or ambiguous clouds; 3.3-3.9x the refinement time, 1.8x a registration's). "
    "Default: the server's (MFGNET_DEFAULT_REFINE; icp-plane unless the operator changed it); 'none' = the network's "
    "pose alone, unrefined (or the initial_transform where it fits better)."
)

DROP_ISOLATED_DESCRIPTION = (
    "Leave out isolated points (flying pixels, sparse clutter: mean distance to their 8 nearest others above 3x "
    "the cloud's median) before sampling the working clouds; false keeps every point a candidate."
)
RefinePoints = Annotated[int, Field(ge=REFINE_POINTS_RANGE[0], le=REFINE_POINTS_RANGE[1]),
                         BeforeValidator(_whole_float_as_int)]
REFINE_POINTS_DESCRIPTION = (
    "Points per cloud the refinement uses (all of them when fewer, else one per voxel); default: the network's "
    "working clouds (768). More points give a more precise pose on dense scans at a higher cost: 1536 independent "
    "points per cloud, median rotation error 0.162 -> 0.112 deg. At or below the working size it changes nothing (a "
    "thinner refinement moved right poses off by degrees). With refine 'none' (named or the server's default) a 422."
)

ROTATION_SEARCH_DESCRIPTION = (
    "Search over initial rotations covering SO(3), for any relative orientation (1.4-2.6x the time with a "
    "refinement, 7-15x without): true = always; "
    "'auto' = only when the plain result may be wrong (inlier ratio below "
    f"{AUTO_SEARCH_RELATIVE_RATIO} of what the target's point density allows, or off a dense target's surface, or "
    "both clouds built of orthogonal planes like rooms over a dense target; never on degenerate clouds), then "
    "the better of both is returned and timing_ms has a 'search' key; false = never. Default (null): the "
    "server's (MFGNET_DEFAULT_ROTATION_SEARCH; 'auto' unless the operator set off or on) when the request is "
    "refined, false with refine 'none'. 422 when the loaded pipeline does not support it."
)


def _one_rotation_search_error(value: Any, handler: Any) -> Any:
    """One clear message instead of one per member of the union."""
    try:
        return handler(value)
    except ValidationError:
        raise PydanticCustomError("rotation_search", "Input should be true, false or 'auto'") from None


RotationSearch = Annotated[bool | Literal["auto"], WrapValidator(_one_rotation_search_error)]

# The examples' pair: an asymmetric corner (a floor 0.6 x 0.4, a wall along it, a short side wall; MIN_POINTS points)
# and the same corner turned 10 deg about z and moved by (0.1, 0.05, 0): a pose the defaults find, `reliable`
# (a shift along a line of points or a symmetric shape would have no single right answer).
_EXAMPLE_SOURCE = ([[round(0.15 * i, 4), round(0.1 * j, 4), 0.0] for i in range(5) for j in range(1, 5)]
                   + [[round(0.15 * i + 0.05, 4), 0.0, round(0.1 * k, 4)] for i in range(4) for k in range(1, 3)]
                   + [[0.0, round(0.1 * j, 4), round(0.15 * k, 4)] for j in range(1, 3) for k in range(1, 3)])
_EXAMPLE_COS, _EXAMPLE_SIN = math.cos(math.radians(10)), math.sin(math.radians(10))
_EXAMPLE_TARGET = [[round(_EXAMPLE_COS * x - _EXAMPLE_SIN * y + 0.1, 4),
                    round(_EXAMPLE_SIN * x + _EXAMPLE_COS * y + 0.05, 4), z] for x, y, z in _EXAMPLE_SOURCE]


class ErrorResponse(BaseModel):
    """Every error body: a sentence saying what is wrong (validation errors add ``detail``)."""

    error: str = Field(
        description="What is wrong, as one sentence naming the field or file and the problem.",
        examples=["invalid request: source[5]: List should have at least 3 items after validation"],
    )
    detail: list[dict[str, Any]] | None = Field(
        None, description="Per-field validation problems: 'loc' (the field's path) and 'msg' (validation errors only)."
    )

    model_config = ConfigDict(extra="allow")


# -- /v1/register ------------------------------------------------------------------------------------
class RegisterOptions(BaseModel):
    """Options shared by the JSON body, the multipart form fields and each batch pair."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(None, min_length=1, max_length=128,
                              description="Model name (GET /v1/models); default: the server's.")
    iterations: Iterations | None = Field(None, description="Network iterations; default: the model's.")
    keypoints: Keypoints | None = Field(None, description="Keypoints per cloud; default: the model's.")
    refine: Refine | None = Field(None, description=REFINE_DESCRIPTION)
    refine_points: RefinePoints | None = Field(None, description=REFINE_POINTS_DESCRIPTION)
    drop_isolated: bool = Field(True, description=DROP_ISOLATED_DESCRIPTION)
    initial_transform: Matrix4 | None = Field(
        None, description="Rigid 4x4 src_to_tgt guess; the network starts from the source moved by it, and the guess "
        "itself is kept where it fits better than the network's poses (with refine 'none' too, unrefined). A "
        "rotation part within "
        "0.002 of orthonormal (a pose printed with three decimals) is taken as its nearest rotation."
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
    """One keypoint match: a row of the source and the row of the target it was matched to."""

    source_index: int = Field(description="Row (0-based) of the request's source array: a source keypoint.")
    target_index: int = Field(description="Row (0-based) of the request's target array: the point the source "
                              "keypoint was matched to.")
    credibility: float = Field(ge=0, le=1, description="Predicted probability that the match is correct, "
                               "unitless, 0..1.")
    weight: float = Field(ge=0, description="The match's weight in the network's final weighted SVD, unitless "
                          "(the weights sum to 1).")


class Quality(BaseModel):
    """How far the returned pose can be trusted, measured on the working clouds at the pose the pipeline judged: the
    returned one, or on a dense target the one before the fine refinement, which then moves no working source point
    more than 3 inlier distances (docs/DESIGN.md, "Fine refinement")."""

    inlier_ratio: float = Field(
        description="Share (0..1) of the working source points that, moved by the judged pose, have a target "
        "point within the inlier distance: 0.05 in the model's normalised units (the source scaled to the model's "
        "reference RMS radius), i.e. a fixed fraction of the source's size."
    )
    residual_rms: float = Field(
        description="RMS distance from those inlier source points (moved by the pose) to their nearest target "
        "points, in the caller's units; 0 when there is no inlier."
    )
    reliable: bool = Field(
        description="False when the quality checks or degeneracy warnings flag the result: an inlier ratio below "
        "0.3 or below 0.45-0.5 of what a right pose can reach at the target's sampling, clouds whose points lie "
        "farther apart than the inlier distance (a 'scattered points' warning, unless 0.9 of the source lands on the "
        "target's points), a loose fit (source "
        "points near the target but off its surface: a 'loose fit' warning), identical / collinear points, a weakly "
        "constrained pose (stability below 0.01, 0.02 on a dense target: a 'weakly constrained' warning), or "
        "another pose -- turned far from the returned one, or placing the source elsewhere -- that fits almost as "
        "well (an 'ambiguous' warning), or, where a cloud is a range image, a pose that puts the other cloud's "
        "surface where that sensor saw through (a 'through free space' warning); a loose fit of range images, or a "
        "pose only the second rotation search found, whose free space confirms the pose is reliable (a 'confirmed by "
        "free space' note), as is a room's poor fit, weak constraint or other place that fits, or an object's weak "
        "turn about its axis, weak slide or loose fit, that at least 30 matched surface patches of the two clouds "
        "agree with (a 'confirmed by descriptors' note; the warning is kept). "
        "docs/RELIABILITY.md lists each condition."
    )
    stability: float | None = Field(
        default=None,
        description="How firmly the geometry pins the pose down: the smallest eigenvalue of the point-to-plane "
        "information matrix per paired point (unitless: rotation arms in units of the target's RMS radius). "
        "Below 0.01 (0.02 where the target holds 4x the working points) some motion -- a turn about an axis of "
        "symmetry, a slide along a flat overlap -- hardly changes the fit and the pose along it is a guess; null "
        "with too few paired points.",
    )


_ELEMENTARY = (
    "Rx(θ), Ry(θ), Rz(θ) are the right-handed rotations by θ about the x, y, z axes, acting on column vectors "
    "(Rz(θ) = [[cos θ, -sin θ, 0], [sin θ, cos θ, 0], [0, 0, 1]]); R = rotation."
)
EULER_ZYX_DESCRIPTION = (
    "[a, b, c] in degrees: scipy Rotation.as_euler('zyx') (lowercase = extrinsic, fixed axes), i.e. rotate about "
    "the fixed z axis by a, then about the fixed y axis by b, then about the fixed x axis by c: "
    "R = Rx(c) @ Ry(b) @ Rz(a) (rebuild: Rotation.from_euler('zyx', [a, b, c], degrees=True)). Equivalently the "
    "intrinsic x-y'-z'' angles (c, b, a). a, c in [-180, 180], b in [-90, 90]. These are NOT yaw, pitch, roll "
    "(see yaw_pitch_roll_deg): for R = Rz(30) Ry(-20) Rx(15) this is [34.5, -9.0, 23.2]. " + _ELEMENTARY
)
YAW_PITCH_ROLL_DESCRIPTION = (
    "[yaw, pitch, roll] in degrees: the intrinsic z-y'-x'' (Tait-Bryan) angles, scipy Rotation.as_euler('ZYX'): "
    "R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (rebuild: Rotation.from_euler('ZYX', [yaw, pitch, roll], degrees=True)). "
    "yaw, roll in [-180, 180], pitch in [-90, 90]: for R = Rz(30) Ry(-20) Rx(15) this is [30, -20, 15]. " + _ELEMENTARY
)

QUATERNION_DESCRIPTION = (
    "[x, y, z, w]: the rotation as a unit quaternion, scalar last, as ROS geometry_msgs/Quaternion (tf2), Eigen's "
    "Quaternion::coeffs() and scipy Rotation.as_quat() take it (rebuild: Rotation.from_quat([x, y, z, w])); "
    "w >= 0 (q and -q are the same rotation). For R = Rz(30) Ry(-20) Rx(15): [0.1687, -0.1330, 0.2746, 0.9372]."
)
Vector4 = Annotated[list[float], Field(min_length=4, max_length=4)]


class ModelRef(BaseModel):
    """The model that computed the result."""

    name: str = Field(description="Model name (as in GET /v1/models).")
    version: str = Field(description="The model's version (its manifest's 'version').")
    sha256: str = Field(description="sha256 of the model's manifest.json (hex).")


ROTATION_DESCRIPTION = (
    "[3, 3] rotation matrix R, src_to_tgt, row-major (rows are lists): a source point p (column vector) maps to "
    "R p + t in the target's frame; for row arrays, target ~= source @ R.T + translation. Unitless, det +1."
)
TRANSLATION_DESCRIPTION = (
    "[3] translation t, src_to_tgt, in the caller's units (the units of the submitted points), applied after "
    "the rotation: R p + t."
)


class IterationPoseOut(BaseModel):
    """The cumulative pose after one network iteration (before any refinement)."""

    rotation: Matrix3 = Field(description=ROTATION_DESCRIPTION)
    translation: Vector3 = Field(description=TRANSLATION_DESCRIPTION)


class RegisterResponse(BaseModel):
    """The pose ``src_to_tgt`` and how it was found."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "rotation": [[0.9848, -0.1736, 0], [0.1736, 0.9848, 0], [0, 0, 1]],
                    "translation": [0.1, 0.05, 0],
                    "transform": [[0.9848, -0.1736, 0, 0.1], [0.1736, 0.9848, 0, 0.05], [0, 0, 1, 0], [0, 0, 0, 1]],
                    "euler_zyx_deg": [10, 0, 0],
                    "yaw_pitch_roll_deg": [10, 0, 0],
                    "quaternion_xyzw": [0, 0, 0.0872, 0.9962],
                    "correspondences": [{"source_index": 3, "target_index": 3, "credibility": 0.97, "weight": 0.02}],
                    "quality": {"inlier_ratio": 1.0, "residual_rms": 0.00003, "reliable": True, "stability": 0.07},
                    "warnings": [],
                    "model": {"name": "general", "version": "0.2.0", "sha256": "..."},
                    "iterations": 4,
                    "timing_ms": {"queue": 0.1, "preprocess": 30.2, "encoder": 35.0, "total": 110.5},
                }
            ]
        }
    )

    rotation: Matrix3 = Field(description=ROTATION_DESCRIPTION)
    translation: Vector3 = Field(description=TRANSLATION_DESCRIPTION)
    transform: list[list[float]] = Field(
        description="[4, 4] homogeneous rigid transform src_to_tgt, row-major: [[R, t], [0, 0, 0, 1]] with R = "
        "rotation and t = translation (caller's units); target ~= T @ [p, 1] for a source point p."
    )
    euler_zyx_deg: Vector3 = Field(description=EULER_ZYX_DESCRIPTION)
    yaw_pitch_roll_deg: Vector3 = Field(description=YAW_PITCH_ROLL_DESCRIPTION)
    quaternion_xyzw: Vector4 = Field(description=QUATERNION_DESCRIPTION)
    correspondences: list[Correspondence] | None = Field(
        None, description="Keypoint matches (when return_correspondences, the default): one per source keypoint, "
        "indices into the request's arrays; after a refined rotation search with a model that searches a "
        "subsample (its manifest's 'search' section), those of the subsample."
    )
    quality: Quality = Field(description="How far the pose can be trusted (see its fields).")
    warnings: list[str] = Field(
        description="Human-readable warnings, each starting with its kind and a colon (e.g. 'weakly constrained: "
        "...'); empty when there is nothing to warn about."
    )
    model: ModelRef = Field(description="The model that computed the result: name, version, manifest sha256.")
    iterations: int = Field(description="Network iterations that ran (count).")
    timing_ms: dict[str, float] = Field(
        description="Wall-clock time per stage, in milliseconds: 'queue' = wait for a worker slot; 'total' = the "
        "whole pipeline (excluding 'queue' and the HTTP decoding); stage keys such as 'preprocess', 'encoder', "
        "'iterations', 'svd', 'refine', 'postprocess', 'features' when rotation_search 'auto' computed a "
        "feature-matched candidate, 'consensus' when it compared a result that is not reliable, or a reliable room's "
        "whose views overlap in part, with the descriptors' consensus pose, and 'search' / 'search_per_hypothesis' "
        "when the rotation search ran. Stages may overlap or be absent; only 'queue' and 'total' are always there."
    )
    iteration_poses: list[IterationPoseOut] | None = Field(
        None, description="Cumulative network pose src_to_tgt after each iteration (when return_iterations), "
        "caller's units, before refinement; with refine 'none' the last is the transform unless the caller's "
        "initial_transform fitted better and was returned."
    )


class BatchRequest(BaseModel):
    """Several independent pairs, registered one after another in one worker."""

    model_config = ConfigDict(extra="forbid")

    pairs: list[RegisterRequest] = Field(
        min_length=1,
        description="At most the server's MFGNET_MAX_BATCH pairs, whose clouds hold at most 2 x MFGNET_MAX_POINTS "
        "points in all.",
    )


class BatchResponse(BaseModel):
    """The results of a batch."""

    results: list[RegisterResponse] = Field(description="One result per pair, in request order.")


# -- /v1/models -------------------------------------------------------------------------------------
class ModelInfo(BaseModel):
    """One model the server knows of."""

    name: str = Field(description="Model name (the 'model' option, the {name} of the /v2 routes).")
    status: Literal["loading", "ready", "failed"] = Field(description="Load status.")
    error: str | None = Field(None, description="Why a failed model is not served.")
    default: bool = Field(False, description="True for the model used when a request names none.")
    version: str | None = Field(None, description="The model's version (manifest), once loaded.")
    sha256: str | None = Field(None, description="sha256 of the model's manifest.json (hex), once loaded.")
    config: dict[str, Any] | None = Field(
        None, description="The model's configuration from its manifest (network sizes, keypoints, iterations, ...)."
    )
    accuracy: dict[str, Any] | None = Field(
        None, description="Accuracy recorded in the manifest at export: 'metrics' (rotation errors in degrees, "
        "translation errors in the evaluation clouds' units, recalls 0..1, ms_per_pair in ms) and 'on' (the "
        "evaluation pairs)."
    )
    load_seconds: float | None = Field(None, description="Time taken to verify, load and warm the model, seconds.")


class ModelList(BaseModel):
    """The models the server knows of."""

    default_model: str = Field(description="Name of the model used when a request names none.")
    models: list[ModelInfo] = Field(description="Every configured model, loaded or not.")


# -- health -----------------------------------------------------------------------------------------
class LiveResponse(BaseModel):
    live: bool = Field(True, description="Always true: the process answers.")


class ReadyResponse(BaseModel):
    ready: bool = Field(description="True once every model is verified, loaded and warmed up.")
    models: dict[str, str] = Field(description="Model name -> loading | ready | failed.")
    errors: dict[str, str] | None = Field(None, description="Failed model -> why it is not served (if any).")


class NotReadyResponse(BaseModel):
    """``GET /v2/health/ready`` while not ready (503): an error body that also says each model's status."""

    error: str = Field(description="'not ready: ' and why (models loading, or which failed and why).")
    ready: Literal[False] = Field(description="Always false here.")
    models: dict[str, str] = Field(description="Model name -> loading | ready | failed.")
    errors: dict[str, str] | None = Field(None, description="Failed model -> why it is not served (if any).")


# -- Open Inference Protocol v2 ---------------------------------------------------------------------
Parameters = dict[str, bool | int | float | str]


class ServerMetadata(BaseModel):
    name: str = Field(description="Server name ('mfgnet').")
    version: str = Field(description="Server version (the installed mfgnet package's).")
    extensions: list[str] = Field(
        description="Protocol extensions supported: 'binary_tensor_data' (tensors as raw bytes after the JSON)."
    )


class TensorMetadata(BaseModel):
    name: str = Field(description="Tensor name: inputs SOURCE, TARGET, INITIAL_TRANSFORM (optional); outputs "
                      "TRANSFORM, SOURCE_INDEX, TARGET_INDEX, CREDIBILITY.")
    datatype: str = Field(description="OIP datatype (FP32, INT64).")
    shape: list[int] = Field(description="Shape; -1 for a size that varies (N points, K matches).")


class ModelMetadata(BaseModel):
    name: str = Field(description="Model name.")
    versions: list[str] = Field(description="The model's version (one).")
    platform: str = Field(description="Runtime platform ('mfgnet_onnxruntime').")
    inputs: list[TensorMetadata] = Field(
        description="SOURCE and TARGET: FP32 [-1, 3] points, caller's units; INITIAL_TRANSFORM (optional): FP32 "
        "[4, 4], a rigid src_to_tgt guess (row-major, caller's units)."
    )
    outputs: list[TensorMetadata] = Field(
        description="TRANSFORM FP32 [4, 4] (src_to_tgt, caller's units), SOURCE_INDEX / TARGET_INDEX INT64 [-1] "
        "(rows of the inputs), CREDIBILITY FP32 [-1] (probability 0..1)."
    )


class ModelReady(BaseModel):
    name: str = Field(description="Model name.")
    ready: bool = Field(description="True: the model is loaded and serves requests.")


class InferInputTensor(BaseModel):
    name: str = Field(description="SOURCE, TARGET or (optional) INITIAL_TRANSFORM.")
    shape: list[StrictInt] = Field(description="SOURCE, TARGET: [N, 3] or [1, N, 3]; INITIAL_TRANSFORM: [4, 4] or "
                                   "[1, 4, 4]. Integers (not 3.0 or \"3\").")
    datatype: str = Field(description="FP32.")
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data_size: the tensor's byte count (N x 3 x 4; 64 for INITIAL_TRANSFORM) when its "
        "values follow the JSON as binary data (then no 'data')."
    )
    data: list[Any] | None = Field(
        None,
        description="Row-major numbers, flat or nested as the shape; absent when the tensor is sent as binary data.",
    )


class InferRequestedOutput(BaseModel):
    name: str = Field(description="TRANSFORM, SOURCE_INDEX, TARGET_INDEX or CREDIBILITY.")
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data: true to get this output as binary data after the JSON (overrides the "
        "request's binary_data_output). Triton's shared_memory_* and classification parameters are not served "
        "(422)."
    )


class InferRequest(BaseModel):
    """OIP v2 inference request; options go into ``parameters``: iterations, keypoints, refine, refine_points,
    drop_isolated, rotation_search, and binary_data_output (every output as binary data)."""

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

    id: UnicodeText | None = None  # echoed in the response: text that UTF-8 can write
    parameters: dict[str, Any] | None = None
    inputs: list[InferInputTensor] = Field(min_length=1)
    outputs: list[InferRequestedOutput] | None = None


class InferParameters(BaseModel):
    """The request ``parameters`` this server understands (others are ignored, as OIP allows, but for
    ``initial_transform``: a 422 naming the INITIAL_TRANSFORM input)."""

    iterations: Iterations | None = None
    keypoints: Keypoints | None = None
    refine: Refine | None = Field(None, description=REFINE_DESCRIPTION)
    refine_points: RefinePoints | None = Field(None, description=REFINE_POINTS_DESCRIPTION)
    drop_isolated: bool = Field(True, description=DROP_ISOLATED_DESCRIPTION)
    rotation_search: RotationSearch | None = Field(None, description=ROTATION_SEARCH_DESCRIPTION)
    binary_data_output: bool = Field(
        False, description="true: every output as binary data after the JSON, unless its own binary_data says false."
    )


class InferOutputTensor(BaseModel):
    """One output: TRANSFORM FP32 [4, 4] src_to_tgt (caller's units), SOURCE_INDEX / TARGET_INDEX INT64 [K] (rows
    of the SOURCE / TARGET inputs, one per keypoint match), CREDIBILITY FP32 [K] (probability 0..1)."""

    name: str = Field(description="TRANSFORM, SOURCE_INDEX, TARGET_INDEX or CREDIBILITY.")
    shape: list[int] = Field(description="[4, 4] for TRANSFORM; [K] (K keypoint matches) for the others.")
    datatype: str = Field(description="FP32 (TRANSFORM, CREDIBILITY) or INT64 (SOURCE_INDEX, TARGET_INDEX).")
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data_size: byte count of this output's little-endian bytes after the JSON (binary "
        "outputs only; then no 'data')."
    )
    data: list[int | float] | None = Field(
        None, description="The values, flat row-major (TRANSFORM: R[0], t[0], R[1], t[1], ... as the 4x4 rows); "
        "absent for a binary output."
    )


class InferResponse(BaseModel):
    """OIP v2 inference response (JSON, or the JSON header of a binary response)."""

    model_name: str = Field(description="The model that computed the result.")
    model_version: str | None = Field(None, description="That model's version.")
    id: str | None = Field(None, description="The request's id, echoed (absent when the request had none).")
    parameters: Parameters | None = Field(
        None, description="iterations (count), inlier_ratio (0..1), residual_rms (caller's units), reliable (bool), "
        "warnings (one per line: '\\n'-joined text), total_ms (pipeline time, ms), stability (unitless; when defined), "
        "search_ms (rotation search time, ms; when it ran). Meanings as in RegisterResponse.quality and timing_ms."
    )
    outputs: list[InferOutputTensor] = Field(description="The outputs asked for, in request order (default: all "
                                             "four in the order TRANSFORM, SOURCE_INDEX, TARGET_INDEX, CREDIBILITY).")
