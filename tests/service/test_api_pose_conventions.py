"""What every response number means: the Euler-angle conventions, rebuilt from hand-written elementary
rotations (not scipy, whose naming is the thing being pinned down), and a description on every response
field of the OpenAPI document, with its frame and units."""

from __future__ import annotations

import numpy as np
import pytest
from api_server import MODEL, modelnet_pair

from service.pose_json import pose_fields


def Rx(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def from_euler_zyx_deg(a: float, b: float, c: float) -> np.ndarray:
    """The documented rebuild of ``euler_zyx_deg = [a, b, c]``: extrinsic z, y, x -> ``Rx(c) Ry(b) Rz(a)``."""
    return Rx(c) @ Ry(b) @ Rz(a)


def from_yaw_pitch_roll_deg(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """The documented rebuild of ``yaw_pitch_roll_deg``: intrinsic z-y'-x'' -> ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    return Rz(yaw) @ Ry(pitch) @ Rx(roll)


ISSUE_ROTATION = Rz(30) @ Ry(-20) @ Rx(15)  # the example of the OpenAPI descriptions


def test_pose_fields_give_the_documented_angles_of_the_example_rotation():
    fields = pose_fields(ISSUE_ROTATION, np.zeros(3))
    np.testing.assert_allclose(fields["euler_zyx_deg"], [34.5, -9.0, 23.2], atol=0.05)
    np.testing.assert_allclose(from_euler_zyx_deg(*fields["euler_zyx_deg"]), ISSUE_ROTATION, atol=1e-12)
    np.testing.assert_allclose(fields["yaw_pitch_roll_deg"], [30, -20, 15], atol=1e-9)
    np.testing.assert_allclose(fields["quaternion_xyzw"], [0.1687, -0.1330, 0.2746, 0.9372], atol=5e-5)  # documented


def from_quaternion_xyzw(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The unit quaternion's rotation matrix, written out (scalar last, as ROS's geometry_msgs/Quaternion)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


@pytest.mark.parametrize("seed", range(20))
def test_both_conventions_rebuild_random_rotations(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    fields = pose_fields(R, np.zeros(3))
    np.testing.assert_allclose(from_euler_zyx_deg(*fields["euler_zyx_deg"]), R, atol=1e-9)
    np.testing.assert_allclose(from_yaw_pitch_roll_deg(*fields["yaw_pitch_roll_deg"]), R, atol=1e-9)
    assert -90 <= fields["euler_zyx_deg"][1] <= 90 and -90 <= fields["yaw_pitch_roll_deg"][1] <= 90
    q = fields["quaternion_xyzw"]
    np.testing.assert_allclose(from_quaternion_xyzw(*q), R, atol=1e-9)
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0


def test_returned_angles_rebuild_the_returned_rotation_over_http(client):
    """The example rotation applied to a whole ModelNet40 shape, registered by the server: both angle triples
    rebuild the returned rotation under their documented convention, and the returned pose is the one applied."""
    points = modelnet_pair(4).source.astype(np.float64)  # [700, 3]
    t = np.array([0.1, -0.2, 0.05])
    target = points @ ISSUE_ROTATION.T + t
    response = client.post("/v1/register", json={"source": points.tolist(), "target": target.tolist(),
                                                  "model": MODEL, "rotation_search": True})
    assert response.status_code == 200, response.text
    body = response.json()
    R = np.array(body["rotation"])
    np.testing.assert_allclose(from_euler_zyx_deg(*body["euler_zyx_deg"]), R, atol=1e-9)
    np.testing.assert_allclose(from_yaw_pitch_roll_deg(*body["yaw_pitch_roll_deg"]), R, atol=1e-9)
    np.testing.assert_allclose(from_quaternion_xyzw(*body["quaternion_xyzw"]), R, atol=1e-9)
    # the same points, exactly moved: the pose is found to well under a degree
    np.testing.assert_allclose(body["yaw_pitch_roll_deg"], [30, -20, 15], atol=0.5)
    np.testing.assert_allclose(body["euler_zyx_deg"], [34.5, -9.0, 23.2], atol=0.5)


# -- the OpenAPI document -----------------------------------------------------------------------------
def _resolve(doc: dict, schema: dict) -> tuple[str, dict]:
    ref = schema.get("$ref")
    if ref is None:
        return "", schema
    name = ref.rsplit("/", 1)[-1]
    return name, doc["components"]["schemas"][name]


def _response_properties(doc: dict) -> dict[str, dict]:
    """``"Schema.field" -> property schema`` for every property reachable from any response body."""
    found: dict[str, dict] = {}
    seen: set[str] = set()

    def walk(schema: dict, where: str) -> None:
        name, schema = _resolve(doc, schema)
        if name:
            if name in seen:
                return
            seen.add(name)
            where = name
        for key in ("anyOf", "oneOf", "allOf", "prefixItems"):
            for sub in schema.get(key, []):
                walk(sub, where)
        for key in ("items", "additionalProperties"):
            if isinstance(schema.get(key), dict):
                walk(schema[key], where)
        for prop, sub in schema.get("properties", {}).items():
            found[f"{where}.{prop}"] = sub
            walk(sub, f"{where}.{prop}")

    for path, methods in doc["paths"].items():
        for method, operation in methods.items():
            for status, response in operation.get("responses", {}).items():
                for media, content in response.get("content", {}).items():
                    if "schema" in content:
                        walk(content["schema"], f"{method.upper()} {path} {status} {media}")
    return found


@pytest.fixture(scope="module")
def openapi(client) -> dict:
    return client.get("/openapi.json").json()


def test_every_response_field_has_a_description(openapi):
    properties = _response_properties(openapi)
    assert {"RegisterResponse.euler_zyx_deg", "InferOutputTensor.data", "Quality.residual_rms"} <= set(properties)
    missing = sorted(name for name, prop in properties.items() if not prop.get("description", "").strip())
    assert not missing, f"response fields without a description: {missing}"


@pytest.mark.parametrize(
    ("field", "words"),
    [
        ("RegisterResponse.rotation", ["src_to_tgt", "R p + t"]),
        ("RegisterResponse.translation", ["src_to_tgt", "caller's units"]),
        ("RegisterResponse.transform", ["src_to_tgt", "caller's units", "row-major"]),
        ("RegisterResponse.euler_zyx_deg", ["degrees", "extrinsic", "Rx(c) @ Ry(b) @ Rz(a)", "[34.5, -9.0, 23.2]"]),
        ("RegisterResponse.yaw_pitch_roll_deg", ["degrees", "intrinsic", "Rz(yaw) @ Ry(pitch) @ Rx(roll)"]),
        ("RegisterResponse.timing_ms", ["milliseconds", "queue", "total"]),
        ("RegisterResponse.iteration_poses", ["src_to_tgt", "caller's units"]),
        ("Correspondence.source_index", ["row", "source"]),
        ("Correspondence.target_index", ["row", "target"]),
        ("Quality.inlier_ratio", ["0..1", "inlier distance"]),
        ("Quality.residual_rms", ["caller's units"]),
        ("Quality.stability", ["unitless"]),
        ("InferOutputTensor.shape", ["[4, 4]", "[K]"]),
        ("InferResponse.parameters", ["caller's units", "ms"]),
    ],
)
def test_frames_and_units_are_stated(openapi, field, words):
    description = _response_properties(openapi)[field]["description"]
    for word in words:
        assert word.lower() in description.lower(), (field, word, description)


def test_infer_documents_every_output_name_shape_and_the_binary_extension(openapi):
    text = openapi["paths"]["/v2/models/{name}/infer"]["post"]["description"]
    for words in ("TRANSFORM, FP32 [4, 4]", "src_to_tgt", "SOURCE_INDEX, INT64 [K]", "TARGET_INDEX, INT64 [K]",
                  "CREDIBILITY, FP32 [K]", "binary_data_size", "Inference-Header-Content-Length",
                  "binary_data_output"):
        assert words in text, words
    body = openapi["paths"]["/v2/models/{name}/infer"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/octet-stream"} <= set(body)
