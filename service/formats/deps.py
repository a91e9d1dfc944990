"""Optional reader libraries: imported on first use, with an error naming the extra that installs them."""

from __future__ import annotations

import importlib
from types import ModuleType

from service.formats.errors import MissingReaderError

EXTRA = "formats"  # pyproject.toml: plyfile, pypcd4, laspy + lazrs, e57 (the serve extra includes it)


def require(module: str, what: str) -> ModuleType:
    """``import module``, or :class:`MissingReaderError` saying that ``what`` needs it and how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingReaderError(
            f"{what} needs the '{module}' package, which is not installed: pip install 'mfgnet[{EXTRA}]'"
        ) from None
