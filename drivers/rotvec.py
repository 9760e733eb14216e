"""Rotation parametrisations used by device protocols, to and from the project's quaternions and
dual quaternions.

Rotation vectors (axis times angle, radians) are what Universal Robots controllers speak: a UR pose
``p6 = [x, y, z, rx, ry, rz]`` is a translation in metres followed by a rotation vector, and maps
tool points to base points like ``T_base_tool``.

Every function broadcasts over leading dimensions and stays exact near angle 0 (series instead of
0/0) and near pi (``atan2`` instead of ``acos``).
"""
from __future__ import annotations

import numpy as np

from dqpose import dq
from dqpose.errors import rename

__all__ = ["quat_from_rotvec", "rotvec_from_quat", "pose_from_rotvec", "rotvec_from_pose"]



def _as_array(x, name: str, last: int) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != last:
        raise ValueError(f"{name}: expected shape (..., {last}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return a


# A rotation vector is twice the real part of the dual-quaternion log of the rotation, so the
# core's exp and log (series near 0, atan2 near pi, the short way round) do the work.

def quat_from_rotvec(rotvec) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` (axis times angle) to unit quaternions ``(..., 4)``
    ``[w, x, y, z]``. Any angle is accepted; the result has ``w = cos(angle / 2)``."""
    r = _as_array(rotvec, "rotvec", 3)
    x = np.concatenate([0.5 * r, np.zeros_like(r)], axis=-1)
    return dq.exp(x)[..., :4]


def rotvec_from_quat(q) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` ``[w, x, y, z]`` (w first) to rotation vectors ``(..., 3)``
    with angle in ``[0, pi]`` (``q`` and ``-q`` give the same vector, except at exactly pi where
    the sign of the axis follows ``q``). Quaternions within 1e-6 of unit norm are normalised."""
    q = _as_array(q, "q", 4)
    try:
        return 2.0 * dq.log(np.concatenate([q, np.zeros_like(q)], axis=-1))[..., :3]
    except ValueError as e:
        raise rename(e, {"a": "q{}"}) from None


def pose_from_rotvec(p6) -> np.ndarray:
    """UR poses ``(..., 6)`` ``[x, y, z, rx, ry, rz]`` to dual quaternions ``(..., 8)``."""
    p = _as_array(p6, "p6", 6)
    return dq.from_pose(quat_from_rotvec(p[..., 3:]), p[..., :3])


def rotvec_from_pose(pose) -> np.ndarray:
    """Dual quaternions ``(..., 8)`` to UR poses ``(..., 6)`` ``[x, y, z, rx, ry, rz]``, rotation
    angle in ``[0, pi]``."""
    a = _as_array(pose, "pose", 8)
    try:
        q, t = dq.to_pose(a)
    except ValueError as e:
        raise rename(e, {"a": "pose{}"}) from None
    return np.concatenate([t, rotvec_from_quat(q)], axis=-1)
