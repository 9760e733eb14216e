"""The limits on the spline's control points (velocity, acceleration and jerk control points
from the increments) and the QP that keeps one channel within them: the norm limits as boxes
inscribed in the ball, aligned with the reference, solved by PIQP through ``casadi.conic``, rows
added where the solution breaks one (:mod:`dqpose.smoothing`'s docstring, "The solver", step 2).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from dqpose.errors import Infeasible
from dqpose.smoothing.spline import Model, Problem

if TYPE_CHECKING:
    import scipy.sparse as sp

_BOX_ALONG = 0.995        # a of the inscribed box where the reference is at or over the limit
_SELECT = 0.6             # QP rows only where the reference exceeds this share of the limit
_ROUNDS = 4               # QP solves per linearisation (rows added when the solution breaks one)
TOL = 1e-9               # relative slack when checking limits (rounding)
# PIQP's tolerances, in units of the limits (rows are scaled by them) and of the scaled cost;
# the box is drawn that much inside the ball so a row met only to the tolerance stays inside.
_EPS = 1e-6
# No Ruiz preconditioning: the rows and the cost are scaled already (see solve_qp); it cost 15 % of
# the solve and moved the optimum by 1e-9 of itself.
PIQP = {"verbose": False, "eps_abs": _EPS, "eps_rel": _EPS, "preconditioner_iter": 0}


def _quantities(d: np.ndarray, h: float):
    """Velocity, acceleration, jerk control points from the increments."""
    return d / h, np.diff(d, axis=0) / h ** 2, np.diff(d, 2, axis=0) / h ** 3


def breaks(d: np.ndarray, h: float, lims) -> bool:
    return any(L > 0 and np.linalg.norm(Q, axis=1).max(initial=0) > L * (1 + TOL)
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
    import scipy.sparse as sp  # the [planning] extra, here once a Problem was built

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


def solve_qp(prob: Problem, model: Model, lims, name: str, solver=("piqp", PIQP)) -> np.ndarray:
    """Correction ``(m, 3)`` of the control points: the linearised cost under the limits."""
    import casadi as ca
    import scipy.sparse as sp

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
            over = np.setdiff1d(np.flatnonzero(np.linalg.norm(Q, axis=1) > L * (1 + TOL)),
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
    import scipy.sparse as sp

    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.DM(_sparsity(M), M.data.tolist())
