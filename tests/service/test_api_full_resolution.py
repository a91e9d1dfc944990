"""Full-resolution clouds over HTTP: two 2,000,000-point .npy uploads register with bounded server memory."""

from __future__ import annotations

import io

import numpy as np
from api_server import assert_error, main_server
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

POINTS = 2_000_000  # the default per-cloud limit of file uploads (MFGNET_MAX_FILE_POINTS)
PEAK_MIB = 2048  # the largest accepted request must fit in this much server memory


def npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points.astype(np.float32))
    return buffer.getvalue()


def peak_rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) / 1024 for line in status if line.startswith("VmHWM:"))


def test_two_full_resolution_clouds_register_within_the_memory_bound():
    server = main_server()
    rotation = Rotation.from_euler("zyx", [25.0, -10.0, 5.0], degrees=True).as_matrix()
    source = asymmetric_blob(POINTS, 0)  # [2M, 3] independent samples of one surface
    target = asymmetric_blob(POINTS, 1) @ rotation.T + [0.2, -0.1, 0.05]
    files = {"source": ("source.npy", npy(source)), "target": ("target.npy", npy(target))}
    del source, target
    with server.client() as client:
        response = client.post("/v1/register", files=files)
    assert response.status_code == 200, response.text[:300]
    body = response.json()
    error = np.degrees(np.arccos(np.clip((np.trace(np.array(body["rotation"]).T @ rotation) - 1) / 2, -1, 1)))
    assert error < 1.0 and body["quality"]["reliable"]
    assert peak_rss_mib(server.extra["proc"].pid) < PEAK_MIB


def test_one_point_above_the_limit_is_refused_with_413():
    server = main_server()
    files = {"source": ("big.npy", npy(np.zeros((POINTS + 1, 3)))), "target": ("t.npy", npy(np.ones((64, 3))))}
    with server.client() as client:
        assert_error(client.post("/v1/register", files=files), 413, "source", "2000000")
