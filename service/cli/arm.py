"""``dqpose arm list`` and ``dqpose arm get NAME``: the arms a server drives (``dqpose serve
--arm``), where each is and what it is doing, as a table for people or as JSON."""
from __future__ import annotations

import json
import sys

from dqpose.cli.common import client, connection_args, failure


def configure(name: str, p) -> None:
    p.description = ("The arms of the server at --server (those `dqpose serve --arm` opened): "
                     "where each tool is (T_base_tool), how fast it moves, its run's state, its "
                     "limits and faults.")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    listing = sub.add_parser("list", help="every arm, one line each",
                             description="Every arm of the server, one line each.")
    get = sub.add_parser("get", help="one arm in full",
                         description="One arm: its pose, velocities, state, limits and faults.")
    get.add_argument("name", metavar="NAME", help="the arm's name (as given to --arm NAME=...)")
    for q in (listing, get):
        q.add_argument("--format", choices=["table", "json"], default="table",
                       help="table for people, or JSON: the pose as the pose files write it "
                            "(default: %(default)s)")
        connection_args(q)
    p.set_defaults(func=_run)


def _run(args) -> int:
    try:
        with client(args) as c:
            arms = c.list_arms() if args.action == "list" else [c.get_arm(args.name)]
    except Exception as e:
        return failure(f"arm {args.action}", args, e)
    if args.format == "json":
        doc = [as_json(a) for a in arms]
        print(json.dumps(doc if args.action == "list" else doc[0], indent=2))
    elif args.action == "list":
        sys.stdout.write(table(arms) if arms else NO_ARMS)
    else:
        sys.stdout.write(details(arms[0]))
    return 0


#: what ``arm list`` says of a server without arms
NO_ARMS = ("no arms: this server drives none; start it with one or more --arm NAME=KIND:TARGET "
           "(e.g. dqpose serve --arm ur=ur:192.168.1.10), or with --sims for the simulated UR "
           "and PiPER (make run does)\n")


def _pose(a):
    """``(x, y, z), (qw, qx, qy, qz)`` of the arm's pose with ``qw >= 0``, or None."""
    if a.pose is None:
        return None
    from dqpose import dq
    q, t = dq.to_pose(a.pose)
    return [float(v) for v in t], [float(v) for v in (q if q[0] >= 0 else -q)]


def as_json(a) -> dict:
    pose = _pose(a)
    return {
        "arm": a.arm,
        "pose": None if pose is None else {
            "position": dict(zip("xyz", pose[0])), "orientation": dict(zip("wxyz", pose[1]))},
        "linear_velocity": [float(v) for v in a.linear_velocity],
        "angular_velocity": [float(v) for v in a.angular_velocity],
        "state": a.state, "busy": a.busy,
        "limits": {name: getattr(a.limits, name) for name in _limits()},
        "faults": list(a.faults),
    }


def _limits() -> dict:
    """The arms' limits the server reports, by the proto's name: their units."""
    from dqpose.rpc.arms import ARM_LIMITS
    return ARM_LIMITS


def _speeds(a) -> tuple[float, float]:
    import numpy as np
    return float(np.linalg.norm(a.linear_velocity)), float(np.linalg.norm(a.angular_velocity))


def table(arms) -> str:
    rows = [("ARM", "STATE", "BUSY", "X m", "Y m", "Z m", "QW", "QX", "QY", "QZ", "m/s",
             "rad/s", "FAULTS")]
    for a in arms:
        pose = _pose(a)
        numbers = ["-"] * 7 if pose is None else [f"{v:.4f}" for v in pose[0] + pose[1]]
        v, w = _speeds(a)
        # no run yet: idle (a run's state stays shown after it ended)
        rows.append((a.arm, a.state or "idle", "yes" if a.busy else "no", *numbers,
                     f"{v:.3g}", f"{w:.3g}", "; ".join(a.faults) or "none"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "".join("  ".join(c.ljust(n) for c, n in zip(r, widths)) + "  " + r[-1] + "\n"
                   for r in rows)


def details(a) -> str:
    pose = _pose(a)
    v, w = _speeds(a)
    lines = [f"arm {a.arm}: {'busy' if a.busy else 'idle'}; its run: {a.state or 'none yet'}",
             "pose T_base_tool (x,y,z m; qw,qx,qy,qz):",
             "  " + ("unknown" if pose is None else
                     ",".join(f"{x:.9g}" for x in pose[0] + pose[1])),
             f"linear velocity (m/s): {','.join(f'{x:.6g}' for x in a.linear_velocity)} "
             f"(|v| {v:.6g})",
             f"angular velocity (rad/s): {','.join(f'{x:.6g}' for x in a.angular_velocity)} "
             f"(|w| {w:.6g})",
             "limits (an Execute above them is refused):"]
    lines += [f"  {name} {getattr(a.limits, name):.6g} {unit}" for name, unit in _limits().items()]
    lines.append("faults: " + ("none" if not a.faults else ""))
    lines += [f"  {f}" for f in a.faults]
    return "\n".join(lines) + "\n"
