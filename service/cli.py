"""The ``mfgnet`` command. Runtime sub-commands live here; training-side ones (train, evaluate,
make-pairs, export, ...) are discovered through the ``mfgnet.commands`` entry-point group, so this
module never imports torch, ``model`` or ``export``."""

from __future__ import annotations

from importlib.metadata import entry_points
from importlib.util import find_spec

import typer

app = typer.Typer(help="MFGNet point-cloud registration", no_args_is_help=True, add_completion=False)

TRAIN_EXTRA_HINT = "this command needs the training side: pip install 'mfgnet[train]'"


def _missing_command(name: str, error: Exception):
    def command(ctx: typer.Context) -> None:
        typer.echo(f"mfgnet {name}: {TRAIN_EXTRA_HINT} ({error})", err=True)
        raise typer.Exit(code=2)

    command.__doc__ = f"[needs the train extra] {name}"
    return command


def _register_plugins() -> None:
    torch_missing = find_spec("torch") is None  # checked without importing torch
    for ep in entry_points(group="mfgnet.commands"):
        try:
            if torch_missing:
                raise ImportError("torch is not installed")
            fn = ep.load()
        except ImportError as exc:  # torch or another training dependency is absent
            app.command(ep.name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(
                _missing_command(ep.name, exc))
        else:
            app.command(ep.name)(fn)


_register_plugins()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
