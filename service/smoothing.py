"""Smoothing of noisy recorded pose paths under the tool's velocity and acceleration limits.

``smooth(times, poses, limits, smoothing, rate_hz, free_ends)`` takes a recorded path
(teleoperation, demonstrations: poses ``T_base_tool`` at their time stamps, with noise) and returns
a smooth path on the same clock that a controller can execute: it starts and ends at rest (unless
``free_ends``: a piece of a longer motion, whose ends keep the data's motion), and the tool point's
linear velocity and acceleration and the tool's angular velocity and acceleration stay within
``limits`` as norms (jerk too where a jerk limit is given), measured from the returned samples.

The model
---------
The path is a cubic B-spline with uniform knots over ``[times[0], times[-1]]``, as many spans as
input intervals (N poses, N + 2 control points; the stamps need not be uniform) or, when smoothing,
spans of at most ``tau / 3`` (below: 19 spans per period of the cutoff, where a cubic spline
follows the smoothed path to ~2e-4 of its amplitude; at 100 Hz and ``smoothing = 1`` a knot every
2.6 samples, 0.38 of the unknowns of the QPs below): the tool point's
position is a B-spline in R^3 and the orientation a cumulative B-spline on SO(3)
(``R(t) = Rc_i Exp(B1 d_i+1) Exp(B2 d_i+2) Exp(B3 d_i+3)`` with the body increments
``d_j = Log(Rc_j-1^-1 Rc_j)``). Its first three and last three control points coincide, which
is rest (zero velocity and acceleration) at both ends; with ``free_ends`` every control point is
free and the ends follow the data. The cost is

    sum_k w_k |e_k|^2 + tau^6 * integral |jerk|^2 dt

separately for the position (``e_k`` in metres) and the orientation (``e_k = Log(R_k^-1 R(t_k))``
in radians, the angular jerk that of the increments), ``w_k`` the time each sample covers. Without
limits this is a zero-phase low-pass filter with gain ``1 / (1 + (f / f_c)^6)`` (a smoothing
spline of order 3; the MAP estimate for white jerk of spectral density ``q`` and white noise of
variance ``s^2`` at spacing ``dt`` when ``tau^6 = s^2 dt / q``).

``smoothing`` is ``tau`` in units of ``1 / (2 pi CUTOFF_HZ)``: ``smoothing = 1`` keeps motion
slower than ``f_c = 2 Hz`` (human teleoperation is mostly below) and removes faster motion,
``smoothing = s`` moves the cutoff to ``2 / s`` Hz, and ``0`` keeps the samples as closely as
the limits allow (no jerk term). ``f_c`` is where the gain is 1/2.

Limits are kept on the spline's control points: velocity, acceleration and jerk of a uniform
B-spline are B-splines of the control-point differences, so a bound on the norm of each
difference bounds the norm everywhere between samples (convex hull) and every finite difference
of samples taken at any rate (a finite difference is a positive, unit-mass average of the
derivative). For the position this is exact; for the orientation it holds to first order in the
rotation per span (the neglected terms are at most ``|w| dt`` of the limit, ~1 % at 1 rad/s and
100 Hz, and vanish while the rotation axis turns slowly), and an angular jerk limit bounds the
increments' (body-frame) jerk while the samples' base-frame jerk differs from it by ``w x alpha``.
So the returned samples are measured (:func:`peaks`) and a limit they break is tightened and
solved again.

The solver
----------
1. One banded solve (a Cholesky factor of bandwidth 3 shared by every step below): the
   unconstrained position; a chordal smoothing of the sign-aligned quaternions as the reference
   orientation; one Gauss-Newton step of the orientation cost about it.
2. If the result obeys the limits, that is the answer. Otherwise one QP per offending channel,
   linearised about the unconstrained solution (not the noisy samples), solved by PIQP through
   ``casadi.conic``. The norm limits are written as an inner polyhedral approximation of the
   ball: per control-point difference a box aligned with the reference direction ``u`` and
   inscribed in the ball (``|u.Q| <= a L``, ``|e_i.Q| <= b L``, ``a^2 + 2 b^2 = 1``), with ``a``
   halfway between the reference's share of the limit and 1 (at most 0.995: where a limit binds,
   0.5 % of it is lost along the motion and the sideways freedom is ``b L``, 7 % of it). Three
   rows per limited quantity and control point, the same count as a per-axis box, and only where
   the reference exceeds 60 % of the limit; rows that the solution then breaks are added and the
   QP solved again. The orientation's rows are held back by 0.5 % for the linearisation error of
   the increments; it is relinearised and solved again only if the exact increments still break
   a limit. The exact second-order cone (``|Q| <= L``) needs a conic solver: of casadi's bundled
   plugins only SuperSCS (first order, like OSQP) takes cones (not tried); IPOPT on the exact
   nonlinear problem takes seconds (tests/bench/bench_smoothing.py).
3. The returned samples are measured (:func:`peaks`); a limit they break (the orientation's
   first-order terms, or a base-frame angular jerk) is tightened by the ratio and solved again.

With rest at the ends, the first and last control points of the QP are pinned where the
unconstrained solution puts them, so a path whose ends are too far apart for its duration under the
limits is reported (:class:`Infeasible`) instead of being cut short silently. With ``free_ends``
nothing is pinned: the ends move as far from the data as the limits need.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from dqpose import dq, lie
from dqpose.trajectory import Limits, Peaks, peaks  # noqa: F401 (Peaks: part of the API)
from dqpose.errors import Infeasible, rename, require

__all__ = ["CUTOFF_HZ", "Infeasible", "Peaks", "peaks", "smooth"]

CUTOFF_HZ = 2.0
MIN_POSES = 4

_BOX_ALONG = 0.995        # a of the inscribed box where the reference is at or over the limit
_SELECT = 0.6             # QP rows only where the reference exceeds this share of the limit
_ROUNDS = 4               # QP solves per linearisation (rows added when the solution breaks one)
_LINEARISATIONS = 3       # orientation QPs about successive solutions at most
_ROTATION_MARGIN = 0.005
_CHECKS = 4               # solves with limits tightened by what the samples measured
_SPANS_PER_TAU = 3         # the spline's span is at most tau / this (module docstring)
_TOL = 1e-9               # relative slack when checking limits (rounding)
# PIQP's tolerances, in units of the limits (rows are scaled by them) and of the scaled cost;
# the box is drawn that much inside the ball so a row met only to the tolerance stays inside.
_EPS = 1e-6
# No Ruiz preconditioning: the rows and the cost are scaled already (see _qp); it cost 15 % of
# the solve and moved the optimum by 1e-9 of itself.
_PIQP = {"verbose": False, "eps_abs": _EPS, "eps_rel": _EPS, "preconditioner_iter": 0}


# scipy and casadi are the [planning] extra: imported when a problem is built, not with this
# module, which the server imports to serve everything else without them.
sp = cho_solve_banded = cholesky_banded = None


def _solvers() -> None:
    """Imports the extra's modules (``MissingExtra`` when they are not installed)."""
    global sp, cho_solve_banded, cholesky_banded
    require("scipy", "casadi")
    import scipy.sparse as sp
    from scipy.linalg import cho_solve_banded, cholesky_banded


# ---- small SO(3) helpers on rotation-only dual quaternions (real part = quaternion) ------------
def _rot(w: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> rotation-only dual quaternions (..., 8)."""
    x = np.zeros(w.shape[:-1] + (6,))
    x[..., :3] = 0.5 * w
    return dq.exp(x)


def _rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation part of dual quaternions (..., 8) -> rotation vectors (..., 3), angle in [0, pi]."""
    return 2.0 * dq.log(_only_rotation(r))[..., :3]


def _only_rotation(r: np.ndarray) -> np.ndarray:
    out = np.zeros(r.shape[:-1] + (8,))
    out[..., :4] = r[..., :4]
    return out


def _quat_rot(q: np.ndarray) -> np.ndarray:
    out = np.zeros(q.shape[:-1] + (8,))
    out[..., :4] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return out


# ---- argument checks ---------------------------------------------------------------------------
def _check(times, poses, limits, smoothing, rate_hz):
    try:
        t = np.asarray(times, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"times: expected numbers, got {type(times).__name__}") from None
    if t.ndim != 1:
        raise ValueError(f"times: expected a 1-D array, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"times[{bad[0]}]: {float(t[bad[0]])!r} is not finite")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(f"times[{i}]: {float(t[i])!r} is not after times[{i - 1}] = "
                         f"{float(t[i - 1])!r} (times must be strictly increasing)")
    try:
        x = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"poses: expected numbers, got {type(poses).__name__}") from None
    if x.ndim != 2 or x.shape[1] != 8:
        raise ValueError(f"poses: expected shape (N, 8), got {x.shape}")
    if x.shape[0] != t.shape[0]:
        raise ValueError(f"poses: {x.shape[0]} poses for {t.shape[0]} times")
    if t.shape[0] < MIN_POSES:
        raise ValueError(f"poses: need at least {MIN_POSES} poses, got {t.shape[0]}")
    try:
        q, p = dq.to_pose(x)
    except ValueError as e:
        raise rename(e, {"a": "poses{}"}) from None
    if not isinstance(limits, Limits):
        raise ValueError(f"limits: expected a Limits, got {type(limits).__name__}")
    for name, v in (("smoothing", smoothing), ("rate_hz", rate_hz)):
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name}: expected a number, got {v!r}") from None
        if not (math.isfinite(f) and f >= 0):
            raise ValueError(f"{name}: {v!r} must be finite and >= 0")
    return t, q, p, float(smoothing), float(rate_hz)


# ---- the spline ---------------------------------------------------------------------------------
def _diff(n: int, order: int = 1) -> sp.csr_matrix:
    """Forward differences of the given order, ``(n - order) x n``."""
    coef = np.array([math.comb(order, i) * (-1) ** (order - i) for i in range(order + 1)], float)
    return sp.diags(list(coef), list(range(order + 1)), shape=(n - order, n), format="csr")


def _free_index(j: np.ndarray, n: int, rest: bool) -> np.ndarray:
    """The free control point that control point ``j`` (of ``n + 2``) is: with ``rest`` the first
    three are one and the last three are one (``n - 2`` free), else each is its own."""
    return np.clip(j - 2, 0, n - 3) if rest else j


class _Spline:
    """Uniform cubic B-spline on ``[t0, t1]`` with ``n - 1`` spans, at rest at both ends or not.

    ``m = n + 2`` control points: with ``rest`` the first three and the last three are one each,
    ``c = E z`` with ``z`` the ``n - 2`` free ones; without, all ``n + 2`` are free (``E = I``).
    """

    def __init__(self, t0: float, t1: float, n: int, rest: bool = True):
        self.t0, self.t1, self.spans = t0, t1, n - 1
        self.h = (t1 - t0) / (n - 1)
        self.m, self.z = n + 2, (n - 2 if rest else n + 2)
        self.rest = rest
        self.E = _structure(n, rest).E

    def basis(self, t: np.ndarray):
        """Span index ``i`` (control points ``i .. i+3``) and the four weights at each time."""
        s = (t - self.t0) / self.h
        i = np.clip(np.floor(s).astype(np.int64), 0, self.spans - 1)
        u = s - i
        u2, u3 = u * u, u * u * u
        b = np.stack([(1 - u) ** 3, 3 * u3 - 6 * u2 + 4, -3 * u3 + 3 * u2 + 3 * u + 1, u3], -1) / 6
        return i, b

    def positions(self, c: np.ndarray, t: np.ndarray) -> np.ndarray:
        i, b = self.basis(t)
        return np.einsum("kj,kjx->kx", b, c[i[:, None] + np.arange(4)])

    def rotations(self, rc: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The cumulative B-spline on SO(3) through control rotations ``rc`` (m, 8)."""
        i, b = self.basis(t)
        d = _increments(rc)
        cum = np.cumsum(b[:, ::-1], axis=1)[:, ::-1]          # B~_j = b_j + ... + b_3
        r = rc[i]
        for j in (1, 2, 3):
            r = dq.mul(r, _rot(cum[:, j, None] * d[i + j - 1]))
        return r


def _increments(rc: np.ndarray) -> np.ndarray:
    """Body increments ``d_j = Log(Rc_j-1^-1 Rc_j)``, ``(m - 1, 3)``; row j-1 holds ``d_j``."""
    return _rotvec(dq.mul(dq.conj(rc[:-1]), rc[1:]))


def _kron3(a: sp.spmatrix) -> sp.csr_matrix:
    """``kron(a, I3)``: ``a`` acting on interleaved 3-vectors (index ``3 * k + axis``).

    Built directly in CSR: ``scipy.sparse.kron`` took 2 ms of a 20 ms budget."""
    a = sp.csr_matrix(a)
    a.sort_indices()
    n = np.diff(a.indptr)
    indptr = np.concatenate([[0], np.cumsum(np.repeat(n, 3))])
    row = np.repeat(np.arange(a.shape[0]), n)
    # entries ordered by (row, axis, original position)
    order = np.lexsort((np.arange(3 * a.nnz) % a.nnz, np.repeat(np.arange(3), a.nnz),
                        np.tile(row, 3)))
    indices = (3 * np.tile(a.indices, 3) + np.repeat(np.arange(3), a.nnz))[order]
    data = np.tile(a.data, 3)[order]
    return sp.csr_matrix((data, indices, indptr), shape=(3 * a.shape[0], 3 * a.shape[1]))


# ---- one channel (position or orientation) as a linear model about a reference ------------------
class _Model(NamedTuple):
    """Residuals and increments at the reference, and the increments' Jacobian.

    ``r`` (n, 3) residuals at the samples (their Jacobian in the corrections ``x`` is the spline's
    basis on each axis, ``kron(B E, I3)``); ``d`` (m - 1, 3) increments of the control points,
    ``Jd`` their Jacobian (rows and columns interleaved, ``3 * index + axis``). Velocity,
    acceleration and jerk control points are
    ``d / h``, ``diff(d) / h^2``, ``diff(d, 2) / h^3``; the jerk cost is ``|diff(d, 2)|^2``.
    """
    r: np.ndarray
    d: np.ndarray
    Jd: sp.csr_matrix


def _rotation_jacobian(s: _Spline, d: np.ndarray) -> sp.csr_matrix:
    """Jacobian of the increments under body perturbations ``Rc_j Exp(eps_j)``, in ``z``.

    ``Log(Exp(-a) Exp(d) Exp(b)) = d + Jr^-1(d) b - Jl^-1(d) a`` to first order.
    """
    k = d.shape[0]
    blocks = np.concatenate([lie.so3_right_jacobian_inv(d), -lie.so3_left_jacobian_inv(d)])
    # Row r holds d_r+1 = Log(Rc_r^-1 Rc_r+1): +Jr^-1 on control point r + 1, -Jl^-1 on r,
    # each mapped to its free point (c = E z; duplicates summed).
    zc = _free_index(np.concatenate([np.arange(1, k + 1), np.arange(k)]), s.m - 2, s.rest)
    rr = np.concatenate([np.arange(k), np.arange(k)])
    rows = 3 * rr[:, None, None] + np.arange(3)[None, :, None] + np.zeros((1, 1, 3), int)
    cols = 3 * zc[:, None, None] + np.zeros((1, 3, 1), int) + np.arange(3)[None, None, :]
    return sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * k, 3 * s.z))


class _Structure(NamedTuple):
    """What depends on the number of samples only (cached: a recording is smoothed at one length
    again and again, and scipy.sparse costs ~0.1 ms an operation)."""
    E: sp.csr_matrix          # control points from the free ones
    D1E: sp.csr_matrix        # increments from the free control points
    D1E3: sp.csr_matrix       # the same on interleaved 3-vectors
    D2: sp.csr_matrix         # second differences of the increments (the jerk)
    jerk_band: np.ndarray     # (D2 D1E)^T (D2 D1E) as a full band (7, z): [3 + i - j, j] = H[i, j]
    h_sparsity: object        # casadi pattern of kron(H, I3), H of bandwidth 3
    h_band_index: tuple       # where each of its non-zeros sits in the full band


@functools.lru_cache(maxsize=8)
def _structure(n: int, rest: bool = True) -> _Structure:
    import casadi as ca

    m = n + 2
    z = n - 2 if rest else m
    j = np.arange(m)
    E = sp.csr_matrix((np.ones(m), (j, _free_index(j, n, rest))), shape=(m, z))
    D1E = (_diff(m) @ E).tocsr()
    D2 = _diff(m - 1, 2)
    D3E = (D2 @ D1E).tocsr()
    JJ = (D3E.T @ D3E).todia()
    band = np.zeros((7, z))
    for off, row in zip(JJ.offsets, JJ.data):       # dia: row[j] = H[j - off, j]
        if abs(off) <= 3:
            band[3 - off] += row
    # kron(H, I3) in CSC, rows sorted: column 3j + a holds rows 3i + a, i within 3 of j.
    cols = np.repeat(np.arange(z), 3)
    lo, hi = np.maximum(cols - 3, 0), np.minimum(cols + 4, z)
    count = hi - lo
    i = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)])
    jj = np.repeat(cols, count)
    axis = np.repeat(np.tile(np.arange(3), z), count)
    colptr = np.concatenate([[0], np.cumsum(count)])
    sparsity = ca.Sparsity(3 * z, 3 * z, colptr.tolist(), (3 * i + axis).tolist())
    return _Structure(E, D1E, _kron3(D1E), D2, band, sparsity, (3 + i - jj, jj))


def _knots(t: np.ndarray, tau: float) -> int:
    """Knots of the spline: one per sample, or fewer where the jerk term makes the spline smooth
    on a longer scale (a span at most ``tau / _SPANS_PER_TAU``): the smoothed path is the same to
    far below the noise, and the QPs have that many fewer unknowns."""
    n = t.shape[0]
    if not tau > 0:
        return n
    return int(min(n, max(MIN_POSES, math.ceil((t[-1] - t[0]) * _SPANS_PER_TAU / tau) + 1)))


class _Problem:
    """What both channels share: the spline, the sample weights, the cost and its banded factor."""

    def __init__(self, t: np.ndarray, tau: float, rest: bool = True):
        _solvers()
        n = t.shape[0]
        knots = _knots(t, tau)
        self.s = s = _Spline(float(t[0]), float(t[-1]), knots, rest)
        st = self.st = _structure(knots, rest)
        self.D1E, self.D2 = st.D1E, st.D2
        # Each sample stands for the time it covers (non-uniform stamps weigh fairly).
        w = np.empty(n)
        w[1:-1] = 0.5 * (t[2:] - t[:-2])
        w[0], w[-1] = 0.5 * (t[1] - t[0]), 0.5 * (t[-1] - t[-2])
        self.w = w / s.h
        # The jerk weight tau^6 / h^6 after dividing the cost by h; a trace of it at tau = 0
        # keeps the spline determined where samples are sparse.
        self.lam = (tau / s.h) ** 6 + 1e-9
        i, b = s.basis(t)
        zc = _free_index(i[:, None] + np.arange(4), knots, rest)
        self.BE = sp.csr_matrix((b.ravel(), (np.repeat(np.arange(n), 4), zc.ravel())),
                                shape=(n, s.z))
        band = self.lam * st.jerk_band
        wb = self.w[:, None] * b
        for j1 in range(4):
            for j2 in range(4):
                np.add.at(band, (3 + zc[:, j1] - zc[:, j2], zc[:, j2]), wb[:, j1] * b[:, j2])
        self.band = band
        self.chol = cholesky_banded(band[:4], check_finite=False)

    def qp_hessian(self, factor: float):
        """``factor * kron(H, I3)`` as a casadi DM on the cached pattern."""
        import casadi as ca

        return ca.DM(self.st.h_sparsity, (self.band[self.st.h_band_index] * factor).tolist())

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return cho_solve_banded((self.chol, False), rhs, check_finite=False)

    def fit(self, y: np.ndarray) -> np.ndarray:
        """Control points ``(m, k)`` of the unconstrained smoothing of samples ``y`` ``(n, k)``."""
        return self.s.E @ self.solve(self.BE.T @ (self.w[:, None] * y))

    def gauss_newton(self, r: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Correction ``(m, 3)`` minimising the linearised cost, Jacobians taken as identity
        (exact for the position; first order in the rotation per span for the orientation)."""
        g = (self.BE.T @ (self.w[:, None] * r)
             + self.lam * (self.D1E.T @ (self.D2.T @ (self.D2 @ d))))
        return self.s.E @ -self.solve(g)

    def position_model(self, c: np.ndarray, y: np.ndarray, t: np.ndarray) -> _Model:
        return _Model(self.s.positions(c, t) - y, np.diff(c, axis=0), self.st.D1E3)

    def rotation_model(self, rc: np.ndarray, r_meas: np.ndarray, t: np.ndarray,
                       jacobian: bool = True) -> _Model:
        res = _rotvec(dq.mul(dq.conj(r_meas), self.s.rotations(rc, t)))
        d = _increments(rc)
        return _Model(res, d, _rotation_jacobian(self.s, d) if jacobian else None)


# ---- limits on the control points ----------------------------------------------------------------
def _quantities(d: np.ndarray, h: float):
    """Velocity, acceleration, jerk control points from the increments."""
    return d / h, np.diff(d, axis=0) / h ** 2, np.diff(d, 2, axis=0) / h ** 3


def _breaks(d: np.ndarray, h: float, lims) -> bool:
    return any(L > 0 and np.linalg.norm(Q, axis=1).max(initial=0) > L * (1 + _TOL)
               for Q, L in zip(_quantities(d, h), lims))


def _frames(u: np.ndarray) -> np.ndarray:
    """Orthonormal frames (k, 3, 3) whose first row is the unit vector ``u``."""
    a = np.zeros_like(u)
    a[np.arange(u.shape[0]), np.argmin(np.abs(u), axis=1)] = 1.0
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([u, e1, np.cross(u, e1)], axis=1)


def _box_shape(nrm: np.ndarray, L: float):
    """Half-sizes (in units of ``L``) along and across the box for a reference of norm ``nrm``:
    along, halfway between the reference and the limit (room to move both ways, where a box with
    the reference on its face would hold the solution back where no limit is near); across,
    what keeps the corners on the ball."""
    a = np.clip(0.5 * (1 + nrm / L), 1 / math.sqrt(3), _BOX_ALONG)
    return a, np.sqrt(0.5 * (1 - a * a))


def _box_rows(Q: np.ndarray, Jd: sp.csr_matrix, order: int, h: float, rows: np.ndarray,
              L: float, along: np.ndarray):
    """Rows ``lb <= A x <= ub`` keeping the control points ``Q_j`` of the given derivative order
    (``diff(d, order - 1)_j / h^order``, Jacobian from the increments' ``Jd``) in the box
    inscribed in the ball of radius ``L`` aligned with ``along_j``, in units of ``L`` (rows of
    order one keep the interior-point solver well scaled)."""
    nrm = np.linalg.norm(along, axis=1)
    F = _frames(along / nrm[:, None])
    a, b = _box_shape(nrm, L)
    lim = (1 - 10 * _EPS) * np.stack([a, b, b], axis=1).ravel()
    # Row (k, axis a) = sum_i coef_i F_k[a, :] . d_{rows_k + i}: the frames and the differences
    # in one matrix on the increments, then one product with their Jacobian.
    coef = np.array([math.comb(order - 1, i) * (-1) ** (order - 1 - i) for i in range(order)])
    k = rows.shape[0]
    data = (F[:, :, None, :] * (coef / (L * h ** order))[None, None, :, None]).ravel()
    # each row's 3 * order columns are distinct and ascending: CSR directly, no COO pass
    c = (3 * (rows[:, None, None, None] + np.arange(order)[None, None, :, None])
         + np.arange(3)[None, None, None, :] + np.zeros((1, 3, 1, 1), int)).ravel()
    P = sp.csr_matrix((data, c, np.arange(0, 9 * k * order + 1, 3 * order)),
                      shape=(3 * k, Jd.shape[0]))
    off = np.einsum("kab,kb->ka", F, Q[rows]).ravel() / L
    return P @ Jd, -lim - off, lim - off


def _qp(prob: _Problem, model: _Model, lims, name: str, solver=("piqp", _PIQP)) -> np.ndarray:
    """Correction ``(m, 3)`` of the control points: the linearised cost under the limits."""
    import casadi as ca

    s, h = prob.s, prob.s.h
    # Scaled so the solver's tolerances mean something: corrections in units of the largest
    # step the velocity limit allows, cost per unit of fidelity (the raw values are ~1e-10,
    # where any absolute tolerance accepts a wrong answer; scaling by the largest diagonal, the
    # jerk term's, leaves the fidelity ~1e-7 and PIQP at 1e-6 stopped 1.3 deg off).
    unit = lims[0] * h
    scale = unit / prob.w.max()
    # The gradient with the exact Jacobians; the Hessian that of the banded solve on each axis:
    # exact for the position, for the orientation without the cross-axis terms of the
    # increments' Jacobians (relative size |w| h: the step moves by that share of itself, and
    # the solver's work halves).
    g = (prob.BE.T @ (prob.w[:, None] * model.r)).ravel() \
        + prob.lam * (model.Jd.T @ (prob.D2.T @ (prob.D2 @ model.d)).ravel())
    g = g * scale
    Hd = prob.qp_hessian(unit * scale)
    nx = 3 * s.z
    lbx, ubx = np.full(nx, -np.inf), np.full(nx, np.inf)
    if s.rest:
        lbx[:3] = ubx[:3] = lbx[-3:] = ubx[-3:] = 0.0      # ends pinned at rest
    Qs = _quantities(model.d, h)
    chosen = [np.flatnonzero(np.linalg.norm(Q, axis=1) > _SELECT * L) if L > 0
              else np.zeros(0, int) for Q, L in zip(Qs, lims)]
    along = [Q[c] for Q, c in zip(Qs, chosen)]
    x = np.zeros(nx)
    turned = False
    for _ in range(_ROUNDS):
        parts = [_box_rows(Q, model.Jd, o + 1, h, c, L, al)
                 for o, (Q, c, L, al) in enumerate(zip(Qs, chosen, lims, along))
                 if L > 0 and c.size]
        A = sp.vstack([p[0] for p in parts] or [sp.csr_matrix((0, nx))]).tocsc()
        lba = np.concatenate([p[1] for p in parts] or [np.zeros(0)])
        uba = np.concatenate([p[2] for p in parts] or [np.zeros(0)])
        Ad = _dm(A * unit)
        qp = ca.conic("smooth", solver[0], {"h": Hd.sparsity(), "a": Ad.sparsity()},
                      {"print_time": False, "error_on_fail": False, solver[0]: solver[1]})
        sol = qp(h=Hd, g=g.tolist(), a=Ad, lba=lba.tolist(), uba=uba.tolist(),
                     lbx=lbx.tolist(), ubx=ubx.tolist())
        stats = qp.stats()
        if not stats.get("success"):
            ends = " with rest at both ends" if s.rest else ""
            raise Infeasible(f"{name}: no path within the limits keeps this clock{ends} (QP: "
                             f"{stats.get('return_status')}); allow more time or raise the "
                             f"limits")
        x = unit * np.asarray(sol["x"]).ravel()
        d = model.d + (model.Jd @ x).reshape(-1, 3)
        added = False
        for o, (Q, L) in enumerate(zip(_quantities(d, h), lims)):
            if L <= 0:
                continue
            over = np.setdiff1d(np.flatnonzero(np.linalg.norm(Q, axis=1) > L * (1 + _TOL)),
                                chosen[o])
            if over.size:
                chosen[o] = np.concatenate([chosen[o], over])
                along[o] = np.concatenate([along[o], Q[over]])
                added = True
        if not added and not turned:
            # Where the solution presses on a box's side, the box faces the wrong way (the
            # reference's direction, not the solution's): turned once to the solution's
            # directions and solved again, a step of SQP (after any rows added: turning and
            # adding in one round made PIQP take 5x the iterations on one trial). It brought
            # ours 1.6-5x closer to IPOPT's optimum of the nonlinear problem where limits bind.
            turned = True
            for o, (Q, L) in enumerate(zip(_quantities(d, h), lims)):
                if L <= 0 or not chosen[o].size:
                    continue
                Qc, al = Q[chosen[o]], along[o]
                u = al / np.linalg.norm(al, axis=1, keepdims=True)
                side = np.linalg.norm(Qc - np.einsum("kx,kx->k", Qc, u)[:, None] * u, axis=1)
                if np.any(side > 0.9 * _box_shape(np.linalg.norm(al, axis=1), L)[1] * L):
                    keep = np.linalg.norm(Qc, axis=1) > 1e-9 * L
                    along[o] = np.where(keep[:, None], Qc, al)
                    added = True
        if not added:
            break
    return s.E @ x.reshape(-1, 3)


def _sparsity(M: sp.csc_matrix):
    import casadi as ca

    # Through lists: casadi converts NumPy arrays element by element, 10x slower.
    return ca.Sparsity(M.shape[0], M.shape[1], M.indptr.tolist(), M.indices.tolist())


def _dm(M: sp.spmatrix):
    """A scipy sparse matrix as a casadi DM."""
    import casadi as ca

    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.DM(_sparsity(M), M.data.tolist())


def _rest_to_rest_time(dist: float, v: float, a: float) -> float:
    """Shortest rest-to-rest time over ``dist`` with speed ``v`` and acceleration ``a``."""
    if dist <= v * v / a:
        return 2.0 * math.sqrt(dist / a)
    return dist / v + v / a


def _check_ends(duration: float, dist: float, angle: float, limits: Limits) -> None:
    for what, x, v, a, unit in (
            ("moves", dist, limits.max_linear_velocity, limits.max_linear_acceleration, "m"),
            ("turns", angle, limits.max_angular_velocity, limits.max_angular_acceleration, "rad")):
        need = _rest_to_rest_time(x, v, a)
        if need > duration:
            raise Infeasible(f"times: the path {what} {x:.6g} {unit} between its ends in "
                             f"{duration:.6g} s, which needs at least {need:.6g} s from rest to "
                             f"rest under the limits ({v:g} {unit}/s, {a:g} {unit}/s^2)")


# ---- the entry point ----------------------------------------------------------------------------
def smooth(times, poses, limits: Limits, smoothing: float = 1.0, rate_hz: float = 0.0,
           free_ends: bool = False):
    """A smooth path through noisy time-stamped poses, within ``limits``.

    ``times`` (N,) strictly increasing seconds, ``poses`` (N, 8) unit dual quaternions
    ``T_base_tool``, N >= 4. ``smoothing`` >= 0 sets the cutoff ``2 / smoothing`` Hz (module
    docstring); ``rate_hz`` 0 returns the path at ``times``, else at ``times[0] + k / rate_hz``
    and at ``times[-1]``. Returns ``(times (M,), poses (M, 8))``, starting and ending at rest
    (velocity and acceleration zero, so the ends move off the data as far as the data moves
    there), or, with ``free_ends``, following the data's motion at both ends.

    ``limits``: issue 10's ``Limits`` (velocity and acceleration required; a jerk limit of 0 is
    none). Errors: ``ValueError`` naming the argument and index; :class:`Infeasible` (a
    ``ValueError``) when the limits cannot be met on this clock.
    """
    t, q, p, smoothing, rate_hz = _check(times, poses, limits, smoothing, rate_hz)
    if not isinstance(free_ends, (bool, np.bool_)):
        raise ValueError(f"free_ends: expected True or False, got {free_ends!r}")
    return _smooth(t, q, p, limits, smoothing, rate_hz, rest=not free_ends)


def _unconstrained(t: np.ndarray, q: np.ndarray, p: np.ndarray, smoothing: float,
                   rest: bool = True):
    """The banded start: the problem, position and orientation control points, the samples'
    rotations."""
    prob = _Problem(t, smoothing / (2 * math.pi * CUTOFF_HZ), rest)
    r_meas = _quat_rot(q)
    # Position: exact in one banded solve.
    c = prob.fit(p)
    # Orientation: chordal smoothing of the sign-aligned quaternions as a reference, then one
    # Gauss-Newton step of the geodesic cost about it with the same factor.
    flip = np.cumsum(np.r_[0, np.einsum("ij,ij->i", q[1:], q[:-1]) < 0]) % 2
    rc = _quat_rot(prob.fit(np.where(flip[:, None] == 1, -q, q)))
    m = prob.rotation_model(rc, r_meas, t, jacobian=False)
    return prob, c, dq.mul(rc, _rot(prob.gauss_newton(m.r, m.d))), r_meas


def _evaluate(prob: _Problem, c: np.ndarray, rc: np.ndarray, times: np.ndarray) -> np.ndarray:
    rot = prob.s.rotations(rc, times)
    return dq.from_pose(rot[:, :4], prob.s.positions(c, times))


def _smooth(t, q, p, limits: Limits, smoothing: float, rate_hz: float,
            solver=("piqp", _PIQP), verify: bool = True, rest: bool = True):
    """:func:`smooth` after the checks; ``solver`` and ``verify=False`` (one pass, the samples
    not measured) are for the benchmark's peers."""
    prob, c, rc, r_meas = _unconstrained(t, q, p, smoothing, rest)
    h = prob.s.h
    if rest:
        _check_ends(t[-1] - t[0], float(np.linalg.norm(c[-1] - c[0])),
                    float(np.linalg.norm(_rotvec(dq.mul(dq.conj(rc[0]), rc[-1])))), limits)

    lin = [limits.max_linear_velocity, limits.max_linear_acceleration, limits.max_linear_jerk]
    ang = [limits.max_angular_velocity, limits.max_angular_acceleration, limits.max_angular_jerk]
    out_t = _output_times(t, rate_hz)
    for _ in range(_CHECKS):
        if _breaks(np.diff(c, axis=0), h, lin):
            c = c + _qp(prob, prob.position_model(c, p, t), lin, "poses", solver)
        for _ in range(_LINEARISATIONS):
            if not _breaks(_increments(rc), h, ang):
                break
            # The increments are linearised: held back by their second-order error (~0.5 % of
            # the limit for corrections of a few degrees), one linearisation usually suffices.
            rc = dq.mul(rc, _rot(_qp(prob, prob.rotation_model(rc, r_meas, t),
                                     [L * (1 - _ROTATION_MARGIN) for L in ang], "poses", solver)))
        out = _evaluate(prob, c, rc, out_t)
        if not verify:
            return out_t, out
        # The control points obey the limits; the samples do too for the position (convex
        # hull) and to first order in the rotation per span for the orientation. What the
        # caller gets is measured, and a limit the samples break is tightened by that ratio.
        pk = peaks(out_t, out)
        measured = [[pk.linear_velocity, pk.linear_acceleration, pk.linear_jerk],
                    [pk.angular_velocity, pk.angular_acceleration, pk.angular_jerk]]
        ok = True
        for held, given, seen in zip((lin, ang), _limit_rows(limits), measured):
            for i, (L, v) in enumerate(zip(given, seen)):
                if L > 0 and v > L * (1 + _TOL):
                    # squared: the angular jerk of the samples (base frame) exceeds that of the
                    # increments (body frame) by w x alpha, which does not shrink with the limit
                    held[i] = min(held[i], held[i] * (L / v) ** 2 * (1 - 1e-3))
                    ok = False
        if ok:
            return out_t, out
    raise Infeasible("poses: the smoothed samples still break the limits after "
                     f"{_CHECKS} tightenings")


def _limit_rows(limits: Limits):
    return ((limits.max_linear_velocity, limits.max_linear_acceleration, limits.max_linear_jerk),
            (limits.max_angular_velocity, limits.max_angular_acceleration,
             limits.max_angular_jerk))


def _output_times(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """``times``, or ``times[0] + k / rate_hz`` before ``times[-1]`` and then ``times[-1]``."""
    if rate_hz <= 0:
        return t.copy()
    k = np.arange(int(math.floor((t[-1] - t[0]) * rate_hz * (1 + 1e-12))) + 1)
    out_t = t[0] + k / rate_hz
    return np.append(out_t[out_t < t[-1] - 1e-9 / rate_hz], t[-1])
