"""Input checks shared by the pipeline and the HTTP API: clouds and the initial transform."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from service.errors import InputError

MIN_POINTS = 32
# How far from orthonormal (max |R R^T - I|) an initial_transform's rotation may be: a pose printed with three
# decimals is within 1.7e-3 (the most over 100,000 random rotations); a scale of 1.001 or more is refused.
ORTHONORMAL_TOLERANCE = 2e-3
EXACT_TOLERANCE = 1e-12  # orthonormal to float64 rounding: taken as it is, not projected
# A Python float: compared with one, a float64 stays float64 (NumPy 2 compared it with np.float32's max in float32,
# whose cast of 1e39 overflowed with a RuntimeWarning on the caller's stderr)
FLOAT32_MAX = float(np.finfo(np.float32).max)
# The smallest largest |coordinate| of a cloud (all zeros aside: one repeated point, which the quality stage names).
# Clouds scaled down to it register as at their own size; float32 uploads drift and lose `reliable` near float32's
# smallest normal number (1.2e-38), float64 clouds fail below about 1e-155, where squared distances underflow
# (docs/decisions/0104-a-floor-for-tiny-coordinates.md).
SMALLEST_COORDINATES = 1e-30


def max_abs(values: np.ndarray) -> float:
    """The largest ``|value|`` of a non-empty array, without a temporary ``|values|`` of its size (46 MiB for a
    2,000,000-point cloud)."""
    return max(float(values.max()), -float(values.min()))


# Depth cameras mark missing returns with NaN rows: an organized PCD file's are left out on read
# (service/formats/pcd.py); in arrays and other files the caller drops them
LEAVE_NAN_ROWS_OUT = "leave such rows out (e.g. points[np.isfinite(points).all(axis=1)])"


def one_row_per_axis(rows: int, columns: int) -> bool:
    """Whether ``rows`` rows of ``columns`` numbers read as one row per axis: 3 (x, y, z) or 4 (homogeneous) rows of
    more numbers than rows."""
    return rows in (3, 4) and columns > rows


def per_axis_problem(shape: list[int]) -> str:
    """What is wrong with a cloud sent as one row per axis (``shape``: as sent, ``[3, N]`` or ``[4, N]``, homogeneous
    coordinates, perhaps after a leading 1), and how to mend it; the same words for arrays in process, JSON clouds
    (``service/api/json_shapes.py``) and ``.npy`` files (``service/formats/arrays.py``)."""
    if shape[-2] == 3:
        return f"expected shape [N, 3], got {shape}: one row per axis; send one [x, y, z] row per point (the array " \
            "transposed)"
    return (f"expected shape [N, 3], got {shape}: one row per axis, as homogeneous coordinates are; send one [x, y, z] "
            "row per point (the first three rows transposed, cloud[:3].T, where the fourth is all 1)")


def columns_problem(rows: int, columns: int) -> str:
    """What is wrong with a cloud of ``rows`` rows of ``columns`` numbers (``columns != 3``), and how to mend it; the
    same words for arrays in process and for JSON clouds (``service/api/json_shapes.py``)."""
    if one_row_per_axis(rows, columns):
        return per_axis_problem([rows, columns])
    extra = ("; x, y, z only: the first three columns (cloud[:, :3]) where they are x, y, z; a point-cloud file may "
             "carry other fields") if columns > 3 else ""
    return f"expected shape [N, 3], rows of [x, y, z], got [{rows}, {columns}]{extra}"


def check_cloud(points: ArrayLike, name: str) -> np.ndarray:
    """``points`` as float64 ``[N, 3]`` with ``N >= MIN_POINTS`` and finite values, none beyond float32's largest
    and not all below ``SMALLEST_COORDINATES`` (all zero aside), or ``InputError``.

    A float64 array comes back as itself (or a view of it), not copied: a 2,000,000-point cloud is 46 MiB, and no
    stage writes to the caller's clouds (the anchor stage only records their centroids)."""
    try:
        arr = np.asarray(points)
    except ValueError:  # rows of different lengths
        raise InputError(f"{name}: expected an [N, 3] array of numbers, got rows of different lengths") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected numbers, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim == 2 and arr.shape[1] != 3:
        raise InputError(f"{name}: {columns_problem(*arr.shape)}")
    if arr.ndim != 2:
        raise InputError(f"{name}: expected shape [N, 3], got {list(arr.shape)}")
    if isinstance(points, list | tuple) and points and isinstance(points[0], np.ma.MaskedArray):  # [masked], rows
        points = np.ma.array(points)  # their masks, which np.asarray drops
    if isinstance(points, np.ma.MaskedArray) and np.ma.is_masked(points):  # np.asarray drops the mask
        mask = np.ma.getmaskarray(points).reshape(arr.shape)  # [N, 3], as arr ([1, N, 3] taken as [N, 3])
        rows = int(mask.any(axis=1).sum())
        raise InputError(f"{name}: a masked array with {rows} masked row{'s' if rows != 1 else ''}; its masked values "
                         "would be used as points: leave them out first (e.g. "
                         "points[~np.ma.getmaskarray(points).any(axis=-1)])")
    if arr.shape[0] < MIN_POINTS:
        raise InputError(f"{name}: needs at least {MIN_POINTS} points, got {arr.shape[0]}")
    arr = np.asarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        bad = ~np.isfinite(arr).all(axis=1)  # [N]
        raise InputError(f"{name}: contains NaN or infinite coordinates in {int(bad.sum())} of {len(arr)} rows, first "
                         f"at row {int(np.argmax(bad))}; {LEAVE_NAN_ROWS_OUT}")
    largest = max_abs(arr)
    if largest > FLOAT32_MAX:
        beyond = (np.abs(arr) > FLOAT32_MAX).any(axis=1)  # [N]
        raise InputError(f"{name}: coordinates overflow float32 (|value| > {FLOAT32_MAX:.4g}) in {int(beyond.sum())} "
                         f"of {len(arr)} rows, first at row {int(np.argmax(beyond))}; {LEAVE_NAN_ROWS_OUT}")
    if 0 < largest < SMALLEST_COORDINATES:
        raise InputError(f"{name}: coordinates too small: the largest |value| is {largest:.3g}, below "
                         f"{SMALLEST_COORDINATES:g}; send the cloud in a unit that gives it a size (metres, "
                         "millimetres)")
    return arr


def check_transform(matrix: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """A 4x4 rigid ``src_to_tgt`` guess -> ``(R, t)``; rejects non-rigid or non-finite matrices.

    Poses written with a few decimals (a dataset's ground truth, another tool's output) are orthonormal only to
    about their last digit: a rotation part within ``ORTHONORMAL_TOLERANCE`` of orthonormal is taken as the nearest
    rotation (as it is when orthonormal to float64 rounding). A larger deviation is a scale or shear, which no
    rigid pose has, and is refused.
    """
    try:
        T = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):  # strings, rows of different lengths
        raise InputError(f"initial_transform must be a 4x4 matrix of numbers, got {type(matrix).__name__}") from None
    if T.shape != (4, 4):
        raise InputError(f"initial_transform must be 4x4, got {list(T.shape)}")
    if not np.isfinite(T).all():
        raise InputError("initial_transform contains NaN or infinite values")
    R, t = T[:3, :3], T[:3, 3]
    deviation = float(np.abs(R @ R.T - np.eye(3)).max())
    problems = []  # each names what is wrong, so a right rotation with a wrong last row is not told "off by 0"
    if deviation > ORTHONORMAL_TOLERANCE:
        problems.append(f"its rotation must be orthonormal (R R^T within {ORTHONORMAL_TOLERANCE:g} of the identity), "
                        f"off by {deviation:.3g}")
    elif np.linalg.det(R) < 0:
        problems.append(f"its rotation must have det +1, got {np.linalg.det(R):.3g} (a reflection)")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        problems.append(f"its last row must be 0 0 0 1, got {' '.join(f'{v:.6g}' for v in T[3])}")
    if problems:
        raise InputError(f"initial_transform must be rigid: {'; '.join(problems)}")
    return (R.copy() if deviation <= EXACT_TOLERANCE else nearest_rotation(R)), t.copy()


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation ``[3, 3]`` nearest ``matrix [3, 3]`` in the Frobenius norm (its polar factor, det +1)."""
    U, _, Vt = np.linalg.svd(matrix)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
