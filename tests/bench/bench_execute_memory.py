"""What handing a 10-minute plan to an arm costs its caller (the server), before and after the
control loop sampled plans itself: the plan sampled at the arm's 500 Hz and pushed
(`Trajectory.at_rate` + `Executor.push` + `finish`, what the Execute servicer did) against
`Executor.push_plan(trajectory)`; and a plan that does not start at the arm, refused.

    .venv/bin/python -m tests.bench.bench_execute_memory            # ~1 min
    .venv/bin/python -m tests.bench.bench_execute_memory --minutes 10 --executor thread

Each row runs against the simulated UR through ur_rtde, the loop in a thread or in the arm's own
process; the run is cancelled as soon as it started. "Peak" is the largest amount of Python and
NumPy memory the caller held at once (tracemalloc) from just before the call until the run
started (or was refused); "shared" the set-point ring in shared memory (an arm process's);
"time" how long the call took the caller.
"""
from __future__ import annotations

import argparse
import gc
import time
import tracemalloc

import numpy as np

from dqpose import dq, drivers, trajectory
from dqpose.drivers.executor import Executor
from dqpose.drivers.sim import ur as ursim


def ten_minutes(start: np.ndarray, minutes: float, offset=(0.0, 0.0, 0.0)):
    """A straight 0.2 m line from ``start`` (moved by ``offset``), slow enough to last
    ``minutes``."""
    q, t = dq.to_pose(start)
    t0 = t + np.asarray(offset)
    speed = 0.2 / (60.0 * minutes)
    return trajectory.plan([trajectory.Waypoint(dq.from_pose(q, t0)),
                            trajectory.Waypoint(dq.from_pose(q, t0 + [0.2, 0.0, 0.0]))],
                           trajectory.Limits(speed, 0.5, 1.0, 2.0))


def measure(arm, traj, how: str) -> dict:
    gc.collect()
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    ex = Executor(arm)
    refused = ""
    try:
        if how == "push_plan":
            ex.push_plan(traj)
        else:
            s = traj.at_rate(1.0 / arm.period)
            ex.push(s.time, s.pose)
            ex.finish()
    except ValueError as e:
        refused = str(e).split(";")[0]
    took = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    ring = getattr(ex._run, "ring", None)
    shared = 0 if ring is None else ring.head.nbytes + ring.reason.nbytes + ring.slots.nbytes
    ex.cancel()
    ex.wait(10)
    return {"peak": peak, "shared": shared, "time": took, "refused": refused}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--executor", choices=("both", "process", "thread"), default="both")
    args = ap.parse_args(argv)
    places = ("thread", "process") if args.executor == "both" else (args.executor,)
    rows = []
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        for place in places:
            with drivers.open_arm(f"ur:{sim.host}", process=place == "process",
                                  stale_after=0.5) as arm:
                for name, how, offset in (
                        ("sampled and pushed (before)", "push", (0, 0, 0)),
                        ("push_plan (after)", "push_plan", (0, 0, 0)),
                        ("not at the arm, sampled and pushed (before)", "push", (0.01, 0, 0)),
                        ("not at the arm, push_plan (after)", "push_plan", (0.01, 0, 0))):
                    sim.set_pose(ursim.SimConfig().pose)
                    time.sleep(0.05)
                    traj = ten_minutes(arm.tool_pose()[1], args.minutes, offset)
                    r = measure(arm, traj, how)
                    r.update(place=place, name=name, duration=traj.duration,
                             setpoints=int(np.ceil(traj.duration / arm.period)) + 1)
                    rows.append(r)
    print(f"\nA {args.minutes:g}-minute plan (2 waypoints) handed to the simulated UR at 500 Hz")
    print("| loop | call | plan (s) | set-points | peak (MB) | shared (MB) | time (ms) | "
          "refused |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['place']} | {r['name']} | {r['duration']:.0f} | {r['setpoints']:,} | "
              f"{r['peak'] / 1e6:.2f} | {r['shared'] / 1e6:.2f} | {r['time'] * 1e3:.1f} | "
              f"{r['refused'] or '—'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
