"""Dual quaternions for rigid motions: NumPy in, NumPy out, computed by the C core.

Conventions (stated once, used everywhere in dqpose):

* A dual quaternion is a float64 array of shape ``(..., 8)``: ``[w, x, y, z, w', x', y', z']``,
  real part first; the dual part is ``1/2 * t * r``.
* Quaternions are scalar first ``[w, x, y, z]`` (ROS, Eigen's ``coeffs()`` and scipy put w
  last: reorder with ``q[..., [3, 0, 1, 2]]``); metres, radians, seconds.
* A pose named ``T_a_b`` maps points from frame b to frame a; ``mul(T_a_b, T_b_c) = T_a_c``.
* ``log`` returns ``(..., 6)``: the real vector part, then the dual vector part. It is half the
  se(3) twist ``(omega, v)`` of the same motion, with the rotation taken the short way.
* ``q`` and ``-q`` are the same pose. Quaternions within :data:`UNIT_TOL` (1e-3) of unit norm
  are normalised, so rounded input (``0.7071``) is taken; rotation matrices within it of
  orthonormal are projected to the nearest rotation. Anything further off, non-finite, or not
  rigid raises ``ValueError`` naming the argument and saying how far.

Every function broadcasts over leading dimensions like a NumPy ufunc and releases the GIL on
batches.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dqpose import _dqcore as _c

__all__ = [
    "METHODS", "Method", "UNIT_TOL", "DIBResult", "Screw",
    "identity", "mul", "conj", "inv", "normalize", "log", "exp", "power",
    "from_matrix", "to_matrix", "from_pose", "to_pose", "transform", "screw",
    "sclerp", "dlb", "dib", "lin", "dec", "logblend", "blend",
]

#: The input tolerance (``DQ_UNIT_TOL`` of the C core): norms, orthogonality, orthonormality.
UNIT_TOL = _c.UNIT_TOL


class Method(NamedTuple):
    """A blending method: its code in the C core (= its ``dqpose.v1.Method`` value), its name in
    the paper's tables, and what it computes, in one line for help texts."""
    code: int
    label: str
    description: str


# The blending methods, written once, in the order of the paper's Table 1. Every other list
# derives from this one: the proto enum maps by name (METHOD_<NAME>), the CLI takes the names
# and descriptions. Tests check the C enum (blend.h; tests/dq/test_hard_cases.py) and the proto enum
# (tests/rpc/test_geometry.py) against it.
METHODS: dict[str, Method] = {
    "lin": Method(4, "Lin", "weighted mean of the 4x4 matrices, projected to the nearest rotation"),
    "dec": Method(5, "Dec", "rotation (spherical mean) and translation (mean) blended separately"),
    "log": Method(6, "Log", "exp of the weighted sum of the principal logs (Alexa)"),
    "sclerp": Method(3, "ScLERP",
                     "screw motion between exactly two poses, at tau = w1 / (w0 + w1)"),
    "dlb": Method(2, "DLB", "normalised weighted sum of the dual quaternions (closed form)"),
    "dib": Method(1, "DIB", "iterative bi-invariant weighted mean (exact; Kavan et al.)"),
}
_DIB, _DLB, _LIN, _DEC, _LOG = (METHODS[m].code for m in ("dib", "dlb", "lin", "dec", "log"))


class DIBResult(NamedTuple):
    """The DIB mean with how it was reached (arrays over the leading dimensions)."""
    mean: np.ndarray
    iterations: np.ndarray
    residual: np.ndarray


class Screw(NamedTuple):
    """Screw parameters: rotation angle in [0, pi], translation along the axis, axis direction,
    moment (p x axis for any point p on the axis)."""
    theta: np.ndarray
    d: np.ndarray
    axis: np.ndarray
    moment: np.ndarray


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity poses of the given leading shape."""
    out = np.zeros(tuple(shape) + (8,))
    out[..., 0] = 1.0
    return out


# The algebra maps straight onto the core; these are the documented names.
def mul(a, b) -> np.ndarray:
    """Product ``a b``: for poses, ``mul(T_a_b, T_b_c) = T_a_c``."""
    return _c.mul(a, b)


def conj(a) -> np.ndarray:
    """Quaternion conjugate of both parts; the inverse of a unit dual quaternion."""
    return _c.conj(a)


inv = conj


def normalize(a) -> np.ndarray:
    """Divide by the dual-number norm, so the result is exactly unit (any non-zero real part)."""
    return _c.normalize(a)


def log(a) -> np.ndarray:
    """``(..., 8) -> (..., 6)``: half the se(3) twist, rotation taken the short way."""
    return _c.log(a)


def exp(x) -> np.ndarray:
    """``(..., 6) -> (..., 8)``; the inverse of :func:`log`."""
    return _c.exp(x)


def power(a, tau) -> np.ndarray:
    """``exp(tau * log(a))``: the screw motion of ``a`` scaled by ``tau``."""
    return _c.power(a, tau)


def from_matrix(T) -> np.ndarray:
    """4x4 rigid transforms ``(..., 4, 4)`` to dual quaternions (scalar part >= 0). A rotation
    block within :data:`UNIT_TOL` of orthonormal (max ``|R^T R - I|``, det > 0) is replaced by the
    nearest rotation (Frobenius norm, as the SVD gives)."""
    return _c.from_matrix(T)


def to_matrix(a) -> np.ndarray:
    """Dual quaternions to 4x4 homogeneous matrices."""
    return _c.to_matrix(a)


def from_pose(q_wxyz, t) -> np.ndarray:
    """Rotation quaternion ``[w, x, y, z]`` (w first; ROS's, Eigen's ``coeffs()`` and scipy's
    ``as_quat()`` put it last: pass ``q[..., [3, 0, 1, 2]]``) and translation ``[x, y, z]`` to a
    dual quaternion."""
    return _c.from_pose(q_wxyz, t)


def to_pose(a) -> tuple[np.ndarray, np.ndarray]:
    """Dual quaternion to ``(q_wxyz, t)``: the quaternion w first (for ROS, Eigen or scipy's
    x, y, z, w: ``q[..., [1, 2, 3, 0]]``), keeping the sign of the input."""
    return _c.to_pose(a)


def transform(a, p) -> np.ndarray:
    """Apply poses to points ``(..., 3)``: ``R p + t``."""
    return _c.transform(a, p)


def screw(a) -> Screw:
    """Screw parameters of each pose (see :class:`Screw`)."""
    theta, d, lm = _c.screw(a)
    return Screw(theta, d, lm[..., :3], lm[..., 3:])


def sclerp(a, b, tau) -> np.ndarray:
    """Screw linear interpolation ``a (a* b)^tau`` along the shortest screw.

    ``a``, ``b`` are ``(..., 8)`` and ``tau`` a scalar or array; all three broadcast together, so
    one pair with ``tau`` of shape ``(N,)`` gives ``(N, 8)``. The screw of a pair is computed
    once however many ``tau`` it is evaluated at.
    """
    return _c.sclerp(a, b, tau)


def _method_code(method: str) -> int:
    try:
        return METHODS[method].code
    except (KeyError, TypeError):
        raise ValueError(f"method: unknown blending method {method!r}; "
                         f"expected one of {', '.join(METHODS)}") from None


def dlb(dqs, weights=None) -> np.ndarray:
    """Dual-quaternion linear blending: the normalised weighted sum, ``(..., n, 8) -> (..., 8)``."""
    return _c.blend(dqs, weights, _DLB)


def dib(dqs, weights=None, tol: float = 1e-12, max_iter: int = 100, *, return_info: bool = False):
    """Dual-quaternion iterative blending: the exact bi-invariant weighted mean.

    Starts at DLB and takes Gauss-Newton steps ``b <- b exp(sum w_i log(b* q_i))`` until the step
    is shorter than ``tol`` or ``max_iter`` steps were taken. With ``return_info`` returns a
    :class:`DIBResult` with the number of steps and the final residual (the norm of the weighted
    log sum at the returned mean; half-twist units: radians and metres).
    """
    mean, iters, res = _c.blend(dqs, weights, _DIB, as_tol(tol), as_iter(max_iter))
    if return_info:
        return DIBResult(mean, iters.astype(np.int64), res)
    return mean


def as_iter(max_iter) -> int:
    """``max_iter`` of a blend or a fit checked: a whole number in 0..1000000."""
    try:
        m = int(max_iter)
        whole = m == max_iter and not isinstance(max_iter, (bool, np.bool_))
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise ValueError(f"max_iter: must be a whole number, got {max_iter!r}")
    if not 0 <= m <= 1_000_000:
        raise ValueError(f"max_iter: must be within 0..1000000, got {m}")
    return m


def as_tol(tol) -> float:
    """``tol`` of a blend or a fit checked: finite and >= 0."""
    try:
        t = float(tol)
    except (TypeError, ValueError):
        t = float("nan")
    if not (0.0 <= t < float("inf")):
        raise ValueError(f"tol: must be finite and >= 0, got {tol!r}")
    return t


def lin(dqs, weights=None) -> np.ndarray:
    """Linear blend of 4x4 matrices ``(..., n, 8) -> (..., 4, 4)``. Not rigid in general
    (``blend(..., method="lin")`` projects it to the nearest rigid motion)."""
    return _c.lin(dqs, weights)


def dec(dqs, weights=None, tol: float = 1e-12, max_iter: int = 100) -> np.ndarray:
    """Rotation (spherical weighted mean) and translation (weighted mean) blended separately."""
    return _c.blend(dqs, weights, _DEC, as_tol(tol), as_iter(max_iter))


def logblend(dqs, weights=None) -> np.ndarray:
    """Alexa's log-matrix blend: ``exp(sum w_i log q_i)`` with principal logs."""
    return _c.blend(dqs, weights, _LOG)


def blend(dqs, weights=None, method: str = "dib", tol: float = 1e-12, max_iter: int = 100):
    """Blend ``(..., n, 8)`` poses with ``weights`` ``(..., n)`` (default: equal) into ``(..., 8)``.

    ``method`` is a name of :data:`METHODS`; ``"sclerp"`` needs exactly two poses and
    interpolates at ``tau = w_1 / (w_0 + w_1)``. ``"lin"`` blends matrices, which is not rigid;
    its rotation block is projected to the nearest rotation (in the Frobenius norm) here (use
    :func:`lin` for the raw blend). Weights must be finite, non-negative, with a positive sum;
    they are normalised to sum 1.
    """
    code = _method_code(method)
    out = _c.blend(dqs, weights, code, as_tol(tol), as_iter(max_iter))
    return out[0] if code == _DIB else out
