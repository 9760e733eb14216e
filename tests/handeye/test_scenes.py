"""The synthetic hand-eye scenes themselves (tests/_handeye.py): the loop closes, the noise has the
asked spread, the wrist views are at working distance."""
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.handeye.setups import reading
from tests import _handeye as H
from tests.handeye._cases import CASES, _close


# ---- the scenes themselves ---------------------------------------------------------------------
@pytest.mark.parametrize("setup,geometry", CASES)
def test_scene_closes_the_loop(setup, geometry):
    s = H.scene(12, setup, geometry, camera_noise=(0.0, 0.0), seed=3)
    Z = dq.mul(dq.mul(reading(s.base_flange, setup), s.x), s.camera_target)
    assert all(_close(z, s.z, 1e-12) for z in Z)


def test_scene_noise_has_the_asked_spread():
    s = H.scene(4000, camera_noise=(0.2, 1.0), robot_noise=(0.05, 0.3), seed=1)
    cam = lie.se3_log(dq.mul(dq.inv(s.true_camera_target), s.camera_target))
    rob = lie.se3_log(dq.mul(dq.inv(s.true_base_flange), s.base_flange))
    np.testing.assert_allclose(cam.std(axis=0), np.sqrt(np.diag(s.camera_covariance)), rtol=0.05)
    np.testing.assert_allclose(rob.std(axis=0), np.sqrt(np.diag(s.robot_covariance)), rtol=0.05)


def test_wrist_views_are_at_working_distance():
    s = H.scene(50, seed=2, camera_noise=(0.0, 0.0))
    d = np.linalg.norm(dq.to_pose(s.camera_target)[1], axis=1)
    assert np.all((d > 0.25) & (d < 0.8))
