"""``dqpose demo trajectory``: plan a blended path with the Trajectories service and execute it
on the simulated UR (the simulated controller in its own process, driven through the real
``ur_rtde`` client by the server's executor at 500 Hz), then print the tracking error and the
period jitter as the controller saw it, and plot the plan against its limits. A run that ends
short of the plan (the executor stopped the arm) is reported too, its state and message, and
why when the set-points reached the controller late (a busy machine); the exit status is 1.
The last line is a one-line verdict.

The path: from where the arm stands, the tool point goes round a 10 cm square in the horizontal
plane, turning the tool by 30 degrees about the vertical on the way, with 2 cm blends at the
corners (no stop there). With ``--record FILE.mcap`` the in-process server records the plan and
its execution (the feedback, the planned path, the limits), which ``dqpose view`` draws: the
arm's actual path beside the planned one.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import sys
from typing import NamedTuple

import numpy as np

from dqpose import dq, trajectory

LIMITS = trajectory.Limits(max_linear_velocity=0.2, max_angular_velocity=0.8,
                           max_linear_acceleration=1.0, max_angular_acceleration=2.0,
                           max_linear_jerk=10.0, max_angular_jerk=20.0)
_HOME = (0.40, -0.10, 0.30, math.pi, 0.0, 0.0)     # UR rotation-vector pose: tool pointing down


def _rz(deg: float) -> np.ndarray:
    h = math.radians(deg) / 2
    return np.array([math.cos(h), 0.0, 0.0, math.sin(h)])


def waypoints(start: np.ndarray, side: float = 0.1, turn: float = 30.0, blend: float = 0.02):
    """The square from ``start`` (T_base_tool), corners blended, back to ``start``."""
    q0, t0 = dq.to_pose(start)
    corners = [(0, 0), (side, 0), (side, side), (0, side), (0, 0)]
    turns = [0, turn / 2, turn, turn / 2, 0]
    out = []
    for k, ((x, y), a) in enumerate(zip(corners, turns)):
        pose = dq.mul(dq.from_pose(_rz(a), [0, 0, 0]), dq.from_pose(q0, [0, 0, 0]))
        pose = dq.from_pose(dq.to_pose(pose)[0], t0 + [x, y, 0.0])
        r = blend if 0 < k < len(corners) - 1 else 0.0
        out.append(trajectory.Waypoint(pose, blend_radius=r))
    return out


class Result(NamedTuple):
    state: str
    message: str
    duration: float
    segments: tuple
    plan: object                 # client.Planned at the arm's rate
    tracking_mm: np.ndarray      # |actual - commanded| of the tool point, per feedback record
    tracking_deg: np.ndarray
    periods: np.ndarray          # time between set-points arriving at the controller, s
    period: float


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    qa, _ = dq.to_pose(a)
    qb, _ = dq.to_pose(b)
    return math.degrees(2 * math.acos(min(1.0, abs(float(qa @ qb)))))


def run(target: str | None = None, progress: bool = False, recorder=None,
        heartbeat: float | None = None) -> Result:
    """The demo on the simulated UR, through ``target`` or a server of its own (recording into
    ``recorder`` when given); ``heartbeat``: the arm's (s, None: the UR's default)."""
    from dqpose import drivers
    from dqpose.cli.common import local_server, open_arm
    from dqpose.drivers.executor import Executor
    from dqpose.drivers.rotvec import pose_from_rotvec
    from dqpose.drivers.sim import ur as ursim
    from dqpose.rpc.client import Client, RpcError

    with contextlib.ExitStack() as stack:
        sim = stack.enter_context(ursim.URSimProcess())
        sim.set_pose(_HOME)
        spec = f"ur:{sim.host}"        # in its own process where it can, as `dqpose serve` opens it
        arm = stack.enter_context(open_arm(spec, process=drivers.process_problem(spec) is None,
                                           simulated=True, stale_after=0.5,
                                           **({} if heartbeat is None
                                              else {"heartbeat": heartbeat})))
        if target is None:
            target = stack.enter_context(local_server(
                arms={"ur": arm}, executor=Executor,
                **({} if recorder is None else {"recorder": recorder})))
        client = stack.enter_context(Client(target))
        wps = waypoints(pose_from_rotvec(np.array(_HOME)))
        plan = client.plan(wps, LIMITS, 1.0 / arm.period)
        mark = sim.log()["next"]
        feedback = []
        try:
            for fb in client.execute("ur", wps, LIMITS):
                feedback.append(fb)
                if progress:
                    print(f"\r  executing: {fb.time:6.3f} / {plan.duration:.3f} s", end="",
                          file=sys.stderr, flush=True)
        except RpcError as e:
            if e.feedback is None:      # refused before it ran: nothing to report on
                raise
            # it ran and ended short of the plan (its last record, already taken, says how):
            # the report says so, and why when the machine shows why
        finally:
            if progress:
                print(file=sys.stderr)
        arrivals = servo_arrivals(sim, mark)
        period = arm.period
    moving = [f for f in feedback if f.actual is not None and f.commanded is not None]
    mm = np.array([1e3 * np.linalg.norm(dq.to_pose(f.actual)[1] - dq.to_pose(f.commanded)[1])
                   for f in moving])
    deg = np.array([_angle(f.actual, f.commanded) for f in moving])
    last = feedback[-1]
    return Result(last.state, last.message, plan.duration, plan.segments, plan, mm, deg,
                  np.diff(np.asarray(arrivals)), period)


def servo_arrivals(sim, mark: int) -> np.ndarray:
    """When each servoL set-point since the hook log's entry ``mark`` reached the simulated
    controller (``time.monotonic()`` seconds)."""
    from dqpose.drivers.sim import ur as ursim
    arrivals = []
    while True:        # read in pages: the simulator answers a bounded log per call
        got = sim.log(mark, cmd=ursim.SERVOL, keys=["mono"])
        if not got["entries"]:
            return np.asarray(arrivals)
        arrivals += [e["mono"] for e in got["entries"]]
        mark = got["next"]


def missed_cycles(periods: np.ndarray, period: float) -> int:
    """Controller cycles that got no set-point, from the times between set-points."""
    return int(np.clip(np.round(np.asarray(periods) / period) - 1, 0, None).sum())


def report(r: Result, out=None) -> None:
    out = out or sys.stdout
    print(f"plan: {r.duration:.3f} s through 5 waypoints, blends of 2 cm at the corners", file=out)
    for i, s in enumerate(r.segments):
        print(f"  segment {i}: {s.start:6.3f} .. {s.start + s.duration:6.3f} s, bound by "
              f"{s.binding}", file=out)
    print(f"execution on the simulated UR (ur_rtde, {1 / r.period:.0f} Hz): {r.state}"
          + (f" ({r.message})" if r.message else ""), file=out)
    if len(r.tracking_mm):
        print(f"  tracking error, actual vs commanded: median {np.median(r.tracking_mm):.3f} mm "
              f"/ {np.median(r.tracking_deg):.3f} deg, max {r.tracking_mm.max():.3f} mm / "
              f"{r.tracking_deg.max():.3f} deg (the controller follows servoL with its lookahead)",
              file=out)
    missed = missed_cycles(r.periods, r.period)
    if len(r.periods):
        jitter = np.abs(r.periods - r.period) * 1e6
        print(f"  set-points at the controller: {len(r.periods) + 1}, period jitter |dt - "
              f"{r.period * 1e3:g} ms| p50 {np.percentile(jitter, 50):.0f} us, p99 "
              f"{np.percentile(jitter, 99):.0f} us, max {jitter.max():.0f} us; missed cycles "
              f"{missed}", file=out)
    if r.state != "FINISHED" and missed:
        print(f"  why: {missed} controller cycles got no set-point in time (a busy machine: "
              f"the simulated controller, the arm's process and the server share its CPUs; a "
              f"real controller runs on its own)", file=out)


def conclusion(r: Result) -> str:
    """The run in one line for a newcomer."""
    if r.state == "FINISHED":
        follow = (f", the arm within {r.tracking_mm.max():.2f} mm of its set-points"
                  if len(r.tracking_mm) else "")
        return (f"verdict: the planned path ({r.duration:.2f} s, within its limits) ran to its "
                f"end on the simulated UR{follow}")
    why = ("'why:' above says what kept it from it" if r.state != "FINISHED"
           and missed_cycles(r.periods, r.period) else "its message above says why")
    return f"verdict: the run stopped short of the plan ({r.state}); {why}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("trajectory mode")
    g.add_argument("--trajectory-plot", default="trajectory_demo.png", metavar="PATH",
                   help="where to write the PNG of the plan against its limits (default "
                        "trajectory_demo.png; needs matplotlib)")


def main(args: argparse.Namespace) -> int:
    target = getattr(args, "server", None)
    path, recorder = getattr(args, "record", None), None
    if path is not None:
        from dqpose.cli.demo_record import finish, open_file_recorder
        recorder, code = open_file_recorder("demo trajectory", path, target)
        if recorder is None:
            return code
    try:
        result = run(target, progress=sys.stderr.isatty(), recorder=recorder)
    finally:        # a run that failed is recorded too: the file is what tells why
        if recorder is not None:
            print(finish(recorder, path))
    report(result)
    try:
        from dqpose.cli.plots import plot_motion
        plot_motion(args.trajectory_plot, result.plan.time, result.plan.pose, LIMITS,
                    title="dqpose demo trajectory: the plan, measured from its samples")
        print(f"plot: {args.trajectory_plot}")
    except ModuleNotFoundError as e:
        from dqpose.errors import missing
        print(f"no plot: {missing(e)}")
    print(conclusion(result))
    return 0 if result.state == "FINISHED" else 1
