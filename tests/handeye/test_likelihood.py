"""dqpose.handeye.likelihood: the model's Jacobian against finite differences."""
import numpy as np

from dqpose import dq, lie
from dqpose.handeye.likelihood import evaluate, linearise
from dqpose.handeye.noise import Noise
from tests import _handeye as H


# ---- the model's Jacobian ----------------------------------------------------------------------
def test_jacobian_matches_finite_differences():
    s = H.scene(6, camera_noise=(1.0, 5.0), seed=4)
    A, C = s.base_flange, s.camera_target
    noise = Noise(None, np.broadcast_to(s.camera_covariance, (6, 6, 6)), False)
    use = np.ones(6, bool)
    _, r, J, _ = linearise(A, C, lie.adjoint(dq.inv(C)), s.x, s.z, noise, use)
    h = 1e-6
    for k in range(12):
        d = np.zeros(12)
        d[k] = h
        rp = evaluate(A, C, dq.mul(s.x, lie.se3_exp(d[:6])),
                               dq.mul(s.z, lie.se3_exp(d[6:])))[1]
        rm = evaluate(A, C, dq.mul(s.x, lie.se3_exp(-d[:6])),
                               dq.mul(s.z, lie.se3_exp(-d[6:])))[1]
        np.testing.assert_allclose((rp - rm) / (2 * h), J[:, :, k], atol=1e-7)
