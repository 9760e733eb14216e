"""dqpose.handeye.corners: the corner-level fit (exact, consistent, robot noise, focal length,
malformed corners, view_at)."""
import numpy as np
import pytest

from dqpose import dq, handeye, lie
from dqpose.errors import FieldError
from tests import _handeye as H
from tests.handeye._cases import _close, _nees


# ---- corner level ------------------------------------------------------------------------------
def test_exact_corners_solved_exactly():
    s = H.scene(10, seed=13)
    c = handeye.calibrate(s.base_flange, s.camera_target, corners=H.corners(s, 0.0))
    assert _close(c.x, s.x, 1e-9) and _close(c.z, s.z, 1e-9)
    assert np.all(c.reprojection < 1e-6)


@pytest.mark.parametrize("setup", H.SETUPS)
def test_corner_level_is_consistent_and_beats_poses(setup):
    nees, pose, corner = [], [], []
    for seed in range(60):
        s = H.scene(15, setup, camera_noise=(0.1, 0.5), seed=seed)
        a = handeye.calibrate(s.base_flange, s.camera_target, setup)
        c = handeye.calibrate(s.base_flange, s.camera_target, setup,
                              corners=H.corners(s, 0.2, seed=seed))
        nees.append(_nees(c.x, s.x, c.covariance_x))
        pose.append(H.pose_error(a.x, s.x))
        corner.append(H.pose_error(c.x, s.x))
        assert c.pixel_sigma == pytest.approx(0.2, rel=0.25)
    assert 5.0 <= np.mean(nees) <= 7.0, np.mean(nees)
    assert np.all(np.median(corner, axis=0) < np.median(pose, axis=0))


def test_robot_noise_at_corner_level():
    """Robot noise given or estimated keeps the covariance honest; the robot taken as exact
    (only the camera's noise given) does not."""
    given, estimated, exact = [], [], []
    for seed in range(30):
        s = H.scene(15, camera_noise=(0.1, 0.5), robot_noise=(0.02, 0.1), seed=seed)
        cs = H.corners(s, 0.2, seed=seed)
        a = handeye.calibrate(s.base_flange, s.camera_target, corners=cs,
                              camera_covariance=s.camera_covariance,
                              robot_covariance=s.robot_covariance)
        b = handeye.calibrate(s.base_flange, s.camera_target, corners=cs)
        c = handeye.calibrate(s.base_flange, s.camera_target, corners=cs,
                              camera_covariance=s.camera_covariance)
        given.append(_nees(a.x, s.x, a.covariance_x))
        estimated.append(_nees(b.x, s.x, b.covariance_x))
        exact.append(_nees(c.x, s.x, c.covariance_x))
    assert 4.0 <= np.mean(given) <= 8.0
    assert 4.0 <= np.mean(estimated) <= 8.0
    assert np.mean(exact) > 3 * np.mean(given)


def test_focal_length_refined():
    s = H.scene(15, seed=14)
    wrong = H.CAMERA_MATRIX @ np.diag([1.01, 1.01, 1.0])     # focal lengths 1 % long
    cs = [(b, u, wrong) for b, u, _ in H.corners(s, 0.1, seed=14)]
    c = handeye.calibrate(s.base_flange, s.camera_target, corners=cs, refine_focal=True)
    assert abs(c.focal_scale * 1.01 - 1.0) < 4 * c.focal_sigma
    d = handeye.calibrate(s.base_flange, s.camera_target, corners=cs)
    assert H.pose_error(c.x, s.x)[1] < H.pose_error(d.x, s.x)[1] / 5


def test_malformed_corners_named():
    s = H.scene(5, seed=15)
    cs = H.corners(s)
    F, C = s.base_flange, s.camera_target
    with pytest.raises(FieldError, match=r"^corners: 4 views for 5"):
        handeye.calibrate(F, C, corners=cs[:4])
    bad = list(cs)
    bad[2] = (cs[2][0], cs[2][1][:-1], cs[2][2])
    with pytest.raises(FieldError, match=r"^corners\[2\]\.image_points: "):
        handeye.calibrate(F, C, corners=bad)
    bad[2] = (cs[2][0], cs[2][1], -cs[2][2])
    with pytest.raises(FieldError, match=r"^corners\[2\]\.K: "):
        handeye.calibrate(F, C, corners=bad)
    bad[2] = (cs[2][0][:3], cs[2][1][:3], cs[2][2])
    with pytest.raises(FieldError, match=r"^corners\[2\]\.board_points: 3 corners"):
        handeye.calibrate(F, C, corners=bad)
    with pytest.raises(FieldError, match=r"^pixel_sigma: "):
        handeye.calibrate(F, C, corners=cs, pixel_sigma=0.0)


@pytest.mark.parametrize("setup", handeye.SETUPS)
def test_view_at_is_the_calibration_identity_and_flange_for_its_inverse(setup):
    s = H.scene(6, setup, camera_noise=(0.0, 0.0), seed=3)
    view = handeye.view_at(s.base_flange, s.x, s.z, setup)
    # eye-in-hand A·X·C = Z with A = base_flange; eye-to-hand with A = base_flange⁻¹
    A = s.base_flange if setup == "eye_in_hand" else dq.inv(s.base_flange)
    for a, c in zip(A, view):
        assert np.abs(lie.se3_log(dq.mul(dq.inv(s.z), dq.mul(dq.mul(a, s.x), c)))).max() < 1e-12
    back = handeye.flange_for(view, s.x, s.z, setup)
    assert np.abs(lie.se3_log(dq.mul(dq.inv(s.base_flange), back))).max() < 1e-12
