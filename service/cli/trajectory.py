"""``dqpose plan`` and ``dqpose smooth``: a time-scaled path through waypoints, and a noisy
recorded path smoothed, both under linear and angular limits, from a JSON, YAML or CSV file; on a
server (the ``dqpose.v1.Trajectories`` service) or ``--local``ly by the same code. CSV or JSON out,
and ``--plot`` draws position, velocity, acceleration and jerk against the limits."""
from __future__ import annotations

import argparse
import sys

from dqpose.cli.common import client, connection_args, failure
from dqpose.cli.inputs import add_quaternion_order
from dqpose.errors import require

PLAN_EPILOG = """\
input formats (FILE, or - for standard input; chosen by the extension, else sniffed):
  JSON  the PlanRequest body grpcurl sends to dqpose.v1.Trajectories/Plan, e.g.
          {"waypoints": [{"pose": {"position": {"x": 0.4, "y": 0, "z": 0.3},
                                   "orientation": {"w": 0, "x": 1, "y": 0, "z": 0}}},
                         {"pose": {...}, "blend_radius": 0.02},
                         {"pose": {...}, "time": 4.0}],
           "limits": {"max_linear_velocity": 0.25, "max_angular_velocity": 1.0,
                      "max_linear_acceleration": 1.0, "max_angular_acceleration": 2.0,
                      "max_linear_jerk": 10, "max_angular_jerk": 20},
           "rate_hz": 125, "interpolation": "TOOL_LINEAR"}
        a bare list of waypoints is accepted too; a key not shown here is an error.
  YAML  the same document in YAML (.yaml, .yml; needs the [yaml] extra).
  CSV   one waypoint per line: x,y,z,qw,qx,qy,qz and, by header name, time (s from the start
        it must be reached; 0: as fast as the limits allow) and blend_radius (m); separated
        by commas, semicolons, tabs or spaces; a file without a header needs
        --quaternion-order.
  an orientation is {"w": .., "x": .., "y": .., "z": ..}, or "orientation_xyzw" /
  "orientation_wxyz": four numbers in that order.
poses are T_base_tool; limits are norms of the tool point's (linear) and the tool's (angular)
motion in the base frame. Flags override the file's limits; velocity and acceleration limits are
required, a jerk limit of 0 (the default) means none.

output: samples at --rate as CSV t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz (or JSON with -o x.json),
and on standard error the duration and, per segment, the limit that decides its speed.

example: dqpose plan --local path.csv --max-linear-velocity 0.2 --max-angular-velocity 1 \\
           --max-linear-acceleration 1 --max-angular-acceleration 2 --plot plan.png
"""

SMOOTH_EPILOG = """\
input formats (FILE, or - for standard input):
  JSON  the SmoothRequest body of dqpose.v1.Trajectories/Smooth: {"poses": [{"time": 0.0,
        "pose": {...}}, ...], "limits": {...}, "smoothing": 1, "rate_hz": 0}
  YAML  the same document in YAML (.yaml, .yml; needs the [yaml] extra).
  CSV   t,x,y,z,qw,qx,qy,qz (commas, semicolons, tabs or spaces; a file without a header needs
        --quaternion-order), times strictly increasing.
output: the smoothed poses as CSV t,x,y,z,qw,qx,qy,qz (or JSON with -o x.json), and on
standard error how far its ends are from the recording's. By default the path starts and ends at
rest (velocity and acceleration zero, as a controller starts and stops): where the recording is
moving at its first or last sample, the smoothed ends lie off it by about as far as it moves in
the smoothing's time scale. --free-ends keeps the recording's motion at both ends (a piece of a
longer motion; the ends then follow the data).

example: dqpose smooth --local demo.csv --max-linear-velocity 0.5 --max-angular-velocity 2 \\
           --max-linear-acceleration 2 --max-angular-acceleration 4 --plot smooth.png
"""

_LIMIT_HELP = {
    "max_linear_velocity": "m/s", "max_angular_velocity": "rad/s",
    "max_linear_acceleration": "m/s^2", "max_angular_acceleration": "rad/s^2",
    "max_linear_jerk": "m/s^3, 0: none", "max_angular_jerk": "rad/s^3, 0: none",
}


def configure(name: str, p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    if name == "plan":
        p.description = ("Plan the fastest motion through the waypoints in FILE that the limits "
                         "allow (on the server at --server, or --local) and print its samples.")
        p.epilog = PLAN_EPILOG
        p.add_argument("file", metavar="FILE",
                       help="waypoints (JSON, YAML or CSV; - reads standard input)")
        p.add_argument("--rate", type=float,
                       help="samples per second (default: the file's, else 125)")
        p.add_argument("--interpolation", choices=("tool_linear", "screw"),
                       help="tool point on straight lines (default), or screw motions (ScLERP)")
    else:
        p.description = ("Smooth the noisy recorded path in FILE (fidelity plus jerk) under the "
                         "velocity and acceleration limits (on the server at --server, or "
                         "--local) and print it.")
        p.epilog = SMOOTH_EPILOG
        p.add_argument("file", metavar="FILE",
                       help="time-stamped poses (JSON, YAML or CSV; - reads standard input)")
        p.add_argument("--smoothing", type=float,
                       help="see service/smoothing/ (default: the file's, else 1)")
        p.add_argument("--rate", type=float,
                       help="resample at this rate (default: the input times)")
        p.add_argument("--free-ends", action="store_true",
                       help="keep the recording's motion at its first and last sample (default: "
                            "start and end at rest)")
    g = p.add_argument_group("limits (override the file's)")
    for key, unit in _LIMIT_HELP.items():
        g.add_argument("--" + key.replace("_", "-"), type=float, dest=key, metavar="X",
                       help=unit)
    p.add_argument("-o", "--output",
                   help="write the samples here (.json: JSON, else CSV; default: standard output "
                        "as CSV)")
    p.add_argument("--plot", metavar="PNG",
                   help="draw position, velocity, acceleration and jerk against the limits")
    p.add_argument("--local", action="store_true",
                   help="compute in this process instead of on a server")
    add_quaternion_order(p)
    connection_args(p)
    p.set_defaults(func=_plan if name == "plan" else _smooth)


def _limits(args, from_file: dict):
    from dqpose import trajectory
    values = dict(from_file)
    for key in _LIMIT_HELP:
        if getattr(args, key) is not None:
            values[key] = getattr(args, key)
    missing = [k for k in _LIMIT_HELP if "jerk" not in k and k not in values]
    if missing:
        raise ValueError(f"--{missing[0].replace('_', '-')}: required (or \"limits\" in the "
                         f"JSON file)")
    return trajectory.Limits(**values)


def _write(args, times, poses, velocities) -> None:
    """The samples in --output (JSON when it ends in .json, else CSV), or CSV on stdout."""
    from dqpose.cli.posefile import format_trajectory
    fmt = "json" if (args.output or "").lower().endswith(".json") else "csv"
    text = format_trajectory(times, poses, velocities, fmt)
    if args.output:
        with open(args.output, "w", encoding="utf-8") as f:
            f.write(text)
    else:
        sys.stdout.write(text)


def _read(args, reader):
    """The input file read with ``reader`` and its limits (the flags' first); matplotlib
    checked for --plot before the work, not after it."""
    if args.plot:
        require("matplotlib")
    f = reader(args.file, args.quaternion_order)
    return f, _limits(args, f.limits)


def _plot(args, action: str, times, poses, limits, **kw) -> None:
    """The motion plotted into --plot (the [plot] extra), its file said on stderr."""
    from dqpose.cli.plots import plot_motion
    plot_motion(args.plot, times, poses, limits, title=f"dqpose {action} {args.file}", **kw)
    print(f"plot: {args.plot}", file=sys.stderr)


def _plan(args) -> int:
    import numpy as np

    from dqpose import trajectory
    from dqpose.cli.posefile import read_plan

    try:
        f, limits = _read(args, read_plan)
        rate = args.rate or f.rate_hz or 125.0
        mode = args.interpolation or f.mode or "tool_linear"
        waypoints = [trajectory.Waypoint(pose=p, time=t, blend_radius=r)
                     for p, t, r in zip(f.dqs, f.times, f.blend_radii)]
        if args.local:
            traj = trajectory.plan(waypoints, limits, mode)
            s = traj.at_rate(rate)
            times, poses = s.time, s.pose
            vel = np.concatenate([s.linear_velocity, s.angular_velocity], axis=1)
            duration, segments = traj.duration, traj.segments
        else:
            with client(args) as c:
                p = c.plan(waypoints, limits, rate, mode)
            times, poses, duration, segments = p.time, p.pose, p.duration, p.segments
            vel = np.concatenate([p.linear_velocity, p.angular_velocity], axis=1)
        _write(args, times, poses, vel)
        print(f"duration {duration:.4f} s, {len(times)} samples at {rate:g} Hz", file=sys.stderr)
        for i, seg in enumerate(segments):
            print(f"  segment {i}: {seg.start:.4f} .. {seg.start + seg.duration:.4f} s, "
                  f"bound by {seg.binding}", file=sys.stderr)
        if args.plot:
            _plot(args, "plan", times, poses, limits)
    except Exception as e:
        return failure("plan", args, e)
    return 0


def _smooth(args) -> int:
    from dqpose import smoothing
    from dqpose.cli.posefile import read_stamped

    try:
        f, limits = _read(args, read_stamped)
        weight = args.smoothing or f.smoothing or 1.0
        rate = args.rate or f.rate_hz or 0.0
        if args.local:
            times, poses = smoothing.smooth(f.times, f.dqs, limits, smoothing=weight,
                                             rate_hz=rate, free_ends=args.free_ends)
        else:
            with client(args) as c:
                times, poses = c.smooth(f.times, f.dqs, limits, weight, rate,
                                        free_ends=args.free_ends)
        _write(args, times, poses, None)
        note = ends_note(f.dqs, poses, args.free_ends)
        print(note, file=sys.stderr)
        if args.plot:
            _plot(args, "smooth", times, poses, limits, raw=(f.times, f.dqs), note=note)
    except Exception as e:
        return failure("smooth", args, e)
    return 0


def ends_note(recorded, smoothed, free_ends: bool) -> str:
    """What the smoothed path's ends are (at rest, or free) and how far each lies from the
    recording's first and last pose (the output always starts and ends on those times)."""
    import math

    import numpy as np

    from dqpose import dq
    off = []
    for k in (0, -1):
        qa, pa = dq.to_pose(recorded[k])
        qb, pb = dq.to_pose(smoothed[k])
        angle = 2.0 * math.acos(min(1.0, abs(float(np.dot(qa, qb)))))
        off.append(f"{1e3 * float(np.linalg.norm(pa - pb)):.2f} mm / {math.degrees(angle):.2f} deg")
    where = f"first pose {off[0]}, last {off[1]} from the recording's"
    if free_ends:
        return f"ends free (--free-ends), following the recording's motion: {where}"
    return (f"ends held at rest (zero velocity and acceleration, as a controller starts and "
            f"stops): {where}; --free-ends keeps the recording's motion there")
