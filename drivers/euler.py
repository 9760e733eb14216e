"""Static-axes ``sxyz`` Euler angles (the convention of AgileX PiPER and ``piper_sdk``) to and from
quaternions and dual quaternions.

``sxyz`` means: rotate about the fixed x axis by ``rx``, then about the fixed y axis by ``ry``,
then about the fixed z axis by ``rz``, so ``R = Rz(rz) @ Ry(ry) @ Rx(rx)`` (the same matrix as the
intrinsic z-y'-x'' "yaw, pitch, roll"). Angles are radians; ``ry`` comes back in [-pi/2, pi/2] and
the others in [-pi, pi]. At the gimbal lock (``|ry| = pi/2``) only ``rx - rz`` (or ``rx + rz``) is
defined; we return ``rz = 0`` there.

All functions broadcast over leading dimensions.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq

__all__ = ["quat_from_sxyz", "sxyz_from_quat", "matrix_from_sxyz", "dq_from_xyz_sxyz",
           "xyz_sxyz_from_dq"]

# cos(ry) below this is treated as the gimbal lock; 1e-9 keeps rx exact to ~1e-9 rad elsewhere.
_GIMBAL_EPS = 1e-9


def quat_from_sxyz(rx, ry, rz) -> np.ndarray:
    """``q = qz(rz) * qy(ry) * qx(rx)`` as ``(..., 4)`` ``[w, x, y, z]`` with ``w >= 0``."""
    rx, ry, rz = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (rx, ry, rz)))
    cx, sx = np.cos(rx / 2), np.sin(rx / 2)
    cy, sy = np.cos(ry / 2), np.sin(ry / 2)
    cz, sz = np.cos(rz / 2), np.sin(rz / 2)
    q = np.stack([
        cz * cy * cx + sz * sy * sx,
        cz * cy * sx - sz * sy * cx,
        cz * sy * cx + sz * cy * sx,
        sz * cy * cx - cz * sy * sx,
    ], axis=-1)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_from_sxyz(rx, ry, rz) -> np.ndarray:
    """``Rz(rz) @ Ry(ry) @ Rx(rx)`` as ``(..., 3, 3)``."""
    rx, ry, rz = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (rx, ry, rz)))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    return np.stack([
        np.stack([cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx], axis=-1),
        np.stack([sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx], axis=-1),
        np.stack([-sy, cy * sx, cy * cx], axis=-1),
    ], axis=-2)


def sxyz_from_quat(q) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` ``[w, x, y, z]`` (w first) to ``(..., 3)`` angles
    ``[rx, ry, rz]``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    # Matrix entries written in quaternion components: no intermediate 3x3 round-off.
    r00 = 1 - 2 * (y * y + z * z)
    r10 = 2 * (x * y + w * z)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    cy = np.hypot(r00, r10)
    ry = np.arctan2(-r20, cy)
    locked = cy < _GIMBAL_EPS
    rx = np.where(locked, np.arctan2(-r12, r11), np.arctan2(r21, r22))
    rz = np.where(locked, 0.0, np.arctan2(r10, r00))
    return np.stack([rx, ry, rz], axis=-1)


def dq_from_xyz_sxyz(xyz, rxyz) -> np.ndarray:
    """Position ``(..., 3)`` in metres and ``sxyz`` angles ``(..., 3)`` in radians to a pose."""
    rxyz = np.asarray(rxyz, dtype=float)
    return dq.from_pose(quat_from_sxyz(rxyz[..., 0], rxyz[..., 1], rxyz[..., 2]),
                        np.asarray(xyz, dtype=float))


def xyz_sxyz_from_dq(pose) -> tuple[np.ndarray, np.ndarray]:
    """A pose to ``(position in metres, sxyz angles in radians)``."""
    q, t = dq.to_pose(pose)
    return t, sxyz_from_quat(q)
