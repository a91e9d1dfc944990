"""Reading and writing point clouds for the CLI and the service: a thin front to :mod:`service.formats`.

Every reader returns finite float64 ``(N, 3)`` coordinates (``N >= 1``; float64 so that large LAS/UTM
coordinates keep their precision) and raises :class:`PointCloudFormatError` (a ``ValueError``) with the
file's name and the reason. The format is detected from the content; the extension is only a name.
"""

from __future__ import annotations

import os

import numpy as np

from service.formats import READ_SUFFIXES, WRITE_SUFFIXES, PointCloudFormatError, read_cloud, write_cloud

SUFFIXES = WRITE_SUFFIXES  # the extensions write_points knows (read_points reads .las/.laz too: READ_SUFFIXES)

__all__ = ["READ_SUFFIXES", "SUFFIXES", "PointCloudFormatError", "parse_points", "read_points", "write_points"]


def read_points(path: str | os.PathLike[str]) -> np.ndarray:
    """float64 ``(N, 3)`` coordinates of the cloud in ``path`` (any format of :mod:`service.formats`).

    Raises:
        PointCloudFormatError: unreadable or unrecognised content, fewer than 3 columns, no points,
            NaN/Inf values, a missing reader library.
        OSError: the file cannot be opened.
    """
    return read_cloud(path)


def parse_points(data: bytes, suffix: str = "", name: str = "<bytes>") -> np.ndarray:
    """Like :func:`read_points` for a file's ``data``; ``suffix`` is ignored (the content decides)."""
    return read_cloud(data, name)


def write_points(path: str | os.PathLike[str], points: np.ndarray) -> None:
    """Write ``points (N, 3)`` in the format of ``path``'s extension (:data:`SUFFIXES`): float32, float64 for map
    coordinates (:func:`service.formats.write_cloud`)."""
    write_cloud(path, points)
