"""The moving-body table of bench_fusion: a body on a smooth always-accelerating path, three
cameras at 30 Hz and the arm at 500 Hz with latencies; each source alone as a user does it, ours
time-aligned (constant twist, acceleration as process noise, latency estimated online) and
static."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from dqpose import dq, fusion, lie
from tests.bench._table import markdown
from tests.bench.fusion_scenes import (
    ARM,
    CAMERAS,
    Series,
    _fmt_s,
    _random_rotation,
    _timed,
    errors,
    nees,
    profiles,
)

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


