"""dqpose.fusion with uncertain extrinsics (Source.extrinsic_covariance): the joint fit against
GTSAM's graph (a prior on each extrinsic, a BetweenFactorPose3 per measurement), the checks, the
fit over time and the tracker, and sources without one untouched."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Measurement, Source, Status, Tracker

gtsam = pytest.importorskip("gtsam")
from tests import _gtsam  # noqa: E402  (needs gtsam)
from tests.fusion._scenes import error, random_cov, random_pose  # noqa: E402


def ext_cov(rng, scale=1.0):
    return random_cov(rng, (0.1 * scale, 0.5 * scale), (0.3e-3 * scale, 2e-3 * scale))


def scene(rng, with_cov=(True, False, True, False), per_source=(2, 3, 1, 2), offset=(2,)):
    """Sources with random extrinsics (some uncertain, ``with_cov``), ``per_source``
    measurements each of one body, drawn with the extrinsics' true errors shared by a source's
    measurements. Returns (X, sources, names, Z, S)."""
    X = random_pose(rng, 0.5)
    sources, names, Z, S = [], [], [], []
    for k, (uncertain, m) in enumerate(zip(with_cov, per_source)):
        E = random_pose(rng, 0.7)
        off = random_pose(rng, 0.1) if k in offset else None
        SE = ext_cov(rng) if uncertain else None
        E_true = dq.mul(E, lie.se3_exp(rng.multivariate_normal(np.zeros(6), SE))) if uncertain \
            else E
        sources.append(Source(f"s{k}", E, off, extrinsic_covariance=SE))
        Zt = dq.mul(dq.conj(E_true), X)
        if off is not None:
            Zt = dq.mul(Zt, dq.conj(off))
        for _ in range(m):
            c = random_cov(rng)
            Z.append(dq.mul(Zt, lie.se3_exp(-rng.multivariate_normal(np.zeros(6), c))))
            S.append(c)
            names.append(f"s{k}")
    return X, sources, names, np.array(Z), np.array(S)


def gtsam_graph(sources, names, Z, S):
    """X is key 0; an uncertain source's extrinsic key 1 + its index."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    table = {s.name: (k, s) for k, s in enumerate(sources)}
    P3 = gtsam.Pose3

    def noise(c):
        return gtsam.noiseModel.Gaussian.Covariance(c, False)

    for k, s in enumerate(sources):
        if s.extrinsic_covariance is not None:
            graph.add(gtsam.PriorFactorPose3(1 + k, P3(dq.to_matrix(s.extrinsic)),
                                             noise(s.extrinsic_covariance)))
            values.insert(1 + k, P3(dq.to_matrix(s.extrinsic)))
    for z, c, name in zip(Z, S, names):
        k, s = table[name]
        zo, co = z, c
        if s.body_offset is not None:
            zo, co = dq.mul(z, s.body_offset), lie.cov_compose(c, s.body_offset, None)
        if s.extrinsic_covariance is not None:
            # BetweenFactor(E, X, m): error Log(m⁻¹ E⁻¹ X), X = E·(Z O) measured
            graph.add(gtsam.BetweenFactorPose3(1 + k, 0, P3(dq.to_matrix(zo)), noise(co)))
        else:
            graph.add(gtsam.PriorFactorPose3(0, P3(dq.to_matrix(dq.mul(s.extrinsic, zo))),
                                             noise(co)))
    first = table[names[0]][1]
    start = dq.mul(first.extrinsic, Z[0] if first.body_offset is None
                   else dq.mul(Z[0], first.body_offset))
    values.insert(0, P3(dq.to_matrix(start)))
    result = _gtsam.lm(graph, values)
    for _ in range(200):
        delta = graph.linearize(result).optimize()
        result = result.retract(delta)
        if max(np.linalg.norm(delta.at(key)) for key in values.keys()) < 1e-13:
            break
    return _gtsam.pose(result), _gtsam.marginal(graph, result), 2.0 * graph.error(result)


@pytest.mark.parametrize("seed", range(6))
def test_equals_gtsam_joint_graph(seed):
    rng = np.random.default_rng(300 + seed)
    X, sources, names, Z, S = scene(rng)
    f = fusion.fuse(Z, S, names=names, sources=sources)
    Xg, Pg, chi2 = gtsam_graph(sources, names, Z, S)
    assert f.status == Status.CONVERGED
    assert np.linalg.norm(error(f.mean, Xg)) < 1e-10
    assert np.abs(f.covariance - Pg).max() <= 1e-8 * np.abs(Pg).max()
    assert f.chi2 == pytest.approx(chi2, rel=1e-8)


def test_extrinsic_covariance_grows_the_covariance_by_the_shared_error():
    """One source, many measurements: its shared extrinsic error does not average out, so the
    fused covariance tends to the extrinsic's (carried to the body) and not to zero."""
    rng = np.random.default_rng(7)
    X = random_pose(rng)
    E = random_pose(rng)
    SE = ext_cov(rng)
    c = random_cov(rng)
    Zf = dq.mul(dq.conj(E), X)
    Z = np.repeat(Zf[None], 50, axis=0)
    S = np.repeat(c[None], 50, axis=0)
    plain = fusion.fuse(Z, S, names=["c"] * 50, sources=[Source("c", E)])
    shared = fusion.fuse(Z, S, names=["c"] * 50, sources=[Source("c", E,
                                                                  extrinsic_covariance=SE)])
    A = lie.adjoint(dq.conj(Zf))
    expected = A @ SE @ A.T + c / 50
    np.testing.assert_allclose(plain.covariance, c / 50, rtol=1e-9)
    np.testing.assert_allclose(shared.covariance, expected, rtol=1e-6, atol=1e-15)


def test_sources_without_it_unchanged_bit_for_bit():
    rng = np.random.default_rng(8)
    X, sources, names, Z, S = scene(rng, with_cov=(False, False, False, False))
    a = fusion.fuse(Z, S, names=names, sources=sources)
    _, c_sources, *_ = scene(np.random.default_rng(8), with_cov=(False, False, False, False))
    # a source with a covariance that measures nothing here changes nothing either
    extra = Source("idle", random_pose(rng), extrinsic_covariance=ext_cov(rng))
    b = fusion.fuse(Z, S, names=names, sources=list(c_sources) + [extra])
    assert a.mean.tobytes() == b.mean.tobytes()
    assert a.covariance.tobytes() == b.covariance.tobytes()


@pytest.mark.parametrize("bad, problem", [
    (np.eye(5), "expected shape (6, 6)"),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1) * 0.1, "not symmetric"),
    (-np.eye(6), "not positive definite"),
    (np.diag([1, 1, 1, 1, 1, 0.0]), "not positive definite"),
])
def test_bad_extrinsic_covariance_named(bad, problem):
    with pytest.raises(ValueError, match=r"^sources\[1\]\.extrinsic_covariance: ") as e:
        fusion.fuse(np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]]), names=["b"],
                    sources=[Source("a"), Source("b", extrinsic_covariance=bad)])
    assert problem in str(e.value)


def test_over_time_one_instant_is_the_static_joint_fit():
    rng = np.random.default_rng(9)
    X, sources, names, Z, S = scene(rng)
    static = fusion.fuse(Z, S, names=names, sources=sources)
    timed = fusion.fuse(Z, S, names=names, sources=sources, times=np.full(len(Z), 3.0))
    assert static.mean.tobytes() == timed.mean.tobytes()
    assert static.covariance.tobytes() == timed.covariance.tobytes()


def moving(rng, sources, names, n_times=4, V=None):
    """Measurements of a body moving with twist V at times 0, 0.02, ...: each source measures at
    each time, through its true extrinsic (one error per source, shared)."""
    V = np.array([0.1, -0.2, 0.05, 0.1, 0.02, -0.05]) if V is None else V
    X0 = random_pose(rng, 0.5)
    truth = {s.name: (s.extrinsic if s.extrinsic_covariance is None else dq.mul(
        s.extrinsic, lie.se3_exp(rng.multivariate_normal(np.zeros(6), s.extrinsic_covariance))))
        for s in sources}
    Z, S, N, T = [], [], [], []
    for t in np.arange(n_times) * 0.02:
        Xt = dq.mul(X0, lie.se3_exp(t * V))
        for s in sources:
            c = random_cov(rng)
            Z.append(dq.mul(dq.mul(dq.conj(truth[s.name]), Xt),
                            lie.se3_exp(-rng.multivariate_normal(np.zeros(6), c))))
            S.append(c)
            N.append(s.name)
            T.append(t)
    return np.array(Z), np.array(S), N, np.array(T)


def test_over_time_tends_to_the_exact_extrinsic_when_its_covariance_vanishes():
    rng = np.random.default_rng(10)
    E = [random_pose(rng) for _ in range(3)]
    exact = [Source(f"s{k}", e) for k, e in enumerate(E)]
    Z, S, N, T = moving(rng, exact, None)
    tiny = [Source(f"s{k}", e, extrinsic_covariance=np.eye(6) * 1e-22 if k != 1 else None)
            for k, e in enumerate(E)]
    a = fusion.fuse(Z, S, names=N, sources=exact, times=T)
    b = fusion.fuse(Z, S, names=N, sources=tiny, times=T)
    assert np.linalg.norm(error(a.mean, b.mean)) < 1e-9
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-6, atol=1e-18)
    np.testing.assert_allclose(b.twist, a.twist, atol=1e-8)


def test_over_time_shared_error_in_the_covariance():
    """Over time, every measurement of a single uncertain camera shares its error: the fused
    covariance is at least the extrinsic's carried to the body."""
    rng = np.random.default_rng(11)
    E = random_pose(rng)
    SE = ext_cov(rng)
    src = [Source("cam", E, extrinsic_covariance=SE)]
    Z, S, N, T = moving(rng, src, None, n_times=20)
    f = fusion.fuse(Z, S, names=N, sources=src, times=T)
    A = lie.adjoint(dq.mul(dq.conj(f.mean), E))
    floor = A @ SE @ A.T
    assert np.linalg.eigvalsh(f.covariance - floor).min() > -1e-12 * np.abs(floor).max()
    plain = fusion.fuse(Z, S, names=N, sources=[Source("cam", E)], times=T)
    assert np.trace(f.covariance) > 2 * np.trace(plain.covariance)


def test_tracker_estimate_is_fuse_with_extrinsic_covariance():
    rng = np.random.default_rng(12)
    E = [random_pose(rng) for _ in range(2)]
    src = [Source("a", E[0], extrinsic_covariance=ext_cov(rng)), Source("b", E[1])]
    Z, S, N, T = moving(rng, src, None)
    tr = Tracker(1.0, sources=src)
    tr.ingest([Measurement(n, "box", float(t), z, c) for n, t, z, c in zip(N, T, Z, S)],
              all_or_none=True)
    a = tr.estimate("box")
    b = fusion.fuse(Z, S, names=N, sources=src, times=T)
    assert a.mean.tobytes() == b.mean.tobytes()
    assert a.covariance.tobytes() == b.covariance.tobytes()


def test_robust_rejects_an_outlier_with_extrinsic_covariance():
    rng = np.random.default_rng(13)
    X, sources, names, Z, S = scene(rng, per_source=(3, 3, 3, 3))
    Z = Z.copy()
    Z[4] = dq.mul(Z[4], lie.se3_exp(np.array([0.3, 0, 0, 0.1, 0, 0])))
    f = fusion.fuse(Z, S, names=names, sources=sources, robust=True)
    assert [r.index for r in f.rejected] == [4]
    keep = np.arange(len(Z)) != 4
    g = fusion.fuse(Z[keep], S[keep], names=[n for n, k in zip(names, keep) if k],
                    sources=sources)
    assert np.linalg.norm(error(f.mean, g.mean)) < 1e-12


def test_acceleration_psd_with_extrinsic_covariance_refused():
    rng = np.random.default_rng(14)
    src = [Source("a", random_pose(rng), extrinsic_covariance=ext_cov(rng))]
    Z, S, N, T = moving(rng, src, None)
    with pytest.raises(ValueError, match="^acceleration_psd: not supported"):
        fusion.fuse(Z, S, names=N, sources=src, times=T, acceleration_psd=np.eye(6) * 1e-4)


def test_leave_one_out_nis_is_chi2_6_with_shared_errors():
    """Each measurement against the joint fit of the others (the extrinsics' priors kept): its
    NIS has mean 6 when the extrinsics' errors are drawn as their covariances say."""
    rng = np.random.default_rng(15)
    vals = []
    for _ in range(300):
        X, sources, names, Z, S = scene(rng)
        f = fusion.fuse(Z, S, names=names, sources=sources)
        vals.extend(f.nis[f.tested].tolist())
    assert len(vals) == 2400
    assert 5.6 <= np.mean(vals) <= 6.4


def test_leaving_out_the_nis_changes_nothing_else():
    """The joint fit without its leave-one-out NIS (what World.relative and a Lookup ask for)
    gives the same state, covariance and residuals to the last bit as with them (Fuse's)."""
    from dqpose.fusion.alignment import time_setup
    from dqpose.fusion.extrinsics import motion_fit_ext
    rng = np.random.default_rng(16)
    src = [Source("a", random_pose(rng), latency=0.01, latency_sigma=0.005,
                  extrinsic_covariance=ext_cov(rng)), Source("b", random_pose(rng))]
    Z, S, N, T = moving(rng, src, None, n_times=6)
    table = {s.name: s for s in src}
    Zw, Sw = fusion.sources.to_world(Z, S, N, table)
    u = time_setup(Zw, N, table, T, None, None, None, None, None)
    inlier = np.ones(len(Z), bool)
    start = fusion.fuse(Z, S, names=N, sources=src, times=T)
    args = (Zw, Sw, u.model, u.model.extrinsics, inlier, start.mean, np.array(start.twist),
            np.array([lat.value for lat in start.latencies]), 1e-12, 100)
    with_nis, without = motion_fit_ext(*args, nis=True), motion_fit_ext(*args, nis=False)
    for k in ("mean", "V", "ell", "H", "P", "r", "cost"):
        assert getattr(with_nis, k).tobytes() == getattr(without, k).tobytes(), k
    assert without.nis is None and with_nis.nis is not None
    assert with_nis.tested is not None and with_nis.tested.all() and (with_nis.nis > 0).all()
