"""dqpose.fusion.validation and chi2: bad input names the argument and index; chi-square quantiles
against SciPy."""
import numpy as np
import pytest

from dqpose import fusion
from dqpose.fusion import Source
from tests.fusion._scenes import (
    random_cov,
    random_pose,
)

gtsam = pytest.importorskip("gtsam")


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
