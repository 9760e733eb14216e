"""The robust mode's gate, shared by the fit of one instant and the fit over time: a start from the
largest pairwise-consistent group (:func:`consensus`), then inliers removed and admitted on their
leave-one-out NIS against the χ² gate until the set settles (:func:`nis_gate`). The answer is always
the plain maximum-likelihood fit of the inliers, so a rejected measurement never moves it.
"""
from __future__ import annotations

import math

import numpy as np

from dqpose import _dqcore as _c
from dqpose.fusion.results import Rejection, Status

# The consensus compares every measurement with at most this many candidates for the group's
# centre (all of them when there are no more): O(n) rather than every pair's O(n^2).
_CANDIDATES = 64


def consensus(Z: np.ndarray, S: np.ndarray, gate2: float) -> np.ndarray:
    """The measurement agreeing with most others, and those: pairwise ``Log(Z_i⁻¹ Z_j)`` against
    ``Σ_i + Σ_j`` (to first order ``Exp(ε_i) Exp(-ε_j)``, both in the body frame), in C. Beyond
    ``_CANDIDATES`` measurements the centre is sought among that many spread over them (any
    inlier finds the inliers' group; the gate that follows judges every measurement)."""
    n = Z.shape[0]
    cand = np.arange(n) if n <= _CANDIDATES else (np.arange(_CANDIDATES) * n) // _CANDIDATES
    D2 = _c.pair_distances(Z, S, cand)
    agree = D2 <= gate2
    agree[np.arange(len(cand)), cand] = True
    count = agree.sum(axis=1)
    spread = np.where(agree, D2, 0.0).sum(axis=1)
    best = min(range(len(cand)), key=lambda a: (-count[a], spread[a], a))
    return agree[best].copy()


# The gate refits at most this many times (each fit is linear in the measurements, or cubic with
# an acceleration_psd): the bound of a robust fit's cost (service/limits.py).
_GATE_FITS = 50


def nis_gate(inlier, allowed, fit_of, nis_of, gate2):
    """From ``inlier``: remove the worst failing inlier, one at a time (an outlier inside pulls
    the others' innovations), then admit every ``allowed`` measurement that passes; until
    nothing changes, a set repeats or ``_GATE_FITS`` fits were made."""
    seen = set()
    status = None
    while True:
        fit = fit_of(inlier)
        nis, tested = nis_of(fit, inlier)
        key = inlier.tobytes()
        if key in seen or len(seen) >= _GATE_FITS:
            status = Status.GATE_UNSTABLE
            break
        seen.add(key)
        fails = inlier & tested & (nis > gate2)
        if fails.any():
            worst = int(np.argmax(np.where(fails, nis, -np.inf)))
            inlier = inlier.copy()
            inlier[worst] = False
            continue
        joins = allowed & ~inlier & (nis <= gate2)
        if not joins.any():
            break
        inlier = inlier | joins
    return fit, nis, tested, inlier, status


def rejections(names, nis: np.ndarray, out: np.ndarray, gate2: float,
                probability: float) -> tuple[Rejection, ...]:
    """The measurements ``out`` selects, each as the gate rejected it."""
    if not out.any():
        return ()
    gate = math.sqrt(gate2)
    return tuple(Rejection(int(i), names[i], float(math.sqrt(nis[i])), gate, probability)
                 for i in np.flatnonzero(out))
