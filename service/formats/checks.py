"""The checks every reader applies: the point-count limit (before reading) and usable coordinates (after)."""

from __future__ import annotations

import numpy as np

from service.checks import LEAVE_NAN_ROWS_OUT, max_abs
from service.formats.errors import InvalidPointsError, TooManyPointsError

FLOAT32_MAX = float(np.finfo(np.float32).max)


def check_count(count: int, max_points: int | None) -> None:
    """:class:`TooManyPointsError` when a header announces more than ``max_points`` points."""
    if max_points is not None and count > max_points:
        raise TooManyPointsError(f"has {count} points; the limit is {max_points} per cloud", count, max_points)


def xyz_columns(columns: list[np.ndarray]) -> np.ndarray:
    """Three coordinate columns (any numeric dtype) -> checked float64 ``[N, 3]``."""
    for column in columns:
        if column.dtype.kind not in "fiu":
            raise InvalidPointsError(f"coordinates must be real numbers, got dtype {column.dtype}")
    xyz = np.empty((len(columns[0]), 3), dtype=np.float64)  # [N, 3]
    for axis, column in enumerate(columns):
        xyz[:, axis] = column
    return checked(xyz)


def checked(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` float64 ``[N, 3]`` if it has points, all finite and within float32's range."""
    if xyz.shape[0] == 0:
        raise InvalidPointsError("the cloud is empty")
    if np.isfinite(xyz).all() and max_abs(xyz) <= FLOAT32_MAX:
        return xyz
    bad = ~(np.abs(xyz) <= FLOAT32_MAX).all(axis=1)  # NaN compares false
    if bad.any():
        raise InvalidPointsError(
            f"{int(bad.sum())} point(s) with NaN/Inf coordinates or beyond the float32 range, "
            f"first at index {int(np.argmax(bad))}; {LEAVE_NAN_ROWS_OUT}"
        )
    return xyz
