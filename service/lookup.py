"""A World's Lookups (:meth:`dqpose.world.World.relative`): ``T_target_source`` at a time from
each body's rows of a Lookup's window (the window ending half a window after the time, or at the
body's newest if sooner).

Bodies whose rows share a source with an uncertain extrinsic or an estimated latency are fitted
together (one error per such source), else each alone; the relative pose's covariance is
``J P Jᵀ`` of their joint covariance (:func:`~dqpose.fusion.extrinsics.relative_covariance`).
Where the fit is the constant-twist fit over time (not robust, no ``acceleration_psd`` or
``max_skew``, more than one instant, within ``max_extrapolation``) the whole Lookup is one C call
(``_dqcore.lookup``, service/csrc/lookup.c), which starts each body where its last Lookup left it
(its pose carried on its twist) and each shared latency and extrinsic at its last estimate: warm
starts, so a Lookup after a few new measurements takes one or two Gauss-Newton steps fewer; the
answer moves with the start only within the fit's ``tol``. The other Lookups are the fits of
:class:`~dqpose.fusion.Tracker` (``estimate``, ``joint``), with their errors.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Mapping, Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq
from dqpose.answers import Kept
from dqpose.body_pose import BodyPose
from dqpose.fusion.extrinsics import relative_covariance
from dqpose.fusion.results import DOF, read_only
from dqpose.fusion.validation import twist_information

if TYPE_CHECKING:
    from dqpose.fusion import Tracker
    from dqpose.world import World

_IDENT = dq.identity()


class Lookups:
    """One world's Lookups and their warm starts (per body its last estimate, per source code
    its last latency and extrinsic), which only ever move where a fit starts."""

    def __init__(self, world: "World"):
        self._world = world
        self._warm = Kept()        # per body its last estimate: [t0, X (8), V (6)]
        self._tracker: Optional["Tracker"] = None
        self._kept: Optional[tuple] = None     # _table's
        # per fit (a body's alone, two bodies' together) the record of its last run
        # (service/csrc/lookup.h): where the next one's first step comes from
        self._records = Kept()
        self._L = np.empty(0)
        self._E = np.empty((0, 8))

    def relative(self, target: str, source: str, at: float) -> BodyPose:
        """``T_target_source`` at the checked time ``at`` of known bodies (either may be "", the
        world frame, not both; not the same body), the world's read lock held."""
        w = self._world
        t = w.tracker
        riders = w.riders
        if riders.parents and riders.rides(target, source):
            # a rider's rows composed with its parent's poses (dqpose.riders): the two bodies
            # fitted together over the uncertain sources they share, else each alone
            got = riders.joint(target, source, at) if target and source else None
            if got is None:
                return composed_independent(target, source, at,
                                 {b: w.pose_only(b, at) for b in (target, source) if b})
            Xa, Xb, P = got
            return BodyPose(source, at, read_only(dq.mul(dq.conj(Xa), Xb)),
                            read_only(relative_covariance(Xa, Xb, P)), None)
        if t.exact or not (target and source):
            # nothing uncertain two bodies could share: each body's own pose (a kept fit's)
            kept = {b: w.kept_pose(b, at) for b in (target, source) if b}
            poses = {b: k for b, k in kept.items() if k is not None}
            if len(poses) == len(kept):
                return composed_independent(target, source, at, poses)
        answer = self._in_c(target, source, at) if _plain(t) else None
        return answer if answer is not None else self._fitted(target, source, at)

    def _in_c(self, target: str, source: str, at: float) -> Optional[BodyPose]:
        """The Lookup in one C call, or None where it is another path's."""
        w = self._world
        t = w.tracker
        latency, latency_w, E, E_info, uncertain, twist_w = self._table(t)
        L, Ehat = self._starts(t, len(latency))
        rows = [w.rows_for(b, at) if b else None for b in (target, source)]
        warm = [self._warm_of(b, at) for b in (target, source)]
        s = t.store
        covs = s.wcovs if "wcovs" in s.arrays else s.covs
        o = t.options
        limit = o.max_extrapolation
        keys = ((target,), (source,), (target, source))
        records = self._records
        got = _c.lookup(s.ids, s.wposes, covs, s.times[:s.n], s.codes, latency, latency_w, E,
                        E_info, uncertain, rows[0], rows[1], twist_w, warm[0], warm[1], L, Ehat,
                        *(records.get(k) for k in keys), at,
                        math.inf if limit is None else float(limit), o.tol, o.max_iter)
        if got is None:
            return None
        pose, cov, wa, wb, self._L, self._E, *made, _ = got
        for b, warmed in ((target, wa), (source, wb)):
            if b:
                self._warm.keep(b, warmed)
        for k, rec in zip(keys, made):
            if rec is not None:     # bounded as a world's fits are: ~16 doubles a "row"
                records.keep(k, rec, rec.size // 16 + 1)
        return BodyPose(source, at, read_only(pose), read_only(cov), None)

    def _table(self, t: "Tracker") -> tuple:
        """What ``_dqcore.lookup`` reads of tracker ``t``'s sources, by source code: configured
        latency, an estimated latency's prior information (else 0), extrinsic, its prior's
        information and whether it is uncertain; then the twist's prior information (or None).
        Made again when the tracker (a configuration) or its codes change."""
        if self._tracker is not t:     # a new configuration: its own codes and estimates
            self._tracker, self._kept = t, None
            self._warm.clear()
            self._records.clear()
            self._L, self._E = np.empty(0), np.empty((0, 8))
        names = t.source_names
        kept = self._kept
        if kept is not None and len(kept[0]) == len(names):
            return kept
        n = len(names)
        latency_w, E = np.zeros(n), np.tile(_IDENT, (n, 1))
        info, uncertain = np.zeros((n, DOF, DOF)), np.zeros(n, bool)
        for c, name in enumerate(names):
            src = t.table.get(name)
            if src is None:
                continue
            if src.latency_sigma is not None:
                latency_w[c] = src.latency_sigma ** -2
            if src.extrinsic is not None:
                E[c] = src.extrinsic
            if src.extrinsic_covariance is not None:
                uncertain[c] = True
                inv = np.linalg.inv(src.extrinsic_covariance)
                info[c] = 0.5 * (inv + inv.T)
        o = t.options
        twist_w = (None if o.twist_covariance is None
                   else twist_information(o.twist_covariance)[1])
        self._kept = (t.latencies[:n].copy(), latency_w, E, info, uncertain, twist_w)
        return self._kept

    def _starts(self, t: "Tracker", codes: int) -> tuple[np.ndarray, np.ndarray]:
        """The sources' warm starts for tracker ``t``'s ``codes`` source codes (NaN: none)."""
        if len(self._L) < codes:
            grow = codes - len(self._L)
            self._L = np.r_[self._L, np.full(grow, np.nan)]
            self._E = np.r_[self._E, np.full((grow, 8), np.nan)]
        return self._L[:codes], self._E[:codes]

    def _warm_of(self, body: str, at: float) -> Optional[np.ndarray]:
        """``body``'s last estimate if it is within a window of ``at`` (else a cold start)."""
        warm = self._warm.get(body) if body else None
        if warm is None or abs(at - warm[0]) > self._world.options.window:
            return None
        return warm

    def _fitted(self, target: str, source: str, at: float) -> BodyPose:
        """The Lookup through the tracker's fits (robust, ``acceleration_psd``, ``max_skew``,
        one instant, extrapolation, and their errors)."""
        w = self._world
        if not target:      # the world frame is exact: the body's own pose
            return BodyPose(source, at, *w.pose_only(source, at), None)
        if not source or w.tracker.exact or not self.share(target, source, at):
            # nothing uncertain that two bodies could share: each body's own pose
            return composed_independent(target, source, at,
                             {b: w.pose_only(b, at) for b in (target, source) if b})
        # each body's start for the joint fit: its constant-twist fit, unless robust (the
        # gate's inliers need the whole fit); kept apart from the body's own fits
        t = w.tracker
        rows = [w.rows_for(b, at) for b in (target, source)]
        fits = [w.fit_of(b, r, lambda r: t.estimate(None, at, rows=r, fit="start"))
                for b, r in zip((target, source), rows)]
        (Xa, Xb), P = t.joint(rows, fits, at)
        return BodyPose(source, at, read_only(dq.mul(dq.conj(Xa), Xb)),
                        read_only(relative_covariance(Xa, Xb, P)), None)

    def share(self, a: str, b: str, at: float) -> bool:
        """Whether bodies ``a`` and ``b`` have measurements in their windows of a Lookup at
        ``at`` from a common source whose extrinsic is uncertain or whose latency is estimated
        (errors the two poses then share)."""
        w = self._world
        t, window = w.tracker, w.options.window
        common = (t.sources_of(t.rows_ending(a, w.window_end(a, at), window))
                  & t.sources_of(t.rows_ending(b, w.window_end(b, at), window)))
        return any(not t.table[s].exact for s in common if s in t.table)


def _plain(t: "Tracker") -> bool:
    """Whether tracker ``t``'s fit over time is the constant-twist fit ``_dqcore.lookup`` runs
    (not robust, no ``acceleration_psd``, no ``max_skew``)."""
    o = t.options
    return not o.robust and o.acceleration_psd is None and o.max_skew is None


def composed_independent(target: str, source: str, at: float,
              poses: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> BodyPose:
    """``T_target_source`` composed of the two bodies' own poses and covariances (``poses``),
    as if their errors were independent (the world frame "" is exact): the answer when they
    share no uncertain extrinsic, and the comparison the benchmark shows when they do."""
    zero = np.zeros((DOF, DOF))
    Xa, Pa = poses[target] if target else (_IDENT, zero)
    Xb, Pb = poses[source] if source else (_IDENT, zero)
    P = np.zeros((2 * DOF, 2 * DOF))
    P[:DOF, :DOF], P[DOF:, DOF:] = Pa, Pb
    return BodyPose(source, at, read_only(dq.mul(dq.conj(Xa), Xb)),
                    read_only(relative_covariance(Xa, Xb, P)), None)
