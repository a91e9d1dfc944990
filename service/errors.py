"""The pipeline's input error, in a module of its own so that ``registrar`` and ``rotation_search`` can both
raise it (``service.registrar.InputError`` is the same class)."""

from __future__ import annotations


class InputError(ValueError):
    """A request the pipeline cannot run (bad shape, non-finite values, out-of-range option)."""
