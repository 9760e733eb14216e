"""Exactness and bad-input tests of the dual-quaternion core (service/dq.py over service/csrc).

Every numeric result is compared with tests/reference.py, an independent SE(3) implementation on
4x4 matrices, to 1e-12 relative to the translation scale (atol = 1e-12 * max(1, |t|)). Poses are
compared as matrices or as dual quaternions up to sign (q and -q are the same pose).
"""
from __future__ import annotations

import numpy as np
import pytest
import reference as ref
from conftest import random_dqs, random_quaternions
from hypothesis import assume, given
from hypothesis import strategies as st

from dqpose import dq

TOL = 1e-12
N = 5000
PI = np.pi
# Rotation angles where the closed forms change branch or degenerate.
HARD_ANGLES = [0.0, 1e-300, 1e-160, 1e-15, 1e-12, 1e-9, 1e-6, PI - 1e-6, PI - 1e-9,
               PI - 1e-12, PI - 4e-16, PI]


# ---- helpers ------------------------------------------------------------------------------------

def tscale(*Ts: np.ndarray) -> np.ndarray:
    """max(1, |t|) over the given poses (matrices), the scale of the absolute tolerance."""
    s = np.ones(np.broadcast_shapes(*(T.shape[:-2] for T in Ts)))
    for T in Ts:
        s = np.maximum(s, np.linalg.norm(T[..., :3, 3], axis=-1))
    return s


def matrix_error(A: np.ndarray, B: np.ndarray, scale: np.ndarray) -> float:
    return float(np.max(np.abs(A - B).max(axis=(-2, -1)) / scale, initial=0.0))


def assert_matrices_close(A, B, scale=None, tol=TOL):
    scale = tscale(B) if scale is None else scale
    err = matrix_error(A, B, scale)
    assert err <= tol, f"max scaled error {err:.3g} > {tol:g}"


def assert_poses_close(q, T, scale=None, tol=TOL):
    """Dual quaternions ``q`` (any sign) represent the matrices ``T``."""
    assert_matrices_close(ref.matrix_from_dq(q), T, scale, tol)


def align(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """q with each element's sign chosen to match p's real part (q ~ -q)."""
    s = np.where(np.sum(q[..., :4] * p[..., :4], axis=-1) < 0.0, -1.0, 1.0)
    return q * s[..., None]


def dq_error(q: np.ndarray, p: np.ndarray) -> float:
    """Largest difference up to sign, relative to max(1, |t|) of p."""
    scale = np.maximum(1.0, np.linalg.norm(ref.translation_of_dq(p), axis=-1))
    return float(np.max(np.abs(align(q, p) - p).max(axis=-1) / scale, initial=0.0))


def assert_dq_close(q, p, tol=TOL):
    err = dq_error(q, p)
    assert err <= tol, f"max scaled error {err:.3g} > {tol:g}"


def random_signs(rng, shape) -> np.ndarray:
    return np.where(rng.random(shape) < 0.5, -1.0, 1.0)[..., None]


def unit_axes(rng, n) -> np.ndarray:
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def quats_at_angle(rng, theta: float, n: int) -> np.ndarray:
    """Unit quaternions rotating by exactly ``theta`` about random axes, random signs."""
    w = 0.0 if theta == PI else np.cos(0.5 * theta)  # cos(pi/2) is 6e-17, not 0
    r = np.concatenate([np.full((n, 1), w), unit_axes(rng, n) * np.sin(0.5 * theta)], axis=-1)
    return r * random_signs(rng, n)


def twists_near(rng, n, max_angle, scale=1.0) -> np.ndarray:
    """Twists with rotation angle uniform in [0, max_angle] and translation ~ N(0, scale^2)."""
    om = unit_axes(rng, n) * rng.uniform(0.0, max_angle, size=(n, 1))
    return np.concatenate([om, scale * rng.normal(size=(n, 3))], axis=-1)


def dlb_definition(Q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Sum w_i q_i / |.| with every q_i in the hemisphere of the largest weight's pose."""
    w = np.broadcast_to(w / w.sum(axis=-1, keepdims=True), Q.shape[:-1])
    k = np.argmax(w, axis=-1)
    pivot = np.take_along_axis(Q, k[..., None, None], axis=-2)
    sign = np.where(np.sum(Q[..., :4] * pivot[..., :4], axis=-1) < 0.0, -1.0, 1.0)
    s = np.sum((w * sign)[..., None] * Q, axis=-2)
    r, d = s[..., :4], s[..., 4:]
    rr = np.sum(r * r, axis=-1, keepdims=True)
    d = (d - r * np.sum(r * d, axis=-1, keepdims=True) / rr) / np.sqrt(rr)
    return np.concatenate([r / np.sqrt(rr), d], axis=-1)


SCALES = [1.0, 1e3]


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


def clustered_sets(rng, batch, n, spread, scale=1.0):
    """(batch, n, 8) poses within rotation angle ``spread`` of a random centre per set."""
    centre = random_dqs(rng, (batch, 1), scale)
    offsets = dq.exp(0.5 * twists_near(rng, batch * n, spread, 0.5).reshape(batch, n, 6))
    return dq.mul(centre, offsets) * random_signs(rng, (batch, n))


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


# ---- broadcasting -------------------------------------------------------------------------------

def test_broadcasting_of_leading_dimensions(rng):
    a, b = random_dqs(rng, (3, 1)), random_dqs(rng, (1, 4))
    ab = dq.mul(a, b)
    assert ab.shape == (3, 4, 8)
    np.testing.assert_array_equal(ab[2, 3], dq.mul(a[2, 0], b[0, 3]))
    assert dq.mul(a[0, 0], b[0, 0]).shape == (8,)
    assert dq.mul(a[0, 0], random_dqs(rng, 5)).shape == (5, 8)
    tau = rng.uniform(0, 1, (1, 6))
    s = dq.sclerp(a, b[:, :1], tau)
    assert s.shape == (3, 6, 8)
    np.testing.assert_array_equal(s[1, 4], dq.sclerp(a[1, 0], b[0, 0], tau[0, 4]))
    assert dq.sclerp(a[0, 0], b[0, 0], np.linspace(0, 1, 11)).shape == (11, 8)
    assert dq.power(a[0, 0], rng.uniform(0, 1, (2, 3))).shape == (2, 3, 8)
    assert dq.power(a, 0.5).shape == (3, 1, 8)
    assert dq.transform(a[0, 0], rng.normal(size=(7, 3))).shape == (7, 3)
    assert dq.transform(a, rng.normal(size=(4, 3))).shape == (3, 4, 3)
    assert dq.from_pose(random_quaternions(rng, (2, 1)), rng.normal(size=(5, 3))).shape == (2, 5, 8)
    r, t = dq.to_pose(a)
    assert r.shape == (3, 1, 4) and t.shape == (3, 1, 3)
    assert dq.to_matrix(a).shape == (3, 1, 4, 4)
    assert dq.from_matrix(dq.to_matrix(a)).shape == (3, 1, 8)
    assert dq.log(a).shape == (3, 1, 6) and dq.exp(dq.log(a)).shape == (3, 1, 8)
    sc = dq.screw(a)
    assert sc.theta.shape == (3, 1) and sc.axis.shape == (3, 1, 3)
    # empty leading dimensions give empty results, not errors
    assert dq.mul(np.zeros((0, 8)), a[0, 0]).shape == (0, 8)
    assert dq.dlb(np.zeros((0, 3, 8))).shape == (0, 8)
    assert dq.identity((2, 3)).shape == (2, 3, 8)


def test_blend_broadcasting(rng):
    Q = random_dqs(rng, (5, 3))
    w = rng.uniform(0.1, 1.0, 3)
    out = dq.dlb(Q, w)  # one weight vector for every set
    assert out.shape == (5, 8)
    np.testing.assert_array_equal(out[2], dq.dlb(Q[2], w))
    W = rng.uniform(0.1, 1.0, (4, 1, 3))
    out = dq.dib(Q, W)  # (4, 1) x (5,) sets -> (4, 5)
    assert out.shape == (4, 5, 8)
    np.testing.assert_allclose(out[3, 1], dq.dib(Q[1], W[3, 0]), atol=0)
    info = dq.dib(Q, W, return_info=True)
    assert info.iterations.shape == info.residual.shape == (4, 5)
    assert dq.dlb(Q[0]).shape == (8,) and dq.lin(Q).shape == (5, 4, 4)
    for m in dq.METHODS:
        pair = Q[:, :2]
        assert dq.blend(pair, w[:2], method=m).shape == (5, 8)


# ---- property-based invariances -----------------------------------------------------------------

finite = dict(allow_nan=False, allow_infinity=False)
quats = st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))
vec3 = st.lists(st.floats(-100, 100, **finite), min_size=3, max_size=3).map(np.array)
poses = st.builds(ref.dq_from_rt, quats, vec3)
small_poses = st.builds(  # within rotation angle ~1.2 of the identity, so sets have one mean
    lambda x, t: dq.exp(np.concatenate([x, t])),
    st.lists(st.floats(-0.35, 0.35, **finite), min_size=3, max_size=3).map(np.array),
    st.lists(st.floats(-5, 5, **finite), min_size=3, max_size=3).map(np.array))
weights = st.floats(0.05, 1.0, **finite)


def pose_tol(*qs, tol=1e-11):
    return tol * max(1.0, *(np.linalg.norm(ref.translation_of_dq(q)) for q in qs))


@given(poses)
def test_exp_of_log_is_the_pose(q):
    assert dq_error(dq.exp(dq.log(q)), q) <= TOL
    assert dq_error(dq.exp(dq.log(-q)), q) <= TOL


@given(st.lists(st.floats(-PI / 2, PI / 2, **finite), min_size=3, max_size=3),
       st.lists(st.floats(-100, 100, **finite), min_size=3, max_size=3))
def test_log_of_exp_is_the_vector(r, d):
    r = np.array(r)
    assume(np.linalg.norm(r) < PI / 2 - 1e-6)
    x = np.concatenate([r, d])
    np.testing.assert_allclose(dq.log(dq.exp(x)), x, rtol=0, atol=TOL * max(1.0, np.abs(d).max()))


@given(poses)
def test_pose_times_its_conjugate_is_identity(q):
    np.testing.assert_allclose(dq.mul(q, dq.conj(q)), dq.identity(), rtol=0,
                               atol=pose_tol(q, tol=TOL))
    np.testing.assert_allclose(dq.mul(dq.conj(q), q), dq.identity(), rtol=0,
                               atol=pose_tol(q, tol=TOL))


def _well_separated(qs, margin=1e-3):
    """Hemisphere choices are robust: no pair is within ``margin`` of orthogonal real parts."""
    R = np.array([q[:4] for q in qs])
    return np.all(np.abs(R @ R.T) > margin)


@given(st.lists(small_poses, min_size=2, max_size=5), st.data(), poses)
def test_blends_are_bi_invariant(qs, data, r):
    Q = np.array(qs)
    w = np.array(data.draw(st.lists(weights, min_size=len(qs), max_size=len(qs))))
    left, right = dq.mul(r, Q), dq.mul(Q, r)
    for f in (dq.dlb, dq.dib):
        b = f(Q, w)
        assert dq_error(f(left, w), dq.mul(r, b)) <= pose_tol(r, b)
        assert dq_error(f(right, w), dq.mul(b, r)) <= pose_tol(r, b)


@given(poses, poses, poses, st.floats(-1, 2, **finite))
def test_sclerp_is_bi_invariant(a, b, r, tau):
    assume(_well_separated([a, b]))
    s = dq.sclerp(a, b, tau)
    tol = pose_tol(r, a, b, s)
    assert dq_error(dq.sclerp(dq.mul(r, a), dq.mul(r, b), tau), dq.mul(r, s)) <= tol
    assert dq_error(dq.sclerp(dq.mul(a, r), dq.mul(b, r), tau), dq.mul(s, r)) <= tol


@given(st.lists(poses, min_size=2, max_size=5), st.data(), poses)
def test_dlb_is_bi_invariant_for_any_spread(qs, data, r):
    assume(_well_separated(qs))
    Q = np.array(qs)
    w = np.array(data.draw(st.lists(weights, min_size=len(qs), max_size=len(qs))))
    b = dq.dlb(Q, w)
    assert dq_error(dq.dlb(dq.mul(r, Q), w), dq.mul(r, b)) <= pose_tol(r, b, *qs)
    assert dq_error(dq.dlb(dq.mul(Q, r), w), dq.mul(b, r)) <= pose_tol(r, b, *qs)


@given(poses, poses, st.floats(-1, 2, **finite))
def test_sclerp_is_symmetric(a, b, tau):
    assume(_well_separated([a, b]))
    assert dq_error(dq.sclerp(a, b, tau), dq.sclerp(b, a, 1 - tau)) <= pose_tol(a, b)


# ---- bad input ----------------------------------------------------------------------------------

I8 = dq.identity()
GOOD = np.array([0.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0])
GOOD = ref.dq_from_rt(GOOD[:4], [1.0, 2.0, 3.0])
SET = np.stack([GOOD, I8, dq.conj(GOOD)])
W3 = np.array([1.0, 2.0, 3.0])

# (name, function, arguments): every array argument is listed with a valid value.
CALLS = [
    ("mul", dq.mul, dict(a=GOOD, b=GOOD)),
    ("conj", dq.conj, dict(a=GOOD)),
    ("normalize", dq.normalize, dict(a=GOOD)),
    ("log", dq.log, dict(a=GOOD)),
    ("exp", dq.exp, dict(x=dq.log(GOOD))),
    ("power", dq.power, dict(a=GOOD, tau=0.3)),
    ("from_matrix", dq.from_matrix, dict(T=dq.to_matrix(GOOD))),
    ("to_matrix", dq.to_matrix, dict(a=GOOD)),
    ("from_pose", lambda q, t: dq.from_pose(q, t), dict(q=GOOD[:4], t=np.array([1.0, 2.0, 3.0]))),
    ("to_pose", dq.to_pose, dict(a=GOOD)),
    ("transform", dq.transform, dict(a=GOOD, p=np.array([1.0, 2.0, 3.0]))),
    ("screw", dq.screw, dict(a=GOOD)),
    ("sclerp", dq.sclerp, dict(a=GOOD, b=I8, tau=0.3)),
    ("dlb", dq.dlb, dict(dqs=SET, weights=W3)),
    ("dib", dq.dib, dict(dqs=SET, weights=W3)),
    ("lin", dq.lin, dict(dqs=SET, weights=W3)),
    ("dec", dq.dec, dict(dqs=SET, weights=W3)),
    ("logblend", dq.logblend, dict(dqs=SET, weights=W3)),
] + [("blend-" + m, lambda dqs, weights, m=m: dq.blend(dqs, weights, method=m),
      dict(dqs=SET[:2] if m == "sclerp" else SET, weights=W3[:2] if m == "sclerp" else W3))
     for m in dq.METHODS]

POSE_ARGS = [(name, f, kw, arg) for name, f, kw in CALLS for arg in kw
             if arg in ("a", "b", "dqs", "q") and name not in ("mul", "conj", "normalize")]
ALL_ARGS = [(name, f, kw, arg) for name, f, kw in CALLS for arg in kw]


def call(f, kw, **changes):
    return f(**{**kw, **changes})


def batched(value, k: int, bad):
    """A batch of 4 copies of ``value`` with element k replaced by ``bad``. For a set (dqs) the
    bad element is pose k of the set; for weights weight k."""
    v = np.array(value, dtype=float)
    out = np.stack([v] * 4) if v.ndim in (0, 1) else v.copy()
    out[k] = bad
    return out


def index_pattern(arg, kw, k):
    return rf"{arg}\[{k}\]"


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("name,f,kw,arg", ALL_ARGS, ids=[f"{c[0]}-{c[3]}" for c in ALL_ARGS])
def test_non_finite_values_are_rejected(name, f, kw, arg, bad):
    v = np.array(kw[arg], dtype=float)
    k = 1 if arg in ("dqs", "weights") else 2
    if arg in ("dqs",):
        x = v.copy()
        x[k, 3] = bad
    elif arg == "weights":
        x = v.copy()
        x[k] = bad
    elif v.ndim == 0:
        x = batched(v, k, bad)
    else:
        x = np.stack([v] * 4)
        x[(k,) + (0,) * (v.ndim - 1)] = bad
    with pytest.raises(ValueError, match=rf"^{arg}\[{k}\]: contains NaN or infinity"):
        call(f, kw, **{arg: x})


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -1.0, "x"])
@pytest.mark.parametrize("f", [dq.dib, dq.dec, lambda *a, **k: dq.blend(*a, **k, method="dib")])
def test_bad_tolerance_is_rejected(f, bad):
    with pytest.raises(ValueError, match=r"^tol: must be finite and >= 0"):
        f(SET, W3, tol=bad)


@pytest.mark.parametrize("bad,problem", [(-1, "must be within 0..1000000"),
                                         (2_000_000, "must be within 0..1000000"),
                                         (1.5, "must be a whole number"),
                                         (True, "must be a whole number"),
                                         (np.nan, "must be a whole number"),
                                         (np.inf, "must be a whole number"),
                                         (None, "must be a whole number"),
                                         ("x", "must be a whole number")])
@pytest.mark.parametrize("f", [dq.dib, dq.dec, lambda *a, **k: dq.blend(*a, **k, method="dlb")])
def test_bad_max_iter_is_rejected(f, bad, problem):
    with pytest.raises(ValueError, match=rf"^max_iter: {problem}"):
        f(SET, W3, max_iter=bad)


TOL = dq.UNIT_TOL
SUGGESTION = "if it is a rotation, divide it by its norm"


def test_the_unit_tolerance_takes_rounded_input():
    """1e-3: a rotation written with four decimals (0.7071 for cos 45 deg) is within it."""
    assert TOL == 1e-3
    q = np.array([0.7071, 0.0, 0.0, 0.7071])
    np.testing.assert_allclose(dq.from_pose(q, [0.1, 0, 0]),
                               dq.from_pose(q / np.linalg.norm(q), [0.1, 0, 0]), atol=1e-15)


@pytest.mark.parametrize("scale,problem", [
    (1.1, rf"quaternion norm 1.1 is not unit \(off by 0.1, beyond the tolerance 0.001 "
          rf"within which it is normalised\); {SUGGESTION}$"),
    # just outside
    (1 + 1.01 * TOL, r"quaternion norm 1.00101 is not unit \(off by 0.00101, beyond"),
    (1 - 1.01 * TOL, r"quaternion norm 0.99899 is not unit \(off by 0.00101, beyond"),
    (0.9, "quaternion norm 0.9 is not unit"),
    (0.0, "zero quaternion")])
@pytest.mark.parametrize("name,f,kw,arg", POSE_ARGS, ids=[f"{c[0]}-{c[3]}" for c in POSE_ARGS])
def test_non_unit_poses_are_rejected(name, f, kw, arg, scale, problem):
    v = np.array(kw[arg], dtype=float)
    x = v.copy() if arg == "dqs" else np.stack([v] * 3)
    x[1, :4] *= scale
    with pytest.raises(ValueError, match=rf"^{arg}\[1\]: {problem}"):
        call(f, kw, **{arg: x})


@pytest.mark.parametrize("scale", [1 + 0.99 * TOL, 1 - 0.99 * TOL])           # just inside
@pytest.mark.parametrize("name,f,kw,arg", POSE_ARGS, ids=[f"{c[0]}-{c[3]}" for c in POSE_ARGS])
def test_poses_within_the_tolerance_are_normalised(name, f, kw, arg, scale):
    v = np.array(kw[arg], dtype=float)
    x = v.copy() if arg == "dqs" else np.stack([v] * 3)
    exact = call(f, kw, **{arg: x})
    x[1, :4 if arg == "q" else 8] *= scale     # a dual quaternion scaled as a whole stays rigid
    out = call(f, kw, **{arg: x})
    for o, e in zip(out if isinstance(out, tuple) else (out,),
                    exact if isinstance(exact, tuple) else (exact,)):
        np.testing.assert_allclose(o, e, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name,f,kw,arg", [c for c in POSE_ARGS if c[3] != "q"],
                         ids=[f"{c[0]}-{c[3]}" for c in POSE_ARGS if c[3] != "q"])
def test_dual_part_must_be_orthogonal(name, f, kw, arg):
    v = np.array(kw[arg], dtype=float)
    x = v.copy() if arg == "dqs" else np.stack([v] * 3)
    size = max(1.0, np.linalg.norm(x[1, 4:]))     # the tolerance is relative to the dual part
    x[1, 4:] += 1.01 * TOL * size * x[1, :4]       # just outside
    with pytest.raises(ValueError, match=rf"^{arg}\[1\]: dual part is not orthogonal to the "
                                         rf"real part \(<r, d> = .*, tolerance 0.001 of "
                                         rf"max\(\|d\|, 1\)\)"):
        call(f, kw, **{arg: x})
    x[1, 4:] -= 0.02 * TOL * size * x[1, :4]       # just inside: made rigid
    out = call(f, kw, **{arg: x})
    assert all(np.all(np.isfinite(o)) for o in (out if isinstance(out, tuple) else (out,)))


def test_other_methods_reject_non_unit_too():
    with pytest.raises(ValueError, match=r"^a: quaternion norm 2 is not unit"):
        dq.power(2 * GOOD, 0.5)
    with pytest.raises(ValueError, match=r"^a: zero quaternion"):
        dq.normalize(np.zeros(8))
    with pytest.raises(ValueError, match=r"^q\[1\]: zero quaternion"):
        dq.from_pose([[1, 0, 0, 0], [0, 0, 0, 0]], [0, 0, 0])
    with pytest.raises(ValueError, match=r"^q: quaternion norm 1.1 is not unit"):
        dq.from_pose([1.1, 0, 0, 0], [0, 0, 0])


def _matrices():
    T = dq.to_matrix(GOOD)
    scaled = T.copy()
    scaled[:3, :3] *= 1.01
    sheared = T.copy()
    sheared[:3, :3] = sheared[:3, :3] @ np.array([[1, 0.01, 0], [0, 1, 0], [0, 0, 1]])
    reflected = T.copy()
    reflected[:3, 0] *= -1
    bottom = T.copy()
    bottom[3, 1] = 1.01 * TOL
    bottom2 = T.copy()
    bottom2[3, 3] = 2.0
    return [(scaled, r"rotation block is not orthonormal \(\|R\^T R - I\| = 0.0201, beyond the "
                     r"tolerance 0.001 within which it is projected to the nearest rotation\)"),
            (sheared, "rotation block is not orthonormal"),
            (reflected, r"det\(R\) = -1, not 1 \(a reflection\)"),
            (bottom, r"bottom row is not \[0, 0, 0, 1\]"),
            (bottom2, r"bottom row is not \[0, 0, 0, 1\]"),
            (np.zeros((4, 4)), "bottom row")]


@pytest.mark.parametrize("M,problem", _matrices())
def test_non_rigid_matrices_are_rejected(M, problem):
    batch = np.stack([np.eye(4), M, np.eye(4)])
    with pytest.raises(ValueError, match=rf"^T\[1\]: not a rigid transform: {problem}"):
        dq.from_matrix(batch)


def _nearest_rotation(M):
    """The rotation nearest to M's 3x3 block in the Frobenius norm (SVD, det +1)."""
    U, _, Vt = np.linalg.svd(M[:3, :3])
    return U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt


def _off_by(T, e, rng):
    """T with its rotation block stretched along a random axis u, R (I + c u u^T), so that
    max |R^T R - I| = (2c + c^2) max u_i^2 = e; its nearest rotation is R (the polar factor)."""
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    c = np.sqrt(1.0 + e / np.max(u * u)) - 1.0
    M = T.copy()
    M[:3, :3] = T[:3, :3] @ (np.eye(3) + c * np.outer(u, u))
    return M


def test_nearly_rigid_matrices_are_projected_to_the_nearest_rotation(rng):
    T = dq.to_matrix(GOOD)
    for e in (0.99 * TOL, 0.3 * TOL, 1e-9):                       # just inside, and less
        M = _off_by(T, e, rng)
        assert dq_rotation_error(M) == pytest.approx(e, rel=1e-6)
        back = dq.to_matrix(dq.from_matrix(M))
        np.testing.assert_allclose(_nearest_rotation(M), T[:3, :3], atol=1e-13)
        np.testing.assert_allclose(back[:3, :3], T[:3, :3], atol=1e-13)
        np.testing.assert_allclose(back[:3, 3], M[:3, 3], atol=0)
    rounded = np.round(T, 4)                                       # a printed matrix
    np.testing.assert_allclose(dq.to_matrix(dq.from_matrix(rounded))[:3, :3],
                               _nearest_rotation(rounded), atol=1e-13)
    M = _off_by(T, 1.01 * TOL, rng)                                # just outside
    with pytest.raises(ValueError, match=r"^T: not a rigid transform: rotation block is not "
                                         r"orthonormal \(\|R\^T R - I\| = 0.00101, beyond"):
        dq.from_matrix(M)


@pytest.mark.parametrize("f", [dq.dlb, dq.dib, dq.lin, dq.dec, dq.logblend,
                               lambda q, w: dq.blend(q, w, method="log")])
def test_bad_weights_are_rejected(f):
    with pytest.raises(ValueError, match=r"^weights\[1\]: negative weight -2"):
        f(SET, [1.0, -2.0, 1.0])
    with pytest.raises(ValueError, match=r"^weights\[2\]: contains NaN or infinity"):
        f(SET, [1.0, 1.0, np.nan])
    with pytest.raises(ValueError, match=r"^weights: all weights are zero"):
        f(SET, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"^weights\[1\]: all weights are zero"):
        f(SET, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    with pytest.raises(ValueError,
                       match=r"^weights: length 2 does not match the number of poses \(3\)"):
        f(SET, [1.0, 1.0])
    with pytest.raises(ValueError,
                       match=r"^weights: length 4 does not match the number of poses \(3\)"):
        f(SET, [1.0, 1.0, 1.0, 1.0])
    # finite weights stay valid at any magnitude: they are normalised to sum 1
    for w in (W3 / 3 * 1e308, W3 * 1e-320):
        np.testing.assert_allclose(f(SET, w), f(SET, W3), atol=1e-15)


@pytest.mark.parametrize("f,args,pattern", [
    (dq.mul, (np.zeros((3, 7)), GOOD), r"^a: expected shape \(\.\.\., 8\), got \(3, 7\)"),
    (dq.mul, (GOOD, np.zeros(9)), r"^b: expected shape \(\.\.\., 8\), got \(9,\)"),
    (dq.log, (np.float64(1.0),), r"^a: expected shape \(\.\.\., 8\), got \(\)"),
    (dq.exp, (np.zeros(8),), r"^x: expected shape \(\.\.\., 6\), got \(8,\)"),
    (dq.from_matrix, (np.eye(3),), r"^T: expected shape \(\.\.\., 4, 4\), got \(3, 3\)"),
    (dq.from_matrix, (np.zeros(16),), r"^T: expected shape \(\.\.\., 4, 4\), got \(16,\)"),
    (dq.from_pose, ([1, 0, 0], [0, 0, 0]), r"^q: expected shape \(\.\.\., 4\), got \(3,\)"),
    (dq.from_pose, ([1, 0, 0, 0], [0, 0, 0, 0]), r"^t: expected shape \(\.\.\., 3\), got \(4,\)"),
    (dq.transform, (GOOD, [0, 0]), r"^p: expected shape \(\.\.\., 3\), got \(2,\)"),
    (dq.dlb, (GOOD,), r"^dqs: expected shape \(\.\.\., n, 8\), got \(8,\)"),
    (dq.dib, (np.zeros((2, 6)),), r"^dqs: expected shape \(\.\.\., n, 8\), got \(2, 6\)"),
    (dq.to_pose, ([[1, 2]],), r"^a: expected shape"),
    (dq.mul, (np.zeros((3, 8)), np.zeros((4, 8))),
     r"^shape mismatch: b has leading shape \(4,\), which does not broadcast with \(3,\)"),
    (dq.sclerp, (np.tile(I8, (3, 1)), I8, np.zeros(5)),
     r"^shape mismatch: tau has leading shape \(5,\)"),
    (dq.power, (np.tile(I8, (3, 1)), np.zeros((2, 1, 4))), r"^shape mismatch: tau"),
    (dq.transform, (np.tile(I8, (2, 1)), np.zeros((3, 3))), r"^shape mismatch: p"),
    (dq.dlb, (np.tile(I8, (3, 2, 1)), np.ones((4, 2))),
     r"^shape mismatch: weights has leading shape \(4,\)"),
    (dq.dlb, (np.zeros((0, 8)),), r"^dqs: empty set of poses"),
    (dq.dib, (np.zeros((3, 0, 8)), np.zeros(0)), r"^dqs: empty set of poses"),
    (dq.mul, ("abc", GOOD), r"^a: not convertible to a float64 array"),
    (dq.dlb, ([[1, 0, 0, 0], [1, 0]],), r"^dqs: not convertible to a float64 array"),
])
def test_bad_shapes_are_rejected(f, args, pattern):
    with pytest.raises(ValueError, match=pattern):
        f(*args)


NOT_FLOAT = [SET[:2].astype(complex), SET[:2].astype(object), SET[:2].astype(str),
             [[1, 0, 0, 0, 0, 0, 0, 0], [1j, 0, 0, 0, 0, 0, 0, 0]]]


@pytest.mark.parametrize("method", list(dq.METHODS))
def test_non_float_sets_get_one_message_for_every_method(method):
    # one conversion in the core for every method (sclerp once converted twice, unnamed)
    for bad in NOT_FLOAT:
        with pytest.raises(ValueError, match=r"^dqs: not convertible to a float64 array"):
            dq.blend(bad, method=method)
        with pytest.raises(ValueError, match=r"^weights: not convertible to a float64 array"):
            dq.blend(SET[:2], np.array(bad)[:, 0], method=method)
    for bad in NOT_FLOAT[:3]:
        with pytest.raises(ValueError, match=r"^a: not convertible to a float64 array"):
            dq.sclerp(bad[0], SET[1], 0.5)


def test_bad_methods_are_rejected():
    for m in ("foo", "DIB", None, 3, ""):
        with pytest.raises(ValueError,
                           match=r"^method: unknown blending method .*expected one of lin, dec"):
            dq.blend(SET, method=m)
    for n in (1, 3):
        with pytest.raises(ValueError, match=rf"^dqs: sclerp blends exactly 2 poses, got {n}"):
            dq.blend(np.tile(I8, (n, 1)), method="sclerp")


@pytest.mark.parametrize("f,args,pattern", [
    (dq.exp, (np.full(6, 1e300),), r"^x: result is not finite"),
    (dq.exp, (np.array([0.0, 0, 1e300, 0, 0, 0]),), r"^x: result is not finite"),
    (dq.mul, (np.full(8, 1e300), np.full(8, 1e300)), r"^a: result is not finite"),
    (dq.power, (GOOD, 1e300), r"^tau: result is not finite"),
    (dq.sclerp, (I8, dq.exp([0.1, 0, 0, 10.0, 0, 0]), 1e308), r"^tau: result is not finite"),
    (dq.sclerp, (I8, dq.exp([0.0, 0, 0, 10.0, 0, 0]), 1e308), r"^tau: result is not finite"),
    (dq.from_matrix, (np.block([[dq.to_matrix(GOOD)[:3, :3], np.full((3, 1), 1.7e308)],
                                [np.zeros((1, 3)), np.ones((1, 1))]]),),
     r"^T: result is not finite"),
    (dq.to_matrix, (np.array([1.0, 0, 0, 0, 0, 1e308, 1e308, 0]),), r"^a: result is not finite"),
    (dq.to_pose, (np.array([1.0, 0, 0, 0, 0, 1e200, 1e200, 0]),), r"^a: result is not finite"),
    (dq.log, (np.array([1.0, 0, 0, 0, 0, 1e308, 1e308, 0]),), r"^a: result is not finite"),
    (dq.screw, (np.array([0.5, 0.5, 0.5, 0.5, 0, 1e300, -1e300, 0]),), r"^a: result is not finite"),
    (dq.transform, (dq.exp([0, 0, PI / 8, 0, 0, 0]), [1.7e308, 1.7e308, 0]),
     r"^p: result is not finite"),
    (dq.lin, (np.stack([np.array([1.0, 0, 0, 0, 0, 1e150, 0, 0])] * 2),), None),
])
def test_overflow_raises_instead_of_returning_inf(f, args, pattern):
    if pattern is None:
        assert np.all(np.isfinite(f(*args)))
        return
    with pytest.raises(ValueError, match=pattern):
        f(*args)


def test_tiny_rotation_with_huge_translation_stays_finite():
    # The moment |t_perp| / (theta/2) = 1e149 / 1e-160 overflows unless the rotation, far below
    # rounding, is treated as zero.
    q = dq.exp([1e-160, 0, 0, 0, 1e149, 0])
    s = dq.screw(q)
    assert np.all(np.isfinite(s.moment)) and s.theta < 1e-150
    np.testing.assert_allclose(s.d * s.axis + s.theta * s.moment, [0, 2e149, 0], rtol=1e-12)
    half = dq.sclerp(dq.identity(), q, 0.5)
    np.testing.assert_allclose(half, [1, 0, 0, 0, 0, 0, 0.5e149, 0], rtol=1e-12, atol=1e-150)


def dq_rotation_error(M):
    return np.abs(M[:3, :3].T @ M[:3, :3] - np.eye(3)).max()


def test_from_pose_overflow_names_t():
    with pytest.raises(ValueError, match=r"^t: result is not finite"):
        dq.from_pose(GOOD[:4], np.full(3, 1.7e308))


def test_errors_leave_the_module_usable():
    with pytest.raises(ValueError):
        dq.dib(np.full((3, 8), np.nan))
    np.testing.assert_allclose(dq.dib(SET, W3), dq.dib(SET, W3))


# ---- fuzz ---------------------------------------------------------------------------------------

SPECIAL = np.array([np.nan, np.inf, -np.inf, 1e300, -1e300, 1e-300, 5e-324, 0.0, -0.0, 1e154,
                    1e-160, 1.0 + 0.99 * dq.UNIT_TOL, 1.0 + 1.01 * dq.UNIT_TOL])


def _garbage(rng, core, lead):
    """Mostly valid values with a few poisoned entries, sometimes pure noise."""
    shape = lead + core
    kind = rng.integers(0, 4)
    if core == (8,) or core == (None, 8):
        x = random_dqs(rng, shape[:-1], 10.0 ** rng.integers(-3, 4))
    elif core == (4, 4):
        x = (dq.to_matrix(random_dqs(rng, lead, 10.0 ** rng.integers(-3, 4))) if kind
             else rng.normal(size=shape))
    elif core == (4,):
        x = random_quaternions(rng, lead)
    else:
        x = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4)
    x = np.array(x, dtype=float)
    if kind == 0:
        x = rng.normal(size=x.shape) * 10.0 ** rng.integers(-300, 300)
    if x.size and kind in (1, 2):
        flat = x.reshape(-1)
        idx = rng.integers(0, flat.size, rng.integers(1, 4))
        with np.errstate(invalid="ignore", over="ignore"):
            flat[idx] = (rng.choice(SPECIAL, idx.size) if kind == 1
                         else flat[idx] * rng.choice(SPECIAL, idx.size))
    return x


FUZZ_SPECS = [  # (function, core shapes of its arguments; None = set size)
    (dq.mul, [(8,), (8,)]), (dq.conj, [(8,)]), (dq.normalize, [(8,)]), (dq.log, [(8,)]),
    (dq.exp, [(6,)]), (dq.power, [(8,), ()]), (dq.from_matrix, [(4, 4)]), (dq.to_matrix, [(8,)]),
    (dq.from_pose, [(4,), (3,)]), (dq.to_pose, [(8,)]), (dq.transform, [(8,), (3,)]),
    (dq.screw, [(8,)]), (dq.sclerp, [(8,), (8,), ()]),
    (dq.dlb, [(None, 8), (None,)]), (dq.dib, [(None, 8), (None,)]), (dq.lin, [(None, 8), (None,)]),
    (dq.dec, [(None, 8), (None,)]), (dq.logblend, [(None, 8), (None,)]),
    (lambda q, w: dq.blend(q, w, method="sclerp"), [(2, 8), (2,)]),
]


@pytest.mark.parametrize("f,cores", FUZZ_SPECS, ids=lambda v: getattr(v, "__name__", None))
def test_fuzz_returns_finite_or_raises_value_error(rng, f, cores):
    for _ in range(300):
        lead = tuple(int(k) for k in rng.integers(1, 4, rng.integers(0, 3)))
        n = int(rng.integers(1, 5))
        args = []
        for core in cores:
            core = tuple(n if c is None else c for c in core)
            if rng.random() < 0.05:  # a wrong core shape now and then
                core = core[:-1] + (core[-1] + 1,) if core else (2,)
            arg_lead = lead[int(rng.integers(0, len(lead) + 1)):]
            if core in ((n, 8), (2, 8)):
                x = _garbage(rng, (8,), arg_lead + core[:-1])
            else:
                x = _garbage(rng, core, arg_lead)
                if cores[-1] in ((None,), (2,)) and rng.random() < 0.8:
                    x = np.abs(x)  # mostly valid weights, so the blends themselves get exercised
            args.append(x)
        try:
            out = f(*args)
        except ValueError as e:
            assert str(e).split(":")[0].split("[")[0] in (
                "a", "b", "x", "tau", "T", "q", "t", "p", "dqs", "weights",
                "shape mismatch"), str(e)
            continue
        outs = out if isinstance(out, tuple) else (out,)
        for o in outs:
            assert np.all(np.isfinite(o)), (f, args, out)
