"""dqpose.fusion.robust: the gate against gross outliers; the answer is the ML fit of the
inliers."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Status
from tests.fusion._scenes import (
    error,
    measure,
    random_cov,
    random_pose,
)

gtsam = pytest.importorskip("gtsam")


# ---- robust mode -------------------------------------------------------------------------------
def outlier(rng, kind, X, Z):
    """A gross error of the given kind for a measurement Z of X."""
    if kind == "wrong marker":
        return random_pose(rng)
    if kind == "flipped":  # PnP's mirror solution: 180 deg about an axis of the body
        axis = np.eye(3)[rng.integers(3)]
        return dq.mul(Z, lie.se3_exp(np.r_[np.pi * axis, 0.0, 0.0, 0.0]))
    # a stale arm: where the body was some 50-200 ms ago
    return dq.mul(Z, lie.se3_exp(np.r_[rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.03]))


def contaminated_scene(rng, n=10, n_out=2):
    X = random_pose(rng)
    S = np.array([random_cov(rng) for _ in range(n)])
    Z = measure(rng, X, S)
    bad = rng.choice(n, n_out, replace=False)
    kinds = ["wrong marker", "flipped", "stale arm"]
    Zc = Z.copy()
    for i in bad:
        Zc[i] = outlier(rng, kinds[rng.integers(3)], X, Z[i])
    return X, S, Z, Zc, bad


def sigmas_off(Z, X, S):
    """How many sigmas each measurement is off the truth (Mahalanobis distance)."""
    e = error(X, Z)
    return np.sqrt(np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0]))


def test_robust_answer_is_the_ml_answer_on_its_inliers():
    rng = np.random.default_rng(31)
    for _ in range(20):
        X, S, Z, Zc, bad = contaminated_scene(rng)
        names = [f"cam{i % 3}" for i in range(len(Z))]
        f = fusion.fuse(Zc, S, names=names, robust=True)
        g = fusion.fuse(Zc[f.inliers], S[f.inliers])
        assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)
        assert f.chi2 == g.chi2 and f.dof == g.dof and f.iterations == g.iterations
        # and moving a rejected measurement anywhere else does not move it either
        for rej in f.rejected:
            Zm = Zc.copy()
            Zm[rej.index] = random_pose(rng)
            h = fusion.fuse(Zm, S, names=names, robust=True)
            if np.array_equal(h.inliers, f.inliers):
                assert np.array_equal(h.mean, f.mean)
        assert {r.index for r in f.rejected} | set(f.inliers.tolist()) == set(range(len(Z)))
        for r in f.rejected:
            assert r.source == names[r.index] and r.distance > r.gate
            assert r.reason.startswith(f"measurement {r.index} ({names[r.index]}): Mahalanobis")


def test_robust_rejects_gross_outliers_and_keeps_the_clean_accuracy():
    rng = np.random.default_rng(32)
    robust_rot, robust_trans, clean_rot, clean_trans = [], [], [], []
    false_rejections = kept = 0
    for _ in range(300):
        X, S, Z, Zc, bad = contaminated_scene(rng)
        f = fusion.fuse(Zc, S, robust=True)
        assert f.status == Status.CONVERGED
        rejected = {r.index for r in f.rejected}
        off = sigmas_off(Zc, X, S)
        for i in bad:
            if off[i] > 10:
                assert i in rejected, f"outlier {i} {off[i]:.1f} sigma off was kept"
            else:
                kept += 1
        false_rejections += len(rejected - set(bad.tolist()))
        good = np.setdiff1d(np.arange(len(Z)), bad)
        clean = fusion.fuse(Z[good], S[good])
        e, c = error(f.mean, X), error(clean.mean, X)
        robust_rot.append(np.linalg.norm(e[:3]))
        robust_trans.append(np.linalg.norm(e[3:]))
        clean_rot.append(np.linalg.norm(c[:3]))
        clean_trans.append(np.linalg.norm(c[3:]))
    assert np.median(robust_rot) <= 1.2 * np.median(clean_rot)
    assert np.median(robust_trans) <= 1.2 * np.median(clean_trans)
    assert false_rejections <= 0.01 * 300 * 8  # the gate's 0.1 % and then some


def test_robust_without_outliers_changes_nothing():
    rng = np.random.default_rng(33)
    changed = 0
    for _ in range(50):
        X = random_pose(rng)
        S = np.array([random_cov(rng) for _ in range(6)])
        Z = measure(rng, X, S)
        f, g = fusion.fuse(Z, S, robust=True), fusion.fuse(Z, S)
        if f.rejected:
            changed += 1
        else:
            assert np.array_equal(f.mean, g.mean)
    assert changed <= 2


def test_robust_gate_probability_sets_the_gate():
    rng = np.random.default_rng(34)
    X, S, Z, Zc, bad = contaminated_scene(rng)
    f = fusion.fuse(Zc, S, robust=True, probability=0.99)
    assert all(r.gate == pytest.approx(np.sqrt(fusion.chi2_quantile(0.99, 6))) for r in f.rejected)
    assert f.rejected and all(r.probability == 0.99 for r in f.rejected)
