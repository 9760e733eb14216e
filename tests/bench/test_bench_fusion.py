"""The fusion benchmark's scene generator: its conclusions rest on the ground truth being what the
measurements' covariances say and on the injected outliers being the gross errors it names."""
import numpy as np
import pytest

from dqpose import dq, lie
from tests.bench import fusion_moving as fm
from tests.bench import fusion_scenes as scenes


def test_clean_measurements_follow_their_covariances():
    """X = Z Exp(xi), xi ~ N(0, S): per source, the whitened errors have identity covariance
    (so the NEES of every source is 6) and zero mean."""
    ts = scenes.trials(seed=5, n=600, fraction=0.0)
    white = {}
    for tr in ts:
        assert not tr.outlier.any() and np.array_equal(tr.Z, tr.clean)
        assert set(tr.kinds) == {""}
        e = lie.se3_log(dq.mul(dq.conj(tr.Z), tr.X))
        for name, s, x in zip(tr.names, tr.S, e):
            white.setdefault(name, []).append(np.linalg.solve(np.linalg.cholesky(s), x))
    assert set(white) == set(scenes.CAMERAS) | {scenes.ARM}
    for name, w in white.items():
        w = np.array(w)
        k = len(w)
        assert k >= 200
        # 6 sigma bounds on the sample mean and covariance of k standard normal vectors
        assert np.abs(w.mean(axis=0)).max() < 6 / np.sqrt(k), name
        assert np.abs(np.cov(w.T) - np.eye(6)).max() < 6 * np.sqrt(2 / k), name


def test_sources_differ_and_are_anisotropic_and_correlated():
    profs = scenes.profiles()
    for p in profs:
        s = np.sqrt(np.diag(p.cov))
        corr = p.cov / np.outer(s, s)
        assert np.abs(corr - np.eye(6)).max() > 0.1, p.name  # correlated
        np.linalg.cholesky(p.cov)
    for p in profs[:len(scenes.CAMERAS)]:
        s = np.sqrt(np.diag(p.cov))
        assert s[5] > 3 * s[3] and s[0] > 3 * s[2], p.name  # depth and tilt poor
    views = [p.R_world[:, 2] for p in profs if p.R_world is not None]
    assert all(abs(a @ b) < 0.9 for i, a in enumerate(views) for b in views[i + 1:])
    tr = scenes.trials(seed=6, n=3, fraction=0.0)
    assert [len(t.names) for t in tr] == [3, 4, 5]  # 2, 3, 4 cameras and the arm


@pytest.mark.parametrize("fraction", [0.1, 0.2])
def test_outliers_are_the_fraction_the_kind_and_gross(fraction):
    ts = scenes.trials(seed=7, n=800, fraction=fraction)
    clean = scenes.trials(seed=7, n=800, fraction=0.0)
    n_out = n_meas = 0
    for tr, ref in zip(ts, clean):
        # the same bodies and noise as the outlier-free run; only the outliers differ
        assert np.array_equal(tr.X, ref.X) and np.array_equal(tr.clean, ref.clean)
        n_meas += len(tr.names)
        n_out += int(tr.outlier.sum())
        assert tr.outlier.sum() <= np.ceil(fraction * len(tr.names))  # never a majority
        assert np.array_equal(tr.Z[~tr.outlier], tr.clean[~tr.outlier])
        off = scenes.sigmas_off(tr.Z, tr.X, tr.S)
        for i in np.flatnonzero(tr.outlier):
            kind, name = tr.kinds[i], tr.names[i]
            assert (kind == "stale arm") == (name == scenes.ARM)
            rel = lie.se3_log(dq.mul(dq.conj(tr.clean[i]), tr.Z[i]))
            angle = np.linalg.norm(rel[:3])
            if kind == "flipped PnP":  # 180 deg about a horizontal world axis, same position
                R = dq.to_matrix(tr.clean[i])[:3, :3]
                axis = R @ rel[:3] / angle
                assert angle == pytest.approx(np.pi, abs=1e-9)
                assert abs(axis[2]) < 1e-9
                assert np.allclose(dq.to_pose(tr.Z[i])[1], dq.to_pose(tr.clean[i])[1],
                                   atol=1e-12)
            elif kind == "stale arm":
                dt = np.linalg.norm(dq.to_pose(tr.Z[i])[1] - dq.to_pose(tr.clean[i])[1])
                assert np.deg2rad(5) - 1e-9 <= angle <= np.deg2rad(30) + 1e-9
                assert 0.02 - 1e-9 <= dt <= 0.10 + 1e-9
            else:
                assert kind == "wrong marker"
                d = np.abs(dq.to_pose(tr.Z[i])[1] - dq.to_pose(tr.X)[1])
                assert d.max() <= 0.2
            assert off[i] > scenes.GROSS, (kind, off[i])
        assert (off[~tr.outlier] < 8).all()  # the clean ones are not gross by accident
    assert n_out / n_meas == pytest.approx(fraction, abs=0.02)


def test_errors_and_nees_measure_what_they_say():
    X = dq.from_pose([1.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.3])
    Y = dq.mul(X, lie.se3_exp([0.0, 0.0, np.deg2rad(3.0), 0.0, 0.0, 0.0]))
    Y = dq.mul(dq.from_pose([1.0, 0.0, 0.0, 0.0], [0.004, 0.0, 0.0]), Y)
    rot, trans = scenes.errors(Y, X)
    assert rot == pytest.approx(3.0) and trans == pytest.approx(4.0)
    assert scenes.errors(-Y, X) == pytest.approx((rot, trans))  # q and -q are one pose
    xi = np.array([0.01, -0.02, 0.005, 0.001, 0.002, -0.003])
    P = np.diag([1e-4, 2e-4, 1e-4, 1e-6, 4e-6, 1e-6])
    Xt = dq.mul(X, lie.se3_exp(xi))
    assert scenes.nees(X, P, Xt) == pytest.approx(xi @ np.linalg.solve(P, xi))


# ---- the moving body -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def moving():
    return fm.moving_scene(seed=3, seconds=2.0)


def test_moving_path_is_smooth_realistic_and_accelerating(moving):
    w, v, alpha, acc = moving.path.motion(np.arange(0.0, 2.0, 0.01))
    assert 0.2 <= np.median(v) <= 0.5 and v.max() < 0.6
    assert 30 <= np.degrees(np.median(w)) <= 90 and np.degrees(w.max()) < 120
    assert np.median(acc) > 0.1 and np.degrees(np.median(alpha)) > 10  # never a constant twist
    # smooth: the pose 1 ms apart moves by speed × 1 ms, nothing jumps
    T = moving.path(np.arange(0.0, 2.0, 0.001))
    step = lie.se3_log(dq.mul(dq.conj(T[:-1]), T[1:]))
    assert np.linalg.norm(step[:, 3:], axis=1).max() < 0.6e-3
    assert np.linalg.norm(step[:, :3], axis=1).max() < np.radians(120) * 1e-3


def test_moving_streams_have_their_rates_latencies_and_stamps(moving):
    names = [s.name for s in moving.streams]
    assert names == list(fm.MOVING_CAMERAS) + [scenes.ARM]
    for s in moving.streams:
        rate, latency = ((fm.ARM_RATE, fm.ARM_LATENCY) if s.name == scenes.ARM else
                         (fm.CAMERA_RATE, fm.CAMERA_LATENCY))
        assert s.rate == rate and s.latency == latency
        np.testing.assert_allclose(np.diff(s.capture), 1 / rate, rtol=1e-9)
        assert 0 <= s.capture[0] < 1 / rate and s.capture[-1] > 2.0 - 1 / rate - 1e-9
        np.testing.assert_allclose(s.stamp - s.capture, latency, atol=1e-12)
    assert np.diff(moving.queries) == pytest.approx(1 / fm.QUERY_RATE)
    # the cameras' frames are not in step
    assert len({round(s.capture[0], 6) for s in moving.streams}) == len(moving.streams)


def test_moving_measurements_follow_their_covariances_at_the_capture_time(moving):
    white = []
    for s in moving.streams:
        e = lie.se3_log(dq.mul(dq.conj(s.Z), moving.path(s.capture)))
        w = np.linalg.solve(np.linalg.cholesky(s.S), e[..., None])[..., 0]
        k = len(w)
        assert np.abs(w.mean(axis=0)).max() < 6 / np.sqrt(k), s.name
        assert np.abs(np.cov(w.T) - np.eye(6)).max() < 6 * np.sqrt(2 / k), s.name
        white.append(w)
        # against the stamp (latency not subtracted) the error is far beyond the noise
        e = lie.se3_log(dq.mul(dq.conj(s.Z), moving.path(s.stamp)))
        w = np.linalg.solve(np.linalg.cholesky(s.S), e[..., None])[..., 0]
        assert np.median(np.einsum("ni,ni->n", w, w)) > 100, s.name
    arm = moving.streams[-1]
    assert np.sqrt(np.diag(arm.S[0]))[3:].max() < 0.3e-3  # a precise arm


def test_moving_window_holds_what_was_stamped_in_it(moving):
    t_q = 1.2345
    Z, S, names, stamps = moving.window(t_q)
    assert np.all(stamps <= t_q) and np.all(stamps > t_q - fm.FUSION_WINDOW)
    for s in moving.streams:
        inside = (s.stamp <= t_q) & (s.stamp > t_q - fm.FUSION_WINDOW)
        assert names.count(s.name) == inside.sum()
    assert len(names) == len(Z) == len(S)


def test_single_source_interpolates_and_extrapolates_along_the_screw():
    """On a constant-twist path without noise, ScLERP between the bracketing samples and the
    extrapolation of the newest two are exact; only what was stamped by the query is used."""
    V = np.array([0.3, -0.2, 0.5, 0.2, 0.1, -0.15])
    X0 = lie.se3_exp(np.array([0.1, 0.2, -0.3, 0.05, 0.0, 0.3]))
    capture = np.arange(0.0, 1.0, 1 / 30)
    Z = dq.mul(X0, lie.se3_exp(capture[:, None] * V))
    s = fm.Stream("cam", 30.0, 0.04, capture, capture + 0.04, Z, np.zeros((capture.size, 6, 6)))
    for t_q, time in ((0.5, 0.41), (0.5, 0.49), (0.5, 0.3)):
        got = fm.single(s, t_q, time)
        want = dq.mul(X0, lie.se3_exp(time * V))
        assert np.linalg.norm(lie.se3_log(dq.mul(dq.conj(got), want))) < 1e-12
    # at t_q = 0.5 the newest known frame was taken at 0.4333: time 0.49 is an extrapolation;
    # a frame stamped after t_q would have made it an interpolation, and must not be used
    noisy = s.Z.copy()
    noisy[14:] = dq.mul(noisy[14:], lie.se3_exp(np.full(6, 0.1)))  # captured at 0.4667 on
    s2 = fm.Stream("cam", 30.0, 0.04, capture, capture + 0.04, noisy, s.S)
    assert np.array_equal(fm.single(s2, 0.5, 0.49), fm.single(s, 0.5, 0.49))


def test_acceleration_rule_is_the_paths_rms_acceleration_over_the_window(moving):
    Q = fm.acceleration_rule(moving.path, 2.0)
    _, _, alpha, acc = moving.path.motion(np.arange(0.0, 2.0, 0.01))
    assert Q[0, 0] == pytest.approx(fm.FUSION_WINDOW * np.mean(alpha ** 2) / 3)
    assert Q[3, 3] == pytest.approx(fm.FUSION_WINDOW * np.mean(acc ** 2) / 3)
    assert np.count_nonzero(Q - np.diag(np.diag(Q))) == 0
