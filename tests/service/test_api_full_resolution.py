"""Full-resolution clouds over HTTP: two 2,000,000-point .npy uploads register with bounded server memory."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest
from api_server import assert_error, main_server, start_subprocess_server

from bench.full_resolution import full_resolution_pair, rotation_error_deg
from bench.full_resolution import npy_bytes as npy

POINTS = 2_000_000  # the default per-cloud limit of file uploads (MFGNET_MAX_FILE_POINTS)
PEAK_MIB = 2048  # the largest accepted request must fit in this much server memory
DEPLOYMENT = Path(__file__).resolve().parents[2] / "deploy" / "k8s" / "deployment.yaml"


def peak_rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) / 1024 for line in status if line.startswith("VmHWM:"))


def full_resolution_upload(seed: int, degrees: float) -> tuple[dict, np.ndarray]:
    """The two 2,000,000-point clouds of ``bench.full_resolution`` as float32 ``.npy`` files: the multipart files and
    the true rotation ``[3, 3]``."""
    source, target, rotation = full_resolution_pair(seed, degrees, POINTS)
    return {"source": ("source.npy", npy(source)), "target": ("target.npy", npy(target))}, rotation


def assert_registered(response: httpx.Response, rotation: np.ndarray) -> None:
    assert response.status_code == 200, response.text[:300]
    body = response.json()
    assert rotation_error_deg(np.array(body["rotation"]), rotation) < 1.0 and body["quality"]["reliable"]


def test_two_full_resolution_clouds_register_within_the_memory_bound():
    server = main_server()
    files, rotation = full_resolution_upload(0, 25.0)
    with server.client() as client:
        assert_registered(client.post("/v1/register", files=files), rotation)
    peak = peak_rss_mib(server.extra["proc"].pid)
    print(f"peak server RSS {peak:.0f} MiB")
    assert peak < PEAK_MIB


def manifest_memory_limit_mib() -> float:
    """The memory limit of the Kubernetes manifest's container (``deploy/k8s/deployment.yaml``), in MiB."""
    yaml = pytest.importorskip("yaml")
    deployment = yaml.safe_load(DEPLOYMENT.read_text())
    limit = deployment["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"]["memory"]
    assert limit.endswith("Gi") or limit.endswith("Mi"), limit
    return float(limit[:-2]) * (1024 if limit.endswith("Gi") else 1)


@pytest.mark.slow
def test_two_full_resolution_requests_at_once_fit_the_manifests_memory_limit():
    """The manifest's server (every bundled model, one thread, two requests at once), each request uploading two
    2,000,000-point clouds, both at once: the server's peak memory stays below the manifest's limit."""
    server = start_subprocess_server("manifest", MFGNET_BUNDLED_MODELS="true", MFGNET_MODEL_DIRS="",
                                     MFGNET_DEFAULT_MODEL="general", MFGNET_MAX_CONCURRENCY="2")
    uploads = [full_resolution_upload(seed, degrees) for seed, degrees in ((0, 25.0), (1, 65.0))]
    with server.client() as client, ThreadPoolExecutor(2) as pool:
        responses = list(pool.map(lambda upload: client.post("/v1/register", files=upload[0]), uploads))
    for response, (_, rotation) in zip(responses, uploads, strict=True):
        assert_registered(response, rotation)
    peak, limit = peak_rss_mib(server.extra["proc"].pid), manifest_memory_limit_mib()
    print(f"peak server RSS {peak:.0f} MiB, manifest limit {limit:.0f} MiB")
    assert peak < limit


def test_one_point_above_the_limit_is_refused_with_413():
    server = main_server()
    files = {"source": ("big.npy", npy(np.zeros((POINTS + 1, 3)))), "target": ("t.npy", npy(np.ones((64, 3))))}
    with server.client() as client:
        assert_error(client.post("/v1/register", files=files), 413, "source", "2000000")


def few_distinct(rows: int, distinct: int, seed: int) -> np.ndarray:
    """``[rows, 3]``: one point stacked ``rows - distinct + 1`` times (a sensor's invalid returns), and
    ``distinct - 1`` others."""
    points = np.zeros((rows, 3))
    points[: distinct - 1] = np.random.default_rng(seed).normal(size=(distinct - 1, 3))
    return points


@pytest.mark.parametrize(("rows", "distinct", "kind"), [(POINTS, 1, "identical"), (300_000, 11, "few distinct points")])
def test_full_resolution_stacks_of_one_point_get_a_pose_and_warnings(rows, distinct, kind):
    """Reduced on entry, a cloud of a few distinct points stacked to full resolution keeps enough rows to judge: the
    answer is a pose that is not ``reliable``, with warnings, never an error."""
    server = main_server()
    files = {"source": ("source.npy", npy(few_distinct(rows, distinct, 0))),
             "target": ("target.npy", npy(few_distinct(rows, distinct, 1)))}
    with server.client() as client:
        response = client.post("/v1/register", files=files)
    assert response.status_code == 200, response.text[:300]
    body = response.json()
    assert np.isfinite(body["transform"]).all() and not body["quality"]["reliable"]
    assert any(warning.startswith(f"source {kind}") for warning in body["warnings"]), body["warnings"]
