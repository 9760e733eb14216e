"""dqpose.handeye (service/handeye/) against the truth of the synthetic scenes (tests/_handeye.py):
exact data solved exactly, noisy data solved with a consistent covariance, every broken data set
flagged."""
from dataclasses import replace

import numpy as np
import pytest

from dqpose import dq, handeye, lie
from dqpose.errors import FieldError, Infeasible
from tests import _handeye as H

CASES = [(setup, geometry) for setup in H.SETUPS for geometry in H.GEOMETRIES]


def _close(a, b, tol):
    """Poses equal up to sign, to ``tol`` in every component."""
    a, b = np.asarray(a), np.asarray(b)
    s = np.where((a[..., :4] * b[..., :4]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    return np.max(np.abs(a - s * b)) < tol


def _nees(estimate, truth, cov):
    xi = lie.se3_log(dq.mul(dq.inv(estimate), truth))
    return float(xi @ np.linalg.solve(cov, xi))


def _reading(F, setup):
    return F if setup == "eye_in_hand" else dq.inv(F)


# ---- the scenes themselves ---------------------------------------------------------------------
@pytest.mark.parametrize("setup,geometry", CASES)
def test_scene_closes_the_loop(setup, geometry):
    s = H.scene(12, setup, geometry, camera_noise=(0.0, 0.0), seed=3)
    Z = dq.mul(dq.mul(_reading(s.base_flange, setup), s.x), s.camera_target)
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


# ---- exact data --------------------------------------------------------------------------------
@pytest.mark.parametrize("setup,geometry", CASES)
def test_exact_data_solved_exactly(setup, geometry):
    s = H.scene(15, setup, geometry, camera_noise=(0.0, 0.0), seed=5)
    c = handeye.calibrate(s.base_flange, s.camera_target, setup)
    assert c.setup == setup
    assert _close(c.x, s.x, 1e-9) and _close(c.z, s.z, 1e-9)
    assert _close(c.closed_form_x, s.x, 1e-9)
    # A X = X B for every motion pair, with the answer.
    A = _reading(s.base_flange, setup)
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


# ---- the model's Jacobian ----------------------------------------------------------------------
def test_jacobian_matches_finite_differences():
    s = H.scene(6, camera_noise=(1.0, 5.0), seed=4)
    A, C = s.base_flange, s.camera_target
    noise = handeye._Noise(None, np.broadcast_to(s.camera_covariance, (6, 6, 6)), False)
    use = np.ones(6, bool)
    _, r, J, _ = handeye._linearise(A, C, lie.adjoint(dq.inv(C)), s.x, s.z, noise, use)
    h = 1e-6
    for k in range(12):
        d = np.zeros(12)
        d[k] = h
        rp = handeye._evaluate(A, C, dq.mul(s.x, lie.se3_exp(d[:6])),
                               dq.mul(s.z, lie.se3_exp(d[6:])))[1]
        rm = handeye._evaluate(A, C, dq.mul(s.x, lie.se3_exp(-d[:6])),
                               dq.mul(s.z, lie.se3_exp(-d[6:])))[1]
        np.testing.assert_allclose((rp - rm) / (2 * h), J[:, :, k], atol=1e-7)


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


# ---- checks ------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", H.BROKEN)
def test_every_broken_data_set_is_flagged(kind):
    b = H.broken(kind, seed=1)
    try:
        c = handeye.calibrate(b.base_flange, b.camera_target, b.setup)
    except Infeasible as e:
        assert not isinstance(e, FieldError)
        assert str(e).split(":")[0] in ("base_flange", "camera_target",
                                        "base_flange, camera_target")
        return
    assert c.warnings, kind
    named = " ".join(c.warnings)
    for k in b.bad:
        assert str(k) in named
    if kind in ("outliers", "marker_flips"):
        assert sorted(r.index for r in c.rejected) == list(b.bad)
        assert H.pose_error(c.x, b.scene.x)[0] < 0.5
    if kind == "marker_flips":
        assert all("marker flip" in r.reason for r in c.rejected)
    if kind == "board_scale":
        assert any("scaled by" in w for w in c.warnings)
        assert abs(c.camera_scale[0] * 1.02 - 1.0) < 5 * c.camera_scale[1]
    if kind == "inverted_both":
        assert any("look both inverted" in w for w in c.warnings)


@pytest.mark.parametrize("setup", H.SETUPS)
@pytest.mark.parametrize("kind", ["inverted_both", "board_scale"])
def test_readings_that_fit_as_well_are_answered_right(kind, setup):
    """Both poses inverted fits exactly as well as the truth, a 2 % board scale nearly so; the
    answer is the right reading's, within its covariance, and the warning says what was done."""
    nees = []
    for seed in range(10):
        b = H.broken(kind, setup=setup, seed=seed)
        c = handeye.calibrate(b.base_flange, b.camera_target, b.setup)
        assert any("Solved as inverted" in w or "Solved with camera_target's translations" in w
                   for w in c.warnings)
        deg, mm = H.pose_error(c.x, b.scene.x)
        assert deg < 0.3 and mm < 3.0, (deg, mm)
        nees.append(_nees(c.x, b.scene.x, c.covariance_x))
    assert np.mean(nees) < 12.0, nees     # χ²₆: 6 on average; the wrong reading is ~1e4


def test_wrong_board_size_at_corner_level():
    """The board's square size 2 % off in the corners too (PnP then scales every translation):
    the scale is refined with the corners, and X is right within its covariance."""
    nees = []
    for seed in range(10):
        s = H.scene(15, camera_noise=(0.1, 0.5), seed=seed)
        C = s.camera_target.copy()
        C[:, 4:] *= 1.02
        cs = [(b * 1.02, u, K) for b, u, K in H.corners(s, 0.2, seed=seed)]
        c = handeye.calibrate(s.base_flange, C, corners=cs)
        assert any("scaled by" in w for w in c.warnings)
        assert abs(c.camera_scale[0] * 1.02 - 1.0) < 5 * c.camera_scale[1]
        assert H.pose_error(c.x, s.x)[1] < 0.5
        nees.append(_nees(c.x, s.x, c.covariance_x))
    assert np.mean(nees) < 12.0, nees     # 6 on average; ~160–600 with the scale taken as exact


def test_both_inverted_refused_when_the_data_cannot_tell():
    """Both inverted with a board frame whose z points out of the board: the camera then lies at
    positive z in the target's frame, so the inverted poses put the target in front too, and
    only the mount says something is wrong, not which reading is right."""
    b = H.broken("inverted_both", seed=4)
    out = dq.mul(b.scene.camera_target, H.rotation([np.pi, 0.0, 0.0]))   # z out of the board
    with pytest.raises(Infeasible, match="The data cannot tell which"):
        handeye.calibrate(b.base_flange, dq.inv(out))
    c = handeye.calibrate(b.scene.base_flange, out)      # as given, the same board is fine
    assert H.pose_error(c.x, b.scene.x)[0] < 0.3 and not c.warnings


@pytest.mark.parametrize("kind,says", [
    ("two_poses", "at least 3"), ("pure_translation", "pure translation"),
    ("parallel_axes", "parallel"), ("time_shift", "do not correspond"),
    ("millimetres", "millimetres"), ("inverted_camera", "T_target_camera"),
    ("inverted_robot", "T_flange_base"), ("swapped_setup", "swapped")])
def test_unusable_data_says_why(kind, says):
    b = H.broken(kind, seed=2)
    with pytest.raises(Infeasible, match=says):
        handeye.calibrate(b.base_flange, b.camera_target, b.setup)
    with pytest.raises(Infeasible, match=says):
        handeye.check(b.base_flange, b.camera_target, b.setup)


def test_reading_that_fits_is_named_with_its_residuals():
    b = H.broken("swapped_setup", seed=3)
    with pytest.raises(Infeasible) as e:
        handeye.calibrate(b.base_flange, b.camera_target, b.setup)
    assert "the data fit eye_in_hand far better than eye_to_hand" in str(e.value)
    c = handeye.calibrate(b.base_flange, b.camera_target, b.scene.setup)
    assert c.readings[0][0] == "eye_in_hand"
    assert all(c.readings[0][1] < r[1] / 10 for r in c.readings[1:])


def test_outliers_kept_and_named_without_robust_mode():
    b = H.broken("outliers", seed=4)
    c = handeye.calibrate(b.base_flange, b.camera_target, robust=False)
    assert c.rejected == () and c.inliers.all()
    w = [w for w in c.warnings if "outliers (kept" in w]
    assert w and all(str(k) in w[0] for k in b.bad)


def test_check_of_healthy_data_is_silent():
    s = H.scene(20, seed=6)
    assert handeye.check(s.base_flange, s.camera_target) == ()


def test_duplicates_are_counted_once():
    b = H.broken("duplicates", seed=5)
    c = handeye.calibrate(b.base_flange, b.camera_target)
    assert not c.inliers[list(b.bad)].any()
    first = len(b.base_flange) - len(b.bad)      # the copies were appended after these
    d = handeye.calibrate(b.base_flange[:first], b.camera_target[:first])
    assert _close(c.x, d.x, 1e-9)


def test_random_poses_never_give_nan():
    rng = np.random.default_rng(0)
    for _seed in range(5):
        q = rng.normal(size=(2, 10, 4))
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        F, C = dq.from_pose(q, rng.normal(size=(2, 10, 3)))
        try:
            c = handeye.calibrate(F, C)
        except Infeasible:
            continue
        for v in (c.x, c.z, c.covariance, c.residuals, c.leave_one_out):
            assert np.all(np.isfinite(v))
        assert c.warnings


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
