"""Every ``python -m bench.*`` command answers a user's mistake with a usage error before any work: exit code 2, a
one-line message naming the problem, no traceback. Each case replaces the command's work (its registrations, servers,
data loading) by a function that fails the test, so a check that comes too late, or not at all, fails fast."""

from __future__ import annotations

import importlib
import json
import socket
import sys

import click
import numpy as np
import pytest
import typer


def _no_work(*args, **kwargs):
    raise AssertionError("the benchmark started its work before checking its command line")


@pytest.fixture()
def files(tmp_path, monkeypatch):
    """Bad and good inputs: ``{name: path}``; the real-scan set of the tests is a fake one of two pairs."""
    rng = np.random.default_rng(0)
    good = tmp_path / "pairs.npz"
    np.savez(
        good,
        source=rng.normal(size=(1, 8, 3)),
        target=rng.normal(size=(1, 8, 3)),
        rotation=np.eye(3)[None],
        translation=np.zeros((1, 3)),
        label=np.zeros(1),
    )
    np.savez(tmp_path / "wrong.npz", x=np.zeros(3))
    (tmp_path / "text.npz").write_text("not an archive")
    (tmp_path / "list.json").write_text(json.dumps([1]))
    scans = tmp_path / "scans"
    scans.mkdir()
    for name in ("dragon_a", "dragon_b"):
        cloud = rng.normal(size=(20, 3)).astype(np.float32)
        np.savez(scans / f"{name}.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="cyberware-range")
    (tmp_path / "empty").mkdir()
    for name in ("nopose", "textpair"):  # a real-scan set whose one file is no pair
        (tmp_path / name).mkdir()
    np.savez(tmp_path / "nopose" / "a.npz", source=np.ones((20, 3)), target=np.ones((20, 3)), sensor="lidar")
    (tmp_path / "textpair" / "a.npz").write_text("not an archive")
    (tmp_path / "unjudged").mkdir()  # a real-scan set whose one pair's sensor has no success thresholds
    cloud = rng.normal(size=(20, 3)).astype(np.float32)
    np.savez(tmp_path / "unjudged" / "a.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="sonar")
    (tmp_path / "checkout").mkdir()  # a folder, but no checkout of the project
    import torch

    from model.config import MFGNetConfig

    other = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.ReLU(), torch.nn.Linear(8, 1))
    torch.save({"model": other.state_dict(), "config": MFGNetConfig().to_dict()}, tmp_path / "other_arch.pt")
    monkeypatch.setenv("MFGNET_REAL_DATA", str(scans))
    with socket.socket() as s:  # a port with no server behind it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return {
        "pairs": str(good),
        "other_arch": str(tmp_path / "other_arch.pt"),  # weights of another network beside MFGNet's config
        "wrong": str(tmp_path / "wrong.npz"),
        "text": str(tmp_path / "text.npz"),
        "list": str(tmp_path / "list.json"),
        "empty": str(tmp_path / "empty"),
        "missing": str(tmp_path / "missing" / "out.json"),
        "checkout": str(tmp_path / "checkout"),
        "scans": str(scans),
        "url": f"http://127.0.0.1:{port}",
        "nopose": str(tmp_path / "nopose"),
        "textpair": str(tmp_path / "textpair"),
        "unjudged": str(tmp_path / "unjudged"),
    }


# (module, argv with {file} names, the work replaced, a fragment of the message)
CASES = [
    ("kdtree", ["--pairs", "{wrong}"], "run", "not an .npz of source, target (no source, target)"),
    ("kdtree", ["--pairs", "{pairs}", "--count", "0"], "run", "--count: must be at least 1, got 0"),
    ("kdtree", ["--pairs", "{pairs}", "--model", "nope"], "run", "--model nope: no such model folder"),
    ("kdtree", ["--pairs", "{pairs}", "--json", "{empty}"], "run", "a folder, not a file"),
    ("graph_ops", ["--pairs", "{text}"], "run", "not an .npz archive"),
    ("graph_ops", ["--pairs", "{pairs}", "--repeats", "0"], "run", "--repeats: must be at least 1"),
    ("settings", ["--pairs", "{pairs}", "--setting", '{{"bogus": 1}}'], "run", "unknown register option bogus"),
    ("settings", ["--pairs", "{wrong}", "--setting", "{{}}"], "run", "lacks ['source'"),
    ("settings", ["--pairs", "{pairs}", "--setting", "{{}}", "--count", "-1"], "run", "--count: must be at least 1"),
    ("vs_fpfh", ["--pairs", "{pairs}", "--rounds", "0"], "run", "--rounds: must be at least 1"),
    ("vs_fpfh", ["--pairs", "{pairs}", "--refine", "bogus"], "run", "--refine: invalid choice: 'bogus'"),
    ("local_search", ["--pairs", "{pairs}", "--angles", "x"], "run", "--angles: invalid"),
    ("local_search", ["--pairs", "{pairs}", "--model", "{empty}"], "run", "not a usable model folder"),
    ("search_pruning", ["--pairs", "{missing}"], "run", "no such file"),
    ("select", ["--checkpoint", "nope", "--pairs", "{pairs}"], "select", "--checkpoint nope: no checkpoint"),
    ("select", ["--checkpoint", "clean", "--pairs", "{pairs}", "--json", "{missing}"], "select", "does not exist"),
    ("select", ["--checkpoint", "{other_arch}", "--pairs", "{pairs}"], "select", "other_arch.pt"),  # a traceback
    ("refine_http", ["--pairs", "{pairs}", "--model", "nope"], "Server", "--model nope: not a bundled model"),
    ("refine_http", ["--pairs", "{pairs}", "--count", "0"], "Server", "--count: must be at least 1"),
    ("auto_trigger", ["report", "{list}", "--pairs", "{pairs}"], "report", "not what collect wrote"),
    ("auto_trigger", ["collect", "--pairs", "{pairs}", "--out", "{missing}"], "collect", "--out"),
    ("load", ["--pairs", "{wrong}"], "compare_load", "(no source, target)"),
    ("load", ["--pairs", "{pairs}", "--concurrency", "0"], "compare_load", "--concurrency: must be at least 1"),
    ("load", ["--pairs", "{pairs}", "--compare-root", "{checkout}"], "compare_load", "not a checkout"),
    ("load", ["--pairs", "{pairs}", "--json", "{missing}"], "compare_load", "does not exist"),
    ("scan_reliability", ["--model", "nope"], "seed_rows", "--model nope"),
    ("scan_reliability", ["--count", "1", "--data", "{empty}"], "seed_rows", "ModelNet40 file not found"),
    ("train_profile", ["--setting", "bogus"], "load_shapes", "unknown setting 'bogus'"),
    ("train_profile", ["--steps", "0"], "load_shapes", "--steps: must be at least 1"),
    ("real_scans", ["--pairs", "nope", "dragon_a"], "load_cases", "--pairs: no pair nope"),
    ("real_scans", ["--options", "[1]"], "load_cases", "--options: not a JSON object"),
    ("real_scans", ["--options", '{{"bogus": 1}}'], "load_cases", "--options: bogus"),
    ("real_scans", ["--model-dir", "{empty}"], "load_cases", "--model-dir"),
    ("real_scans", ["--compare-root", "{checkout}"], "load_cases", "not a checkout of this project"),
    ("real_scans", ["--url", "{url}"], "run_service", "no server answers"),
    ("real_scans", ["--json", "{empty}"], "load_cases", "a folder, not a file"),
    ("real_scans", ["{empty}"], "load_cases", "no *.npz pairs"),
    ("real_scans", ["{nopose}"], "load_cases", "nopose/a.npz: not a scan pair (no transform)"),
    ("failures", ["--data", "{textpair}"], "cases", "textpair/a.npz: not a scan pair (not an .npz archive)"),
    ("search_network", ["{empty}", "--data", "{nopose}"], "cases", "not a scan pair (no transform)"),
    ("real_scans", ["{unjudged}"], "Server", "sensor 'sonar' is of no class with success thresholds"),
    ("failures", ["--data", "{unjudged}"], "Registrar", "sensor 'sonar' is of no class with success thresholds"),
    ("altered_scans", ["{unjudged}"], "general_registrar", "sensor 'sonar' is of no class with success thresholds"),
    ("search_network", ["general", "--data", "{unjudged}"], "compare", "sensor 'sonar' is of no class"),
    ("real_scans", ["--seed", "-1"], "load_cases", "--seed: must be at least 0, got -1"),
    ("failures", ["--seeds", "0", "-1"], "cases", "--seeds: must be at least 0, got -1"),
    ("search_network", ["{empty}", "--seeds", "-1"], "cases", "--seeds: must be at least 0, got -1"),
    ("scan_reliability", ["--seeds", "-1"], "seed_rows", "--seeds: must be at least 0, got -1"),
    ("server_memory", ["--seed", "-1"], "measure", "--seed: must be at least 0, got -1"),
    ("abandoned_requests", ["--seed", "-1"], "compare", "--seed: must be at least 0, got -1"),
    ("real_scans", ["--scales", "1", "0"], "load_cases", "--scales: must be a finite number above 0, got 0"),
    ("failures", ["--scales", "-1000"], "cases", "--scales: must be a finite number above 0"),
    ("search_network", ["{empty}", "--scales", "inf"], "cases", "--scales: must be a finite number above 0"),
    ("failures", ["--turns", "0"], "cases", "--turns: must be at least 1"),
    ("failures", ["--pairs", "nope"], "cases", "--pairs: no pair nope"),
    ("failures", ["--data", "{empty}/nowhere"], "cases", "no real-scan set"),
    ("failures", ["--model-dir", "{empty}"], "cases", "--model-dir"),
    ("search_network", ["{empty}"], "cases", "not a usable model folder"),
    ("search_network", ["{empty}", "--pairs", "nope"], "cases", "--pairs: no pair nope"),
    ("altered_scans", ["{empty}"], "general_registrar", "no *.npz pairs"),
    ("altered_scans", ["--json", "{missing}"], "general_registrar", "does not exist"),
    ("lidar_variants", [], "variants", "no LiDAR pair"),
    ("network_cost", ["--pair", "nope"], "exported", "--pair: no pair nope"),
    ("network_cost", ["--pair", "dragon_a", "--shapes", '{{"bogus": 3}}'], "exported", "unknown MFGNetConfig field"),
    ("network_cost", ["--pair", "dragon_a", "--rounds", "0"], "exported", "--rounds: must be at least 1"),
    ("abandoned_requests", ["--compare-root", "{checkout}"], "compare", "not a checkout"),
    ("abandoned_requests", ["--requests", "0"], "compare", "--requests: must be at least 1"),
    ("default_request", ["--pairs", "0"], "compare", "--pairs: must be at least 1"),
    ("default_request", ["--json", "{empty}"], "compare", "a folder, not a file"),
    ("queued_bodies", ["--json", "{missing}"], "measure", "does not exist"),
    ("queued_bodies", ["--compare-root", "{checkout}"], "measure", "--compare-root"),
    ("server_memory", ["--models", "general,nope"], "measure", "--models: no bundled model nope"),
    ("server_memory", ["--aligned", "ply,xyz"], "measure_aligned", "--aligned: expected formats among ply, pcd"),
    ("server_memory", ["--aligned-pair", "xyz"], "measure_aligned", "--aligned-pair: invalid choice"),
    ("http_latency", ["--big-requests", "0"], "bench_overhead", "--big-requests: must be at least 1"),
    ("http_latency", ["--compare-root", "{checkout}"], "bench_overhead", "not a checkout"),
    ("plot", ["{list}", "{missing}"], "plot_report", "not an mfgnet bench report"),
]


@pytest.mark.parametrize(("module", "argv", "work", "fragment"), CASES, ids=[f"{c[0]}:{' '.join(c[1])}" for c in CASES])
def test_mistake_is_a_usage_error_before_any_work(module, argv, work, fragment, files, monkeypatch, capsys):
    bench = importlib.import_module(f"bench.{module}")
    monkeypatch.setattr(bench, work, _no_work)
    with pytest.raises(SystemExit) as ended:
        bench.main([arg.format(**files) for arg in argv])
    assert ended.value.code == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error: " in message and fragment in message


@pytest.mark.parametrize(("module", "argv", "work"), [
    ("real_scans", [], "run_service"), ("altered_scans", [], "general_registrar"),
    ("lidar_variants", ["{sensors}"], "variants"), ("room_crops", ["{sensors}"], "general_registrar"),
    ("turntable_scans", ["--shapes", "cup", "--count", "1"], "modelnet_shapes"),
    ("vs_fpfh", ["--pairs", "{pairs}"], "run"),
])
def test_a_benchmark_beside_fpfh_without_open3d_says_how_to_install_it_before_any_work(module, argv, work, files,
                                                                                       tmp_path, monkeypatch, capsys):
    """Without the bench extra these ran the service's cases first, then ended in an ImportError traceback. The
    other usage errors come first (the CI's environment has no Open3D)."""
    sensors = tmp_path / "sensors"  # a LiDAR pair and a room pair, as the LiDAR and room benchmarks need
    sensors.mkdir()
    cloud = np.random.default_rng(1).normal(size=(40, 3)).astype(np.float32)
    for name, sensor in (("lidar_small_gicp", "lidar"), ("3dm_room_1_0", "kinect-v1")):
        np.savez(sensors / f"{name}.npz", source=cloud, target=cloud, transform=np.eye(4), sensor=sensor)
    files = {**files, "sensors": str(sensors)}
    bench = importlib.import_module(f"bench.{module}")
    monkeypatch.setattr(bench, work, _no_work)
    monkeypatch.setitem(sys.modules, "open3d", None)  # as where the bench extra is not installed
    with pytest.raises(SystemExit) as ended:
        bench.main([arg.format(**files) for arg in argv])
    assert ended.value.code == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert "pip install -e '.[bench]'" in message, message
    assert ("--no-fpfh" in message) == (module != "vs_fpfh"), message


def test_evaluate_with_a_baseline_without_open3d_is_a_usage_error(files, monkeypatch):
    from typer.testing import CliRunner

    from service.cli import app

    monkeypatch.setitem(sys.modules, "open3d", None)
    result = CliRunner().invoke(app, ["evaluate", "--baseline", "fpfh-ransac-icp", "--pairs", files["pairs"]])
    assert result.exit_code == 2 and "pip install -e '.[bench]'" in result.output, result.output


@pytest.mark.parametrize(
    ("folders", "fragment"),
    [
        (["x/candidate", "y/candidate"], "DIR: candidates need distinct folder names other than general"),
        (["x/general", "y/other"], "DIR: candidates need distinct folder names other than general"),
        (["unseen"], "normalises clouds to a reference radius of"),
    ],
)
def test_search_network_candidates_are_checked_before_any_work(folders, fragment, files, tmp_path, monkeypatch, capsys):
    import shutil

    from bench import search_network
    from service.manifest import bundled_models_dir

    dirs = []
    for folder in folders:  # copies of the bundled model under the given names, or a bundled name as it is
        if "/" in folder:
            shutil.copytree(bundled_models_dir() / "general", tmp_path / folder)
            manifest = tmp_path / folder / "manifest.json"  # its name is its folder's
            manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "name": folder.split("/")[1]}))
        dirs.append(str(tmp_path / folder) if "/" in folder else folder)
    for work in ("cases", "compare", "Registrar"):
        monkeypatch.setattr(search_network, work, _no_work)
    with pytest.raises(SystemExit) as ended:
        search_network.main([*dirs, "--pairs", "dragon_a"])
    assert ended.value.code == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error: " in message and fragment in message


def test_modelnet_data_missing_is_a_usage_error(files, monkeypatch, capsys):
    from bench import default_request

    monkeypatch.setenv("MFGNET_DATA", files["empty"])
    monkeypatch.setattr(default_request, "compare", _no_work)
    with pytest.raises(SystemExit) as ended:
        default_request.main([])
    assert ended.value.code == 2
    assert "ModelNet40 file not found" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("options", "fragment"),
    [({"json_out": "missing"}, "does not exist"), ({"settings": ["bogus"]}, "unknown setting 'bogus'")],
)
def test_rotation_search_checks_its_options_before_the_cost_stage(options, fragment, files, monkeypatch, capsys):
    from pathlib import Path

    from bench.rotation_search import search_bench

    monkeypatch.setattr("service.registrar.Registrar", _no_work)
    options = {k: Path(files[v]) if k == "json_out" else v for k, v in options.items()}
    with pytest.raises(typer.Exit) as ended:
        search_bench(**options)
    assert ended.value.exit_code == 2
    assert fragment in capsys.readouterr().err


@pytest.mark.parametrize(
    "command",
    [
        ["evaluate", "--checkpoint", "nope"],  # mfgnet evaluate
        ["bench", "--model", "nope"],  # mfgnet bench (bench.latency)
        ["rotation_search", "--model", "nope"],  # python -m bench.rotation_search
    ],
    ids=lambda command: command[0],
)
def test_negative_seed_of_a_typer_bench_is_a_usage_error(command):
    """The seed is checked as the command line is parsed, before the command's own checks (here: a missing model)."""
    from typer.testing import CliRunner

    from bench.rotation_search import search_bench
    from service.cli import app

    if command[0] == "rotation_search":
        app, command = typer.Typer(), command[1:]
        app.command()(search_bench)
    result = CliRunner().invoke(app, [*command, "--seed", "-1"])
    output = click.unstyle(result.output)  # typer colours its errors where GITHUB_ACTIONS or FORCE_COLOR is set
    assert result.exit_code == 2 and "Traceback" not in output
    assert "Invalid value for '--seed'" in output, output


@pytest.mark.parametrize("option", [["--repeats", "0"], ["--threads", "0"], ["--http-requests", "-1"]])
def test_mfgnet_bench_counts_below_their_least_are_usage_errors(option):
    """`--repeats 0` ran the whole benchmark, then ended in an IndexError of an empty percentile; `--threads 0` in
    torch's RuntimeError."""
    from typer.testing import CliRunner

    from service.cli import app

    result = CliRunner().invoke(app, ["bench", "--model", "nope", *option])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert f"Invalid value for '{option[0]}'" in result.output, result.output


def test_mfgnet_bench_without_modelnet_names_the_variable_it_reads(files, monkeypatch):
    """It said "set --data or $MFGNET_DATA"; `mfgnet bench` has no --data."""
    from typer.testing import CliRunner

    from service.cli import app

    monkeypatch.setenv("MFGNET_DATA", files["empty"])
    result = CliRunner().invoke(app, ["bench", "--model", "general", "--checkpoint", "general"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "ModelNet40 file not found" in result.output and "(set $MFGNET_DATA)" in result.output, result.output


def test_mfgnet_bench_refuses_a_checkpoint_other_than_the_models_source():
    """`--model general` beside the default `--checkpoint clean` timed PyTorch's clean against ONNX's general and
    reported a speed-up between two networks."""
    from typer.testing import CliRunner

    from service.cli import app

    result = CliRunner().invoke(app, ["bench", "--model", "general"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "--checkpoint clean: not the checkpoint --model general was exported from (general.pt" in result.output
