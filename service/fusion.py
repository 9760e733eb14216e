"""Pose fusion: n measurements of one rigid body in, one estimate with an honest covariance out.

Conventions (stated once; :mod:`service.lie` holds the tangent-space tools used here):

* A covariance is 6×6, row-major, **rotation first** (``[ωx ωy ωz vx vy vz]``, radians then
  metres), for a **right (body-frame) perturbation**: the true pose is ``T · Exp(ξ)``,
  ``ξ ~ N(0, Σ)``, with ``Exp`` the SE(3) exponential. This is GTSAM's ``Pose3`` convention
  (``retract`` = compose with ``Expmap``), so a user can check us against GTSAM, and the tests do.
* A measurement is ``T_frame_body`` in its source's frame; each source has an extrinsic
  ``T_world_frame`` (identity when not given) and, for an arm, the body's offset in the flange
  frame ``T_flange_body``; the fused pose is ``T_world_body``. A measurement enters the fusion as
  ``T_world_frame · T_frame_body · T_flange_body``; the constant extrinsic on the left leaves its
  covariance as it is, the constant offset on the right maps it exactly to
  ``Ad(O⁻¹) Σ Ad(O⁻¹)ᵀ`` (:func:`service.lie.cov_compose`).
* The residual of measurement ``Z_i`` at the estimate ``X`` is ``r_i = Log(X⁻¹ Z_i)``; its
  negative is GTSAM's ``PriorFactorPose3`` error ``Log(Z_i⁻¹ X)``, so both minimise the same cost
  ``Σ r_iᵀ Σ_i⁻¹ r_i``. Its exact Jacobian for ``X · Exp(δ)`` is ``-Jl⁻¹(r_i) = -Jr⁻¹(-r_i)``.
* Scalar weights are the isotropic special case: ``Σ_i = I / w_i``.

The maximum-likelihood estimate is found by Gauss–Newton on SE(3) from the DIB mean
(:func:`service.dq.dib`) until a step is shorter than ``tol``, in the C core (``fusion.c``); its covariance is the inverse of the
information ``Σ Jᵢᵀ Σᵢ⁻¹ Jᵢ`` at the optimum (GTSAM's marginal). The robust mode starts from the
largest pairwise-consistent group and gates every measurement on its leave-one-out normalised
innovation squared (NIS: the measurement against the fit of the other inliers, ``χ²`` with 6 degrees
of freedom for a consistent source); the answer is always the plain maximum-likelihood fit of the
inliers, so a rejected measurement never moves it.

Time alignment (measurements at different times, latency, a constant-twist motion model) is not
here yet; it will enter as keyword arguments of :func:`fuse` and fields of :class:`Source`.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterable, Optional, Sequence

import numpy as np

from service import _dqcore as _c
from service import dq, lie
from service.errors import rename

__all__ = ["DOF", "Status", "Verdict", "Source", "Rejection", "SourceStats", "Fused",
           "fuse", "chi2_quantile"]

DOF = 6
# Relative asymmetry a covariance may have and still be taken as symmetric (its mean with its
# transpose is used): a product J Σ Jᵀ computed in float64 is asymmetric at ~1e-16.
_SYMMETRY_TOL = 1e-9


class Status(enum.IntEnum):
    """How the estimate was reached (ruckig-style result code)."""
    CONVERGED = 0        # the last Gauss-Newton step was shorter than tol
    MAX_ITERATIONS = 1   # max_iter steps taken, the last one still longer than tol
    GATE_UNSTABLE = 2    # robust mode: the inlier set cycled; the fit of the last set is returned


class Verdict(enum.IntEnum):
    """A source's covariance against its innovations (two-sided χ² test of the NIS sum)."""
    UNTESTED = 0         # no inlier of the source could be checked against other inliers
    CONSISTENT = 1
    OPTIMISTIC = 2       # innovations larger than the covariance says: it claims too much
    PESSIMISTIC = 3      # innovations smaller than the covariance says


@dataclass(frozen=True)
class Source:
    """A source's frames: ``extrinsic`` is ``T_world_frame`` and ``body_offset`` the body in the
    frame the source measures (``T_flange_body`` for an arm); ``None`` is the identity."""
    name: str
    extrinsic: Optional[np.ndarray] = None
    body_offset: Optional[np.ndarray] = None


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
        who = f"measurement {self.index}" + (f" ({self.source})" if self.source else "")
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
            None if s.body_offset is None else _pose(s.body_offset, f"sources[{k}].body_offset"))
    return table


def _to_world(Z: np.ndarray, S: np.ndarray, names: tuple[str, ...],
              table: dict[str, Source]) -> tuple[np.ndarray, np.ndarray]:
    """``T_world_frame · Z · T_flange_body`` and the exactly transported covariances."""
    Z, S = Z.copy(), S.copy()
    for name, src in table.items():
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
def _consensus(Z: np.ndarray, S: np.ndarray, gate2: float) -> np.ndarray:
    """The measurement agreeing with most others, and those: pairwise ``Log(Z_i⁻¹ Z_j)`` against
    ``Σ_i + Σ_j`` (to first order ``Exp(ε_i) Exp(-ε_j)``, both in the body frame)."""
    n = Z.shape[0]
    d = lie.se3_log(dq.mul(dq.conj(Z)[:, None], Z[None]))
    D2 = np.einsum("ijk,ijk->ij", d,
                   np.linalg.solve(S[:, None] + S[None], d[..., None])[..., 0])
    agree = D2 <= gate2
    np.fill_diagonal(agree, True)
    count = agree.sum(axis=1)
    spread = np.where(agree, D2, 0.0).sum(axis=1)
    best = min(range(n), key=lambda i: (-count[i], spread[i], i))
    return agree[best].copy()


def _robust(Z, S, gate2, tol, max_iter):
    inlier = _consensus(Z, S, gate2)
    seen = set()
    status = None
    while True:
        fit = _fit(Z, S, inlier, tol, max_iter)
        nis, tested = fit.nis, fit.tested
        key = inlier.tobytes()
        if key in seen:
            status = Status.GATE_UNSTABLE
            break
        seen.add(key)
        fails = inlier & tested & (nis > gate2)
        if fails.any():  # one at a time: an outlier inside pulls the others' innovations
            worst = int(np.argmax(np.where(fails, nis, -np.inf)))
            inlier = inlier.copy()
            inlier[worst] = False
            continue
        joins = ~inlier & (nis <= gate2)
        if not joins.any():
            break
        inlier = inlier | joins
    return fit, nis, tested, inlier, status


# ---- consistency -------------------------------------------------------------------------------
def _source_stats(names, nis, tested, inlier, probability) -> tuple[SourceStats, ...]:
    out = []
    for name in dict.fromkeys(names):
        mine = np.array([s == name for s in names])
        use = mine & tested & inlier
        count = int(np.count_nonzero(use))
        rejected = int(np.count_nonzero(mine & ~inlier))
        if count == 0:
            out.append(SourceStats(name, 0, rejected, 0.0, 0.0, 0.0, Verdict.UNTESTED))
            continue
        mean = float(nis[use].mean())
        low = chi2_quantile(0.5 * (1.0 - probability), DOF * count) / count
        high = chi2_quantile(0.5 * (1.0 + probability), DOF * count) / count
        verdict = (Verdict.OPTIMISTIC if mean > high else
                   Verdict.PESSIMISTIC if mean < low else Verdict.CONSISTENT)
        out.append(SourceStats(name, count, rejected, mean, low, high, verdict))
    return tuple(out)


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


# ---- the API -----------------------------------------------------------------------------------
def fuse(poses, covariances=None, *, weights=None, names: Optional[Sequence[str]] = None,
         sources: Optional[Iterable[Source]] = None, robust: bool = False,
         probability: float = 0.999, tol: float = 1e-12, max_iter: int = 100) -> Fused:
    """Fuse ``poses`` ``(n, 8)`` (``T_frame_body`` each) with ``covariances`` ``(n, 6, 6)`` (or
    scalar ``weights`` ``(n,)``, covariance ``I / w``; neither: identity) into ``T_world_body``.

    ``names[i]`` is the source of measurement i; a source listed in ``sources`` has its frames
    applied (others are in the world frame already). ``robust`` rejects measurements whose
    leave-one-out NIS exceeds the χ² quantile ``probability`` (6 dof); ``probability`` also sets
    the per-source consistency interval. Bad input is a ``ValueError`` naming the argument and
    index.
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
        sources=_source_stats(names, nis, tested, inlier, probability),
    )
