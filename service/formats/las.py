"""LAS and LAZ with ``laspy`` (LAZ through its ``lazrs`` backend): scaled x, y, z in float64.

LAS stores integers with a scale and an offset, often UTM coordinates of millions of metres;
they are returned in float64, unrounded (the registrar centres each cloud before its float32 stages).
"""

from __future__ import annotations

from typing import BinaryIO

import numpy as np

from service.formats.checks import check_count, xyz_columns
from service.formats.deps import require
from service.formats.errors import MissingReaderError, PointCloudFormatError


def read_las(f: BinaryIO, max_points: int | None) -> np.ndarray:
    laspy = require("laspy", "reading LAS/LAZ files")
    try:
        with laspy.open(f, closefd=False) as reader:
            count = int(reader.header.point_count)
            check_count(count, max_points)
            if reader.header.are_points_compressed and not laspy.LazBackend.detect_available():
                raise MissingReaderError("reading LAZ files needs the 'lazrs' package, which is not installed: "
                                         "pip install 'mfgnet[formats]'")
            points = reader.read_points(count)
    except PointCloudFormatError:
        raise
    except Exception as exc:  # laspy's LaspyException, or what numpy and the LAZ backend raise on bad data
        raise PointCloudFormatError(f"corrupt LAS/LAZ data ({type(exc).__name__}: {exc})") from None
    if len(points) != count:
        raise PointCloudFormatError(f"LAS data holds {len(points)} points; the header says {count}")
    return xyz_columns([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)])
