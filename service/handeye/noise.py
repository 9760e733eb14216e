"""The residual covariances ``Σ_r,i`` of the pose-level fit: transported from the poses' given
noise, or estimated as three variance components by REML, with the estimate's uncertainty
propagated into the reported covariance (Kenward–Roger).

Noise on both the robot and the camera poses enters each residual ``r_i = Log(Z⁻¹ A_i X C_i)``
through ``Σ_r,i = Jr⁻¹(r_i) (Ad(K_i⁻¹) Σ_A,i Ad(K_i⁻¹)ᵀ + Σ_C,i) Jr⁻ᵀ``, ``K_i = X C_i`` (the
errors-in-variables problem with the true poses eliminated, to first order).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError
from dqpose.handeye.checks import checked_covariances
from dqpose.handeye.setups import EYE_IN_HAND, EYE_TO_HAND

FLOORS = np.array([1e-9, 1e-9, 1e-12]) ** 2   # smallest estimated variances: exact data


def transported(X, C, SA, SC, Jri):
    """Σ_r,i = Jr⁻¹(r) (Ad(K⁻¹) Σ_A Ad(K⁻¹)ᵀ + Σ_C) Jr⁻ᵀ, K = X C_i (see the module docstring)."""
    S = SC.copy() if SC is not None else np.zeros((C.shape[0], 6, 6))
    if SA is not None:
        S = S + lie.cov_left_to_right(dq.mul(X, C), SA)
    return Jri @ S @ np.swapaxes(Jri, -1, -2)


_ROT, _TRANS = np.diag([1.0] * 3 + [0.0] * 3), np.diag([0.0] * 3 + [1.0] * 3)


class Noise:
    """The residual covariances ``Σ_r,i``: transported from the given pose noise, or estimated.

    Estimated (no covariance given): three isotropic variance components, camera rotation
    ``θ₁``, translation ``θ₂`` (the camera's and the robot's: isotropic translation noise on
    either pose reaches the residual identically) and robot rotation ``θ₃``, transported like a
    given robot noise (it reaches the residual's translation through the lever arm ``X C_i``,
    which is what tells it from the camera's). ``Σ_r,i = Σ θ_k G_k,i``; the θ are re-estimated
    at every Gauss–Newton iterate by the iterated variance-component (REML) update
    ``θ_k ← θ_k · Σ rᵢᵀWᵢG_kWᵢrᵢ / (Σ tr(WᵢG_k) − tr(P Σ JᵢᵀWᵢG_kWᵢJᵢ))``, which keeps them
    positive and takes the 12 fitted degrees of freedom out by leverage (:meth:`update`)."""

    def __init__(self, SA, SC, estimate: bool, robot_frames: Optional[np.ndarray] = None):
        self.SA, self.SC, self.estimate = SA, SC, estimate
        self.frames = robot_frames            # Ad(F_i) for eye_to_hand (A = F⁻¹), else None
        self.theta: Optional[np.ndarray] = None
        self.step: Optional[np.ndarray] = None
        self.G: Optional[np.ndarray] = None   # (n, 3, 6, 6) at the last evaluation

    def components(self, X, C, Jri, use) -> np.ndarray:
        n = len(C)
        rot = _ROT if self.frames is None else self.frames[use] @ _ROT @ np.swapaxes(
            self.frames[use], 1, 2)
        G = np.empty((n, 3, 6, 6))
        G[:, 0], G[:, 1] = _ROT, _TRANS
        G[:, 2] = lie.cov_left_to_right(dq.mul(X, C), np.broadcast_to(rot, (n, 6, 6)))
        if Jri is not None:
            G = Jri[:, None] @ G @ np.swapaxes(Jri, 1, 2)[:, None]
        return G

    def __call__(self, X, C, r, Jri, use=None) -> np.ndarray:
        if self.estimate:
            self.G = self.components(X, C, Jri, use)
            if self.theta is None:
                v = (1.4826 * np.median(np.abs(r), axis=0)) ** 2   # outliers do not inflate it
                self.theta = np.array([v[:3].mean(), v[3:].mean(), 0.1 * v[:3].mean()])
                self.theta = np.maximum(self.theta, FLOORS)
            return np.einsum("k,nkij->nij", self.theta, self.G)
        SA = None if self.SA is None else self.SA[use]
        return transported(X, C, SA, self.SC[use], Jri)

    def _reml(self, J: np.ndarray, P: np.ndarray):
        """The pieces of the REML score and information at the current ``θ``: ``W_i = Σ_r,i⁻¹``,
        ``B_i = W_i J_i``, ``M_k = Σ B_iᵀ G_k,i B_i`` (12×12, ``−∂H/∂θ_k``),
        ``Q_kl = Σ B_iᵀ G_k,i W_i G_l,i B_i`` and ``F_kl = tr(R G_k R G_l)`` (twice the REML
        information), ``R = W − W J P Jᵀ W``: every trace expanded over the blocks, so nothing
        6n × 6n is formed."""
        G, theta = self.G, self.theta
        assert G is not None and theta is not None, "set by __call__ (estimated)"
        W = np.linalg.inv(np.einsum("k,nkij->nij", theta, G))
        B = W @ J                                                   # (n, 6, 12)
        WG = W[:, None] @ G                                         # (n, 3, 6, 6)
        GB = G @ B[:, None]                                         # (n, 3, 6, 12)
        GBt = np.swapaxes(GB, 2, 3)
        M = (np.swapaxes(B, 1, 2)[:, None] @ GB).sum(axis=0)        # (3, 12, 12) Uᵀ G_k U
        WGB = W[:, None] @ GB                                       # (n, 3, 6, 12)
        Q = (GBt[:, :, None] @ WGB[:, None]).sum(axis=0)            # (3, 3, 12, 12) Uᵀ G_k D G_l U
        PM = P @ M                                                  # (3, 12, 12)
        F = ((WG[:, :, None] * np.swapaxes(WG, 2, 3)[:, None]).sum(axis=(0, 3, 4))
             - 2.0 * (P * Q).sum(axis=(2, 3))                       # Q_lk = Q_klᵀ, P symmetric
             + (PM[:, None] * np.swapaxes(PM, 1, 2)[None]).sum(axis=(2, 3)))
        return W, B, M, Q, F

    def update(self, r: np.ndarray, J: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, bool]:
        """One REML (Fisher-scoring) step of the variance components at residuals ``r``
        (Jacobian ``J``, covariance ``P`` of the fit): ``θ = F⁻¹ q`` with
        ``F_kl = tr(R G_k R G_l)``, ``q_k = rᵀ R G_k R r``, ``R = W − W J P Jᵀ W`` (the residual
        projector: the 12 fitted degrees of freedom taken out by leverage); a component that
        comes out below its floor is held there and the others re-solved. Returns the new
        residual covariances and whether the components settled."""
        G, last = self.G, self.theta
        assert G is not None and last is not None, "set by __call__ (estimated)"
        W, B, _, _, F = self._reml(J, P)
        Btr = (np.swapaxes(B, 1, 2) @ r[..., None]).sum(0)
        u = (W @ r[..., None])[..., 0] - B @ (P @ Btr)[..., 0]
        q = (u[:, None, None, :] @ G @ u[:, None, :, None])[..., 0, 0].sum(axis=0)
        free = np.ones(3, bool)
        theta = last
        for _ in range(3):
            t = np.array(FLOORS)
            try:
                t[free] = np.linalg.solve(F[np.ix_(free, free)],
                                          q[free] - F[np.ix_(free, ~free)] @ t[~free])
            except np.linalg.LinAlgError:
                t[:] = np.nan
            low = free & (t < FLOORS)
            if not np.any(low):
                theta = t
                break
            free &= ~low
            theta = np.maximum(t, FLOORS)
        # Far from the answer scoring can overshoot: when a component carrying a share of the
        # residuals more than triples or falls below a third (or a negligible one grows a
        # hundredfold), the multiplicative (EM) step θ_k q_k / (F θ)_k is taken instead, slower
        # but never leaving the positive cone. A negligible component may drop to its floor.
        share = last * (F @ last) / max(float(last @ F @ last), 1e-300)
        jump = np.where(share > 0.05, (theta > 3.0 * last) | (theta < last / 3.0),
                        theta > 100.0 * np.maximum(last, 1e-4 * last.max()))
        if not np.all(np.isfinite(theta)) or np.any(jump):
            theta = last * q / np.maximum(F @ last, 1e-300)
        theta = np.maximum(theta, FLOORS)
        # Near the boundary scoring can cycle between two points: a component whose step
        # reverses its last one moves half as far.
        step = theta - last
        if self.step is not None:
            step = np.where(step * self.step < 0.0, 0.5 * step, step)
            theta = np.maximum(last + step, FLOORS)
        self.step = step
        # Settled when the residual degrees of freedom the components account for,
        # θ_k tr(R G_k) = θ_k (F θ)_k (summing to 6n − 12), move by less than 1e-3 of them.
        Ft = F @ last
        settled = bool((np.abs(theta - last) @ Ft) <= 1e-3 * max(float(last @ Ft), 1e-300))
        self.theta = theta
        return np.einsum("k,nkij->nij", self.theta, G), settled

    def covariances(self):
        """The estimated (camera, robot) pose noise, in the module's convention."""
        t = self.theta
        return np.diag([t[0]] * 3 + [t[1]] * 3), np.diag([t[2]] * 3 + [0.0] * 3)

    def kenward_roger(self, J: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The covariance of ``(X, Z)`` to report when ``θ`` is estimated: ``P = H(θ̂)⁻¹`` with
        the uncertainty of ``θ̂`` propagated (Kenward & Roger 1997, Biometrics 53:983; the
        small-sample inference for fixed effects under REML variance components).

        ``H(θ̂)⁻¹`` is too small on average for two reasons, both of the order of
        ``Var(θ̂)/θ²`` — about 2/(residual degrees of freedom per component): 10 poses leave
        ``6n − 12 = 48`` shared by three components, some of them (the robot's rotation against
        the camera's, through the lever arm) poorly separated. (1) ``(X̂, Ẑ)`` varies more than
        ``H(θ)⁻¹`` says because ``θ̂`` varies, and ``H(θ̂)⁻¹`` is a biased estimate of ``H(θ)⁻¹``:
        to second order in ``θ̂ − θ`` both together are
        ``Φ_A = P + 2 P Λ P``, ``Λ = Σ_kl V_kl (Q_kl − M_k P M_l)``, ``V = Cov(θ̂) = 2 F⁻¹``
        (the inverse REML information; see :meth:`_reml` for ``M``, ``Q``, ``F``; the
        covariance is linear in ``θ``, so KR's second-derivative term is zero). (2) Even an
        unbiased ``Φ_A`` is a random matrix, and ``E[ξᵀ Φ_A⁻¹ ξ] > 6`` by Jensen: KR match
        the Wald statistic's first two moments to a scaled ``F(ℓ, m)``, whose mean gives
        ``E[ξᵀ Φ_A⁻¹ ξ] ≈ ℓ E*``, ``E* = 1 / (1 − A₂/ℓ)``,
        ``A₂ = Σ_kl V_kl tr(Θ P M_k P Θ P M_l P)``, ``Θ`` the inverse of the block's ``P``.
        Reporting ``E* Φ_A`` per block is then the covariance of the Student-t-like predictive
        distribution of the block (mean NEES ℓ). With one component this is exactly the
        t factor ``ν / (ν − 2)``, ``ν = 6n − 12``, and ``Φ_A = P``. X and Z get their own ``E*``
        (ℓ = 6 each); the joint covariance is ``D Φ_A D``, ``D = diag(√E*_X I₆, √E*_Z I₆)``.
        A component held at its floor keeps its uncertainty: an estimate of zero robot noise
        from 10 poses does not make the robot exact (taking it as known left the NEES of
        OpenCV's geometry at 10 poses 0.5 higher). ``1 − A₂/ℓ`` is kept
        above 0.05: so few residual degrees of freedom that it is not would be a t with about
        two, whose variance is unbounded."""
        _, _, M, Q, F = self._reml(J, P)
        try:
            V = 2.0 * np.linalg.inv(F)
        except np.linalg.LinAlgError:
            return P
        MP = M @ P                                                  # (3, 12, 12)
        MPM = MP[:, None] @ M[None]                                 # (3, 3, 12, 12)
        Lam = np.einsum("kl,klij->ij", V, Q - MPM)
        PA = P + 2.0 * P @ Lam @ P
        d = np.empty(12)
        for b in (slice(0, 6), slice(6, 12)):
            T = np.zeros((12, 12))
            T[b, b] = np.linalg.inv(P[b, b])
            Y = T @ P @ MP                                          # (3, 12, 12): Θ P M_k P
            A2 = float(np.einsum("kl,kij,lji->", V, Y, Y))
            d[b] = np.sqrt(1.0 / max(1.0 - A2 / 6.0, 0.05))
        PA = PA * d[:, None] * d[None, :]
        return 0.5 * (PA + PA.T)


def noise_model(p, camera_covariance, robot_covariance) -> tuple:
    """The noise model of a solve on the checked data ``p``: ``(Σ_C, Σ_robot, Noise)``, the
    given covariances validated (``None`` where not given); estimated when no camera noise is
    given, the robot then exact unless its noise is given too."""
    n = p.F.shape[0]
    SC = checked_covariances(camera_covariance, "camera_covariance", n)
    SRob = checked_covariances(robot_covariance, "robot_covariance", n)
    if SC is None and SRob is not None:
        raise FieldError("camera_covariance: needed when robot_covariance is given (or give "
                         "neither to estimate the noise)")
    estimate = SC is None
    # Noise of A_i = base_flange_i⁻¹ (eye_to_hand) is the inverse's: Ad(F) Σ Ad(F)ᵀ.
    SA = None
    if SRob is not None:
        SA = SRob if p.setup == EYE_IN_HAND else lie.cov_inverse(p.F, SRob)
        if not np.any(SA):
            SA = None
    noise = Noise(SA, SC, estimate,
                   lie.adjoint(p.F) if p.setup == EYE_TO_HAND and estimate else None)
    if not estimate:
        S0 = noise(p.closed[0], p.C, np.zeros((n, 6)), np.broadcast_to(np.eye(6), (n, 6, 6)),
                   np.ones(n, bool))
        singular = np.flatnonzero(~(np.linalg.eigvalsh(S0)[:, 0] > 0.0))
        if len(singular):
            i = int(singular[0])
            given = f"camera_covariance[{i}]" + (
                f", robot_covariance[{i}]" if SRob is not None else "")
            raise FieldError(f"{given}: the residual covariance of this sample (its camera and "
                             f"robot noise together) is singular; give every pose some noise "
                             f"in every axis")
    return SC, SRob, noise
