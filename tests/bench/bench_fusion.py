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

import numpy as np

from dqpose import dq, fusion, lie
from tests.bench._table import markdown
from tests.bench.fusion_moving import (
    MOVING_SECONDS,
    QUERY_RATE,
    START,
    plot_moving,
    render_moving,
    run_moving,
    summary_moving,
)
from tests.bench.fusion_scenes import (
    ARM,
    CAMERAS,
    FRACTIONS,
    GROSS,
    TRIALS,
    Series,
    _fmt_s,
    _timed,
    errors,
    nees,
    sigmas_off,
    trials,
)


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
