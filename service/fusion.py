"""Pose fusion: n measurements of one rigid body in, one estimate with an honest covariance out.

Conventions (stated once; :mod:`dqpose.lie` holds the tangent-space tools used here):

* A covariance is 6×6, row-major, **rotation first** (``[ωx ωy ωz vx vy vz]``, radians then
  metres), for a **right (body-frame) perturbation**: the true pose is ``T · Exp(ξ)``,
  ``ξ ~ N(0, Σ)``, with ``Exp`` the SE(3) exponential. This is GTSAM's ``Pose3`` convention
  (``retract`` = compose with ``Expmap``), so a user can check us against GTSAM, and the tests do.
* A measurement is ``T_frame_body`` in its source's frame; each source has an extrinsic
  ``T_world_frame`` (identity when not given) and, for an arm, the body's offset in the flange
  frame ``T_flange_body``; the fused pose is ``T_world_body``. A measurement enters the fusion as
  ``T_world_frame · T_frame_body · T_flange_body``; the constant extrinsic on the left leaves its
  covariance as it is, the constant offset on the right maps it exactly to
  ``Ad(O⁻¹) Σ Ad(O⁻¹)ᵀ`` (:func:`dqpose.lie.cov_compose`).
* The residual of measurement ``Z_i`` at the estimate ``X`` is ``r_i = Log(X⁻¹ Z_i)``; its
  negative is GTSAM's ``PriorFactorPose3`` error ``Log(Z_i⁻¹ X)``, so both minimise the same cost
  ``Σ r_iᵀ Σ_i⁻¹ r_i``. Its exact Jacobian for ``X · Exp(δ)`` is ``-Jl⁻¹(r_i) = -Jr⁻¹(-r_i)``.
* Scalar weights are the isotropic special case: ``Σ_i = I / w_i``.

The maximum-likelihood estimate is found by Gauss–Newton on SE(3) from the DIB mean
(:func:`dqpose.dq.dib`) until a step is shorter than ``tol``, in the C core (``fusion.c``); its covariance is the inverse of the
information ``Σ Jᵢᵀ Σᵢ⁻¹ Jᵢ`` at the optimum (GTSAM's marginal). The robust mode starts from the
largest pairwise-consistent group and gates every measurement on its leave-one-out normalised
innovation squared (NIS: the measurement against the fit of the other inliers, ``χ²`` with 6 degrees
of freedom for a consistent source); the answer is always the plain maximum-likelihood fit of the
inliers, so a rejected measurement never moves it.

Time alignment (:func:`fuse` with ``times``): a measurement stamped ``t`` by a source with latency
``ℓ`` was taken at ``τ = t − ℓ``. The body moves with a constant body twist ``V`` over the window,
``T(τ) = X · Exp((τ − time) V)`` with ``X`` the pose at the fusion time, so the prediction of
measurement i is ``P_i = X Exp(dt_i V)``, ``dt_i = τ_i − time``, and its residual
``r_i = Log(P_i⁻¹ Z_i)``. Pose, twist (and the latencies a source asks to have estimated) are
found jointly by Gauss–Newton with exact Jacobians (in C, ``dq_motion_fit`` in
``fusion.c``, leave-one-out NIS included; the correlated model below is NumPy): for ``X · Exp(δ)``, ``V + ε`` and ``ℓ + λ`` the
prediction moves by ``Exp(η)`` on the right with ``η = Ad(Exp(−dt V)) δ + dt Jr(dt V) ε − V λ``,
and ``r_i`` by ``−Jl⁻¹(r_i) η``. The covariance is the inverse of the joint information; its pose
block is the marginal at the fusion time, so it carries the twist's (and latencies') uncertainty.

A body that accelerates leaves the constant-twist model, and without process noise the fit then
claims more than it knows (mean NEES 7.4–8.3 instead of 6 for the accelerating body of
tests/test_fusion_time.py). ``acceleration_psd`` ``Q`` (6 × 6, rotation first, rad²/s³ and m²/s³)
models exactly this, and nothing more: the true pose at ``τ`` is
``T(τ) = X · Exp(dt V) · Exp(ε(τ))`` with ``ε`` the twice-integrated white noise of power
spectral density ``Q`` started at the fusion time (``ε(τ) = ∫ (τ − s) w(s) ds`` from the fusion
time to ``τ``: the twist a random walk whose covariance grows by ``Q`` per second, the
white-noise-on-acceleration prior, conditioned on the pose and twist at the fusion time). Its
errors are correlated: ``Cov(ε(τ_i), ε(τ_j)) = k(dt_i, dt_j) Q`` with ``k = m² M / 2 − m³ / 6``
(``m``, ``M`` the smaller and larger of ``|dt_i|``, ``|dt_j|``) on the same side of the fusion
time, 0 on opposite sides. The fit uses the joint covariance of all residuals, the measurements'
own block-diagonal ``Σ_i`` plus this (``r`` ≈ ``ε_i − ξ_i``, the model error taken at the
prediction), so the cost is ``rᵀ C⁻¹ r`` with a dense ``C`` (6n × 6n: ≈ 35 ms for 112
measurements in NumPy) and the covariance is the inverse of ``Gᵀ C⁻¹ G``. ``C`` is held at the
latencies it was evaluated at; estimated latencies are re-solved with it re-evaluated at their
estimate until they settle. The leave-one-out NIS conditions each measurement on the others'
residuals as well as on the state (:func:`_correlated_nis`); ``distances`` use the
measurement's own share ``Σ_i + |dt_i|³/3 Q``; ``chi2`` is ``rᵀ C⁻¹ r`` (same dof). A rule of
thumb: accelerations of size ``a`` held over a window ``L`` change the twist by ``a L``, the
random walk by ``sqrt(Q L)``, so ``Q ≈ a² L``. ``Q = 0`` is the constant-twist model, computed
exactly as without it.
:class:`Tracker` keeps a sliding window of measurements per body for live streams.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Iterable, NamedTuple, Optional, Sequence

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq, lie
from dqpose import limits as _limits
from dqpose.errors import rename

__all__ = ["DOF", "DEFAULT_PROBABILITY", "DEFAULT_MAX_EXTRAPOLATION", "Status", "Verdict", "Source", "Rejection", "SourceStats", "Fused",
           "fuse", "chi2_quantile", "Dropped", "Latency", "Measurement", "Window", "Tracker"]

DOF = 6
#: the χ² probability of the robust gate and of a fused pose's consistency verdict
DEFAULT_PROBABILITY = 0.999
#: seconds a fused pose's time may lie past its newest measurement (extrapolated on the twist)
DEFAULT_MAX_EXTRAPOLATION = 0.1
# Relative asymmetry a covariance may have and still be taken as symmetric (its mean with its
# transpose is used): a product J Σ Jᵀ computed in float64 is asymmetric at ~1e-16.
_SYMMETRY_TOL = 1e-9
# The variances a covariance may have (standard deviations 1e-12 to 1e12 rad or m): beyond them
# its information cannot be used (service/csrc/fusion.h, which checks the same for StreamFuse).
_MIN_VARIANCE, _MAX_VARIANCE = _c.MIN_VARIANCE, _c.MAX_VARIANCE
# The motion model's Gauss-Newton halves a step that raises the cost by more than _COST_SLACK
# (relative), at most _MAX_HALVINGS times: the rule of the static fit in service/csrc/fusion.c.
_COST_SLACK = 1e-12
_MAX_HALVINGS = 30


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


@dataclass(frozen=True)
class Source:
    """A source's frames: ``extrinsic`` is ``T_world_frame`` and ``body_offset`` the body in the
    frame the source measures (``T_flange_body`` for an arm); ``None`` is the identity.

    ``latency`` (seconds): a measurement stamped ``t`` was taken at ``t - latency`` (used when
    :func:`fuse` is given times). ``latency_sigma``: ``None`` takes the latency as exact; a
    positive value makes it a prior ``N(latency, latency_sigma²)`` and estimates it from the data
    jointly with the motion (reported in :attr:`Fused.latencies`)."""
    name: str
    extrinsic: Optional[np.ndarray] = None
    body_offset: Optional[np.ndarray] = None
    latency: float = 0.0
    latency_sigma: Optional[float] = None


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
    convention above. ``residuals[i] = Log(mean⁻¹ Z_i)`` of the measurement in the world frame,
    ``distances[i] = sqrt(r_iᵀ Σ_i⁻¹ r_i)``; ``nis[i]`` is the leave-one-out normalised innovation
    squared (0 for a measurement with no other inlier to check it against, flagged in
    ``tested``). ``chi2`` is the sum of the inliers' squared distances (the cost at the optimum,
    twice GTSAM's graph error) with ``dof = 6 (len(inliers) - 1)`` degrees of freedom.

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


# ---- χ² quantiles (no SciPy in the core) -------------------------------------------------------
def _gamma_p(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function P(a, x) (series / continued fraction)."""
    if x <= 0.0:
        return 0.0
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        k = a
        while abs(term) > abs(total) * 1e-17:
            k += 1.0
            term *= x / k
            total += term
        return min(1.0, total * math.exp(log_front))
    # Lentz's continued fraction for Q(a, x)
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 100000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return max(0.0, 1.0 - math.exp(log_front) * h)


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """The ``probability`` quantile of the χ² distribution with ``dof`` degrees of freedom."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability: must be within (0, 1), got {probability!r}")
    if dof < 1:
        raise ValueError(f"dof: must be >= 1, got {dof!r}")
    a = 0.5 * dof
    lo, hi = 0.0, max(1.0, float(dof))
    while _gamma_p(a, 0.5 * hi) < probability:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if _gamma_p(a, 0.5 * mid) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# ---- input -------------------------------------------------------------------------------------
def _finite(x, name: str, tail: tuple[int, ...], n: Optional[int]) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers, got {type(x).__name__}") from None
    want = ((n,) if n is not None else (None,)) + tail
    if a.ndim != len(want) or any(w is not None and s != w for s, w in zip(a.shape, want)):
        shape = ", ".join("n" if w is None else str(w) for w in want)
        got = f"{a.shape}" + (f" for {n} poses" if n is not None else "")
        raise ValueError(f"{name}: expected shape ({shape}), got {got}")
    if a.size == 0:
        return a
    bad = ~np.isfinite(a).reshape(a.shape[0], -1).all(axis=1)
    if np.any(bad):
        raise ValueError(f"{name}[{int(np.flatnonzero(bad)[0])}]: contains NaN or infinity")
    return a


def _poses(poses) -> np.ndarray:
    Z = _finite(poses, "poses", (8,), None)
    if Z.shape[0] == 0:
        raise ValueError("poses: no measurements (expected at least one pose)")
    try:
        dq.to_matrix(Z)  # the core's unit and rigidity checks, with the index
    except ValueError as e:
        raise rename(e, {"a": "poses{}"}) from None
    return dq.normalize(Z)


def _pose(T, name: str) -> np.ndarray:
    a = _finite(np.asarray(T, dtype=np.float64)[None] if np.ndim(T) == 1 else T, name, (8,), 1)
    try:
        dq.to_matrix(a)
    except ValueError as e:
        raise ValueError(f"{name}: {str(e).split(': ', 1)[-1]}") from None
    return dq.normalize(a[0])


def _covariances(covariances, weights, n: int) -> np.ndarray:
    if covariances is not None and weights is not None:
        raise ValueError("weights: give covariances or weights, not both")
    if weights is not None:
        w = _finite(weights, "weights", (), n)
        bad = ~(w > 0.0)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"weights[{i}]: must be positive, got {w[i]!r}")
        return np.eye(DOF) / w[:, None, None]
    if covariances is None:
        return np.broadcast_to(np.eye(DOF), (n, DOF, DOF)).copy()
    S = _finite(covariances, "covariances", (DOF, DOF), n)
    scale = np.abs(S).reshape(n, -1).max(axis=1)
    asym = np.abs(S - np.swapaxes(S, 1, 2)).reshape(n, -1).max(axis=1)
    bad = ~(asym <= _SYMMETRY_TOL * scale)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"covariances[{i}]: not symmetric (largest asymmetry {asym[i]:.3g})")
    var = np.diagonal(S, axis1=1, axis2=2)
    out = (var > 0.0) & ~((var >= _MIN_VARIANCE) & (var <= _MAX_VARIANCE))   # <= 0: not SPD
    bad = out.any(axis=1)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        v = var[i][out[i]][0]
        raise ValueError(f"covariances[{i}]: variance {v:.6g} outside [{_MIN_VARIANCE:g}, "
                         f"{_MAX_VARIANCE:g}] (standard deviations 1e-12 to 1e+12 rad or m): "
                         f"its information cannot be used")
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        for i in range(n):  # one matrix at a time, so the message can name the index
            try:
                np.linalg.cholesky(S[i])
            except np.linalg.LinAlgError:
                raise ValueError(f"covariances[{i}]: not positive definite") from None
    return S


def _names(names, n: int) -> tuple[str, ...]:
    if names is None:
        return ("",) * n
    if isinstance(names, str):
        raise ValueError("names: expected one source name per measurement, got a string")
    out = tuple(names)
    if len(out) != n:
        raise ValueError(f"names: expected {n} source names, got {len(out)}")
    for i, s in enumerate(out):
        if not isinstance(s, str):
            raise ValueError(f"names[{i}]: expected a string, got {type(s).__name__}")
    return out


def _sources(sources: Optional[Iterable[Source]]) -> dict[str, Source]:
    table: dict[str, Source] = {}
    for k, s in enumerate(sources or ()):
        if not isinstance(s, Source):
            raise ValueError(f"sources[{k}]: expected a Source, got {type(s).__name__}")
        if not s.name:
            raise ValueError(f"sources[{k}]: a source needs a name")
        if s.name in table:
            raise ValueError(f"sources[{k}]: source {s.name!r} given twice")
        table[s.name] = Source(
            s.name,
            None if s.extrinsic is None else _pose(s.extrinsic, f"sources[{k}].extrinsic"),
            None if s.body_offset is None else _pose(s.body_offset, f"sources[{k}].body_offset"),
            *_latency(s, k))
    return table


def _to_world(Z: np.ndarray, S: np.ndarray, names: tuple[str, ...],
              table: dict[str, Source]) -> tuple[np.ndarray, np.ndarray]:
    """``T_world_frame · Z · T_flange_body`` and the exactly transported covariances."""
    framed = [(name, src) for name, src in table.items()
              if src.body_offset is not None or src.extrinsic is not None]
    if framed:
        Z, S = Z.copy(), S.copy()
    for name, src in framed:
        idx = [i for i, s in enumerate(names) if s == name]
        if not idx:
            continue
        if src.body_offset is not None:
            Z[idx] = dq.mul(Z[idx], src.body_offset)
            S[idx] = lie.cov_compose(S[idx], src.body_offset, None)
        if src.extrinsic is not None:
            Z[idx] = dq.mul(src.extrinsic, Z[idx])
    return dq.normalize(Z), S


# ---- the maximum-likelihood core (service/csrc/fusion.c; tests/fusion_reference.py in NumPy) ----
@dataclass(frozen=True)
class _Fit:
    status: Status
    mean: np.ndarray
    covariance: np.ndarray  # inverse information at the optimum
    r: np.ndarray           # residuals Log(mean⁻¹ Z_i), all measurements
    distances: np.ndarray   # sqrt(r_iᵀ Σ_i⁻¹ r_i), all measurements
    nis: np.ndarray         # leave-one-out NIS against the fit of the other inliers
    tested: np.ndarray
    chi2: float             # the inliers' squared distances summed (the cost at the optimum)
    iterations: int


def _fit(Z: np.ndarray, S: np.ndarray, inlier: np.ndarray, tol: float, max_iter: int) -> _Fit:
    """ML fit of the measurements ``inlier`` selects, evaluated at every measurement, with the
    leave-one-out NIS of each: measurement j against the fit of the other inliers (one
    Gauss-Newton step from the optimum; an outlier against all inliers; untested without
    another inlier)."""
    mean, P, r, d, nis, tested, status, iterations, chi2 = _c.fuse(Z, S, inlier, tol, max_iter)
    return _Fit(Status(int(status)), mean, P, r, d, nis, tested, float(chi2), int(iterations))


# ---- robust mode -------------------------------------------------------------------------------
# The consensus compares every measurement with at most this many candidates for the group's
# centre (all of them when there are no more): O(n) rather than every pair's O(n^2).
_CANDIDATES = 64


def _consensus(Z: np.ndarray, S: np.ndarray, gate2: float) -> np.ndarray:
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


def _robust(Z, S, gate2, tol, max_iter):
    # the C fit computes each measurement's leave-one-out NIS with the fit itself
    return _gate(_consensus(Z, S, gate2), np.ones(Z.shape[0], dtype=bool),
                 lambda inlier: _fit(Z, S, inlier, tol, max_iter),
                 lambda fit, inlier: (fit.nis, fit.tested), gate2)


# ---- consistency -------------------------------------------------------------------------------
def _codes(names) -> tuple[tuple[str, ...], np.ndarray]:
    """Each source once, in order of first appearance, and each measurement's index in that."""
    order = {name: k for k, name in enumerate(dict.fromkeys(names))}
    return tuple(order), np.array([order[s] for s in names], dtype=np.intp)


def _source_stats(sources, code, nis, tested, inlier, probability) -> tuple[SourceStats, ...]:
    """Per source (``sources``, measurement i's ``sources[code[i]]``)."""
    out = []
    use = tested & inlier
    m = len(sources)
    counts = np.bincount(code, use, m).astype(np.intp).tolist()
    rejected = np.bincount(code, ~inlier, m).astype(np.intp).tolist()
    sums = np.bincount(code, np.where(use, nis, 0.0), m).tolist()
    for k, name in enumerate(sources):
        count = counts[k]
        if count == 0:
            out.append(SourceStats(name, 0, rejected[k], 0.0, 0.0, 0.0, Verdict.UNTESTED))
            continue
        mean = sums[k] / count
        low = chi2_quantile(0.5 * (1.0 - probability), DOF * count) / count
        high = chi2_quantile(0.5 * (1.0 + probability), DOF * count) / count
        verdict = (Verdict.OPTIMISTIC if mean > high else
                   Verdict.PESSIMISTIC if mean < low else Verdict.CONSISTENT)
        out.append(SourceStats(name, count, rejected[k], mean, low, high, verdict))
    return tuple(out)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


# ---- the API -----------------------------------------------------------------------------------
def fuse(poses, covariances=None, *, weights=None, names: Optional[Sequence[str]] = None,
         sources: Optional[Iterable[Source]] = None, robust: bool = False,
         probability: float = DEFAULT_PROBABILITY, tol: float = 1e-12, max_iter: int = 100,
         times=None, time: Optional[float] = None, max_skew: Optional[float] = None,
         max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION, twist_covariance=None,
         acceleration_psd=None) -> Fused:
    """Fuse ``poses`` ``(n, 8)`` (``T_frame_body`` each) with ``covariances`` ``(n, 6, 6)`` (or
    scalar ``weights`` ``(n,)``, covariance ``I / w``; neither: identity) into ``T_world_body``.

    ``names[i]`` is the source of measurement i; a source listed in ``sources`` has its frames
    applied (others are in the world frame already). ``robust`` rejects measurements whose
    leave-one-out NIS exceeds the χ² quantile ``probability`` (6 dof); ``probability`` also sets
    the per-source consistency interval. Bad input is a ``ValueError`` naming the argument and
    index.

    ``times`` ``(n,)`` (seconds, the sources' stamps) turns on time alignment: the result is the
    pose at ``time`` (default: the newest time a measurement was taken, stamp minus latency) under
    a constant-twist motion model estimated with it; a measurement taken more than ``max_skew``
    from ``time`` is dropped (:attr:`Fused.dropped`); a ``time`` more than ``max_extrapolation``
    outside the measurements' span is refused (``None``: unbounded). ``twist_covariance`` is an
    optional zero-mean prior on the body twist, needed when the measurements are all from one
    instant and ``time`` is another. ``acceleration_psd`` ``(6, 6)`` (rotation first, rad²/s³
    and m²/s³) lets the twist drift as a random walk, so that a body that accelerates is not
    claimed to be known better than the constant-twist model can know it (module docstring);
    ``None`` or zeros: the twist is constant over the window. Measurements all taken at one
    instant and fused at that instant give the static fit exactly (the same C core, bit for
    bit); then the twist keeps its prior and each estimated latency its prior, as one instant
    shows neither. Without ``times`` none of this applies and latencies are ignored.
    """
    Z = _poses(poses)
    n = Z.shape[0]
    S = _covariances(covariances, weights, n)
    names = _names(names, n)
    table = _sources(sources)
    try:
        probability = float(probability)
    except (TypeError, ValueError):
        probability = float("nan")
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability: must be within (0, 1), got {probability!r}")
    tol = dq._as_tol(tol)
    max_iter = dq._as_iter(max_iter)
    Z, S = _to_world(Z, S, names, table)
    gate2 = chi2_quantile(probability, DOF)
    if times is not None:
        return _fuse_in_time(Z, S, names, table, _finite(times, "times", (), n), time, max_skew,
                             max_extrapolation, twist_covariance, acceleration_psd, robust,
                             probability, gate2, tol, max_iter)
    for key, value in (("time", time), ("max_skew", max_skew),
                       ("twist_covariance", twist_covariance),
                       ("acceleration_psd", acceleration_psd)):
        if value is not None:
            raise ValueError(f"{key}: needs the measurements' times (times=...)")

    return _fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter)


class _Checked(NamedTuple):
    """:func:`fuse`'s options as its checks leave them, for a caller that fuses many times
    with the same options (:class:`Tracker`)."""
    table: dict
    robust: bool
    probability: float
    gate2: float
    tol: float
    max_iter: int
    max_skew: Optional[float]
    max_extrapolation: Optional[float]
    twist_covariance: Optional[np.ndarray]
    acceleration_psd: Optional[np.ndarray]


def _fuse_rows(Z, S, names, times, time, o: _Checked) -> Fused:
    """:func:`fuse` with times of rows already checked by its rules (finite stamps, unit rigid
    poses, symmetric positive definite covariances symmetrised, names as strings) and checked
    options: the same result, bit for bit, without checking them again."""
    Z, S = _to_world(dq.normalize(Z), S, names, o.table)
    return _fuse_in_time(Z, S, names, o.table, times, time, o.max_skew, o.max_extrapolation,
                         o.twist_covariance, o.acceleration_psd, o.robust, o.probability,
                         o.gate2, o.tol, o.max_iter)


def _fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter) -> Fused:
    """The fit of one instant: the C core's, robust or not."""
    n = Z.shape[0]
    if robust and n > 1:
        fit, nis, tested, inlier, gate_status = _robust(Z, S, gate2, tol, max_iter)
    else:
        inlier = np.ones(n, dtype=bool)
        fit = _fit(Z, S, inlier, tol, max_iter)
        nis, tested = fit.nis, fit.tested
        gate_status = None
    gate = math.sqrt(gate2)
    rejected = tuple(Rejection(int(i), names[i], float(math.sqrt(nis[i])), gate, probability)
                     for i in np.flatnonzero(~inlier))
    k = int(np.count_nonzero(inlier))
    return Fused(
        status=gate_status if gate_status is not None else fit.status,
        mean=_frozen(fit.mean),
        covariance=_frozen(fit.covariance),
        residuals=_frozen(fit.r),
        distances=_frozen(fit.distances),
        nis=_frozen(nis),
        tested=_frozen(tested),
        inliers=_frozen(np.flatnonzero(inlier)),
        rejected=rejected,
        chi2=fit.chi2,
        dof=DOF * (k - 1),
        iterations=fit.iterations,
        sources=_source_stats(*_codes(names), nis, tested, inlier, probability),
    )


# ---- time alignment and motion -----------------------------------------------------------------
@dataclass(frozen=True)
class Dropped:
    """Measurement ``index`` (of source ``source``) was taken ``age`` seconds before the fusion
    time (negative: after it), further than ``max_skew`` from it; it did not enter the fit."""
    index: int
    source: str
    age: float
    max_skew: float

    @property
    def reason(self) -> str:
        who = _who(self.index, self.source)
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


def _seconds(x, name: str, least: Optional[str] = None) -> float:
    """A finite number of seconds; ``least`` ``"positive"`` or ``"nonnegative"`` bounds it."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected seconds, got {type(x).__name__}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {v!r}")
    if (least == "positive" and not v > 0.0) or (least == "nonnegative" and v < 0.0):
        raise ValueError(f"{name}: must be {least}, got {v!r}")
    return v


# What a latency and its prior's standard deviation may be (seconds): a prior of 5e-324 s has an
# information (sigma^-2) no double holds.
_MAX_LATENCY = 1e6
_LATENCY_SIGMA = (1e-9, 1e6)


def _latency(s: Source, k: int) -> tuple[float, Optional[float]]:
    latency = _seconds(s.latency, f"sources[{k}].latency")
    if abs(latency) > _MAX_LATENCY:
        raise ValueError(f"sources[{k}].latency: {latency:.6g} s is beyond +-{_MAX_LATENCY:g} s")
    if s.latency_sigma is None:
        return latency, None
    sigma = _seconds(s.latency_sigma, f"sources[{k}].latency_sigma", "positive")
    lo, hi = _LATENCY_SIGMA
    if not lo <= sigma <= hi:
        raise ValueError(f"sources[{k}].latency_sigma: {sigma:.6g} s is outside [{lo:g}, "
                         f"{hi:g}] s")
    return latency, sigma


def _shape(x):
    """``np.shape`` that names a ragged sequence rather than raising NumPy's error."""
    try:
        return np.shape(x)
    except ValueError:
        return "a ragged sequence"


def _twist_information(twist_covariance) -> tuple[np.ndarray, np.ndarray]:
    """The twist's zero-mean prior checked like a measurement's covariance, and its
    information."""
    shape = _shape(twist_covariance)
    if shape != (DOF, DOF):
        raise ValueError(f"twist_covariance: expected shape (6, 6), got {shape}")
    try:
        C = _covariances([twist_covariance], None, 1)[0]
    except ValueError as e:
        raise rename(e, {"covariances": "twist_covariance"}) from None
    Wp = np.linalg.inv(C)
    return C, 0.5 * (Wp + Wp.T)


def _acceleration(acceleration_psd) -> Optional[np.ndarray]:
    """The acceleration's power spectral density, symmetric positive semidefinite; None when
    not given or zero (the constant-twist model, computed as without it)."""
    if acceleration_psd is None:
        return None
    shape = _shape(acceleration_psd)
    if shape != (DOF, DOF):
        raise ValueError(f"acceleration_psd: expected shape (6, 6), got {shape}")
    try:
        Q = np.asarray(acceleration_psd, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("acceleration_psd: expected numbers") from None
    if not np.isfinite(Q).all():
        raise ValueError("acceleration_psd: contains NaN or infinity")
    scale = float(np.abs(Q).max())
    if scale == 0.0:
        return None
    if np.abs(Q - Q.T).max() > _SYMMETRY_TOL * scale:
        raise ValueError(f"acceleration_psd: not symmetric (largest asymmetry "
                         f"{np.abs(Q - Q.T).max():.3g})")
    Q = 0.5 * (Q + Q.T)
    low = float(np.linalg.eigvalsh(Q).min())
    if low < -_SYMMETRY_TOL * scale:
        raise ValueError(f"acceleration_psd: not positive semidefinite (eigenvalue {low:.3g})")
    return Q


@dataclass(frozen=True)
class _Model:
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

    @property
    def offset(self) -> int:  # where the latencies start in the state vector
        return 12 if self.twist else 6

    @property
    def dim(self) -> int:
        return self.offset + self.prior.size

    def take(self, mask: np.ndarray) -> "_Model":
        return _Model(self.stamp[mask], self.latency[mask], self.slot[mask], self.prior,
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
class _MotionFit:
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


def _motion_evaluate(X, V, ell, Z, W, model: _Model):
    dt = model.dt(ell)
    r, cost = _evaluate(dq.mul(X, lie.se3_exp(dt[:, None] * V)), Z, W)
    return dt, r, cost


def _motion_jacobian(V, dt, r, model: _Model) -> np.ndarray:
    """``G_i = Jl⁻¹(r_i) [Ad(Exp(−dt V)), dt Jr(dt V), −V e_slot]``: ``r_i`` moves by ``−G_i Δ``."""
    B = np.zeros(r.shape[:1] + (DOF, model.dim))
    B[:, :, :6] = lie.adjoint(lie.se3_exp(-dt[:, None] * V))
    if model.twist:
        B[:, :, 6:12] = dt[:, None, None] * lie.se3_right_jacobian(dt[:, None] * V)
    est = np.flatnonzero(model.slot >= 0)
    B[est, :, model.offset + model.slot[est]] = -V
    return lie.se3_left_jacobian_inv(r) @ B


def _kernel(dt: np.ndarray) -> np.ndarray:
    """``k(dt_i, dt_j)``: the covariance, per unit power spectral density, of the twice-integrated
    white noise at offsets ``dt_i`` and ``dt_j`` from the fusion time (zero on opposite sides of
    it: given the state there, past and future are independent)."""
    a = np.abs(dt)
    m = np.minimum(a[:, None], a[None])
    M = np.maximum(a[:, None], a[None])
    same = np.sign(dt)[:, None] * np.sign(dt)[None] > 0
    return np.where(same, 0.5 * m * m * M - m ** 3 / 6.0, 0.0)


def _model_error(S: np.ndarray, dt: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The joint covariance ``(6n, 6n)`` of the residuals: the measurements' own (block
    diagonal) and the motion model's error, ``k(dt_i, dt_j) · Q`` between measurements i and j."""
    n = S.shape[0]
    C = np.kron(_kernel(dt), accel)
    idx = np.arange(n)
    C.reshape(n, DOF, n, DOF)[idx, :, idx, :] += S
    return 0.5 * (C + C.T)


def _information(S: np.ndarray, dt: np.ndarray, accel: np.ndarray) -> np.ndarray:
    C = np.linalg.inv(_model_error(S, dt, accel))
    return 0.5 * (C + C.T)


def _marginal_information(S: np.ndarray, dt: np.ndarray, accel: Optional[np.ndarray]):
    """Each measurement's information with its own share of the model error, ``(S_i + dt_i³/3
    Q)⁻¹``: what its distance is measured with."""
    if accel is None:
        return None
    W = np.linalg.inv(S + (np.abs(dt) ** 3 / 3.0)[:, None, None] * accel)
    return 0.5 * (W + np.swapaxes(W, 1, 2))


def _data_cost(r: np.ndarray, info: np.ndarray) -> float:
    """``rᵀ C⁻¹ r`` with ``info`` the joint information ``C⁻¹`` ``(6n, 6n)``, or (the reference
    tests/fusion_reference.py checks the C constant-twist fit with) the measurements' own
    ``(n, 6, 6)`` when they are independent."""
    if info.ndim == 3:
        return float(np.einsum("ni,nij,nj->", r, info, r))
    rf = r.ravel()
    return float(rf @ info @ rf)


def _normal(G: np.ndarray, r: np.ndarray, info: np.ndarray):
    """The data's information ``Gᵀ C⁻¹ G`` and gradient ``Gᵀ C⁻¹ r`` (``info`` as for
    :func:`_data_cost`)."""
    if info.ndim == 3:
        GtW = np.swapaxes(G, 1, 2) @ info
        return (np.tensordot(GtW, G, axes=([0, 2], [0, 1])),
                (GtW @ r[..., None]).sum(axis=0)[:, 0])
    Gf = G.reshape(-1, G.shape[-1])
    CG = info @ Gf
    return Gf.T @ CG, CG.T @ r.ravel()


def _motion_solve(Z, model: _Model, X, V, ell, tol: float, max_iter: int, info: np.ndarray):
    """Gauss-Newton over pose, twist and latencies in NumPy, for residuals correlated by the
    model error: ``info`` their joint information (held at its value at the start of this
    solve). The step and its halving are the C constant-twist fit's (``dq_motion_fit``)."""
    dt, r, _ = _motion_evaluate(X, V, ell, Z, None, model)
    total = _data_cost(r, info) + model.prior_cost(V, ell)
    off = model.offset
    for it in range(1, max_iter + 1):
        G = _motion_jacobian(V, dt, r, model)
        Hd, gd = _normal(G, r, info)
        Hp, gp = model.prior_terms(V, ell)
        H = Hd + Hp
        g = gd + gp
        delta = np.linalg.solve(H, g)
        step = float(np.linalg.norm(delta))
        for _ in range(_MAX_HALVINGS):
            X_new = dq.normalize(dq.mul(X, lie.se3_exp(delta[:6])))
            V_new = V + delta[6:12] if model.twist else V
            ell_new = ell + delta[off:]
            dt_new, r_new, _ = _motion_evaluate(X_new, V_new, ell_new, Z, None, model)
            total_new = _data_cost(r_new, info) + model.prior_cost(V_new, ell_new)
            if total_new <= total * (1.0 + _COST_SLACK) or step < tol:
                break
            delta = 0.5 * delta
            step *= 0.5
        X, V, ell, dt, r, total = X_new, V_new, ell_new, dt_new, r_new, total_new
        if step < tol:
            return X, V, ell, Status.CONVERGED, it
    return X, V, ell, Status.MAX_ITERATIONS, max_iter


# The model error's covariance depends on the latencies; estimated, they are re-solved with it
# evaluated at the previous solution until they move less than this (seconds), at most _PASSES.
_LATENCY_SETTLED = 1e-9
_PASSES = 4


def _motion_start(Z, S, model: _Model, inlier: np.ndarray) -> Optional[np.ndarray]:
    """Where the motion fit starts: with a twist None, for the C fit's own start (the inlier
    nearest the fusion time, at rest: Gauss-Newton finds the motion); with none (one instant)
    the static fit's start."""
    if model.twist:
        return None
    weights = np.exp(-np.linalg.slogdet(S[inlier])[1] / DOF)
    return dq.dib(Z[inlier], weights / weights.max())


def _constant_twist(Z, S, model: _Model, inlier, tol, max_iter, tested=None):
    """The C constant-twist fit (``dq_motion_fit``): the ``_dqcore.motion_fit`` tuple;
    ``tested`` True: the NIS of every measurement :func:`_determined_without_each` allows."""
    return _c.motion_fit(Z, S, inlier, _motion_start(Z, S, model, inlier), model.stamp,
                         model.latency, model.slot, model.prior, model.prior_w, model.twist,
                         model.twist_w, tested, tol, max_iter)


def _motion_fit(Z, S, model: _Model, inlier: np.ndarray, tol: float,
                max_iter: int) -> _MotionFit:
    """Fit of the measurements ``inlier`` selects, evaluated at every measurement. The constant
    twist is fitted in C, leave-one-out NIS and covariance included; the correlated model in
    NumPy from the constant-twist fit."""
    if model.accel is None:
        (X, V, ell, H, chi2, status, iterations, dt, r, cost, _, nis, tested,
         P) = _constant_twist(Z, S, model, inlier, tol, max_iter, True)
        return _MotionFit(Status(int(status)), X, V, ell, H, P, dt, r, None, cost, float(chi2),
                          int(iterations), nis=nis, tested=tested)
    Zi, Si, mi = Z[inlier], S[inlier], model.take(inlier)
    # the constant-twist fit starts it: cheap, and near when the model error is small
    X, V, ell, *_, iterations = _constant_twist(Z, S, model, inlier, tol, max_iter)[:7]
    iterations = int(iterations)
    at = ell
    Cinv = _information(Si, mi.dt(at), model.accel)
    for _ in range(_PASSES if ell.size else 1):
        X, V, ell, status, it = _motion_solve(Zi, mi, X, V, ell, tol, max_iter, Cinv)
        iterations += it
        if np.all(np.abs(ell - at) < _LATENCY_SETTLED):
            break
        at = ell
        Cinv = _information(Si, mi.dt(at), model.accel)
    dt, r, _ = _motion_evaluate(X, V, ell, Z, None, model)
    Wm = _marginal_information(S, dt, model.accel)
    cost = np.einsum("ni,nij,nj->n", r, Wm, r)
    G = _motion_jacobian(V, dt, r, model)
    Hp, _ = model.prior_terms(V, ell)
    Hd, _ = _normal(G[inlier], r[inlier], Cinv)
    H = Hd + Hp
    P = np.linalg.inv(H)
    chi2 = _data_cost(r[inlier], Cinv) + model.prior_cost(V, ell)
    return _MotionFit(status, X, V, ell, H, 0.5 * (P + P.T), dt, r, G, cost, float(chi2),
                      iterations, Cinv)


def _determined_without_each(model: _Model, inlier: np.ndarray) -> np.ndarray:
    """For each measurement: do the inliers other than it determine the state? The twist needs
    two instants unless it has a prior; the latencies always have theirs (in C,
    ``dq_motion_determined``, which the constant-twist fit also runs)."""
    return _c.motion_determined(model.stamp, model.latency, inlier,
                                model.twist and model.twist_w is None)


def _motion_nis(fit: _MotionFit, S, inlier: np.ndarray, model: _Model):
    """Each measurement's leave-one-out NIS against the fit of the other inliers (:func:`_nis`
    for the joint state; the constant-twist fit computed them with the fit)."""
    if fit.nis is not None:
        return fit.nis, fit.tested
    return _correlated_nis(fit, S, inlier, model)


def _blocks(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The 6 × 6 diagonal blocks of ``A Bᵀ`` (both ``(6m, k)``)."""
    m = A.shape[0] // DOF
    return np.einsum("mak,mbk->mab", A.reshape(m, DOF, -1), B.reshape(m, DOF, -1))


def _correlated_nis(fit: _MotionFit, S, inlier: np.ndarray, model: _Model):
    """The leave-one-out NIS when the model error correlates the residuals (joint covariance
    ``C``, information ``H`` of the inliers' fit). An inlier i: with ``Ω = C⁻¹ − C⁻¹ G H⁻¹ Gᵀ
    C⁻¹`` over the inliers, ``(Ω r)_iᵀ Ω_ii⁻¹ (Ω r)_i`` is the NIS of its residual against the
    prediction from all the others (its conditional mean given their residuals included); with
    independent residuals this is :func:`_nis`. Any other measurement j: its residual less its
    conditional mean given the inliers', against that covariance plus the fit's."""
    n, dim = S.shape[0], model.dim
    rows = np.repeat(inlier, DOF)
    G = fit.G.reshape(n * DOF, dim)
    r = fit.r.ravel()
    Ci = fit.Cinv
    A = Ci @ G[rows]
    u = Ci @ r[rows]
    Hinv = fit.P
    _, gp = model.prior_terms(fit.V, fit.ell)
    w = u - A @ (Hinv @ (A.T @ r[rows] + gp))
    tested = ~inlier | _determined_without_each(model, inlier)
    nis = np.zeros(n)
    k = np.flatnonzero(inlier)
    Om = Ci.reshape(k.size, DOF, k.size, DOF)[np.arange(k.size), :, np.arange(k.size), :]
    Om = Om - _blocks(A, A @ Hinv)
    ok = tested[k]
    Om[~ok] = np.eye(DOF)
    w = w.reshape(-1, DOF)
    nis[k] = np.einsum("ni,ni->n", w, np.linalg.solve(Om, w[..., None])[..., 0])
    out = ~inlier
    if out.any():
        C = _model_error(S, fit.dt, model.accel)
        cols = np.repeat(out, DOF)
        Cji = C[np.ix_(cols, rows)]
        nu = (r[cols] - Cji @ u).reshape(-1, DOF)
        M = G[cols] - Cji @ A
        cov = (C[np.ix_(cols, cols)].reshape(-1, DOF, out.sum(), DOF)
               [np.arange(out.sum()), :, np.arange(out.sum()), :]
               - _blocks(Cji, Cji @ Ci) + _blocks(M, M @ Hinv))
        nis[out] = np.einsum("ni,ni->n", nu, np.linalg.solve(cov, nu[..., None])[..., 0])
    return np.where(tested, nis, 0.0), tested


def _robust_motion(Z, S, model: _Model, allowed: np.ndarray, gate2, tol, max_iter):
    """:func:`_robust` over time: the consensus start compares the measurements brought to the
    fusion time with the twist of a first fit of all of them (an outlier biases that twist; the
    gate that follows judges every measurement against the fit of the others)."""
    first = _motion_fit(Z, S, model, allowed, tol, max_iter)
    back = lie.se3_exp(-first.dt[:, None] * first.V)
    Wm = _marginal_information(S, first.dt, model.accel)
    Sm = S if Wm is None else np.linalg.inv(Wm)
    Zt, St = dq.normalize(dq.mul(Z, back)), lie.cov_compose(Sm, back, None)
    inlier = np.zeros_like(allowed)
    inlier[allowed] = _consensus(Zt[allowed], St[allowed], gate2)
    if not _determined_without_each(model, inlier)[~inlier].all():
        inlier = allowed.copy()  # the consensus is of one instant: the twist needs more
    return _gate(inlier, allowed, lambda m: _motion_fit(Z, S, model, m, tol, max_iter),
                 lambda fit, m: _motion_nis(fit, S, m, model), gate2)


# The gate refits at most this many times (each fit is linear in the measurements, or cubic with
# an acceleration_psd): the bound of a robust fit's cost (service/limits.py).
_GATE_FITS = 50


def _gate(inlier, allowed, fit_of, nis_of, gate2):
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


def _fuse_in_time(Z, S, names, table, times, time, max_skew, max_extrapolation,
                  twist_covariance, acceleration_psd, robust, probability, gate2, tol,
                  max_iter) -> Fused:
    n = Z.shape[0]
    stamps = times
    sources, code = _codes(names)
    latency = np.array([table[s].latency if s in table else 0.0 for s in sources])[code]
    taken = stamps - latency
    time = float(taken.max()) if time is None else _seconds(time, "time")
    twist_prior, Wp = (None, None) if twist_covariance is None else _twist_information(
        twist_covariance)
    accel = _acceleration(acceleration_psd)
    if max_skew is None:
        drop, keep, kept = None, None, taken
    else:
        max_skew = _seconds(max_skew, "max_skew", "nonnegative")
        drop = np.abs(time - taken) > max_skew
        keep = ~drop
        if not keep.any():
            nearest = float(np.abs(time - taken).min())
            raise ValueError(f"max_skew: every measurement was taken more than {max_skew:g} s "
                             f"from the fusion time {time!r} (the nearest {nearest:.6g} s)")
        kept = taken[keep]
    lo, hi = float(kept.min()), float(kept.max())
    extrapolation = max(0.0, time - hi, lo - time)
    if max_extrapolation is not None:
        max_extrapolation = _seconds(max_extrapolation, "max_extrapolation", "nonnegative")
        if extrapolation > max_extrapolation:
            raise ValueError(f"time: {time!r} is {extrapolation:.6g} s outside the span "
                             f"[{lo!r}, {hi!r}] of the measurements, beyond max_extrapolation "
                             f"{max_extrapolation:g} s")
    estimated = [s for s in sources if s in table and table[s].latency_sigma is not None]
    one_instant = lo == hi
    if one_instant and extrapolation == 0.0:
        # All taken at the fusion time: nothing moves, the answer is the static fit itself (its
        # C core), bit for bit; the twist keeps its prior, each latency its prior (one instant
        # shows neither).
        f = _fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter)
        return replace(
            f, time=time, extrapolation=0.0,
            twist=None if Wp is None else _frozen(np.zeros(DOF)),
            twist_covariance=None if Wp is None else _frozen(twist_prior),
            latencies=tuple(Latency(s, table[s].latency, table[s].latency_sigma,
                                    table[s].latency, table[s].latency_sigma)
                            for s in estimated))
    twist = Wp is not None or not one_instant
    if not twist and extrapolation > 0.0:
        raise ValueError(f"time: the measurements were all taken at {lo!r}; bringing them to "
                         f"{time!r} needs the body's twist, which one instant does not show "
                         f"(give twist_covariance)")
    slot = np.array([estimated.index(s) if s in estimated else -1 for s in sources])[code]
    model = _Model(
        stamp=stamps - time, latency=latency, slot=slot,
        prior=np.array([table[s].latency for s in estimated], dtype=np.float64),
        prior_w=np.array([table[s].latency_sigma ** -2 for s in estimated], dtype=np.float64),
        twist=twist, twist_w=Wp, accel=accel)

    allowed = np.ones(n, dtype=bool) if keep is None else keep
    if robust and np.count_nonzero(allowed) > 1:
        fit, nis, tested, inlier, gate_status = _robust_motion(Z, S, model, allowed, gate2, tol,
                                                               max_iter)
    else:
        inlier = allowed
        fit = _motion_fit(Z, S, model, inlier, tol, max_iter)
        nis, tested = _motion_nis(fit, S, inlier, model)
        gate_status = None
    gate = math.sqrt(gate2)
    out = ~inlier if keep is None else ~inlier & keep
    rejected = tuple(Rejection(int(i), names[i], float(math.sqrt(nis[i])), gate, probability)
                     for i in np.flatnonzero(out)) if out.any() else ()
    dropped = () if drop is None else tuple(
        Dropped(int(i), names[i], float(time - taken[i]), max_skew) for i in np.flatnonzero(drop))
    P = fit.P
    off = model.offset
    latencies = tuple(Latency(s, table[s].latency, table[s].latency_sigma, float(fit.ell[k]),
                              float(math.sqrt(P[off + k, off + k])))
                      for k, s in enumerate(estimated))
    inliers = np.flatnonzero(inlier)
    # Each prior is as many residuals as the parameters it constrains: only the twist's
    # unconstrained 6 reduce the degrees of freedom beyond the pose's.
    dof = DOF * (inliers.size - 1) - (DOF if twist and Wp is None else 0)
    # a dropped measurement is neither tested nor counted as rejected by the gate
    stats = _source_stats(sources, code, nis, tested if keep is None else tested & keep,
                          inlier if drop is None else inlier | drop, probability)
    return Fused(
        status=gate_status if gate_status is not None else fit.status,
        mean=_frozen(fit.mean),
        covariance=_frozen(P[:6, :6]),
        residuals=_frozen(fit.r),
        distances=_frozen(np.sqrt(fit.cost)),
        nis=_frozen(nis),
        tested=_frozen(tested),
        inliers=_frozen(inliers),
        rejected=rejected,
        chi2=fit.chi2,
        dof=dof,
        iterations=fit.iterations,
        sources=stats,
        time=time,
        twist=_frozen(fit.V) if twist else None,
        twist_covariance=_frozen(P[6:12, 6:12]) if twist else None,
        extrapolation=float(extrapolation),
        dropped=dropped,
        latencies=latencies,
    )


# ---- per-body state for live streams -----------------------------------------------------------
@dataclass(frozen=True)
class Measurement:
    """One pose of ``body`` from ``source`` stamped ``time`` (the proto's ``Measurement``):
    ``pose`` ``T_frame_body`` ``(8,)``, ``covariance`` ``(6, 6)``, or (``None``) isotropic
    ``I / weight`` (no weight: 1)."""
    source: str
    body: str
    time: float
    pose: np.ndarray
    covariance: Optional[np.ndarray] = None
    weight: Optional[float] = None


class Window(NamedTuple):
    """A body's sliding window as arrays, in arrival order (the order of the indices of its
    :meth:`Tracker.estimate`): per measurement the caller's number (``ids``), source, stamp,
    the time it was taken (stamp minus the source's latency), pose (as given: checked to be a
    unit rigid motion, normalised by :func:`fuse`) and covariance (symmetrised)."""
    ids: np.ndarray
    sources: tuple[str, ...]
    times: np.ndarray
    taken: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray


class _Store:
    """Every body's measurements in one set of preallocated arrays, in arrival order, each row
    tagged with its body. A message costs a few NumPy operations whatever the number of bodies
    in it; rows that fell out of their body's window are dropped when the arrays are full
    (compacted in place, grown only when the live rows fill half), so memory follows the largest
    live window, flat over a long stream."""

    _ARRAYS = ("ids", "body", "codes", "times", "taken", "poses", "covs")

    def __init__(self, capacity: int = 256):
        self.n = 0
        self.ids = np.empty(capacity, np.int64)
        self.body = np.empty(capacity, np.int64)
        self.codes = np.empty(capacity, np.int64)
        self.times = np.empty(capacity)
        self.taken = np.empty(capacity)
        self.poses = np.empty((capacity, 8))
        self.covs = np.empty((capacity, DOF, DOF))

    def live(self, newest: np.ndarray, window: float, cap: Optional[int] = None) -> np.ndarray:
        """The rows in their body's window: taken within ``window`` of its newest, and among
        the last ``cap`` of those (arrival order) when a cap is given."""
        body = self.body[:self.n]
        live = self.taken[:self.n] >= newest[body] - window
        if cap is not None:
            idx = np.flatnonzero(live)
            b = body[idx]
            order = np.lexsort((-idx, b))              # by body, newest arrival first
            start = np.flatnonzero(np.r_[True, b[order][1:] != b[order][:-1]])
            rank = np.arange(len(order)) - np.repeat(start, np.diff(np.r_[start, len(order)]))
            live[idx[order[rank >= cap]]] = False
        return live

    def rows(self, b: int, newest: np.ndarray, window: float,
             cap: Optional[int] = None) -> np.ndarray:
        """Body ``b``'s rows in its window, in arrival order (the last ``cap`` of them)."""
        body = self.body[:self.n]
        rows = np.flatnonzero((body == b) & (self.taken[:self.n] >= newest[b] - window))
        return rows if cap is None or len(rows) <= cap else rows[len(rows) - cap:]

    def keep(self, mask: np.ndarray) -> None:
        k = int(np.count_nonzero(mask))
        for a in self._ARRAYS:
            arr = getattr(self, a)
            arr[:k] = arr[:self.n][mask]
        self.n = k

    def append(self, newest: np.ndarray, window: float, cap: Optional[int] = None,
               **rows) -> None:
        m = len(rows["ids"])
        if self.n + m > len(self.ids):
            self.keep(self.live(newest, window, cap))
            if 2 * (self.n + m) > len(self.ids):
                size = max(2 * len(self.ids), 2 * (self.n + m))
                for a in self._ARRAYS:
                    old = getattr(self, a)
                    new = np.empty((size,) + old.shape[1:], old.dtype)
                    new[:self.n] = old[:self.n]
                    setattr(self, a, new)
        for a in self._ARRAYS:
            getattr(self, a)[self.n:self.n + m] = rows[a]
        self.n += m


class Tracker:
    """Sliding-window state of many bodies, keyed by name, for a live stream of measurements.

    Each body keeps its measurements taken (stamp minus the source's latency) within ``window``
    seconds of its newest; one taken further back than that is refused, naming it.
    :meth:`ingest` takes arrays of measurements of any bodies, checks them together in NumPy and
    keeps every valid one, returning the errors of the others (a live stream goes on past a bad
    measurement); :meth:`add` takes :class:`Measurement` s, all or none. :meth:`estimate` fuses a
    body's window at a time with :func:`fuse` (its keyword options are those given here).
    Bodies are independent: nothing of one enters another's estimate.

    ``limits`` (a server's :class:`dqpose.limits.Limits`; None: unbounded) bounds what a stream
    keeps: a body's window holds its last ``max_window`` measurements (``max_robust`` when
    robust, ``max_correlated`` with an ``acceleration_psd``), the stream
    ``max_stream_measurements`` in all (more are refused), and a measurement taken more than
    ``max_time_jump`` after its body's newest is refused without moving the body, unless the
    body's next such measurement confirms the jump (a clock that really moved, a body seen
    again after a pause): one stray stamp never poisons a body.
    """

    def __init__(self, window: float, *, sources: Optional[Iterable[Source]] = None,
                 robust: bool = False, probability: float = DEFAULT_PROBABILITY,
                 max_skew: Optional[float] = None, max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION,
                 twist_covariance=None, acceleration_psd=None, tol: float = 1e-12,
                 max_iter: int = 100, limits: Optional[_limits.Limits] = None):
        self.window = _seconds(window, "window", "positive")
        self.limits = limits
        self.sources = tuple(sources or ())
        self._table = _sources(self.sources)
        # the options' checks are fuse's: one fusion of a placeholder runs them now, not later
        fuse(np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]]), times=[0.0], sources=self.sources,
             robust=robust, probability=probability, max_skew=max_skew,
             max_extrapolation=max_extrapolation, twist_covariance=twist_covariance,
             acceleration_psd=acceleration_psd, tol=tol, max_iter=max_iter)
        probability = float(probability)
        self._checked = _Checked(self._table, robust, probability,
                                 chi2_quantile(probability, DOF), dq._as_tol(tol),
                                 dq._as_iter(max_iter), max_skew, max_extrapolation,
                                 twist_covariance, acceleration_psd)
        self._store = _Store()
        # bodies and sources as small integers in the store: a body's newest taken time, a
        # source's configured latency
        self._body_codes: dict[str, int] = {}
        self._active: dict[str, None] = {}        # bodies with measurements, in order
        self._newest = np.full(16, -math.inf)
        self._codes: dict[str, int] = {}
        self._names: list[str] = []
        self._latency = np.empty(0)
        self._count = 0            # measurements offered so far: the default ids
        # per body code: the time of its last refused jump, which a second one near it confirms
        self._jumps: dict[int, float] = {}
        self.cap = None            # measurements a body's window holds (None: all)
        if limits is not None:
            correlated = acceleration_psd is not None and np.any(acceleration_psd)
            self.cap = min(limits.max_window, limits.max_robust if robust else limits.max_window,
                           limits.max_correlated if correlated else limits.max_window)

    @property
    def bodies(self) -> tuple[str, ...]:
        return tuple(self._active)

    def window_of(self, body: str) -> Window:
        """``body``'s window as arrays, in the order of its :meth:`estimate`'s indices."""
        s, rows = self._store, self._rows(body)
        return Window(s.ids[rows], tuple(self._names[c] for c in s.codes[rows]), s.times[rows],
                      s.taken[rows], s.poses[rows], s.covs[rows])

    def measurements(self, body: str) -> tuple[Measurement, ...]:
        """``body``'s window, in the order of the indices in its :meth:`estimate`."""
        w = self.window_of(body)
        return tuple(Measurement(s, body, float(t), p, c)
                     for s, t, p, c in zip(w.sources, w.times, w.poses, w.covariances))

    def newest(self, body: str) -> float:
        """When ``body``'s newest measurement was taken."""
        return float(self._newest[self._code_of(body)])

    def newest_of(self, bodies: Iterable[str]) -> list[float]:
        """:meth:`newest` of each of ``bodies`` (which have measurements), in one go."""
        codes = self._body_codes
        return self._newest[[codes[b] for b in bodies]].tolist()

    def count(self, body: str) -> int:
        """How many measurements ``body``'s window holds."""
        return len(self._rows(body))

    def capped(self, body: str) -> bool:
        """Whether ``body``'s window leaves measurements out for its ``cap``."""
        if self.cap is None:
            return False
        s = self._store
        return len(s.rows(self._code_of(body), self._newest, self.window)) > self.cap

    def oldest(self, body: str) -> float:
        """When the oldest measurement in ``body``'s window was taken."""
        return float(self._store.taken[self._rows(body)].min())

    def remove(self, body: str) -> None:
        b = self._code_of(body)
        s = self._store
        s.keep(s.body[:s.n] != b)
        self._newest[b] = -math.inf
        del self._active[body]

    def add(self, *measurements: Measurement) -> None:
        """Add measurements of any bodies; all or none (the first bad one is a ``ValueError``
        naming ``measurements[k]``, its body, source and time)."""
        n = len(measurements)
        poses, covs, times = np.empty((n, 8)), np.empty((n, DOF, DOF)), np.empty(n)
        for k, m in enumerate(measurements):
            name = f"measurements[{k}]"
            if not isinstance(m, Measurement):
                raise ValueError(f"{name}: expected a Measurement, got {type(m).__name__}")
            times[k] = _seconds(m.time, f"{name}.time")
            if _shape(m.pose) != (8,):
                raise ValueError(f"{name}.pose: expected shape (8,), got {_shape(m.pose)}")
            try:
                poses[k] = m.pose
            except (TypeError, ValueError):
                raise ValueError(f"{name}.pose: expected numbers, got "
                                 f"{type(m.pose).__name__}") from None
            if m.covariance is not None and _shape(m.covariance) != (DOF, DOF):
                raise ValueError(f"{name}.covariance: expected shape (6, 6), "
                                 f"got {_shape(m.covariance)}")
            try:
                covs[k] = _covariances(None if m.covariance is None else [m.covariance],
                                       None if m.weight is None else [m.weight], 1)[0]
            except ValueError as e:
                raise rename(e, {"covariances": f"{name}.covariance",
                                 "weights": f"{name}.weight"}) from None
        errors = self._ingest([m.body for m in measurements], [m.source for m in measurements],
                              times, poses, covs, None, all_or_none=True)
        if errors:
            raise errors[0][1]

    def ingest(self, bodies: Sequence[str], sources: Sequence[str], times, poses,
               covariances=None, *, ids=None) -> list[tuple[int, ValueError]]:
        """Add measurements given as arrays: ``bodies`` and ``sources`` (one name each),
        ``times`` ``(n,)`` (stamps), ``poses`` ``(n, 8)`` (``T_frame_body``), ``covariances``
        ``(n, 6, 6)`` (``None``: identity), and the caller's numbers ``ids`` ``(n,)`` (default:
        counting every measurement offered to this tracker), which :meth:`window_of` returns.
        Every valid measurement is kept; returned are ``(k, ValueError)`` for the others, each
        naming ``measurements[k]`` and the problem (a time that is not finite, a pose that is not
        a unit rigid motion, a covariance that is not symmetric positive definite, a time taken
        further back than the window). Arrays of the wrong shape are a ``ValueError`` for the
        call."""
        return self._ingest(bodies, sources, times, poses, covariances, ids, all_or_none=False)

    def estimate(self, body: str, time: Optional[float] = None) -> Fused:
        """``body``'s pose at ``time`` (default: its newest measurement's) from its window."""
        return self.estimate_ids(body, time)[0]

    def estimate_ids(self, body: str, time: Optional[float] = None) -> tuple[Fused, np.ndarray]:
        """:meth:`estimate`, and the ids of the measurements it fused (:meth:`window_of`'s)."""
        s, rows = self._store, self._rows(body)
        # the rows were checked by fuse's rules when they came in
        return _fuse_rows(s.poses[rows], s.covs[rows],
                          tuple(self._names[c] for c in s.codes[rows].tolist()), s.times[rows],
                          time, self._checked), s.ids[rows]

    def _code_of(self, body: str) -> int:
        if body not in self._active:
            raise ValueError(f"body: no measurements of {body!r}")
        return self._body_codes[body]

    def _rows(self, body: str) -> np.ndarray:
        return self._store.rows(self._code_of(body), self._newest, self.window, self.cap)

    def _source_code(self, source: str) -> int:
        code = self._codes.get(source)
        if code is None:
            code = self._codes[source] = len(self._names)
            self._names.append(source)
            src = self._table.get(source)
            self._latency = np.append(self._latency, src.latency if src is not None else 0.0)
        return code

    def _body_code(self, body: str) -> int:
        code = self._body_codes.get(body)
        if code is None:
            code = self._body_codes[body] = len(self._body_codes)
            if code >= len(self._newest):
                self._newest = np.concatenate([self._newest, np.full(len(self._newest),
                                                                     -math.inf)])
        return code

    def _ingest(self, bodies, sources, times, poses, covariances, ids, all_or_none: bool):
        n = len(bodies)
        if len(sources) != n:
            raise ValueError(f"sources: expected {n} names, got {len(sources)}")
        times = _finite_shape(times, "times", (n,))
        poses = _finite_shape(poses, "poses", (n, 8))
        covs = (np.broadcast_to(np.eye(DOF), (n, DOF, DOF)) if covariances is None
                else _finite_shape(covariances, "covariances", (n, DOF, DOF)))
        ids = np.arange(self._count, self._count + n) if ids is None else np.asarray(ids, np.int64)
        if ids.shape != (n,):
            raise ValueError(f"ids: expected shape {(n,)}, got {ids.shape}")
        ok, errors, covs = _check_rows(bodies, sources, times, poses, covs)
        return self._admit(bodies, sources, times, poses, covs, ids, ok, errors, n, all_or_none)

    @staticmethod
    def refusals(bodies, sources, times, poses, covariances) -> list[tuple[int, ValueError]]:
        """What :meth:`ingest` would refuse of these measurements (arrays as it takes them) by
        the checks that need no state (all but the window), each ``(k, ValueError)`` naming
        ``measurements[k]``."""
        return sorted(_check_rows(bodies, sources, np.asarray(times, np.float64),
                                  np.asarray(poses, np.float64),
                                  np.asarray(covariances, np.float64))[1].items())

    def _ingest_valid(self, bodies, sources, times, poses, covariances, ids,
                      offered: int) -> list[tuple[int, ValueError]]:
        """:meth:`ingest` of measurements already checked by its rules, with nothing checked
        again but the window: ``times`` finite, ``poses`` unit (as ``dq.from_pose`` makes them),
        ``covariances`` the symmetric part of symmetric positive definite ones, every body named.
        service/csrc/wire.c checks them so for StreamFuse. ``offered``: how many measurements
        the caller had, these and those it refused (they count, as in :meth:`ingest`)."""
        n = len(bodies)
        return self._admit(bodies, sources, times, poses, covariances, ids, np.ones(n, bool), {},
                           offered, False)

    def _admit(self, bodies, sources, times, poses, covs, ids, ok, errors, offered: int,
               all_or_none: bool):
        """Checked measurements (``ok``; ``errors`` those refused so far) into the windows: the
        window-floor check, then the store."""
        every = bool(ok.all())
        # known sources and bodies by plain look-ups (the common case), else coded on the way
        codes = [self._codes.get(s) for s in sources] if every else [None]
        if None in codes:
            use = ok.tolist()
            codes = [self._source_code(s) if u else 0 for u, s in zip(use, sources)]
        body = [self._body_codes.get(b) for b in bodies] if every else [None]
        if None in body:
            use = ok.tolist()
            body = [self._body_code(b) if u else 0 for u, b in zip(use, bodies)]
        codes = np.array(codes, dtype=np.int64)
        body = np.array(body, dtype=np.int64)
        taken = times - (self._latency[codes] if self._names else 0.0)
        if self.limits is not None:
            self._jump_check(bodies, sources, times, body, taken, ok, errors)
            every = bool(ok.all())
        # Taken no further back than the window before the body's newest, counting the earlier
        # measurements of the same call: checked at once against the newest of the whole call,
        # and only the rows that fail that (stricter) test one by one in order.
        newest = self._newest.copy()
        if every:
            np.maximum.at(newest, body, taken)
        else:
            np.maximum.at(newest, body[ok], taken[ok])
        late = np.flatnonzero(ok & (taken < newest[body] - self.window)).tolist()
        for k in late:
            floor = max([self._newest[body[k]]] + [
                taken[j] for j in range(k) if ok[j] and body[j] == body[k]])
            if taken[k] < floor - self.window:
                ok[k] = False
                errors[k] = ValueError(
                    f"measurements[{k}] (body {bodies[k]!r}, source {sources[k]!r}, time "
                    f"{float(times[k])!r}): taken at {float(taken[k])!r}, "
                    f"{floor - taken[k]:.6g} s before the newest measurement of the body, "
                    f"beyond the window {self.window:g} s")
        if self.limits is not None:
            self._room(ok, errors)
            every = every and bool(ok.all())
        if all_or_none and errors:
            return [min(errors.items())]
        self._count += offered
        if every and not late:
            self._newest = newest     # the maxima over these rows, taken above
            self._store.append(self._newest, self.window, self.cap, ids=ids, body=body,
                               codes=codes, times=times, taken=taken, poses=poses, covs=covs)
            for b in bodies:
                self._active.setdefault(b, None)
        elif ok.all():
            np.maximum.at(self._newest, body, taken)
            self._store.append(self._newest, self.window, self.cap, ids=ids, body=body,
                               codes=codes, times=times, taken=taken, poses=poses, covs=covs)
            for b in bodies:
                self._active.setdefault(b, None)
        elif ok.any():
            np.maximum.at(self._newest, body[ok], taken[ok])
            self._store.append(self._newest, self.window, self.cap, ids=ids[ok], body=body[ok],
                               codes=codes[ok], times=times[ok], taken=taken[ok],
                               poses=poses[ok], covs=covs[ok])
            for k in np.flatnonzero(ok).tolist():
                self._active.setdefault(bodies[k], None)
        return sorted(errors.items())


    def _jump_check(self, bodies, sources, times, body, taken, ok, errors) -> None:
        """Refuses (in ``ok`` and ``errors``) the rows taken more than ``max_time_jump`` after
        their body's newest measurement, the earlier rows of the call counted (for a body new
        to the stream, its earliest row of the call is the reference), unless the row confirms
        the body's last refused jump by lying within ``max_time_jump`` of it."""
        jump = self.limits.max_time_jump
        ref = self._newest[body]
        fresh = ~np.isfinite(ref)
        if fresh.any():
            first = np.full(len(self._newest), np.inf)
            np.minimum.at(first, body[ok], taken[ok])
            ref = np.where(fresh, first[body], ref)
        ahead = np.flatnonzero(ok & (taken > ref + jump))
        if not len(ahead):
            return
        suspects = set(body[ahead].tolist())
        current = {}
        for k in range(len(body)):
            b = int(body[k])
            if not ok[k] or b not in suspects:
                continue
            cur = current.get(b, float(ref[k]))
            t = float(taken[k])
            if t <= cur + jump:
                current[b] = max(cur, t)
                continue
            pending = self._jumps.get(b)
            if pending is not None and abs(t - pending) <= jump:
                del self._jumps[b]       # a second measurement confirms it: the body moves on
                current[b] = t
                continue
            self._jumps[b] = t
            ok[k] = False
            errors[k] = _limits.over(
                f"measurements[{k}]", f"body {bodies[k]!r}, source {sources[k]!r}, time "
                f"{float(times[k])!r}: taken {t - cur:.6g} s after the newest measurement of "
                f"the body, so not used (a second measurement near it would confirm the jump)",
                self.limits, "max_time_jump")

    def _room(self, ok, errors) -> None:
        """Refuses the rows that would take the stream past ``max_stream_measurements`` live
        measurements (those out of their window dropped first)."""
        s, cap = self._store, self.limits.max_stream_measurements
        k = int(np.count_nonzero(ok))
        if s.n + k <= cap:
            return
        s.keep(s.live(self._newest, self.window, self.cap))
        over = s.n + k - cap
        if over <= 0:
            return
        for j in np.flatnonzero(ok)[k - over:].tolist():
            ok[j] = False
            errors[j] = _limits.over(
                f"measurements[{j}]", f"the stream's windows hold {s.n} measurements", self.limits,
                "max_stream_measurements")


def _check_rows(bodies, sources, times, poses, covs):
    """The checks of :meth:`Tracker.ingest` that need no state: ``(ok, errors, covs)``, ``ok``
    the rows that pass, ``errors`` ``{k: ValueError}`` of the others, ``covs`` a copy with the
    rows that pass symmetrised."""
    errors: dict[int, ValueError] = {}
    for k, (b, s) in enumerate(zip(bodies, sources)):
        if not isinstance(b, str) or not b:
            errors[k] = ValueError(f"measurements[{k}].body: " + (
                "empty (every measurement names its body)" if isinstance(b, str) else
                f"expected a string, got {type(b).__name__}"))
        elif not isinstance(s, str):
            errors[k] = ValueError(f"measurements[{k}].source: expected a string, "
                                   f"got {type(s).__name__}")
    if len(errors) == len(times):       # every row refused by its names: nothing else to check
        return np.zeros(len(times), bool), errors, np.array(covs)
    ok = np.isfinite(times)
    for k in np.flatnonzero(~ok).tolist():
        errors.setdefault(k, ValueError(f"measurements[{k}].time: must be finite, "
                                        f"got {float(times[k])!r}"))
    ok[list(errors)] = False
    # The batch is checked at once; only a batch with a bad one is checked row by row. The
    # poses are kept as given (fuse normalises them), so that an estimate is exactly fuse of
    # what was given; the covariances symmetrised (which fuse leaves as they are).
    covs = np.array(covs)
    for arrays, check in ((poses.copy(), lambda a: _poses(a)),
                          (covs, lambda a: _covariances(a, None, len(a)))):
        rows = np.flatnonzero(ok)
        if not len(rows):
            break
        try:
            arrays[rows] = check(arrays[rows])
        except ValueError:
            for k in rows.tolist():
                try:
                    arrays[k] = check(arrays[k:k + 1])[0]
                except ValueError as e:
                    ok[k] = False
                    errors.setdefault(k, rename(e, {
                        "poses": f"measurements[{k}].pose",
                        "covariances": f"measurements[{k}].covariance"}))
    return ok, errors, covs


def _finite_shape(x, name: str, shape: tuple) -> np.ndarray:
    """``x`` as float64 of ``shape`` (values unchecked: the rows are checked one by one)."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a
