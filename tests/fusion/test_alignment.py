"""dqpose.fusion.alignment: fusion over time at the query time (accuracy, NEES, latency), skew and
extrapolation, the robust gate over time, bad time options."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source, Status
from tests.fusion._moving import (
    ARM,
    ARM_LATENCY,
    CAM_A,
    CAM_B,
    LATENCY,
    SOURCES,
    TWIST,
    error,
    naive,
    sample,
    scene,
    sizes,
    subset,
    trajectory,
)


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
