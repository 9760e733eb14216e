"""The fusion benchmark's scene generator: its conclusions rest on the ground truth being what the
measurements' covariances say and on the injected outliers being the gross errors it names."""
import numpy as np
import pytest

from service import dq, lie
from tests.bench import bench_fusion as bench


def test_clean_measurements_follow_their_covariances():
    """X = Z Exp(xi), xi ~ N(0, S): per source, the whitened errors have identity covariance
    (so the NEES of every source is 6) and zero mean."""
    ts = bench.trials(seed=5, n=600, fraction=0.0)
    white = {}
    for tr in ts:
        assert not tr.outlier.any() and np.array_equal(tr.Z, tr.clean)
        assert set(tr.kinds) == {""}
        e = lie.se3_log(dq.mul(dq.conj(tr.Z), tr.X))
        for name, s, x in zip(tr.names, tr.S, e):
            white.setdefault(name, []).append(np.linalg.solve(np.linalg.cholesky(s), x))
    assert set(white) == set(bench.CAMERAS) | {bench.ARM}
    for name, w in white.items():
        w = np.array(w)
        k = len(w)
        assert k >= 200
        # 6 sigma bounds on the sample mean and covariance of k standard normal vectors
        assert np.abs(w.mean(axis=0)).max() < 6 / np.sqrt(k), name
        assert np.abs(np.cov(w.T) - np.eye(6)).max() < 6 * np.sqrt(2 / k), name


def test_sources_differ_and_are_anisotropic_and_correlated():
    profs = bench.profiles()
    for p in profs:
        s = np.sqrt(np.diag(p.cov))
        corr = p.cov / np.outer(s, s)
        assert np.abs(corr - np.eye(6)).max() > 0.1, p.name  # correlated
        np.linalg.cholesky(p.cov)
    for p in profs[:len(bench.CAMERAS)]:
        s = np.sqrt(np.diag(p.cov))
        assert s[5] > 3 * s[3] and s[0] > 3 * s[2], p.name  # depth and tilt poor
    views = [p.R_world[:, 2] for p in profs if p.R_world is not None]
    assert all(abs(a @ b) < 0.9 for i, a in enumerate(views) for b in views[i + 1:])
    tr = bench.trials(seed=6, n=3, fraction=0.0)
    assert [len(t.names) for t in tr] == [3, 4, 5]  # 2, 3, 4 cameras and the arm


@pytest.mark.parametrize("fraction", [0.1, 0.2])
def test_outliers_are_the_fraction_the_kind_and_gross(fraction):
    ts = bench.trials(seed=7, n=800, fraction=fraction)
    clean = bench.trials(seed=7, n=800, fraction=0.0)
    n_out = n_meas = 0
    for tr, ref in zip(ts, clean):
        # the same bodies and noise as the outlier-free run; only the outliers differ
        assert np.array_equal(tr.X, ref.X) and np.array_equal(tr.clean, ref.clean)
        n_meas += len(tr.names)
        n_out += int(tr.outlier.sum())
        assert tr.outlier.sum() <= np.ceil(fraction * len(tr.names))  # never a majority
        assert np.array_equal(tr.Z[~tr.outlier], tr.clean[~tr.outlier])
        off = bench.sigmas_off(tr.Z, tr.X, tr.S)
        for i in np.flatnonzero(tr.outlier):
            kind, name = tr.kinds[i], tr.names[i]
            assert (kind == "stale arm") == (name == bench.ARM)
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
            assert off[i] > bench.GROSS, (kind, off[i])
        assert (off[~tr.outlier] < 8).all()  # the clean ones are not gross by accident
    assert n_out / n_meas == pytest.approx(fraction, abs=0.02)


def test_errors_and_nees_measure_what_they_say():
    X = dq.from_pose([1.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.3])
    Y = dq.mul(X, lie.se3_exp([0.0, 0.0, np.deg2rad(3.0), 0.0, 0.0, 0.0]))
    Y = dq.mul(dq.from_pose([1.0, 0.0, 0.0, 0.0], [0.004, 0.0, 0.0]), Y)
    rot, trans = bench.errors(Y, X)
    assert rot == pytest.approx(3.0) and trans == pytest.approx(4.0)
    assert bench.errors(-Y, X) == pytest.approx((rot, trans))  # q and -q are one pose
    xi = np.array([0.01, -0.02, 0.005, 0.001, 0.002, -0.003])
    P = np.diag([1e-4, 2e-4, 1e-4, 1e-6, 4e-6, 1e-6])
    Xt = dq.mul(X, lie.se3_exp(xi))
    assert bench.nees(X, P, Xt) == pytest.approx(xi @ np.linalg.solve(P, xi))
