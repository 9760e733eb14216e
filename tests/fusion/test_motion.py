"""dqpose.fusion.motion: the constant-twist model's Gauss-Newton Jacobian and twist."""
import numpy as np

from dqpose import dq, fusion, lie
from dqpose.fusion import Status
from dqpose.fusion.motion import Model, motion_evaluate, motion_jacobian
from tests.fusion._moving import (
    TWIST,
    error,
    scene,
    trajectory,
)


# ---- the Gauss-Newton model ----------------------------------------------------------------------
def test_the_jacobian_is_exact_for_pose_twist_and_latency():
    rng = np.random.default_rng(70)
    Z, S, names, stamps, T = scene(rng)
    Z, S, names, stamps = Z[::9], S[::9], names[::9], stamps[::9]
    model = Model(stamp=stamps - 1.0, latency=np.zeros(len(names)),
                          slot=np.array([{"cam_a": 0, "arm": 1}.get(s, -1) for s in names]),
                          prior=np.array([0.03, 0.01]), prior_w=np.array([1e4, 1e4]),
                          twist=True, twist_w=None)
    W = np.linalg.inv(S)
    X, V, ell = T(1.0)[0], TWIST + 0.1, np.array([0.035, 0.002])
    dt, r, _ = motion_evaluate(X, V, ell, Z, W, model)
    G = motion_jacobian(V, dt, r, model)
    h = 1e-6
    for k in range(model.dim):
        d = np.zeros(model.dim)
        d[k] = h
        def residual(sign):
            Xs = dq.mul(X, lie.se3_exp(sign * d[:6]))
            return motion_evaluate(Xs, V + sign * d[6:12], ell + sign * d[12:], Z, W,
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
