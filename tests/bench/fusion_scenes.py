"""The static fusion benchmark's scenes (bench_fusion): cameras' and the arm's fixed noise
profiles, trials with gross outliers of three kinds, errors and NEES, and the timing series the
tables print."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from dqpose import dq, lie

TRIALS = 1000
FRACTIONS = (0.0, 0.1, 0.2)
CAMERAS = ("cam1", "cam2", "cam3", "cam4")
ARM = "arm"
KINDS = ("wrong marker", "flipped PnP", "stale arm")
GROSS = 10.0  # sigmas: the "every injected outlier of more than 10 sigma rejected"


# ---- scenes ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Profile:
    """A source: its covariance in its own axes ``cov`` and those axes in the world ``R_world``
    (a camera: z the optical axis); ``R_world`` None means the covariance is in the body frame."""
    name: str
    cov: np.ndarray
    R_world: np.ndarray | None


def _look_at(direction) -> np.ndarray:
    """Camera axes in the world: z along ``direction`` (towards the body), x horizontal."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return np.column_stack([x, np.cross(z, x), z])


def _correlation(rng, strength) -> np.ndarray:
    """A random correlation matrix, ``strength`` 0 (identity) to 1 (a corrcoef of 12 samples)."""
    C = np.corrcoef(rng.normal(size=(6, 12)))
    return (1.0 - strength) * np.eye(6) + strength * C


def profiles(seed: int = 2) -> tuple[Profile, ...]:
    """Four cameras around and above the body, each a little different, and the arm."""
    rng = np.random.default_rng(seed)
    out = []
    views = ([1.0, 0.2, -0.6], [-0.3, 1.0, -0.5], [-1.0, -0.4, -0.8], [0.2, -1.0, -0.3])
    quality = (0.7, 1.0, 1.4, 1.9)  # a camera farther away sees worse
    for name, view, q in zip(CAMERAS, views, quality):
        rot = np.deg2rad([0.8, 0.8, 0.15]) * q * rng.uniform(0.8, 1.25, 3)   # tilt poor, roll good
        trans = np.array([0.6e-3, 0.6e-3, 4e-3]) * q * rng.uniform(0.8, 1.25, 3)  # depth poor
        s = np.r_[rot, trans]
        out.append(Profile(name, s[:, None] * s[None] * _correlation(rng, 0.8), _look_at(view)))
    s = np.r_[np.deg2rad([0.25, 0.25, 0.25]), [0.8e-3, 0.8e-3, 0.8e-3]]
    out.append(Profile(ARM, s[:, None] * s[None] * _correlation(rng, 0.3), None))
    return tuple(out)


@dataclass(frozen=True)
class Trial:
    """One fusion problem: the truth ``X``, measurements ``Z`` (outliers in) and ``clean`` (none),
    covariances ``S`` (body frame, the convention), source ``names``, ``outlier`` mask and
    ``kinds[i]`` (``""`` for a good measurement)."""
    X: np.ndarray
    Z: np.ndarray
    clean: np.ndarray
    S: np.ndarray
    names: tuple[str, ...]
    outlier: np.ndarray
    kinds: tuple[str, ...]


def _random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _random_pose_near(rng, t, reach) -> np.ndarray:
    return dq.from_pose(_random_rotation(rng), t + rng.uniform(-reach, reach, 3))


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def corrupt(rng, kind: str, X: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """A gross error of ``kind`` replacing measurement ``Z`` of the truth ``X``."""
    t = dq.to_pose(X)[1]
    if kind == "wrong marker":  # another marker in the workspace
        return _random_pose_near(rng, t, 0.2)
    if kind == "flipped PnP":  # 180 deg about a horizontal world axis through the body
        phi = rng.uniform(0.0, 2.0 * np.pi)
        axis_body = dq.to_matrix(Z)[:3, :3].T @ np.array([np.cos(phi), np.sin(phi), 0.0])
        return dq.mul(Z, lie.se3_exp(np.r_[np.pi * axis_body, 0.0, 0.0, 0.0]))
    if kind == "stale arm":  # where the body was before it was put down here
        turn = np.deg2rad(rng.uniform(5.0, 30.0)) * _unit(rng)
        shift = rng.uniform(0.02, 0.10) * _unit(rng)
        return dq.mul(Z, dq.mul(lie.se3_exp(np.r_[turn, 0.0, 0.0, 0.0]),
                                dq.from_pose([1.0, 0.0, 0.0, 0.0], shift)))
    raise ValueError(f"kind: unknown outlier kind {kind!r}")


def make_trial(rng, rng_outliers, profs, n_cameras: int, fraction: float) -> Trial:
    """One scene drawn from ``rng``: ``n_cameras`` cameras and the arm see the body once each;
    ``fraction`` of the measurements (stochastically rounded per trial) become gross outliers,
    drawn from ``rng_outliers`` (so the fraction does not change the scenes)."""
    X = dq.from_pose(_random_rotation(rng), rng.uniform(-0.2, 0.2, 3) + [0.0, 0.0, 0.1])
    R = dq.to_matrix(X)[:3, :3]
    use = list(profs[:n_cameras]) + [p for p in profs if p.name == ARM]
    S = []
    for p in use:
        if p.R_world is None:
            S.append(p.cov)
        else:  # the camera's axes in the body frame: a rotation of the twist's coordinates
            B = np.kron(np.eye(2), R.T @ p.R_world)
            S.append(B @ p.cov @ B.T)
    S = 0.5 * (np.array(S) + np.swapaxes(S, 1, 2))
    xi = np.array([rng.multivariate_normal(np.zeros(6), s) for s in S])
    clean = dq.mul(X, lie.se3_exp(-xi))
    n = len(use)
    k = int(np.floor(fraction * n + rng_outliers.uniform()))
    bad = rng_outliers.choice(n, k, replace=False)
    Z, kinds = clean.copy(), [""] * n
    for i in bad:
        kinds[i] = "stale arm" if use[i].name == ARM else KINDS[int(rng_outliers.integers(2))]
        Z[i] = corrupt(rng_outliers, kinds[i], X, clean[i])
    outlier = np.zeros(n, dtype=bool)
    outlier[bad] = True
    return Trial(X, Z, clean, S, tuple(p.name for p in use), outlier, tuple(kinds))


def trials(seed: int, n: int, fraction: float) -> list[Trial]:
    """``n`` trials of one outlier fraction; the same seed gives the same bodies and noise for
    every fraction, so the outlier-free run is the clean version of the others."""
    profs = profiles()
    rng, rng_outliers = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    return [make_trial(rng, rng_outliers, profs, 2 + k % 3, fraction) for k in range(n)]


def sigmas_off(Z: np.ndarray, X: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Mahalanobis distance of each measurement from the truth, ``ξ = Log(Z⁻¹ X)``."""
    e = lie.se3_log(dq.mul(dq.conj(Z), X))
    return np.sqrt(np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0]))


# ---- errors ------------------------------------------------------------------------------------
def errors(X_hat: np.ndarray, X: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and translation error (mm)."""
    qa, ta = dq.to_pose(X_hat)
    qb, tb = dq.to_pose(X)
    c = min(1.0, abs(float(np.dot(qa, qb))))
    return float(np.degrees(2.0 * np.arccos(c))), float(np.linalg.norm(ta - tb) * 1e3)


def nees(X_hat: np.ndarray, P: np.ndarray, X: np.ndarray) -> float:
    e = lie.se3_log(dq.mul(dq.conj(X_hat), X))
    return float(e @ np.linalg.solve(P, e))




@dataclass
class Series:
    rot: list
    trans: list
    nees: list
    seconds: list


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0




def _fmt_s(s):
    if not s:
        return "—"
    m = float(np.median(s))
    return f"{m * 1e6:.0f} µs" if m < 1e-3 else f"{m * 1e3:.2f} ms"


