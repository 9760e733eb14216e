"""dqpose.handeye.next_best: the informative candidate is preferred."""
import numpy as np

from dqpose import dq, handeye
from tests import _handeye as H


# ---- next best pose ----------------------------------------------------------------------------
def test_next_best_pose_prefers_the_informative_candidate():
    """Adding the top-ranked candidate shrinks X's covariance more than adding the last one."""
    s = H.scene(8, camera_noise=(0.2, 1.0), seed=11)
    more = H.scene(30, camera_noise=(0.2, 1.0), seed=12)
    # Candidates: poses of another scene of the same mount, and copies of poses already taken.
    bf = np.concatenate([s.true_base_flange[:3], more.true_base_flange[:8]])
    x_truth, z_truth = s.x, s.z
    cand = dq.mul(dq.mul(z_truth, dq.inv(handeye.view_at(bf, x_truth, z_truth, "eye_in_hand"))),
                  dq.inv(x_truth))   # T_base_flange for views of the same board
    c = handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=s.camera_covariance)
    order = handeye.next_best_pose(c, s.base_flange, s.camera_target, cand)
    assert sorted(order) == list(range(len(cand)))

    def det_with(k):
        F = np.concatenate([s.base_flange, cand[k:k + 1]])
        C = np.concatenate([s.camera_target,
                            handeye.view_at(cand[k:k + 1], c.x, c.z, "eye_in_hand")])
        return np.linalg.slogdet(handeye.calibrate(F, C, camera_covariance=s.camera_covariance)
                                 .covariance_x)[1]

    assert det_with(order[0]) < det_with(order[-1])
    assert order[-1] < 3 or det_with(order[-1]) >= max(det_with(k) for k in range(3)) - 1e-9
