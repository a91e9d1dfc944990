"""The command line's spelling of ``Registrar.register(rotation_search=...)`` (``False``, ``True`` or ``"auto"``).

Standard library only, so that ``mfgnet --help`` and the training-side commands can use it without
loading scipy or the pipeline.
"""

from __future__ import annotations

from enum import Enum


class RotationSearchMode(str, Enum):
    """Command-line spelling of ``Registrar.register(rotation_search=...)`` (``--rotation-search-mode``)."""

    off = "off"  # False
    on = "on"  # True
    auto = "auto"  # "auto": only when the plain result looks wrong


def rotation_search_from_options(flag: bool | None, mode: str | None) -> bool | str:
    """``rotation_search`` for ``Registrar.register`` from the command line's ``--rotation-search`` /
    ``--no-rotation-search`` flag (``None``: not given) and ``--rotation-search-mode off|on|auto``.

    Either alone decides (neither: off); both must agree, else ``ValueError``.
    """
    values = {"off": False, "on": True, "auto": "auto"}
    if mode is None:
        return bool(flag)
    key = mode.value if isinstance(mode, RotationSearchMode) else str(mode)
    if key not in values:
        raise ValueError(f"--rotation-search-mode must be one of {', '.join(values)}, got {key!r}")
    if flag is not None and values[key] is not flag:
        given = "--rotation-search" if flag else "--no-rotation-search"
        raise ValueError(f"{given} contradicts --rotation-search-mode {key}; give one of them")
    return values[key]
