"""The pose part of every JSON answer (HTTP response, ``mfgnet register --out``): one definition.

Euler angles (as the OpenAPI schema of ``RegisterResponse`` documents them), with Rx, Ry, Rz
the right-handed rotations about the fixed x, y, z axes acting on column vectors:

* ``euler_zyx_deg = [a, b, c]`` is scipy ``as_euler("zyx")``, lowercase = extrinsic: ``R = Rx(c) Ry(b) Rz(a)``.
* ``yaw_pitch_roll_deg = [yaw, pitch, roll]`` is scipy ``as_euler("ZYX")``, intrinsic:
  ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

And the unit quaternion ``quaternion_xyzw = [x, y, z, w]`` (scalar last, as ROS ``geometry_msgs/Quaternion``, Eigen's
``coeffs()`` and scipy ``as_quat()``), with ``w >= 0``: ``q`` and ``-q`` are the same rotation, and one of them is
given.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from service.procrustes import to_matrix


def pose_fields(rotation: np.ndarray, translation: np.ndarray) -> dict:
    """``rotation`` (3x3), ``translation`` (3), ``transform`` (4x4, source -> target), ``euler_zyx_deg`` and
    ``yaw_pitch_roll_deg`` (degrees) and ``quaternion_xyzw`` (see the module docstring), as plain float lists."""
    R = np.asarray(rotation, dtype=np.float64)  # [3, 3]
    t = np.asarray(translation, dtype=np.float64)  # [3]
    return {
        "rotation": R.tolist(),
        "translation": t.tolist(),
        "transform": to_matrix(R, t).tolist(),
        **{key: value.tolist() for key, value in rotation_fields(R).items()},
    }


def rotation_fields(rotation: np.ndarray) -> dict[str, np.ndarray]:
    """``euler_zyx_deg`` [3], ``yaw_pitch_roll_deg`` [3] (degrees) and ``quaternion_xyzw`` [4] (``w >= 0``) of
    ``rotation`` (3x3), as float64 arrays (see the module docstring)."""
    turn = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64))
    return {
        "euler_zyx_deg": turn.as_euler("zyx", degrees=True),  # [3] a, b, c: R = Rx(c) Ry(b) Rz(a)
        "yaw_pitch_roll_deg": turn.as_euler("ZYX", degrees=True),  # [3]: R = Rz(yaw) Ry(pitch) Rx(roll)
        "quaternion_xyzw": turn.as_quat(canonical=True),  # [4] x, y, z, w with w >= 0
    }
