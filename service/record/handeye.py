"""What a recorded hand-eye calibration (a ``dqpose.v1.HandEye/Calibrate`` call: its request's
views and its answer) shows in Foxglove, in the robot's base frame (``world`` standing for it, as
for plans):

- ``/tf``: ``handeye/flange`` (the last view's flange), and X and Z where the setup puts them:
  eye-in-hand ``world`` -> ``handeye/z`` (T_base_target) and ``handeye/flange`` -> ``handeye/x``
  (T_flange_camera); eye-to-hand ``world`` -> ``handeye/x`` (T_base_camera) and
  ``handeye/flange`` -> ``handeye/z`` (T_flange_target);
- ``/handeye/ellipsoids``: X's and Z's position ellipsoids (3 sigma) in their own frames, drawn
  as a fused pose's (:func:`dqpose.record.views.ellipsoid`);
- ``/handeye/flanges``: the views' flange poses; ``/handeye/targets``: where each view puts the
  target in the base frame through the solution (eye-in-hand ``flange_i X view_i``, eye-to-hand
  ``X view_i``): they coincide with Z (with ``flange_i Z``) up to the view's residual;
- ``/handeye/residuals``: per view (JSON) its residual's rotation (rad) and translation (m), its
  NIS, whether it was an inlier, and how far X moves when it is left out.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq

TF = ("handeye/flange", "handeye/x", "handeye/z")
ELLIPSOIDS_TOPIC = "/handeye/ellipsoids"
FLANGES_TOPIC = "/handeye/flanges"
TARGETS_TOPIC = "/handeye/targets"
RESIDUALS_TOPIC = "/handeye/residuals"
RESIDUAL_FIELDS = {"view": "integer", "rotation": "number", "translation": "number",
                   "nis": "number", "inlier": "boolean", "leave_one_out_rotation": "number",
                   "leave_one_out_translation": "number"}
#: CalibrateRequest.setup's value for eye-in-hand (handeye.proto)
EYE_IN_HAND = 1


def _dq(pose) -> np.ndarray:
    p, o = pose.position, pose.orientation
    return dq.from_pose([o.w, o.x, o.y, o.z], [p.x, p.y, p.z])


def _tq(d) -> tuple[tuple, tuple]:
    q, t = dq.to_pose(d)
    return tuple(t.tolist()), tuple(q.tolist())


def transforms(request, answer) -> list[tuple[str, str, tuple, tuple]]:
    """``/tf``'s ``(parent, child, t, q)`` of a calibration (module docstring)."""
    flange, x, z = TF
    last = _dq(request.pairs[-1].base_to_flange)
    base_side, flange_side = ((z, answer.z), (x, answer.x)) \
        if request.setup == EYE_IN_HAND else ((x, answer.x), (z, answer.z))
    return [("world", flange, *_tq(last)),
            ("world", base_side[0], *_tq(_dq(base_side[1]))),
            (flange, flange_side[0], *_tq(_dq(flange_side[1])))]


def paths(request, answer) -> tuple[np.ndarray, np.ndarray]:
    """``(flanges, targets)``: the views' flange poses and the target each view puts in the base
    frame through the solution, dual quaternions ``(n, 8)``."""
    flanges = np.array([_dq(p.base_to_flange) for p in request.pairs])
    views = np.array([_dq(p.camera_to_target) for p in request.pairs])
    x = _dq(answer.x)
    if request.setup == EYE_IN_HAND:
        targets = dq.mul(dq.mul(flanges, x), views)
    else:
        targets = dq.mul(x, views)
    return flanges, targets


def residuals(answer, n: int) -> list[dict]:
    """Per view (of ``n``) its JSON residuals (module docstring)."""
    res = np.asarray(answer.residuals, dtype=np.float64).reshape(-1, 2)
    loo = np.asarray(answer.leave_one_out, dtype=np.float64).reshape(-1, 2)
    out = []
    for i in range(min(n, len(res))):
        d = {"view": i, "rotation": float(res[i, 0]), "translation": float(res[i, 1])}
        if i < len(answer.nis):
            d["nis"] = answer.nis[i]
        if i < len(answer.inliers):
            d["inlier"] = answer.inliers[i]
        if i < len(loo):
            d["leave_one_out_rotation"], d["leave_one_out_translation"] = map(float, loo[i])
        out.append(d)
    return out
