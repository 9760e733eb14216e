"""Static fusion scenes: random covariances and poses, measurements in the convention, errors, NEES,
and GTSAM's answer to compare with."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Status
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
