"""dqpose.fusion over time: a moving body seen by 30 Hz cameras with 40 ms latency and a 500 Hz
arm, fused at the query time under the constant-twist model (accuracy against each source alone,
NEES, latency compensation and its online estimate, skew, extrapolation), the exact Jacobians, and
the per-body sliding window (:class:`dqpose.fusion.Tracker`)."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Measurement, Source, Status, Tracker

CAMERA_RATE, ARM_RATE = 30.0, 500.0
LATENCY = 0.04          # the cameras'; the arm's is 4 ms
ARM_LATENCY = 0.004
WINDOW = 0.2
TWIST = np.array([0.3, -0.2, 0.5, 0.2, 0.1, -0.15])   # rad/s, m/s: 8 mm in the cameras' 40 ms
ACCELERATION = np.array([0.1, 0.05, -0.08, 0.05, -0.03, 0.04])  # rad/s², m/s²: "mildly"


def deg(x):
    return np.deg2rad(x)


# Anisotropic, correlated sources of comparable quality: cameras good across the image, poor in
# depth (each looking along its own axis), an arm with millimetre noise.
def _rotated(C, axis_angle):
    R = np.eye(6)
    R[:3, :3] = R[3:, 3:] = dq.to_matrix(lie.se3_exp(np.r_[axis_angle, 0, 0, 0]))[:3, :3]
    return R @ C @ R.T


CAM_A = _rotated(np.diag([deg(0.15) ** 2] * 3 + [0.5e-3 ** 2, 0.5e-3 ** 2, 3e-3 ** 2]),
                 [0.0, 0.0, 0.0])
CAM_B = _rotated(np.diag([deg(0.2) ** 2] * 3 + [0.6e-3 ** 2, 0.6e-3 ** 2, 4e-3 ** 2]),
                 [1.2, 0.3, 0.0])
ARM = np.diag([deg(0.5) ** 2] * 3 + [2e-3 ** 2] * 3)
SOURCES = [Source("cam_a", latency=LATENCY), Source("cam_b", latency=LATENCY),
           Source("arm", latency=ARM_LATENCY)]


def trajectory(X0, accelerating):
    """Constant twist ``T(t) = X0 Exp(t V)``, or ``X0 Exp(t V + t²/2 a)``."""
    def T(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        xi = t[:, None] * TWIST + (0.5 * t[:, None] ** 2 * ACCELERATION if accelerating else 0.0)
        return dq.mul(X0, lie.se3_exp(xi))
    return T


def sample(rng, T, C, taken):
    """Poses ``T(τ) Exp(-ξ)``, ``ξ ~ N(0, C)``: the truth is ``Z Exp(ξ)`` (the convention)."""
    xi = rng.multivariate_normal(np.zeros(6), C, size=taken.size)
    return dq.mul(T(taken), lie.se3_exp(-xi))


def scene(rng, accelerating=False, end=1.0, window=WINDOW):
    """One window of measurements ending at ``end`` (stamp time): poses, covariances, source
    names, stamps, and the truth as a function of the time a pose was taken."""
    T = trajectory(lie.se3_exp(rng.normal(size=6)), accelerating)
    parts = []
    for name, rate, C, latency in (("cam_a", CAMERA_RATE, CAM_A, LATENCY),
                                   ("cam_b", CAMERA_RATE, CAM_B, LATENCY),
                                   ("arm", ARM_RATE, ARM, ARM_LATENCY)):
        stamps = end - np.arange(0.0, window, 1.0 / rate) - rng.uniform(0.0, 1.0 / rate)
        stamps = np.sort(stamps)
        parts.append((sample(rng, T, C, stamps - latency), np.broadcast_to(C, (stamps.size, 6, 6)),
                      [name] * stamps.size, stamps))
    Z = np.concatenate([p[0] for p in parts])
    S = np.concatenate([p[1] for p in parts])
    names = sum((p[2] for p in parts), [])
    stamps = np.concatenate([p[3] for p in parts])
    return Z, S, names, stamps, T


def error(X_hat, X):
    return lie.se3_log(dq.mul(dq.conj(X_hat), X))


def sizes(e):
    """Rotation angle (rad) and translation error (m) of twists ``e`` ``(..., 6)``."""
    return np.linalg.norm(e[..., :3], axis=-1), np.linalg.norm(e[..., 3:], axis=-1)


def subset(Z, S, names, stamps, keep):
    idx = [i for i, s in enumerate(names) if s in keep]
    return Z[idx], S[idx], [names[i] for i in idx], stamps[idx]


def naive(Z, names, stamps, source, latency, time):
    """A source alone, the plain way: its two newest poses, screw-extrapolated to ``time``."""
    idx = [i for i, s in enumerate(names) if s == source]
    idx = sorted(idx, key=lambda i: stamps[i])[-2:]
    (a, b), (ta, tb) = Z[idx], stamps[idx] - latency
    step = lie.se3_log(dq.mul(dq.conj(a), b))
    return dq.mul(b, lie.se3_exp((time - tb) / (tb - ta) * step))


# ---- accuracy at the query time ------------------------------------------------------------------
@pytest.mark.parametrize("accelerating", [False, True])
def test_fused_pose_beats_every_source_alone_at_the_query_time(accelerating):
    rng = np.random.default_rng(9 + accelerating)
    fused, alone, plain = [], {s.name: [] for s in SOURCES}, {s.name: [] for s in SOURCES}
    for _ in range(100):
        Z, S, names, stamps, T = scene(rng, accelerating)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
        assert f.status == Status.CONVERGED
        truth = T(f.time)[0]
        fused.append(error(f.mean, truth))
        for s in SOURCES:  # the same model on one source, and the plain extrapolation
            Zs, Ss, ns, ts = subset(Z, S, names, stamps, {s.name})
            g = fusion.fuse(Zs, Ss, names=ns, sources=SOURCES, times=ts, time=f.time)
            alone[s.name].append(error(g.mean, truth))
            plain[s.name].append(error(naive(Z, names, stamps, s.name, s.latency, f.time), truth))
    # measurably for a constant twist; under acceleration the model's bias eats part of the gain
    margin = 1.0 if accelerating else 0.85
    rot, trans = (np.median(x) for x in sizes(np.array(fused)))
    for name in alone:
        for errors in (alone[name], plain[name]):
            r, t = (np.median(x) for x in sizes(np.array(errors)))
            assert rot < margin * r and trans < margin * t, (name, rot, r, trans, t)


def test_nees_is_six_for_a_constant_twist_at_the_query_time_ahead_of_it_and_of_the_twist():
    rng = np.random.default_rng(61)
    now, ahead, twist, chi2 = [], [], [], []
    for _ in range(300):
        Z, S, names, stamps, T = scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
        e = error(f.mean, T(f.time)[0])
        now.append(e @ np.linalg.solve(f.covariance, e))
        e = f.twist - TWIST
        twist.append(e @ np.linalg.solve(f.twist_covariance, e))
        chi2.append(f.chi2 / f.dof)
        g = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=f.time + 0.05)
        assert g.extrapolation == pytest.approx(0.05)
        assert np.all(np.linalg.eigvalsh(g.covariance - f.covariance) > 0)  # it grew
        e = error(g.mean, T(g.time)[0])
        ahead.append(e @ np.linalg.solve(g.covariance, e))
    for values in (now, ahead, twist):
        assert 5.5 <= np.mean(values) <= 6.5, (np.mean(now), np.mean(ahead), np.mean(twist))
    assert abs(np.mean(chi2) - 1.0) < 0.02, np.mean(chi2)  # and the dof count is right


def test_latency_compensation_matters():
    rng = np.random.default_rng(63)
    unaware = [Source("cam_a"), Source("cam_b"), Source("arm", latency=ARM_LATENCY)]
    right, wrong, flagged = [], [], 0
    for _ in range(40):
        Z, S, names, stamps, T = scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
        g = fusion.fuse(Z, S, names=names, sources=unaware, times=stamps, time=f.time)
        right.append(sizes(error(f.mean, T(f.time)[0]))[1])
        wrong.append(sizes(error(g.mean, T(g.time)[0]))[1])
        flagged += any(s.verdict == fusion.Verdict.OPTIMISTIC for s in g.sources)
    assert np.median(wrong) > 3.0 * np.median(right), (np.median(wrong), np.median(right))
    assert flagged >= 35  # the consistency report sees the unmodelled latency


def test_latency_estimated_online_comes_out_near_the_truth():
    rng = np.random.default_rng(64)
    guess = [Source("cam_a", latency=0.0, latency_sigma=0.1),
             Source("cam_b", latency=0.0, latency_sigma=0.1), Source("arm", latency=ARM_LATENCY)]
    z, errs, known = [], [], []
    for _ in range(100):
        Z, S, names, stamps, T = scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
        g = fusion.fuse(Z, S, names=names, sources=guess, times=stamps, time=f.time)
        assert g.status == Status.CONVERGED
        assert [lat.name for lat in g.latencies] == ["cam_a", "cam_b"]
        for lat in g.latencies:
            assert lat.configured == 0.0 and lat.prior_sigma == 0.1
            assert lat.sigma < 0.005
            z.append((lat.value - LATENCY) / lat.sigma)
        errs.append(error(g.mean, T(g.time)[0]))
        known.append(sizes(error(f.mean, T(f.time)[0]))[1])
    z = np.array(z)
    assert abs(z.mean()) < 0.5 and 0.6 < z.std() < 1.4, (z.mean(), z.std())
    # the unknown latency costs little accuracy, and the covariance carries its uncertainty
    assert np.median(sizes(np.array(errs))[1]) < 1.5 * np.median(known)


# ---- skew, extrapolation, one instant ------------------------------------------------------------
def test_measurements_beyond_max_skew_are_dropped_with_a_reason_and_never_move_the_answer():
    rng = np.random.default_rng(65)
    Z, S, names, stamps, T = scene(rng)
    taken = stamps - np.array([{"arm": ARM_LATENCY}.get(s, LATENCY) for s in names])
    f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, max_skew=0.1)
    old = np.flatnonzero(f.time - taken > 0.1)
    assert old.size > 0
    assert [d.index for d in f.dropped] == list(old)
    for d in f.dropped:
        assert d.source == names[d.index] and d.age == pytest.approx(f.time - taken[d.index])
        assert d.reason.startswith(f"measurement {d.index} ({names[d.index]}): taken ")
        assert "beyond max_skew 0.1 s" in d.reason
    assert not set(old) & set(f.inliers) and f.rejected == ()
    keep = np.setdiff1d(np.arange(len(names)), old)
    g = fusion.fuse(Z[keep], S[keep], names=[names[i] for i in keep], sources=SOURCES,
                    times=stamps[keep], time=f.time)
    assert np.abs(f.mean - g.mean).max() < 1e-12
    assert np.abs(f.covariance - g.covariance).max() <= 1e-9 * np.abs(g.covariance).max()
    arm = next(s for s in f.sources if s.name == "arm")
    assert arm.rejected == 0 and arm.count == sum(names[i] == "arm" for i in keep)
    with pytest.raises(ValueError, match=r"^max_skew: every measurement"):
        fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=f.time + 1,
                    max_skew=0.1, max_extrapolation=None)


def test_extrapolation_is_reported_and_bounded():
    rng = np.random.default_rng(66)
    Z, S, names, stamps, T = scene(rng)
    f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
    assert f.extrapolation == 0.0
    g = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=f.time + 0.08)
    assert g.extrapolation == pytest.approx(0.08)
    with pytest.raises(ValueError, match=r"^time: .* s outside the span .* beyond "
                                         r"max_extrapolation 0.1 s"):
        fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=f.time + 0.15)
    first = min(t - {"arm": ARM_LATENCY}.get(s, LATENCY) for t, s in zip(stamps, names))
    early = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=first - 0.03)
    assert early.extrapolation == pytest.approx(0.03)
    assert np.all(np.linalg.eigvalsh(early.covariance - f.covariance) > 0)


def test_one_instant_is_the_static_fusion_and_extrapolating_it_needs_a_twist_prior():
    rng = np.random.default_rng(67)
    X = lie.se3_exp(rng.normal(size=6))
    S = np.array([CAM_A, CAM_B, ARM])
    Z = np.concatenate([sample(rng, lambda t: X[None], C, np.zeros(1)) for C in S])
    static = fusion.fuse(Z, S, names=["a", "b", "c"])
    f = fusion.fuse(Z, S, names=["a", "b", "c"], times=[2.5, 2.5, 2.5])
    assert f.time == 2.5 and f.twist is None and f.twist_covariance is None
    assert np.abs(f.mean - static.mean).max() < 1e-12
    assert np.abs(f.covariance - static.covariance).max() <= 1e-9 * np.abs(static.covariance).max()
    assert f.chi2 == pytest.approx(static.chi2) and f.dof == static.dof
    np.testing.assert_allclose(f.nis, static.nis, rtol=1e-9)
    with pytest.raises(ValueError, match=r"^time: the measurements were all taken at 2.5; .*"
                                         r"twist_covariance"):
        fusion.fuse(Z, S, times=[2.5, 2.5, 2.5], time=2.55)
    prior = np.diag([0.5 ** 2] * 3 + [0.2 ** 2] * 3)
    g = fusion.fuse(Z, S, times=[2.5, 2.5, 2.5], time=2.55, twist_covariance=prior)
    assert np.abs(g.twist_covariance - prior).max() < 1e-12
    # the data say nothing of the twist (0 by the prior), so the pose 50 ms on is the same
    # pose, less certain by 50 ms of the prior twist: X = Y Exp(-dt V) with V ~ N(0, prior)
    assert np.abs(g.mean - f.mean).max() < 1e-10 and np.abs(g.twist).max() < 1e-10
    grown = f.covariance + 0.05 ** 2 * prior
    assert np.abs(g.covariance - grown).max() <= 1e-9 * np.abs(grown).max()


def test_equal_stamps_with_different_latencies_are_two_instants():
    rng = np.random.default_rng(68)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    taken = np.array([1.0 - LATENCY, 1.0 - LATENCY, 1.0 - ARM_LATENCY])
    Z = T(taken)
    f = fusion.fuse(Z, np.array([CAM_A, CAM_B, ARM]), names=["cam_a", "cam_b", "arm"],
                    sources=SOURCES, times=[1.0, 1.0, 1.0])
    assert f.time == taken[2] and f.dof == 6 and f.twist is not None
    assert np.linalg.norm(error(f.mean, T(f.time)[0])) < 1e-12
    # without the arm one instant is left, which leaves the twist open: the arm is untested
    assert list(f.tested) == [True, True, False]


# ---- robust mode over time -----------------------------------------------------------------------
def test_robust_rejects_a_flipped_camera_pose_and_keeps_the_rest():
    rng = np.random.default_rng(69)
    for _ in range(10):
        Z, S, names, stamps, T = scene(rng)
        Z = Z.copy()
        bad = [i for i, s in enumerate(names) if s == "cam_b"][-2]
        Z[bad] = dq.mul(Z[bad], lie.se3_exp([np.pi * 0.9, 0, 0, 0.0, 0.05, 0]))
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, robust=True)
        assert [r.index for r in f.rejected] == [bad]
        assert f.rejected[0].reason.startswith(f"measurement {bad} (cam_b): Mahalanobis")
        keep = np.setdiff1d(np.arange(len(names)), [bad])
        g = fusion.fuse(Z[keep], S[keep], names=[names[i] for i in keep], sources=SOURCES,
                        times=stamps[keep], time=f.time)
        assert np.abs(f.mean - g.mean).max() < 1e-12


def test_robust_without_outliers_keeps_nearly_everything_and_never_readmits_a_dropped_one():
    rng = np.random.default_rng(74)
    kept = total = 0
    for _ in range(10):
        Z, S, names, stamps, T = scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, robust=True,
                        max_skew=0.15)
        assert f.dropped and not {d.index for d in f.dropped} & set(f.inliers)
        assert not {d.index for d in f.dropped} & {r.index for r in f.rejected}
        kept += f.inliers.size
        total += len(names) - len(f.dropped)
        if not f.rejected:
            g = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, max_skew=0.15)
            assert np.abs(f.mean - g.mean).max() < 1e-12
    assert kept >= 0.99 * total


# ---- the Gauss-Newton model ----------------------------------------------------------------------
def test_the_jacobian_is_exact_for_pose_twist_and_latency():
    rng = np.random.default_rng(70)
    Z, S, names, stamps, T = scene(rng)
    Z, S, names, stamps = Z[::9], S[::9], names[::9], stamps[::9]
    model = fusion._Model(stamp=stamps - 1.0, latency=np.zeros(len(names)),
                          slot=np.array([{"cam_a": 0, "arm": 1}.get(s, -1) for s in names]),
                          prior=np.array([0.03, 0.01]), prior_w=np.array([1e4, 1e4]),
                          twist=True, twist_w=None)
    W = np.linalg.inv(S)
    X, V, ell = T(1.0)[0], TWIST + 0.1, np.array([0.035, 0.002])
    dt, r, _ = fusion._motion_evaluate(X, V, ell, Z, W, model)
    G = fusion._motion_jacobian(V, dt, r, model)
    h = 1e-6
    for k in range(model.dim):
        d = np.zeros(model.dim)
        d[k] = h
        def residual(sign):
            Xs = dq.mul(X, lie.se3_exp(sign * d[:6]))
            return fusion._motion_evaluate(Xs, V + sign * d[6:12], ell + sign * d[12:], Z, W,
                                           model)[1]
        numeric = (residual(1) - residual(-1)) / (2 * h)
        np.testing.assert_allclose(-G[:, :, k], numeric, atol=1e-7 * max(1, np.abs(numeric).max()))


def test_the_twist_is_the_generating_one_for_noise_free_data():
    rng = np.random.default_rng(71)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    times = np.array([0.0, 0.013, 0.05, 0.1])
    f = fusion.fuse(T(times), times=times, time=0.07)
    assert np.abs(f.twist - TWIST).max() < 1e-10
    assert np.linalg.norm(error(f.mean, T(0.07)[0])) < 1e-12
    assert f.chi2 < 1e-20 and f.status == Status.CONVERGED


# ---- acceleration as process noise ---------------------------------------------------------------
def rule_of_thumb(acceleration, window=WINDOW):
    """``Q ≈ a² L`` (the module docstring), isotropic in rotation and in translation."""
    w, v = np.linalg.norm(acceleration[:3]), np.linalg.norm(acceleration[3:])
    return window * np.diag([w * w / 3] * 3 + [v * v / 3] * 3)


def random_walk_scene(rng, Q, window=0.1):
    """:func:`scene` with the truth drawn from the model ``acceleration_psd`` states: the pose
    ``X`` and twist at the newest time a measurement was taken, the pose at ``τ``
    ``X Exp(dt V) Exp(ε(τ))``, ``ε`` the twice-integrated white noise of density ``Q``
    (covariance ``k(dt_i, dt_j) Q``, drawn as ``A N Bᵀ`` with ``A Aᵀ = k``, ``B Bᵀ = Q``)."""
    Z, S, names, stamps, _ = scene(rng, window=window)
    taken = stamps - np.array([{"arm": ARM_LATENCY}.get(s, LATENCY) for s in names])
    dt = taken - taken.max()
    X = lie.se3_exp(rng.normal(size=6))
    w, U = np.linalg.eigh(fusion._kernel(dt))  # singular at dt = 0
    A = U * np.sqrt(np.maximum(w, 0.0))
    eps = A @ rng.normal(size=(dt.size, 6)) @ np.linalg.cholesky(Q).T
    truth = dq.mul(dq.mul(X, lie.se3_exp(dt[:, None] * TWIST)), lie.se3_exp(eps))
    xi = np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=(dt.size, 6)))
    return dq.mul(truth, lie.se3_exp(-xi)), S, names, stamps, X


def test_acceleration_noise_makes_an_accelerating_body_honest():
    rng = np.random.default_rng(75)
    Q = rule_of_thumb(ACCELERATION)
    plain, noisy, e_plain, e_noisy = [], [], [], []
    for _ in range(100):
        Z, S, names, stamps, T = scene(rng, accelerating=True)
        for out, errs, q in ((plain, e_plain, None), (noisy, e_noisy, Q)):
            f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, acceleration_psd=q)
            assert f.status == Status.CONVERGED
            e = error(f.mean, T(f.time)[0])
            out.append(e @ np.linalg.solve(f.covariance, e))
            errs.append(e)
    assert np.mean(plain) > 7.0, np.mean(plain)  # the constant twist claims too much
    assert 5.0 <= np.mean(noisy) <= 6.8, np.mean(noisy)
    for a, b in zip(sizes(np.array(e_noisy)), sizes(np.array(e_plain))):
        assert np.median(a) < 1.1 * np.median(b)  # honesty costs no accuracy


def test_nees_nis_and_chi2_are_right_when_the_twist_is_the_modelled_random_walk():
    rng = np.random.default_rng(76)
    Q = np.diag([0.5 ** 2] * 3 + [0.2 ** 2] * 3)
    now, twist, chi2, nis, plain = [], [], [], [], []
    for _ in range(150):
        Z, S, names, stamps, X = random_walk_scene(rng, Q)
        f = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, acceleration_psd=Q)
        e = error(f.mean, X)
        now.append(e @ np.linalg.solve(f.covariance, e))
        e = f.twist - TWIST
        twist.append(e @ np.linalg.solve(f.twist_covariance, e))
        chi2.append(f.chi2 / f.dof)
        nis.append([s.nis_mean for s in f.sources])
        g = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps)
        e = error(g.mean, X)
        plain.append(e @ np.linalg.solve(g.covariance, e))
    assert 5.4 <= np.mean(now) <= 6.6 and 5.4 <= np.mean(twist) <= 6.6, (np.mean(now),
                                                                        np.mean(twist))
    assert abs(np.mean(chi2) - 1.0) < 0.03, np.mean(chi2)
    assert np.all(np.abs(np.mean(nis, axis=0) - 6.0) < 0.6), np.mean(nis, axis=0)
    assert np.mean(plain) > 20.0  # what ignoring it claims


def test_zero_acceleration_noise_is_the_constant_twist_model_exactly():
    rng = np.random.default_rng(77)
    Z, S, names, stamps, T = scene(rng, accelerating=True)
    guess = [Source("cam_a", latency=0.03, latency_sigma=0.02), SOURCES[1], SOURCES[2]]
    for kwargs in (dict(), dict(robust=True), dict(sources=guess, time=0.99)):
        kwargs = {"sources": SOURCES, **kwargs}
        f = fusion.fuse(Z, S, names=names, times=stamps, **kwargs)
        g = fusion.fuse(Z, S, names=names, times=stamps, acceleration_psd=np.zeros((6, 6)),
                        **kwargs)
        for a, b in ((f.mean, g.mean), (f.covariance, g.covariance), (f.nis, g.nis),
                     (f.twist_covariance, g.twist_covariance), (f.distances, g.distances)):
            assert np.array_equal(a, b)
        assert f.chi2 == g.chi2 and f.latencies == g.latencies


def test_negligible_acceleration_noise_reproduces_the_independent_fit_nis_included():
    """The correlated path (dense joint covariance, conditional leave-one-out NIS for inliers
    and for rejected measurements) against the block one, where they must agree."""
    rng = np.random.default_rng(78)
    Z, S, names, stamps, T = scene(rng)
    Z = Z.copy()
    bad = [i for i, s in enumerate(names) if s == "cam_a"][-1]
    Z[bad] = dq.mul(Z[bad], lie.se3_exp([0.0, np.pi * 0.9, 0, 0.05, 0, 0]))
    guess = [Source("cam_a", latency=0.03, latency_sigma=0.02), SOURCES[1], SOURCES[2]]
    for sources in (SOURCES, guess):
        f = fusion.fuse(Z, S, names=names, sources=sources, times=stamps, robust=True)
        g = fusion.fuse(Z, S, names=names, sources=sources, times=stamps, robust=True,
                        acceleration_psd=1e-16 * np.eye(6))
        assert [r.index for r in f.rejected] == [r.index for r in g.rejected] == [bad]
        assert np.linalg.norm(error(f.mean, g.mean)) < 1e-9
        np.testing.assert_allclose(g.covariance, f.covariance, rtol=1e-6, atol=1e-18)
        np.testing.assert_allclose(g.nis, f.nis, rtol=1e-6)
        np.testing.assert_allclose(g.distances, f.distances, rtol=1e-6)
        assert g.chi2 == pytest.approx(f.chi2, rel=1e-6)
        for a, b in zip(f.latencies, g.latencies):
            assert a.value == pytest.approx(b.value, abs=1e-9)
            assert a.sigma == pytest.approx(b.sigma, rel=1e-6)


def test_acceleration_noise_with_latency_estimated_and_in_the_tracker():
    rng = np.random.default_rng(79)
    Q = rule_of_thumb(ACCELERATION)
    guess = [Source("cam_a", latency=0.0, latency_sigma=0.1),
             Source("cam_b", latency=0.0, latency_sigma=0.1), SOURCES[2]]
    z = []
    for _ in range(20):
        Z, S, names, stamps, T = scene(rng, accelerating=True)
        f = fusion.fuse(Z, S, names=names, sources=guess, times=stamps, acceleration_psd=Q)
        assert f.status == Status.CONVERGED
        z += [(lat.value - LATENCY) / lat.sigma for lat in f.latencies]
    assert np.all(np.abs(z) < 4.0), z
    T = trajectory(lie.se3_exp(rng.normal(size=6)), True)
    tracker = Tracker(WINDOW, sources=SOURCES, acceleration_psd=Q)
    tracker.add(*stream(rng, T, end=0.5))
    window = tracker.measurements("box")
    f = tracker.estimate("box", time=0.48)
    g = fusion.fuse(np.array([m.pose for m in window]), np.array([m.covariance for m in window]),
                    names=[m.source for m in window], sources=SOURCES,
                    times=[m.time for m in window], time=0.48, acceleration_psd=Q)
    h = fusion.fuse(np.array([m.pose for m in window]), np.array([m.covariance for m in window]),
                    names=[m.source for m in window], sources=SOURCES,
                    times=[m.time for m in window], time=0.48)
    assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)
    assert not np.array_equal(f.covariance, h.covariance)


# ---- input -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, message", [
    (dict(times=[0.0, np.nan]), r"^times\[1\]: contains NaN"),
    (dict(times=[0.0]), r"^times: expected shape \(2\), got \(1,\) for 2 poses"),
    (dict(times=[0.0, 0.1], time="x"), r"^time: expected seconds, got str"),
    (dict(times=[0.0, 0.1], max_skew=-1), r"^max_skew: must be nonnegative"),
    (dict(times=[0.0, 0.1], max_extrapolation=np.inf), r"^max_extrapolation: must be finite"),
    (dict(times=[0.0, 0.1], twist_covariance=np.eye(3)),
     r"^twist_covariance: expected shape \(6, 6\)"),
    (dict(times=[0.0, 0.1], twist_covariance=[[1, 2], [3]]),
     r"^twist_covariance: expected shape \(6, 6\), got a ragged sequence"),
    (dict(times=[0.0, 0.1], twist_covariance=-np.eye(6)),
     r"^twist_covariance: not positive definite"),
    (dict(times=[0.0, 0.1], acceleration_psd=np.eye(3)),
     r"^acceleration_psd: expected shape \(6, 6\)"),
    (dict(times=[0.0, 0.1], acceleration_psd=np.full((6, 6), np.nan)),
     r"^acceleration_psd: contains NaN"),
    (dict(times=[0.0, 0.1], acceleration_psd=np.triu(np.ones((6, 6)))),
     r"^acceleration_psd: not symmetric"),
    (dict(times=[0.0, 0.1], acceleration_psd=-np.eye(6)),
     r"^acceleration_psd: not positive semidefinite"),
    (dict(acceleration_psd=np.eye(6)), r"^acceleration_psd: needs the measurements' times"),
    (dict(time=1.0), r"^time: needs the measurements' times"),
    (dict(max_skew=1.0), r"^max_skew: needs the measurements' times"),
    (dict(times=[0.0, 0.1], names=["a", "b"], sources=[Source("a", latency=np.nan)]),
     r"^sources\[0\]\.latency: must be finite"),
    (dict(times=[0.0, 0.1], names=["a", "b"], sources=[Source("a", latency_sigma=0.0)]),
     r"^sources\[0\]\.latency_sigma: must be positive"),
])
def test_bad_time_options_name_the_argument(kwargs, message):
    Z = lie.se3_exp(np.array([[0.0] * 6, [0.01] * 6]))
    with pytest.raises(ValueError, match=message):
        fusion.fuse(Z, **kwargs)


# ---- the per-body sliding window -----------------------------------------------------------------
def stream(rng, T, end=1.0, start=0.0, body="box", accelerating=False):
    """Measurements as they arrive (by stamp) from two cameras and the arm."""
    out = []
    for name, rate, C, latency in (("cam_a", CAMERA_RATE, CAM_A, LATENCY),
                                   ("cam_b", CAMERA_RATE, CAM_B, LATENCY),
                                   ("arm", ARM_RATE, ARM, ARM_LATENCY)):
        stamps = np.arange(start + rng.uniform(0, 1 / rate), end, 1 / rate)
        Z = sample(rng, T, C, stamps - latency)
        out += [Measurement(name, body, float(t), z, C) for t, z in zip(stamps, Z)]
    return sorted(out, key=lambda m: m.time)


def test_tracker_window_estimates_like_fuse_and_stays_bounded():
    rng = np.random.default_rng(72)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    tracker = Tracker(WINDOW, sources=SOURCES)
    errors, sizes_seen = [], []
    for k, m in enumerate(stream(rng, T)):
        tracker.add(m)
        sizes_seen.append(len(tracker.measurements("box")))
        if k % 50 == 49:
            f = tracker.estimate("box")
            errors.append(sizes(error(f.mean, T(f.time)[0]))[1])
    assert max(sizes_seen) <= WINDOW * (ARM_RATE + 2 * CAMERA_RATE) + 4
    assert np.median(errors) < 1e-3
    window = tracker.measurements("box")
    f = tracker.estimate("box", time=0.98)
    g = fusion.fuse(np.array([m.pose for m in window]), np.array([m.covariance for m in window]),
                    names=[m.source for m in window], sources=SOURCES,
                    times=[m.time for m in window], time=0.98)
    assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)
    assert tracker.bodies == ("box",)


def test_tracker_time_going_back_beyond_the_window_is_an_error_naming_the_measurement():
    tracker = Tracker(WINDOW, sources=SOURCES)
    X = lie.se3_exp(np.full(6, 0.1))
    tracker.add(Measurement("arm", "box", 1.0, X), Measurement("arm", "box", 0.9, X))
    assert len(tracker.measurements("box")) == 2  # out of order within the window is fine
    late = Measurement("cam_a", "box", 0.83, X)  # taken at 0.79, 0.216 s before 1.006
    with pytest.raises(ValueError, match=r"^measurements\[1\] \(body 'box', source 'cam_a', "
                                         r"time 0.83\): taken at 0.7[89].* "
                                         r"beyond the window 0.2 s"):
        tracker.add(Measurement("arm", "box", 1.01, X), late)
    assert len(tracker.measurements("box")) == 2  # all or none
    tracker.add(Measurement("arm", "other", 0.0, X))  # another body has its own clock


def test_tracker_bodies_are_independent():
    rng = np.random.default_rng(73)
    Ta = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    Tb = trajectory(lie.se3_exp(rng.normal(size=6)), True)
    a = stream(rng, Ta, body="a")
    b = stream(rng, Tb, body="b", end=1.3)
    both, alone = Tracker(WINDOW, sources=SOURCES), Tracker(WINDOW, sources=SOURCES)
    for m in sorted(a + b, key=lambda m: m.time):
        both.add(m)
    alone.add(*a)
    assert set(both.bodies) == {"a", "b"}
    fa, ga = both.estimate("a"), alone.estimate("a")
    assert fa.time == ga.time and np.array_equal(fa.mean, ga.mean)
    assert np.array_equal(fa.covariance, ga.covariance)
    fb = both.estimate("b")
    assert fb.time > fa.time + 0.25
    assert sizes(error(fb.mean, Tb(fb.time)[0]))[1] < 3e-3
    both.remove("b")
    with pytest.raises(ValueError, match=r"^body: no measurements of 'b'"):
        both.estimate("b")


@pytest.mark.parametrize("measurement, message", [
    (Measurement("arm", "box", np.nan, np.eye(1, 8)[0]), r"^measurements\[0\]\.time: must be "
                                                          r"finite"),
    (Measurement("arm", "box", 0.0, np.ones(8)), r"^measurements\[0\]\.pose: "),
    (Measurement("arm", "", 0.0, np.eye(1, 8)[0]), r"^measurements\[0\]\.body: empty"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], np.eye(3)),
     r"^measurements\[0\]\.covariance: expected shape \(6, 6\)"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], -np.eye(6)),
     r"^measurements\[0\]\.covariance: not positive definite"),
    (Measurement("arm", "box", 0.0, np.eye(1, 8)[0], weight=0.0),
     r"^measurements\[0\]\.weight: must be positive"),
    (Measurement("arm", "box", 0.0, [[1, 0], [0]]),
     r"^measurements\[0\]\.pose: expected shape \(8,\), got a ragged sequence"),
    ("pose", r"^measurements\[0\]: expected a Measurement, got str"),
])
def test_tracker_bad_measurement_names_it(measurement, message):
    tracker = Tracker(WINDOW)
    with pytest.raises(ValueError, match=message):
        tracker.add(measurement)
    assert tracker.bodies == ()


def test_tracker_bad_options_fail_at_construction():
    with pytest.raises(ValueError, match=r"^window: must be positive"):
        Tracker(0.0)
    with pytest.raises(ValueError, match=r"^max_skew: must be nonnegative"):
        Tracker(0.2, max_skew=-1.0)
    with pytest.raises(ValueError, match=r"^acceleration_psd: not positive semidefinite"):
        Tracker(0.2, acceleration_psd=-np.eye(6))
    with pytest.raises(ValueError, match=r"^sources\[0\]: a source needs a name"):
        Tracker(0.2, sources=[Source("")])


def test_tracker_ingest_keeps_the_valid_measurements_and_names_the_others():
    rng = np.random.default_rng(74)
    T = trajectory(lie.se3_exp(rng.normal(size=6)), False)
    ms = stream(rng, T, end=0.3)
    tracker, alone = Tracker(WINDOW, sources=SOURCES), Tracker(WINDOW, sources=SOURCES)
    head, batch = ms[:-10], ms[-10:]
    tracker.add(*head)
    alone.add(*head)
    poses = np.array([m.pose for m in batch])
    covs = np.array([m.covariance for m in batch])
    times = np.array([m.time for m in batch])
    names = [m.source for m in batch]
    bodies = ["box"] * 10
    poses[1, 0] = np.nan
    covs[4, 1, 1] = -1.0
    times[6] = np.inf
    times[8] -= 0.5
    bodies[9] = ""
    errors = tracker.ingest(bodies, names, times, poses, covs, ids=np.arange(100, 110))
    assert [k for k, _ in errors] == [1, 4, 6, 8, 9]
    text = [str(e) for _, e in errors]
    assert text[0] == "measurements[1].pose: contains NaN or infinity"
    assert text[1] == "measurements[4].covariance: not positive definite"
    assert text[2] == "measurements[6].time: must be finite, got inf"
    assert text[3].startswith("measurements[8] (body 'box'") and "beyond the window" in text[3]
    assert text[4] == "measurements[9].body: empty (every measurement names its body)"
    good = [0, 2, 3, 5, 7]
    alone.add(*[batch[k] for k in good])
    w = tracker.window_of("box")
    assert w.ids[-5:].tolist() == [100 + k for k in good]
    f, g = tracker.estimate("box"), alone.estimate("box")
    assert np.array_equal(f.mean, g.mean) and np.array_equal(f.covariance, g.covariance)


def test_one_instant_at_its_time_is_the_static_fusion_bit_for_bit():
    rng = np.random.default_rng(75)
    X = lie.se3_exp(rng.normal(size=6))
    S = np.array([CAM_A, CAM_B, ARM, ARM])
    Z = np.concatenate([sample(rng, lambda t: X[None], C, np.zeros(1)) for C in S])
    Z[3] = dq.mul(Z[3], lie.se3_exp(np.array([0, 2.5, 0, 0.2, 0, 0])))   # a flipped one
    names = ["cam_a", "cam_b", "arm", "arm"]
    for robust in (False, True):
        static = fusion.fuse(Z, S, names=names, robust=robust)
        f = fusion.fuse(Z, S, names=names, robust=robust, times=[1.5] * 4, time=1.5,
                        max_skew=0.01, sources=[Source("arm", latency_sigma=0.01)])
        assert np.array_equal(f.mean, static.mean)
        assert np.array_equal(f.covariance, static.covariance)
        assert np.array_equal(f.nis, static.nis) and f.rejected == static.rejected
        assert f.time == 1.5 and f.dropped == () and f.twist is None
        assert f.latencies == (fusion.Latency("arm", 0.0, 0.01, 0.0, 0.01),)
    prior = np.diag([0.5 ** 2] * 3 + [0.2 ** 2] * 3)
    f = fusion.fuse(Z[:3], S[:3], times=[1.5] * 3, twist_covariance=prior)
    assert np.array_equal(f.mean, fusion.fuse(Z[:3], S[:3]).mean)
    assert np.array_equal(f.twist, np.zeros(6)) and np.array_equal(f.twist_covariance, prior)
