"""SO(3) and SE(3) tangent-space tools: hat/vee, Exp/Log, adjoint, Jacobians, covariance frames.

Conventions (stated once; they are GTSAM's Pose3 conventions):

* A twist is ``xi = [wx, wy, wz, vx, vy, vz]``, rotation first, ``(..., 6)``; a rotation vector
  is ``w``, ``(..., 3)``. Poses are unit dual quaternions ``(..., 8)`` as in :mod:`dqpose.dq`.
* ``se3_exp(xi)`` is the full SE(3) exponential (rotation ``Exp(w)``, translation ``Jl(w) v``),
  GTSAM's ``Pose3.Expmap``; ``se3_log`` its inverse with the rotation angle in ``[0, pi]``.
  :func:`dqpose.dq.log` is half of this twist: ``se3_exp(xi) == dq.exp(xi / 2)``.
* A covariance is 6x6 row-major, rotation first ``[wx wy wz vx vy vz]``, of a right (body-frame)
  perturbation ``T * Exp(xi)``: GTSAM's Pose3 convention (``Pose3.retract``).
  A left (world-frame) perturbation is ``Exp(xi) * T``.
* ``adjoint(T)`` is the 6x6 ``Ad(T)`` with ``T Exp(xi) T^-1 = Exp(Ad(T) xi)``, so
  ``[[R, 0], [t^ R, R]]`` in this ordering (GTSAM's ``Pose3.AdjointMap``).
* ``Jl``/``Jr`` are the left/right Jacobians: ``Exp(xi + d) ~ Exp(Jl(xi) d) Exp(xi)
  ~ Exp(xi) Exp(Jr(xi) d)``, and ``Jr(xi) = Jl(-xi)``. ``se3_right_jacobian`` is GTSAM's
  ``Pose3.ExpmapDerivative``; ``se3_right_jacobian_inv(se3_log(T))`` its ``LogmapDerivative(T)``.
  The inverse Jacobians are singular at rotation angles that are non-zero multiples of 2 pi
  (``ValueError`` there); every other angle, including pi, gives a finite matrix.

Every function broadcasts over leading axes. Bad input is a ``ValueError`` naming the argument
(wrong shape, NaN or infinity, a pose that is not a unit dual quaternion).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq
from dqpose.errors import rename

__all__ = [
    "so3_hat", "so3_vee", "se3_hat", "se3_vee", "se3_exp", "se3_log", "adjoint",
    "so3_left_jacobian", "so3_right_jacobian", "so3_left_jacobian_inv", "so3_right_jacobian_inv",
    "se3_left_jacobian", "se3_right_jacobian", "se3_left_jacobian_inv", "se3_right_jacobian_inv",
    "cov_right_to_left", "cov_left_to_right", "cov_inverse", "cov_compose",
    "cov_to_ros", "cov_from_ros", "cov_sigmas",
]

# Below this angle the coefficients come from their Taylor series: the closed forms divide
# cancelling differences by up to theta^5 (at 0.2 they were 2e-15 off; from 0.5 on they are
# exact to rounding). Eight terms keep every series exact to rounding below it.
_SERIES_ANGLE = 0.5


# ---- argument checks ---------------------------------------------------------------------------
def _array(x, name: str, tail: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers, got {type(x).__name__}") from None
    if a.ndim < len(tail) or a.shape[a.ndim - len(tail):] != tail:
        want = ", ".join(("...",) + tuple(str(n) for n in tail))
        raise ValueError(f"{name}: expected shape ({want}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinity")
    return a


def _matrix(T, name: str) -> np.ndarray:
    """4x4 matrices of unit dual quaternions; the core checks them and names the index."""
    try:
        return dq.to_matrix(T)
    except ValueError as e:
        raise rename(e, {"a": name + "{}"}) from None


def _sandwich(A: np.ndarray, S: np.ndarray) -> np.ndarray:
    return A @ S @ np.swapaxes(A, -1, -2)


# ---- hat / vee ---------------------------------------------------------------------------------
def _hat(w: np.ndarray) -> np.ndarray:
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def so3_hat(w) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)``: the skew matrix ``w^`` with ``w^ p = w x p``."""
    return _hat(_array(w, "w", (3,)))


def so3_vee(W) -> np.ndarray:
    """``(..., 3, 3) -> (..., 3)``: the inverse of :func:`so3_hat` (of the skew part of ``W``)."""
    W = _array(W, "W", (3, 3))
    return 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2],
                           W[..., 0, 2] - W[..., 2, 0],
                           W[..., 1, 0] - W[..., 0, 1]], axis=-1)


def se3_hat(xi) -> np.ndarray:
    """``(..., 6) -> (..., 4, 4)``: ``[[w^, v], [0, 0]]``."""
    xi = _array(xi, "xi", (6,))
    X = np.zeros(xi.shape[:-1] + (4, 4))
    X[..., :3, :3] = _hat(xi[..., :3])
    X[..., :3, 3] = xi[..., 3:]
    return X


def se3_vee(X) -> np.ndarray:
    """``(..., 4, 4) -> (..., 6)``: the inverse of :func:`se3_hat`."""
    X = _array(X, "X", (4, 4))
    return np.concatenate([so3_vee(X[..., :3, :3]), X[..., :3, 3]], axis=-1)


# ---- Exp / Log / Ad ----------------------------------------------------------------------------
def se3_exp(xi) -> np.ndarray:
    """``(..., 6) -> (..., 8)``: the pose ``Exp(xi)`` (GTSAM ``Pose3.Expmap``)."""
    return dq.exp(0.5 * _array(xi, "xi", (6,)))  # dq.log is the half twist; halving is exact


def se3_log(T) -> np.ndarray:
    """``(..., 8) -> (..., 6)``: the twist of ``T``, rotation angle in ``[0, pi]``."""
    try:
        return 2.0 * dq.log(T)
    except ValueError as e:
        raise rename(e, {"a": "T{}"}) from None


def _adjoint_of_matrix(M: np.ndarray) -> np.ndarray:
    R, t = M[..., :3, :3], M[..., :3, 3]
    A = np.zeros(M.shape[:-2] + (6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., 3:, :3] = _hat(t) @ R
    return A


def _inverse_matrix(M: np.ndarray) -> np.ndarray:
    Rt = np.swapaxes(M[..., :3, :3], -1, -2)
    out = np.zeros_like(M)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ M[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def adjoint(T) -> np.ndarray:
    """``(..., 8) -> (..., 6, 6)``: ``Ad(T) = [[R, 0], [t^ R, R]]`` (GTSAM ``Pose3.AdjointMap``)."""
    return _adjoint_of_matrix(_matrix(T, "T"))


# ---- Jacobians ---------------------------------------------------------------------------------
def _series(theta: np.ndarray, closed, coefficients) -> np.ndarray:
    """``closed(theta)`` away from zero, the even power series ``sum c_k theta^2k`` near it."""
    small = theta < _SERIES_ANGLE
    t2 = theta * theta
    s = np.zeros_like(theta)
    for c in reversed(coefficients):
        s = s * t2 + c
    with np.errstate(divide="ignore", invalid="ignore"):
        big = closed(np.where(small, 1.0, theta))
    return np.where(small, s, big)


def _so3_coefficients(theta: np.ndarray):
    """``(1 - cos t)/t^2`` and ``(t - sin t)/t^3``: ``Jl = I + B w^ + C w^2``."""
    B = _series(theta, lambda t: 2.0 * np.sin(0.5 * t) ** 2 / (t * t),
                (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800, -1 / 479001600,
                 1 / 87178291200, -1 / 20922789888000))
    C = _series(theta, lambda t: (t - np.sin(t)) / t ** 3,
                (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800, -1 / 6227020800,
                 1 / 1307674368000, -1 / 355687428096000))
    return B, C


def _so3_inverse_coefficient(theta: np.ndarray, name: str) -> np.ndarray:
    """``(1 - (t/2) cot(t/2)) / t^2``: ``Jl^-1 = I - w^/2 + D w^2``; infinite at t = 2 pi k."""
    D = _series(theta, lambda t: (1.0 - 0.5 * t * np.cos(0.5 * t) / np.sin(0.5 * t)) / (t * t),
                (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000,
                 1 / 74724249600, 3617 / 10670622842880000))
    # sin(t/2) rounds to about 1e-16, not 0, at 2 pi: the value is huge rather than infinite.
    bad = ~(np.abs(D) < 1e12)
    if np.any(bad):
        i = np.unravel_index(np.flatnonzero(bad)[0], bad.shape) if bad.ndim else ()
        where = f"[{', '.join(str(int(k)) for k in i)}]" if i else ""
        raise ValueError(f"{name}{where}: rotation angle {float(theta[bad].flat[0]):.17g} is a "
                         f"multiple of 2 pi, where the inverse Jacobian does not exist")
    return D


def _so3_jl(w: np.ndarray, sign: float) -> np.ndarray:
    B, C = _so3_coefficients(np.linalg.norm(w, axis=-1))
    K = _hat(w)
    return np.eye(3) + (sign * B)[..., None, None] * K + C[..., None, None] * (K @ K)


def _so3_jl_inv(w: np.ndarray, sign: float, name: str) -> np.ndarray:
    D = _so3_inverse_coefficient(np.linalg.norm(w, axis=-1), name)
    K = _hat(w)
    return np.eye(3) - (0.5 * sign) * K + D[..., None, None] * (K @ K)


def so3_left_jacobian(w) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)``: ``Jl(w) = I + (1-cos t)/t^2 w^ + (t-sin t)/t^3 w^2``."""
    return _so3_jl(_array(w, "w", (3,)), 1.0)


def so3_right_jacobian(w) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)``: ``Jr(w) = Jl(-w)``."""
    return _so3_jl(_array(w, "w", (3,)), -1.0)


def so3_left_jacobian_inv(w) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)``: ``Jl(w)^-1 = I - w^/2 + (1 - (t/2) cot(t/2))/t^2 w^2``."""
    return _so3_jl_inv(_array(w, "w", (3,)), 1.0, "w")


def so3_right_jacobian_inv(w) -> np.ndarray:
    """``(..., 3) -> (..., 3, 3)``: ``Jr(w)^-1 = d Log(Exp(w) Exp(d)) / d d`` at ``d = 0``."""
    return _so3_jl_inv(_array(w, "w", (3,)), -1.0, "w")


def _se3_q(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The lower-left block of the SE(3) left Jacobian, ``Q(v, w)`` (Barfoot, eq. 7.86)."""
    theta = np.linalg.norm(w, axis=-1)
    _, C = _so3_coefficients(theta)
    c2 = _series(theta, lambda t: (t * t + 2.0 * np.cos(t) - 2.0) / (2.0 * t ** 4),
                 (1 / 24, -1 / 720, 1 / 40320, -1 / 3628800, 1 / 479001600, -1 / 87178291200,
                  1 / 20922789888000, -1 / 6402373705728000))
    c3 = _series(theta, lambda t: (2.0 * t - 3.0 * np.sin(t) + t * np.cos(t)) / (2.0 * t ** 5),
                 (1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200, 1 / 1245404160,
                  -1 / 217945728000, 1 / 50812489728000, -1 / 15205637551104000))
    W, V = _hat(w), _hat(v)
    WV, VW, WW = W @ V, V @ W, W @ W
    WVW = WV @ W
    e = (..., None, None)
    return (0.5 * V + C[e] * (WV + VW + WVW) + c2[e] * (WW @ V + VW @ W - 3.0 * WVW)
            + c3[e] * (WVW @ W + W @ WVW))


def _in_core(xi: np.ndarray) -> bool:
    """Whether the C core's Jacobians (service/csrc/se3.c, the same closed forms and series)
    apply: they take the half angle's sine and cosine as a quaternion gives them, so rotations of
    at most pi (every residual's, every small step's); beyond, the NumPy forms below."""
    return xi.size > 0 and bool(np.all(np.einsum("...i,...i->...", xi[..., :3], xi[..., :3])
                                       <= np.pi ** 2))


def _se3_jl(xi: np.ndarray, sign: float) -> np.ndarray:
    if _in_core(xi):
        return _c.se3_jr(-sign * xi)        # Jl(x) = Jr(-x)
    return _se3_jl_numpy(xi, sign)


def _se3_jl_inv(xi: np.ndarray, sign: float) -> np.ndarray:
    if _in_core(xi):
        return _c.se3_jl_inv(sign * xi)
    return _se3_jl_inv_numpy(xi, sign)


def _se3_jl_numpy(xi: np.ndarray, sign: float) -> np.ndarray:
    w, v = sign * xi[..., :3], sign * xi[..., 3:]
    J = np.zeros(xi.shape[:-1] + (6, 6))
    J[..., :3, :3] = J[..., 3:, 3:] = _so3_jl(w, 1.0)
    J[..., 3:, :3] = _se3_q(w, v)
    return J


def _se3_jl_inv_numpy(xi: np.ndarray, sign: float) -> np.ndarray:
    w, v = sign * xi[..., :3], sign * xi[..., 3:]
    Ji = _so3_jl_inv(w, 1.0, "xi")
    J = np.zeros(xi.shape[:-1] + (6, 6))
    J[..., :3, :3] = J[..., 3:, 3:] = Ji
    J[..., 3:, :3] = -Ji @ _se3_q(w, v) @ Ji
    return J


def se3_left_jacobian(xi) -> np.ndarray:
    """``(..., 6) -> (..., 6, 6)``: ``Jl(xi) = [[Jl(w), 0], [Q(v, w), Jl(w)]]``."""
    return _se3_jl(_array(xi, "xi", (6,)), 1.0)


def se3_right_jacobian(xi) -> np.ndarray:
    """``(..., 6) -> (..., 6, 6)``: ``Jr(xi) = Jl(-xi)`` (GTSAM ``Pose3.ExpmapDerivative``)."""
    return _se3_jl(_array(xi, "xi", (6,)), -1.0)


def se3_left_jacobian_inv(xi) -> np.ndarray:
    """``(..., 6) -> (..., 6, 6)``: ``[[Jl^-1, 0], [-Jl^-1 Q Jl^-1, Jl^-1]]``."""
    return _se3_jl_inv(_array(xi, "xi", (6,)), 1.0)


def se3_right_jacobian_inv(xi) -> np.ndarray:
    """``(..., 6) -> (..., 6, 6)``: ``Jr(xi)^-1``; at ``xi = se3_log(T)`` it is GTSAM's
    ``Pose3.LogmapDerivative(T)``."""
    return _se3_jl_inv(_array(xi, "xi", (6,)), -1.0)


# ---- covariance between frames -----------------------------------------------------------------
def _through_inverse(M: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``Ad(T^-1) cov Ad(T^-1)^T`` for the 4x4 matrices ``M`` of ``T``."""
    return _sandwich(_adjoint_of_matrix(_inverse_matrix(M)), cov)


def cov_right_to_left(T, cov) -> np.ndarray:
    """Covariance of a right perturbation ``T Exp(xi)`` as the left one ``Exp(Ad(T) xi) T``:
    ``Ad(T) cov Ad(T)^T``. ``T`` ``(..., 8)``, ``cov`` ``(..., 6, 6)``."""
    return _sandwich(adjoint(T), _array(cov, "cov", (6, 6)))


def cov_left_to_right(T, cov) -> np.ndarray:
    """The inverse of :func:`cov_right_to_left`: ``Ad(T^-1) cov Ad(T^-1)^T``."""
    return _through_inverse(_matrix(T, "T"), _array(cov, "cov", (6, 6)))


def cov_inverse(T, cov) -> np.ndarray:
    """Covariance of ``T^-1`` from that of ``T``: ``(T Exp(xi))^-1 = T^-1 Exp(-Ad(T) xi)``, so
    ``Ad(T) cov Ad(T)^T``, the same matrix as :func:`cov_right_to_left`."""
    return cov_right_to_left(T, cov)


def cov_compose(cov_a: Optional[np.ndarray], T_b, cov_b: Optional[np.ndarray]) -> np.ndarray:
    """Covariance of ``T_a T_b`` from independent covariances of ``T_a`` and ``T_b`` (first order).

    ``T_a Exp(xa) T_b Exp(xb) = T_a T_b Exp(Ad(T_b^-1) xa) Exp(xb)``, so the result is
    ``Ad(T_b^-1) cov_a Ad(T_b^-1)^T + cov_b``; ``T_a`` itself does not enter. ``None`` stands for a
    constant (exactly known) pose: a constant on the left leaves ``cov_b`` unchanged, a constant
    ``T_b`` on the right maps ``cov_a`` to ``Ad(T_b^-1) cov_a Ad(T_b^-1)^T``.
    """
    if cov_a is None and cov_b is None:
        raise ValueError("cov_a, cov_b: at least one covariance is needed (both are None)")
    M = _matrix(T_b, "T_b")
    out = np.zeros(M.shape[:-2] + (6, 6))
    if cov_a is not None:
        out = out + _through_inverse(M, _array(cov_a, "cov_a", (6, 6)))
    if cov_b is not None:
        out = out + _array(cov_b, "cov_b", (6, 6))
    return out


def cov_sigmas(cov) -> np.ndarray:
    """``(..., 2)``: the one-sigma rotation (rad) and translation (m) of 6x6 covariances
    ``(..., 6, 6)`` (rotation first): the square roots of the largest eigenvalues of the rotation
    and of the translation block, the standard deviation along the least certain direction
    (frame-independent, as a rotation of the frame leaves the eigenvalues). Every sigma dqpose
    prints or records for a pose is this one; a negative eigenvalue (round-off) is 0."""
    c = _array(cov, "cov", (6, 6))
    largest = np.stack([np.linalg.eigvalsh(c[..., :3, :3])[..., -1],
                        np.linalg.eigvalsh(c[..., 3:, 3:])[..., -1]], axis=-1)
    return np.sqrt(np.maximum(largest, 0.0))


# ---- ROS's pose covariance -------------------------------------------------------------------
def _ros_jacobian(M: np.ndarray) -> np.ndarray:
    """``d(dt, dtheta) / d(w, v)`` at the 4x4 ``M``: ``[[0, R], [R, 0]]``."""
    R = M[..., :3, :3]
    J = np.zeros(M.shape[:-2] + (6, 6))
    J[..., :3, 3:] = R
    J[..., 3:, :3] = R
    return J


def cov_to_ros(T, cov) -> np.ndarray:
    """Our covariance of ``T`` (rotation first, right perturbation ``T Exp([w, v])``) as ROS's
    ``PoseWithCovariance.covariance`` (and Foxglove's ``pose_covariance``): translation first,
    the pose perturbed as ``(t + dt, Exp(dtheta) R)``, ``dt`` and the rotation vector ``dtheta``
    both along the parent frame's axes. To first order ``dt = R v`` and ``dtheta = R w`` (the
    rotation's adjoint; the translation's coupling to ``w`` in SE(3)'s adjoint belongs to a left
    perturbation of the whole pose, which ROS's separate translation is not), so the result is
    ``J cov J^T`` with ``J = [[0, R], [R, 0]]``. ``T`` ``(..., 8)``, ``cov`` ``(..., 6, 6)``."""
    return _sandwich(_ros_jacobian(_matrix(T, "T")), _array(cov, "cov", (6, 6)))


def cov_from_ros(T, cov) -> np.ndarray:
    """The inverse of :func:`cov_to_ros`: ROS's translation-first, parent-axes covariance of
    ``T`` as ours. ``J`` is orthogonal, so its inverse is ``J^T``."""
    J = _ros_jacobian(_matrix(T, "T"))
    return _sandwich(np.swapaxes(J, -1, -2), _array(cov, "cov", (6, 6)))
