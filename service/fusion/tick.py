"""A tick's answer in one C call (service/csrc/tick.h): a tracker's rows to the ``FusedPose``
bytes of their fit over time, the answer :meth:`Tracker.estimate` and
:func:`dqpose.rpc.wire.fused_pose_bytes` give, bit for bit, for the common case (not robust,
the constant twist or one instant, jointly with uncertain extrinsics); None where the C leaves
the answer to that Python path (robust, ``acceleration_psd``; it also names every error).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from dqpose import _dqcore, dq
from dqpose.fusion.consistency import verdict_bounds
from dqpose.fusion.tracker import Tracker
from dqpose.fusion.validation import checked_seconds, twist_information


def _options(t: Tracker) -> _dqcore.FitOptions:
    """The C tick's options of tracker ``t``: its checked options and, per source code, the
    source's latency and prior and whether its extrinsic is exact (the numbers the Python set-up
    computes, by the same expressions)."""
    o, table, names = t.options, t.table, list(t.source_names)
    srcs = [table.get(name) for name in names]
    sigma = [None if s is None else s.latency_sigma for s in srcs]   # None: not estimated
    C, Wp = (None, None) if o.twist_covariance is None else twist_information(
        o.twist_covariance)
    # the uncertain extrinsics and their information, as extrinsics.uncertain_extrinsics makes them
    E, info = np.zeros((len(names), 8)), np.zeros((len(names), 6, 6))
    uncertain = [(k, s) for k, s in enumerate(srcs) if s is not None
                 and s.extrinsic_covariance is not None]
    if uncertain:
        ident = dq.identity()
        at = [k for k, _ in uncertain]
        E[at] = np.array([ident if s.extrinsic is None else s.extrinsic for _, s in uncertain])
        inv = np.linalg.inv(np.array([s.extrinsic_covariance for _, s in uncertain]))
        info[at] = 0.5 * (inv + np.swapaxes(inv, 1, 2))
    return _dqcore.FitOptions(
        np.array(t.latencies, np.float64),
        np.array([math.nan if x is None else x for x in sigma], np.float64),
        np.array([math.nan if x is None else x ** -2 for x in sigma], np.float64),
        np.array([x is not None for x in sigma], bool),
        np.array([s is None or s.extrinsic_covariance is None for s in srcs], bool), names,
        E.ravel(), info.ravel(),
        None if o.max_skew is None else checked_seconds(o.max_skew, "max_skew", "nonnegative"),
        None if o.max_extrapolation is None else checked_seconds(
            o.max_extrapolation, "max_extrapolation", "nonnegative"),
        None if Wp is None else np.ascontiguousarray(Wp).ravel(),
        None if C is None else np.ascontiguousarray(C).ravel(), o.probability, o.tol, o.max_iter)


class WireTicks:
    """Tracker ``tracker``'s ticks in C: its options made once (again when it has met a new
    source); None for every tick when its fit is robust or correlated (``acceleration_psd``)."""

    def __init__(self, tracker: Tracker):
        self.tracker = tracker
        o = tracker.options
        self.plain = not o.robust and (o.acceleration_psd is None
                                       or not np.any(o.acceleration_psd))
        self._options: Optional[_dqcore.FitOptions] = None

    def __call__(self, rows: np.ndarray, time: Optional[float], body: str, request: int,
                 pose=None, covariance=None) -> Optional[bytes]:
        """The ``FusedPose`` bytes of the fit of ``rows`` at ``time`` (None: their newest
        taken) as ``body``'s answer to ``request``, with the rows' ids (``pose`` and
        ``covariance``: the answer's instead of the fit's); None: not made here."""
        if not self.plain:
            return None
        t = self.tracker
        opts = self._options
        if opts is None or opts.sources != len(t.source_names):
            opts = self._options = _options(t)
        s = t.store
        return _dqcore.tick(opts, s.wposes, s.wcovs if "wcovs" in s.arrays else s.covs,
                            s.times, s.codes, s.ids, rows, math.nan if time is None else time,
                            body, request, verdict_bounds(t.options.probability, len(rows)),
                            pose, covariance)
