"""dqpose.dq refuses bad input with a ValueError naming the argument and index: non-finite, non-
unit, non-rigid, bad weights, shapes, methods, overflow."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq
from tests import reference as ref
from tests.dq._poses import (
    PI,
    TOL,
)

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
