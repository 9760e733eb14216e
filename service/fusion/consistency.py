"""Each source's covariance judged against its innovations: the mean leave-one-out NIS of its
tested inliers against the two-sided χ² interval of the gate's probability
(:class:`~dqpose.fusion.results.SourceStats`: consistent, optimistic or pessimistic).
"""
from __future__ import annotations

import numpy as np

from dqpose.fusion.chi2 import chi2_quantile
from dqpose.fusion.results import DOF, SourceStats, Verdict

#: per probability, the verdict's interval by count (:func:`verdict_bounds`)
_BOUNDS: dict[float, np.ndarray] = {}


def verdict_bounds(probability: float, n: int) -> np.ndarray:
    """``(2, c)``, ``c > n``: the mean NIS interval ``[low, high]`` of a consistent source with
    ``count`` tested measurements in column ``count`` (column 0 unused), for ``probability``.
    One table a process (a quantile costs ~1 ms of Python): grown when a window needs more; the
    C tick (service/csrc/tick.h) reads the same numbers."""
    b = _BOUNDS.get(probability)
    if b is not None and b.shape[1] > n:
        return b
    old = 1 if b is None else b.shape[1]
    grown = np.zeros((2, n + 17))
    if b is not None:
        grown[:, :old] = b
    for count in range(old, n + 17):
        grown[0, count] = chi2_quantile(0.5 * (1.0 - probability), DOF * count) / count
        grown[1, count] = chi2_quantile(0.5 * (1.0 + probability), DOF * count) / count
    grown.flags.writeable = False
    _BOUNDS[probability] = grown
    return grown


def codes(names) -> tuple[tuple[str, ...], np.ndarray]:
    """Each source once, in order of first appearance, and each measurement's index in that."""
    order = {name: k for k, name in enumerate(dict.fromkeys(names))}
    return tuple(order), np.array([order[s] for s in names], dtype=np.intp)


def source_stats(sources, code, nis, tested, inlier, probability) -> tuple[SourceStats, ...]:
    """Per source (``sources``, measurement i's ``sources[code[i]]``)."""
    out = []
    use = tested & inlier
    m = len(sources)
    if not use.any():   # nothing tested (a fit without its NIS): every source untested
        rejected = [len(inlier) - int(np.count_nonzero(inlier))] if m == 1 else np.bincount(
            code, ~inlier, m).astype(np.intp).tolist()
        return tuple(SourceStats(name, 0, rejected[k], 0.0, 0.0, 0.0, Verdict.UNTESTED)
                     for k, name in enumerate(sources))
    if m == 1:      # one source (a common case): its counts without two bincounts
        counts = [int(np.count_nonzero(use))]
        rejected = [len(inlier) - int(np.count_nonzero(inlier))]
    else:
        counts = np.bincount(code, use, m).astype(np.intp).tolist()
        rejected = np.bincount(code, ~inlier, m).astype(np.intp).tolist()
    sums = np.bincount(code, np.where(use, nis, 0.0), m).tolist()
    bounds = verdict_bounds(probability, len(code))
    for k, name in enumerate(sources):
        count = counts[k]
        if count == 0:
            out.append(SourceStats(name, 0, rejected[k], 0.0, 0.0, 0.0, Verdict.UNTESTED))
            continue
        mean = sums[k] / count
        low, high = float(bounds[0, count]), float(bounds[1, count])
        verdict = (Verdict.OPTIMISTIC if mean > high else
                   Verdict.PESSIMISTIC if mean < low else Verdict.CONSISTENT)
        out.append(SourceStats(name, count, rejected[k], mean, low, high, verdict))
    return tuple(out)
