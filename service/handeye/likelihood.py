"""Maximum likelihood on ``(X, Z)``: Gauss–Newton on SE(3)×SE(3) with right perturbations and
exact Jacobians (:mod:`dqpose.lie`) of the residuals ``r_i = Log(Z⁻¹ A_i X C_i)``, weighted by
the residual covariances of :mod:`dqpose.handeye.noise` (re-evaluated, and when estimated
re-estimated, at every iterate). The covariance of ``(X, Z)`` is the inverse of the information
``Σ Jᵢᵀ Σ_r,i⁻¹ Jᵢ`` at the optimum.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dqpose import dq, lie
from dqpose.errors import Infeasible
from dqpose.handeye.noise import Noise

TOL = 1e-8                            # a step this short in its own σ (squared): converged
_MAX_ITER = 30


def evaluate(A, C, X, Z):
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z), A), X), C)
    return E, lie.se3_log(E)


@dataclass
class Fit:
    X: np.ndarray
    Z: np.ndarray
    E: np.ndarray
    r: np.ndarray
    J: np.ndarray      # (n,6,12) d r_i / d(δx, δz)
    S: np.ndarray      # (n,6,6) residual covariances
    H: np.ndarray      # (12,12) information
    P: np.ndarray      # (12,12) covariance at the noise as estimated or given
    iterations: int
    reported: np.ndarray   # (12,12) P with the noise estimate's uncertainty (Kenward–Roger)


def linearise(A, C, AdCi, X, Z, noise: Noise, use):
    E, r = evaluate(A, C, X, Z)
    Jri = lie.se3_right_jacobian_inv(r)
    S = noise(X, C, r, Jri, use)
    J = np.empty((len(r), 6, 12))
    # r_i = Log(Z⁻¹ A_i X C_i): X Exp(δx) moves it by Jr⁻¹ Ad(C_i⁻¹) δx, Z Exp(δz) by
    # −Jl⁻¹(r) δz = −Jr⁻¹(r) Ad(E_i⁻¹) δz.
    J[:, :, :6] = Jri @ AdCi
    J[:, :, 6:] = -Jri @ lie.adjoint(dq.inv(E))
    return E, r, J, S


def gauss_newton(A, C, X, Z, noise: Noise, use) -> Fit:
    """Gauss–Newton on ``(X, Z)`` over the samples ``use``, minimising Σ r_iᵀ Σ_r,i⁻¹ r_i; steps
    halved while the cost (at the step's weights) rises."""
    Au, Cu = A[use], C[use]
    AdCi = lie.adjoint(dq.inv(Cu))
    it = 0
    for it in range(1, _MAX_ITER + 1):  # noqa: B007 (the count is read after the loop)
        E, r, J, S = linearise(Au, Cu, AdCi, X, Z, noise, use)
        for _ in range(20 if noise.estimate else 1):
            W = np.linalg.inv(S)
            JtW = np.swapaxes(J, 1, 2) @ W
            H = (JtW @ J).sum(axis=0)
            g = np.einsum("nij,nj->i", JtW, r)
            if not noise.estimate:
                break
            # The shared noise settled at this linearisation's optimum (the residuals after
            # the step), so the outer iterations converge as fast as with known noise.
            try:
                Hi = np.linalg.inv(H)
            except np.linalg.LinAlgError:
                break
            S, settled = noise.update(r, J, Hi)
            if settled:
                break
        cost = float(np.einsum("ni,nij,nj->", r, W, r))
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            step = None
        if step is None or not np.all(np.isfinite(step)):
            raise Infeasible("base_flange: the motions do not determine X and Z (singular "
                             "information); add poses rotating about other axes")
        t = 1.0
        for _ in range(30):
            Xn = dq.mul(X, lie.se3_exp(t * step[:6]))
            Zn = dq.mul(Z, lie.se3_exp(t * step[6:]))
            rn = evaluate(Au, Cu, Xn, Zn)[1]
            if float(np.einsum("ni,nij,nj->", rn, W, rn)) <= cost * (1 + 1e-12) + 1e-300:
                break
            t *= 0.5
        X, Z = Xn, Zn
        if (t * t) * float(step @ H @ step) < TOL or t < 1e-8:
            break
    E, r, J, S = linearise(Au, Cu, AdCi, X, Z, noise, use)
    for _ in range(20 if noise.estimate else 1):   # the shared noise settled at the optimum
        JtW = np.swapaxes(J, 1, 2) @ np.linalg.inv(S)
        H = (JtW @ J).sum(axis=0)
        H = 0.5 * (H + H.T)
        if not noise.estimate:
            break
        S, settled = noise.update(r, J, np.linalg.inv(H))
        if settled:
            break
    try:
        P = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        P = np.full((12, 12), np.inf)
    if not np.all(np.isfinite(P)):
        raise Infeasible("base_flange: the motions do not determine X and Z (singular "
                         "information); add poses rotating about other axes")
    P = 0.5 * (P + P.T)
    return Fit(X, Z, E, r, J, np.array(S), H, P, it,
                noise.kenward_roger(J, P) if noise.estimate else P)


def standardised(fit: Fit) -> tuple[np.ndarray, np.ndarray]:
    """``r_iᵀ S_i⁻¹ r_i`` with ``S_i = Σ_r,i − J_i H⁻¹ J_iᵀ``, and ``S_i⁻¹ r_i`` (for the
    leave-one-out shift)."""
    Si = fit.S - fit.J @ fit.P @ np.swapaxes(fit.J, 1, 2)
    Si = 0.5 * (Si + np.swapaxes(Si, 1, 2))
    # A sample that alone fixes a direction has S_i singular there: pseudo-inverse, not NaN.
    y = np.einsum("nij,nj->ni", np.linalg.pinv(Si, rcond=1e-10, hermitian=True), fit.r)
    return np.einsum("ni,ni->n", fit.r, y), y
