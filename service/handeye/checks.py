"""The data checks of a hand-eye solve, before any refinement: malformed input is a
:class:`~dqpose.errors.FieldError` naming the argument and index; unusable data an
:class:`~dqpose.errors.Infeasible` naming the reason and the samples (fewer than 3 distinct
poses, no rotation between samples, rotation axes all parallel, poses that do not correspond,
millimetres given as metres, the data fitting another reading far better); anything doubtful
but solvable a warning naming the samples (duplicates, stale poses, small or nearly parallel
rotations, samples not screw-congruent: the rotation angle and pitch of a robot motion and its
camera motion must agree).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dqpose import dq
from dqpose.errors import FieldError, Infeasible, rename
from dqpose.fusion.validation import MAX_VARIANCE, MIN_VARIANCE, finite
from dqpose.handeye.closed_form import MIN_PAIR_ANGLE, closed_form, hemisphere, motions
from dqpose.handeye.readings import compare_readings
from dqpose.handeye.setups import EYE_IN_HAND, checked_setup, reading

MIN_POSES = 3
_DUPLICATE_ANGLE = np.radians(1e-3)    # two samples this close in rotation and translation
_DUPLICATE_DISTANCE = 1e-6             # (m) on both sides are one sample taken twice
_PURE_TRANSLATION = np.radians(0.5)    # no pair rotates more: X's translation is not determined
_SMALL_ROTATION = np.radians(10.0)     # warn when no pair rotates more than this
_MIN_EXCITATION = np.radians(0.5)      # smallest rotation excitation: below it, axes parallel
_LOW_EXCITATION = np.radians(3.0)      # warn below this (a healthy wrist set: ~15–30°)
_SUSPECT = 4.0                         # a sample whose median congruence error is this many σ off
_MISMATCH_ANGLE = np.radians(3.0)      # median congruence errors beyond these: poses do not
_MISMATCH_PITCH = 0.02                 # correspond (time or pairing), for most samples (m)


def poses(x, name: str) -> np.ndarray:
    try:
        a = finite(x, name, (8,), None)   # shape and finiteness, with the index
        dq.to_matrix(a)                           # the core's unit and rigidity checks
    except ValueError as e:
        raise rename(e, {"a": name + "{}"}) from None
    return dq.normalize(a)


def checked_covariances(cov, name: str, n: int) -> Optional[np.ndarray]:
    if cov is None:
        return None
    try:
        S = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError(f"{name}: expected numbers, got {type(cov).__name__}") from None
    if S.shape not in ((6, 6), (n, 6, 6)):
        raise FieldError(f"{name}: expected shape (6, 6) or ({n}, 6, 6), got {S.shape}")
    S = np.broadcast_to(S, (n, 6, 6))
    for i in range(n if S.ndim == 3 and np.shape(cov) != (6, 6) else 1):
        s = S[i]
        where = f"{name}[{i}]" if np.shape(cov) != (6, 6) else name
        if not np.all(np.isfinite(s)):
            raise FieldError(f"{where}: contains NaN or infinity")
        if not np.allclose(s, s.T, rtol=1e-9, atol=0.0):
            raise FieldError(f"{where}: not symmetric")
        if np.linalg.eigvalsh(0.5 * (s + s.T))[0] < 0.0:
            raise FieldError(f"{where}: not positive semi-definite")
        var = np.diagonal(s)
        bad = (var > 0.0) & ~((var >= MIN_VARIANCE) & (var <= MAX_VARIANCE))
        if bad.any():
            raise FieldError(f"{where}: variance {var[bad][0]:.6g} outside "
                             f"[{MIN_VARIANCE:g}, {MAX_VARIANCE:g}] (0 is "
                             f"exact): its information cannot be used")
    return 0.5 * (S + np.swapaxes(S, -1, -2))


def samples(idx) -> str:
    idx = [int(i) for i in idx]
    return f"sample{'s' if len(idx) != 1 else ''} {', '.join(map(str, idx))}"


@dataclass
class _Congruence:
    i: np.ndarray
    j: np.ndarray
    angle_a: np.ndarray
    angle_b: np.ndarray
    pitch_a: np.ndarray
    pitch_b: np.ndarray


def _congruence(A, C) -> _Congruence:
    n = A.shape[0]
    i, j = np.triu_indices(n, 1)
    a, b = motions(A, C, i, j)
    sa, sb = dq.screw(a), dq.screw(b)
    return _Congruence(i, j, sa.theta, sb.theta, sa.d, sb.d)


def _per_sample_median(n, i, j, v) -> np.ndarray:
    """Per sample, the median of ``v`` over the pairs it is in."""
    M = np.full((n, n), np.nan)
    M[i, j] = v
    M[j, i] = v
    out = np.zeros(n)
    seen = ~np.all(np.isnan(M), axis=1)
    out[seen] = np.nanmedian(M[seen], axis=1)
    return out


@dataclass
class Prepared:
    setup: str
    F: np.ndarray
    A: np.ndarray
    C: np.ndarray
    use: np.ndarray          # samples not duplicates
    suspect: np.ndarray      # samples whose pairs are not screw-congruent
    warnings: list
    closed: tuple            # (X, Z, pairs) of the given reading
    readings: tuple
    condition: float
    excitation: float


def _rotation_information(A, i, j):
    """``Σ θ² (I − k kᵀ)`` over the pairs' robot rotation axes ``k``: the rotation of X is seen
    only across the axes; its condition number and the RMS angle of its smallest eigenvalue."""
    a = hemisphere(dq.mul(dq.inv(A[j]), A[i]))
    v = a[:, 1:4]
    s = np.linalg.norm(v, axis=1)
    k = v / np.maximum(s, 1e-300)[:, None]
    th = 2.0 * np.arctan2(s, a[:, 0])
    M = np.einsum("p,pij->ij", th ** 2, np.eye(3) - k[:, :, None] * k[:, None, :])
    e = np.linalg.eigvalsh(M)
    m = max(len(th), 1)
    cond = float(e[-1] / e[0]) if e[0] > 1e-300 else float("inf")
    return cond, float(np.sqrt(max(e[0], 0.0) / m))


def prepare(base_flange, camera_target, setup) -> Prepared:
    """The checked data of a solve: its poses read, duplicates and stale samples found, the
    rotations' excitation and the motions' correspondence checked, and the closed form of the
    reading given against the others (:func:`~dqpose.handeye.readings.compare_readings`)."""
    setup = checked_setup(setup)
    F = poses(base_flange, "base_flange")
    C = poses(camera_target, "camera_target")
    n = F.shape[0]
    if C.shape[0] != n:
        raise FieldError(f"camera_target: {C.shape[0]} poses for {n} in base_flange "
                         f"(one per sample)")
    if n < MIN_POSES:
        raise Infeasible(f"base_flange: {n} pose{'s' if n != 1 else ''}; at least {MIN_POSES} "
                         f"are needed (two motions about different axes)")
    A = reading(F, setup)
    warnings: list[str] = []
    cg = _congruence(A, C)
    use, still = _distinct(A, C, cg, warnings)
    pu = use[cg.i] & use[cg.j]
    cond, excitation = _excitation(A, cg, use, pu, warnings)
    suspect, s_th, s_d = _correspondence(cg, use, pu, still, warnings)
    base_use = use & ~suspect
    closed = closed_form(A, C, base_use)
    if closed is None:
        raise Infeasible(f"base_flange: fewer than two pairs of samples rotate by more than "
                         f"{np.degrees(MIN_PAIR_ANGLE):.0f}°; add poses rotating about "
                         f"different axes")
    readings = compare_readings(F, A, C, setup, base_use, closed, s_th, s_d)
    return Prepared(setup, F, A, C, use, suspect, warnings, closed, readings, cond, excitation)


def _distinct(A, C, cg: _Congruence, warnings: list) -> tuple[np.ndarray, np.ndarray]:
    """The samples to use, each duplicate kept once, and each pair's translations ``(A, C)``.
    Duplicates: the same sample twice (both sides unmoved); stale: the robot moved, the camera
    did not (or the other way round)."""
    n = A.shape[0]
    i, j = cg.i, cg.j
    da = _pair_distance(A, i, j, left=True)
    db = _pair_distance(C, i, j, left=False)
    still_a = (cg.angle_a < _DUPLICATE_ANGLE) & (da < _DUPLICATE_DISTANCE)
    still_b = (cg.angle_b < _DUPLICATE_ANGLE) & (db < _DUPLICATE_DISTANCE)
    use = np.ones(n, bool)
    dup = still_a & still_b
    if np.any(dup):
        for p in np.flatnonzero(dup):
            use[j[p]] = False if use[i[p]] else use[j[p]]
        groups = sorted({(int(i[p]), int(j[p])) for p in np.flatnonzero(dup)})
        warnings.append(f"{samples(sorted({k for g in groups for k in g}))}: duplicate poses "
                        f"({', '.join(f'{a} = {b}' for a, b in groups)}); each kept once")
    stale = still_a ^ still_b
    if np.any(stale):
        which = [(int(i[p]), int(j[p]), "robot" if still_a[p] else "camera")
                 for p in np.flatnonzero(stale)]
        warnings.append(f"{samples(sorted({k for w in which for k in w[:2]}))}: stale poses ("
                        + "; ".join(f"{a} and {b}: the {who} did not move while the other did"
                                    for a, b, who in which[:5])
                        + ("; …" if len(which) > 5 else "") + ")")
    if np.count_nonzero(use) < MIN_POSES:
        raise Infeasible(f"base_flange: {np.count_nonzero(use)} distinct poses after removing "
                         f"duplicates; at least {MIN_POSES} are needed")
    return use, da + db


def _excitation(A, cg: _Congruence, use, pu, warnings: list) -> tuple[float, float]:
    """The rotation information's condition number and excitation (:func:`_rotation_information`)
    over the usable pairs ``pu``: refused when nothing rotates or all axes are parallel, warned
    when the rotations are small or the axes nearly parallel."""
    largest = float(np.max(cg.angle_a[pu]))
    if largest < _PURE_TRANSLATION:
        raise Infeasible(f"base_flange: pure translation: no two samples differ in rotation by "
                         f"more than {np.degrees(largest):.2f}°; the camera's position cannot be "
                         f"found without rotations about at least two axes "
                         f"({samples(np.flatnonzero(use))})")
    cond, excitation = _rotation_information(A, cg.i[pu], cg.j[pu])
    if excitation < _MIN_EXCITATION:
        raise Infeasible(f"base_flange: the rotation axes of all motions are parallel "
                         f"(smallest rotation excitation {np.degrees(excitation):.2f}°, "
                         f"condition number {cond:.3g} of the rotation information); rotate "
                         f"about at least two different axes ({samples(np.flatnonzero(use))})")
    if largest < _SMALL_ROTATION:
        warnings.append(f"{samples(np.flatnonzero(use))}: small rotations (largest between "
                        f"two samples {np.degrees(largest):.1f}°); X is poorly determined")
    if excitation < _LOW_EXCITATION:
        warnings.append(f"{samples(np.flatnonzero(use))}: rotation axes nearly parallel or "
                        f"coplanar (smallest excitation {np.degrees(excitation):.2f}°, condition "
                        f"number {cond:.3g} of the rotation information)")
    return cond, excitation


def _correspondence(cg: _Congruence, use, pu, moved, warnings: list):
    """Screw congruence: angle and pitch of A-motions and C-motions must agree. Refused when the
    angles do not for most pairs (misaligned or mispaired samples) or the pitches are at another
    scale (:func:`_units`); returns the samples whose pairs disagree (``suspect``), and the
    robust σ of the angle and pitch differences. ``moved``: each pair's translations, summed."""
    n = use.shape[0]
    dth = np.abs(cg.angle_a - cg.angle_b)[pu]
    dd = np.abs(cg.pitch_a - cg.pitch_b)[pu]
    ip, jp = cg.i[pu], cg.j[pu]
    # The median over samples of each sample's median over its pairs: a pair is off when either
    # sample is, so with 30 % outlier samples half the pairs are, and the median over pairs
    # refused data the consensus solves; per sample, a genuine one's pairs are mostly genuine.
    # Misaligned or mispaired data (every sample off) are still refused.
    per_th = _per_sample_median(n, ip, jp, dth)[use]
    per_d = _per_sample_median(n, ip, jp, dd)[use]
    med_th, med_d = float(np.median(per_th)), float(np.median(per_d))
    if med_th > _MISMATCH_ANGLE:
        raise Infeasible(f"base_flange, camera_target: the robot and camera motions do not "
                         f"correspond: their rotation angles differ by {np.degrees(med_th):.1f}° "
                         f"(median over pairs; about the noise when they do); samples misaligned "
                         f"in time or paired wrongly ({samples(np.flatnonzero(use))})")
    _units(cg, pu, use)
    s_th = max(1.4826 * med_th, np.radians(0.01))
    s_d = max(1.4826 * med_d, 1e-4)
    # A pitch is the translation along an axis that rotation noise tilts by about σ/θ, so it is
    # noisy by |t| σ/θ: centimetres on healthy data with the target metres away (OpenCV's
    # geometry at 0.5°: 45 mm median). Pitches off by more than that only warn: misaligned
    # samples show in the angles, and a wrong reading is refused by compare_readings.
    expected = s_th * moved[pu] / np.maximum(cg.angle_a[pu], 0.1) + 1e-3
    if med_d > _MISMATCH_PITCH and float(np.median(dd / expected)) > 5.0:
        warnings.append(f"{samples(np.flatnonzero(use))}: the robot's and the camera's "
                        f"translations along the screw axes differ by {1e3 * med_d:.1f} mm "
                        f"(median over pairs) while the angles agree "
                        f"({np.degrees(med_th):.2f}°): samples misaligned in time, or noisy "
                        f"camera poses far from the target")
    score = np.maximum(_per_sample_median(n, ip, jp, dth / s_th),
                       _per_sample_median(n, ip, jp, dd / s_d))
    suspect = use & (score > _SUSPECT)
    if np.count_nonzero(use & ~suspect) < MIN_POSES:
        suspect[:] = False
    return suspect, s_th, s_d


def _pair_distance(P, i, j, left: bool) -> np.ndarray:
    M = dq.mul(dq.inv(P[j]), P[i]) if left else dq.mul(P[j], dq.inv(P[i]))
    return np.linalg.norm(dq.to_pose(M)[1], axis=1)


def _units(cg: _Congruence, pu: np.ndarray, use: np.ndarray) -> None:
    """Pitch of the robot's motions against the camera's: a ratio near 1000 is millimetres."""
    da, db = cg.pitch_a[pu], cg.pitch_b[pu]
    if np.sum(db * db) <= 0.0 or np.sum(da * da) <= 0.0:
        return
    s = float(np.sum(da * db) / np.sum(db * db))     # da ≈ s db
    resid = np.sqrt(np.mean((da - s * db) ** 2))
    if resid > 0.3 * np.sqrt(np.mean(da * da)):
        return                                         # no clean scale: not a unit problem
    if s < 0.1 or s > 10.0:
        big, small, f = (("camera_target", "base_flange", 1 / s) if s < 1 else
                         ("base_flange", "camera_target", s))
        unit = " (millimetres given as metres?)" if 300 < f < 3000 else ""
        raise Infeasible(f"{big}: translations {f:.4g}× those of {small} along the same screw "
                         f"axes{unit}; give both in metres ({samples(np.flatnonzero(use))})")


def check(base_flange, camera_target, setup: str = EYE_IN_HAND) -> tuple[str, ...]:
    """The data checks of :func:`calibrate` without the refinement: raises what it would raise
    (``FieldError`` for malformed input, ``Infeasible`` for unusable data), returns its warnings
    (each naming the samples), samples failing screw congruence among them."""
    p = prepare(base_flange, camera_target, setup)
    w = list(p.warnings)
    if np.any(p.suspect):
        w.append(f"{samples(np.flatnonzero(p.suspect))}: robot and camera motions not "
                 f"screw-congruent with the other samples (outliers, a robot that had not "
                 f"settled, or a marker flip)")
    return tuple(w)
