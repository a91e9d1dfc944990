"""The command line's spelling of ``Registrar.register(rotation_search=...)`` (``False``, ``True`` or ``"auto"``).

Standard library only, so that ``mfgnet --help`` and the training-side commands can use it without
loading scipy or the pipeline.
"""

from __future__ import annotations

from enum import Enum

# What the HTTP API and `mfgnet register` run when a request names no rotation search (the server's
# MFGNET_DEFAULT_ROTATION_SEARCH), applied only to refined requests (unrefined network poses of independent
# scans never fit tightly, so "auto" would search every one). "auto": users' scans arrive at any relative
# orientation, and the search runs only when the plain result may be wrong: it fits worse than the clouds' density
# allows, lies off a dense target's surface, or both clouds are rooms (docs/decisions/0007-real-scan-defaults.md,
# 0022, 0023). Operators who need the lowest latency on clouds known to be
# within ~45 deg of each other set MFGNET_DEFAULT_ROTATION_SEARCH=off.
SERVICE_DEFAULT_ROTATION_SEARCH = "auto"
MODE_VALUES: dict[str, bool | str] = {"off": False, "on": True, "auto": "auto"}


class RotationSearchMode(str, Enum):
    """Command-line spelling of ``Registrar.register(rotation_search=...)`` (``--rotation-search-mode``)."""

    off = "off"  # False
    on = "on"  # True
    auto = "auto"  # "auto": only when the plain result looks wrong


def rotation_search_from_options(flag: bool | None, mode: str | None) -> bool | str | None:
    """``rotation_search`` for ``Registrar.register`` from the command line's ``--rotation-search`` /
    ``--no-rotation-search`` flag (``None``: not given) and ``--rotation-search-mode off|on|auto``.

    Either alone decides; neither gives ``None`` (the caller's default); both must agree, else ``ValueError``.
    """
    if mode is None:
        return flag
    key = mode.value if isinstance(mode, RotationSearchMode) else str(mode)
    if key not in MODE_VALUES:
        raise ValueError(f"--rotation-search-mode must be one of {', '.join(MODE_VALUES)}, got {key!r}")
    if flag is not None and MODE_VALUES[key] is not flag:
        given = "--rotation-search" if flag else "--no-rotation-search"
        raise ValueError(f"{given} contradicts --rotation-search-mode {key}; give one of them")
    return MODE_VALUES[key]


def service_rotation_search(
    requested: bool | str | None, refine: str, default: str = SERVICE_DEFAULT_ROTATION_SEARCH
) -> bool | str:
    """The rotation search the service runs: the request's own choice when it made one; otherwise the
    server's ``default`` (``"off"``, ``"on"`` or ``"auto"``) for a refined request and ``False`` for
    ``refine="none"`` (see ``SERVICE_DEFAULT_ROTATION_SEARCH``)."""
    if requested is not None:
        return requested
    return False if refine == "none" else MODE_VALUES[default]
