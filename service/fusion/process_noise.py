"""Acceleration as process noise: the motion model of :mod:`dqpose.fusion.motion` for a body that
accelerates, with residuals correlated by the model's error (NumPy).

A body that accelerates leaves the constant-twist model, and without process noise the fit then
claims more than it knows (mean NEES 7.4–8.3 instead of 6 for the accelerating body of
tests/fusion/test_process_noise.py). ``acceleration_psd`` ``Q`` (6 × 6, rotation first, rad²/s³
and m²/s³) models exactly this, and nothing more: the true pose at ``τ`` is
``T(τ) = X · Exp(dt V) · Exp(ε(τ))`` with ``ε`` the twice-integrated white noise of power
spectral density ``Q`` started at the fusion time (``ε(τ) = ∫ (τ − s) w(s) ds`` from the fusion
time to ``τ``: the twist a random walk whose covariance grows by ``Q`` per second, the
white-noise-on-acceleration prior, conditioned on the pose and twist at the fusion time). Its
errors are correlated: ``Cov(ε(τ_i), ε(τ_j)) = k(dt_i, dt_j) Q`` with ``k = m² M / 2 − m³ / 6``
(``m``, ``M`` the smaller and larger of ``|dt_i|``, ``|dt_j|``) on the same side of the fusion
time, 0 on opposite sides. The fit uses the joint covariance of all residuals, the measurements'
own block-diagonal ``Σ_i`` plus this (``r`` ≈ ``ε_i − ξ_i``, the model error taken at the
prediction), so the cost is ``rᵀ C⁻¹ r`` with a dense ``C`` (6n × 6n: ≈ 35 ms for 112
measurements in NumPy) and the covariance is the inverse of ``Gᵀ C⁻¹ G``. ``C`` is held at the
latencies it was evaluated at; estimated latencies are re-solved with it re-evaluated at their
estimate until they settle. The leave-one-out NIS conditions each measurement on the others'
residuals as well as on the state (:func:`correlated_nis`); ``distances`` use the
measurement's own share ``Σ_i + |dt_i|³/3 Q``; ``chi2`` is ``rᵀ C⁻¹ r`` (same dof). A rule of
thumb: accelerations of size ``a`` held over a window ``L`` change the twist by ``a L``, the
random walk by ``sqrt(Q L)``, so ``Q ≈ a² L``. ``Q = 0`` is the constant-twist model, computed
exactly as without it.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose import dq, lie
from dqpose._dqcore import COST_SLACK, MAX_HALVINGS
from dqpose.fusion.motion import (
    Model,
    MotionFit,
    constant_twist,
    determined_without_each,
    motion_evaluate,
    motion_jacobian,
)
from dqpose.fusion.results import DOF, Status

# The C fits' step rule (service/csrc/gn.h): a step that raises the cost by more than
# COST_SLACK (relative) is halved, at most MAX_HALVINGS times.


def kernel(dt: np.ndarray) -> np.ndarray:
    """``k(dt_i, dt_j)``: the covariance, per unit power spectral density, of the twice-integrated
    white noise at offsets ``dt_i`` and ``dt_j`` from the fusion time (zero on opposite sides of
    it: given the state there, past and future are independent)."""
    a = np.abs(dt)
    m = np.minimum(a[:, None], a[None])
    M = np.maximum(a[:, None], a[None])
    same = np.sign(dt)[:, None] * np.sign(dt)[None] > 0
    return np.where(same, 0.5 * m * m * M - m ** 3 / 6.0, 0.0)


def _model_error(S: np.ndarray, dt: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The joint covariance ``(6n, 6n)`` of the residuals: the measurements' own (block
    diagonal) and the motion model's error, ``k(dt_i, dt_j) · Q`` between measurements i and j."""
    n = S.shape[0]
    C = np.kron(kernel(dt), accel)
    idx = np.arange(n)
    C.reshape(n, DOF, n, DOF)[idx, :, idx, :] += S
    return 0.5 * (C + C.T)


def _information(S: np.ndarray, dt: np.ndarray, accel: np.ndarray) -> np.ndarray:
    C = np.linalg.inv(_model_error(S, dt, accel))
    return 0.5 * (C + C.T)


def marginal_information(S: np.ndarray, dt: np.ndarray, accel: Optional[np.ndarray]):
    """Each measurement's information with its own share of the model error, ``(S_i + dt_i³/3
    Q)⁻¹``: what its distance is measured with."""
    if accel is None:
        return None
    W = np.linalg.inv(S + (np.abs(dt) ** 3 / 3.0)[:, None, None] * accel)
    return 0.5 * (W + np.swapaxes(W, 1, 2))


def _data_cost(r: np.ndarray, info: np.ndarray) -> float:
    """``rᵀ C⁻¹ r`` with ``info`` the joint information ``C⁻¹`` ``(6n, 6n)``, or (the reference
    tests/fusion_reference.py checks the C constant-twist fit with) the measurements' own
    ``(n, 6, 6)`` when they are independent."""
    if info.ndim == 3:
        return float(np.einsum("ni,nij,nj->", r, info, r))
    rf = r.ravel()
    return float(rf @ info @ rf)


def _normal(G: np.ndarray, r: np.ndarray, info: np.ndarray):
    """The data's information ``Gᵀ C⁻¹ G`` and gradient ``Gᵀ C⁻¹ r`` (``info`` as for
    :func:`_data_cost`)."""
    if info.ndim == 3:
        GtW = np.swapaxes(G, 1, 2) @ info
        return (np.tensordot(GtW, G, axes=([0, 2], [0, 1])),
                (GtW @ r[..., None]).sum(axis=0)[:, 0])
    Gf = G.reshape(-1, G.shape[-1])
    CG = info @ Gf
    return Gf.T @ CG, CG.T @ r.ravel()


def motion_solve(Z, model: Model, X, V, ell, tol: float, max_iter: int, info: np.ndarray):
    """Gauss-Newton over pose, twist and latencies in NumPy, for residuals correlated by the
    model error: ``info`` their joint information (held at its value at the start of this
    solve). The step, its halving and the step shorter than ``tol`` left untaken are the C
    constant-twist fit's (``dq_motion_fit``)."""
    dt, r, _ = motion_evaluate(X, V, ell, Z, None, model)
    total = _data_cost(r, info) + model.prior_cost(V, ell)
    off = model.offset
    for it in range(1, max_iter + 1):
        G = motion_jacobian(V, dt, r, model)
        Hd, gd = _normal(G, r, info)
        Hp, gp = model.prior_terms(V, ell)
        H = Hd + Hp
        g = gd + gp
        delta = np.linalg.solve(H, g)
        step = float(np.linalg.norm(delta))
        if step < tol:
            return X, V, ell, Status.CONVERGED, it
        for _ in range(MAX_HALVINGS):
            X_new = dq.normalize(dq.mul(X, lie.se3_exp(delta[:6])))
            V_new = V + delta[6:12] if model.twist else V
            ell_new = ell + delta[off:]
            dt_new, r_new, _ = motion_evaluate(X_new, V_new, ell_new, Z, None, model)
            total_new = _data_cost(r_new, info) + model.prior_cost(V_new, ell_new)
            if total_new <= total * (1.0 + COST_SLACK) or step < tol:
                break
            delta = 0.5 * delta
            step *= 0.5
        X, V, ell, dt, r, total = X_new, V_new, ell_new, dt_new, r_new, total_new
        if step < tol:
            return X, V, ell, Status.CONVERGED, it
    return X, V, ell, Status.MAX_ITERATIONS, max_iter


# The model error's covariance depends on the latencies; estimated, they are re-solved with it
# evaluated at the previous solution until they move less than this (seconds), at most _PASSES.
_LATENCY_SETTLED = 1e-9
_PASSES = 4


def correlated_fit(Z, S, model: Model, inlier: np.ndarray, tol: float,
                    max_iter: int) -> MotionFit:
    """Fit of the measurements ``inlier`` selects under the model error, evaluated at every
    measurement, started from the constant-twist fit."""
    Zi, Si, mi = Z[inlier], S[inlier], model.take(inlier)
    accel = model.accel
    assert accel is not None        # this fit is the model error's
    # the constant-twist fit starts it: cheap, and near when the model error is small
    X, V, ell, *_, iterations = constant_twist(Z, S, model, inlier, tol, max_iter)[:7]
    iterations = int(iterations)
    at = ell
    Cinv = _information(Si, mi.dt(at), accel)
    for _ in range(_PASSES if ell.size else 1):
        X, V, ell, status, it = motion_solve(Zi, mi, X, V, ell, tol, max_iter, Cinv)
        iterations += it
        if np.all(np.abs(ell - at) < _LATENCY_SETTLED):
            break
        at = ell
        Cinv = _information(Si, mi.dt(at), accel)
    dt, r, _ = motion_evaluate(X, V, ell, Z, None, model)
    Wm = marginal_information(S, dt, model.accel)
    cost = np.einsum("ni,nij,nj->n", r, Wm, r)
    G = motion_jacobian(V, dt, r, model)
    Hp, _ = model.prior_terms(V, ell)
    Hd, _ = _normal(G[inlier], r[inlier], Cinv)
    H = Hd + Hp
    P = np.linalg.inv(H)
    chi2 = _data_cost(r[inlier], Cinv) + model.prior_cost(V, ell)
    return MotionFit(status, X, V, ell, H, 0.5 * (P + P.T), dt, r, G, cost, float(chi2),
                      iterations, Cinv)


def _blocks(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The 6 × 6 diagonal blocks of ``A Bᵀ`` (both ``(6m, k)``)."""
    m = A.shape[0] // DOF
    return np.einsum("mak,mbk->mab", A.reshape(m, DOF, -1), B.reshape(m, DOF, -1))


def correlated_nis(fit: MotionFit, S, inlier: np.ndarray, model: Model):
    """The leave-one-out NIS when the model error correlates the residuals (joint covariance
    ``C``, information ``H`` of the inliers' fit). An inlier i: with ``Ω = C⁻¹ − C⁻¹ G H⁻¹ Gᵀ
    C⁻¹`` over the inliers, ``(Ω r)_iᵀ Ω_ii⁻¹ (Ω r)_i`` is the NIS of its residual against the
    prediction from all the others (its conditional mean given their residuals included); with
    independent residuals this is the joint fit's (service/csrc/joint_nis.c). Any other
    measurement j: its residual less its conditional mean given the inliers', against that
    covariance plus the fit's."""
    n, dim = S.shape[0], model.dim
    rows = np.repeat(inlier, DOF)
    assert fit.G is not None and fit.Cinv is not None and model.accel is not None  # correlated
    G = fit.G.reshape(n * DOF, dim)
    r = fit.r.ravel()
    Ci = fit.Cinv
    A = Ci @ G[rows]
    u = Ci @ r[rows]
    Hinv = fit.P
    _, gp = model.prior_terms(fit.V, fit.ell)
    w = u - A @ (Hinv @ (A.T @ r[rows] + gp))
    tested = ~inlier | determined_without_each(model, inlier)
    nis = np.zeros(n)
    k = np.flatnonzero(inlier)
    Om = Ci.reshape(k.size, DOF, k.size, DOF)[np.arange(k.size), :, np.arange(k.size), :]
    Om = Om - _blocks(A, A @ Hinv)
    ok = tested[k]
    Om[~ok] = np.eye(DOF)
    w = w.reshape(-1, DOF)
    nis[k] = np.einsum("ni,ni->n", w, np.linalg.solve(Om, w[..., None])[..., 0])
    out = ~inlier
    if out.any():
        C = _model_error(S, fit.dt, model.accel)
        cols = np.repeat(out, DOF)
        Cji = C[np.ix_(cols, rows)]
        nu = (r[cols] - Cji @ u).reshape(-1, DOF)
        M = G[cols] - Cji @ A
        cov = (C[np.ix_(cols, cols)].reshape(-1, DOF, out.sum(), DOF)
               [np.arange(out.sum()), :, np.arange(out.sum()), :]
               - _blocks(Cji, Cji @ Ci) + _blocks(M, M @ Hinv))
        nis[out] = np.einsum("ni,ni->n", nu, np.linalg.solve(cov, nu[..., None])[..., 0])
    return np.where(tested, nis, 0.0), tested
