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

from dqpose import dq, lie
from dqpose.fusion.motion import motion_evaluate, motion_jacobian
from dqpose.fusion.process_noise import motion_solve

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
        _, r, c = motion_evaluate(start, V, m.prior, Z[inlier], W[inlier], m)
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
    ``start`` (``model`` a :class:`dqpose.fusion.motion.Model` without ``accel``): the
    Gauss-Newton loop of :func:`dqpose.fusion.process_noise.motion_solve` with the measurements'
    own (block-diagonal)
    information; then at the estimate the information ``H = Σ G_iᵀ W_i G_i`` of the inliers
    plus the priors' and, where ``tested``, the leave-one-out NIS ``νᵀ (S + K)⁻¹ ν`` with
    ``K = G Hj⁻¹ Gᵀ``, ``Hj`` the priors' and the other inliers' information (summed, so a
    dominant measurement does not cancel the others away; ``H`` for an outlier) and
    ``ν = r + K W r`` (``r`` for an outlier)."""
    W = np.linalg.inv(S)
    W = 0.5 * (W + np.swapaxes(W, 1, 2))
    n, dim = Z.shape[0], model.dim
    X, V, ell, status, iterations = motion_solve(
        Z[inlier], model.take(inlier), start, motion_twist_start(Z, W, model, inlier, start),
        model.prior.copy(), tol, max_iter, W[inlier])
    dt, r, cost = motion_evaluate(X, V, ell, Z, W, model)
    G = motion_jacobian(V, dt, r, model)
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


# ---- the joint fit with uncertain extrinsics (dq_joint_fit, bound as _dqcore.joint_fit) -------
# dqpose.fusion.extrinsics's model and layout; here its Gauss-Newton in NumPy, as it was before
# service/csrc/joint.c: residuals, Jacobians and normal equations of every part, the covariance
# and each measurement's leave-one-out NIS.


class Prepared(NamedTuple):
    """A :class:`~dqpose.fusion.extrinsics.Part` with what every iteration uses: the
    measurements' information and, for those with an uncertain extrinsic,
    ``A_i = Ad(W_i⁻¹ E_s)`` (a constant of the data)."""
    Z: np.ndarray
    S: np.ndarray
    model: object
    inlier: np.ndarray
    slot: np.ndarray
    start: np.ndarray
    V: np.ndarray
    ell: np.ndarray
    shared: object
    W: np.ndarray
    A: np.ndarray


def _carried(p, ext) -> np.ndarray:
    has = p.slot >= 0
    if not has.any():
        return np.zeros((0, 6, 6))
    return lie.adjoint(dq.mul(dq.conj(p.Z[has]), ext.E[p.slot[has]]))


def _inv(S: np.ndarray) -> np.ndarray:
    W = np.linalg.inv(S)
    return 0.5 * (W + np.swapaxes(W, 1, 2))


def _latencies(lay, L: np.ndarray) -> list:
    return [L[m] for m in lay.maps]


def joint_residuals(parts, ext, lay, X, V, L, Ehat):
    """Every part's ``dt`` and residuals at the current state, and the total cost."""
    shift = dq.mul(Ehat, dq.conj(ext.E)) if len(ext.names) else ext.E   # Ê E⁻¹ per slot
    ell = _latencies(lay, L)
    dts, rs = [], []
    cost = float(np.sum(lay.prior_w * (L - lay.prior) ** 2))
    for k, p in enumerate(parts):
        dt = p.model.dt(ell[k])
        W = p.Z.copy()
        has = p.slot >= 0
        if has.any():
            W[has] = dq.mul(shift[p.slot[has]], p.Z[has])
        pred = dq.mul(X[k], lie.se3_exp(dt[:, None] * V[k]))
        r = lie.se3_log(dq.mul(dq.conj(pred), dq.normalize(W)))
        m = p.inlier
        cost += float(np.einsum("ni,nij,nj->", r[m], p.W[m], r[m]))
        if p.model.twist and p.model.twist_w is not None:
            cost += float(V[k] @ p.model.twist_w @ V[k])
        dts.append(dt)
        rs.append(r)
    pr = lie.se3_log(dq.mul(dq.conj(ext.E), Ehat)) if len(ext.names) else np.zeros((0, 6))
    cost += float(np.einsum("si,sij,sj->", pr, ext.info, pr))
    return dts, rs, pr, cost


def joint_state(parts, ext, lay, X, V, L, Ehat):
    """Residuals, Jacobians, the normal equations and the cost of every part at the current
    state."""
    total, first_e = lay.total, lay.total - 6 * len(ext.names)
    dts, rs, pr, cost = joint_residuals(parts, ext, lay, X, V, L, Ehat)
    Gs = []
    H = np.zeros((total, total))
    g = np.zeros(total)
    lat = lay.latencies + np.arange(L.size)
    H[lat, lat] = lay.prior_w
    g[lat] = -lay.prior_w * (L - lay.prior)
    for k, p in enumerate(parts):
        r, dt = rs[k], dts[k]
        G = np.zeros((len(r), 6, total))
        G[:, :, lay.columns(k, p.model)] = motion_jacobian(V[k], dt, r, p.model)
        has = p.slot >= 0
        if has.any():
            Ge = -lie.se3_right_jacobian_inv(r[has]) @ p.A
            slots = p.slot[has]
            rows = np.flatnonzero(has)
            for s in np.unique(slots).tolist():
                c = first_e + 6 * s
                G[rows[slots == s], :, c:c + 6] = Ge[slots == s]
        m = p.inlier
        GtW = np.swapaxes(G[m], 1, 2) @ p.W[m]
        H += np.tensordot(GtW, G[m], axes=([0, 2], [0, 1]))
        g += (GtW @ r[m][..., None]).sum(axis=0)[:, 0]
        if p.model.twist and p.model.twist_w is not None:
            sl = slice(lay.offsets[k] + 6, lay.offsets[k] + 12)
            H[sl, sl] += p.model.twist_w
            g[sl] -= p.model.twist_w @ V[k]
        Gs.append(G)
    Jp = lie.se3_right_jacobian_inv(pr)
    for s in range(len(ext.names)):
        c = slice(first_e + 6 * s, first_e + 6 * (s + 1))
        JtI = Jp[s].T @ ext.info[s]
        H[c, c] += JtI @ Jp[s]
        g[c] -= JtI @ pr[s]
    return rs, Gs, dts, H, g, cost


def joint_fit(given, ext, tol, max_iter):
    """Gauss-Newton over every part's state and the ε's from the parts' starts and the
    configured extrinsics: a step that raises the cost by more than 1e-12 (relative) halved up
    to 30 times, then taken; a step shorter than ``tol`` is not taken and ends the loop, one
    halved below it is taken and ends it (:func:`_solve`'s rule). An
    :class:`dqpose.fusion.extrinsics._Joint` (its ``nis``, ``tested`` and ``cost`` None)."""
    from dqpose.fusion.extrinsics import _Joint, _layout
    parts = [Prepared(*p, W=_inv(p.S), A=_carried(p, ext)) for p in given]
    lay = _layout(parts, ext)
    X = [p.start for p in parts]
    V = [p.V for p in parts]
    # a shared latency starts from the mean of the parts' own estimates of it
    L, seen = np.zeros(lay.prior.size), np.zeros(lay.prior.size)
    for p, m in zip(parts, lay.maps):
        np.add.at(L, m, p.ell)
        np.add.at(seen, m, 1.0)
    L = np.where(seen > 0, L / np.maximum(seen, 1.0), lay.prior)
    Ehat = ext.E.copy()
    first_e = lay.total - 6 * len(ext.names)
    rs, Gs, dts, H, g, cost = joint_state(parts, ext, lay, X, V, L, Ehat)
    status, iterations = 1, max_iter
    for it in range(1, max_iter + 1):
        delta = np.linalg.solve(H, g)
        step = float(np.linalg.norm(delta))
        if step < tol:   # not taken: the state is the optimum to within tol
            status, iterations = 0, it
            break
        for _ in range(MAX_HALVINGS):
            X2, V2 = [], []
            for k, p in enumerate(parts):
                d = delta[lay.offsets[k]:lay.offsets[k] + p.model.offset]
                X2.append(dq.normalize(dq.mul(X[k], lie.se3_exp(d[:6]))))
                V2.append(V[k] + d[6:12] if p.model.twist else V[k])
            L2 = L + delta[lay.latencies:first_e]
            de = delta[first_e:].reshape(-1, 6)
            E2 = dq.normalize(dq.mul(Ehat, lie.se3_exp(de))) if len(de) else Ehat
            if joint_residuals(parts, ext, lay, X2, V2, L2, E2)[3] <= cost * (1.0 + COST_SLACK) \
                    or step < tol:
                break
            delta = 0.5 * delta
            step *= 0.5
        X, V, L, Ehat = X2, V2, L2, E2
        rs, Gs, dts, H, g, cost = joint_state(parts, ext, lay, X, V, L, Ehat)
        if step < tol:
            status, iterations = 0, it
            break
    P = np.linalg.inv(H)
    return _Joint(status, X, V, _latencies(lay, L), Ehat, 0.5 * (P + P.T), H, g, rs, Gs, dts,
                  cost, iterations, lay.offsets)


def joint_nis(fit, k: int, part):
    """Each measurement of part ``k``'s leave-one-out NIS against the fit of all the other
    inliers and priors (independent residuals: the gradient at the answer kept), and which are
    tested (an outlier, or an inlier whose part stays determined without it)."""
    r, G, S, inlier = fit.r[k], fit.G[k], part.S, part.inlier
    Wi = np.linalg.inv(S)
    P = fit.P
    w = np.einsum("nij,nj->ni", Wi, r) - np.einsum("nij,njk,k->ni", Wi, G, P @ fit.g)
    WG = Wi @ G
    Om = Wi - WG @ P @ np.swapaxes(WG, 1, 2)
    nis = np.zeros(len(r))
    tested = ~inlier | determined_without_each(part.model, inlier)
    ok = inlier & tested
    if ok.any():
        nis[ok] = np.einsum("ni,ni->n", w[ok], np.linalg.solve(Om[ok], w[ok][..., None])[..., 0])
    out = ~inlier
    if out.any():
        cov = S[out] + G[out] @ P @ np.swapaxes(G[out], 1, 2)
        nis[out] = np.einsum("ni,ni->n", r[out], np.linalg.solve(cov, r[out][..., None])[..., 0])
    return np.where(tested, nis, 0.0), tested
