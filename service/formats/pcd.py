"""PCD (ascii, binary, binary_compressed) with ``pypcd4``: the x, y, z fields.

The header is parsed first (``pypcd4.MetaData``) so that the point count and the compressed
block's declared size are checked before anything is allocated. Other fields are ignored.
"""

from __future__ import annotations

import struct
from typing import BinaryIO

import numpy as np

from service.formats.checks import check_count, xyz_columns
from service.formats.deps import require
from service.formats.errors import InvalidPointsError, PointCloudFormatError

MAX_HEADER_LINES = 64
MAX_LINE_BYTES = 4096


def read_pcd(f: BinaryIO, max_points: int | None) -> np.ndarray:
    pypcd4 = require("pypcd4", "reading PCD files")
    require("lzf", "reading PCD files")  # pypcd4 imports it for binary_compressed
    start = f.tell()
    meta = _metadata(pypcd4, f)
    check_count(meta.points, max_points)
    missing = [axis for axis in "xyz" if axis not in meta.fields]
    if missing:
        raise InvalidPointsError(f"PCD file lacks fields {missing}")
    if meta.data == "binary_compressed":
        _check_compressed_sizes(f, meta)
    f.seek(start)
    try:
        cloud = pypcd4.PointCloud.from_fileobj(f)
    except Exception as exc:  # pypcd4 raises what numpy, struct and lzf raise on bad data
        raise PointCloudFormatError(f"corrupt PCD data ({type(exc).__name__}: {exc})") from None
    table = np.atleast_1d(cloud.pc_data)
    if len(table) != meta.points:
        raise PointCloudFormatError(f"PCD data holds {len(table)} points; the header says {meta.points}")
    return xyz_columns([np.asarray(table[axis]).reshape(len(table), -1)[:, 0] for axis in "xyz"])


def _metadata(pypcd4, f: BinaryIO):
    lines: list[str] = []
    for _ in range(MAX_HEADER_LINES):
        raw = f.readline(MAX_LINE_BYTES)
        if not raw:
            break
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudFormatError("invalid PCD header (not ASCII text)") from None
        if line and not line.startswith("#"):
            lines.append(line)
            if line.upper().startswith("DATA"):
                break
    else:
        raise PointCloudFormatError("invalid PCD header (no DATA line)")
    try:
        return pypcd4.MetaData.parse_header(lines)
    except Exception as exc:  # pydantic's ValidationError: a missing or malformed header entry
        reason = " ".join(str(exc).split())[:300]
        raise PointCloudFormatError(f"invalid PCD header ({reason})") from None


def _check_compressed_sizes(f: BinaryIO, meta) -> None:
    sizes = f.read(8)
    if len(sizes) != 8:
        raise PointCloudFormatError("PCD binary_compressed data cut short")
    _, raw = struct.unpack("<II", sizes)
    expected = meta.points * meta.build_dtype().itemsize
    if raw != expected:
        raise PointCloudFormatError(f"PCD binary_compressed block declares {raw} bytes; the fields need {expected}")
