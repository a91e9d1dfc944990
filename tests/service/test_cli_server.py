"""``mfgnet register --server`` and ``service.client`` against a real ``mfgnet serve`` (uvicorn, a
subprocess on 127.0.0.1, torch hidden as in the container): same pose as in-process, the server's
error messages on 4xx."""

from __future__ import annotations

import json
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from cli_support import python_without_torch, snapshot_model, synthetic_pair
from typer.testing import CliRunner

import service
from service.cli import app
from service.client import MfgnetClient, MfgnetError
from service.pointcloud_io import read_points

pytestmark = pytest.mark.skipif(not (Path(service.__file__).parent / "api" / "app.py").exists(),
                                reason="service/api/app.py does not exist yet")
runner = CliRunner()
OPTIONS = ("--iterations", "2", "--keypoints", "64")  # small and fast; the same on both sides
MFGNET = "import sys; sys.argv = ['mfgnet', *sys.argv[1:]]; from service.cli import main; main()"
SOURCE, TARGET = synthetic_pair()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return snapshot_model(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="module")
def server(tmp_path_factory, model_dir) -> str:
    """Base URL of ``mfgnet serve --model-dir <snapshot>`` (bundled models off), ready."""
    workdir = tmp_path_factory.mktemp("server")
    python, env = python_without_torch(workdir)
    env.update(MFGNET_BUNDLED_MODELS="false", MFGNET_API_KEY="", MFGNET_LOG_LEVEL="warning")
    port = free_port()
    args = ["serve", "--host", "127.0.0.1", "--port", str(port), "--model-dir", str(model_dir), "--threads", "1"]
    log_path = workdir / "server.log"
    with log_path.open("w") as log:
        process = subprocess.Popen([*python, "-c", MFGNET, *args], env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        with MfgnetClient(url) as client:
            deadline = time.monotonic() + 90
            while not client.ready():
                if process.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"mfgnet serve did not become ready:\n{log_path.read_text()[-3000:]}")
                time.sleep(0.2)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@pytest.fixture
def pair_files(tmp_path) -> tuple[Path, Path]:
    src, tgt = tmp_path / "source.ply", tmp_path / "target.pcd"
    from service.pointcloud_io import write_points

    write_points(src, SOURCE)
    write_points(tgt, TARGET)
    return src, tgt


def register(*args) -> tuple[int, dict | None, str]:
    result = runner.invoke(app, ["register", *map(str, args), *OPTIONS, "--json"])
    record = json.loads(result.stdout) if result.exit_code == 0 else None
    return result.exit_code, record, result.stderr


@pytest.mark.parametrize("upload", ["json", "binary"])
def test_server_mode_gives_the_same_transform_as_in_process(server, model_dir, pair_files, tmp_path, upload):
    src, tgt = pair_files
    code, local, err = register(src, tgt, "--model-dir", model_dir)
    assert code == 0, err
    aligned = tmp_path / "aligned.npz"
    extra = ["--no-binary"] if upload == "json" else []  # .npy uploads by default
    code, remote, err = register(src, tgt, "--server", server, "--write-aligned", aligned, *extra)
    assert code == 0, err
    assert remote["model"]["sha256"] == local["model"]["sha256"]
    assert np.allclose(remote["transform"], local["transform"], atol=1e-4)
    assert remote["iterations"] == local["iterations"] == 2
    assert set(remote) == set(local) and "queue" in remote["timing_ms"]
    R, t = np.asarray(remote["rotation"]), np.asarray(remote["translation"])
    assert np.allclose(read_points(aligned), SOURCE.astype(np.float64) @ R.T + t, atol=1e-5)


@pytest.mark.parametrize("upload", ["json", "binary"])
def test_server_mode_keeps_map_coordinates(server, model_dir, tmp_path, upload):
    """Clouds 4,000 km from the origin (UTM): the command cast them to float32 before the client could re-centre
    them (0.25-0.5 m steps on a unit-size shape), and the pose came back degrees off, still reliable."""
    offset = np.array([512_345.0, 4_123_456.0, 150.0])
    src, tgt = tmp_path / "s.npy", tmp_path / "t.npy"
    np.save(src, SOURCE.astype(np.float64) + offset)
    np.save(tgt, TARGET.astype(np.float64) + offset)
    code, local, err = register(src, tgt, "--model-dir", model_dir)
    assert code == 0, err
    code, remote, err = register(src, tgt, "--server", server, *(["--no-binary"] if upload == "json" else []))
    assert code == 0, err
    np.testing.assert_allclose(remote["rotation"], local["rotation"], atol=1e-4)
    np.testing.assert_allclose(remote["translation"], local["translation"], atol=1e-2)


def test_server_mode_gives_up_after_its_timeout_and_names_the_url_scheme(tmp_path, pair_files) -> None:
    with socket.socket() as silent:  # accepts connections, never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        started = time.monotonic()
        result = runner.invoke(app, ["register", *map(str, pair_files), "--server",
                                     f"http://127.0.0.1:{silent.getsockname()[1]}", "--timeout", "1"])
        assert result.exit_code == 1 and time.monotonic() - started < 10, result.output
    result = runner.invoke(app, ["register", *map(str, pair_files), "--server", "127.0.0.1:8080"])
    assert result.exit_code == 2 and "http://" in result.stderr


def test_server_refusal_exits_2_with_the_servers_message(server, tmp_path, pair_files) -> None:
    small = tmp_path / "small.npy"
    np.save(small, SOURCE[:5])
    code, _, err = register(small, pair_files[1], "--server", server)
    assert code == 2
    assert "server: HTTP 4" in err and "32" in err and "Traceback" not in err


def test_client_raises_mfgnet_error_with_the_servers_message_on_4xx(server) -> None:
    with MfgnetClient(server) as client:
        with pytest.raises(MfgnetError) as info:
            client.register(SOURCE[:5], TARGET)
        assert 400 <= info.value.status < 500
        assert "source" in info.value.message and "32" in info.value.message
        with pytest.raises(MfgnetError) as info:
            client.register(SOURCE, TARGET, model="nope")
        assert info.value.status == 404 and "nope" in info.value.message


def test_client_sees_the_served_model_and_readiness(server) -> None:
    with MfgnetClient(server) as client:
        assert client.ready()
        client.wait_ready(timeout=1)
        assert [m["name"] for m in client.models()] == ["clean"]
        response = client.register(SOURCE, TARGET, iterations=1, keypoints=32)
    assert len(response["correspondences"]) == 32
    assert {"source_index", "target_index", "credibility", "weight"} == set(response["correspondences"][0])


def with_non_finite(points: np.ndarray, row: int, value: float = np.nan) -> np.ndarray:
    """A float64 copy of ``points [N, 3]`` whose ``row`` holds ``value`` in its first coordinate."""
    bad = np.array(points, dtype=np.float64)
    bad[row, 0] = value
    return bad


@pytest.mark.parametrize("binary", [False, True])
def test_client_nan_cloud_is_the_servers_422_naming_one_row_and_the_first(server, binary) -> None:
    with MfgnetClient(server) as client, pytest.raises(MfgnetError) as info:
        client.register(with_non_finite(SOURCE, 3), TARGET, binary=binary)
    assert info.value.status == 422
    assert "source" in info.value.message and "1 point(s)" in info.value.message
    assert "first at index 3" in info.value.message


def test_client_infinite_target_in_nested_lists_is_the_servers_422(server) -> None:
    with MfgnetClient(server) as client, pytest.raises(MfgnetError) as info:
        client.register(SOURCE.tolist(), with_non_finite(TARGET, 7, -np.inf).tolist())
    assert info.value.status == 422
    assert "target" in info.value.message and "1 point(s)" in info.value.message
    assert "first at index 7" in info.value.message


def test_client_nan_initial_transform_is_the_servers_422(server) -> None:
    transform = np.eye(4)
    transform[0, 3] = np.nan
    with MfgnetClient(server) as client, pytest.raises(MfgnetError) as info:
        client.register(SOURCE, TARGET, initial_transform=transform)
    assert info.value.status == 422 and "initial_transform" in info.value.message


def test_client_takes_lists_of_numpy_rows_and_numpy_scalar_options(server) -> None:
    with MfgnetClient(server) as client:
        plain = client.register(SOURCE, TARGET, iterations=1, keypoints=32, refine="none")
        numpy_typed = client.register(list(SOURCE), list(TARGET.astype(np.float64)), iterations=np.int64(1),
                                      keypoints=np.int32(32), refine=np.str_("none"),
                                      return_correspondences=np.bool_(True), initial_transform=list(np.eye(4)))
    assert np.allclose(numpy_typed["transform"], plain["transform"], atol=1e-5)
    assert len(numpy_typed["correspondences"]) == 32


def test_client_takes_numpy_float32_timeouts(server) -> None:
    with MfgnetClient(server, timeout=np.float32(30)) as client:
        client.wait_ready(timeout=np.float32(1), interval=np.float32(0.01))
        assert client.register(SOURCE, TARGET, iterations=1, keypoints=32)["iterations"] == 1


def test_server_mode_writes_the_source_file_moved_with_its_colours(server, tmp_path):
    """The aligned file is written here from the local source file, whatever computed the pose: a coloured PLY keeps
    its colours through --server as in process."""
    import plyfile

    vertex = np.empty(len(SOURCE), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("alpha", "u1")])
    for axis, name in enumerate("xyz"):
        vertex[name] = SOURCE[:, axis]
    vertex["red"], vertex["alpha"] = np.arange(len(SOURCE)) % 251, 255
    src, tgt, aligned = tmp_path / "scan.ply", tmp_path / "target.npy", tmp_path / "aligned.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(src))
    np.save(tgt, TARGET)
    code, remote, err = register(src, tgt, "--server", server, "--write-aligned", aligned)
    assert code == 0, err
    rows = plyfile.PlyData.read(str(aligned))["vertex"].data
    assert rows["red"].tobytes() == vertex["red"].tobytes() and rows["alpha"].tobytes() == vertex["alpha"].tobytes()
    R, t = np.asarray(remote["rotation"]), np.asarray(remote["translation"])
    np.testing.assert_allclose(read_points(aligned), SOURCE.astype(np.float64) @ R.T + t, atol=1e-5)


def test_server_mode_checks_the_aligned_source_before_anything_is_sent(tmp_path):
    """--write-aligned's check of the source file (:func:`service.cli.common.check_aligned_source`) runs before the
    upload, as in process: the usage error names the file though nothing listens at the address (the upload would have
    been exit 1, server unreachable), and no aligned file is written."""
    wide = np.zeros((len(SOURCE), 40), dtype=np.int16)  # [N, 40]: 80 bytes a row, 320 as float64
    wide[:, :3] = np.round(SOURCE * 1000)
    src, tgt, aligned = tmp_path / "wide.npy", tmp_path / "target.npy", tmp_path / "aligned.npy"
    np.save(src, wide)
    np.save(tgt, TARGET * 1000)
    code, _, err = register(src, tgt, "--server", f"http://127.0.0.1:{free_port()}", "--write-aligned", aligned)
    assert code == 2, err
    assert "aligned.npy: wide.npy cannot be written moved as NPY: rows of 40 int16 values would be 320" in " ".join(
        err.split()
    )
    assert not aligned.exists()
