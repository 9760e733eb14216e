"""dqpose.fusion.static: the exact ML fit of one instant against GTSAM (prior factors, LM,
marginals), the hard cases, NEES over seeded trials."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Status, Verdict
from tests.fusion._scenes import (
    assert_matches_gtsam,
    error,
    gtsam_fuse,
    measure,
    nees,
    random_cov,
    random_pose,
)

gtsam = pytest.importorskip("gtsam")


# ---- maximum likelihood ------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 5, 8])
def test_equals_gtsam_optimum_and_marginal(n):
    rng = np.random.default_rng(100 + n)
    for _ in range(10):
        X = random_pose(rng)
        S = np.array([random_cov(rng) for _ in range(n)])
        f = assert_matches_gtsam(measure(rng, X, S), S)
        assert f.dof == 6 * (n - 1) and len(f.inliers) == n and f.rejected == ()
        assert f.mean.shape == (8,) and f.covariance.shape == (6, 6)
        assert f.residuals.shape == (n, 6) and f.distances.shape == (n,)


def test_residuals_and_distances_are_those_of_the_returned_mean():
    rng = np.random.default_rng(7)
    X = random_pose(rng)
    S = np.array([random_cov(rng) for _ in range(4)])
    Z = measure(rng, X, S)
    f = fusion.fuse(Z, S)
    r = lie.se3_log(dq.mul(dq.conj(f.mean), Z))
    assert np.allclose(f.residuals, r, atol=1e-15)
    d2 = np.einsum("ni,ni->n", r, np.linalg.solve(S, r[..., None])[..., 0])
    assert np.allclose(f.distances ** 2, d2, rtol=1e-9)
    assert f.chi2 == pytest.approx(d2.sum(), rel=1e-9)
    # stationarity of the exact cost: sum_i Jl^-T(r_i) S_i^-1 r_i = 0 (scaled by the information)
    A = lie.se3_left_jacobian_inv(r)
    g = np.einsum("nji,nj->i", A, np.linalg.solve(S, r[..., None])[..., 0])
    assert np.linalg.norm(f.covariance @ g) < 1e-13
    with pytest.raises(ValueError):
        f.mean[0] = 2.0  # results are read-only


def test_hard_measurements_far_apart():
    """Large covariances, measurements radians and metres apart: a strongly nonlinear cost."""
    rng = np.random.default_rng(11)
    for _ in range(10):
        X = random_pose(rng, spread=3.0)
        S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
        assert_matches_gtsam(measure(rng, X, S), S)


def test_hard_near_pi_rotations_between_measurements():
    """Two measurements 179 deg apart about one axis (and a third off it): the mean lies between."""
    rng = np.random.default_rng(12)
    for k in range(8):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        X = random_pose(rng)
        half = np.deg2rad(89.5 + 0.06 * k)
        Z = np.array([dq.mul(X, lie.se3_exp(np.r_[s * half * axis, rng.normal(size=3) * 0.1]))
                      for s in (1.0, -1.0)] + [dq.mul(X, lie.se3_exp(np.r_[rng.normal(size=3) * 0.3,
                                                                           0.0, 0.0, 0.1]))])
        S = np.array([random_cov(rng, (30, 60), (0.05, 0.2)) for _ in range(3)])
        start = fusion.fuse(Z, S).mean
        f = assert_matches_gtsam(Z, S, start)
        # and GTSAM started at a measurement reaches the same optimum
        assert np.linalg.norm(error(f.mean, gtsam_fuse(Z, S)[0])) < 1e-9


def test_hard_one_measurement_with_a_tiny_covariance():
    rng = np.random.default_rng(13)
    X = random_pose(rng)
    S = np.array([random_cov(rng) for _ in range(5)])
    S[2] *= 1e-8
    Z = measure(rng, X, S)
    f = assert_matches_gtsam(Z, S)
    assert np.linalg.norm(error(f.mean, Z[2])) < 1e-6
    assert np.allclose(f.covariance, S[2], rtol=1e-5, atol=1e-5 * np.abs(S[2]).max())


def test_one_measurement_is_its_own_estimate():
    rng = np.random.default_rng(14)
    Z = random_pose(rng)[None]
    S = random_cov(rng)[None]
    f = fusion.fuse(Z, S)
    assert f.status == Status.CONVERGED and f.iterations == 0
    assert np.array_equal(f.mean, Z[0])
    assert np.allclose(f.covariance, S[0], rtol=1e-12, atol=1e-12 * np.abs(S).max())
    assert f.chi2 < 1e-20 and f.dof == 0 and not f.tested[0] and f.nis[0] == 0.0
    assert f.sources[0].verdict == Verdict.UNTESTED


def test_scalar_weights_are_isotropic_covariances():
    rng = np.random.default_rng(15)
    Z = np.array([random_pose(rng, 0.5) for _ in range(4)])
    w = rng.uniform(0.5, 3.0, 4)
    a = fusion.fuse(Z, weights=w)
    b = fusion.fuse(Z, np.eye(6) / w[:, None, None])
    assert np.allclose(a.mean, b.mean, atol=1e-15) and np.allclose(a.covariance, b.covariance)
    # for pure rotations the exact ML step is DIB's step: Jl^-T(w) w = w
    R = lie.se3_exp(np.c_[rng.normal(size=(4, 3)) * 0.7, np.zeros((4, 3))])
    m = fusion.fuse(R, weights=w).mean
    d = dq.dib(R, w)
    assert np.linalg.norm(error(m, d)) < 1e-12
    assert np.allclose(fusion.fuse(Z).covariance, fusion.fuse(Z, weights=np.ones(4)).covariance)


def test_step_limit_is_reported():
    rng = np.random.default_rng(16)
    S = np.array([random_cov(rng, (20, 60), (0.3, 2.0)) for _ in range(5)])
    Z = measure(rng, random_pose(rng), S)
    f = fusion.fuse(Z, S, max_iter=1)
    assert f.status == Status.MAX_ITERATIONS and f.iterations == 1
    assert fusion.fuse(Z, S).status == Status.CONVERGED


def test_nees_is_six_and_fusion_beats_every_source():
    rng = np.random.default_rng(2024)
    trials, n = 1000, 4
    covs = [np.array([random_cov(rng) for _ in range(n)]) for _ in range(trials)]
    values, fused_err, source_err = [], [], []
    for S in covs:
        X = random_pose(rng)
        Z = measure(rng, X, S)
        f = fusion.fuse(Z, S)
        values.append(nees(f, X))
        fused_err.append(np.linalg.norm(error(f.mean, X)[:3]))
        source_err.append(np.linalg.norm(error(Z, X)[:, :3], axis=1))
    assert 5.5 <= np.mean(values) <= 6.5
    best_single = np.min(np.median(source_err, axis=0))
    assert np.median(fused_err) < best_single


def test_fusion_beats_the_best_source_with_fixed_sources():
    """Sources with fixed covariances: the fused rotation and translation errors are below the
    best single source's in the median."""
    rng = np.random.default_rng(2025)
    S = np.array([random_cov(rng) for _ in range(3)])
    rot, trans = [], []
    for _ in range(300):
        X = random_pose(rng)
        Z = np.concatenate([measure(rng, X, S)])
        f = fusion.fuse(Z, S)
        e = np.concatenate([error(f.mean, X)[None], error(Z, X)])
        rot.append(np.linalg.norm(e[:, :3], axis=1))
        trans.append(np.linalg.norm(dq.to_pose(f.mean)[1] - dq.to_pose(X)[1])
                     if False else np.linalg.norm(e[:, 3:], axis=1))
    rot, trans = np.median(rot, axis=0), np.median(trans, axis=0)
    assert rot[0] < rot[1:].min() and trans[0] < trans[1:].min()
