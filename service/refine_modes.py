"""Refinement modes of ``Registrar.register(refine=...)`` and what the service applies by default.

Standard library only, so that ``mfgnet --help`` and the settings can use it without loading the
pipeline.
"""

from __future__ import annotations

from enum import Enum

# icp: point-to-point, mutual nearest neighbours; icp-plane: wide robust symmetric stage + point-to-plane;
# icp-plane-multistart: icp-plane, then the best of 13 turned starts (service.multistart)
REFINE_MODES = ("none", "icp", "icp-plane", "icp-plane-multistart")
PLANE_MODES = ("icp-plane", "icp-plane-multistart")  # the modes whose refinement ends point-to-plane

# What the HTTP API and `mfgnet register` apply when a request names no refinement (the server's
# MFGNET_DEFAULT_REFINE): two independently sampled scans need it (docs/DESIGN.md, "Default
# refinement"). `Registrar.register` itself keeps refine=None = the network's pose alone (the paper).
SERVICE_DEFAULT_REFINE = "icp-plane"

# refine_points: how many points per cloud the refinement may use instead of the network's working clouds
# (its cost grows with them; the smallest cloud the service takes has 32 points)
REFINE_POINTS_RANGE = (32, 8192)


class Refine(str, Enum):
    """Command-line spelling of ``refine``."""

    none = "none"
    icp = "icp"
    icp_plane = "icp-plane"
    icp_plane_multistart = "icp-plane-multistart"
