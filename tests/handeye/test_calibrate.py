"""dqpose.handeye.calibrate against the truth of the synthetic scenes: exact data solved exactly,
noisy data solved with a consistent covariance, better than the closed form, leave-one-out."""
import numpy as np
import pytest

from dqpose import dq, handeye
from dqpose.handeye.setups import reading
from tests import _handeye as H
from tests.handeye._cases import CASES, _close, _nees


# ---- exact data --------------------------------------------------------------------------------
@pytest.mark.parametrize("setup,geometry", CASES)
def test_exact_data_solved_exactly(setup, geometry):
    s = H.scene(15, setup, geometry, camera_noise=(0.0, 0.0), seed=5)
    c = handeye.calibrate(s.base_flange, s.camera_target, setup)
    assert c.setup == setup
    assert _close(c.x, s.x, 1e-9) and _close(c.z, s.z, 1e-9)
    assert _close(c.closed_form_x, s.x, 1e-9)
    # A X = X B for every motion pair, with the answer.
    A = reading(s.base_flange, setup)
    i, j = np.triu_indices(15, 1)
    lhs = dq.mul(dq.mul(dq.inv(A[j]), A[i]), c.x)
    rhs = dq.mul(c.x, dq.mul(s.camera_target[j], dq.inv(s.camera_target[i])))
    assert _close(lhs, rhs, 1e-9)
    assert np.all(c.residuals < 1e-9) and c.warnings == () and c.rejected == ()


def test_eye_to_hand_is_eye_in_hand_on_inverted_flange_poses():
    """With the robot exact (the noise of base_flange and of its inverse differ otherwise)."""
    s = H.scene(15, "eye_to_hand", seed=8)
    S = s.camera_covariance
    a = handeye.calibrate(s.base_flange, s.camera_target, "eye_to_hand", camera_covariance=S)
    b = handeye.calibrate(dq.inv(s.base_flange), s.camera_target, "eye_in_hand",
                          camera_covariance=S)
    assert _close(a.x, b.x, 1e-9) and _close(a.z, b.z, 1e-9)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-6, atol=1e-15)


# ---- noisy data: accuracy and consistency ------------------------------------------------------
def _trials(count, n=20, setup="eye_in_hand", geometry="wrist", camera=(0.1, 0.5), robot=None,
            given=True, seed0=0):
    out = []
    for seed in range(seed0, seed0 + count):
        s = H.scene(n, setup, geometry, camera_noise=camera, robot_noise=robot, seed=seed)
        kw = dict(camera_covariance=s.camera_covariance, robot_covariance=s.robot_covariance) \
            if given else {}
        out.append((s, handeye.calibrate(s.base_flange, s.camera_target, setup, **kw)))
    return out


@pytest.mark.parametrize("n,geometry,robot,given", [
    (20, "wrist", (0.05, 0.3), True), (20, "wrist", None, False),
    (10, "wrist", (0.05, 0.2), False), (10, "opencv", (0.05, 0.2), False)],
    ids=["robot-and-camera-noise-given", "noise-estimated", "noise-estimated-10-poses",
         "noise-estimated-10-poses-opencv-geometry"])
def test_covariance_of_x_is_consistent(n, geometry, robot, given):
    """Mean NEES of X over 200 seeded trials: 6 for a consistent 6-DoF estimate. With the noise
    estimated from 10 poses only with its uncertainty propagated (Kenward–Roger; 7.1 and 9.3
    without)."""
    runs = _trials(200, n=n, geometry=geometry, robot=robot, given=given)
    nees = [_nees(c.x, s.x, c.covariance_x) for s, c in runs]
    nees_z = [_nees(c.z, s.z, c.covariance_z) for s, c in runs]
    assert 5.0 <= np.mean(nees) <= 7.0, np.mean(nees)
    assert 5.0 <= np.mean(nees_z) <= 7.0, np.mean(nees_z)


def test_refinement_beats_the_closed_form():
    runs = _trials(30, camera=(0.5, 2.0), robot=(0.1, 0.5))
    ref = np.array([H.pose_error(c.x, s.x) for s, c in runs])
    cf = np.array([H.pose_error(c.closed_form_x, s.x) for s, c in runs])
    assert np.median(ref[:, 0]) < np.median(cf[:, 0])
    assert np.median(ref[:, 1]) < np.median(cf[:, 1])


def test_modelling_robot_noise_helps():
    """Robot noise given beats robot poses taken as exact (camera noise alone)."""
    both, cam_only = [], []
    for seed in range(30):
        s = H.scene(20, camera_noise=(0.05, 0.2), robot_noise=(0.1, 0.5), seed=seed)
        a = handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=s.camera_covariance,
                              robot_covariance=s.robot_covariance)
        b = handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=s.camera_covariance)
        both.append(_nees(a.x, s.x, a.covariance_x))
        cam_only.append(_nees(b.x, s.x, b.covariance_x))
    # Ignoring the robot's noise claims far more than it knows.
    assert np.mean(cam_only) > 3 * np.mean(both)


@pytest.mark.parametrize("setup,geometry", CASES)
def test_noisy_answer_is_within_its_covariance(setup, geometry):
    for s, c in _trials(5, setup=setup, geometry=geometry, given=False, seed0=100):
        assert c.setup == setup
        assert _nees(c.x, s.x, c.covariance_x) < 30.0   # χ²₆ beyond 0.99999 otherwise
        assert np.all(np.isfinite(c.covariance)) and np.all(np.linalg.eigvalsh(c.covariance) > 0)
        assert c.residuals.shape == (20, 2) and c.leave_one_out.shape == (20, 2)


def test_leave_one_out_predicts_the_resolve():
    s = H.scene(12, camera_noise=(0.3, 1.5), seed=9)
    C0 = s.camera_covariance
    c = handeye.calibrate(s.base_flange, s.camera_target, camera_covariance=C0)
    for k in (0, 5, 11):
        keep = np.arange(12) != k
        d = handeye.calibrate(s.base_flange[keep], s.camera_target[keep], camera_covariance=C0)
        m = dq.mul(dq.inv(c.x), d.x)
        moved = (2 * np.arctan2(np.linalg.norm(m[1:4]), abs(m[0])),
                 np.linalg.norm(dq.to_pose(d.x)[1] - dq.to_pose(c.x)[1]))
        np.testing.assert_allclose(c.leave_one_out[k], moved, rtol=0.1, atol=1e-6)


def test_closed_form_agreement_reported():
    s, c = _trials(1, camera=(0.3, 1.0), given=False)[0]
    rad, m, nees = c.agreement
    expect = H.pose_error(c.closed_form_x, c.x)
    assert rad == pytest.approx(np.radians(expect[0]), rel=1e-6)
    assert m == pytest.approx(expect[1] * 1e-3, rel=1e-6)
    assert nees == pytest.approx(_nees(c.x, c.closed_form_x, c.covariance_x), rel=1e-6)
