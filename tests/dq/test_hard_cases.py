"""dqpose.dq where the closed forms change branch or degenerate (angles near 0 and pi, pure
translations, antipodal pairs, signs, near-unit input) and Lin's projection near ties."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq
from tests import reference as ref
from tests.conftest import random_dqs
from tests.dq._poses import (
    HARD_ANGLES,
    PI,
    TOL,
    assert_dq_close,
    assert_matrices_close,
    assert_poses_close,
    clustered_sets,
    quats_at_angle,
    random_signs,
    tscale,
)

# ---- hard cases -----------------------------------------------------------------------------

@pytest.mark.parametrize("theta", HARD_ANGLES)
@pytest.mark.parametrize("scale", [0.0, 1.0, 1e3])
def test_hard_angles(rng, theta, scale):
    n = 500
    r = quats_at_angle(rng, theta, n)
    q = ref.dq_from_rt(r, scale * rng.normal(size=(n, 3)))
    T = ref.matrix_from_dq(q)
    s = tscale(T)
    # conversions, both ways and both signs
    assert_matrices_close(dq.to_matrix(q), T, s)
    assert_matrices_close(dq.to_matrix(-q), T, s)
    assert_poses_close(dq.from_matrix(T), T, s)
    # log: the angle is theta, and exp(log) is the pose again from either sign
    for sign in (1, -1):
        lq = dq.log(sign * q)
        np.testing.assert_allclose(2 * np.linalg.norm(lq[:, :3], axis=-1), theta, rtol=0,
                                   atol=1e-15)
        assert_matrices_close(ref.exp(2 * lq), T, s)
        assert_poses_close(dq.exp(lq), T, s)
    tau = np.concatenate([[0.0, 1.0, 0.5, -1.0, 2.0], rng.uniform(-2, 3, n - 5)])
    # Within a few ulp of pi the matrix no longer tells the two screws apart: treat it as pi.
    unique = theta <= PI - 1e-12
    if unique:
        assert np.max(np.abs(dq.log(q) - 0.5 * ref.log(T)) / s[:, None]) <= TOL
        P = ref.power(T, tau)
    else:
        # at pi both screws are shortest; power follows the log the core chose
        P = ref.exp(tau[:, None] * 2 * dq.log(q))
    assert_poses_close(dq.power(q, tau), P, tscale(P, T))
    assert_dq_close(dq.power(q, 1.0), q)
    assert_dq_close(dq.power(q, 0.0), dq.identity((n,)))
    # ScLERP from a random pose c to c q: the relative motion has the hard angle.
    c = random_dqs(rng, n, max(scale, 1.0))
    Tc = ref.matrix_from_dq(c)
    cq = dq.mul(c, q)
    if unique:
        S = ref.sclerp(Tc, Tc @ T, tau)
        for sb in (1, -1):
            assert_poses_close(dq.sclerp(c, sb * cq, tau), S, tscale(S, Tc, T))
    for sb in (1, -1):
        assert_dq_close(dq.sclerp(c, sb * cq, 0.0), c)
        assert_dq_close(dq.sclerp(c, sb * cq, 1.0), cq)


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-160, 1e-12, 1e-9])
def test_screw_of_pure_and_nearly_pure_translations(rng, theta):
    n = 200
    t = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1))
    q = ref.dq_from_rt(quats_at_angle(rng, theta, n), t)
    s = dq.screw(q)
    np.testing.assert_allclose(s.theta, theta, rtol=0, atol=1e-15)
    assert np.all(np.isfinite(s.moment))
    # Whatever branch, the parameters rebuild the pose.
    rebuilt = ref.exp(np.concatenate([s.theta[:, None] * s.axis,
                                      s.d[:, None] * s.axis + s.theta[:, None] * s.moment], -1))
    assert_matrices_close(rebuilt, ref.matrix_from_dq(q))
    if theta == 0.0:
        tn = np.linalg.norm(t, axis=-1)
        np.testing.assert_allclose(s.d, tn, rtol=1e-15)
        np.testing.assert_allclose(s.axis, t / tn[:, None], rtol=0, atol=TOL)
        assert np.all(s.moment == 0.0)
    ident = dq.screw(dq.identity())
    assert ident.theta == 0 and ident.d == 0 and not ident.axis.any() and not ident.moment.any()


@pytest.mark.parametrize("gap", [1e-3, 1e-6, 1e-9, 1e-12])
def test_sclerp_antipodal_pairs(rng, gap):
    """Relative rotation just short of pi: the short way is unique and the sign of b is
    irrelevant."""
    n = 500
    a = random_dqs(rng, n, 1e3)
    rel = ref.dq_from_rt(quats_at_angle(rng, PI - gap, n), rng.normal(size=(n, 3)))
    b = dq.mul(a, rel)
    tau = rng.uniform(-0.5, 1.5, n)
    Ta, Tb = ref.matrix_from_dq(a), ref.matrix_from_dq(b)
    S = ref.sclerp(Ta, Tb, tau)
    for sb in (1, -1):
        out = dq.sclerp(a, sb * b, tau)
        assert_poses_close(out, S, tscale(S, Ta, Tb))
        # the rotation from a grows linearly to pi - gap at tau = 1
        rel_t = dq.screw(dq.mul(dq.conj(a), out)).theta
        angle = np.abs(tau) * (PI - gap) % (2 * PI)
        np.testing.assert_allclose(rel_t, np.minimum(angle, 2 * PI - angle), rtol=0, atol=1e-12)


def test_blends_ignore_the_sign_of_their_inputs(rng):
    Q = clustered_sets(rng, 300, 4, 2.0, scale=10.0)
    w = rng.uniform(0.1, 1.0, (300, 4))
    flipped = Q * random_signs(rng, (300, 4))
    for f in (dq.dlb, dq.dib, dq.logblend, dq.dec):
        assert_dq_close(f(flipped, w), f(Q, w), tol=1e-11)
    np.testing.assert_allclose(dq.lin(flipped, w), dq.lin(Q, w), atol=1e-11)


def test_near_unit_inputs_are_normalised(rng):
    q = random_dqs(rng, 100, 5.0)
    for k in (1 + 5e-7, 1 - 5e-7):
        scaled = q * k
        np.testing.assert_allclose(dq.log(scaled), dq.log(q), atol=1e-12)
        r, t = dq.to_pose(scaled)
        np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, rtol=0, atol=1e-15)
        np.testing.assert_allclose(t, dq.to_pose(q)[1], atol=1e-12)
        M = dq.to_matrix(scaled)
        np.testing.assert_allclose(M[:, :3, :3] @ np.swapaxes(M[:, :3, :3], 1, 2),
                                   np.broadcast_to(np.eye(3), (100, 3, 3)), atol=1e-15)
        np.testing.assert_allclose(dq.from_pose(r * k, t), q, atol=1e-12)
    # a dual part slightly off orthogonal is projected back onto the rigid motions
    skew = q.copy()
    skew[:, 4:] += 1e-8 * q[:, :4]
    np.testing.assert_allclose(dq.to_matrix(skew), dq.to_matrix(q), atol=1e-15)
    # normalize accepts any non-zero real part and makes the result exactly unit
    big = q * rng.uniform(0.1, 10, (100, 1))
    big[:, 4:] += rng.normal(size=(100, 1)) * q[:, :4]
    u = dq.normalize(big)
    np.testing.assert_allclose(np.linalg.norm(u[:, :4], axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.sum(u[:, :4] * u[:, 4:], axis=-1), 0.0, atol=1e-14)
    assert_dq_close(u, q)


# ---- Lin's projection (blend.c: the top eigenvector of Bar-Itzhack's 4x4 matrix, by Jacobi) -----

def svd_nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to M (..., 3, 3) in the Frobenius norm: the SVD with det correction."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(U.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def fit(R: np.ndarray, M: np.ndarray) -> np.ndarray:
    """trace(R^T M), which the nearest rotation maximises."""
    return np.einsum("...ij,...ij->...", R, M)


@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_lin_blend_is_the_nearest_rigid_motion(rng, n):
    Q = random_dqs(rng, (3000, n), 3.0)     # uniform rotations: far apart, some det(M) < 0
    w = rng.uniform(0.0, 1.0, (3000, n))
    w[:, 0] += 1e-3
    M = dq.lin(Q, w)
    out = dq.blend(Q, w, method="lin")
    T = dq.to_matrix(out)
    R, want = T[..., :3, :3], svd_nearest_rotation(M[..., :3, :3])
    np.testing.assert_allclose(np.linalg.det(R), 1.0, rtol=0, atol=1e-14)
    assert_matrices_close(T[..., :3, 3:], M[..., :3, 3:], tscale(M))
    np.testing.assert_allclose(fit(R, M[..., :3, :3]), fit(want, M[..., :3, :3]), rtol=0,
                               atol=1e-13)
    # where the answer is unique enough: the eigengap of K is 2 (s2 + sign(det M) s3)
    s = np.linalg.svd(M[..., :3, :3], compute_uv=False)
    gap = 2 * (s[:, 1] + np.sign(np.linalg.det(M[..., :3, :3])) * s[:, 2])
    ok = gap > 1e-3
    assert ok.mean() > 0.9
    np.testing.assert_allclose(R[ok], want[ok], rtol=0, atol=1e-12)
    assert out[:, 0].min() >= 0.0            # canonical sign, as from_matrix gives
    if n >= 3:
        assert (np.linalg.det(M[..., :3, :3]) < 0).sum() > 10


# The four rotations diag(1,1,1), diag(1,-1,-1), diag(-1,1,-1), diag(-1,-1,1) span the convex hull
# of SO(3) as U conv{D_k} V^T: blending U D_k V^T with weights beta gives M = U diag(D beta) V^T,
# whose K has the eigenvalues 4 beta_k - 1. So the nearest rotation is U D_k V^T for the largest
# beta_k, and the gap between the two largest weights sets how unique it is.
D4 = np.array([np.diag(d) for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])], float)


@pytest.mark.parametrize("gap", [0.3, 1e-3, 1e-6, 1e-9, 0.0])
def test_lin_projection_near_ties(rng, gap):
    m = 1000
    U, V = ref.rot_exp(rng.normal(size=(m, 3))), ref.rot_exp(rng.normal(size=(m, 3)))
    Rk = U[:, None] @ D4[None] @ np.swapaxes(V, -1, -2)[:, None]          # (m, 4, 3, 3)
    x = rng.uniform(0.34, 0.45, m) if gap < 0.3 else rng.uniform(0.34, 0.35, m)
    rest = 1 - 2 * x - gap
    u = rng.uniform(0, 1, m)
    beta = np.stack([x + gap, x, u * rest, (1 - u) * rest], axis=-1)
    perm = rng.permuted(np.tile(np.arange(4), (m, 1)), axis=1)
    # slot perm[i] holds beta[i]
    beta = np.take_along_axis(beta, np.argsort(perm, axis=1), axis=1)
    first = perm[:, 0]
    Q = ref.dq_from_matrix(ref.make(Rk, rng.normal(size=(m, 4, 3))))
    M = dq.lin(Q, beta)[..., :3, :3]
    R = dq.to_matrix(dq.blend(Q, beta, method="lin"))[..., :3, :3]
    exact = Rk[np.arange(m), first]
    np.testing.assert_allclose(fit(R, M), 4 * beta.max(axis=1) - 1, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(3), R.shape),
                               rtol=0, atol=1e-14)
    assert (np.linalg.det(M) < 0).sum() > m // 10 or gap == 0.3
    if gap > 0:
        # an eigenvector is as accurate as rounding over the eigengap (4 gap); so is the SVD's
        tol = max(1e-12, 1e-14 / gap)
        np.testing.assert_allclose(R, exact, rtol=0, atol=tol)
        np.testing.assert_allclose(svd_nearest_rotation(M), exact, rtol=0, atol=tol)
    # all four weights equal: M = 0, every rotation is as near; still a rotation, no NaN
    Z = dq.blend(Q[:5], np.full((5, 4), 0.25), method="lin")
    assert np.isfinite(Z).all()
    np.testing.assert_allclose(np.linalg.det(dq.to_matrix(Z)[:, :3, :3]), 1.0, atol=1e-14)


def test_the_method_table_is_the_c_enum():
    from dqpose import _dqcore
    assert _dqcore.METHODS == {name.upper(): m.code for name, m in dq.METHODS.items()}
    assert all(m.description and m.label.lower() == name for name, m in dq.METHODS.items())
