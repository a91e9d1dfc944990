"""Point-cloud files: one content-detected reader for every entry point, and a writer.

=======================  =====================================================  ==================
format                   read (detected from the content)                       written as
=======================  =====================================================  ==================
PLY (``plyfile``)        ascii, binary little/big endian; vertex x, y, z         binary LE float32;
                                                                                a PLY source moved
PCD (``pypcd4``)         ascii, binary, binary_compressed; fields x, y, z        binary float32;
                         (``VERSION`` ignored, as PCL does)                     a PCD source moved
LAS/LAZ (``laspy``,      scaled x, y, z in float64                               a LAS/LAZ source
``lazrs``)                                                                      moved
E57 (``e57``)            every scan moved into the file's frame by its pose,     --
                         appended; spherical converted; invalid points left out
XYZ/CSV/TXT              whitespace, comma or semicolon separated, the columns   ``%.9g`` text;
                         a header names x, y, z (else the first 3), values      a text source moved
                         optionally quoted; ``#`` comments and one header
                         line skipped
PTS                      blocks of a point count line and that many rows         a PTS source moved
                         ``x y z [i [r g b]]``; each count checked
PTX                      scans of a 10-line header and columns x rows rows,      a PTX source moved
                         each moved by its 4x4; ``0 0 0`` rows left out
NPY                      numbers ``(N, >=3)`` (first 3 columns, any int/float    float32 ``(N, 3)``
                         dtype, cast) or fields x, y, z; no pickles
NPZ                      array ``points``, else ``positions`` (Open3D), else     key ``points``
                         the only array
=======================  =====================================================  ==================

Colours, intensity, normals and faces are not read. "A ... source moved": the source file itself, its points moved
and everything else kept (:func:`service.formats.moved.write_moved`, ``mfgnet register --write-aligned``). The PLY,
PCD, LAS/LAZ and E57 libraries come with the ``formats`` extra (part of ``serve``); without one, reading that format
raises :class:`MissingReaderError` (HTTP 415) naming the extra.
"""

from service.formats.errors import (
    InvalidPointsError,
    MissingReaderError,
    PointCloudFormatError,
    TooManyPointsError,
)
from service.formats.read import READ_SUFFIXES, read_cloud
from service.formats.write import WRITE_SUFFIXES, write_cloud

__all__ = [
    "READ_SUFFIXES",
    "WRITE_SUFFIXES",
    "InvalidPointsError",
    "MissingReaderError",
    "PointCloudFormatError",
    "TooManyPointsError",
    "read_cloud",
    "write_cloud",
]
