"""Specification of ``mfgnet sequence``: frame i registered onto frame i-1 in one process, the relative poses chained
into frame 0's coordinates, written as JSON lines and as KITTI odometry poses; usage errors before any registration.

The frames are independent samples of one asymmetric shape, each seen from a sensor moved by a known small motion
(one step turns back, as a robot reversing does), written as ``.npy`` files; the model is a verified copy of the
bundled ``general``, run with the service's defaults."""

from __future__ import annotations

import itertools
import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from api_server import free_port, start_subprocess_server
from cli_support import python_without_torch, snapshot_model
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob, unit_directions
from typer.testing import CliRunner

from service.cli import app

runner = CliRunner()
RECORD_KEYS = {"rotation", "translation", "transform", "euler_zyx_deg", "yaw_pitch_roll_deg", "quaternion_xyzw",
               "quality", "warnings", "model", "iterations", "timing_ms"}  # `mfgnet register --json`
STEP_KEYS = {"index", "source", "target", *RECORD_KEYS, "initial_transform", "accumulated_transform",
             "accumulated_reliable"}
MAX_DEG, MAX_SHIFT = 1.0, 0.01  # chained pose against the truth (the shape's radius is about 1)


def pose(rotvec_deg: list[float], shift: list[float]) -> np.ndarray:
    """``[4, 4]``: a turn (rotation vector, degrees) and a shift."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix(), shift
    return T


# T_{i-1}_i of each step: the sensor turns 10-12 deg about z a frame, then turns back 25 deg, then on again
MOTIONS = [pose([2, -3, 10], [0.05, 0.02, 0.0]), pose([-1, 2, 12], [0.04, -0.03, 0.01]),
           pose([3, 1, -25], [0.06, 0.0, -0.02]), pose([0, -2, 11], [0.03, 0.04, 0.0])]


def world_poses() -> list[np.ndarray]:
    """``T_0_i`` of every frame: the motions chained."""
    poses = [np.eye(4)]
    for motion in MOTIONS:
        poses.append(poses[-1] @ motion)
    return poses


def gap(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(degrees, shift) between two ``[4, 4]`` poses."""
    off = np.linalg.inv(truth) @ np.asarray(T)
    return float(np.degrees(Rotation.from_matrix(off[:3, :3]).magnitude())), float(np.linalg.norm(off[:3, 3]))


def sequence(*args, model_dir: Path):
    """``mfgnet sequence ARGS --model-dir MODEL_DIR``."""
    return runner.invoke(app, ["sequence", *map(str, args), "--model-dir", str(model_dir)])


def steps_of(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines()]


def assert_usage_error(result, *fragments: str) -> None:
    """Exit 2 with the message on stderr, no traceback, and no step registered."""
    assert result.exit_code == 2, result.output
    assert not isinstance(result.exception, Exception), result.exception  # SystemExit only
    assert "Traceback" not in result.output and "[1/" not in result.stderr and not result.stdout
    for fragment in fragments:
        assert fragment in result.stderr, result.stderr


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return snapshot_model(tmp_path_factory.mktemp("models"), "general")


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> list[Path]:
    """``frame_i.npy``: 1500 points of the shape drawn anew for each frame, in frame i's sensor coordinates."""
    folder = tmp_path_factory.mktemp("frames")
    paths = []
    for index, T_0_i in enumerate(world_poses()):
        path = folder / f"frame_{index}.npy"
        np.save(path, (asymmetric_blob(1500, seed=10 + index) - T_0_i[:3, 3]) @ T_0_i[:3, :3])  # [N, 3]
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def plain_run(tmp_path_factory, frames, model_dir) -> dict:
    """The whole sequence without a guess, with ``--out`` and ``--kitti``."""
    folder = tmp_path_factory.mktemp("plain")
    out, kitti = folder / "poses.jsonl", folder / "poses.txt"
    result = sequence(*frames, "--out", out, "--kitti", kitti, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    return {"result": result, "steps": steps_of(out.read_text()), "kitti": kitti.read_text()}


def test_chained_poses_follow_the_known_motion(plain_run, frames) -> None:
    steps, truth = plain_run["steps"], world_poses()
    assert [step["index"] for step in steps] == [1, 2, 3, 4]
    for step in steps:
        i = step["index"]
        assert (step["source"], step["target"]) == (str(frames[i]), str(frames[i - 1]))
        degrees, shift = gap(step["transform"], MOTIONS[i - 1])  # T_{i-1}_i
        assert degrees < MAX_DEG and shift < MAX_SHIFT, (i, degrees, shift)
        degrees, shift = gap(step["accumulated_transform"], truth[i])  # T_0_i
        assert degrees < MAX_DEG and shift < MAX_SHIFT, (i, degrees, shift)
        assert step["quality"]["reliable"] and step["warnings"] == [] and step["initial_transform"] is None


def test_each_line_is_the_register_record_of_its_pair_and_the_product_so_far(plain_run, frames, model_dir) -> None:
    T_0_i = np.eye(4)
    for step in plain_run["steps"]:
        assert set(step) == STEP_KEYS
        i = step["index"]
        single = runner.invoke(app, ["register", str(frames[i]), str(frames[i - 1]), "--json",
                                     "--model-dir", str(model_dir)])
        assert single.exit_code == 0, single.output
        record = json.loads(single.stdout)
        assert {key: step[key] for key in RECORD_KEYS - {"timing_ms"}} == {
            key: record[key] for key in RECORD_KEYS - {"timing_ms"}}, i
        assert step["timing_ms"]["total"] > 0
        T_0_i = T_0_i @ np.asarray(step["transform"])
        np.testing.assert_allclose(step["accumulated_transform"], T_0_i, rtol=0, atol=1e-12)


def test_the_kitti_file_holds_a_line_of_12_numbers_per_frame(plain_run) -> None:
    lines = plain_run["kitti"].splitlines()
    assert len(lines) == 5 and all(len(line.split()) == 12 for line in lines)
    poses = np.loadtxt(plain_run["kitti"].splitlines()).reshape(5, 3, 4)  # as evo and the KITTI devkit read it
    np.testing.assert_array_equal(poses[0], np.eye(4)[:3])
    for step in plain_run["steps"]:
        np.testing.assert_allclose(poses[step["index"]], np.asarray(step["accumulated_transform"])[:3],
                                   rtol=0, atol=1e-11)


def test_progress_goes_to_stderr_one_line_per_step(plain_run) -> None:
    result = plain_run["result"]
    assert result.stdout == ""  # the lines went to --out
    progress = [line for line in result.stderr.splitlines() if line.startswith("[")]
    assert [line.split()[0] for line in progress] == ["[1/4]", "[2/4]", "[3/4]", "[4/4]"]
    assert all("-> frame_" in line and ": reliable," in line for line in progress), progress


def test_progress_names_how_far_the_centroid_moves_also_in_georeferenced_coordinates(tmp_path, frames, model_dir
                                                                                     ) -> None:
    """Frames in one far frame (a UTM map's): each step's translation grows with the origin's distance (a 10 deg turn
    at 500 km: 87 km); the line prints how far the pose moves the source's centroid, and says so (a bare "shift" read
    as |t|, which it is not even near the origin)."""
    offset = np.array([512_345.0, 4_123_456.0, 87.0])
    far = []
    for path in frames:
        far.append(tmp_path / path.name)
        np.save(far[-1], np.load(path) + offset)
    result = sequence(*far, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    shifts = [float(line.split("centroid moved ")[1].split(",")[0]) for line in result.stderr.splitlines()
              if "centroid moved " in line]
    steps = steps_of(result.stdout)
    assert len(shifts) == 4 and max(np.linalg.norm(step["translation"]) for step in steps) > 1e4
    for shift, path, step in zip(shifts, far[1:], steps, strict=True):
        T, c = np.asarray(step["transform"]), np.load(path).mean(axis=0)
        assert shift == pytest.approx(np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - c), rel=1e-3) and shift < 1.0


@pytest.fixture(scope="module")
def velocity_run(frames, model_dir) -> list[dict]:
    """The whole sequence with ``--constant-velocity``, its JSON lines on standard output."""
    result = sequence(*frames, "--constant-velocity", model_dir=model_dir)
    assert result.exit_code == 0, result.output
    return steps_of(result.stdout)


def test_constant_velocity_passes_the_last_step_as_the_guess(plain_run, velocity_run) -> None:
    """The guess is the step before's relative pose; where the sensor turns back, the result departs from it (with
    the warning) and still follows the motion."""
    steps = velocity_run
    assert len(steps) == 4 and steps[0]["initial_transform"] is None
    for before, step in itertools.pairwise(steps):
        assert step["initial_transform"] == before["transform"]
    far = [step["index"] for step in steps if any(w.startswith("far from initial transform") for w in step["warnings"])]
    assert far == [3, 4]  # +12 deg guessed, -25 turned; then -25 guessed, +11 turned
    for step in steps[2:]:  # said of the prior the sequence passed, not advice to mend a prior the caller gave
        warning = next(w for w in step["warnings"] if w.startswith("far from initial transform"))
        assert "departs from the previous step's (the --constant-velocity prior) by " in warning, warning
        assert "invert it" not in warning and "leave it out" not in warning
        turned = gap(step["transform"], step["initial_transform"])[0]
        assert f"by {turned:.1f} deg and " in warning, (turned, warning)
    assert not any(w.startswith("far from") for step in plain_run["steps"] for w in step["warnings"])  # no guess
    for step in steps:
        degrees, shift = gap(step["transform"], MOTIONS[step["index"] - 1])
        assert degrees < MAX_DEG and shift < MAX_SHIFT, (step["index"], degrees, shift)


@pytest.fixture(scope="module")
def server(model_dir) -> Iterator[str]:
    """Base URL of a real server (uvicorn in a subprocess on 127.0.0.1) serving the same copy of ``general``."""
    served = start_subprocess_server("sequence", MFGNET_MODEL_DIRS=str(model_dir.parent),
                                     MFGNET_DEFAULT_MODEL=model_dir.name)
    yield served.url
    served.stop()


def assert_same_steps_but_timing(remote: list[dict], local: list[dict]) -> None:
    """The JSON lines of ``--server`` and in-process: the same keys, frames, guesses passed, model, warnings and
    reliability; the numbers within float32 rounding of the uploaded clouds; only ``timing_ms`` differs."""
    assert len(remote) == len(local)
    for there, here in zip(remote, local, strict=True):
        assert set(there) == set(here) == STEP_KEYS
        for key in ("index", "source", "target", "model", "iterations", "warnings"):
            assert there[key] == here[key], (here["index"], key)
        assert there["quality"]["reliable"] == here["quality"]["reliable"]
        for key in ("inlier_ratio", "residual_rms", "stability"):
            np.testing.assert_allclose(there["quality"][key], here["quality"][key], rtol=1e-5, atol=1e-8)
        for key in ("rotation", "translation", "transform", "quaternion_xyzw", "accumulated_transform"):
            np.testing.assert_allclose(there[key], here[key], rtol=0, atol=1e-6, err_msg=f"{here['index']} {key}")
        for key in ("euler_zyx_deg", "yaw_pitch_roll_deg"):
            np.testing.assert_allclose(there[key], here[key], rtol=0, atol=1e-4, err_msg=f"{here['index']} {key}")
        if here["initial_transform"] is None:
            assert there["initial_transform"] is None
        else:
            np.testing.assert_allclose(there["initial_transform"], here["initial_transform"], rtol=0, atol=1e-6)
        assert "queue" in there["timing_ms"] and "queue" not in here["timing_ms"]  # the server's own stage


def test_server_lines_and_kitti_poses_equal_the_in_process_ones_but_timing(server, plain_run, frames,
                                                                          tmp_path) -> None:
    out, kitti = tmp_path / "poses.jsonl", tmp_path / "poses.txt"
    result = runner.invoke(app, ["sequence", *map(str, frames), "--server", server, "--out", str(out),
                                 "--kitti", str(kitti)])
    assert result.exit_code == 0, result.output
    steps = steps_of(out.read_text())
    assert_same_steps_but_timing(steps, plain_run["steps"])
    poses = np.loadtxt(kitti.read_text().splitlines()).reshape(5, 3, 4)
    np.testing.assert_array_equal(poses[0], np.eye(4)[:3])
    for step in steps:
        np.testing.assert_allclose(poses[step["index"]], np.asarray(step["accumulated_transform"])[:3],
                                   rtol=0, atol=1e-11)
    np.testing.assert_allclose(poses, np.loadtxt(plain_run["kitti"].splitlines()).reshape(5, 3, 4), rtol=0, atol=1e-4)
    progress = [line.split()[0] for line in result.stderr.splitlines() if line.startswith("[")]
    assert progress == ["[1/4]", "[2/4]", "[3/4]", "[4/4]"]


def test_server_constant_velocity_sends_the_last_step_as_the_guess(server, velocity_run, frames) -> None:
    result = runner.invoke(app, ["sequence", *map(str, frames), "--server", server, "--constant-velocity"])
    assert result.exit_code == 0, result.output
    steps = steps_of(result.stdout)
    assert_same_steps_but_timing(steps, velocity_run)
    for before, step in itertools.pairwise(steps):
        assert step["initial_transform"] == before["transform"]


def test_a_step_the_server_refuses_exits_2_naming_both_frames_after_the_steps_before(server, frames,
                                                                                    tmp_path) -> None:
    few = tmp_path / "few.npy"
    np.save(few, asymmetric_blob(10))  # fewer points than the server takes
    out = tmp_path / "poses.jsonl"
    result = runner.invoke(app, ["sequence", str(frames[0]), str(frames[1]), str(few), "--server", server,
                                 "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert f"frame 2 {few} onto frame 1 {frames[1]}: server: HTTP 422" in result.stderr, result.stderr
    assert "Traceback" not in result.output and len(out.read_text().splitlines()) == 1


def test_an_unreachable_server_exits_1_naming_the_first_step(frames, tmp_path) -> None:
    out = tmp_path / "poses.jsonl"
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    result = runner.invoke(app, ["sequence", *map(str, frames[:3]), "--server", url, "--out", str(out),
                                 "--busy-retries", "0", "--timeout", "5"])
    assert result.exit_code == 1, result.output
    assert f"frame 1 {frames[1]} onto frame 0 {frames[0]}: server: cannot reach {url}" in result.stderr
    assert "Traceback" not in result.output and out.read_text() == ""


@pytest.mark.parametrize("case", ["model-dir", "threads", "no-scheme", "no-url", "key-with-a-line-break",
                                  "key-not-ascii"])
def test_server_usage_errors_exit_2_before_any_request(tmp_path, frames, model_dir, case) -> None:
    """The last three were a traceback, or exit 1 as if the server could not be reached."""
    args, fragment = {
        "model-dir": (["--server", "http://127.0.0.1:9", "--model-dir", str(model_dir)], "--model-dir only applies"),
        "threads": (["--server", "http://127.0.0.1:9", "--threads", "2"], "--threads only applies in-process"),
        "no-scheme": (["--server", "127.0.0.1:8080"], "http://"),
        "no-url": (["--server", "http://[::1"], "is not a URL"),
        "key-with-a-line-break": (["--server", "http://127.0.0.1:9", "--api-key", "s3cret\n"], "--api-key must be"),
        "key-not-ascii": (["--server", "http://127.0.0.1:9", "--api-key", "ключ"], "printable ASCII"),
    }[case]
    assert_usage_error(runner.invoke(app, ["sequence", *map(str, frames[:2]), *args]), fragment)


def test_a_repeated_frame_is_registered_onto_itself_as_the_identity(plain_run, frames, model_dir) -> None:
    result = sequence(frames[0], frames[0], frames[1], model_dir=model_dir)
    assert result.exit_code == 0, result.output
    same, step = steps_of(result.stdout)
    np.testing.assert_allclose(same["transform"], np.eye(4), rtol=0, atol=1e-6)
    assert step["transform"] == plain_run["steps"][0]["transform"]  # frame 1 onto frame 0, as in the plain run
    np.testing.assert_allclose(step["accumulated_transform"], plain_run["steps"][0]["transform"], rtol=0, atol=1e-6)


def test_require_reliable_exits_3_on_spheres_and_still_writes_every_step(tmp_path, model_dir) -> None:
    """Samples of a sphere: any turn fits, so no step is reliable."""
    paths = []
    for index in range(3):
        paths.append(tmp_path / f"sphere_{index}.npy")
        np.save(paths[-1], unit_directions(np.random.default_rng(index), 1000))
    out = tmp_path / "poses.jsonl"
    assert sequence(*paths, model_dir=model_dir).exit_code == 0
    result = sequence(*paths, "--require-reliable", "--out", out, model_dir=model_dir)
    assert result.exit_code == 3, result.output
    assert "steps 1, 2 not reliable (--require-reliable)" in result.stderr
    assert [step["quality"]["reliable"] for step in steps_of(out.read_text())] == [False, False]


def test_the_warnings_said_of_the_prior_are_the_guess_checks_kinds() -> None:
    from service.sequence import FAR_FROM_PRIOR, PRIOR_RETURNED
    from service.stages.guess_check import FAR_FROM_GUESS, GUESS_RETURNED

    assert (FAR_FROM_PRIOR, PRIOR_RETURNED) == (FAR_FROM_GUESS, GUESS_RETURNED)


def test_steps_after_an_unreliable_one_say_their_accumulated_pose_rests_on_it(tmp_path, frames, model_dir) -> None:
    """A sphere in place of frame 2: steps 2 and 3 are not reliable; step 4 is, but its ``T_0_4`` chains theirs."""
    paths = list(frames)
    paths[2] = tmp_path / "frame_2.npy"
    np.save(paths[2], unit_directions(np.random.default_rng(0), 1500))
    result = sequence(*paths, model_dir=model_dir)
    assert result.exit_code == 0, result.output
    steps = steps_of(result.stdout)
    assert [step["quality"]["reliable"] for step in steps] == [True, False, False, True]
    assert [step["accumulated_reliable"] for step in steps] == [True, False, False, False]
    progress = result.stderr.splitlines()
    assert progress[3].startswith("[4/4] frame_4.npy -> frame_3.npy: reliable (its accumulated pose rests on a step "
                                  "that is not), "), progress[3]
    assert "reliable (its accumulated" not in progress[0]
    assert "4 steps, 2 not reliable (every accumulated pose from step 2 on rests on an unreliable step)" in (
        result.stderr)


def test_a_frame_unreadable_midway_exits_2_naming_it_after_the_steps_before(tmp_path, frames, model_dir) -> None:
    bad = tmp_path / "frame_2.npy"
    np.save(bad, np.full((100, 3), np.nan))
    out, kitti = tmp_path / "poses.jsonl", tmp_path / "poses.txt"
    result = sequence(frames[0], frames[1], bad, frames[3], "--out", out, "--kitti", kitti, model_dir=model_dir)
    assert result.exit_code == 2, result.output
    assert f"frame 2 {bad}:" in result.stderr and "Traceback" not in result.output
    assert "[1/3]" in result.stderr and "[2/3]" not in result.stderr
    assert len(out.read_text().splitlines()) == 1 and len(kitti.read_text().splitlines()) == 2


def test_a_pair_the_pipeline_refuses_exits_2_naming_both_frames(tmp_path, frames, model_dir) -> None:
    few = tmp_path / "few.npy"
    np.save(few, asymmetric_blob(10))  # fewer points than the pipeline takes
    result = sequence(frames[0], few, model_dir=model_dir)
    assert result.exit_code == 2, result.output
    assert f"frame 1 {few} onto frame 0 {frames[0]}:" in result.stderr and "Traceback" not in result.output


@pytest.mark.parametrize("case", ["one-frame", "missing", "unmatched-glob", "extension", "folder", "output-is-a-frame",
                                  "kitti-folder", "same-outputs", "kitti-on-stdout", "keypoints", "iterations"])
def test_usage_errors_exit_2_before_any_registration(tmp_path, frames, model_dir, case) -> None:
    out = tmp_path / "poses.jsonl"
    f0, f1, f2 = map(str, frames[:3])
    args, fragments = {
        "one-frame": ([f0], ["at least two frames, got 1"]),
        "missing": ([f0, f1, tmp_path / "nope.ply", f2], [f"frame 2 {tmp_path / 'nope.ply'}: no such file"]),
        # a shell glob that matched nothing reaches the command as itself: named, not counted as one frame
        "unmatched-glob": ([tmp_path / "scans" / "*.ply"], [f"frame 0 {tmp_path / 'scans' / '*.ply'}: no such file"]),
        "extension": ([f0, f1, tmp_path / "scan.bin"], ["frame 2", "unknown extension '.bin'", ".ply"]),
        "folder": ([f0, tmp_path], [f"frame 1 {tmp_path}: a folder"]),
        "output-is-a-frame": ([f0, f1, "--kitti", f1], ["--kitti", "is one of the frames"]),
        "kitti-folder": ([f0, f1, "--kitti", tmp_path / "no" / "poses.txt"], ["--kitti", "does not exist"]),
        "same-outputs": ([f0, f1, "--kitti", out], ["--out and --kitti are the same file"]),
        "kitti-on-stdout": ([f0, f1, "--kitti", "-"], ["--kitti -", "name a file"]),
        "keypoints": ([f0, f1, "--keypoints", "600"], ["--keypoints", "512"]),  # it failed at step 1, --out emptied
        "iterations": ([f0, f1, "--iterations", "0"], ["--iterations", "1"]),
    }[case]
    (tmp_path / "scan.bin").write_bytes(np.zeros((100, 3), np.float32).tobytes())
    before = frames[1].read_bytes()
    assert_usage_error(sequence(*args, "--out", out, model_dir=model_dir), *fragments)
    assert not out.exists() and frames[1].read_bytes() == before


def test_help_runs_without_torch(tmp_path) -> None:
    """``mfgnet sequence --help`` in a real subprocess of a Python that cannot import torch, as in the container."""
    argv, env = python_without_torch(tmp_path)
    code = ("import sys; from service.cli import main; sys.argv = ['mfgnet', 'sequence', '--help']\n"
            "try:\n    main()\nfinally:\n"
            "    print('LEAKED', sorted(m for m in sys.modules if m.split('.')[0] in "
            "('torch', 'model', 'export', 'bench')), file=sys.stderr)")
    run = subprocess.run([*argv, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "Usage: mfgnet sequence" in run.stdout and "--constant-velocity" in run.stdout
    assert "--kitti" in run.stdout and "--require-reliable" in run.stdout and "LEAKED []" in run.stderr
