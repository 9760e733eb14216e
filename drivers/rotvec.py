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

from service import dq

__all__ = ["quat_from_rotvec", "rotvec_from_quat", "pose_from_rotvec", "rotvec_from_pose"]

# Below this angle the Taylor series of sin(a/2)/a (and of a/sin(a/2)) are exact to double
# precision with three terms; above it the closed forms have no cancellation.
_SMALL = 1e-3


def _as_array(x, name: str, last: int) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != last:
        raise ValueError(f"{name}: expected shape (..., {last}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return a


def quat_from_rotvec(rotvec) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` (axis times angle) to unit quaternions ``(..., 4)``
    ``[w, x, y, z]``. Any angle is accepted; the result has ``w = cos(angle / 2)``."""
    r = _as_array(rotvec, "rotvec", 3)
    angle = np.linalg.norm(r, axis=-1)
    small = angle < _SMALL
    a2 = angle * angle
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(small, 0.5 - a2 / 48.0 + a2 * a2 / 3840.0, np.sin(0.5 * angle) / angle)
    return np.concatenate([np.cos(0.5 * angle)[..., None], k[..., None] * r], axis=-1)


def rotvec_from_quat(q) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` ``[w, x, y, z]`` to rotation vectors ``(..., 3)`` with angle
    in ``[0, pi]`` (``q`` and ``-q`` give the same vector, except at exactly pi where the
    sign of the axis follows ``q``). Quaternions within 1e-6 of unit norm are normalised."""
    q = _as_array(q, "q", 4)
    n = np.linalg.norm(q, axis=-1)
    bad = np.abs(n - 1.0) > dq.UNIT_TOL
    if np.any(bad):
        i = np.argwhere(bad)[0] if bad.ndim else ()
        where = "q" + "".join(f"[{int(j)}]" for j in i)
        raise ValueError(f"{where}: quaternion norm {float(n[tuple(i)]):.6g} is not unit "
                         f"(tolerance {dq.UNIT_TOL:g})")
    q = q / n[..., None]
    # The short way round: w >= 0 puts the angle in [0, pi].
    q = np.where(q[..., :1] < 0.0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    small = angle < _SMALL
    a2 = angle * angle
    with np.errstate(invalid="ignore", divide="ignore"):
        # angle / sin(angle / 2), by series where s is tiny.
        k = np.where(small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, angle / s)
    return k[..., None] * v


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
    except ValueError as e:     # the core names its argument "a"; ours is "pose"
        msg = str(e)
        raise ValueError("pose" + msg[1:] if msg.startswith("a") else msg) from None
    return np.concatenate([t, rotvec_from_quat(q)], axis=-1)
