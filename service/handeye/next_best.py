"""The next best pose: which candidate robot pose, added to a calibration's samples, shrinks the
covariance of X most."""
from __future__ import annotations

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError
from dqpose.handeye.checks import poses
from dqpose.handeye.noise import transported
from dqpose.handeye.result import Calibration
from dqpose.handeye.setups import EYE_TO_HAND, reading


def next_best_pose(calibration: Calibration, base_flange, camera_target, candidates) -> np.ndarray:
    """Indices of the candidate robot poses ``T_base_flange`` (m, 8), most informative first:
    the one whose sample, added to the information of ``calibration``, shrinks the covariance of
    X most (smallest determinant of X's marginal). The candidate's camera pose is predicted from
    the calibration; its noise is the calibration's noise model (``base_flange`` and
    ``camera_target`` are the samples it was solved from, checked for shape only)."""
    poses(base_flange, "base_flange")
    poses(camera_target, "camera_target")
    cand = poses(candidates, "candidates")
    if cand.shape[0] == 0:
        raise FieldError("candidates: no candidate poses")
    c = calibration
    if c.information is None:
        raise FieldError("calibration: has no information matrix (one calibrate() returned "
                         "with a covariance is needed)")
    A = reading(cand, c.setup)
    X, Z = c.x, c.z
    C = dq.mul(dq.mul(dq.inv(X), dq.inv(A)), Z)             # A X C = Z
    m = cand.shape[0]
    I6 = np.broadcast_to(np.eye(6), (m, 6, 6))
    J = np.concatenate([lie.adjoint(dq.inv(C)), -I6], axis=2)   # at r = 0
    # The candidate's noise: the calibration's noise model (given or estimated), that of its
    # last sample when given per sample.
    SC = np.broadcast_to(np.asarray(c.camera_covariance).reshape(-1, 6, 6)[-1], (m, 6, 6))
    SA = None
    if c.robot_covariance is not None:
        SA = np.broadcast_to(np.asarray(c.robot_covariance).reshape(-1, 6, 6)[-1], (m, 6, 6))
        if c.setup == EYE_TO_HAND:
            SA = lie.cov_inverse(cand, SA)
    S = transported(X, C, SA, SC, I6)
    W = np.linalg.inv(S)
    H = c.information[None] + np.swapaxes(J, 1, 2) @ W @ J
    P = np.linalg.inv(H)
    score = np.linalg.slogdet(P[:, :6, :6])[1]
    return np.argsort(score, kind="stable")
