"""dqpose.fusion: exact ML fusion against GTSAM (prior factors, LM, marginals), NEES over seeded
trials, the robust gate against gross outliers, per-source NIS and frames transport."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source, Status, Verdict

gtsam = pytest.importorskip("gtsam")
from tests import _gtsam  # noqa: E402  (needs gtsam)


# ---- scenes ------------------------------------------------------------------------------------
def random_cov(rng, rot_deg=(0.2, 2.0), trans_m=(0.5e-3, 5e-3)):
    """Anisotropic, correlated: rotation sigma 0.2-2 deg, translation sigma 0.5-5 mm."""
    s = np.concatenate([np.deg2rad(rng.uniform(*rot_deg, 3)), rng.uniform(*trans_m, 3)])
    C = np.corrcoef(rng.normal(size=(6, 12)))  # a random correlation matrix, well inside PD
    return s[:, None] * s[None] * C


def random_pose(rng, spread=1.0):
    return lie.se3_exp(np.concatenate([rng.normal(size=3) * spread, rng.normal(size=3) * spread]))


def measure(rng, X, covs):
    """Measurements Z_i with X = Z_i Exp(xi_i), xi_i ~ N(0, covs[i]) (the convention)."""
    xi = np.array([rng.multivariate_normal(np.zeros(6), c) for c in covs])
    return dq.mul(X, lie.se3_exp(-xi))


def error(X_hat, X):
    return lie.se3_log(dq.mul(dq.conj(X_hat), X))


def nees(f, X):
    e = error(f.mean, X)
    return float(e @ np.linalg.solve(f.covariance, e))


def gtsam_fuse(Z, S, start=None):
    graph, values = _gtsam.priors(Z, S, start)
    result = _gtsam.finish(graph, _gtsam.lm(graph, values))
    return _gtsam.pose(result), _gtsam.marginal(graph, result), 2.0 * graph.error(result)


def assert_matches_gtsam(Z, S, start=None):
    f = fusion.fuse(Z, S)
    X, P, chi2 = gtsam_fuse(Z, S, start)
    assert f.status == Status.CONVERGED
    assert np.linalg.norm(error(f.mean, X)) < 1e-9
    assert np.abs(f.covariance - P).max() <= 1e-6 * np.abs(P).max()
    assert f.chi2 == pytest.approx(chi2, rel=1e-6, abs=1e-12)
    return f


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


# ---- bad input ---------------------------------------------------------------------------------
def _ok(n=3):
    rng = np.random.default_rng(0)
    return (np.array([random_pose(rng) for _ in range(n)]),
            np.array([random_cov(rng) for _ in range(n)]))


@pytest.mark.parametrize("mutate, message", [
    (lambda Z, S: (Z[:0], S[:0]), "poses: no measurements"),
    (lambda Z, S: (Z[:, :7], S), r"poses: expected shape \(n, 8\)"),
    (lambda Z, S: (np.where(np.arange(3)[:, None] == 1, np.nan, Z), S),
     r"poses\[1\]: contains NaN"),
    (lambda Z, S: (Z * np.array([1, 1, 1.1])[:, None], S), r"poses\[2\]: quaternion norm"),
    (lambda Z, S: (Z, S[:2]), r"covariances: expected shape \(3, 6, 6\)"),
    (lambda Z, S: (Z, S * np.array([1, 1, np.inf])[:, None, None]),
     r"covariances\[2\]: contains NaN"),
    (lambda Z, S: (Z, S - 1.01 * np.eye(6) * np.max(S) * (np.arange(3) == 2)[:, None, None]),
     r"covariances\[2\]: not positive definite"),
    (lambda Z, S: (Z, S + np.triu(np.ones((6, 6)), 1) * 1e-6 * (np.arange(3) == 1)[:, None, None]),
     r"covariances\[1\]: not symmetric"),
])
def test_bad_input_names_the_argument_and_index(mutate, message):
    Z, S = mutate(*_ok())
    with pytest.raises(ValueError, match=message):
        fusion.fuse(Z, S)


def test_bad_options():
    Z, S = _ok()
    for kwargs, message in [
        (dict(weights=[1, 0, 1]), r"weights\[1\]: must be positive"),
        (dict(weights=[1, 1]), r"weights: expected shape \(3\)"),
        (dict(probability=1.0), "probability: must be within"),
        (dict(names=["a", "b"]), "names: expected 3 source names"),
        (dict(names="abc"), "names: expected one source name per measurement"),
        (dict(sources=[Source("a"), Source("a")]), r"sources\[1\]: source 'a' given twice"),
        (dict(sources=[Source("a", extrinsic=np.ones(8))]), r"sources\[0\].extrinsic: "),
        (dict(tol=-1), "tol: must be finite"),
        (dict(max_iter=1.5), "max_iter: must be a whole number"),
    ]:
        with pytest.raises(ValueError, match=message):
            fusion.fuse(Z, None if "weights" in kwargs else S, **kwargs)
    with pytest.raises(ValueError, match="weights: give covariances or weights, not both"):
        fusion.fuse(Z, S, weights=np.ones(3))
    # a covariance asymmetric at rounding level is accepted (and symmetrised)
    fusion.fuse(Z, S + np.triu(np.ones((6, 6)), 1) * 1e-14 * np.abs(S).max())


def test_chi2_quantile_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for p in (0.0005, 0.05, 0.5, 0.999, 0.9995):
        for k in (1, 6, 12, 60, 600, 6000):
            assert fusion.chi2_quantile(p, k) == pytest.approx(stats.chi2.ppf(p, k), rel=1e-10)


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


# ---- consistency -------------------------------------------------------------------------------
def test_a_source_claiming_ten_times_too_small_a_covariance_is_flagged():
    """Four sources of five measurements each; source 'c' reports a covariance 10x smaller than
    its noise. Its NIS stands out; the honest sources stay consistent."""
    rng = np.random.default_rng(41)
    flags = {s: 0 for s in "abcd"}
    trials = 40
    for _ in range(trials):
        X = random_pose(rng)
        S_true = np.repeat(np.array([random_cov(rng) for _ in range(4)]), 5, axis=0)
        names = [s for s in "abcd" for _ in range(5)]
        Z = measure(rng, X, S_true)
        S_claimed = S_true.copy()
        S_claimed[10:15] /= 10.0
        f = fusion.fuse(Z, S_claimed, names=names)
        stats = {s.name: s for s in f.sources}
        assert [s.name for s in f.sources] == list("abcd")
        assert all(s.count == 5 and s.rejected == 0 for s in f.sources)
        # counts are ints: a wire message's uint32 fields take nothing else
        assert all(type(s.count) is int and type(s.rejected) is int for s in f.sources)
        for s in "abcd":
            flags[s] += stats[s].verdict != Verdict.CONSISTENT
        assert stats["c"].verdict == Verdict.OPTIMISTIC and stats["c"].nis_mean > stats["c"].high
    assert flags["c"] == trials
    assert flags["a"] + flags["b"] + flags["d"] <= 0.05 * 3 * trials


def test_nis_of_consistent_sources_averages_six():
    rng = np.random.default_rng(42)
    values = []
    for _ in range(300):
        S = np.array([random_cov(rng) for _ in range(4)])
        f = fusion.fuse(measure(rng, random_pose(rng), S), S)
        assert f.tested.all()
        values.extend(f.nis)
    assert 5.7 <= np.mean(values) <= 6.3


def test_a_source_claiming_too_large_a_covariance_is_pessimistic():
    rng = np.random.default_rng(43)
    S_true = np.array([random_cov(rng) for _ in range(12)])
    names = ["a"] * 6 + ["b"] * 6
    S_claimed = S_true.copy()
    S_claimed[6:] *= 10.0
    f = fusion.fuse(measure(rng, random_pose(rng), S_true), S_claimed, names=names)
    verdicts = {s.name: s.verdict for s in f.sources}
    assert verdicts == {"a": Verdict.CONSISTENT, "b": Verdict.PESSIMISTIC}


# ---- frames ------------------------------------------------------------------------------------
def frames_scene(rng):
    """Two cameras (T_cam_body in their frames) and an arm (T_base_flange, the body offset in the
    flange frame) of one body X = T_world_body; each source's own covariance in its frame."""
    X = random_pose(rng)
    E = {name: random_pose(rng) for name in ("cam0", "cam1", "arm")}
    offset = random_pose(rng, 0.3)
    sources = [Source("cam0", extrinsic=E["cam0"]), Source("cam1", extrinsic=E["cam1"]),
               Source("arm", extrinsic=E["arm"], body_offset=offset)]
    names = ["cam0", "cam0", "cam1", "arm"]
    S = np.array([random_cov(rng) for _ in names])
    S[3] = random_cov(rng, (0.05, 0.2), (0.1e-3, 0.5e-3))
    truth = [dq.mul(dq.conj(E[s]), X) for s in names[:3]]
    truth.append(dq.mul(dq.mul(dq.conj(E["arm"]), X), dq.conj(offset)))
    Z = np.array([measure(rng, t, s[None])[0] for t, s in zip(truth, S)])
    return X, Z, S, names, sources, E, offset


def test_frames_fuse_to_the_world_pose_and_match_gtsam_on_transported_factors():
    rng = np.random.default_rng(51)
    for _ in range(10):
        X, Z, S, names, sources, E, offset = frames_scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=sources)
        # the same factors built with GTSAM's own algebra: Z_world = E Z offset,
        # Ad(offset^-1) S Ad(offset^-1)^T
        Zw, Sw = [], []
        for z, s, name in zip(Z, S, names):
            P = gtsam.Pose3(dq.to_matrix(E[name])).compose(gtsam.Pose3(dq.to_matrix(z)))
            if name == "arm":
                A = gtsam.Pose3(dq.to_matrix(offset)).inverse().AdjointMap()
                P, s = P.compose(gtsam.Pose3(dq.to_matrix(offset))), A @ s @ A.T
            Zw.append(dq.from_matrix(P.matrix()))
            Sw.append(s)
        Xg, Pg, chi2 = gtsam_fuse(np.array(Zw), np.array(Sw))
        assert np.linalg.norm(error(f.mean, Xg)) < 1e-9
        assert np.abs(f.covariance - Pg).max() <= 1e-6 * np.abs(Pg).max()
        assert f.chi2 == pytest.approx(chi2, rel=1e-6)
        assert np.linalg.norm(error(f.mean, X)[:3]) < 0.01


def test_frames_nees_is_six():
    rng = np.random.default_rng(52)
    values = []
    for _ in range(300):
        X, Z, S, names, sources, _, _ = frames_scene(rng)
        values.append(nees(fusion.fuse(Z, S, names=names, sources=sources), X))
    assert 5.3 <= np.mean(values) <= 6.7


def test_frames_transport_a_covariance_exactly_monte_carlo():
    """One arm measurement: the fused pose is E Z offset and its covariance the flange covariance
    carried to the body; samples of the true flange pose carried through agree."""
    rng = np.random.default_rng(53)
    E, offset, Z = random_pose(rng), random_pose(rng, 0.5), random_pose(rng)
    S = random_cov(rng, (2, 10), (5e-3, 2e-2))
    f = fusion.fuse(Z[None], S[None], names=["arm"], sources=[Source("arm", E, offset)])
    assert np.linalg.norm(error(f.mean, dq.mul(dq.mul(E, Z), offset))) < 1e-14
    xi = rng.multivariate_normal(np.zeros(6), S, size=20000)
    body = dq.mul(dq.mul(E, dq.mul(Z, lie.se3_exp(xi))), offset)  # the true body pose, sampled
    d = error(f.mean, body)
    empirical = d.T @ d / len(d)
    sd = np.sqrt(np.diag(f.covariance))
    assert np.abs((empirical - f.covariance) / np.outer(sd, sd)).max() < 0.04
    # a camera's extrinsic alone (constant on the left) leaves the covariance as it is
    g = fusion.fuse(Z[None], S[None], names=["cam"], sources=[Source("cam", extrinsic=E)])
    assert np.allclose(g.covariance, S, rtol=1e-12, atol=1e-12 * np.abs(S).max())
    # a measurement of a source not listed is taken in the world frame
    h = fusion.fuse(Z[None], S[None], names=["other"], sources=[Source("cam", extrinsic=E)])
    assert np.array_equal(h.mean, Z)
