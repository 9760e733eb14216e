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
measurement. Gauss–Newton on that joint state (in C, ``dq_joint_fit`` of service/csrc/joint.c;
tests/fusion_reference.py holds it in NumPy) with exact Jacobians: ``r_i`` moves by
``Jr⁻¹(r_i) A_i Δ`` for ``Ê_s Exp(Δ)`` and ``p_s`` by ``Jr⁻¹(p_s) Δ``; the covariance is the inverse
joint information, so the body's block is the marginal with every ``ε`` integrated out (GLS with
the shared errors). Several bodies fitted together (:func:`joint_fit` with several parts) share
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

from dqpose import _dqcore as _c
from dqpose import dq, lie
from dqpose.fusion.motion import Model, MotionFit
from dqpose.fusion.results import DOF, Status


@dataclass(frozen=True)
class Extrinsics:
    """The uncertain extrinsics a set of measurements uses: per measurement the slot of its
    source's ``ε`` (-1: an exact extrinsic); per slot the source, its configured extrinsic and
    the prior's covariance and information."""
    slot: np.ndarray
    names: tuple[str, ...]
    E: np.ndarray
    cov: np.ndarray
    info: np.ndarray


def uncertain_extrinsics(names: Sequence[str], table: dict) -> Optional[Extrinsics]:
    """The uncertain extrinsics of the measurements ``names`` (their sources' in ``table``), in
    order of first appearance; None when none has one."""
    order = [s for s in dict.fromkeys(names)
             if s in table and table[s].extrinsic_covariance is not None]
    if not order:
        return None
    index = {s: k for k, s in enumerate(order)}
    slot = np.array([index.get(s, -1) for s in names], dtype=np.intp)
    ident = dq.identity()
    E = np.array([ident if table[s].extrinsic is None else table[s].extrinsic for s in order])
    cov = np.array([table[s].extrinsic_covariance for s in order])
    info = np.linalg.inv(cov)
    return Extrinsics(slot, tuple(order), E, cov, 0.5 * (info + np.swapaxes(info, 1, 2)))


def no_extrinsics(n: int) -> Extrinsics:
    """No uncertain extrinsic among ``n`` measurements (a joint fit that shares latencies
    only)."""
    return Extrinsics(np.full(n, -1, np.intp), (), np.zeros((0, 8)), np.zeros((0, DOF, DOF)),
                       np.zeros((0, DOF, DOF)))


class Part(NamedTuple):
    """One body in a joint fit: its world-frame measurements, their covariances and model, the
    inliers, and the slots of its measurements' extrinsics (:class:`Extrinsics`)."""
    Z: np.ndarray
    S: np.ndarray
    model: Model
    inlier: np.ndarray
    slot: np.ndarray
    start: np.ndarray   # (8,) the pose the fit starts from
    V: np.ndarray       # (6,) its twist
    ell: np.ndarray     # its latencies
    # where each of its latencies is in the fit's latencies, which parts share by source
    # (None: latencies of its own)
    shared: Optional[np.ndarray] = None


def static_model(n: int) -> Model:
    """The one-instant fit as a motion model: no twist, no latencies, every stamp at zero."""
    return Model(stamp=np.zeros(n), latency=np.zeros(n), slot=np.full(n, -1, np.intp),
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
    r: list            # per part: residuals, their Jacobians (r moves by -G Δ; None unless
    G: Optional[list]  # asked for), dt
    dt: list
    chi2: float
    iterations: int
    offsets: list      # where each part's pose and twist start in the joint state (then the
    #                    latencies, then the ε's)
    cost: Optional[list] = None    # per part: r_iᵀ Σ_i⁻¹ r_i
    nis: Optional[list] = None     # per part: leave-one-out NIS (0 where not tested)
    tested: Optional[list] = None  # per part: an outlier, or an inlier whose part stays
    #                                determined without it


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

    def columns(self, k: int, model: Model) -> np.ndarray:
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


def _part_slots(p: Part, m: np.ndarray) -> np.ndarray:
    """Part ``p``'s measurements' latencies among the fit's (``m`` its map), -1 where exact."""
    if m.size == 0:
        return np.full(p.model.slot.shape, -1, np.int64)
    return np.where(p.model.slot >= 0, m[np.maximum(p.model.slot, 0)], -1).astype(np.int64)


def joint_fit(parts: Sequence[Part], ext: Extrinsics, tol: float, max_iter: int,
               nis: bool = False, jacobians: bool = False) -> _Joint:
    """Gauss-Newton over every part's state and the ε's (the module's docstring), from the
    parts' starts and the configured extrinsics, in C (``dq_joint_fit``, service/csrc/joint.c;
    tests/fusion_reference.py holds it in NumPy); with ``nis`` each measurement's leave-one-out
    NIS, with ``jacobians`` each part's ``G``."""
    lay = _layout(parts, ext)
    cat: tuple[np.ndarray, ...]
    if len(parts) == 1:
        p = parts[0]
        cat = (p.Z, p.S, p.inlier, p.model.stamp, p.model.latency, _part_slots(p, lay.maps[0]),
               p.slot)
        L0 = p.ell
    else:
        cat = tuple(np.concatenate(a) for a in zip(*(
            (p.Z, p.S, p.inlier, p.model.stamp, p.model.latency, _part_slots(p, m), p.slot)
            for p, m in zip(parts, lay.maps))))
        # a shared latency starts from the mean of the parts' own estimates of it
        L0, seen = np.zeros(lay.prior.size), np.zeros(lay.prior.size)
        for p, m in zip(parts, lay.maps):
            np.add.at(L0, m, p.ell)
            np.add.at(seen, m, 1.0)
        L0 = np.where(seen > 0, L0 / np.maximum(seen, 1.0), lay.prior)
    counts = np.array([p.Z.shape[0] for p in parts], np.int64)
    priors = np.array([p.model.twist and p.model.twist_w is not None for p in parts])
    twist_w = np.array([p.model.twist_w if prior else np.zeros((DOF, DOF))
                        for p, prior in zip(parts, priors)])
    Z, S, inlier, stamp, latency, lat_slot, ext_slot = cat
    (X, V, L, Ehat, H, P, g, dt, r, cost, G, loo, tested, chi2, status, iterations) = \
        _c.joint_fit(Z, S, inlier, counts, stamp, latency, lat_slot, ext_slot,
                     np.array([p.start for p in parts]),
                     np.array([p.V for p in parts]), np.array([p.model.twist for p in parts]),
                     twist_w, priors, L0, lay.prior, lay.prior_w, ext.E, ext.info, nis, tol,
                     max_iter, jacobians)
    cut = np.cumsum(counts)[:-1]

    def split(a):
        return None if a is None else np.split(a, cut)
    return _Joint(Status(status), list(X), list(V), [L[m] for m in lay.maps], Ehat, P, H, g,
                  split(r), split(G), split(dt), chi2, iterations, lay.offsets, split(cost),
                  split(loo), split(tested))


def motion_fit_ext(Z, S, model: Model, ext: Extrinsics, inlier: np.ndarray, start, V,
                    ell, tol: float, max_iter: int, nis: bool = True) -> MotionFit:
    """One body's joint fit as a :class:`~dqpose.fusion.motion.MotionFit` (its state's block of
    the covariance first, the ε's after), leave-one-out NIS included when ``nis`` (else its
    ``nis`` and ``tested`` are None); its ``G`` is None."""
    part = Part(Z, S, model, inlier, ext.slot, start, V, ell, None)
    fit = joint_fit([part], ext, tol, max_iter, nis)
    assert fit.cost is not None
    return MotionFit(fit.status, fit.X[0], fit.V[0], fit.ell[0], fit.H, fit.P, fit.dt[0],
                      fit.r[0], None, fit.cost[0], fit.chi2, fit.iterations,
                      nis=fit.nis[0] if nis and fit.nis else None,
                      tested=fit.tested[0] if nis and fit.tested else None)


def relative_covariance(T_a: np.ndarray, T_b: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The covariance of ``T_a⁻¹ T_b`` from the joint covariance ``P`` ``(12, 12)`` of
    ``(δ_a, δ_b)`` (both right perturbations): ``T_a Exp(δ_a)`` and ``T_b Exp(δ_b)`` give
    ``T_ab Exp(δ_b − Ad(T_ab⁻¹) δ_a)`` to first order."""
    T_ab = dq.mul(dq.conj(T_a), T_b)
    J = np.hstack([-lie.adjoint(dq.conj(T_ab)), np.eye(DOF)])
    C = J @ P @ J.T
    return 0.5 * (C + C.T)
