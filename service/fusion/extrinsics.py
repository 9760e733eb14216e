"""Uncertain extrinsics: a source's ``extrinsic_covariance`` honoured exactly.

The true extrinsic of source s is ``E_s · Exp(ε_s)``, ``ε_s ~ N(0, Σ_E,s)``, and every measurement
of the source shares that one ``ε_s``, so its measurements are correlated. Measurement i of s in
the world frame, ``W_i = E_s Z_i O_s``, is then ``W_i · Exp(A_i ε_s)`` with
``A_i = Ad((Z_i O_s)⁻¹) = Ad(W_i⁻¹ E_s)`` (exact: ``Exp(ε) M = M Exp(Ad(M⁻¹) ε)``). The
maximum-likelihood answer estimates the body's state (pose; twist and latencies over time)
jointly with one extrinsic ``Ê_s = E_s Exp(Δ)`` per uncertain source under its prior: the cost is
``Σ r_iᵀ Σ_i⁻¹ r_i + Σ_s p_sᵀ Σ_E,s⁻¹ p_s`` with ``r_i = Log(P_i⁻¹ Ê_s E_s⁻¹ W_i)`` (``P_i`` the
prediction of :mod:`dqpose.fusion.motion`) and ``p_s = Log(E_s⁻¹ Ê_s)``: GTSAM's graph of a
``PriorFactorPose3`` on each extrinsic and a ``BetweenFactorPose3(E_s, X, Z_i O_s)`` per
measurement. Gauss–Newton on that joint state (NumPy) with exact Jacobians: ``r_i`` moves by
``Jr⁻¹(r_i) A_i Δ`` for ``Ê_s Exp(Δ)`` and ``p_s`` by ``Jr⁻¹(p_s) Δ``; the covariance is the inverse
joint information, so the body's block is the marginal with every ``ε`` integrated out (GLS with
the shared errors). Several bodies fitted together (:func:`_joint_fit` with several parts) share
the ``ε`` of a common source, and one latency per source whose latency is estimated (a camera's
clock offset is the same whichever body it sees): their joint covariance has the
cross-covariance both cause.

Sources without ``extrinsic_covariance`` never come here: their fusion is the C core's, unchanged.
The leave-one-out NIS is that of :mod:`dqpose.fusion.process_noise` for independent residuals
(the priors stay in). Not supported together with ``acceleration_psd`` (a ``ValueError``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq, lie
from dqpose.fusion.motion import _determined_without_each, _Model, _motion_jacobian, _MotionFit
from dqpose.fusion.process_noise import _COST_SLACK, _MAX_HALVINGS
from dqpose.fusion.results import DOF, Status


@dataclass(frozen=True)
class _Extrinsics:
    """The uncertain extrinsics a set of measurements uses: per measurement the slot of its
    source's ``ε`` (-1: an exact extrinsic); per slot the source, its configured extrinsic and
    the prior's covariance and information."""
    slot: np.ndarray
    names: tuple[str, ...]
    E: np.ndarray
    cov: np.ndarray
    info: np.ndarray


def _extrinsics(names: Sequence[str], table: dict) -> Optional[_Extrinsics]:
    """The uncertain extrinsics of the measurements ``names`` (their sources' in ``table``), in
    order of first appearance; None when none has one."""
    order = [s for s in dict.fromkeys(names)
             if s in table and table[s].extrinsic_covariance is not None]
    if not order:
        return None
    index = {s: k for k, s in enumerate(order)}
    slot = np.array([index.get(s, -1) for s in names], dtype=np.intp)
    ident = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
    E = np.array([ident if table[s].extrinsic is None else table[s].extrinsic for s in order])
    cov = np.array([table[s].extrinsic_covariance for s in order])
    info = np.linalg.inv(cov)
    return _Extrinsics(slot, tuple(order), E, cov, 0.5 * (info + np.swapaxes(info, 1, 2)))


def _no_extrinsics(n: int) -> _Extrinsics:
    """No uncertain extrinsic among ``n`` measurements (a joint fit that shares latencies
    only)."""
    return _Extrinsics(np.full(n, -1, np.intp), (), np.zeros((0, 8)), np.zeros((0, DOF, DOF)),
                       np.zeros((0, DOF, DOF)))


class _Part(NamedTuple):
    """One body in a joint fit: its world-frame measurements, their covariances and model, the
    inliers, and the slots of its measurements' extrinsics (:class:`_Extrinsics`)."""
    Z: np.ndarray
    S: np.ndarray
    model: _Model
    inlier: np.ndarray
    slot: np.ndarray
    start: np.ndarray   # (8,) the pose the fit starts from
    V: np.ndarray       # (6,) its twist
    ell: np.ndarray     # its latencies
    # where each of its latencies is in the fit's latencies, which parts share by source
    # (None: latencies of its own)
    shared: Optional[np.ndarray] = None


class _Prepared(NamedTuple):
    """A :class:`_Part` with what every iteration uses: the measurements' information and, for
    those with an uncertain extrinsic, ``A_i = Ad(W_i⁻¹ E_s)`` (a constant of the data)."""
    Z: np.ndarray
    S: np.ndarray
    model: _Model
    inlier: np.ndarray
    slot: np.ndarray
    start: np.ndarray
    V: np.ndarray
    ell: np.ndarray
    shared: Optional[np.ndarray]
    W: np.ndarray
    A: np.ndarray


def _carried(p: _Part, ext: _Extrinsics) -> np.ndarray:
    """``A_i = Ad(W_i⁻¹ E_s)`` of the measurements with an uncertain extrinsic."""
    has = p.slot >= 0
    if not has.any():
        return np.zeros((0, DOF, DOF))
    return lie.adjoint(dq.mul(dq.conj(p.Z[has]), ext.E[p.slot[has]]))


def _inv(S: np.ndarray) -> np.ndarray:
    W = np.linalg.inv(S)
    return 0.5 * (W + np.swapaxes(W, 1, 2))


def _static_model(n: int) -> _Model:
    """The one-instant fit as a motion model: no twist, no latencies, every stamp at zero."""
    return _Model(stamp=np.zeros(n), latency=np.zeros(n), slot=np.full(n, -1, np.intp),
                  prior=np.zeros(0), prior_w=np.zeros(0), twist=False, twist_w=None)


class _Joint(NamedTuple):
    status: Status
    X: list            # per part: pose, twist, latencies
    V: list
    ell: list
    Ehat: np.ndarray   # the extrinsics estimated
    P: np.ndarray      # the joint covariance (parts' states in order, then the ε's)
    H: np.ndarray
    g: np.ndarray      # the gradient at the answer (the step's right-hand side)
    r: list            # per part: residuals, their Jacobians (r moves by -G Δ), dt
    G: list
    dt: list
    chi2: float
    iterations: int
    offsets: list      # where each part's pose and twist start in the joint state (then the
    #                    latencies, then the ε's)


class _Layout(NamedTuple):
    """Where things are in the joint state: each part's pose and twist (``offsets[k]``), then
    the latencies (one per estimated source, shared by the parts), then one ``ε`` per uncertain
    extrinsic; ``maps[k]`` the latencies of part k among them, ``prior``/``prior_w`` theirs."""
    offsets: list
    latencies: int          # where the latencies start
    maps: list
    prior: np.ndarray
    prior_w: np.ndarray
    total: int

    def columns(self, k: int, model: _Model) -> np.ndarray:
        """The joint state's columns of part k's own state vector (pose, twist, latencies)."""
        return np.r_[np.arange(self.offsets[k], self.offsets[k] + model.offset),
                     self.latencies + self.maps[k]].astype(np.intp)


def _layout(parts, ext) -> _Layout:
    maps, count = [], 0
    for p in parts:
        if p.shared is None:
            maps.append(np.arange(count, count + p.ell.size, dtype=np.intp))
            count += p.ell.size
        else:
            maps.append(np.asarray(p.shared, np.intp))
            count = max(count, int(maps[-1].max()) + 1 if maps[-1].size else 0)
    prior, prior_w = np.zeros(count), np.zeros(count)
    for p, m in zip(parts, maps):       # a source's prior is the same in every part
        prior[m], prior_w[m] = p.model.prior, p.model.prior_w
    offsets = np.cumsum([0] + [p.model.offset for p in parts]).tolist()
    return _Layout(offsets[:-1], offsets[-1], maps, prior, prior_w,
                   offsets[-1] + count + DOF * len(ext.names))


def _latencies(lay: _Layout, L: np.ndarray) -> list:
    return [L[m] for m in lay.maps]


def _residuals(parts, ext, lay: _Layout, X, V, L, Ehat):
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
    pr = lie.se3_log(dq.mul(dq.conj(ext.E), Ehat)) if len(ext.names) else np.zeros((0, DOF))
    cost += float(np.einsum("si,sij,sj->", pr, ext.info, pr))
    return dts, rs, pr, cost


def _state(parts, ext, lay: _Layout, X, V, L, Ehat):
    """Residuals, Jacobians, the normal equations and the cost of every part at the current
    state."""
    total, first_e = lay.total, lay.total - DOF * len(ext.names)
    dts, rs, pr, cost = _residuals(parts, ext, lay, X, V, L, Ehat)
    Gs = []
    H = np.zeros((total, total))
    g = np.zeros(total)
    lat = lay.latencies + np.arange(L.size)
    H[lat, lat] = lay.prior_w
    g[lat] = -lay.prior_w * (L - lay.prior)
    for k, p in enumerate(parts):
        r, dt = rs[k], dts[k]
        G = np.zeros((len(r), DOF, total))
        G[:, :, lay.columns(k, p.model)] = _motion_jacobian(V[k], dt, r, p.model)
        has = p.slot >= 0
        if has.any():
            Ge = -lie.se3_right_jacobian_inv(r[has]) @ p.A
            slots = p.slot[has]
            rows = np.flatnonzero(has)
            for s in np.unique(slots).tolist():
                c = first_e + DOF * s
                G[rows[slots == s], :, c:c + DOF] = Ge[slots == s]
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
        c = slice(first_e + DOF * s, first_e + DOF * (s + 1))
        JtI = Jp[s].T @ ext.info[s]
        H[c, c] += JtI @ Jp[s]
        g[c] -= JtI @ pr[s]
    return rs, Gs, dts, H, g, cost


def _joint_fit(given: Sequence[_Part], ext: _Extrinsics, tol: float, max_iter: int) -> _Joint:
    """Gauss-Newton over every part's state and the ε's (the module's docstring), from the
    parts' starts and the configured extrinsics; a step that raises the cost is halved (the
    C fits' rule)."""
    parts = [_Prepared(*p, W=_inv(p.S), A=_carried(p, ext)) for p in given]
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
    first_e = lay.total - DOF * len(ext.names)
    rs, Gs, dts, H, g, cost = _state(parts, ext, lay, X, V, L, Ehat)
    status, iterations = Status.MAX_ITERATIONS, max_iter
    for it in range(1, max_iter + 1):
        delta = np.linalg.solve(H, g)
        step = float(np.linalg.norm(delta))
        for _ in range(_MAX_HALVINGS):
            X2, V2 = [], []
            for k, p in enumerate(parts):
                d = delta[lay.offsets[k]:lay.offsets[k] + p.model.offset]
                X2.append(dq.normalize(dq.mul(X[k], lie.se3_exp(d[:6]))))
                V2.append(V[k] + d[6:12] if p.model.twist else V[k])
            L2 = L + delta[lay.latencies:first_e]
            de = delta[first_e:].reshape(-1, DOF)
            E2 = dq.normalize(dq.mul(Ehat, lie.se3_exp(de))) if len(de) else Ehat
            if _residuals(parts, ext, lay, X2, V2, L2, E2)[3] <= cost * (1.0 + _COST_SLACK) \
                    or step < tol:
                break
            delta = 0.5 * delta
            step *= 0.5
        X, V, L, Ehat = X2, V2, L2, E2
        rs, Gs, dts, H, g, cost = _state(parts, ext, lay, X, V, L, Ehat)
        if step < tol:
            status, iterations = Status.CONVERGED, it
            break
    P = np.linalg.inv(H)
    return _Joint(status, X, V, _latencies(lay, L), Ehat, 0.5 * (P + P.T), H, g, rs, Gs, dts,
                  cost, iterations, lay.offsets)


def _nis(fit: _Joint, k: int, part: _Part):
    """Each measurement of part ``k``'s leave-one-out NIS against the fit of all the other
    inliers and priors (independent residuals: :func:`dqpose.fusion.process_noise.
    _correlated_nis` with a block-diagonal ``C``)."""
    r, G, S, inlier = fit.r[k], fit.G[k], part.S, part.inlier
    Wi = np.linalg.inv(S)
    P = fit.P
    # the gradient at the answer (0 at an exact optimum) kept, as in _correlated_nis
    w = np.einsum("nij,nj->ni", Wi, r) - np.einsum("nij,njk,k->ni", Wi, G, P @ fit.g)
    WG = Wi @ G
    Om = Wi - WG @ P @ np.swapaxes(WG, 1, 2)
    nis = np.zeros(len(r))
    tested = ~inlier | _determined_without_each(part.model, inlier)
    ok = inlier & tested
    if ok.any():
        nis[ok] = np.einsum("ni,ni->n", w[ok], np.linalg.solve(Om[ok], w[ok][..., None])[..., 0])
    out = ~inlier
    if out.any():
        cov = S[out] + G[out] @ P @ np.swapaxes(G[out], 1, 2)
        nis[out] = np.einsum("ni,ni->n", r[out], np.linalg.solve(cov, r[out][..., None])[..., 0])
    return np.where(tested, nis, 0.0), tested


def _motion_fit_ext(Z, S, model: _Model, ext: _Extrinsics, inlier: np.ndarray, start, V,
                    ell, tol: float, max_iter: int, nis: bool = True) -> _MotionFit:
    """One body's joint fit as a :class:`~dqpose.fusion.motion._MotionFit` (its state's block of
    the covariance first, the ε's after), leave-one-out NIS included when ``nis`` (else its
    ``nis`` and ``tested`` are None)."""
    part = _Part(Z, S, model, inlier, ext.slot, start, V, ell, None)
    fit = _joint_fit([part], ext, tol, max_iter)
    nis_, tested = _nis(fit, 0, part) if nis else (None, None)
    r = fit.r[0]
    cost = np.einsum("ni,nij,nj->n", r, np.linalg.inv(S), r)
    return _MotionFit(fit.status, fit.X[0], fit.V[0], fit.ell[0], fit.H, fit.P, fit.dt[0], r,
                      fit.G[0], cost, fit.chi2, fit.iterations, nis=nis_, tested=tested)


def _relative_covariance(T_a: np.ndarray, T_b: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The covariance of ``T_a⁻¹ T_b`` from the joint covariance ``P`` ``(12, 12)`` of
    ``(δ_a, δ_b)`` (both right perturbations): ``T_a Exp(δ_a)`` and ``T_b Exp(δ_b)`` give
    ``T_ab Exp(δ_b − Ad(T_ab⁻¹) δ_a)`` to first order."""
    T_ab = dq.mul(dq.conj(T_a), T_b)
    J = np.hstack([-lie.adjoint(dq.conj(T_ab)), np.eye(DOF)])
    C = J @ P @ J.T
    return 0.5 * (C + C.T)
