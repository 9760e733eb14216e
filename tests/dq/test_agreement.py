"""dqpose.dq against tests/reference.py (an independent SE(3) implementation on 4x4 matrices) on
random poses, to 1e-12 relative to the translation scale; DIB is the Karcher mean; pytransform3d
agrees."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq
from tests import reference as ref
from tests.conftest import random_dqs, random_quaternions
from tests.dq._poses import (
    PI,
    SCALES,
    TOL,
    N,
    assert_dq_close,
    assert_matrices_close,
    assert_poses_close,
    clustered_sets,
    dlb_definition,
    dq_error,
    random_signs,
    tscale,
    twists_near,
    unit_axes,
)

# ---- agreement with the reference on random poses ------------------------------------------

@pytest.mark.parametrize("scale", SCALES)
def test_to_matrix_matches_reference(rng, scale):
    q = random_dqs(rng, N, scale)
    T = ref.matrix_from_dq(q)
    assert_matrices_close(dq.to_matrix(q), T)
    assert_matrices_close(dq.to_matrix(-q), T)


@pytest.mark.parametrize("scale", SCALES)
def test_from_matrix_matches_reference(rng, scale):
    q = random_dqs(rng, N, scale)
    T = ref.matrix_from_dq(q)
    out = dq.from_matrix(T)
    assert_dq_close(out, ref.dq_from_matrix(T))
    assert np.all(out[..., 0] >= 0.0), "from_matrix documents a scalar part >= 0"
    assert_matrices_close(dq.to_matrix(out), T)


@pytest.mark.parametrize("scale", SCALES)
def test_from_pose_and_to_pose_match_reference(rng, scale):
    r = random_quaternions(rng, N)
    t = scale * rng.normal(size=(N, 3))
    q = dq.from_pose(r, t)
    assert_dq_close(q, ref.dq_from_rt(r, t))
    r2, t2 = dq.to_pose(q)
    # to_pose keeps the sign of its input, so the round trip is exact including the sign.
    np.testing.assert_allclose(r2, r, rtol=0, atol=TOL)
    assert np.max(np.abs(t2 - t).max(axis=-1) / np.maximum(1, np.linalg.norm(t, axis=-1))) <= TOL
    r3, t3 = dq.to_pose(-q)
    np.testing.assert_allclose(r3, -r, rtol=0, atol=TOL)
    np.testing.assert_allclose(t3, t2, rtol=0, atol=TOL * scale)


@pytest.mark.parametrize("scale", SCALES)
def test_transform_matches_matrix(rng, scale):
    q = random_dqs(rng, N, scale)
    p = scale * rng.normal(size=(N, 3))
    T = ref.matrix_from_dq(q)
    expected = np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]
    s = np.maximum(1, np.linalg.norm(p, axis=-1) + np.linalg.norm(T[:, :3, 3], axis=-1))
    for sign in (1, -1):
        err = np.max(np.abs(dq.transform(sign * q, p) - expected).max(axis=-1) / s)
        assert err <= TOL


@pytest.mark.parametrize("scale", SCALES)
def test_mul_is_matrix_composition(rng, scale):
    a, b = random_dqs(rng, N, scale), random_dqs(rng, N, scale)
    Ta, Tb = ref.matrix_from_dq(a), ref.matrix_from_dq(b)
    assert_poses_close(dq.mul(a, b), Ta @ Tb, tscale(Ta, Tb))
    assert_poses_close(dq.mul(-a, b), Ta @ Tb, tscale(Ta, Tb))


@pytest.mark.parametrize("scale", SCALES)
def test_conj_is_matrix_inverse(rng, scale):
    a = random_dqs(rng, N, scale)
    Ta = ref.matrix_from_dq(a)
    assert_poses_close(dq.conj(a), ref.inv(Ta), tscale(Ta))
    assert dq.inv is dq.conj


@pytest.mark.parametrize("scale", SCALES)
def test_log_is_half_matrix_log(rng, scale):
    a = random_dqs(rng, N, scale)
    T = ref.matrix_from_dq(a)
    half_twist = 0.5 * ref.log(T)
    s = tscale(T)[:, None]
    for sign in (1, -1):
        assert np.max(np.abs(dq.log(sign * a) - half_twist) / s) <= TOL


@pytest.mark.parametrize("scale", SCALES)
def test_exp_is_matrix_exp(rng, scale):
    # Rotation angles up to 3 pi: exp needs no principal branch.
    x = 0.5 * twists_near(rng, N, 3 * PI, scale)
    T = ref.exp(2.0 * x)
    assert_poses_close(dq.exp(x), T)


@pytest.mark.parametrize("scale", SCALES)
def test_power_matches_matrix_power(rng, scale):
    a = random_dqs(rng, N, scale)
    tau = rng.uniform(-2.0, 3.0, N)
    P = ref.power(ref.matrix_from_dq(a), tau)
    assert_poses_close(dq.power(a, tau), P, tscale(P, ref.matrix_from_dq(a)))
    assert_poses_close(dq.power(-a, tau), P, tscale(P, ref.matrix_from_dq(a)))


@pytest.mark.parametrize("scale", SCALES)
def test_sclerp_matches_reference_on_pairs(rng, scale):
    a, b = random_dqs(rng, N, scale), random_dqs(rng, N, scale)
    tau = rng.uniform(-1.0, 2.0, N)  # outside [0, 1] too: the screw extrapolates
    Ta, Tb = ref.matrix_from_dq(a), ref.matrix_from_dq(b)
    S = ref.sclerp(Ta, Tb, tau)
    s = tscale(S, Ta, Tb)
    for sa in (1, -1):
        for sb in (1, -1):
            assert_poses_close(dq.sclerp(sa * a, sb * b, tau), S, s)


def test_sclerp_one_pair_many_tau(rng):
    a, b = random_dqs(rng, (), 2.0), random_dqs(rng, (), 2.0)
    tau = np.concatenate([[0.0, 1.0], rng.uniform(-3.0, 4.0, N)])
    out = dq.sclerp(a, b, tau)
    assert out.shape == (N + 2, 8)
    Ta, Tb = ref.matrix_from_dq(a), ref.matrix_from_dq(b)
    S = ref.sclerp(Ta, Tb, tau)
    assert_poses_close(out, S, tscale(S, Ta[None], Tb[None]))
    # Each tau of the batch agrees with the same call on its own (the cached screw is right).
    for i in (0, 1, 7, N):
        np.testing.assert_array_equal(dq.sclerp(a, b, tau[i]), out[i])


def test_sclerp_endpoints_are_reproduced(rng):
    a, b = random_dqs(rng, N, 10.0), random_dqs(rng, N, 10.0)
    assert_dq_close(dq.sclerp(a, b, 0.0), a)
    assert_dq_close(dq.sclerp(a, b, 1.0), b)
    assert_dq_close(dq.sclerp(a, -b, 1.0), b)
    assert_dq_close(dq.sclerp(a, a, 0.5), a)


def test_dlb_matches_definition(rng):
    for n in (1, 2, 3, 7):
        Q = random_dqs(rng, (400, n), 3.0) * random_signs(rng, (400, n))
        w = rng.uniform(0.0, 1.0, (400, n)) + 1e-3
        out = dq.dlb(Q, w)
        assert out.shape == (400, 8)
        assert_dq_close(out, dlb_definition(Q, w))
        # default weights are equal
        assert_dq_close(dq.dlb(Q), dlb_definition(Q, np.ones(n)))


@pytest.mark.parametrize("n", [2, 3, 6])
def test_dib_is_the_karcher_mean(rng, n):
    batch = 300
    Q = clustered_sets(rng, batch, n, 1.2, scale=5.0)
    w = rng.uniform(0.05, 1.0, (batch, n))
    mean, iters, res = dq.dib(Q, w, tol=1e-14, return_info=True)
    M, _, step = ref.karcher_mean(ref.matrix_from_dq(Q), w, tol=1e-14)
    assert step < 1e-13
    assert_poses_close(mean, M, tscale(M))
    assert np.all(res < 1e-14) and np.all(iters >= 1)


def test_dib_of_two_poses_is_sclerp(rng):
    a, b = random_dqs(rng, N, 2.0), random_dqs(rng, N, 2.0)
    w = rng.uniform(0.01, 1.0, (N, 2))
    tau = w[:, 1] / w.sum(axis=-1)
    mean = dq.dib(np.stack([a, b], axis=-2), w, tol=1e-14)
    assert_dq_close(mean, dq.sclerp(a, b, tau))
    S = ref.sclerp(ref.matrix_from_dq(a), ref.matrix_from_dq(b), tau)
    assert_poses_close(mean, S)
    assert_dq_close(dq.blend(np.stack([a, b], axis=-2), w, "sclerp"), dq.sclerp(a, b, tau))


def test_dib_info_reports_its_residual(rng):
    Q = clustered_sets(rng, 200, 4, 1.0, scale=2.0)
    w = rng.uniform(0.1, 1.0, (200, 4))
    for max_iter in (0, 1, 2, 100):
        mean, iters, res = dq.dib(Q, w, tol=1e-12, max_iter=max_iter, return_info=True)
        assert iters.shape == res.shape == (200,) and iters.dtype == np.int64
        assert np.all((iters >= 0) & (iters <= max_iter))
        converged = iters < max_iter
        assert np.all(res[converged] < 1e-12)
        assert np.all((res >= 1e-12) | converged | (iters == max_iter))
        # The residual is the norm of the weighted mean half-twist at the returned mean.
        Tm = ref.matrix_from_dq(mean)
        wn = w / w.sum(axis=-1, keepdims=True)
        xi = 0.5 * np.einsum("bn,bnk->bk", wn,
                             ref.log(ref.inv(Tm)[:, None] @ ref.matrix_from_dq(Q)))
        np.testing.assert_allclose(res, np.linalg.norm(xi, axis=-1), rtol=1e-6, atol=1e-14)
        if max_iter == 0:
            assert_dq_close(mean, dq.dlb(Q, w))
    assert np.all(iters < 100), "DIB must converge on clustered sets"


@pytest.mark.parametrize("scale", SCALES)
def test_screw_matches_matrix_log(rng, scale):
    theta = rng.uniform(0.05, PI - 0.05, N)
    r = np.concatenate([np.cos(theta / 2)[:, None],
                        unit_axes(rng, N) * np.sin(theta / 2)[:, None]], -1)
    q = ref.dq_from_rt(r * random_signs(rng, N), scale * rng.normal(size=(N, 3)))
    T = ref.matrix_from_dq(q)
    tw = ref.log(T)
    th = np.linalg.norm(tw[:, :3], axis=-1)
    axis = tw[:, :3] / th[:, None]
    d = np.sum(axis * tw[:, 3:], axis=-1)
    moment = (tw[:, 3:] - d[:, None] * axis) / th[:, None]
    s = screw = dq.screw(q)
    assert s.theta.shape == s.d.shape == (N,) and s.axis.shape == s.moment.shape == (N, 3)
    sc = tscale(T)
    assert np.max(np.abs(screw.theta - th)) <= TOL
    assert np.max(np.abs(screw.axis - axis)) <= TOL
    assert np.max(np.abs(screw.d - d) / sc) <= TOL
    assert np.max(np.abs(screw.moment - moment).max(axis=-1) / (sc / th)) <= TOL
    # The parameters rebuild the pose: twist (theta l, d l + theta m).
    rebuilt = ref.exp(np.concatenate([screw.theta[:, None] * screw.axis,
                                      screw.d[:, None] * screw.axis
                                      + screw.theta[:, None] * screw.moment], -1))
    assert_matrices_close(rebuilt, T, sc)


def test_pytransform3d_cross_check(rng):
    """A second, external opinion on the reference and the core (pytransform3d's own tolerances
    are looser, so 1e-9 here)."""
    pt = pytest.importorskip("pytransform3d.transformations")
    for _ in range(50):
        a, b = random_dqs(rng, (), 2.0), random_dqs(rng, (), 2.0)
        T = ref.matrix_from_dq(a)
        np.testing.assert_allclose(pt.exponential_coordinates_from_transform(T), ref.log(T),
                                   atol=1e-9)
        tau = rng.uniform(0, 1)
        theirs = pt.dual_quaternion_sclerp(a, b, tau)
        assert dq_error(dq.sclerp(a, b, tau), theirs) <= 1e-9
        np.testing.assert_allclose(dq.to_matrix(a), pt.transform_from_dual_quaternion(a),
                                   atol=1e-12)
