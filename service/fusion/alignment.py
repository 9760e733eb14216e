"""Fusion over time (:func:`dqpose.fusion.fuse` with ``times``): the fusion time (by default the
newest time a measurement was taken, its stamp minus its source's latency), the measurements
dropped for skew, the bound on extrapolation, the one-instant case (the static fit itself, bit for
bit), the motion model built from the sources' latencies and the twist's prior, its fit (robust or
not) and the result. The model is :mod:`dqpose.fusion.motion`'s, with an ``acceleration_psd``
:mod:`dqpose.fusion.process_noise`'s.
"""
from __future__ import annotations

import functools
import math
from dataclasses import replace
from typing import NamedTuple, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError
from dqpose.fusion.consistency import codes, source_stats
from dqpose.fusion.extrinsics import motion_fit_ext, uncertain_extrinsics
from dqpose.fusion.motion import (
    Model,
    MotionFit,
    constant_twist_fit,
    constant_twist_pose,
    determined_without_each,
)
from dqpose.fusion.process_noise import correlated_fit, correlated_nis, marginal_information
from dqpose.fusion.results import DOF, Dropped, Fused, Latency, read_only
from dqpose.fusion.robust import consensus, nis_gate, rejections
from dqpose.fusion.static import fuse_static
from dqpose.fusion.validation import checked_acceleration, checked_seconds, twist_information

#: seconds a fused pose's time may lie past its newest measurement (extrapolated on the twist)
DEFAULT_MAX_EXTRAPOLATION = 0.1


def _motion_fit(Z, S, model: Model, inlier: np.ndarray, tol: float, max_iter: int,
                nis: bool = True, joint: bool = True) -> MotionFit:
    """Fit of the measurements ``inlier`` selects, evaluated at every measurement. The constant
    twist is fitted in C, covariance and (``nis``) leave-one-out NIS included; the correlated
    model in NumPy from the constant-twist fit (its NIS: :func:`_motion_nis`). Without ``nis``
    the fit's ``nis`` is None: what needs only the pose and its covariance skips them. Without
    ``joint`` the fit with uncertain extrinsics stops at the constant-twist fit it starts from
    (the start of a joint fit of several bodies, which needs no more)."""
    if model.extrinsics is not None and joint:
        # the joint fit with the uncertain extrinsics, from the C fit without them (whose NIS
        # nothing uses)
        first = constant_twist_fit(Z, S, model, inlier, tol, max_iter, False)
        return motion_fit_ext(Z, S, model, model.extrinsics, inlier, first.mean, first.V,
                               first.ell, tol, max_iter, nis)
    if model.accel is None:
        return constant_twist_fit(Z, S, model, inlier, tol, max_iter, nis)
    return correlated_fit(Z, S, model, inlier, tol, max_iter)


def _motion_nis(fit: MotionFit, S, inlier: np.ndarray, model: Model):
    """Each measurement's leave-one-out NIS against the fit of the other inliers
    (:func:`correlated_nis` for the joint state; the constant-twist fit computed them with the
    fit)."""
    if fit.nis is not None:
        return fit.nis, fit.tested
    return correlated_nis(fit, S, inlier, model)


def _robust_motion(Z, S, model: Model, allowed: np.ndarray, gate2, tol, max_iter):
    """:func:`_robust` over time: the consensus start compares the measurements brought to the
    fusion time with the twist of a first fit of all of them (an outlier biases that twist; the
    gate that follows judges every measurement against the fit of the others)."""
    first = _motion_fit(Z, S, model, allowed, tol, max_iter, False)   # its dt and twist
    back = lie.se3_exp(-first.dt[:, None] * first.V)
    Wm = marginal_information(S, first.dt, model.accel)
    Sm = S if Wm is None else np.linalg.inv(Wm)
    Zt, St = dq.normalize(dq.mul(Z, back)), lie.cov_compose(Sm, back, None)
    inlier = np.zeros_like(allowed)
    inlier[allowed] = consensus(Zt[allowed], St[allowed], gate2)
    if not determined_without_each(model, inlier)[~inlier].all():
        inlier = allowed.copy()  # the consensus is of one instant: the twist needs more
    return nis_gate(inlier, allowed, lambda m: _motion_fit(Z, S, model, m, tol, max_iter),
                 lambda fit, m: _motion_nis(fit, S, m, model), gate2)


class _Span(NamedTuple):
    """Which measurements a fusion at a time uses, and how far that time lies outside them."""
    drop: Optional[np.ndarray]   # taken further than max_skew from it (None: no max_skew)
    keep: Optional[np.ndarray]   # the others
    lo: float                    # the span of the times the kept measurements were taken
    hi: float
    extrapolation: float         # how far the fusion time lies outside [lo, hi]
    max_skew: Optional[float]    # as checked


def _span(taken: np.ndarray, time: float, max_skew, max_extrapolation) -> _Span:
    """The measurements taken within ``max_skew`` of the fusion time, and their span; a fusion
    time further than ``max_extrapolation`` outside it is refused."""
    if max_skew is None:
        drop, keep, kept = None, None, taken
    else:
        max_skew = checked_seconds(max_skew, "max_skew", "nonnegative")
        drop = np.abs(time - taken) > max_skew
        keep = ~drop
        if not keep.any():
            nearest = float(np.abs(time - taken).min())
            raise FieldError("max_skew", f"every measurement was taken more than {max_skew:g} s "
                             f"from the fusion time {time!r} (the nearest {nearest:.6g} s)")
        kept = taken[keep]
    lo, hi = float(kept.min()), float(kept.max())
    extrapolation = max(0.0, time - hi, lo - time)
    if max_extrapolation is not None:
        max_extrapolation = checked_seconds(max_extrapolation, "max_extrapolation", "nonnegative")
        if extrapolation > max_extrapolation:
            raise FieldError("time", f"{time!r} is {extrapolation:.6g} s outside the span "
                             f"[{lo!r}, {hi!r}] of the measurements, beyond max_extrapolation "
                             f"{max_extrapolation:g} s")
    return _Span(drop, keep, lo, hi, extrapolation, max_skew)


class _Setup(NamedTuple):
    """A fusion over time before its fit: the fusion time, when each measurement was taken, the
    span, the sources (each once, and each measurement's index), the estimated latencies, the
    twist's prior (covariance and information) and the motion model."""
    time: float
    taken: np.ndarray
    span: _Span
    sources: tuple
    code: np.ndarray
    estimated: list
    twist_prior: Optional[np.ndarray]
    Wp: Optional[np.ndarray]
    model: Model

    @property
    def one_instant(self) -> bool:
        """All taken at the fusion time: nothing moves (the static fit)."""
        return self.span.lo == self.span.hi and self.span.extrapolation == 0.0

    @property
    def allowed(self) -> np.ndarray:
        n = self.taken.shape[0]
        return np.ones(n, dtype=bool) if self.span.keep is None else self.span.keep


def time_setup(Z, names, table, times, time, max_skew, max_extrapolation, twist_covariance,
           acceleration_psd) -> _Setup:
    """The fusion time, the measurements' span and the motion model of :func:`fuse_in_time`."""
    stamps = times
    sources, code = codes(names)
    latency = np.array([table[s].latency if s in table else 0.0 for s in sources])[code]
    taken = stamps - latency
    time = float(taken.max()) if time is None else checked_seconds(time, "time")
    twist_prior, Wp = (None, None) if twist_covariance is None else twist_information(
        twist_covariance)
    accel = checked_acceleration(acceleration_psd)
    ext = uncertain_extrinsics(names, table)
    if ext is not None and accel is not None:
        raise FieldError("acceleration_psd", f"not supported with a source's extrinsic_covariance "
                         f"(source {ext.names[0]!r})")
    span = _span(taken, time, max_skew, max_extrapolation)
    estimated = [s for s in sources if s in table and table[s].latency_sigma is not None]
    one_instant = span.lo == span.hi
    twist = Wp is not None or not one_instant
    if not twist and span.extrapolation > 0.0:
        raise FieldError("time", f"the measurements were all taken at {span.lo!r}; bringing them "
                         f"to {time!r} needs the body's twist, which one instant does not show "
                         f"(give twist_covariance)")
    slot = np.array([estimated.index(s) if s in estimated else -1 for s in sources])[code]
    model = Model(
        stamp=stamps - time, latency=latency, slot=slot,
        prior=np.array([table[s].latency for s in estimated], dtype=np.float64),
        prior_w=np.array([table[s].latency_sigma ** -2 for s in estimated], dtype=np.float64),
        twist=twist, twist_w=Wp, accel=accel, extrinsics=ext)
    return _Setup(time, taken, span, sources, code, estimated, twist_prior, Wp, model)


def fuse_in_time(Z, S, names, table, times, time, max_skew, max_extrapolation,
                  twist_covariance, acceleration_psd, robust, probability, gate2, tol,
                  max_iter, nis: bool = True, joint: bool = True) -> Fused:
    """:func:`dqpose.fusion.fuse` with times, after its checks: the fusion time and the
    measurements' span, then the fit of one instant or of the motion model over the window.
    Without ``nis`` (and not robust, whose gate needs them) the fit over time skips the
    leave-one-out NIS: ``nis`` is zeros and ``tested`` all False (every source UNTESTED), the
    pose, covariance and everything else the same to the last bit. Without ``joint`` (and not
    robust, whose gate needs the whole fit) a fit over time with uncertain extrinsics is the
    constant-twist fit it would start from: where a joint fit of several bodies starts (its
    pose, twist, latencies and inliers; its covariance leaves the extrinsics' errors out)."""
    u = time_setup(Z, names, table, times, time, max_skew, max_extrapolation, twist_covariance,
               acceleration_psd)
    time, model, Wp, estimated = u.time, u.model, u.Wp, u.estimated
    # Which fit runs is decided here; for a Lookup's pose alone pose_in_time (the constant-twist
    # fit) and pose_over_time (any fit over time that is not robust) restate it, and
    # tests/test_world.py holds them to the same bits.
    if u.one_instant:
        # All taken at the fusion time: nothing moves, the answer is the static fit itself (its
        # C core), bit for bit; the twist keeps its prior, each latency its prior (one instant
        # shows neither).
        f = fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter,
                         model.extrinsics)
        return replace(
            f, time=time, extrapolation=0.0,
            twist=None if Wp is None else read_only(np.zeros(DOF)),
            twist_covariance=None if Wp is None or u.twist_prior is None
            else read_only(u.twist_prior),
            latencies=tuple(Latency(s, table[s].latency, table[s].latency_sigma,
                                    table[s].latency, table[s].latency_sigma)
                            for s in estimated))
    allowed = u.allowed
    if robust and np.count_nonzero(allowed) > 1:
        gated = _robust_motion(Z, S, model, allowed, gate2, tol, max_iter)
    else:
        fit = _motion_fit(Z, S, model, allowed, tol, max_iter, nis, joint)
        tests = (_motion_nis(fit, S, allowed, model) if nis else
                 (np.zeros(Z.shape[0]), np.zeros(Z.shape[0], dtype=bool)))
        gated = (fit, *tests, allowed, None)
    return _result(gated, u.span, model, names, u.sources, u.code, table, estimated, time,
                   u.taken, gate2, probability)


_NO_PRIORS = read_only(np.empty(0))     # shared by every Lookup's model: read-only


def pose_in_time(Z, S, latency: np.ndarray, stamps: np.ndarray, taken: np.ndarray,
                  time: float, o) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The pose and covariance of :func:`fuse_in_time` (``nis`` False) alone, bit for bit, for
    measurements whose sources' extrinsics and latencies are exact (``latency`` each
    measurement's, ``taken`` = ``stamps - latency``), when its fit is the constant-twist fit:
    not robust, no ``acceleration_psd`` or ``max_skew``, more than one instant. None when
    another fit applies.
    A Lookup of a body needs no more, and the rest of the answer (the sources' names and
    verdicts, the residuals as read-only arrays) cost it a third of its time. ``o``:
    :class:`dqpose.fusion.api.Checked`."""
    if o.robust or o.acceleration_psd is not None or o.max_skew is not None:
        return None
    span = _span(taken, time, None, o.max_extrapolation)
    if span.lo == span.hi:
        return None
    Wp = None if o.twist_covariance is None else twist_information(o.twist_covariance)[1]
    model = Model(stamps - time, latency, _no_slots(Z.shape[0]), _NO_PRIORS, _NO_PRIORS, True,
                   Wp)
    # every measurement an inlier: None tells the C fit so without a mask
    mean, P = constant_twist_pose(Z, S, model, None, o.tol, o.max_iter)
    return read_only(mean), read_only(P[:6, :6])


def pose_over_time(Z, S, names, times, time: float, o) -> Optional[tuple[np.ndarray,
                                                                           np.ndarray]]:
    """The pose and covariance of :func:`fuse_in_time` (``nis`` False) alone, bit for bit, for
    any fit over time that is not robust (a source's uncertain extrinsic or estimated latency
    included, where :func:`pose_in_time` does not apply): the same set-up and fit, without the
    answer's other fields (the rejections, the sources' verdicts, the latencies). None when the
    fit is robust or of one instant. ``o``: :class:`dqpose.fusion.api.Checked`."""
    u = _plain_setup(Z, names, times, time, o)
    if u is None:
        return None
    fit = _motion_fit(Z, S, u.model, u.allowed, o.tol, o.max_iter, False)
    return read_only(fit.mean), read_only(fit.P[:6, :6])


def _plain_setup(Z, names, times, time: float, o) -> Optional[_Setup]:
    """:func:`fuse_in_time`'s set-up when its fit is a fit over time that is not robust (the
    one fit over the allowed measurements), else None."""
    if o.robust:
        return None
    u = time_setup(Z, names, o.table, times, time, o.max_skew, o.max_extrapolation,
               o.twist_covariance, o.acceleration_psd)
    return None if u.one_instant else u


class Start(NamedTuple):
    """Where a body starts in a joint fit of several bodies: its set-up (:func:`time_setup`), and
    its own fit's pose, twist, latencies and inliers (a mask)."""
    setup: _Setup
    mean: np.ndarray
    V: np.ndarray
    ell: np.ndarray
    inlier: np.ndarray

    @classmethod
    def of(cls, f: Fused, u: _Setup) -> "Start":
        """The start a fit ``f`` (a :class:`~dqpose.fusion.Fused`) of the set-up ``u`` gives."""
        inlier = np.zeros(u.taken.shape[0], dtype=bool)
        inlier[f.inliers] = True
        V = np.zeros(DOF) if f.twist is None else np.array(f.twist)
        return cls(u, f.mean, V, np.array([lat.value for lat in f.latencies], dtype=np.float64),
                   inlier)


def joint_start(Z, S, names, times, time: float, o) -> Optional[Start]:
    """The start of :class:`Start`.of(:func:`fuse_in_time` (``nis`` and ``joint`` False)),
    bit for bit, for a fit over time that is not robust, without that answer's other fields;
    None when the fit is robust or of one instant. ``o``: :class:`dqpose.fusion.api.Checked`."""
    u = _plain_setup(Z, names, times, time, o)
    if u is None:
        return None
    fit = _motion_fit(Z, S, u.model, u.allowed, o.tol, o.max_iter, False, False)
    return Start(u, fit.mean, np.array(fit.V), np.array(fit.ell, dtype=np.float64),
                  u.allowed.copy())


@functools.lru_cache(maxsize=256)
def _no_slots(n: int) -> np.ndarray:
    """n measurements' slots among the estimated latencies when none is (-1 each), read-only."""
    return read_only(np.full(n, -1))


def _result(gated, span: _Span, model: Model, names, sources, code, table, estimated,
            time: float, taken: np.ndarray, gate2: float, probability: float) -> Fused:
    """The fit over time as a :class:`~dqpose.fusion.Fused`: ``gated`` is the gate's ``(fit,
    nis, tested, inlier, status)``; the pose's, twist's and latencies' blocks of the joint
    covariance, the measurements rejected and dropped, the sources' verdicts."""
    fit, nis, tested, inlier, gate_status = gated
    drop, keep, twist = span.drop, span.keep, model.twist
    out = ~inlier if keep is None else ~inlier & keep
    rejected = rejections(names, nis, out, gate2, probability)
    dropped: tuple = ()
    if drop is not None:
        assert span.max_skew is not None    # measurements are dropped by the skew bound only
        dropped = tuple(Dropped(int(i), names[i], float(time - taken[i]), span.max_skew)
                        for i in np.flatnonzero(drop))
    P = fit.P
    off = model.offset
    latencies = tuple(Latency(s, table[s].latency, table[s].latency_sigma, float(fit.ell[k]),
                              float(math.sqrt(P[off + k, off + k])))
                      for k, s in enumerate(estimated))
    inliers = np.flatnonzero(inlier)
    # Each prior is as many residuals as the parameters it constrains: only the twist's
    # unconstrained 6 reduce the degrees of freedom beyond the pose's.
    dof = DOF * (inliers.size - 1) - (DOF if twist and model.twist_w is None else 0)
    # a dropped measurement is neither tested nor counted as rejected by the gate
    stats = source_stats(sources, code, nis, tested if keep is None else tested & keep,
                          inlier if drop is None else inlier | drop, probability)
    return Fused(
        status=gate_status if gate_status is not None else fit.status,
        mean=read_only(fit.mean),
        covariance=read_only(P[:6, :6]),
        residuals=read_only(fit.r),
        distances=read_only(np.sqrt(fit.cost)),
        nis=read_only(nis),
        tested=read_only(tested),
        inliers=read_only(inliers),
        rejected=rejected,
        chi2=fit.chi2,
        dof=dof,
        iterations=fit.iterations,
        sources=stats,
        time=time,
        twist=read_only(fit.V) if twist else None,
        twist_covariance=read_only(P[6:12, 6:12]) if twist else None,
        extrapolation=float(span.extrapolation),
        dropped=dropped,
        latencies=latencies,
    )
