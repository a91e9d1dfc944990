"""The server's temporary folder (``TMPDIR``, else ``/tmp``) gone or full after the server started: an upload past
1 MiB (spooled there) and an aligned answer (written there) are 503s saying so, with ``Retry-After``, not 500s; the
server stays up and answers again once the folder is back."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from api_server import assert_error, start_subprocess_server

from service.formats import write_cloud


def npy(points: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, points)
    return buffer.getvalue()


def ply(points: np.ndarray, folder: Path) -> bytes:
    """A binary PLY of ``points``."""
    write_cloud(folder / "cloud.ply", points)
    return (folder / "cloud.ply").read_bytes()


@pytest.fixture(scope="module")
def server_and_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("server_tmp")
    server = start_subprocess_server("temp_storage", TMPDIR=str(folder))
    yield server, folder
    server.stop()


def test_a_temporary_folder_gone_is_a_503_saying_so_and_the_server_answers_once_it_is_back(server_and_folder,
                                                                                            tmp_path) -> None:
    server, folder = server_and_folder
    scratch = tmp_path
    rng = np.random.default_rng(0)
    large = npy(rng.normal(size=(100_000, 3)).astype(np.float32))  # 1.2 MB: spooled to the folder
    small = npy(rng.normal(size=(2_000, 3)).astype(np.float32))  # kept in memory
    with server.client() as client:
        answer = client.post("/v1/register", files={"source": ("a.npy", large), "target": ("b.npy", large)})
        assert answer.status_code == 200, answer.text  # the folder is found (Python keeps it) and used
        shutil.rmtree(folder)
        answer = client.post("/v1/register", files={"source": ("a.npy", large), "target": ("b.npy", large)})
        assert_error(answer, 503, "could not write the upload to its temporary folder", "full or not writable")
        assert answer.headers["retry-after"] == "5"
        answer = client.post("/v1/register/aligned", files={"source": ("a.npy", small)},
                             data={"transform": json.dumps(np.eye(4).tolist())})
        assert_error(answer, 503, "could not write the moved file to its temporary folder")
        small_ply = ply(rng.normal(size=(2_000, 3)).astype(np.float32), scratch)  # copied to a file to be read
        answer = client.post("/v1/register", files={"source": ("a.ply", small_ply), "target": ("b.ply", small_ply)})
        assert_error(answer, 503, "could not write a copy of the upload to its temporary folder")
        folder.mkdir()
        answer = client.post("/v1/register", files={"source": ("a.npy", large), "target": ("b.npy", large)})
        assert answer.status_code == 200, answer.text
