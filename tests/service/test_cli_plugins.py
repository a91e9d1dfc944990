"""Specification of the training-side plug-ins of ``mfgnet``: where torch is absent, the commands from the
``mfgnet.commands`` entry points still appear and answer with the install hint; the runtime commands
work and never import torch, ``model``, ``export`` or ``bench``, also where they are installed (the plug-ins load
only when one of them is run or listed)."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import entry_points

import pytest
import typer
from cli_support import python_without_torch
from typer.testing import CliRunner

from service.cli.plugins import TRAIN_EXTRA_HINT, missing_command

# Runs `mfgnet ARGS`, then reports on stderr whether a training-side module got imported anyway.
MFGNET = """
import sys
sys.argv = ["mfgnet", *sys.argv[1:]]
try:
    from service.cli import main
    main()
finally:
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "model", "export", "bench"))
    print("LEAKED", leaked, file=sys.stderr)
"""
TRAINING_COMMANDS = sorted(ep.name for ep in entry_points(group="mfgnet.commands"))


@pytest.fixture(scope="module")
def mfgnet_without_torch(tmp_path_factory):
    """``run(*args)``: ``mfgnet ARGS`` in a Python where torch is not installed."""
    argv, env = python_without_torch(tmp_path_factory.mktemp("no-torch"))

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([*argv, "-c", MFGNET, *args], env=env, capture_output=True, text=True, timeout=60)

    return run


def mfgnet_here(*args: str) -> subprocess.CompletedProcess:
    """``mfgnet ARGS`` in this Python, where torch and the training side are installed."""
    return subprocess.run([sys.executable, "-c", MFGNET, *args], capture_output=True, text=True, timeout=120)


def test_the_entry_point_group_declares_the_training_commands() -> None:
    assert {"train", "evaluate", "make-pairs", "export", "import-checkpoint"} <= set(TRAINING_COMMANDS)


def test_without_torch_training_commands_answer_with_the_install_hint(mfgnet_without_torch) -> None:
    run = mfgnet_without_torch("train", "--epochs", "1", "--setting", "clean")  # options are accepted, not parsed
    assert run.returncode == 2, run.stderr
    assert "mfgnet train: this command needs the training side (the train extra): make install-dev" in run.stderr
    assert "pip install 'mfgnet[train]'" not in run.stderr  # that takes PyPI's CUDA torch on Linux
    assert "(torch is not installed)" in run.stderr
    assert "Traceback" not in run.stderr
    assert "LEAKED []" in run.stderr


def test_without_torch_help_lists_runtime_and_training_commands(mfgnet_without_torch) -> None:
    run = mfgnet_without_torch("--help")
    assert run.returncode == 0, run.stderr
    for name in ("serve", "register", "models", *TRAINING_COMMANDS):
        assert name in run.stdout
    assert "needs the train extra" in run.stdout
    assert "LEAKED []" in run.stderr


def test_without_torch_the_runtime_commands_work(mfgnet_without_torch) -> None:
    run = mfgnet_without_torch("models", "--json")
    assert run.returncode in (0, 1), run.stderr  # 1 only when no model is exported yet
    assert run.stdout.lstrip().startswith("[")
    assert "LEAKED []" in run.stderr


def test_the_stub_factory_reports_the_import_error_and_exits_2() -> None:
    app = typer.Typer()
    app.command("export", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(
        missing_command("export", ImportError("No module named 'onnx'")))
    app.command("noop")(lambda: None)  # a second command keeps typer from collapsing the app into one command
    result = CliRunner().invoke(app, ["export", "--checkpoint", "x.pt"])
    assert result.exit_code == 2
    assert f"mfgnet export: {TRAIN_EXTRA_HINT} (No module named 'onnx')" in result.stderr


@pytest.mark.skipif(not TRAINING_COMMANDS, reason="the package's entry points are not installed")
def test_with_the_training_side_installed_runtime_commands_import_none_of_it() -> None:
    for args in (("models", "--json"), ("register", "--help"), ("serve", "--help")):
        run = mfgnet_here(*args)
        assert run.returncode in (0, 1), run.stderr  # models: 1 only when no model is exported yet
        assert "LEAKED []" in run.stderr, (args, run.stderr)


@pytest.mark.skipif(not TRAINING_COMMANDS, reason="the package's entry points are not installed")
def test_with_the_training_side_installed_a_training_command_loads_when_run() -> None:
    pytest.importorskip("torch")
    run = mfgnet_here("make-pairs", "--help")
    assert run.returncode == 0, run.stderr
    assert "--setting" in run.stdout and "not installed here" not in run.stdout
    assert "'model.cli'" in run.stderr  # loaded for this command alone
