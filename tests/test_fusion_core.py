"""The C fusion core (service/csrc/fusion.c, bound as ``_dqcore.fuse``) against the NumPy reference
(tests/fusion_reference.py) on random and hard problems, its batch axis, and its errors."""
import numpy as np
import pytest

from service import _dqcore as _c
from service import dq, lie

import fusion_reference as ref
from test_fusion import measure, random_cov, random_pose

FIELDS = ("mean", "covariance", "residuals", "distances", "nis", "tested", "status",
          "iterations", "chi2")


def core(Z, S, inlier=None, tol=1e-12, max_iter=100):
    return dict(zip(FIELDS, _c.fuse(Z, S, inlier, tol, max_iter)))


def assert_agrees(Z, S, inlier=None, tol=1e-12, max_iter=100, rel=1e-12):
    a = ref.fit(Z, S, inlier, tol, max_iter)
    b = core(Z, S, inlier, tol, max_iter)
    assert int(b["status"]) == a.status and int(b["iterations"]) == a.iterations
    assert np.array_equal(b["tested"], a.tested)
    assert np.abs(lie.se3_log(dq.mul(dq.conj(a.mean), b["mean"]))).max() < 1e-13
    scale = np.abs(a.covariance).max()
    assert np.abs(b["covariance"] - a.covariance).max() <= rel * scale
    assert np.array_equal(b["covariance"], b["covariance"].T)
    assert np.abs(b["residuals"] - a.residuals).max() < 1e-13
    # squared distances are a quadratic form in residuals of ~1e-3 with weights of ~1e6: an
    # absolute residual difference of 1e-16 is 1e-13 of them; relative to the largest
    big = max(1.0, a.distances.max())
    assert np.abs(b["distances"] - a.distances).max() <= 1e3 * rel * big
    assert np.abs(b["nis"] - a.nis).max() <= 1e4 * rel * max(1.0, a.nis.max())
    assert b["chi2"] == pytest.approx(a.chi2, rel=1e3 * rel, abs=1e-20)
    return b


@pytest.mark.parametrize("n", [1, 2, 3, 5, 10, 40])
def test_agrees_with_the_reference_on_random_problems(n):
    rng = np.random.default_rng(300 + n)
    for _ in range(20):
        S = np.array([random_cov(rng) for _ in range(n)])
        Z = measure(rng, random_pose(rng), S)
        b = assert_agrees(Z, S)
        assert b["mean"].shape == (8,) and b["covariance"].shape == (6, 6)
        assert b["residuals"].shape == (n, 6) and b["nis"].shape == (n,)


def test_agrees_on_inlier_subsets():
    """Outliers get residuals, distances and NIS against all inliers; the fit ignores them."""
    rng = np.random.default_rng(310)
    for _ in range(30):
        n = 8
        S = np.array([random_cov(rng) for _ in range(n)])
        Z = measure(rng, random_pose(rng), S)
        inlier = rng.random(n) < 0.6
        inlier[rng.integers(n)] = True
        b = assert_agrees(Z, S, inlier)
        Zm = Z.copy()
        for i in np.flatnonzero(~inlier):
            Zm[i] = random_pose(rng)
        c = core(Zm, S, inlier)
        assert np.array_equal(c["mean"], b["mean"])
        assert np.array_equal(c["covariance"], b["covariance"])


def test_agrees_far_apart():
    rng = np.random.default_rng(311)
    for _ in range(20):
        S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
        assert_agrees(measure(rng, random_pose(rng, 3.0), S), S)


def test_agrees_near_pi():
    """Residual rotations near pi: the closed forms of the Jacobian, not the series."""
    rng = np.random.default_rng(312)
    for k in range(10):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        # two measurements (89.5 + 0.05 k) deg either side of X about one axis, a third off it
        xi = np.zeros((3, 6))
        xi[:2, :3] = np.outer([1.0, -1.0], np.deg2rad(89.5 + 0.05 * k) * axis)
        xi[:2, 3:] = rng.normal(size=(2, 3)) * 0.1
        xi[2, :3], xi[2, 5] = rng.normal(size=3) * 0.3, 0.1
        Z = dq.mul(random_pose(rng), lie.se3_exp(xi))
        S = np.array([random_cov(rng, (30, 60), (0.05, 0.2)) for _ in range(3)])
        b = assert_agrees(Z, S)
        assert np.linalg.norm(b["residuals"][:2, :3], axis=1).max() > 1.5


def test_agrees_with_a_tiny_covariance():
    """One measurement 1e4 times more certain than the rest: its leave-one-out information is the
    others' (summed, not cancelled out of the total)."""
    rng = np.random.default_rng(313)
    for _ in range(20):
        S = np.array([random_cov(rng) for _ in range(5)])
        S[2] *= 1e-8
        b = assert_agrees(measure(rng, random_pose(rng), S), S)
        assert b["tested"].all()


def test_one_inlier_is_its_own_estimate():
    rng = np.random.default_rng(314)
    S = np.array([random_cov(rng) for _ in range(3)])
    Z = measure(rng, random_pose(rng), S)
    b = assert_agrees(Z, S, np.array([False, True, False]))
    assert np.array_equal(b["mean"], Z[1]) and int(b["iterations"]) == 0
    assert list(b["tested"]) == [True, False, True] and b["nis"][1] == 0.0


def test_step_limit_and_zero_steps():
    rng = np.random.default_rng(315)
    S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
    Z = measure(rng, random_pose(rng), S)
    for max_iter in (0, 1, 2):
        b = assert_agrees(Z, S, max_iter=max_iter)
        assert int(b["status"]) == 1 and int(b["iterations"]) == max_iter


def test_batch_axis_is_the_loop_over_problems():
    rng = np.random.default_rng(316)
    B, n = 7, 4
    S = np.array([[random_cov(rng) for _ in range(n)] for _ in range(B)])
    Z = np.array([measure(rng, random_pose(rng), s) for s in S])
    inlier = rng.random((B, n)) < 0.8
    inlier[:, 0] = True
    out = core(Z.reshape(B, 1, n, 8), S.reshape(B, 1, n, 6, 6), inlier.reshape(B, 1, n))
    assert out["mean"].shape == (B, 1, 8) and out["covariance"].shape == (B, 1, 6, 6)
    assert out["nis"].shape == (B, 1, n) and out["status"].shape == (B, 1)
    for k in range(B):
        one = core(Z[k], S[k], inlier[k])
        for f in FIELDS:
            assert np.array_equal(np.asarray(out[f])[k, 0], one[f]), f


def test_without_nis():
    rng = np.random.default_rng(317)
    S = np.array([random_cov(rng) for _ in range(4)])
    Z = measure(rng, random_pose(rng), S)
    full = _c.fuse(Z, S, None)
    lean = _c.fuse(Z, S, None, 1e-12, 100, False)
    assert lean[4] is None and lean[5] is None
    for k in (0, 1, 2, 3, 6, 7, 8):
        assert np.array_equal(full[k], lean[k])


def test_errors_name_the_argument_and_index():
    rng = np.random.default_rng(318)
    S = np.array([[random_cov(rng) for _ in range(3)] for _ in range(2)])
    Z = np.array([measure(rng, random_pose(rng), s) for s in S])
    bad = Z.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"poses\[1, 2\]: contains NaN"):
        _c.fuse(bad, S, None)
    bad = Z.copy()
    bad[0, 1] *= 1.1
    with pytest.raises(ValueError, match=r"poses\[0, 1\]: quaternion norm"):
        _c.fuse(bad, S, None)
    badS = S.copy()
    badS[1, 0] -= 2.0 * np.abs(badS[1, 0]).max() * np.eye(6)
    with pytest.raises(ValueError, match=r"covariances\[1, 0\]: not positive definite"):
        _c.fuse(Z, badS, None)
    badS = S.copy()
    badS[0, 2, 3, 3] = np.inf
    with pytest.raises(ValueError, match=r"covariances\[0, 2\]: contains NaN"):
        _c.fuse(Z, badS, None)
    with pytest.raises(ValueError, match=r"inliers\[1\]: selects no measurement"):
        _c.fuse(Z, S, np.array([[True, False, False], [False, False, False]]))
    with pytest.raises(ValueError, match=r"covariances: expected shape \(\.\.\., n, 6, 6\)"):
        _c.fuse(Z, S[:, :2], None)
    with pytest.raises(ValueError, match=r"poses: expected shape \(\.\.\., n, 8\)"):
        _c.fuse(Z[..., :7], S, None)
    with pytest.raises(ValueError, match=r"inliers: expected shape"):
        _c.fuse(Z, S, np.ones(3, bool))
    with pytest.raises(ValueError, match="poses: no measurements"):
        _c.fuse(Z[:, :0], S[:, :0], None)
    with pytest.raises(ValueError, match="tol: must be finite"):
        _c.fuse(Z, S, None, np.nan)
    with pytest.raises(ValueError, match="max_iter: must be >= 0"):
        _c.fuse(Z, S, None, 1e-12, -1)
