"""The maximum-likelihood fusion in NumPy: the reference the C core (``service/csrc/fusion.c``)
is tested against. The same math, written with :mod:`dqpose.lie`'s vectorised Jacobians.

The static fit (:func:`fit`, ``dq_fuse``):

* ``r_i = Log(X⁻¹ Z_i)``, Jacobian ``-Jl⁻¹(r_i)``, cost ``Σ r_iᵀ W_i r_i`` over the inliers,
  ``W_i = Σ_i⁻¹``;
* Gauss–Newton from the DIB mean weighted by ``det(W_i)^(1/6)``, a step that raises the cost by
  more than 1e-12 (relative) halved up to 30 times, until a step is shorter than ``tol`` (that
  step is not taken: the point it was computed at is the optimum to within ``tol``);
* at the optimum: the information ``H = Σ Aᵢᵀ Wᵢ Aᵢ`` (``A = Jl⁻¹(r)``) and each measurement's
  leave-one-out NIS against the fit of the other inliers.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dqpose import dq, fusion, lie

COST_SLACK = 1e-12
MAX_HALVINGS = 30


class Fit(NamedTuple):
    status: int            # 0 converged, 1 step limit
    mean: np.ndarray
    covariance: np.ndarray  # inverse information at the optimum
    residuals: np.ndarray
    distances: np.ndarray
    nis: np.ndarray
    tested: np.ndarray
    chi2: float
    iterations: int


def _evaluate(X, Z, W):
    r = lie.se3_log(dq.mul(dq.conj(X), Z))
    return r, np.einsum("ni,nij,nj->n", r, W, r)


def _solve(Z, W, start, tol, max_iter):
    X = start
    r, cost = _evaluate(X, Z, W)
    total = cost.sum()
    for it in range(1, max_iter + 1):
        A = lie.se3_left_jacobian_inv(r)
        AtW = np.swapaxes(A, 1, 2) @ W
        H = np.einsum("nij,njk->ik", AtW, A)
        g = np.einsum("nij,nj->i", AtW, r)
        delta = np.linalg.solve(H, g)
        step = float(np.linalg.norm(delta))
        if step < tol:
            return X, 0, it
        for _ in range(MAX_HALVINGS):
            X_new = dq.normalize(dq.mul(X, lie.se3_exp(delta)))
            r_new, cost_new = _evaluate(X_new, Z, W)
            total_new = cost_new.sum()
            if total_new <= total * (1.0 + COST_SLACK) or step < tol:
                break
            delta = 0.5 * delta
            step *= 0.5
        X, r, total = X_new, r_new, total_new
        if step < tol:  # halved below tol: the line search found no lower cost
            return X, 0, it
    return X, 1, max_iter


def fit(Z, S, inlier=None, tol=1e-12, max_iter=100) -> Fit:
    """ML fit of the measurements ``inlier`` selects (all by default), evaluated at every one."""
    Z, S = np.asarray(Z, float), np.asarray(S, float)
    n = Z.shape[0]
    inlier = np.ones(n, bool) if inlier is None else np.asarray(inlier, bool)
    W = np.linalg.inv(S)
    W = 0.5 * (W + np.swapaxes(W, 1, 2))
    Zi, Wi = Z[inlier], W[inlier]
    if Zi.shape[0] == 1:
        mean, status, iterations = Zi[0].copy(), 0, 0
    else:
        weights = np.exp(np.linalg.slogdet(Wi)[1] / 6)
        start = dq.dib(Zi, weights / weights.max())
        mean, status, iterations = _solve(Zi, Wi, start, tol, max_iter)
    r, cost = _evaluate(mean, Z, W)
    A = lie.se3_left_jacobian_inv(r)
    own = np.einsum("nji,njk,nkl->nil", A, W, A) * inlier[:, None, None]
    H = own.sum(axis=0)
    # Leave-one-out: Hj the information of the other inliers (summed, not H minus its own, so a
    # dominant measurement does not cancel the others away); H itself for an outlier.
    others = inlier[None, :] & ~np.eye(n, dtype=bool)
    Hj = np.where(inlier[:, None, None], np.einsum("jk,kab->jab", others.astype(float), own),
                  H[None])
    tested = ~inlier | (np.count_nonzero(inlier) > 1)
    Hj[~tested] = np.eye(6)
    K = A @ np.linalg.solve(Hj, np.swapaxes(A, 1, 2))
    nu = r + inlier[:, None] * np.einsum("nij,njk,nk->ni", K, W, r)
    nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S + K, nu[..., None])[..., 0])
    P = np.linalg.inv(H)
    return Fit(status, mean, 0.5 * (P + P.T), r, np.sqrt(cost), np.where(tested, nis, 0.0),
               tested, float(cost[inlier].sum()), iterations)


class MotionFit(NamedTuple):
    mean: np.ndarray
    twist: np.ndarray
    ell: np.ndarray
    H: np.ndarray           # joint information at the estimate, priors included
    chi2: float
    status: int
    iterations: int
    dt: np.ndarray
    residuals: np.ndarray
    cost: np.ndarray
    G: np.ndarray
    nis: np.ndarray


def motion_start(Z, model, inlier) -> np.ndarray:
    """Where the C fit of a moving body starts (``dq_motion_nearest``): the first inlier taken
    nearest the fusion time, the estimated latencies at their priors."""
    return Z[inlier][int(np.argmin(np.abs(model.dt(model.prior)[inlier])))]


def motion_twist_start(Z, W, model, inlier, start) -> np.ndarray:
    """Where the C fit's twist starts (``motion_twist_start`` in motion.c): the motion between
    the first inliers taken earliest and latest, ``Log(Z_a⁻¹ Z_b) / (t_b − t_a)``, when their
    rotation is within a quarter turn and it fits the inliers better from ``start`` than rest
    does; else rest."""
    rest = np.zeros(6)
    if not model.twist:
        return rest
    t = model.dt(model.prior)
    idx = np.flatnonzero(inlier)
    a, b = idx[np.argmin(t[idx])], idx[np.argmax(t[idx])]
    if not t[b] > t[a]:
        return rest
    D = dq.mul(dq.conj(Z[a]), Z[b])
    if abs(dq.normalize(D)[0]) < np.cos(np.pi / 8):
        return rest
    V0 = lie.se3_log(D) / (t[b] - t[a])
    if not V0.any():
        return rest
    m = model.take(inlier)

    def cost(V):
        _, r, c = fusion._motion_evaluate(start, V, m.prior, Z[inlier], W[inlier], m)
        return float(c.sum()) + m.prior_cost(V, m.prior)
    return V0 if cost(V0) < cost(rest) else rest


def determined_without_each(model, inlier) -> np.ndarray:
    """``dq_motion_determined``: do the inliers other than each measurement determine the state?
    The twist needs two instants (times taken, stamp minus configured latency) unless it has a
    prior or is not estimated."""
    others = np.count_nonzero(inlier) - inlier.astype(int)
    if not model.twist or model.twist_w is not None:
        return others >= 1
    t = (model.stamp - model.latency)[inlier]
    instants = np.unique(t)
    alone = np.zeros(inlier.shape, dtype=bool)
    alone[inlier] = [np.count_nonzero(t == v) == 1 for v in t]
    return instants.size - alone >= 2


def motion_fit(Z, S, model, inlier, start, tested, tol=1e-12, max_iter=100) -> MotionFit:
    """The constant-twist fit (``dq_motion_fit``) of the measurements ``inlier`` selects from
    ``start`` (``model`` a :class:`dqpose.fusion._Model` without ``accel``): the Gauss-Newton
    loop of :func:`dqpose.fusion._motion_solve` with the measurements' own (block-diagonal)
    information; then at the estimate the information ``H = Σ G_iᵀ W_i G_i`` of the inliers
    plus the priors' and, where ``tested``, the leave-one-out NIS ``νᵀ (S + K)⁻¹ ν`` with
    ``K = G Hj⁻¹ Gᵀ``, ``Hj`` the priors' and the other inliers' information (summed, so a
    dominant measurement does not cancel the others away; ``H`` for an outlier) and
    ``ν = r + K W r`` (``r`` for an outlier)."""
    W = np.linalg.inv(S)
    W = 0.5 * (W + np.swapaxes(W, 1, 2))
    n, dim = Z.shape[0], model.dim
    X, V, ell, status, iterations = fusion._motion_solve(
        Z[inlier], model.take(inlier), start, motion_twist_start(Z, W, model, inlier, start),
        model.prior.copy(), tol, max_iter, W[inlier])
    dt, r, cost = fusion._motion_evaluate(X, V, ell, Z, W, model)
    G = fusion._motion_jacobian(V, dt, r, model)
    Hp, _ = model.prior_terms(V, ell)
    own = np.einsum("nji,njk,nkl->nil", G, W, G) * inlier[:, None, None]
    H = own.sum(axis=0) + Hp
    others = (inlier[None, :] & ~np.eye(n, dtype=bool)).astype(float)
    Hj = np.where(inlier[:, None, None], Hp + np.einsum("jk,kab->jab", others, own), H[None])
    Hj[~tested] = np.eye(dim)
    K = G @ np.linalg.solve(Hj, np.swapaxes(G, 1, 2))
    nu = r + inlier[:, None] * np.einsum("nij,njk,nk->ni", K, W, r)
    nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S + K, nu[..., None])[..., 0])
    chi2 = float(cost[inlier].sum()) + model.prior_cost(V, ell)
    return MotionFit(X, V, ell, 0.5 * (H + H.T), chi2, int(status), iterations, dt, r, cost, G,
                     np.where(tested, nis, 0.0))
