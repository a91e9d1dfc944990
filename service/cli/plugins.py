"""The training-side commands of ``mfgnet`` (train, evaluate, make-pairs, export, ...), found through the
``mfgnet.commands`` entry-point group and loaded only when one of them is run or help lists them.

A runtime command (serve, register, sequence, models) therefore never imports ``model``, ``export`` or ``bench``,
even in an install that has them; where torch is absent, a training command answers with the install hint instead.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import EntryPoint, entry_points
from importlib.util import find_spec

import click
import typer
from typer.core import TyperGroup

PLUGIN_GROUP = "mfgnet.commands"
# Not `pip install 'mfgnet[train]'`: on Linux that takes PyPI's torch, the CUDA build (README, Set-up).
TRAIN_EXTRA_HINT = (
    "this command needs the training side (the train extra): make install-dev in a source checkout, "
    "which takes torch from PyTorch's CPU index"
)
STUB_SETTINGS = {"allow_extra_args": True, "ignore_unknown_options": True}  # a stub accepts any options


def missing_command(name: str, error: Exception) -> Callable[[typer.Context], None]:
    """A command that says why ``name`` cannot run here and exits with 2."""

    def command(ctx: typer.Context) -> None:
        typer.echo(f"mfgnet {name}: {TRAIN_EXTRA_HINT} ({error})", err=True)
        raise typer.Exit(code=2)

    command.__doc__ = f"(not installed here: needs the train extra) {name}"  # no [...]: rich markup eats it
    return command


def plugin_command(entry: EntryPoint) -> click.Command:
    """The click command of one entry point: its function, or the install hint where it cannot be imported."""
    app = typer.Typer(add_completion=False, rich_markup_mode=None)
    try:
        if find_spec("torch") is None:  # checked without importing torch
            raise ImportError("torch is not installed")
        app.command(entry.name)(entry.load())
    except ImportError as exc:  # torch or another training dependency is absent
        app.command(entry.name, context_settings=STUB_SETTINGS)(missing_command(entry.name, exc))
    return typer.main.get_command(app)  # a one-command Typer is that command


class PluginGroup(TyperGroup):
    """``mfgnet``'s command group: the built-in commands, then the entry points', each loaded when first asked for."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)
        self.plugins = {ep.name: ep for ep in entry_points(group=PLUGIN_GROUP)}

    def list_commands(self, ctx: click.Context) -> list[str]:
        built_in = super().list_commands(ctx)
        return built_in + sorted(name for name in self.plugins if name not in built_in)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        command = super().get_command(ctx, cmd_name)
        if command is None and cmd_name in self.plugins:  # loaded once, then a command of the group like the others
            command = plugin_command(self.plugins[cmd_name])
            self.add_command(command, cmd_name)
        return command
