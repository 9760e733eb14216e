"""``dqpose demo``: a first look at dqpose: blend and interpolate a few sample poses and print
the results, and a one-line verdict."""
from __future__ import annotations

import sys

import numpy as np

from dqpose import dq


def _fmt(pose: np.ndarray) -> str:
    q, t = dq.to_pose(pose)
    if q[0] < 0:  # q and -q are the same rotation; print the one with w >= 0
        q = -q
    angle = np.degrees(2 * np.arctan2(np.linalg.norm(q[1:]), q[0]))
    return (f"t = [{t[0]:+.4f} {t[1]:+.4f} {t[2]:+.4f}] m   "
            f"q = [{q[0]:+.4f} {q[1]:+.4f} {q[2]:+.4f} {q[3]:+.4f}]   ({angle:6.2f} deg)")


def main() -> None:
    # Three measurements of one tool pose, as three sensors might report it.
    def rz(deg: float) -> list[float]:
        h = np.radians(deg) / 2
        return [np.cos(h), 0.0, 0.0, np.sin(h)]

    poses = dq.from_pose(np.array([rz(29.0), rz(31.5), rz(30.2)]),
                         np.array([[0.500, 0.101, 0.300], [0.503, 0.099, 0.298],
                                   [0.499, 0.100, 0.301]]))
    weights = np.array([1.0, 0.5, 2.0])
    print("Three measured poses (weights 1, 0.5, 2):")
    for p in poses:
        print("  ", _fmt(p))
    print("\nBlended with each method:")
    for method in dq.METHODS:
        if method == "sclerp":
            continue  # two poses only; shown below
        print(f"  {method:6s}", _fmt(dq.blend(poses, weights, method=method)))
    mean, iters, res = dq.dib(poses, weights, return_info=True)
    print(f"  DIB converged in {int(iters)} steps, residual {float(res):.1e}")

    print("\nScLERP from the first pose to a pose 90 deg and 0.3 m away (screw motion):")
    goal = dq.from_pose(rz(120.0), [0.8, 0.1, 0.3])
    taus = np.linspace(0.0, 1.0, 5)
    path = dq.sclerp(poses[0], goal, taus)
    for tau, p in zip(taus, path):
        print(f"  tau = {tau:4.2f}  ", _fmt(p))
    means = np.array([dq.blend(poses, weights, method=m) for m in dq.METHODS if m != "sclerp"])
    print(verdict(means, path[-1], goal))


def verdict(means: np.ndarray, end: np.ndarray, goal: np.ndarray) -> str:
    """The run in one line: how far apart the methods' means are, and where ScLERP ended."""
    q, t = dq.to_pose(means)
    mm = 1e3 * max(np.linalg.norm(a - b) for a in t for b in t)
    deg = max(np.degrees(2 * np.arccos(min(1.0, abs(float(a @ b))))) for a in q for b in q)
    off = 1e3 * np.linalg.norm(dq.to_pose(end)[1] - dq.to_pose(goal)[1])
    return (f"\nverdict: on three close measurements every method gives nearly the same mean "
            f"(within {mm:.2g} mm and {deg:.2g} deg of each other; they part ways as poses lie "
            f"further apart), and ScLERP moves along one screw, ending on its goal ({off:.1e} "
            f"mm off)")


if __name__ == "__main__":
    main()


def configure(name: str, p) -> None:
    p.description = ("Blend three measurements of one tool pose with every method, and follow a "
                     "screw motion from one pose to another: a first look at what dqpose "
                     "computes, printed as positions (m), quaternions and angles (deg). "
                     "`dqpose demo fusion`: two simulated cameras and a simulated UR holding a "
                     "board, fused live through the Fusion service; prints each source's error "
                     "and the fused one's against the ground truth and plots them over time. "
                     "`dqpose demo trajectory`: a blended path planned by the Trajectories "
                     "service and executed on the simulated UR through ur_rtde; prints the "
                     "tracking error and the period jitter at the controller. "
                     "`dqpose demo world`: two simulated cameras in two processes and the "
                     "simulated UR publish into one server's World; prints the fused box pose "
                     "against the truth and looks the box up in the tool frame.")
    p.add_argument("mode", nargs="?", choices=("blend", "fusion", "trajectory", "world"),
                   default="blend",
                   help="blend (default): the blending methods; fusion: live pose fusion; "
                        "trajectory: plan and execute on a simulated arm; world: producers in "
                        "three processes feeding one shared world")
    from dqpose.cli import demo_fusion, demo_trajectory, demo_world
    from dqpose.cli.common import INTERRUPTED
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="fusion, trajectory: record the in-process server's calls into "
                        "FILE.mcap (the [record] extra), which `dqpose view` and `dqpose "
                        "replay` open")
    demo_fusion.add_arguments(p)
    demo_trajectory.add_arguments(p)
    demo_world.add_arguments(p)

    def run(args) -> int:
        if args.mode == "blend":
            main()
            return 0
        demo = {"fusion": demo_fusion, "trajectory": demo_trajectory,
                "world": demo_world}[args.mode]
        try:        # the simulated devices' demos fail alike: a missing extra, a device gone
            return demo.main(args)
        except KeyboardInterrupt:   # raised through the demo's exits: the arm closed by now
            print(f"dqpose demo {args.mode}: interrupted; the simulated arm was stopped and its "
                  f"simulator ended", file=sys.stderr)
            return INTERRUPTED
        except ModuleNotFoundError as e:
            from dqpose.cli.common import missing_extra
            return missing_extra(f"demo {args.mode}", e)
        except (OSError, RuntimeError) as e:
            print(f"dqpose demo {args.mode}: {e}", file=sys.stderr)
        return 1
    p.set_defaults(func=run)
