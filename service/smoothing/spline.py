"""The model of :mod:`dqpose.smoothing` as B-splines: the uniform cubic B-spline (the position) and
the cumulative one on SO(3) (the orientation), at rest at both ends or free; the structure that
depends on the number of knots only (cached); the banded problem both channels share (sample
weights, the jerk term, its Cholesky factor); and one channel as a linear model about a reference.
"""
from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from dqpose import dq, lie
from dqpose.errors import require

MIN_POSES = 4
_SPANS_PER_TAU = 3         # the spline's span is at most tau / this (dqpose.smoothing's docstring)

# scipy and casadi are the [planning] extra: imported when a problem is built, not with this
# module, which the server imports to serve everything else without them.
if TYPE_CHECKING:
    import scipy.sparse as sp
    from scipy.linalg import cho_solve_banded, cholesky_banded
else:
    sp = cho_solve_banded = cholesky_banded = None


def _solvers() -> None:
    """Imports the extra's modules (``MissingExtra`` when they are not installed)."""
    global sp, cho_solve_banded, cholesky_banded
    require("scipy", "casadi")
    import scipy.sparse as sp
    from scipy.linalg import cho_solve_banded, cholesky_banded


# ---- small SO(3) helpers on rotation-only dual quaternions (real part = quaternion) ------------
def rot_dq(w: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> rotation-only dual quaternions (..., 8)."""
    x = np.zeros(w.shape[:-1] + (6,))
    x[..., :3] = 0.5 * w
    return dq.exp(x)


def rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation part of dual quaternions (..., 8) -> rotation vectors (..., 3), angle in [0, pi]."""
    return 2.0 * dq.log(_only_rotation(r))[..., :3]


def _only_rotation(r: np.ndarray) -> np.ndarray:
    out = np.zeros(r.shape[:-1] + (8,))
    out[..., :4] = r[..., :4]
    return out


def quat_rot(q: np.ndarray) -> np.ndarray:
    out = np.zeros(q.shape[:-1] + (8,))
    out[..., :4] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return out

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
        d = increments(rc)
        cum = np.cumsum(b[:, ::-1], axis=1)[:, ::-1]          # B~_j = b_j + ... + b_3
        r = rc[i]
        for j in (1, 2, 3):
            r = dq.mul(r, rot_dq(cum[:, j, None] * d[i + j - 1]))
        return r


def increments(rc: np.ndarray) -> np.ndarray:
    """Body increments ``d_j = Log(Rc_j-1^-1 Rc_j)``, ``(m - 1, 3)``; row j-1 holds ``d_j``."""
    return rotvec(dq.mul(dq.conj(rc[:-1]), rc[1:]))


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
class Model(NamedTuple):
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
    h_sparsity: Any           # casadi pattern of kron(H, I3), H of bandwidth 3
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


class Problem:
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

    def position_model(self, c: np.ndarray, y: np.ndarray, t: np.ndarray) -> Model:
        return Model(self.s.positions(c, t) - y, np.diff(c, axis=0), self.st.D1E3)

    def rotation_model(self, rc: np.ndarray, r_meas: np.ndarray, t: np.ndarray,
                       jacobian: bool = True) -> Model:
        res = rotvec(dq.mul(dq.conj(r_meas), self.s.rotations(rc, t)))
        d = increments(rc)
        return Model(res, d, _rotation_jacobian(self.s, d) if jacobian else None)
