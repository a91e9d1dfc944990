"""The page's HTTP side against the main uvicorn server: ``GET /``, ``POST /v1/register/view`` and
``POST /v1/register/aligned`` (the browser itself is driven in ``test_page_browser.py``)."""

from __future__ import annotations

import base64
import fnmatch
import io
import json

import numpy as np
import pytest
from api_server import REPO, assert_error, synthetic_pair

from service.api.routes.page import DISPLAY_CAP, WEB_DIR, decimated_rows, display_cloud
from service.pointcloud_io import parse_points, write_points


def file_bytes(tmp_path, name: str, points: np.ndarray) -> bytes:
    write_points(tmp_path / name, points)
    return (tmp_path / name).read_bytes()


def npy_bytes(points: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, points)
    return buf.getvalue()


def shown(cloud: dict) -> np.ndarray:
    return np.frombuffer(base64.b64decode(cloud["xyz"]), dtype="<f4").reshape(-1, 3)  # [n, 3]


def test_view_answers_what_register_answers_plus_the_display_clouds(client, tmp_path):
    pair = synthetic_pair(seed=5)
    files = {
        "source": ("a.pcd", file_bytes(tmp_path, "a.pcd", pair.source)),
        "target": ("b.xyz", file_bytes(tmp_path, "b.xyz", pair.target)),
    }
    options = {"refine": "icp", "drop_isolated": "false", "return_correspondences": "false"}
    view = client.post("/v1/register/view", files=files, data=options)
    assert view.status_code == 200, view.text
    body = view.json()
    plain = client.post("/v1/register", files=files, data=options).json()  # the same files: the same reader
    for key in ("rotation", "translation", "transform", "euler_zyx_deg", "quality", "warnings", "model"):
        assert body["result"][key] == plain[key], key
    assert body["display"]["cap"] == DISPLAY_CAP
    for name, points in (("source", pair.source), ("target", pair.target)):
        cloud = body["display"][name]
        assert cloud["points"] == cloud["shown"] == len(points)
        np.testing.assert_array_equal(shown(cloud), points)


def test_decimated_keeps_at_most_the_cap_rows_of_the_cloud_in_order():
    points = np.arange(3 * 250, dtype=np.float64).reshape(250, 3)  # row i starts with 3 i
    kept = decimated_rows(points, cap=100)
    assert kept.shape == (100, 3)
    rows = kept[:, 0].astype(int) // 3
    assert np.all(np.diff(rows) > 0)  # distinct rows, file order
    np.testing.assert_array_equal(kept, points[rows])
    np.testing.assert_array_equal(decimated_rows(points, cap=100), kept)  # seeded
    np.testing.assert_array_equal(decimated_rows(points, cap=250), points)


def test_display_rows_of_a_cloud_in_utm_are_sent_relative_to_its_box():
    """float32 keeps a UTM cloud's shape only near its own box: the rows come relative to its centre, the origin sent
    beside them in float64 (they were float32 in the caller's frame, on a 0.25-0.5 m grid); a local cloud's rows are
    its own, origin zero."""
    rng = np.random.default_rng(0)
    local = rng.normal(scale=0.1, size=(500, 3))  # [500, 3] metres
    far = local + np.array([512_345.25, 5_412_345.5, 229.75])
    sent = display_cloud(far)
    origin = np.asarray(sent["origin"])
    rows = np.frombuffer(base64.b64decode(sent["xyz"]), dtype="<f4").reshape(-1, 3).astype(np.float64)
    np.testing.assert_array_equal(origin, np.round((far.min(0) + far.max(0)) / 2))
    assert np.abs(rows + origin - far).max() < 1e-6  # micrometres, not decimetres
    near = display_cloud(local)
    assert near["origin"] == [0.0, 0.0, 0.0]
    np.testing.assert_array_equal(np.frombuffer(base64.b64decode(near["xyz"]), dtype="<f4").reshape(-1, 3),
                                  local.astype(np.float32))


def test_aligned_returns_every_source_point_moved_by_the_transform_as_ply(client, tmp_path):
    pair = synthetic_pair(seed=6)
    R, t = pair.rotation, pair.translation
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    response = client.post(
        "/v1/register/aligned",
        files={"source": ("scan 1.ply", file_bytes(tmp_path, "s.ply", pair.source))},
        data={"transform": json.dumps(T.tolist())},
    )
    assert response.status_code == 200, response.text
    assert response.headers["content-disposition"] == 'attachment; filename="scan_1_aligned.ply"'
    moved = parse_points(response.content, ".ply", "aligned.ply")  # [N, 3]
    expected = pair.source.astype(np.float64) @ R.T + t
    assert moved.shape == pair.source.shape
    assert np.abs(moved - expected).max() <= 1e-6 * np.abs(expected).max()


def test_aligned_keeps_map_coordinates_in_float64(client, tmp_path):
    """The download was float32 whatever the source: a scan in UTM coordinates came back in steps of 0.25-0.5 m."""
    source = synthetic_pair(seed=6).source.astype(np.float64) + np.array([512_345.0, 4_123_456.0, 150.0])
    np.save(tmp_path / "utm.npy", source)
    T = np.eye(4)
    T[:3, 3] = [0.125, -0.5, 2.0]
    response = client.post("/v1/register/aligned", data={"transform": json.dumps(T.tolist())},
                           files={"source": ("utm.npy", (tmp_path / "utm.npy").read_bytes())})
    assert response.status_code == 200, response.text
    moved = parse_points(response.content, ".ply", "aligned.ply")  # [N, 3]
    np.testing.assert_allclose(moved, source + T[:3, 3], rtol=0, atol=1e-6)


def test_aligned_names_a_download_of_any_script_in_ascii_and_in_utf_8(client, tmp_path):
    """HTTP headers are Latin-1: a source named in Cyrillic or CJK made the download a 500 after the whole file was
    read and moved."""
    response = client.post(
        "/v1/register/aligned",
        files={"source": ("скан 日本.ply", file_bytes(tmp_path, "s.ply", synthetic_pair(seed=6).source))},
        data={"transform": json.dumps(np.eye(4).tolist())},
    )
    assert response.status_code == 200, response.text
    assert response.headers["content-disposition"] == (
        "attachment; filename=\"________aligned.ply\"; "
        "filename*=UTF-8''%D1%81%D0%BA%D0%B0%D0%BD_%E6%97%A5%E6%9C%AC_aligned.ply")


def test_bad_uploads_are_4xx_naming_the_problem(client, tmp_path):
    good = file_bytes(tmp_path, "g.ply", synthetic_pair(seed=7).source)
    bad = {"source": ("bad.ply", b"ply\nnot a header"), "target": ("g.ply", good)}
    assert_error(client.post("/v1/register/view", files=bad), 400, "bad.ply")
    assert_error(client.post("/v1/register/view", files={"source": ("g.ply", good)}), 422, "target", "missing")
    assert_error(client.post("/v1/register/view", json={"source": [], "target": []}), 415, "multipart/form-data")
    assert_error(
        client.post("/v1/register/view", files={"source": ("g.ply", good), "target": ("g.ply", good)},
                    data={"refine": "sideways"}),
        422, "refine",
    )
    aligned = "/v1/register/aligned"
    assert_error(client.post(aligned, files={"source": ("g.ply", good)}), 422, "transform", "missing")
    for transform, words in (
        ("[[1, 2]]", ("transform", "4x4")),
        ('[["a", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]', ("transform", "numbers")),
        ('[["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]', ("transform", "numbers")),  # numpy read "1"
        ("[[true, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]", ("transform", "numbers")),
        (json.dumps((2 * np.eye(4)).tolist()), ("transform", "rigid")),
        ("not json", ("transform", "json")),
        ("[" * 30_000 + "]" * 30_000, ("transform", "json")),  # nested deeper than json can read
    ):
        answer = client.post(aligned, files={"source": ("g.ply", good)}, data={"transform": transform})
        assert_error(answer, 422, *words)


def test_index_is_the_page_with_local_assets_only(client):
    response = client.get("/")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
    assert response.headers["content-security-policy"].startswith("default-src 'self'")
    html = response.text
    assert "http://" not in html and "https://" not in html
    for asset in ("page/page.css", "page/viewer.js", "page/page.js"):
        assert f'"{asset}"' in html
        served = client.get("/" + asset)
        assert served.status_code == 200 and served.content == (WEB_DIR / asset.removeprefix("page/")).read_bytes()


def test_the_page_and_docs_assets_ship_in_the_wheel():
    """Every file of service/web matches the package data globs, and the docs assets come from the serve extra."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    globs = config["tool"]["setuptools"]["package-data"]["service"]
    files = [p.relative_to(WEB_DIR.parent).as_posix() for p in WEB_DIR.rglob("*") if p.is_file()]
    assert files
    for name in files:
        assert any(fnmatch.fnmatch(name, g) for g in globs), name
    assert any(dep.startswith("fastapi-offline==") for dep in config["project"]["optional-dependencies"]["serve"])
