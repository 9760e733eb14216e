"""What a fusion returns: the fused pose (:class:`Fused`) and how it was reached (:class:`Status`),
the measurements the gate rejected (:class:`Rejection`) or the time alignment dropped
(:class:`Dropped`), each source's consistency (:class:`SourceStats`, :class:`Verdict`) and the
latencies estimated online (:class:`Latency`). Covariances and residuals are in the convention of
:mod:`dqpose.fusion`.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Optional

import numpy as np

#: a pose's degrees of freedom: the length of its tangent vector, the side of its covariance, the
#: χ² degrees of freedom of one measurement's NIS
DOF = 6


class Status(enum.IntEnum):
    """How the estimate was reached (ruckig-style result code)."""
    CONVERGED = 0        # the last Gauss-Newton step was shorter than tol
    MAX_ITERATIONS = 1   # max_iter steps taken, the last one still longer than tol
    GATE_UNSTABLE = 2    # robust mode: the inlier set cycled, or had not settled after _GATE_FITS
                         # fits; the fit of the last set is returned


class Verdict(enum.IntEnum):
    """A source's covariance against its innovations (two-sided χ² test of the NIS sum)."""
    UNTESTED = 0         # no inlier of the source could be checked against other inliers
    CONSISTENT = 1
    OPTIMISTIC = 2       # innovations larger than the covariance says: it claims too much
    PESSIMISTIC = 3      # innovations smaller than the covariance says

def _who(index: int, source: str) -> str:
    return f"measurement {index}" + (f" ({source})" if source else "")


@dataclass(frozen=True)
class Rejection:
    """Measurement ``index`` (of source ``source``, ``""`` when unnamed) failed the gate: its
    innovation's Mahalanobis distance ``distance`` exceeded ``gate`` (both sqrt of χ², 6 dof)."""
    index: int
    source: str
    distance: float
    gate: float
    probability: float

    @property
    def reason(self) -> str:
        who = _who(self.index, self.source)
        return (f"{who}: Mahalanobis distance {self.distance:.3g} against the other inliers is "
                f"beyond the gate {self.gate:.3g} (chi2, {DOF} dof, p = {self.probability:g})")


@dataclass(frozen=True)
class SourceStats:
    """NIS statistics of one source's inliers: ``nis_mean`` over ``count`` tested measurements
    (6 expected), the interval ``[low, high]`` it falls in with the gate's probability for a
    consistent source, and the verdict; ``rejected`` counts its measurements the gate removed."""
    name: str
    count: int
    rejected: int
    nis_mean: float
    low: float
    high: float
    verdict: Verdict


@dataclass(frozen=True)
class Fused:
    """A fused pose. Arrays are read-only; per-measurement arrays index the input measurements.

    ``mean`` ``(8,)`` is ``T_world_body``; ``covariance`` ``(6, 6)`` its covariance in the
    convention of :mod:`dqpose.fusion`. ``residuals[i] = Log(mean⁻¹ Z_i)`` of the measurement in
    the world frame, ``distances[i] = sqrt(r_iᵀ Σ_i⁻¹ r_i)``; ``nis[i]`` is the leave-one-out
    normalised innovation squared (0 for a measurement with no other inlier to check it against,
    flagged in ``tested``). ``chi2`` is the sum of the inliers' squared distances (the cost at the
    optimum, twice GTSAM's graph error) with ``dof = 6 (len(inliers) - 1)`` degrees of freedom.

    With times, ``mean`` is the pose at ``time`` and ``covariance`` its marginal (the twist's and
    the estimated latencies' uncertainty included); residuals, distances and NIS are against the
    prediction at each measurement's own time; ``chi2`` adds the priors' terms and ``dof`` is
    ``6 (len(inliers) - 1)``, less 6 more when the twist has no prior.
    """
    status: Status
    mean: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    distances: np.ndarray
    nis: np.ndarray
    tested: np.ndarray
    inliers: np.ndarray
    rejected: tuple[Rejection, ...]
    chi2: float
    dof: int
    iterations: int
    sources: tuple[SourceStats, ...]
    # With times (None / empty without): the fusion time the mean is the pose at; the body twist
    # V with T(t) = mean · Exp((t - time) V) and its covariance; how far (seconds) the fusion
    # time lies outside the span of the measurements used; the measurements dropped for skew;
    # the latencies estimated online.
    time: Optional[float] = None
    twist: Optional[np.ndarray] = None
    twist_covariance: Optional[np.ndarray] = None
    extrapolation: float = 0.0
    dropped: tuple["Dropped", ...] = ()
    latencies: tuple["Latency", ...] = ()


@dataclass(frozen=True)
class Dropped:
    """Measurement ``index`` (of source ``source``) was taken ``age`` seconds before the fusion
    time (negative: after it), further than ``max_skew`` from it; it did not enter the fit.
    ``why``: another reason it did not (a World's rider whose parent is not known at its time,
    :mod:`dqpose.riders`)."""
    index: int
    source: str
    age: float
    max_skew: float
    why: str = ""

    @property
    def reason(self) -> str:
        who = _who(self.index, self.source)
        if self.why:
            return f"{who}: {self.why}"
        when = f"{self.age:.6g} s before" if self.age >= 0 else f"{-self.age:.6g} s after"
        return f"{who}: taken {when} the fusion time, beyond max_skew {self.max_skew:g} s"


@dataclass(frozen=True)
class Latency:
    """Source ``name``'s latency estimated online: from the prior ``configured`` ± ``prior_sigma``
    to ``value`` ± ``sigma`` (its marginal standard deviation)."""
    name: str
    configured: float
    prior_sigma: float
    value: float
    sigma: float


def read_only(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a
