"""dqpose.dq's broadcasting of leading dimensions and its invariances, property-based
(hypothesis)."""
from __future__ import annotations

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from dqpose import dq
from tests import reference as ref
from tests.conftest import random_dqs, random_quaternions
from tests.dq._poses import (
    PI,
    TOL,
    dq_error,
)

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
