"""Benchmark of pose fusion: `.venv/bin/python -m tests.bench.bench_fusion [--plot PATH]`.

Simulated scenes with known ground truth, one printed table. Every trial is one static rigid body
seen by 2–4 cameras (2, 3, 4 in turn) and held by an arm; each source has its own fixed profile:

* a camera's covariance is anisotropic and correlated in the camera's axes (depth and the tilt
  about the two in-plane axes poor, the lateral position and the roll about the optical axis
  good; a fixed random correlation between all six), moved into the body frame for the body's
  orientation of the trial, so the cameras, looking from different sides, are good along
  different directions;
* the arm's covariance is small, nearly isotropic, fixed in the body frame.

A measurement is ``Z = X · Exp(-ξ)``, ``ξ ~ N(0, Σ)``, so ``X = Z · Exp(ξ)``: the convention of
:mod:`dqpose.fusion`. Measurements are in the world frame (extrinsics applied: a constant pose
on the left does not change a covariance, so frames would only add the same cost to every row).

Gross outliers replace a fraction (0 %, 10 %, 20 % of all measurements; per trial ``⌊p·n + u⌋``
of them, so never a majority) by: a **wrong marker** (a random pose within 0.2 m of the body), a
**flipped PnP** solution (180° about a horizontal world axis through the body) for a camera, a
**stale arm** (the pose 5–30° and 2–10 cm away the body had before) for the arm.

Rows, all on the same trials in the same run: each single source (its one measurement); DLB and
DIB (``dqpose.dq``, scalar weights ``1/trace Σ``); our ML fusion and robust mode
(``dqpose.fusion.fuse``); GTSAM (``PriorFactorPose3`` per measurement, Levenberg–Marquardt
started at the first measurement, ``Marginals``: what a user of GTSAM from Python runs); a naive
average (mean translation + SciPy ``Rotation.mean``). Errors: rotation angle of ``R̂ᵀR`` (deg) and
``|t̂ − t|`` (mm); NEES ``ξᵀ P⁻¹ ξ`` with ``ξ = Log(X̂⁻¹ X)`` (6 for a consistent estimate); time
is the median wall time of one fusion call from Python.

A second table (same run, ``--moving-seconds``, ``--moving-plot``): a **moving body** on a smooth
path (sines in position and rotation vector: ~0.35 m/s, ~45 °/s, always accelerating), three of
the cameras at 30 Hz with 40 ms latency (each its own frame phase) and the arm at 500 Hz with 25 ms
latency and σ ×0.2 (0.05° / 0.16 mm), stamps = capture + latency. Queries at 100 Hz for the pose
now and 50 ms ago, from what was stamped in the last 150 ms. Rows: each source alone as a user
does it (:func:`single`: ScLERP between its bracketing samples after latency correction, or the
newest two extrapolated); ours time-aligned (constant twist), with ``acceleration_psd`` by the
rule ``Q = a² L`` (:func:`acceleration_rule`), with the cameras' latency estimated online from
0 ± 50 ms; ours static, ignoring time. No GTSAM row: GTSAM's Python API has no Pose3 constant-
twist or white-noise-acceleration factor (``ConstantVelocityFactor`` is on ``NavState``, world
linear velocity, no angular rate); a zero-mean ``BetweenFactorPose3`` chain is a random walk in
pose, a different and worse model, and a ``CustomFactor`` with our model would be a cross-check of
our Gauss-Newton, not a peer.

Below the tables: our estimate against GTSAM's optimum (LM finished by GTSAM's own Gauss–Newton
steps, see ../shared/notes/fusion.md) and our covariance against its marginal on the Gaussian
scene; the robust mode against the outlier-free errors and the share of > 10σ outliers rejected.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass

import numpy as np

from dqpose import dq, fusion, lie
from tests.bench._table import markdown

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


# ---- peers -------------------------------------------------------------------------------------
def _gtsam():
    try:
        from tests import _gtsam
        return _gtsam
    except ImportError:
        return None


def gtsam_fuse(ref, Z, S):
    """What a GTSAM user runs: priors, LM started at the first measurement, the marginal."""
    graph, values = ref.priors(Z, S)
    result = ref.lm(graph, values)
    return graph, result, ref.pose(result), ref.marginal(graph, result)


def naive(Rotation, Z):
    q, t = dq.to_pose(Z)
    return dq.from_pose(Rotation.from_quat(q, scalar_first=True).mean().as_quat(
        scalar_first=True), t.mean(axis=0))


# ---- the run -----------------------------------------------------------------------------------
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


def run(seed: int, n: int):
    """Every method on every trial of every fraction; returns results and the checks."""
    from scipy.spatial.transform import Rotation
    ref = _gtsam()
    methods = list(CAMERAS) + [ARM, "DLB (1/trace)", "DIB (1/trace)", "ours ML", "ours robust",
                                "GTSAM LM + marginals", "naive (mean t + Rotation.mean)"]
    results = {}
    checks = {"dev_pose": 0.0, "dev_cov": 0.0, "gtsam_lm_pose": 0.0}
    robust_info = {}
    for fraction in FRACTIONS:
        res = {m: Series([], [], [], []) for m in methods}
        oracle = Series([], [], [], [])
        gross = rejected_gross = false_rej = n_out = n_meas = 0
        for tr in trials(seed, n, fraction):
            w = 1.0 / np.trace(tr.S, axis1=1, axis2=2)
            w = w / w.max()

            def add(m, X_hat, P=None, seconds=None):
                r, t = errors(X_hat, tr.X)
                res[m].rot.append(r)
                res[m].trans.append(t)
                if P is not None:
                    res[m].nees.append(nees(X_hat, P, tr.X))
                if seconds is not None:
                    res[m].seconds.append(seconds)

            for i, name in enumerate(tr.names):
                add(name, tr.Z[i], tr.S[i])
            X_hat, s = _timed(lambda: dq.dlb(tr.Z, w))
            add("DLB (1/trace)", X_hat, seconds=s)
            X_hat, s = _timed(lambda: dq.dib(tr.Z, w))
            add("DIB (1/trace)", X_hat, seconds=s)
            f, s = _timed(lambda: fusion.fuse(tr.Z, tr.S, names=tr.names))
            add("ours ML", f.mean, f.covariance, s)
            fr, s = _timed(lambda: fusion.fuse(tr.Z, tr.S, names=tr.names, robust=True))
            add("ours robust", fr.mean, fr.covariance, s)
            if ref is not None:
                (graph, result, Xg, Pg), s = _timed(lambda: gtsam_fuse(ref, tr.Z, tr.S))
                add("GTSAM LM + marginals", Xg, Pg, s)
                if fraction == 0.0:
                    optimum = ref.finish(graph, result)
                    Xo, Po = ref.pose(optimum), ref.marginal(graph, optimum)
                    dev = float(np.linalg.norm(lie.se3_log(dq.mul(dq.conj(f.mean), Xo))))
                    checks["dev_pose"] = max(checks["dev_pose"], dev)
                    checks["dev_cov"] = max(checks["dev_cov"], float(
                        np.abs(f.covariance - Po).max() / np.abs(Po).max()))
                    checks["gtsam_lm_pose"] = max(checks["gtsam_lm_pose"], float(
                        np.linalg.norm(lie.se3_log(dq.mul(dq.conj(Xg), Xo)))))
            X_hat, s = _timed(lambda: naive(Rotation, tr.Z))
            add("naive (mean t + Rotation.mean)", X_hat, seconds=s)

            # robust mode against the outliers it was given
            good = ~tr.outlier
            o = fusion.fuse(tr.Z[good], tr.S[good])
            r, t = errors(o.mean, tr.X)
            oracle.rot.append(r)
            oracle.trans.append(t)
            off = sigmas_off(tr.Z, tr.X, tr.S)
            rej = {x.index for x in fr.rejected}
            n_out += int(tr.outlier.sum())
            n_meas += len(tr.names)
            for i in np.flatnonzero(tr.outlier):
                if off[i] > GROSS:
                    gross += 1
                    rejected_gross += i in rej
            false_rej += len(rej - set(np.flatnonzero(tr.outlier).tolist()))
        results[fraction] = res
        robust_info[fraction] = dict(oracle=oracle, gross=gross, rejected_gross=rejected_gross,
                                     false_rej=false_rej, n_out=n_out, n_meas=n_meas)
    return methods, results, checks, robust_info, ref is not None


def _fmt_s(s):
    if not s:
        return "—"
    m = float(np.median(s))
    return f"{m * 1e6:.0f} µs" if m < 1e-3 else f"{m * 1e3:.2f} ms"


def render(methods, results) -> str:
    head = ["outliers", "method", "median rot (deg)", "median trans (mm)", "mean NEES",
            "time / fusion"]
    lines = []
    for fraction, res in results.items():
        for m in methods:
            r = res[m]
            if not r.rot:
                continue
            lines.append([f"{fraction:.0%}", m, f"{np.median(r.rot):.3f}",
                          f"{np.median(r.trans):.3f}",
                          f"{np.mean(r.nees):.3g}" if r.nees else "—", _fmt_s(r.seconds)])
    return markdown(head, lines)


def summary(methods, results, checks, robust_info, have_gtsam, n) -> str:
    ok = lambda b: "PASS" if b else "FAIL"  # noqa: E731
    out = []
    clean = results[0.0]
    if have_gtsam:
        out.append(f"- ours vs GTSAM's optimum (0 % outliers, {n} trials): max pose deviation "
                   f"{checks['dev_pose']:.1e} (target 1e-9: {ok(checks['dev_pose'] <= 1e-9)}); "
                   f"max covariance deviation {checks['dev_cov']:.1e} relative (target 1e-6: "
                   f"{ok(checks['dev_cov'] <= 1e-6)}); GTSAM's LM answer itself is "
                   f"{checks['gtsam_lm_pose']:.1e} from that optimum")
    singles = [m for m in methods if m in CAMERAS or m == ARM]
    best_rot = min(np.median(clean[m].rot) for m in singles)
    best_trans = min(np.median(clean[m].trans) for m in singles)
    ml = clean["ours ML"]
    out.append(f"- ours ML, 0 %: median {np.median(ml.rot):.3f} deg / {np.median(ml.trans):.3f} "
               f"mm against the best single source's {best_rot:.3f} deg / {best_trans:.3f} mm "
               f"({ok(np.median(ml.rot) < best_rot and np.median(ml.trans) < best_trans)}); "
               f"mean NEES {np.mean(ml.nees):.2f} over {len(ml.nees)} trials (target 6 ± 0.5: "
               f"{ok(abs(np.mean(ml.nees) - 6.0) <= 0.5)})")
    for fraction in FRACTIONS[1:]:
        info = robust_info[fraction]
        rb = results[fraction]["ours robust"]
        rr = np.median(rb.rot) / np.median(ml.rot)
        rt = np.median(rb.trans) / np.median(ml.trans)
        orr = np.median(rb.rot) / np.median(info["oracle"].rot)
        ort = np.median(rb.trans) / np.median(info["oracle"].trans)
        share = info["rejected_gross"] / info["gross"] if info["gross"] else 1.0
        out.append(
            f"- robust, {fraction:.0%} ({info['n_out']} outliers in {info['n_meas']} "
            f"measurements): median error ×{rr:.3f} rot / ×{rt:.3f} trans of the outlier-free "
            f"ML's (target ≤ 1.2: {ok(rr <= 1.2 and rt <= 1.2)}); ×{orr:.3f} / ×{ort:.3f} of ML on "
            f"the same trials' good measurements only; > {GROSS:.0f}σ outliers rejected "
            f"{info['rejected_gross']}/{info['gross']} ({share:.1%}, target all: "
            f"{ok(info['rejected_gross'] == info['gross'])}); good measurements rejected "
            f"{info['false_rej']}")
    return "\n".join(out)


def plot(path, methods, results):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [m for m in methods if results[0.0][m].rot]
    fig, axes = plt.subplots(len(results), 2, figsize=(11, 3.2 * len(results)), sharey=True)
    for row, (fraction, res) in enumerate(results.items()):
        for col, (attr, unit) in enumerate((("rot", "rotation error (deg)"),
                                            ("trans", "translation error (mm)"))):
            ax = axes[row, col]
            data = [np.maximum(getattr(res[m], attr), 1e-4) for m in shown]
            ax.boxplot(data, orientation="horizontal", whis=(5, 95), showfliers=False)
            ax.set_xscale("log")
            ax.set_yticks(range(1, len(shown) + 1), shown, fontsize=8)
            ax.invert_yaxis()
            ax.grid(True, axis="x", which="both", alpha=0.3)
            ax.set_title(f"{fraction:.0%} gross outliers: {unit}", fontsize=9)
    fig.suptitle("Pose fusion error per method (box: quartiles, whiskers: 5–95 %)", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot saved to {path}")


# ---- the moving body ---------------------------------------------------------------------------
MOVING_CAMERAS = CAMERAS[:3]
CAMERA_RATE, ARM_RATE, QUERY_RATE = 30.0, 500.0, 100.0
CAMERA_LATENCY, ARM_LATENCY = 0.040, 0.025
ARM_SCALE = 0.2        # the arm of the static scene, its σ ×0.2: 0.05° / 0.16 mm per sample
FUSION_WINDOW = 0.15   # the measurements stamped within the last 150 ms
LAGS = (0.0, 0.05)     # the pose now, and the pose 50 ms ago
MOVING_SECONDS = 3.0
START = 0.3            # the first query, once a full window has arrived
LATENCY_PRIOR = (0.0, 0.05)  # the online-estimated case: the cameras' latency 0 ± 50 ms


@dataclass(frozen=True)
class Path:
    """A smooth path: position ``c + A ⊙ sin(ω t + φ)``, orientation ``R0 · Exp(B ⊙ sin(Ω t +
    ψ))`` (a rotation vector of sines): speed, turn rate and acceleration all vary."""
    center: np.ndarray
    amp: np.ndarray
    omega: np.ndarray
    phase: np.ndarray
    R0: np.ndarray      # a rotation-only dual quaternion
    rot_amp: np.ndarray
    rot_omega: np.ndarray
    rot_phase: np.ndarray

    def __call__(self, t) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))[:, None]
        p = self.center + self.amp * np.sin(self.omega * t + self.phase)
        theta = self.rot_amp * np.sin(self.rot_omega * t + self.rot_phase)
        R = dq.mul(self.R0, lie.se3_exp(np.c_[theta, np.zeros_like(theta)]))
        return dq.from_pose(dq.to_pose(R)[0], p)

    def motion(self, t, h=1e-4):
        """Angular speed (rad/s), speed (m/s), angular and linear acceleration (/s²) at ``t``
        (central differences of the body twist and the position)."""
        t = np.asarray(t, dtype=np.float64)
        T = [self(t + k * h) for k in (-1, 0, 1)]
        V = [lie.se3_log(dq.mul(dq.conj(T[k]), T[k + 1])) / h for k in (0, 1)]
        p = [dq.to_pose(x)[1] for x in T]
        w = 0.5 * (V[0][:, :3] + V[1][:, :3])
        return (np.linalg.norm(w, axis=1), np.linalg.norm((p[2] - p[0]) / (2 * h), axis=1),
                np.linalg.norm((V[1][:, :3] - V[0][:, :3]) / h, axis=1),
                np.linalg.norm((p[2] - 2 * p[1] + p[0]) / h ** 2, axis=1))


def make_path(rng) -> Path:
    """Position amplitudes 0.1–0.16 m at 1.2–2.2 rad/s, rotation 0.35–0.6 rad at 1.0–1.8 rad/s:
    speeds of a few tenths of a metre and tens of degrees per second, always accelerating."""
    return Path(np.array([0.0, 0.0, 0.3]), rng.uniform(0.10, 0.16, 3), rng.uniform(1.2, 2.2, 3),
                rng.uniform(0, 2 * np.pi, 3), dq.from_pose(_random_rotation(rng), np.zeros(3)),
                rng.uniform(0.35, 0.6, 3), rng.uniform(1.0, 1.8, 3), rng.uniform(0, 2 * np.pi, 3))


@dataclass(frozen=True)
class Stream:
    """One source's measurements in stamp order: taken at ``capture``, stamped ``stamp`` =
    capture + ``latency``, poses ``Z`` (``X(capture) = Z · Exp(ξ)``, ``ξ ~ N(0, S)``)."""
    name: str
    rate: float
    latency: float
    capture: np.ndarray
    stamp: np.ndarray
    Z: np.ndarray
    S: np.ndarray


@dataclass(frozen=True)
class MovingScene:
    path: Path
    streams: tuple[Stream, ...]
    queries: np.ndarray   # the query times (stamp clock): what has been stamped by then is known

    def window(self, t_q: float, length: float = FUSION_WINDOW):
        """Every measurement stamped in ``(t_q − length, t_q]``: poses, covariances, source
        names, stamps."""
        parts = []
        for s in self.streams:
            lo, hi = np.searchsorted(s.stamp, [t_q - length, t_q], side="right")
            parts.append((s.Z[lo:hi], s.S[lo:hi], [s.name] * (hi - lo), s.stamp[lo:hi]))
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                sum((p[2] for p in parts), []), np.concatenate([p[3] for p in parts]))


def moving_scene(seed: int, seconds: float = MOVING_SECONDS) -> MovingScene:
    """The three first cameras of :func:`profiles` at 30 Hz with 40 ms latency, each with its own
    frame phase, and the arm at 500 Hz with 25 ms latency, watching one body on a smooth path."""
    rng = np.random.default_rng(seed)
    path = make_path(rng)
    streams = []
    for p in profiles():
        if p.name not in MOVING_CAMERAS and p.name != ARM:
            continue
        rate, latency = (ARM_RATE, ARM_LATENCY) if p.name == ARM else (CAMERA_RATE,
                                                                      CAMERA_LATENCY)
        capture = np.arange(rng.uniform(0, 1 / rate), seconds, 1 / rate)
        X = path(capture)
        if p.R_world is None:
            S = np.broadcast_to(p.cov * ARM_SCALE ** 2, (capture.size, 6, 6)).copy()
        else:  # the camera's axes in each body frame
            R = dq.to_matrix(X)[:, :3, :3]
            B = np.zeros((capture.size, 6, 6))
            B[:, :3, :3] = B[:, 3:, 3:] = np.swapaxes(R, 1, 2) @ p.R_world
            S = B @ p.cov @ np.swapaxes(B, 1, 2)
        S = 0.5 * (S + np.swapaxes(S, 1, 2))
        xi = np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=(capture.size, 6)))
        streams.append(Stream(p.name, rate, latency, capture, capture + latency,
                              dq.mul(X, lie.se3_exp(-xi)), S))
    queries = np.arange(START, seconds, 1 / QUERY_RATE)
    return MovingScene(path, tuple(streams), queries)


def single(stream: Stream, t_q: float, time: float) -> np.ndarray:
    """What a user does with one source: its two samples stamped by ``t_q`` that bracket
    ``time`` (latency subtracted), screw-interpolated (ScLERP), or the newest two extrapolated
    along their screw when ``time`` is beyond the newest."""
    k = int(np.searchsorted(stream.stamp, t_q, side="right"))  # known by t_q: [0, k)
    taken = stream.stamp[:k] - stream.latency
    j = int(np.clip(np.searchsorted(taken, time), 1, k - 1))
    a, b = j - 1, j
    return dq.sclerp(stream.Z[a], stream.Z[b], (time - taken[a]) / (taken[b] - taken[a]))


def acceleration_rule(path: Path, seconds: float) -> np.ndarray:
    """``acceleration_psd`` by dqpose.fusion's rule of thumb ``Q ≈ a² L``: the path's rms angular
    and linear accelerations over the fusion window, isotropic within each."""
    _, _, alpha, acc = path.motion(np.arange(0.0, seconds, 0.01))
    a_w, a_v = np.sqrt(np.mean(alpha ** 2)), np.sqrt(np.mean(acc ** 2))
    return FUSION_WINDOW * np.diag([a_w ** 2 / 3] * 3 + [a_v ** 2 / 3] * 3)


MOVING_OURS = ("ours time-aligned ML", "ours time-aligned + acceleration_psd",
               "ours, camera latency estimated online", "ours static (ignoring time)")


def run_moving(seed: int, seconds: float):
    """Every method at every query time of every lag; returns the per-lag series, the
    latency estimates and the scene."""
    scene = moving_scene(seed, seconds)
    Q = acceleration_rule(scene.path, seconds)
    known = [fusion.Source(s.name, latency=s.latency) for s in scene.streams]
    guess = [fusion.Source(s.name, latency=LATENCY_PRIOR[0], latency_sigma=LATENCY_PRIOR[1])
             if s.name != ARM else fusion.Source(s.name, latency=s.latency)
             for s in scene.streams]
    names = [s.name for s in scene.streams]
    results, latencies = {}, {}
    for lag in LAGS:
        res = {m: Series([], [], [], []) for m in names + list(MOVING_OURS)}
        est = []
        for t_q in scene.queries:
            time_ = float(t_q - lag)
            X = scene.path(time_)[0]
            Z, S, ns, stamps = scene.window(t_q)

            def add(m, X_hat, P=None, seconds=None):
                r, t = errors(X_hat, X)
                res[m].rot.append(r)
                res[m].trans.append(t)
                if P is not None:
                    res[m].nees.append(nees(X_hat, P, X))
                if seconds is not None:
                    res[m].seconds.append(seconds)

            for s in scene.streams:
                X_hat, sec = _timed(lambda: single(s, t_q, time_))
                add(s.name, X_hat, seconds=sec)
            f, sec = _timed(lambda: fusion.fuse(Z, S, names=ns, sources=known, times=stamps,
                                                 time=time_))
            add(MOVING_OURS[0], f.mean, f.covariance, sec)
            f, sec = _timed(lambda: fusion.fuse(Z, S, names=ns, sources=known, times=stamps,
                                                 time=time_, acceleration_psd=Q))
            add(MOVING_OURS[1], f.mean, f.covariance, sec)
            f, sec = _timed(lambda: fusion.fuse(Z, S, names=ns, sources=guess, times=stamps,
                                                 time=time_, acceleration_psd=Q))
            add(MOVING_OURS[2], f.mean, f.covariance, sec)
            est.append([(x.value, x.sigma) for x in f.latencies])
            f, sec = _timed(lambda: fusion.fuse(Z, S, names=ns, sources=known))
            add(MOVING_OURS[3], f.mean, f.covariance, sec)
        results[lag] = res
        latencies[lag] = np.array(est)  # (queries, cameras, [value, sigma])
    return names + list(MOVING_OURS), results, latencies, scene, Q


def render_moving(methods, results) -> str:
    head = ["query", "method", "median rot (deg)", "median trans (mm)", "mean NEES",
            "time / fusion"]
    lines = []
    for lag, res in results.items():
        when = "now" if lag == 0 else f"{lag * 1e3:.0f} ms ago"
        for m in methods:
            r = res[m]
            single_ = m in MOVING_CAMERAS or m == ARM
            lines.append([when, f"{m} (ScLERP)" if single_ else m,
                          f"{np.median(r.rot):.3f}" if r.rot else "—",
                          f"{np.median(r.trans):.3f}" if r.trans else "—",
                          f"{np.mean(r.nees):.3g}" if r.nees else "—", _fmt_s(r.seconds)])
    return markdown(head, lines)


def summary_moving(methods, results, latencies, scene, Q) -> str:
    ok = lambda b: "PASS" if b else "FAIL"  # noqa: E731
    if not len(scene.queries):
        return (f"- no queries: the first is at {START:g} s, once a full window has arrived; "
                f"give --moving-seconds more than that")
    w, v, alpha, acc = scene.path.motion(scene.queries)
    out = [f"- path: speed median {np.median(v):.2f} m/s (max {v.max():.2f}), turn rate median "
           f"{np.degrees(np.median(w)):.0f} °/s (max {np.degrees(w.max()):.0f}), acceleration "
           f"median {np.median(acc):.2f} m/s² / {np.degrees(np.median(alpha)):.0f} °/s²; "
           f"{len(scene.queries)} queries per row; acceleration_psd by the rule Q = a² L: "
           f"{Q[0, 0]:.2g} rad²/s³, {Q[3, 3]:.2g} m²/s³"]
    singles = [m for m in methods if m in MOVING_CAMERAS or m == ARM]
    for lag, res in results.items():
        when = "now" if lag == 0 else f"{lag * 1e3:.0f} ms ago"
        rot = {m: np.median(res[m].rot) for m in methods}
        trans = {m: np.median(res[m].trans) for m in methods}
        b_rot = min(singles, key=rot.get)
        b_trans = min(singles, key=trans.get)
        for m in MOVING_OURS[:2]:
            passed = rot[m] < rot[b_rot] and trans[m] < trans[b_trans]
            out.append(f"- {when}: {m} {rot[m]:.3f} deg / {trans[m]:.3f} mm against the best "
                       f"single source interpolated to the query time ({b_rot} {rot[b_rot]:.3f} "
                       f"deg, {b_trans} {trans[b_trans]:.3f} mm): ×{rot[m] / rot[b_rot]:.2f} / "
                       f"×{trans[m] / trans[b_trans]:.2f} ({ok(passed)}); mean NEES "
                       f"{np.mean(res[m].nees):.2f}")
        est = latencies[lag]
        vals = est[..., 0].ravel() * 1e3
        out.append(f"- {when}: camera latency estimated online from {LATENCY_PRIOR[0] * 1e3:.0f} "
                   f"± {LATENCY_PRIOR[1] * 1e3:.0f} ms (truth {CAMERA_LATENCY * 1e3:.0f} ms): "
                   f"{vals.mean():.2f} ms mean, {vals.std():.2f} ms spread over queries and "
                   f"cameras, reported σ {np.median(est[..., 1]) * 1e3:.2f} ms (median); "
                   f"|error| / σ median "
                   f"{np.median(np.abs(vals / 1e3 - CAMERA_LATENCY) / est[..., 1].ravel()):.2f}")
    return "\n".join(out)


def plot_moving(path, methods, results, scene):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [ARM, MOVING_CAMERAS[0], MOVING_OURS[0], MOVING_OURS[1], MOVING_OURS[3]]
    fig, axes = plt.subplots(len(results), 2, figsize=(12, 3.4 * len(results)), sharex=True)
    for row, (lag, res) in enumerate(results.items()):
        when = "the pose now" if lag == 0 else f"the pose {lag * 1e3:.0f} ms ago"
        for col, (attr, unit) in enumerate((("rot", "rotation error (deg)"),
                                            ("trans", "translation error (mm)"))):
            ax = axes[row, col]
            for m in shown:
                ax.plot(scene.queries, np.maximum(getattr(res[m], attr), 1e-4), lw=0.8,
                        label=m if m in MOVING_OURS else f"{m} (ScLERP)")
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            ax.set_title(f"{when}: {unit}", fontsize=9)
            if row == len(results) - 1:
                ax.set_xlabel("query time (s)")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Moving body: error at the query time (30 Hz cameras, 40 ms latency; 500 Hz "
                 "arm, 25 ms)", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot saved to {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", metavar="PATH", help="also save the error distributions (PNG)")
    ap.add_argument("--trials", type=int, default=TRIALS, help=f"per outlier fraction "
                    f"(default {TRIALS}; the NEES target is stated over 1000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--moving-seconds", type=float, default=MOVING_SECONDS,
                    help=f"length of the moving-body run (default {MOVING_SECONDS:g} s, "
                         f"queries at {QUERY_RATE:g} Hz from {START:g} s; 0 skips it)")
    ap.add_argument("--moving-plot", metavar="PATH", help="also save the moving body's errors "
                    "over time (PNG)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    methods, results, checks, robust_info, have_gtsam = run(args.seed, args.trials)
    print(f"dqpose fusion benchmark — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, NumPy {np.__version__}; "
          f"{args.trials} trials per outlier fraction, seed {args.seed}"
          + ("" if have_gtsam else "; gtsam not installed: no GTSAM row"))
    print(render(methods, results))
    print(summary(methods, results, checks, robust_info, have_gtsam, args.trials))
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.plot:
        plot(args.plot, methods, results)
    if args.moving_seconds > 0:
        t0 = time.perf_counter()
        moving = run_moving(args.seed, args.moving_seconds)
        print(f"\nMoving body, {args.moving_seconds:g} s, seed {args.seed}, load "
              f"{os.getloadavg()[0]:.2f}")
        print(render_moving(moving[0], moving[1]))
        print(summary_moving(*moving))
        print(f"({time.perf_counter() - t0:.0f} s)")
        if args.moving_plot:
            plot_moving(args.moving_plot, moving[0], moving[1], moving[3])


if __name__ == "__main__":
    main()
