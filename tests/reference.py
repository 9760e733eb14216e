"""An independent SE(3) reference for testing the dual-quaternion core.

Everything here works on 4x4 homogeneous matrices and 3x3 rotation matrices with NumPy, vectorised
over leading dimensions; no dual-quaternion algebra is used for the group operations, so an error
in the core's algebra cannot be reproduced here. The closed forms are the standard ones:

* exp: Rodrigues for the rotation, the left Jacobian ``V`` for the translation.
* log: angle from ``atan2(|skew|, (tr R - 1)/2)``; the axis from the skew part while the angle is
  below pi/2 and from the symmetric part above it, where the skew part vanishes; ``V^-1`` for the
  translation. Series are used where the closed forms cancel.

A twist is ``(omega, v)``: ``exp`` of it maps the identity to the pose after unit time. The core's
``dq.log`` is half of it.

The two conversion helpers at the end (``dq_from_matrix``, ``matrix_from_dq``) translate between
the two representations so tests can compare; they go through the axis-angle form of the
rotation, not the quadratic quaternion-to-matrix formulas the core uses.
"""
from __future__ import annotations

import numpy as np

# Below these the closed forms lose digits to cancellation; the series are exact to rounding.
_SMALL_ANGLE = 1e-2
_SMALL_SIN = 1e-4


def hat(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) skew-symmetric matrices with ``hat(w) p = w x p``."""
    w = np.asarray(w, dtype=float)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def vee(K: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat` applied to the skew part of ``K``."""
    return 0.5 * np.stack([K[..., 2, 1] - K[..., 1, 2],
                           K[..., 0, 2] - K[..., 2, 0],
                           K[..., 1, 0] - K[..., 0, 1]], axis=-1)


def _exp_coefficients(theta: np.ndarray):
    """sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3 with series below _SMALL_ANGLE."""
    t2 = theta * theta
    small = theta < _SMALL_ANGLE
    ts = np.where(small, 1.0, theta)  # keeps the closed forms away from 0/0 where unused
    A = np.where(small, 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)), np.sin(ts) / ts)
    # 1 - cos t written as 2 sin^2(t/2): no cancellation at any angle.
    B = np.where(small, 0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56)),
                 2.0 * np.sin(0.5 * ts) ** 2 / (ts * ts))
    C = np.where(small, 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72)),
                 (ts - np.sin(ts)) / (ts ** 3))
    return A, B, C


def rot_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) rotation vectors -> (..., 3, 3) rotation matrices."""
    omega = np.asarray(omega, dtype=float)
    theta = np.linalg.norm(omega, axis=-1)
    A, B, _ = _exp_coefficients(theta)
    K = hat(omega)
    return np.eye(3) + A[..., None, None] * K + B[..., None, None] * (K @ K)


def rot_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors with angle in [0, pi].

    At exactly pi the sign of the axis is arbitrary (both logs are valid)."""
    R = np.asarray(R, dtype=float)
    s = vee(R)  # sin(theta) * axis
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)  # cos(theta)
    sn = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sn, c)
    # Below pi/2: omega = s * theta / sin(theta), with the asin series for tiny sin.
    tiny = sn < _SMALL_SIN
    sn_safe = np.where(tiny, 1.0, sn)
    x = sn * sn
    ratio = np.where(tiny, 1 + x / 6 + 3 * x * x / 40, theta / sn_safe)
    omega_skew = s * ratio[..., None]
    # Above pi/2: (R + R^T)/2 - cos(theta) I = (1 - cos(theta)) a a^T; take the largest column.
    B = 0.5 * (R + np.swapaxes(R, -1, -2)) - c[..., None, None] * np.eye(3)
    k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
    col = np.take_along_axis(B, k[..., None, None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):  # B ~ 0 where this branch is unused
        a = col / np.linalg.norm(col, axis=-1, keepdims=True)
    sign = np.where(np.sum(a * s, axis=-1) < 0.0, -1.0, 1.0)
    omega_sym = a * (sign * theta)[..., None]
    return np.where((c < 0.0)[..., None], omega_sym, omega_skew)


def left_jacobian(omega: np.ndarray) -> np.ndarray:
    """V(omega) = I + (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2."""
    theta = np.linalg.norm(omega, axis=-1)
    _, B, C = _exp_coefficients(theta)
    K = hat(omega)
    return np.eye(3) + B[..., None, None] * K + C[..., None, None] * (K @ K)


def left_jacobian_inv(omega: np.ndarray) -> np.ndarray:
    """V^-1 = I - K/2 + (1 - (t/2) cot(t/2))/t^2 K^2, finite for t in [0, pi]."""
    theta = np.linalg.norm(omega, axis=-1)
    small = theta < _SMALL_ANGLE
    ts = np.where(small, 1.0, theta)
    h = 0.5 * ts
    t2 = theta * theta
    D = np.where(small, 1 / 12 + t2 / 720 + t2 * t2 / 30240,
                 (1 - h * np.cos(h) / np.sin(h)) / (ts * ts))
    K = hat(omega)
    return np.eye(3) - 0.5 * K + D[..., None, None] * (K @ K)


def make(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) and translation (..., 3) -> (..., 4, 4)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv(T: np.ndarray) -> np.ndarray:
    """Rigid inverse [R^T, -R^T t]."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def exp(twist: np.ndarray) -> np.ndarray:
    """se(3) exp: (..., 6) twists (omega, v) -> (..., 4, 4)."""
    twist = np.asarray(twist, dtype=float)
    omega, v = twist[..., :3], twist[..., 3:]
    t = np.einsum("...ij,...j->...i", left_jacobian(omega), v)
    return make(rot_exp(omega), t)


def log(T: np.ndarray) -> np.ndarray:
    """se(3) log: (..., 4, 4) -> (..., 6) twists (omega, v), rotation angle in [0, pi]."""
    T = np.asarray(T, dtype=float)
    omega = rot_log(T[..., :3, :3])
    v = np.einsum("...ij,...j->...i", left_jacobian_inv(omega), T[..., :3, 3])
    return np.concatenate([omega, v], axis=-1)


def power(T: np.ndarray, tau) -> np.ndarray:
    """T^tau = exp(tau log T)."""
    return exp(np.asarray(tau, dtype=float)[..., None] * log(T))


def sclerp(T0: np.ndarray, T1: np.ndarray, tau) -> np.ndarray:
    """T0 (T0^-1 T1)^tau; the principal log makes it the shortest screw."""
    return T0 @ power(inv(T0) @ T1, tau)


def karcher_mean(Ts: np.ndarray, w: np.ndarray | None = None, tol: float = 1e-15,
                 max_iter: int = 200, start: np.ndarray | None = None):
    """Bi-invariant weighted mean of (..., n, 4, 4) by Gauss-Newton on the group.

    X <- X exp(sum_i w_i log(X^-1 T_i)); the fixed point is where the weighted twists balance.
    Returns (mean, iterations, final step norm). Starts at the pose of largest weight unless
    ``start`` is given."""
    Ts = np.asarray(Ts, dtype=float)
    n = Ts.shape[-3]
    w = np.full(Ts.shape[:-2], 1.0 / n) if w is None else np.asarray(w, dtype=float)
    w = np.broadcast_to(w / w.sum(axis=-1, keepdims=True), Ts.shape[:-2])
    if start is None:
        k = np.argmax(w, axis=-1)
        X = np.take_along_axis(Ts, k[..., None, None, None], axis=-3)[..., 0, :, :]
    else:
        X = np.array(start, dtype=float)
    step = np.inf
    for it in range(max_iter):
        xi = np.einsum("...n,...nk->...k", w, log(inv(X)[..., None, :, :] @ Ts))
        step = np.max(np.linalg.norm(xi, axis=-1), initial=0.0)
        X = X @ exp(xi)
        if step < tol:
            return X, it + 1, step
    return X, max_iter, step


# ---- conversions (for comparing with the core) ----------------------------------------------

def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-first quaternions (..., 4)."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    w = aw * bw - np.sum(av * bv, axis=-1, keepdims=True)
    v = aw * bv + bw * av + np.cross(av, bv)
    return np.concatenate([w, v], axis=-1)


def quat_from_rotvec(omega: np.ndarray) -> np.ndarray:
    """(cos(t/2), sin(t/2) axis) for rotation vectors (..., 3)."""
    theta = np.linalg.norm(omega, axis=-1)
    small = theta < _SMALL_ANGLE
    ts = np.where(small, 1.0, theta)
    t2 = theta * theta
    half_sinc = np.where(small, 0.5 - t2 / 48 + t2 * t2 / 3840, np.sin(0.5 * ts) / ts)
    return np.concatenate([np.cos(0.5 * theta)[..., None], omega * half_sinc[..., None]], axis=-1)


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion of either sign, angle in [0, pi]."""
    q = np.where((q[..., :1] < 0.0), -q, q)
    w, v = q[..., 0], q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    # atan2 keeps full relative accuracy for tiny n; only n == 0 needs its limit 2/w.
    ratio = np.where(n == 0.0, 2.0 / np.where(w == 0.0, 1.0, w),
                     2.0 * np.arctan2(n, w) / np.where(n == 0.0, 1.0, n))
    return v * ratio[..., None]


def dq_from_matrix(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 8) with real part (cos(t/2), sin(t/2) axis), t in [0, pi]."""
    r = quat_from_rotvec(rot_log(T[..., :3, :3]))
    t = np.concatenate([np.zeros(T.shape[:-2] + (1,)), T[..., :3, 3]], axis=-1)
    return np.concatenate([r, 0.5 * qmul(t, r)], axis=-1)


def dq_from_rt(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Unit quaternion r (kept as given, sign included) and translation t -> (..., 8)."""
    r = np.asarray(r, dtype=float)
    t = np.asarray(t, dtype=float)
    lead = np.broadcast_shapes(r.shape[:-1], t.shape[:-1])
    r = np.broadcast_to(r, lead + (4,))
    tq = np.concatenate([np.zeros(lead + (1,)), np.broadcast_to(t, lead + (3,))], axis=-1)
    return np.concatenate([r, 0.5 * qmul(tq, r)], axis=-1)


def translation_of_dq(q: np.ndarray) -> np.ndarray:
    """t = 2 vec(d r*)."""
    rc = q[..., :4] * np.array([1.0, -1.0, -1.0, -1.0])
    return 2.0 * qmul(q[..., 4:], rc)[..., 1:]


def matrix_from_dq(q: np.ndarray) -> np.ndarray:
    """(..., 8) unit dual quaternions -> (..., 4, 4) through the rotation vector and Rodrigues."""
    q = np.asarray(q, dtype=float)
    return make(rot_exp(rotvec_from_quat(q[..., :4])), translation_of_dq(q))
