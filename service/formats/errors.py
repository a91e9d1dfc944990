"""The errors of point-cloud reading and writing, each with the HTTP status the service answers."""

from __future__ import annotations


class PointCloudFormatError(ValueError):
    """A point-cloud file that cannot be read (corrupt, unrecognised), or points that cannot be written."""

    status = 400


class InvalidPointsError(PointCloudFormatError):
    """The file reads, but its points are unusable: too few columns, no points, NaN/Inf, a wrong dtype."""

    status = 422


class TooManyPointsError(PointCloudFormatError):
    """The cloud has more points than the caller's limit (found from the header, before the points are read)."""

    status = 413

    def __init__(self, message: str, count: int, limit: int):
        super().__init__(message)
        self.count = count
        self.limit = limit


class MissingReaderError(PointCloudFormatError):
    """The format's reader library is not installed; the message names the package and the extra."""

    status = 415
