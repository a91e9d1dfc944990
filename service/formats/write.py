"""Writing ``(N, 3)`` points in the format named by the file's extension: float32, or float64 where a coordinate is
beyond ``FLOAT32_EXACT_ENOUGH`` (map frames: float32 steps 0.25-0.5 m at UTM northings)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO

import numpy as np

from service.formats.checks import checked
from service.formats.deps import require
from service.formats.errors import PointCloudFormatError

WRITE_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
# Coordinates up to this keep float32 (steps of at most 1 mm in metres); beyond it the file holds float64 (the client's
# LARGE_COORDINATE, where it re-centres clouds before a float32 upload).
FLOAT32_EXACT_ENOUGH = 1.0e4


def write_cloud(path: str | os.PathLike[str], points: np.ndarray) -> None:
    """Write ``points (N, 3)`` as float32 (float64 where a coordinate is beyond ``FLOAT32_EXACT_ENOUGH``):
    ``.ply`` binary little endian (plyfile), ``.pcd`` binary (pypcd4), ``.xyz``/``.txt`` space separated ``%.9g``
    (``%.17g`` for float64; ``.csv``: commas and an ``x,y,z`` line), ``.npy``, ``.npz`` (key ``points``).

    Raises:
        PointCloudFormatError: unknown extension, wrong shape, no points, NaN/Inf or beyond float32
            (``MissingReaderError`` when the library for ``.ply`` / ``.pcd`` is not installed).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    writer = _WRITERS.get(suffix)
    if writer is None:
        raise PointCloudFormatError(
            f"{path}: unknown extension {path.suffix!r}; expected one of {' '.join(WRITE_SUFFIXES)}")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind not in "fiu":
        raise PointCloudFormatError(f"{path.name}: points must be numbers (N, 3), got {points.dtype} {points.shape}")
    try:
        xyz = checked(points.astype(np.float64))  # [N, 3]
    except PointCloudFormatError as exc:
        raise PointCloudFormatError(f"{path.name}: {exc}") from None
    with open(path, "wb") as f:
        writer(f, as_written(xyz), suffix)


def as_written(xyz: np.ndarray) -> np.ndarray:
    """float64 ``xyz [N, 3]`` as a file holds it: float32 where every coordinate is within ``FLOAT32_EXACT_ENOUGH``,
    else as it is."""
    return xyz.astype(np.float32) if np.abs(xyz).max() <= FLOAT32_EXACT_ENOUGH else xyz


def _write_ply(f: BinaryIO, xyz: np.ndarray, suffix: str) -> None:
    plyfile = require("plyfile", "writing PLY files")
    kind = "<f8" if xyz.dtype == np.float64 else "<f4"
    vertices = np.empty(len(xyz), dtype=[("x", kind), ("y", kind), ("z", kind)])
    for axis, name in enumerate("xyz"):
        vertices[name] = xyz[:, axis]
    element = plyfile.PlyElement.describe(vertices, "vertex")
    plyfile.PlyData([element], byte_order="<", comments=["written by mfgnet"]).write(f)


def _write_pcd(f: BinaryIO, xyz: np.ndarray, suffix: str) -> None:
    pypcd4 = require("pypcd4", "writing PCD files")
    cloud = pypcd4.PointCloud.from_points(xyz, ("x", "y", "z"), (xyz.dtype.type,) * 3)
    cloud.save(f, encoding=pypcd4.Encoding.BINARY)


def _write_text(f: BinaryIO, xyz: np.ndarray, suffix: str) -> None:
    fmt = "%.17g" if xyz.dtype == np.float64 else "%.9g"  # each number read back as written
    if suffix == ".csv":
        np.savetxt(f, xyz, fmt=fmt, delimiter=",", header="x,y,z", comments="")
    else:
        np.savetxt(f, xyz, fmt=fmt, delimiter=" ")


def _write_npy(f: BinaryIO, xyz: np.ndarray, suffix: str) -> None:
    np.save(f, xyz, allow_pickle=False)


def _write_npz(f: BinaryIO, xyz: np.ndarray, suffix: str) -> None:
    np.savez(f, points=xyz)


_WRITERS = {".ply": _write_ply, ".pcd": _write_pcd, ".xyz": _write_text, ".txt": _write_text,
            ".csv": _write_text, ".npy": _write_npy, ".npz": _write_npz}
