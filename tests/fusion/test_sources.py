"""dqpose.fusion.sources: frames fuse to the world pose, covariances transported exactly (GTSAM,
Monte Carlo)."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source
from tests.fusion._scenes import (
    error,
    gtsam_fuse,
    measure,
    nees,
    random_cov,
    random_pose,
)

gtsam = pytest.importorskip("gtsam")


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
