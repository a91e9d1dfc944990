"""What is wrong with a JSON cloud's shape, said as a file upload's shape error says it.

A cloud in JSON is a list of ``[x, y, z]`` rows. Pydantic's verdict on another shape names every row ("List should
have at least 3 items ...", and N more) or only the type ("Input should be a valid list"); these messages name the
shape sent and the one expected, as ``.npy`` uploads do (:mod:`service.formats.arrays`), with what a user most often
did: columns sent as an object of arrays, one flat list of numbers, one row per axis, or rows with extra columns.
Mixed rows are left to pydantic, which names the first one that is wrong.
"""

from __future__ import annotations

from numbers import Real
from typing import Any

from service.api.errors import APIError
from service.api.json_clouds import CLOUD_FIELDS
from service.checks import columns_problem, one_row_per_axis, per_axis_problem


def check_cloud_shapes(obj: dict, prefix: str = "") -> None:
    """422 naming the shape of the first of ``obj``'s clouds (``source``, ``target``; ``prefix`` before their names in
    a batch) that is not a list of rows of 3 numbers, where :func:`shape_problem` can say it; else nothing."""
    for name in CLOUD_FIELDS:
        problem = shape_problem(obj.get(name))
        if problem is not None:
            raise APIError(422, f"invalid request: {prefix}{name}: {problem}")


def shape_problem(cloud: Any) -> str | None:
    """What is wrong with ``cloud``'s shape (a parsed JSON value), or ``None`` where it is rows of 3 values, missing,
    or of mixed rows (pydantic's verdict then names the row)."""
    if isinstance(cloud, dict):
        keys = ", ".join(repr(key) for key in list(cloud)[:3])
        return (f"a JSON object (keys {keys}); expected a list of [x, y, z] rows, one per point (columns sent as "
                "arrays? send them as rows)")
    if not isinstance(cloud, list) or not cloud:
        return None
    if all(isinstance(value, Real) and not isinstance(value, bool) for value in cloud):
        return (f"a flat list of {len(cloud)} numbers; expected shape [N, 3], a list of [x, y, z] rows (reshape it to "
                f"[{len(cloud) // 3 if len(cloud) % 3 == 0 else 'N'}, 3])")
    lengths = {len(row) for row in cloud if isinstance(row, list)}
    if len(lengths) != 1 or any(not isinstance(row, list) for row in cloud):
        return None
    if len(cloud) == 1 and per_axis(cloud[0]):  # [1, 3, N] or [1, 4, N]: one row per axis, with a leading 1
        return per_axis_problem([1, len(cloud[0]), len(cloud[0][0])])
    if all(row and all(isinstance(value, list) for value in row) for row in cloud):  # [N, 1, 3]: OpenCV's layout
        inner = {len(value) for row in cloud for value in row}
        return (f"expected shape [N, 3], rows of [x, y, z], got [{len(cloud)}, {lengths.pop()}, "
                f"{inner.pop() if len(inner) == 1 else '...'}]: rows hold lists, not numbers; reshape it to [N, 3]")
    (columns,) = lengths
    if columns == 3:
        return None
    return columns_problem(len(cloud), columns)


def per_axis(rows: list) -> bool:
    """Whether ``rows`` are lists of one length that read as one row per axis (:func:`service.checks.one_row_per_axis`),
    not points."""
    lengths = {len(row) for row in rows if isinstance(row, list)}
    return len(lengths) == 1 and all(isinstance(row, list) for row in rows) and one_row_per_axis(len(rows),
                                                                                                 lengths.pop())
