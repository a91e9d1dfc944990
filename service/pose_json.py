"""The pose part of every JSON answer (HTTP response, ``mfgnet register --out``): one definition."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.procrustes import to_matrix


def pose_fields(rotation, translation) -> dict:
    """``rotation`` (3x3), ``translation`` (3), ``transform`` (4x4, source -> target) and
    ``euler_zyx_deg`` (scipy ``as_euler("zyx", degrees=True)``), as plain float lists."""
    R = np.asarray(rotation, dtype=np.float64)  # [3, 3]
    t = np.asarray(translation, dtype=np.float64)  # [3]
    return {
        "rotation": R.tolist(),
        "translation": t.tolist(),
        "transform": to_matrix(R, t).tolist(),
        "euler_zyx_deg": Rotation.from_matrix(R).as_euler("zyx", degrees=True).tolist(),
    }
