"""The files of ``bench.scan_files`` as the tests of the aligned file use them (``mfgnet register --write-aligned``,
``POST /v1/register/aligned``, the page's download): a PCD kept compressed where asked, a LAS file read back."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pypcd4

from bench import scan_files
from bench.scan_files import PCD_NORMALS, PLY_NORMALS, coloured_ply, unit_normals

__all__ = ["PCD_NORMALS", "PLY_NORMALS", "coloured_ply", "pcd_with_fields", "survey_las", "unit_normals"]


def pcd_with_fields(path: Path, xyz: np.ndarray, encoding: str) -> np.ndarray:
    """:func:`bench.scan_files.pcd_with_fields`, checked to be written in ``encoding`` (compressible data)."""
    records = scan_files.pcd_with_fields(path, xyz, encoding)
    if encoding != "ascii":
        assert pypcd4.PointCloud.from_path(path).metadata.data.value == encoding  # compressible: kept compressed
    return records


def survey_las(path: Path, xyz: np.ndarray, offsets=scan_files.UTM_OFFSETS) -> laspy.LasData:
    """:func:`bench.scan_files.survey_las`, read back."""
    scan_files.survey_las(path, xyz, offsets)
    return laspy.read(str(path))
