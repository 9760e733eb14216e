"""dqpose.fusion.process_noise: acceleration as process noise (honest NEES, NIS and chi2; its
limits)."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source, Status, Tracker
from dqpose.fusion.process_noise import kernel
from tests.fusion._moving import (
    ACCELERATION,
    ARM_LATENCY,
    LATENCY,
    SOURCES,
    TWIST,
    WINDOW,
    error,
    scene,
    sizes,
    stream,
    trajectory,
)


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
    w, U = np.linalg.eigh(kernel(dt))  # singular at dt = 0
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
    tracker.ingest(stream(rng, T, end=0.5), all_or_none=True)
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
