"""The camera's scale (service/handeye/scale.py): no rescale without the evidence, and a real
scale error solved at the joint optimum of the scale, the inliers and the noise."""
import numpy as np
import pytest

from dqpose import dq, handeye
from tests import _handeye as H
from tests.bench.fusion_scenes import nees
from tests.handeye._cases import depth_noisy, monocular


def _rescaled(cal) -> bool:
    return any("scaled by" in w for w in cal.warnings)


def test_depth_heavy_noise_is_no_scale_error():
    """90 views with KinHEC's camera noise c5 (1.15° and 12, 12, 40 mm per axis of the camera's
    frame), no scale error, noise estimated. Without the Jacobian of the scaling in the
    likelihood, shrinking the translations shrank their noise and read as a better fit: 8 of 10
    seeds were "corrected" to a scale of 0.78–0.82, 70–110 mm wrong. Now none is rescaled, and
    the scale reported is 1 within its σ."""
    for seed in range(10):
        s, C = depth_noisy(90, seed)
        cal = handeye.calibrate(s.base_flange, C)
        assert not _rescaled(cal), (seed, cal.camera_scale)
        lam, sigma = cal.camera_scale
        assert abs(lam - 1.0) < 4.0 * sigma, (seed, lam, sigma)
        assert H.pose_error(cal.x, s.x)[1] < 20.0, seed


@pytest.mark.parametrize("given", [True, False], ids=["noise given", "noise estimated"])
@pytest.mark.parametrize("true_scale", [0.5, 2.0])
def test_a_monocular_scale_is_solved_at_the_joint_optimum(given, true_scale):
    """A monocular camera's translations at half or twice the robot's scale, 30 views. One Newton
    step from 1 is far from the scale's optimum (3.03 where 2 is right on KinHEC); the re-solve
    repeats until the scale it finds on its own data is 1 within a tenth of its σ. The answer is
    then as accurate as the covariance says, the scale within 3 σ, and no genuine sample is
    rejected for the scale's sake."""
    for seed in range(6):
        s = H.scene(30, "eye_in_hand", "wrist", camera_noise=(0.1, 0.5), seed=seed)
        C = s.camera_target.copy()
        C[:, 4:] *= true_scale
        kw = {}
        if given:
            D = np.diag([1.0] * 3 + [true_scale] * 3)
            kw = {"camera_covariance": D @ s.camera_covariance @ D}
        cal = handeye.calibrate(s.base_flange, dq.normalize(C), **kw)
        assert _rescaled(cal), seed
        lam, sigma = cal.camera_scale
        assert abs(lam * true_scale - 1.0) < 3.0 * sigma * true_scale, (seed, lam, sigma)
        assert nees(cal.x, cal.covariance_x, s.x) < 25.0, seed
        assert len(cal.rejected) <= 1, seed


@pytest.mark.parametrize("true_scale", [0.5, 2.0])
def test_a_monocular_camera_starting_near_the_base_is_solved_not_refused(true_scale):
    """KinHEC's monocular sequences at 50 a setting: the camera's odometry frame (its first pose)
    0.13–0.33 m from the base. The fit before the rescale puts X and Z at the wrong distances,
    and read there, both poses inverted looked as plausible a mount as the data given: 2 of 100
    sequences were refused ("the data cannot tell which"), here 3 of 6 seeds at half scale. The
    scale is now found before the mount's plausibility is read, at the scale found."""
    for seed in range(6):
        s, F, C = monocular(30, seed, true_scale)
        cal = handeye.calibrate(F, C)
        assert _rescaled(cal), seed
        assert H.pose_error(cal.x, s.x)[1] < 5.0, seed
        assert nees(cal.x, cal.covariance_x, s.x) < 25.0, seed
