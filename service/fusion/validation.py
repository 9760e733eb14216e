"""The checks of fusion's input, each a :class:`~dqpose.errors.FieldError` (as data: the argument,
the index, the problem): poses (finite, unit rigid motions), covariances (the rule of the
convention in :mod:`dqpose.fusion`: symmetric, variances within bounds, positive definite;
service/csrc/fusion.h applies the same rule for StreamFuse) or scalar weights, source names,
seconds, the twist's prior and the acceleration's spectral density, and the rows of a live stream
(:meth:`dqpose.fusion.Tracker.ingest`), each refused alone.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq
from dqpose.errors import FieldError, WorldError, rename
from dqpose.fusion.results import DOF
from dqpose.names import bad_names, name_problem

# Relative asymmetry a covariance may have and still be taken as symmetric (its mean with its
# transpose is used): a product J Σ Jᵀ computed in float64 is asymmetric at ~1e-16.
SYMMETRY_TOL = 1e-9
# The variances a covariance may have (standard deviations 1e-12 to 1e12 rad or m): beyond them
# its information cannot be used (service/csrc/fusion.h, which checks the same for StreamFuse).
MIN_VARIANCE, MAX_VARIANCE = _c.MIN_VARIANCE, _c.MAX_VARIANCE


def finite(x, name: str, tail: tuple[int, ...], n: Optional[int]) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError(name, f"expected numbers, got {type(x).__name__}") from None
    want = ((n,) if n is not None else (None,)) + tail
    if a.ndim != len(want) or any(w is not None and s != w for s, w in zip(a.shape, want)):
        shape = ", ".join("n" if w is None else str(w) for w in want)
        got = f"{a.shape}" + (f" for {n} poses" if n is not None else "")
        raise FieldError(name, f"expected shape ({shape}), got {got}")
    if a.size == 0:
        return a
    bad = ~np.isfinite(a).reshape(a.shape[0], -1).all(axis=1)
    if np.any(bad):
        raise FieldError(name, "contains NaN or infinity", int(np.flatnonzero(bad)[0]))
    return a


def checked_poses(poses) -> np.ndarray:
    Z = finite(poses, "poses", (8,), None)
    if Z.shape[0] == 0:
        raise FieldError("poses", "no measurements (expected at least one pose)")
    try:
        dq.to_matrix(Z)  # the core's unit and rigidity checks, with the index
    except ValueError as e:
        raise rename(e, {"a": "poses{}"}) from None
    return dq.normalize(Z)


def checked_pose(T, name: str) -> np.ndarray:
    a = finite(np.asarray(T, dtype=np.float64)[None] if np.ndim(T) == 1 else T, name, (8,), 1)
    try:
        dq.to_matrix(a)
    except ValueError as e:
        raise FieldError(name, FieldError.of(e).text) from None
    return dq.normalize(a[0])


def checked_covariances(covariances, weights, n: int) -> np.ndarray:
    if covariances is not None and weights is not None:
        raise FieldError("weights", "give covariances or weights, not both")
    if weights is not None:
        w = finite(weights, "weights", (), n)
        bad = ~(w > 0.0)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise FieldError("weights", f"must be positive, got {w[i]!r}", i)
        return np.eye(DOF) / w[:, None, None]
    if covariances is None:
        return np.broadcast_to(np.eye(DOF), (n, DOF, DOF)).copy()
    S = finite(covariances, "covariances", (DOF, DOF), n)
    scale = np.abs(S).reshape(n, -1).max(axis=1)
    asym = np.abs(S - np.swapaxes(S, 1, 2)).reshape(n, -1).max(axis=1)
    bad = ~(asym <= SYMMETRY_TOL * scale)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise FieldError("covariances", f"not symmetric (largest asymmetry {asym[i]:.3g})", i)
    var = np.diagonal(S, axis1=1, axis2=2)
    out = (var > 0.0) & ~((var >= MIN_VARIANCE) & (var <= MAX_VARIANCE))   # <= 0: not SPD
    bad = out.any(axis=1)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        v = var[i][out[i]][0]
        raise FieldError("covariances", f"variance {v:.6g} outside [{MIN_VARIANCE:g}, "
                         f"{MAX_VARIANCE:g}] (standard deviations 1e-12 to 1e+12 rad or m): "
                         f"its information cannot be used", i)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        for i in range(n):  # one matrix at a time, so the message can name the index
            try:
                np.linalg.cholesky(S[i])
            except np.linalg.LinAlgError:
                raise FieldError("covariances", "not positive definite", i) from None
    return S


def checked_names(names, n: int) -> tuple[str, ...]:
    if names is None:
        return ("",) * n
    if isinstance(names, str):
        raise FieldError("names", "expected one source name per measurement, got a string")
    out = tuple(names)
    if len(out) != n:
        raise FieldError("names", f"expected {n} source names, got {len(out)}")
    for i, s in enumerate(out):
        problem = name_problem(s, empty=True)      # "": the world frame
        if problem is not None:
            raise FieldError("names", problem, i)
    return out


def checked_seconds(x, name: str, least: Optional[str] = None) -> float:
    """A finite number of seconds; ``least`` ``"positive"`` or ``"nonnegative"`` bounds it."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise FieldError(name, f"expected seconds, got {type(x).__name__}") from None
    if not math.isfinite(v):
        raise FieldError(name, f"must be finite, got {v!r}")
    if (least == "positive" and not v > 0.0) or (least == "nonnegative" and v < 0.0):
        raise FieldError(name, f"must be {least}, got {v!r}")
    return v


def shape_of(x):
    """``np.shape`` that names a ragged sequence rather than raising NumPy's error."""
    try:
        return np.shape(x)
    except ValueError:
        return "a ragged sequence"


def twist_information(twist_covariance) -> tuple[np.ndarray, np.ndarray]:
    """The twist's zero-mean prior checked like a measurement's covariance, and its
    information."""
    shape = shape_of(twist_covariance)
    if shape != (DOF, DOF):
        raise FieldError("twist_covariance", f"expected shape (6, 6), got {shape}")
    try:
        C = checked_covariances([twist_covariance], None, 1)[0]
    except ValueError as e:
        raise rename(e, {"covariances": "twist_covariance"}) from None
    Wp = np.linalg.inv(C)
    return C, 0.5 * (Wp + Wp.T)


def checked_acceleration(acceleration_psd) -> Optional[np.ndarray]:
    """The acceleration's power spectral density, symmetric positive semidefinite; None when
    not given or zero (the constant-twist model, computed as without it)."""
    if acceleration_psd is None:
        return None
    shape = shape_of(acceleration_psd)
    if shape != (DOF, DOF):
        raise FieldError("acceleration_psd", f"expected shape (6, 6), got {shape}")
    try:
        Q = np.asarray(acceleration_psd, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError("acceleration_psd", "expected numbers") from None
    if not np.isfinite(Q).all():
        raise FieldError("acceleration_psd", "contains NaN or infinity")
    scale = float(np.abs(Q).max())
    if scale == 0.0:
        return None
    if np.abs(Q - Q.T).max() > SYMMETRY_TOL * scale:
        raise FieldError("acceleration_psd", f"not symmetric (largest asymmetry "
                                             f"{np.abs(Q - Q.T).max():.3g})")
    Q = 0.5 * (Q + Q.T)
    low = float(np.linalg.eigvalsh(Q).min())
    if low < -SYMMETRY_TOL * scale:
        raise FieldError("acceleration_psd", f"not positive semidefinite (eigenvalue {low:.3g})")
    return Q


def check_rows(bodies, sources, times, poses, covs):
    """The checks of :meth:`Tracker.ingest` that need no state: ``(ok, errors, covs)``, ``ok``
    the rows that pass, ``errors`` ``{k: WorldError}`` of the others, ``covs`` a copy with the
    rows that pass symmetrised."""
    errors: dict[int, WorldError] = {}
    seen: dict[str, Optional[str]] = {}     # each name checked once, however many rows repeat it

    def problem(name) -> Optional[str]:
        if not isinstance(name, str):
            return name_problem(name)
        if name not in seen:
            seen[name] = name_problem(name, empty=True)     # a source's "": the world frame
        return seen[name]

    for k, (b, s) in enumerate(zip(bodies, sources)):
        if isinstance(b, str) and not b:
            errors[k] = WorldError(k, "body", "empty (every measurement names its body)")
            continue
        for field, name in (("body", b), ("source", s)):
            p = problem(name)
            if p is not None:
                errors[k] = WorldError(k, field, p)
                break
    if len(errors) == len(times):       # every row refused by its names: nothing else to check
        return np.zeros(len(times), bool), errors, np.array(covs)
    ok = np.isfinite(times)
    for k in np.flatnonzero(~ok).tolist():
        errors.setdefault(k, WorldError(k, "time", f"must be finite, got {float(times[k])!r}"))
    ok[list(errors)] = False
    # The batch is checked at once in C (the rules of checked_poses and checked_covariances); only
    # the rows it cannot pass are checked here row by row, to name the problem (or pass one too
    # near the edge of positive definite for the C check to be sure). The poses are kept as given
    # (fuse normalises them), so that an estimate is exactly fuse of what was given; the
    # covariances symmetrised (which fuse leaves as they are).
    rows = np.flatnonzero(ok)
    covs = np.array(covs)
    if len(rows):
        passed, sym = _c.check_rows(poses[rows], covs[rows], SYMMETRY_TOL)
        covs[rows] = sym        # (a row it cannot pass: the covariance as given)
        rows = rows[~passed]
    for arrays, check in ((poses.copy(), lambda a: checked_poses(a)),
                          (covs, lambda a: checked_covariances(a, None, len(a)))):
        rows = rows[ok[rows]]
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
                    errors.setdefault(k, WorldError.of(e, k, {"poses": "pose",
                                                              "covariances": "covariance"}))
    return ok, errors, covs


def named_rows(bodies, sources, known_bodies=(), known_sources=()) -> list[int]:
    """The rows whose body or source breaks the name rule (:mod:`dqpose.names`; a source may be
    "", the world frame), for rows that were decoded as strings: each name checked once, none of
    the ``known`` ones (names that passed before)."""
    bad_bodies = bad_names(set(bodies).difference(known_bodies))
    bad_sources = bad_names(set(sources).difference(known_sources), empty=True)
    if not bad_bodies and not bad_sources:
        return []
    return [k for k, (b, s) in enumerate(zip(bodies, sources))
            if b in bad_bodies or s in bad_sources]


def finite_shape(x, name: str, shape: tuple) -> np.ndarray:
    """``x`` as float64 of ``shape`` (values unchecked: the rows are checked one by one)."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape != shape:
        raise FieldError(name, f"expected shape {shape}, got {a.shape}")
    return a
