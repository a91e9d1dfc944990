"""``service.in_process.LocalRegistrar``: the in-process API gives the pose ``mfgnet register`` (in process) and a
real server give for the same real pair and options, and takes arrays or files; one instance serves many threads."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from api_server import start_subprocess_server
from cli_support import synthetic_pair
from real_scan_cases import skip_without
from typer.testing import CliRunner

from bench.real_scans import data_dir, pose_errors
from service.cli import app
from service.errors import InputError
from service.in_process import LocalRegistrar
from service.manifest import bundled_models_dir
from service.pointcloud_io import write_points
from service.registrar import Registrar

PAIR = "dragon_24_0"  # a real range-image pair of the development set; ~35,000 and ~42,000 points
OPTION_SETS = [{}, {"refine": "none"}, {"refine": "icp"}]  # no option; the rotation search's default follows refine


def cli_flags(options: dict) -> list[str]:
    return [arg for key, value in options.items() for arg in (f"--{key.replace('_', '-')}", str(value))]


@pytest.fixture(scope="module")
def real_pair(tmp_path_factory) -> tuple[np.ndarray, np.ndarray, str, str]:
    """``PAIR``'s source and target (float64) and the ``.npy`` files holding them (a temporary folder)."""
    skip_without(PAIR)
    with np.load(data_dir() / f"{PAIR}.npz") as data:
        source, target = data["source"].astype(np.float64), data["target"].astype(np.float64)
    folder = tmp_path_factory.mktemp("real")
    np.save(folder / "source.npy", source)
    np.save(folder / "target.npy", target)
    return source, target, str(folder / "source.npy"), str(folder / "target.npy")


@pytest.fixture(scope="module")
def local() -> LocalRegistrar:
    if not (bundled_models_dir() / "general" / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    return LocalRegistrar()  # the default model, "general"; two ONNX Runtime threads where two cores are


@pytest.fixture(scope="module")
def general_server(real_pair):
    """A real server (a subprocess, one ONNX Runtime thread) serving only the bundled ``general``, its default."""
    server = start_subprocess_server("in-process", MFGNET_BUNDLED_MODELS="true", MFGNET_MODELS="general",
                                     MFGNET_DEFAULT_MODEL="general")
    yield server
    server.stop()


@pytest.mark.parametrize("options", OPTION_SETS, ids=lambda o: json.dumps(o))
def test_in_process_cli_and_server_give_one_pose_for_a_real_pair(local, real_pair, general_server, options):
    source, target, source_file, target_file = real_pair
    in_process = local.register(source, target, **options)

    cli = CliRunner().invoke(app, ["register", source_file, target_file, "--json", *cli_flags(options)])
    assert cli.exit_code == 0, cli.output
    with general_server.client() as client:
        response = client.post("/v1/register", json={"source": source.tolist(), "target": target.tolist(), **options})
    assert response.status_code == 200, response.text

    record, body = json.loads(cli.stdout), response.json()
    assert record["model"] == body["model"] == {"name": "general", "version": local.manifest.version,
                                                "sha256": local.manifest.sha256}
    np.testing.assert_allclose(record["transform"], in_process.transform, rtol=0, atol=1e-9)
    np.testing.assert_allclose(body["transform"], in_process.transform, rtol=0, atol=1e-9)
    for field in ("quaternion_xyzw", "euler_zyx_deg", "yaw_pitch_roll_deg"):  # a ROS node's pose, as the response's
        np.testing.assert_allclose(getattr(in_process, field), body[field], rtol=0, atol=1e-7, err_msg=field)
        np.testing.assert_allclose(record[field], body[field], rtol=0, atol=1e-7, err_msg=field)
    assert record["warnings"] == body["warnings"] == in_process.warnings
    assert record["quality"]["reliable"] is body["quality"]["reliable"] is in_process.reliable
    assert ("search" in body["timing_ms"]) is ("search" in in_process.timing_ms)  # the same default search ran


def test_no_option_is_the_services_defaults_not_the_bare_registrars(local, real_pair):
    """What the API is for: ``Registrar.register`` alone runs the paper's pipeline (no refinement), and its pose on a
    real pair is another, worse one."""
    source, target, _, _ = real_pair
    with np.load(data_dir() / f"{PAIR}.npz") as data:
        truth = data["transform"]
    served, bare = local.register(source, target), local.registrar.register(source, target)
    explicit = local.registrar.register(source, target, refine="icp-plane", rotation_search="auto")
    np.testing.assert_allclose(served.transform, explicit.transform, rtol=0, atol=1e-12)
    served_degrees, _ = pose_errors(served.rotation, served.translation, truth)
    bare_degrees, _ = pose_errors(bare.rotation, bare.translation, truth)
    assert served_degrees < 1.0 < bare_degrees, (served_degrees, bare_degrees)


def test_files_and_arrays_give_one_pose(local, tmp_path):
    source, target = synthetic_pair()
    write_points(tmp_path / "source.ply", source)
    write_points(tmp_path / "target.pcd", target)
    from_arrays = local.register(source, target)
    from_files = local.register(tmp_path / "source.ply", str(tmp_path / "target.pcd"))
    np.testing.assert_allclose(from_files.transform, from_arrays.transform, rtol=0, atol=1e-9)


def test_one_instance_shared_by_threads_gives_the_sequential_results(local):
    pairs = [synthetic_pair(seed) for seed in (0, 1, 2, 0, 1, 2)]
    sequential = [local.register(source, target).transform for source, target in pairs]
    with ThreadPoolExecutor(3) as pool:
        concurrent = list(pool.map(lambda pair: local.register(*pair).transform, pairs))
    for one, other in zip(sequential, concurrent, strict=True):
        np.testing.assert_array_equal(one, other)


def test_a_model_folder_loads_like_its_name(local):
    folder = LocalRegistrar(bundled_models_dir() / "general", warmup=False)
    assert isinstance(folder.registrar, Registrar) and folder.manifest.sha256 == local.manifest.sha256


@pytest.mark.parametrize("name", ["nope", ""])  # "" named the folder of bundled models
def test_an_unknown_model_is_a_value_error_naming_the_bundled_ones(name):
    with pytest.raises(ValueError, match=rf"'{name}'.*general"):
        LocalRegistrar(name)


def test_a_missing_model_folder_is_a_value_error_not_a_damaged_model(tmp_path):
    with pytest.raises(ValueError, match="no such folder"):  # was ModelIntegrityError: manifest.json is missing
        LocalRegistrar(tmp_path / "no" / "such" / "folder")


@pytest.mark.parametrize("threads", [0, -1, 65, 300, 2.5, "2", True])
def test_threads_out_of_the_command_lines_range_are_a_value_error(threads):
    """ONNX Runtime took 300 (1,500 OS threads) and -1, and answered 2.5 with a binding's TypeError."""
    with pytest.raises(ValueError, match=r"threads must be a whole number in 1\.\.64"):
        LocalRegistrar(threads=threads, warmup=False)


def test_threads_as_a_numpy_integer_are_taken():
    assert LocalRegistrar(threads=np.int64(1), warmup=False).manifest.name == "general"


def test_a_bad_option_is_an_input_error_naming_it(local):
    source, target = synthetic_pair()
    with pytest.raises(InputError, match="keypoints"):
        local.register(source, target, keypoints=4)


BAD_OPTIONS = [  # each the server's 422; in process they were cut (64.7 -> 64), read as truthy or raised raw errors
    ({"keypoints": 64.7}, "keypoints must be a whole number"),
    ({"iterations": 2.9}, "iterations must be a whole number"),
    ({"keypoints": "abc"}, "keypoints must be a whole number"),
    ({"refine_points": "x"}, "refine_points must be a whole number"),
    ({"refine": "none", "refine_points": 1000}, "refine_points sets the refinement's clouds; refine none runs no "),
    ({"refine": ""}, "refine must be one of"),
    ({"return_iterations": "false"}, "return_iterations must be true or false"),
    ({"drop_isolated": "false"}, "drop_isolated must be true or false"),
    ({"return_correspondences": "no"}, "return_correspondences must be true or false"),
    ({"icp_max_distance": -1.0}, "icp_max_distance must be a positive number"),
    ({"refine": "none", "icp_max_distance": 0.01}, "icp_max_distance sets the refinement's pairing distance; refine "),
    ({"initial_transform": "pose.json"}, "initial_transform must be a 4x4 matrix of numbers"),
    ({"initial_transform": [[1, 0, 0], [0, 1, 0, 0]]}, "initial_transform must be a 4x4 matrix of numbers"),
]


@pytest.mark.parametrize(("options", "message"), BAD_OPTIONS, ids=[json.dumps(options) for options, _ in BAD_OPTIONS])
def test_a_wrongly_typed_option_is_an_input_error_naming_it(local, options, message):
    source, target = synthetic_pair()
    with pytest.raises(InputError, match=message):
        local.register(source, target, **options)


def test_whole_numbers_and_numpy_flags_are_taken_as_the_server_takes_them(local):
    source, target = synthetic_pair()
    plain = local.register(source, target, keypoints=64, iterations=2, drop_isolated=False)
    spelled = local.register(source, target, keypoints=64.0, iterations="2", drop_isolated=np.bool_(False),
                             return_correspondences=False)
    np.testing.assert_array_equal(plain.transform, spelled.transform)



@pytest.mark.parametrize(("options", "message"), [
    ({"model": "clean"}, "unknown option model .*the model is chosen by LocalRegistrar\\(model\\)"),
    ({"keypoint": 64}, "unknown option keypoint \\(options: .*keypoints"),
])
def test_an_unknown_option_is_an_input_error_naming_it(local, options, message):
    """As the server's 422; it was RegistrationOptions' own TypeError."""
    source, target = synthetic_pair()
    with pytest.raises(InputError, match=message):
        local.register(source, target, **options)


def test_search_rotations_is_checked_whether_or_not_a_search_runs(local):
    source, target = synthetic_pair()
    with pytest.raises(InputError, match="search_rotations"):
        local.register(source, target, search_rotations=7, rotation_search=False)


@pytest.mark.parametrize(("shape", "message"), [
    ((3, 500), "got \\[3, 500\\]: one row per axis; .*the array transposed"),
    ((500, 4), "got \\[500, 4\\]; x, y, z only: the first three columns \\(cloud\\[:, :3\\]\\)"),
    ((500, 2), "got \\[500, 2\\]$"),
    ((4, 500), "got \\[4, 500\\]: one row per axis, as homogeneous coordinates are; .*cloud\\[:3\\]\\.T"),
])
def test_a_cloud_of_other_columns_is_named_as_the_server_names_it(local, shape, message):
    _, target = synthetic_pair()
    cloud = np.random.default_rng(0).normal(size=shape)
    with pytest.raises(InputError, match="source: expected shape \\[N, 3\\], .*" + message):
        local.register(cloud, target)


def test_a_masked_array_with_masked_rows_is_refused(local):
    """``np.asarray`` drops a mask: the masked rows were registered as points."""
    source, target = synthetic_pair()
    masked = np.ma.masked_array(source, mask=np.zeros_like(source, dtype=bool))
    masked[:5] = np.ma.masked
    with pytest.raises(InputError, match="source: a masked array with 5 masked rows"):
        local.register(masked, target)
    batched = np.ma.masked_array(source[None], mask=np.zeros((1, *source.shape), dtype=bool))  # [1, N, 3]
    batched[0, :5, 2] = np.ma.masked
    with pytest.raises(InputError, match="source: a masked array with 5 masked rows"):  # its rows, not its 1 batch
        local.register(batched, target)
    for listed in ([masked], list(masked)):  # a list of one masked array, or of its masked rows
        with pytest.raises(InputError, match="source: a masked array with 5 masked rows"):
            local.register(listed, target)
    unmasked = local.register(np.ma.masked_array(source), target)  # nothing masked: its values are the points
    np.testing.assert_array_equal(unmasked.transform, local.register(source, target).transform)

def test_a_ragged_cloud_is_an_input_error(local):
    source, target = synthetic_pair()
    with pytest.raises(InputError, match="source: expected an \\[N, 3\\] array of numbers, got rows of different"):
        local.register([*source.tolist(), [1.0, 2.0]], target)


def test_an_options_object_is_refused_for_keywords(local):
    from service.options import RegistrationOptions

    source, target = synthetic_pair()
    with pytest.raises(TypeError, match="keywords"):
        local.register(source, target, options=RegistrationOptions(refine="icp"))


def test_mfgnet_register_runs_through_the_in_process_api(monkeypatch, tmp_path, local):
    """The CLI's in-process path is :class:`LocalRegistrar`, so that its defaults cannot drift from the API's."""
    calls = []
    original = LocalRegistrar.register

    def recording(self, source, target, **options):
        calls.append(options)
        return original(self, source, target, **options)

    monkeypatch.setattr(LocalRegistrar, "register", recording)
    source, target = synthetic_pair()
    write_points(tmp_path / "a.npy", source)
    write_points(tmp_path / "b.npy", target)
    result = CliRunner().invoke(app, ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--json"])
    assert result.exit_code == 0, result.output
    assert len(calls) == 1 and calls[0]["refine"] is None and calls[0]["rotation_search"] is None  # left to the API
