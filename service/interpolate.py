"""Piecewise interpolation between time-stamped keyframe poses (no gRPC here).

Two modes (:data:`dqpose.trajectory.INTERPOLATIONS`, the planner's too), because robotics users
want different paths between the same keyframes:

* ``"screw"``: ScLERP per segment, a constant-rate screw motion (the geodesic of SE(3) under the
  dual-quaternion metric). The tool point follows a helix, which may leave the straight line.
* ``"tool_linear"``: the tool point moves on the straight line between the keyframe positions at
  constant speed while the orientation is slerped, as MoveIt / Pilz LIN, Drake's PiecewisePose and
  tf2 do.

Requested times must lie within the keyframe range: extrapolating a robot's motion past its last
keyframe is never what a caller means, so it is an error rather than a silent clamp.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq
from dqpose.errors import rename
from dqpose.trajectory import INTERPOLATIONS


def _times(name: str, t, ndim_msg: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"{name}: expected {ndim_msg}, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}]: contains NaN or infinity")
    return t


def interpolate(times_k, dqs_k, times, mode: str = "screw") -> np.ndarray:
    """Poses at ``times`` ``(N,)`` between keyframes ``dqs_k`` ``(K, 8)`` stamped ``times_k``
    ``(K,)``.

    ``times_k`` must be strictly increasing with ``K >= 2``; ``times`` may come in any order and
    each must lie in ``[times_k[0], times_k[-1]]``. Returns ``(N, 8)`` unit dual quaternions; the
    keyframes are returned exactly at their own times. Errors are ``ValueError`` naming the
    argument and index, e.g. ``times_k[3]: 1.5 is not after the previous keyframe time 1.5 ...``.
    """
    if mode not in INTERPOLATIONS:
        raise ValueError(f"mode: unknown interpolation {mode!r}; expected one of "
                         f"{', '.join(INTERPOLATIONS)}")
    tk = _times("times_k", times_k, "a 1-D array of keyframe times")
    t = _times("times", times, "a 1-D array of times")
    dqs_k = np.asarray(dqs_k, dtype=np.float64)
    if dqs_k.ndim != 2 or dqs_k.shape[1] != 8:
        raise ValueError(f"dqs_k: expected shape (K, 8), got {dqs_k.shape}")
    if dqs_k.shape[0] != tk.shape[0]:
        raise ValueError(f"times_k: length {tk.shape[0]} does not match the number of keyframes "
                         f"({dqs_k.shape[0]})")
    if tk.shape[0] < 2:
        raise ValueError(f"times_k: need at least 2 keyframes, got {tk.shape[0]}")
    with np.errstate(over="ignore"):   # an overflowing span is refused below, not warned about
        step = np.diff(tk)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(f"times_k[{i}]: {float(tk[i])!r} is not after the previous keyframe time "
                         f"{float(tk[i - 1])!r} (keyframe times must be strictly increasing)")
    # The segment fraction divides by the span: an infinite one would make it NaN.
    bad = np.flatnonzero(np.isinf(step))
    if bad.size:
        i = bad[0] + 1
        raise ValueError(f"times_k[{i}]: the span from the previous keyframe time "
                         f"{float(tk[i - 1])!r} to {float(tk[i])!r} overflows a float64")
    bad = np.flatnonzero((t < tk[0]) | (t > tk[-1]))
    if bad.size:
        i = bad[0]
        raise ValueError(f"times[{i}]: {float(t[i])!r} is outside the keyframe range "
                         f"[{float(tk[0])!r}, {float(tk[-1])!r}]")
    # Validates every keyframe once, naming it, before any segment math.
    q_k, p_k = _to_pose(dqs_k)

    # Segment i covers [tk[i], tk[i+1]]; the last segment also owns tk[-1].
    seg = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, tk.shape[0] - 2)
    tau = (t - tk[seg]) / step[seg]
    if mode == "screw":
        # ScLERP's dual part is a difference of the two keyframes': near a keyframe far from the
        # origin (1e13 m) it cancels to a result that is no longer rigid; projecting it back
        # (the dual-number norm) makes it one, and the last keyframe is returned as given
        out = dq.normalize(dq.sclerp(dqs_k[seg], dqs_k[seg + 1], tau))
        end = tau == 1.0
        out[end] = dqs_k[seg[end] + 1]
        return out
    # Rotation-only dual quaternions: their ScLERP is exactly the slerp of the orientations.
    r_k = np.zeros_like(dqs_k)
    r_k[:, :4] = q_k
    q = dq.sclerp(r_k[seg], r_k[seg + 1], tau)[:, :4]
    p = p_k[seg] + tau[:, None] * (p_k[seg + 1] - p_k[seg])
    return dq.from_pose(q, p)


def _to_pose(dqs_k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dq.to_pose`` with the core's argument name ``a`` renamed to ``dqs_k`` in errors."""
    try:
        return dq.to_pose(dqs_k)
    except ValueError as e:
        raise rename(e, {"a": "dqs_k{}"}) from None
