"""dqpose.handeye.readings: malformed input named by its field; a mount near the base is not
taken for inverted poses; depth-heavy camera noise is not a scale error."""
from dataclasses import replace

import numpy as np
import pytest

from dqpose import dq, handeye
from dqpose.errors import FieldError
from tests import _handeye as H


# ---- malformed input ---------------------------------------------------------------------------
def test_malformed_input_named():
    s = H.scene(5, seed=7)
    F, C = s.base_flange.copy(), s.camera_target.copy()
    bad = F.copy()
    bad[3, 2] = np.nan
    with pytest.raises(FieldError, match=r"^base_flange\[3\]: .*NaN"):
        handeye.calibrate(bad, C)
    bad = C.copy()
    bad[2, :4] *= 1.5
    with pytest.raises(FieldError, match=r"^camera_target\[2\]: .*unit"):
        handeye.calibrate(F, bad)
    with pytest.raises(FieldError, match=r"^camera_target: 4 poses for 5"):
        handeye.calibrate(F, C[:4])
    with pytest.raises(FieldError, match=r"^base_flange: expected shape"):
        handeye.calibrate(F[:, :7], C)
    with pytest.raises(FieldError, match=r"^setup: "):
        handeye.calibrate(F, C, "eye_on_hand")
    with pytest.raises(FieldError, match=r"^camera_covariance: not symmetric"):
        handeye.calibrate(F, C, camera_covariance=np.triu(np.ones((6, 6))))
    with pytest.raises(FieldError, match=r"^camera_covariance: expected shape"):
        handeye.calibrate(F, C, camera_covariance=np.eye(5))
    with pytest.raises(FieldError, match=r"^camera_covariance: needed"):
        handeye.calibrate(F, C, robot_covariance=np.eye(6))
    with pytest.raises(FieldError, match=r"^candidates: "):
        c = handeye.calibrate(F, C)
        handeye.next_best_pose(c, F, C, np.zeros((0, 8)))
    # a Calibration without its information matrix (as a client may build one)
    with pytest.raises(FieldError, match=r"^calibration: "):
        handeye.next_best_pose(replace(c, information=None), F, C, F[:1])


def test_target_near_the_base_is_no_warning():
    """A noise-free scene with the board 0.21 m from the robot base is a real mount: the
    inverted reading is implausible too (its fixed part would be the camera, ~0.1 m from the
    base), so there is nothing to warn about."""
    s = H.scene(12, "eye_in_hand", "wrist", camera_noise=(0.0, 0.0), seed=3)
    t = dq.to_pose(s.z)[1]
    shift = H.pose([0.0, 0.0, 0.0], 0.21 * t / np.linalg.norm(t) - t)
    F = dq.normalize(dq.mul(shift, s.base_flange))            # the whole world moved: Z = shift Z
    cal = handeye.calibrate(F, s.camera_target)
    assert abs(np.linalg.norm(dq.to_pose(cal.z)[1]) - 0.21) < 1e-6
    assert cal.warnings == ()


def _depth_noisy(seed: int, n: int):
    """A healthy scene (0.5° rotation noise) whose camera is 3× noisier along its line of sight
    than across it (3 mm across, 9 mm in depth: a detector's usual shape, KinHEC's camera):
    translation noise added in the camera's frame, which the estimated noise model (isotropic)
    does not describe."""
    s = H.scene(n, "eye_in_hand", "wrist", camera_noise=(0.5, 0.0), seed=seed)
    rng = np.random.default_rng(77 + seed)
    d = rng.normal(size=(n, 3)) * np.array([3e-3, 3e-3, 9e-3])
    shift = np.stack([H.pose([0.0, 0.0, 0.0], v) for v in d])
    return s, dq.normalize(dq.mul(shift, s.camera_target))


def test_depth_noise_is_no_scale_error():
    """True scale 1, camera noise 3× larger in depth: the scale's σ is the sandwich's when the
    residuals scatter more than the noise model says, so the scale stays within its σ (the model
    σ alone put it 1.5 σ off on average, and rescaled seeds 58 and 60 to 0.94–0.95, 20–24 mm
    wrong) and nothing is rescaled over 40 seeds (the test's nominal rate, 5 σ, is < 1e-6)."""
    z = []
    for seed in range(40, 80):
        s, C = _depth_noisy(seed, 40)
        cal = handeye.calibrate(s.base_flange, C)
        assert not any("scaled by" in w for w in cal.warnings), (seed, cal.camera_scale)
        lam, sigma = cal.camera_scale
        z.append((lam - 1.0) / sigma)
    assert np.std(z) < 1.25


@pytest.mark.parametrize("given", [False, True], ids=["estimated", "given"])
def test_one_percent_scale_is_found_with_its_sigma(given):
    """A camera 1 % short (translations × 0.99) over 100 poses: detected, solved at 1 / 0.99
    within 4 σ of it, X as accurate as on the true scale."""
    s = H.scene(100, "eye_in_hand", "wrist", camera_noise=(0.1, 0.5), seed=5)
    C = s.camera_target.copy()
    C[:, 4:] *= 0.99                   # the dual part carries the translation linearly
    D = np.diag([1.0] * 3 + [0.99] * 3)
    kw = {"camera_covariance": D @ s.camera_covariance @ D} if given else {}
    cal = handeye.calibrate(s.base_flange, C, **kw)
    lam, sigma = cal.camera_scale
    assert any("scaled by" in w for w in cal.warnings)
    assert 0.0 < sigma < 0.002 and abs(lam * 0.99 - 1.0) < 4.0 * sigma * 0.99
    deg, mm = H.pose_error(cal.x, s.x)
    assert deg < 0.1 and mm < 1.0
