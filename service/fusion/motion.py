"""The motion model of a fusion over time, and its fit with a constant twist.

A measurement stamped ``t`` by a source with latency ``ℓ`` was taken at ``τ = t − ℓ``. The body
moves with a constant body twist ``V`` over the window, ``T(τ) = X · Exp((τ − time) V)`` with
``X`` the pose at the fusion time, so the prediction of measurement i is ``P_i = X Exp(dt_i V)``,
``dt_i = τ_i − time``, and its residual ``r_i = Log(P_i⁻¹ Z_i)``. Pose, twist (and the latencies a
source asks to have estimated) are found jointly by Gauss–Newton with exact Jacobians (in C,
``dq_motion_fit`` in ``fusion.c``, leave-one-out NIS included; the correlated model of
:mod:`dqpose.fusion.process_noise` is NumPy): for ``X · Exp(δ)``, ``V + ε`` and ``ℓ + λ`` the
prediction moves by ``Exp(η)`` on the right with ``η = Ad(Exp(−dt V)) δ + dt Jr(dt V) ε − V λ``,
and ``r_i`` by ``−Jl⁻¹(r_i) η``. The covariance is the inverse of the joint information; its pose
block is the marginal at the fusion time, so it carries the twist's (and latencies') uncertainty.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq, lie
from dqpose.fusion.results import DOF, Status


@dataclass(frozen=True)
class Model:
    """What the motion fit needs besides the poses: per measurement its stamp relative to the
    fusion time, its configured latency and its slot among the estimated latencies (-1: exact);
    per estimated latency its prior; whether the twist is estimated and its prior information."""
    stamp: np.ndarray
    latency: np.ndarray
    slot: np.ndarray
    prior: np.ndarray
    prior_w: np.ndarray
    twist: bool
    twist_w: Optional[np.ndarray]
    # the power spectral density of the white-noise acceleration (None: the twist is constant)
    accel: Optional[np.ndarray] = None
    # the uncertain extrinsics of the measurements (dqpose.fusion.extrinsics.Extrinsics; None:
    # every extrinsic exact)
    extrinsics: Optional[Any] = None

    @property
    def offset(self) -> int:  # where the latencies start in the state vector
        return 12 if self.twist else 6

    @property
    def dim(self) -> int:
        return self.offset + self.prior.size

    def take(self, mask: np.ndarray) -> "Model":
        return Model(self.stamp[mask], self.latency[mask], self.slot[mask], self.prior,
                      self.prior_w, self.twist, self.twist_w, self.accel)

    def dt(self, ell: np.ndarray) -> np.ndarray:
        """``τ_i − time`` with the latencies ``ell`` in the estimated slots."""
        est = self.slot >= 0
        lat = np.where(est, ell[np.where(est, self.slot, 0)] if ell.size else 0.0, self.latency)
        return self.stamp - lat

    def prior_cost(self, V: np.ndarray, ell: np.ndarray) -> float:
        c = float(np.sum(self.prior_w * (ell - self.prior) ** 2))
        if self.twist and self.twist_w is not None:
            c += float(V @ self.twist_w @ V)
        return c

    def prior_terms(self, V: np.ndarray, ell: np.ndarray):
        """The priors' information and the gradient they add (the descent direction's sign)."""
        H = np.zeros((self.dim, self.dim))
        g = np.zeros(self.dim)
        if self.twist and self.twist_w is not None:
            H[6:12, 6:12] = self.twist_w
            g[6:12] = -self.twist_w @ V
        k = np.arange(self.prior.size) + self.offset
        H[k, k] = self.prior_w
        g[k] = -self.prior_w * (ell - self.prior)
        return H, g


@dataclass(frozen=True)
class MotionFit:
    status: Status
    mean: np.ndarray       # the pose at the fusion time
    V: np.ndarray          # the body twist (zeros when not estimated)
    ell: np.ndarray        # the estimated latencies
    H: np.ndarray          # joint information at the optimum, priors included
    P: np.ndarray          # its inverse: the joint covariance
    dt: np.ndarray         # τ_i − time, all measurements
    r: np.ndarray          # residuals Log(P_i⁻¹ Z_i), all measurements
    G: Optional[np.ndarray]  # Jl⁻¹(r_i) B_i: minus the residuals' Jacobian, (n, 6, dim)
    cost: np.ndarray       # r_iᵀ W_i r_i, all measurements (W_i with its model error's share)
    chi2: float            # the inliers' cost (with the model error: rᵀ C⁻¹ r) and the priors'
    iterations: int
    Cinv: Optional[np.ndarray] = None  # the inliers' joint information, with the model error
    # the constant-twist fit (C) computes the leave-one-out NIS with the fit, for these
    nis: Optional[np.ndarray] = None
    tested: Optional[np.ndarray] = None


def _evaluate(X: np.ndarray, Z: np.ndarray, W: np.ndarray):
    """Residuals ``Log(X⁻¹ Z_i)`` and their costs ``r_iᵀ W_i r_i`` (the static and the
    constant-twist fits do this in C, service/csrc/fusion.c)."""
    r = lie.se3_log(dq.mul(dq.conj(X), Z))
    return r, None if W is None else np.einsum("ni,nij,nj->n", r, W, r)


def motion_evaluate(X, V, ell, Z, W, model: Model):
    dt = model.dt(ell)
    r, cost = _evaluate(dq.mul(X, lie.se3_exp(dt[:, None] * V)), Z, W)
    return dt, r, cost


def motion_jacobian(V, dt, r, model: Model) -> np.ndarray:
    """``G_i = Jl⁻¹(r_i) [Ad(Exp(−dt V)), dt Jr(dt V), −V e_slot]``: ``r_i`` moves by ``−G_i Δ``."""
    B = np.zeros(r.shape[:1] + (DOF, model.dim))
    B[:, :, :6] = lie.adjoint(lie.se3_exp(-dt[:, None] * V))
    if model.twist:
        B[:, :, 6:12] = dt[:, None, None] * lie.se3_right_jacobian(dt[:, None] * V)
    est = np.flatnonzero(model.slot >= 0)
    B[est, :, model.offset + model.slot[est]] = -V
    return lie.se3_left_jacobian_inv(r) @ B


def motion_start(Z, S, model: Model, inlier: np.ndarray) -> Optional[np.ndarray]:
    """Where the motion fit starts: with a twist None, for the C fit's own start (the inlier
    nearest the fusion time, at rest: Gauss-Newton finds the motion); with none (one instant)
    the static fit's start."""
    if model.twist:
        return None
    weights = np.exp(-np.linalg.slogdet(S[inlier])[1] / DOF)
    return dq.dib(Z[inlier], weights / weights.max())


def constant_twist(Z, S, model: Model, inlier, tol, max_iter, tested=None):
    """The C constant-twist fit (``dq_motion_fit``): the ``_dqcore.motion_fit`` tuple;
    ``tested`` True: the NIS of every measurement :func:`determined_without_each` allows."""
    return _c.motion_fit(Z, S, inlier, motion_start(Z, S, model, inlier), model.stamp,
                         model.latency, model.slot, model.prior, model.prior_w, model.twist,
                         model.twist_w, tested, tol, max_iter)


def constant_twist_fit(Z, S, model: Model, inlier: np.ndarray, tol: float,
                        max_iter: int, nis: bool = True) -> MotionFit:
    """The constant-twist fit in C with its covariance, and (``nis``) the leave-one-out NIS
    (without, ``nis`` and ``tested`` are None: a quarter to two fifths of the fit's time
    saved)."""
    (X, V, ell, H, chi2, status, iterations, dt, r, cost, _, loo, tested,
     P) = constant_twist(Z, S, model, inlier, tol, max_iter, True if nis else None)
    return MotionFit(Status(int(status)), X, V, ell, H, P, dt, r, None, cost, float(chi2),
                      int(iterations), nis=loo, tested=tested)


def constant_twist_pose(Z, S, model: Model, inlier: Optional[np.ndarray], tol: float,
                         max_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`constant_twist_fit`'s pose and joint covariance alone (no NIS), for an answer
    that needs no more."""
    out = constant_twist(Z, S, model, inlier, tol, max_iter, None)
    return out[0], out[-1]


def determined_without_each(model: Model, inlier: np.ndarray) -> np.ndarray:
    """For each measurement: do the inliers other than it determine the state? The twist needs
    two instants unless it has a prior; the latencies always have theirs (in C,
    ``dq_motion_determined``, which the constant-twist fit also runs)."""
    return _c.motion_determined(model.stamp, model.latency, inlier,
                                model.twist and model.twist_w is None)
