"""Where the maximum-likelihood fit starts: the consensus of minimal sets (least median of
squares), so that the fit and its χ² gate are never anchored on outliers.

The gate judges each sample against a fit; a fit made on a set holding outliers is pulled towards
them and, with a tight noise given, makes most genuine samples fail too (12 samples, 30 % marker
flips of 1–4° at 0.1° / 0.5 mm given: 8 of 40 seeds 1–6 mm off at NEES 70–680, two with no sample
named). Screw congruence does not catch an outlier whose rotation error lies mostly across the
motions' axes. So: hypotheses ``(X, Z)`` from minimal sets of three samples (Daniilidis on their
three pairs), and the closed form of the whole data as one more; each scored by the ``h``-th
smallest squared Mahalanobis residual over the samples (``h`` just over half: least median of
squares, which tolerates up to half the samples off); the best one's samples within the χ² gate
at its robust scale are the set the fit starts from, and the gate then re-admits or rejects from
the fit on them. On healthy data the closed form wins and the start is every sample it passes.

The residuals are weighed by the given noise (transported, :mod:`~dqpose.handeye.noise`), or
when it is estimated by the isotropic rotation and translation variances of the closed form's
residuals (their median absolute values; only their ratio matters here).
"""
from __future__ import annotations

import itertools
from functools import lru_cache
from typing import TYPE_CHECKING, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.fusion.chi2 import chi2_quantile
from dqpose.handeye.closed_form import (
    MAX_PAIR_ANGLE,
    MIN_PAIR_ANGLE,
    hemisphere,
    rows,
    unit_in_span,
)
from dqpose.handeye.noise import FLOORS, Noise

if TYPE_CHECKING:
    from dqpose.handeye.checks import Prepared

_HYPOTHESES = 128      # minimal sets drawn (all of them when there are fewer): with half the
                       # samples outliers, all three genuine in one of 8, missed in 128 draws
                       # with probability 4e-8
_SEED = 20260909       # the draws are the same for the same data: one answer for one input


def consensus(p: Prepared, noise: Noise,
               gate: float) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(start, X, Z)``: the samples the fit starts from (within the χ²₆ quantile ``gate`` at
    the robust scale) and the best hypothesis; None when there are too few samples for a
    consensus to choose (four or fewer)."""
    idx = np.flatnonzero(p.use)
    n = len(idx)
    if n <= 4:
        return None
    A, C = p.A[idx], p.C[idx]
    X, Z = _hypotheses(A, C, _triples(n))
    X = np.concatenate([p.closed[0][None], X])
    Z = np.concatenate([p.closed[1][None], Z])
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z)[:, None], A[None]), X[:, None]), C[None])
    r = lie.se3_log(E)                                                   # (m, n, 6)
    h = (n + 3) // 2
    W = _metric(p, noise, idx, r[0])
    best, d, cost = _best(r, W, h)
    if noise.estimate and best is not None:
        # The closed form's residuals hold the outliers, which can inflate one component (marker
        # flips: the rotation) and so hide them: the variances again from the best hypothesis'
        # h closest samples.
        W = _metric(p, noise, idx, r[best][np.argsort(d[best])[:h]])
        best, d, cost = _best(r, W, h)
    if best is None:
        return None
    # The robust scale of the best hypothesis' residuals: its h-th smallest against the χ²₆
    # quantile there, with the small-sample correction of least median of squares. With the
    # noise given never below 1, so that the start is never tighter than the gate; with it
    # estimated, the start is where the noise is first estimated from, and starting from only
    # the h closest (a truncated sample) underestimated it enough for the gate to reject
    # genuine samples in turn (10 poses: NEES 8.3, 97 rejections in 200 healthy scenes).
    scale = cost[best] / _quantile(h, n) * (1.0 + 5.0 / (n - 3)) ** 2
    if not noise.estimate:
        scale = max(scale, 1.0)
    start = np.zeros(p.F.shape[0], bool)
    start[idx] = d[best] <= gate * scale
    return start, X[best], Z[best]


def _best(r, W, h: int):
    """The hypothesis whose ``h``-th smallest squared residual in the metric ``W`` is least (None
    when none is finite), every one's squared residuals and those costs."""
    d = np.einsum("mni,nij,mnj->mn", r, W, r)
    cost = np.partition(np.where(np.isfinite(d), d, np.inf), h - 1, axis=1)[:, h - 1]
    best = int(np.argmin(cost))
    return (best if np.isfinite(cost[best]) else None), d, cost


@lru_cache(maxsize=256)
def _quantile(h: int, n: int) -> float:
    return chi2_quantile(h / (n + 1), 6)


def _triples(n: int) -> np.ndarray:
    """``(m, 3)`` sample positions, ascending in each row: every triple when there are at most
    ``_HYPOTHESES``, else that many drawn."""
    if n * (n - 1) * (n - 2) // 6 <= _HYPOTHESES:
        return np.array(list(itertools.combinations(range(n), 3)))
    rng = np.random.default_rng(_SEED)
    return np.sort(np.argpartition(rng.random((_HYPOTHESES, n)), 3, axis=1)[:, :3], axis=1)


def _hypotheses(A, C, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(X, Z)`` of each triple ``t``: Daniilidis on its three pairs' motions (those rotating
    enough, as in the closed form), ``Z`` the mean of its ``A_i X C_i``; the triples with fewer
    than two such pairs left out."""
    m = len(t)
    i, j = t[:, [0, 0, 1]].ravel(), t[:, [1, 2, 2]].ravel()
    a = hemisphere(dq.mul(dq.inv(A[j]), A[i]))
    b = hemisphere(dq.mul(C[j], dq.inv(C[i])))
    ang = 2.0 * np.arccos(np.clip(a[:, 0], -1.0, 1.0))
    keep = ((ang > MIN_PAIR_ANGLE) & (ang < MAX_PAIR_ANGLE)).reshape(m, 3)
    T = rows(a, b).reshape(m, 3, 6, 8) * keep[..., None, None]
    G = np.einsum("mpki,mpkj->mij", T, T)
    _, V = np.linalg.eigh(G)
    with np.errstate(invalid="ignore", divide="ignore"):
        X = unit_in_span(V[..., 0], V[..., 1])
    ok = (keep.sum(axis=1) >= 2) & np.all(np.isfinite(X), axis=1)
    X, t = X[ok], t[ok]
    K = dq.mul(dq.mul(A[t], X[:, None]), C[t])                           # (m, 3, 8)
    K = np.where((np.einsum("mki,mi->mk", K[..., :4], K[:, 0, :4]) < 0.0)[..., None], -K, K)
    return X, dq.normalize(K.sum(axis=1))


def _metric(p: Prepared, noise: Noise, idx, r0) -> np.ndarray:
    """``(n, 6, 6)``: the inverse residual covariances the hypotheses are scored in: the given
    noise transported at the closed form's X, or the isotropic rotation and translation variances
    of the closed form's residuals ``r0`` (as :class:`~dqpose.handeye.noise.Noise` starts)."""
    n = len(idx)
    if noise.estimate:
        v = (1.4826 * np.median(np.abs(r0), axis=0)) ** 2
        var = np.maximum(np.array([v[:3].mean(), v[3:].mean()]), FLOORS[:2])
        return np.broadcast_to(np.diag(np.repeat(1.0 / var, 3)), (n, 6, 6))
    use = np.zeros(p.F.shape[0], bool)
    use[idx] = True
    S = noise(p.closed[0], p.C[idx], np.zeros((n, 6)), np.broadcast_to(np.eye(6), (n, 6, 6)),
              use)
    return np.linalg.inv(S)
