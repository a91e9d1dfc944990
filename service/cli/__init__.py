"""The ``mfgnet`` command. The runtime sub-commands live here, one module each (``serve``, ``register``,
``sequence``, ``models``); training-side ones (train, evaluate, make-pairs, export, ...) come from the
``mfgnet.commands`` entry points, loaded only when run (:mod:`service.cli.plugins`), so a runtime command never
imports torch, ``model``, ``export`` or ``bench``.

Heavy runtime modules (onnxruntime, the HTTP stack) are imported inside the commands that need them,
so ``mfgnet --help`` stays fast and works with the base install.
"""

from __future__ import annotations

import typer

from service.cli.models import models_command
from service.cli.plugins import PluginGroup
from service.cli.register import register_command
from service.cli.sequence import sequence_command
from service.cli.serve import serve_command

app = typer.Typer(
    cls=PluginGroup,
    help="MFGNet point-cloud registration",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
)  # plain click help: flag names never cut at 80 columns


def _keep_flags_whole() -> None:
    """Help text wrapped at spaces only: textwrap's default also breaks after a hyphen, which cut flag names that a
    help text mentions (``--rotation-`` / ``search``, ``--lr-`` / ``drop-at``) at 80 columns. Typer vendors click
    (``typer._click``); its ``wrap_text`` builds a ``TextWrapper`` from ``_textwrap`` at each call."""
    from typer._click import _textwrap

    class WholeWords(_textwrap.TextWrapper):
        def __init__(self, *args, **kwargs):
            kwargs.setdefault("break_on_hyphens", False)
            super().__init__(*args, **kwargs)

    _textwrap.TextWrapper = WholeWords


_keep_flags_whole()
app.command("serve")(serve_command)
app.command("register")(register_command)
app.command("sequence")(sequence_command)
app.command("models")(models_command)


def main() -> None:
    """The ``mfgnet`` console script."""
    app()
