"""Benchmark of trajectory planning: ``python -m tests.bench.bench_trajectory``.

One table. On the same SE(3) paths and the same limits (tool-point velocity 0.5 m/s,
acceleration 2 m/s^2, jerk 20 m/s^3; tool 1 rad/s, 4 rad/s^2, 40 rad/s^3), measured in the same
run:

* **ours** — ``dqpose.trajectory.plan`` (TOOL_LINEAR), its samples from ``at_rate``;
* **Ruckig** (community version) on [xyz, rotation vector], the rotation vector relative to the
  segment's start pose (so a straight move is a straight line in these coordinates), phase
  synchronised; with the limits per axis scaled by the direction of the move (|d_k| * limit, so
  the synchronised profile is limited in norm) and with the naive per-axis limits (each axis
  given the norm's limit). It has no intermediate waypoints (a paid feature), so a path is
  chained rest-to-rest moves;
* **TOPP-RA** on the same 6 coordinates (relative to waypoint 0): a cubic spline through the
  waypoints, joint-like velocity and acceleration constraints on the 6 coordinates, scaled per
  axis by the path's direction along it (its way to say "Cartesian speed"); it has no jerk limit.

Columns: the duration, the worst limit violation measured on each planner's own samples at 1 kHz
(finite differences of positions and of the true rotations, not of rotation-vector
coordinates; the jerk is reported separately because TOPP-RA does not limit it), the planning
time (median). Then ours against Ruckig on 200 random straight moves under random limits. A
second table: dense evaluation cost per pose (best of the repeats, and as a multiple of the same
run's one-pair ScLERP), the issue's target of 100 blended waypoints -> a 5,000-pose stream, and
the planning time of the same 100 waypoints each given a time (1.2x its free arrival).

Options: ``--quick`` (fewer repeats); ``--callgrind CASE`` (one evaluation, for an instruction
count: see ``evaluate_once``).
"""
from __future__ import annotations

import argparse
import math
import platform
import time

import numpy as np

from dqpose import dq, interpolate
from dqpose.trajectory import Limits, Waypoint, plan
from tests._kinematics import NOISE_1KHZ, peaks

LIMITS = Limits(max_linear_velocity=0.5, max_angular_velocity=1.0, max_linear_acceleration=2.0,
                max_angular_acceleration=4.0, max_linear_jerk=20.0, max_angular_jerk=40.0)
RATE = 1000.0


def pose(axis, angle, t) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])
    return dq.from_pose(q, np.asarray(t, float))


def paths() -> dict[str, tuple[list[np.ndarray], float]]:
    """name -> (waypoint poses, blend radius at the inner waypoints)."""
    z = [0, 0, 1]
    out = {
        "straight 1 m": ([pose(z, 0, [0, 0, 0]), pose(z, 0, [0.6, 0.64, 0.48])], 0.0),
        "straight 0.3 m + 90 deg": ([pose(z, 0, [0, 0, 0]),
                                     pose(z, math.pi / 2, [0.3, 0, 0])], 0.0),
        "short 2 cm + 10 deg": ([pose(z, 0, [0, 0, 0]),
                                 pose([1, 1, 0], 0.17, [0.01, 0.01, 0.01])], 0.0),
        "rotation 5 mm + 150 deg": ([pose(z, 0, [0, 0, 0]),
                                     pose([0, 1, 1], 2.6, [0.005, 0, 0])], 0.0),
    }
    rng = np.random.default_rng(7)
    corners = [[0, 0, 0], [0.3, 0, 0], [0.3, 0.3, 0.05], [0, 0.3, 0.1], [0, 0, 0.2],
               [0.3, 0.05, 0.2], [0.35, 0.3, 0.05], [0.05, 0.25, 0]]
    wps = [pose(rng.normal(size=3), rng.uniform(0, 0.6), c) for c in corners]
    out["8 waypoints, blends 5 cm"] = (wps, 0.05)
    out["8 waypoints, stops"] = (wps, 0.0)
    return out


def waypoints(poses, radius):
    return [Waypoint(p, blend_radius=radius if 0 < i < len(poses) - 1 else 0.0)
            for i, p in enumerate(poses)]


def median_time(fn, repeats: int, best: bool = False) -> float:
    """Median (or best) wall time of fn over repeats, after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.min(ts) if best else np.median(ts))


def coordinates(poses, ref) -> np.ndarray:
    """[xyz, rotation vector of R R_ref^T] of each pose: straight moves are straight lines here."""
    q, t = dq.to_pose(poses)
    rel = dq.mul(dq.from_pose(q, np.zeros_like(t)),
                 dq.conj(dq.from_pose(dq.to_pose(ref)[0], np.zeros(3))))
    return np.concatenate([t, 2 * dq.log(rel)[..., :3]], axis=-1)


def from_coordinates(x, ref) -> np.ndarray:
    rot = dq.exp(np.concatenate([x[:, 3:] / 2, np.zeros((len(x), 3))], axis=1))
    q0 = dq.from_pose(dq.to_pose(ref)[0], np.zeros(3))
    return dq.from_pose(dq.mul(rot, q0)[:, :4], x[:, :3])


def axis_limits(direction, scaled: bool, limits: Limits = LIMITS) -> tuple[np.ndarray, ...]:
    """Per-axis [v, a, j] for the 6 coordinates: the norm limits split along the direction of the
    move (scaled) or each axis given the whole norm limit (naive)."""
    lin = np.abs(direction[:3]) / max(np.linalg.norm(direction[:3]), 1e-300)
    ang = np.abs(direction[3:]) / max(np.linalg.norm(direction[3:]), 1e-300)
    if not scaled:
        lin, ang = np.ones(3), np.ones(3)
    L = limits
    out = []
    for lv, av in ((L.max_linear_velocity, L.max_angular_velocity),
                   (L.max_linear_acceleration, L.max_angular_acceleration),
                   (L.max_linear_jerk, L.max_angular_jerk)):
        out.append(np.concatenate([lin * lv, ang * av]) + 1e-9)
    return tuple(out)


# ---- the planners ----------------------------------------------------------------------------

def run_ours(poses, radius):
    wps = waypoints(poses, radius)
    tr = plan(wps, LIMITS)
    s = tr.at_rate(RATE)
    return tr.duration, s.time[:-1], s.pose[:-1], lambda: plan(wps, LIMITS)


def ruckig_moves(poses, scaled: bool, limits: Limits = LIMITS) -> list:
    """One rest-to-rest Ruckig trajectory per segment."""
    import ruckig

    def segment(a, b):
        goal = coordinates(b, a)
        start = coordinates(a, a)
        v, acc, j = axis_limits(goal - start, scaled, limits)
        otg, inp, traj = ruckig.Ruckig(6), ruckig.InputParameter(6), ruckig.Trajectory(6)
        inp.current_position, inp.target_position = list(start), list(goal)
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = list(v), list(acc), list(j)
        inp.synchronization = ruckig.Synchronization.Phase
        res = otg.calculate(inp, traj)
        assert res in (ruckig.Result.Working, ruckig.Result.Finished), res
        return traj

    return [segment(a, b) for a, b in zip(poses[:-1], poses[1:])]


def run_ruckig(poses, scaled: bool):
    def solve():
        return ruckig_moves(poses, scaled)

    trajs = solve()
    total = sum(t.duration for t in trajs)
    times = np.arange(int(total * RATE)) / RATE
    out, t0 = [], 0.0
    for k, traj in enumerate(trajs):
        mine = times[(times >= t0) & ((times < t0 + traj.duration) | (k == len(trajs) - 1))]
        x = np.array([traj.at_time(min(t - t0, traj.duration))[0] for t in mine])
        out.append(from_coordinates(x.reshape(-1, 6), poses[k]))
        t0 += traj.duration
    return total, times, np.concatenate(out), solve


def run_toppra(poses):
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint
    ta.setup_logging("ERROR")
    x = coordinates(np.asarray(poses), poses[0])
    ss = np.linspace(0, 1, len(x))

    def solve():
        path = ta.SplineInterpolator(ss, x)

        def box(scale_of):
            def at(s):
                lim = np.array(axis_limits(path(s, 1), True)[scale_of])
                return np.stack([-lim, lim], axis=1)
            return at

        vel = constraint.JointVelocityConstraintVarying(box(0))
        # acceleration: per-axis bounds along the direction at the path's start (TOPP-RA's
        # linear constraints cannot express a norm; a straight move is exact)
        acc = constraint.JointAccelerationConstraint(
            np.stack([-axis_limits(x[-1] - x[0] if len(x) == 2 else np.ones(6), len(x) == 2)[1],
                      axis_limits(x[-1] - x[0] if len(x) == 2 else np.ones(6), len(x) == 2)[1]],
                     axis=1),
            discretization_scheme=constraint.DiscretizationType.Interpolation)
        inst = algo.TOPPRA([vel, acc], path, parametrizer="ParametrizeConstAccel")
        return inst.compute_trajectory()

    traj = solve()
    times = np.arange(int(traj.duration * RATE)) / RATE
    return traj.duration, times, from_coordinates(traj(times), poses[0]), solve


# ---- measuring ----------------------------------------------------------------------------------

def violations(times, poses):
    """Worst excess over [velocity, acceleration] limits (linear and angular) and over the jerk
    limits, in percent (0 when within, up to the finite differences' rounding)."""
    p = peaks(times, poses)
    L = LIMITS
    lim = np.array([[L.max_linear_velocity, L.max_linear_acceleration, L.max_linear_jerk],
                    [L.max_angular_velocity, L.max_angular_acceleration, L.max_angular_jerk]])
    got = np.stack([p.linear, p.angular]) - np.array(NOISE_1KHZ)
    over = np.maximum(got / lim - 1.0, 0.0) * 100
    return over[:, :2].max(), over[:, 2].max()


def fmt_pct(x: float) -> str:
    return "0" if x == 0 else f"{x:.1f} %"


def planning_table(repeats: int) -> list[tuple]:
    rows = []
    for name, (poses, radius) in paths().items():
        straight = len(poses) == 2
        entries = [("ours (TOOL_LINEAR)", lambda: run_ours(poses, radius))]
        if radius == 0:
            entries += [("Ruckig, norm-scaled axes", lambda: run_ruckig(poses, True)),
                        ("Ruckig, naive per-axis", lambda: run_ruckig(poses, False))]
        entries.append(("TOPP-RA (no jerk)", lambda: run_toppra(poses)))
        ref = None
        for label, fn in entries:
            dur, t, x, solve = fn()
            va, vj = violations(t, x)
            if ref is None:
                ref = dur
            rows.append((name, label, dur, dur / ref, va, vj, median_time(solve, repeats)))
        if straight:
            ours, ruck = rows[-len(entries)][2], rows[-len(entries) + 1][2]
            rows[-len(entries)] += (f"{100 * (ours / ruck - 1):+.1f} % vs Ruckig",)
    return rows


def random_straight_moves(n: int = 200) -> tuple[float, float, float, float]:
    """ours / Ruckig (norm-scaled axes) duration - 1 over random straight moves under random
    limits: median, 95th percentile, worst, and the share within 5 %."""
    rng = np.random.default_rng(11)
    ratios = []
    for _ in range(n):
        limits = Limits(*rng.uniform(0.1, 3, 4), rng.uniform(1, 50), rng.uniform(1, 100))
        d, axis = rng.normal(size=3), rng.normal(size=3)
        dist = 10 ** rng.uniform(-3, 0.5)
        angle = rng.uniform(0, 3.1) if rng.random() < 0.7 else 0.0
        poses = [pose([0, 0, 1], 0, [0, 0, 0]), pose(axis, angle, dist * d / np.linalg.norm(d))]
        ours = plan(waypoints(poses, 0.0), limits).duration
        ratios.append(ours / ruckig_moves(poses, True, limits)[0].duration - 1)
    r = np.array(ratios) * 100
    return (float(np.median(r)), float(np.percentile(r, 95)), float(r.max()),
            float(np.mean(r <= 5) * 100))


def evaluation_path(rng, k: int = 100):
    """k random waypoints (steps of up to 10 cm, small rotations), blend radii 0.4x the shorter
    neighbouring segment."""
    pts = np.cumsum(rng.uniform(-0.1, 0.1, (k, 3)), axis=0)
    qs = rng.normal(size=(k, 4)) * 0.1 + np.array([1, 0, 0, 0])
    poses = dq.from_pose(qs / np.linalg.norm(qs, axis=1, keepdims=True), pts)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return poses, [0.0] + [0.4 * min(seg[i - 1], seg[i]) for i in range(1, k - 1)] + [0.0]


def evaluate_once(case: str, n: int = 20_000) -> None:
    """One dense evaluation of n sorted times, for an instruction count (repeatable under load):
    ``valgrind --tool=callgrind python -m tests.bench.bench_trajectory --callgrind CASE``, then
    ``callgrind_annotate --inclusive=yes`` gives the cost of ``py_traj_eval`` (CASE
    ``tool_linear:blends`` ... ``screw:stops``) or of ``py_sclerp`` (``reference``: one pair)."""
    rng = np.random.default_rng(3)
    poses, radius = evaluation_path(rng)
    if case == "reference":
        dq.sclerp(poses[0], poses[1], rng.uniform(0, 1, n))
        return
    mode, corners = case.split(":")
    tr = plan([Waypoint(p, blend_radius=r if corners == "blends" else 0.0)
               for p, r in zip(poses, radius)], LIMITS, mode)
    tr.sample(np.sort(rng.uniform(0, tr.duration, n)))


def evaluation_table(repeats: int) -> list[tuple]:
    rng = np.random.default_rng(3)
    k = 100
    poses, radius = evaluation_path(rng, k)
    wps = [Waypoint(p, blend_radius=r) for p, r in zip(poses, radius)]
    rows = []
    for mode in ("tool_linear", "screw"):
        tr = plan(wps, LIMITS, mode)
        rate = 5000 / tr.duration
        stream = median_time(lambda: plan(wps, LIMITS, mode).at_rate(rate), repeats, True)
        rows.append((f"100 blended waypoints -> 5,000 poses ({mode}): plan + at_rate",
                     stream * 1e3, "ms", "<= 2 ms"))
        # every waypoint timed at 1.2x its free arrival (a blended corner is reached mid-blend)
        sg = tr.segments
        arrive = ([0.0] + [0.5 * (sg[j].start + sg[j - 1].start + sg[j - 1].duration)
                           if radius[j] > 0 else sg[j].start for j in range(1, k - 1)]
                  + [tr.duration])
        timed = [Waypoint(p, time=1.2 * a, blend_radius=r)
                 for p, a, r in zip(poses, arrive, radius)]
        took = median_time(lambda: plan(timed, LIMITS, mode), max(3, repeats // 10), True)
        rows.append((f"100 blended waypoints, each timed ({mode}): plan", took * 1e3, "ms", ""))
        t = np.sort(rng.uniform(0, tr.duration, 200_000))
        per = median_time(lambda: tr.sample(t), repeats, True) / len(t)
        rows.append((f"dense evaluation, blended path ({mode})", per * 1e9, "ns/pose", "<= 35 ns"))
        nob = plan([Waypoint(p) for p in poses], LIMITS, mode)
        tn = np.sort(rng.uniform(0, nob.duration, 200_000))
        per = median_time(lambda: nob.sample(tn), repeats, True) / len(tn)
        rows.append((f"dense evaluation, no blends ({mode})", per * 1e9, "ns/pose", "<= 35 ns"))
    # peers: the same piecewise-ScLERP path at the same times, by NumPy and by a Python loop
    tk = np.linspace(0, 1, k)
    tau = rng.uniform(0, 1, 200_000)
    per = median_time(lambda: interpolate.interpolate(tk, poses, tau, "screw"), repeats,
                      True) / len(tau)
    rows.append(("NumPy: searchsorted + dq.sclerp per-sample pairs (interpolate.py)", per * 1e9,
                 "ns/pose", ""))
    few = tau[:5000]
    seg_i = np.minimum((few * (k - 1)).astype(int), k - 2)

    def loop():
        for i, s in zip(seg_i, few * (k - 1) - seg_i):
            dq.sclerp(poses[i], poses[i + 1], s)
    per = median_time(loop, max(3, repeats // 5), True) / len(few)
    rows.append(("Python loop: one dq.sclerp call per pose", per * 1e9, "ns/pose", ""))
    a, b = poses[0], poses[1]
    per = median_time(lambda: dq.sclerp(a, b, tau), repeats, True) / len(tau)
    rows.append(("reference: dq.sclerp, one pair x 200k tau (no time law)", per * 1e9, "ns/pose",
                 ""))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--callgrind", metavar="CASE",
                    choices=[f"{m}:{c}" for m in ("tool_linear", "screw")
                             for c in ("blends", "stops")] + ["reference"],
                    help="evaluate once for valgrind (see evaluate_once) and exit")
    args = ap.parse_args()
    if args.callgrind:
        evaluate_once(args.callgrind)
        return
    repeats = 5 if args.quick else 30
    print(f"# Trajectory planning ({platform.processor() or platform.machine()}, Python "
          f"{platform.python_version()})\n")
    print("Limits: " + ", ".join(f"{f}={getattr(LIMITS, f):g}"
                                 for f in LIMITS.__dataclass_fields__))
    print()
    print("| path | planner | duration (s) | vs ours | worst v/a violation | worst jerk violation "
          "| plan time |")
    print("|---|---|---|---|---|---|---|")
    for row in planning_table(repeats):
        name, label, dur, rel, va, vj, tp = row[:7]
        note = f" ({row[7]})" if len(row) > 7 else ""
        print(f"| {name} | {label}{note} | {dur:.4f} | {rel:.3f} | {fmt_pct(va)} | {fmt_pct(vj)} | "
              f"{tp * 1e3:.3f} ms |")
    med, p95, worst, share = random_straight_moves()
    print()
    print(f"Random straight moves (200, random limits), ours / Ruckig (norm-scaled axes) - 1: "
          f"median {med:+.2g} %, 95th percentile {p95:+.2g} %, worst {worst:+.2g} %; "
          f"within 5 %: {share:.0f} %")
    print()
    # best of the repeats (the machine is shared); per pose also as a multiple of the same
    # run's one-pair ScLERP, which a load slows alike
    rows = evaluation_table(repeats)
    ref = rows[-1][1]
    print("| dense evaluation (best of the repeats) | value | unit | x one-pair ScLERP | target |")
    print("|---|---|---|---|---|")
    for name, v, unit, target in rows:
        ratio = f"{v / ref:.2f}" if unit == "ns/pose" else ""
        print(f"| {name} | {v:.3g} | {unit} | {ratio} | {target} |")


if __name__ == "__main__":
    main()
