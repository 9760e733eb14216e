"""``dqpose sim ur`` (also ``python -m dqpose.drivers.sim.ur``): a simulated UR controller
on one address, until SIGTERM, Ctrl-C or (``--exit-with-parent``) its parent's end.
"""
from __future__ import annotations

import argparse
import signal
import sys

from dqpose.drivers.sim import stop_when_orphaned
from dqpose.drivers.sim.ur.model import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, SimConfig
from dqpose.drivers.sim.ur.server import URSim


# -------------------------------------------------------------------- CLI
def _parse_pose(text: str):
    vals = [float(x) for x in text.replace(",", " ").split()]
    if len(vals) != 6:
        raise argparse.ArgumentTypeError("pose: expected 6 numbers x y z rx ry rz")
    return tuple(vals)


def _parse_version(text: str):
    vals = tuple(int(x) for x in text.split("."))
    if len(vals) != 4:
        raise argparse.ArgumentTypeError("version: expected major.minor.bugfix.build")
    return vals


def main(argv: list[str] | None = None) -> int:
    d = SimConfig()
    ap = argparse.ArgumentParser(prog="dqpose sim ur",
                                 # the package docstring's first line says what it is
                                 description=sys.modules[__package__].__doc__.split("\n\n")[0])
    ap.add_argument("--host", default=d.host,
                    help="address to serve on (default %(default)s; one simulator per address, "
                         "0.0.0.0 only inside a container)")
    ap.add_argument("--hook-port", type=int, default=d.hook_port, help="JSON-lines test hooks port")
    ap.add_argument("--pose", type=_parse_pose, default=d.pose,
                    help="initial TCP pose 'x y z rx ry rz' (metres, rotation vector in radians)")
    ap.add_argument("--version", type=_parse_version, default=d.version,
                    help="controller version major.minor.bugfix.build (major 3 = CB3, 125 Hz)")
    ap.add_argument("--servo-lag", type=int, default=d.servo_lag,
                    help="servo lag in controller cycles (2 ms e-series, 8 ms CB3; "
                         "default %(default)s)")
    ap.add_argument("--max-linear-speed", type=float, default=d.max_linear_speed,
                    metavar="M_PER_S",
                    help="the model's tool speed limit in m/s (default %(default)g)")
    ap.add_argument("--max-angular-speed", type=float, default=d.max_angular_speed,
                    metavar="RAD_PER_S",
                    help="the model's tool rotation speed limit in rad/s (default %(default)g)")
    ap.add_argument("--exit-with-parent", action="store_true",
                    help="stop when the process that started this one ends (even if killed)")
    args = ap.parse_args(argv)
    if args.servo_lag < 0:
        ap.error("--servo-lag: must be >= 0")
    cfg = SimConfig(host=args.host, hook_port=args.hook_port, pose=args.pose, version=args.version,
                    servo_lag=args.servo_lag, max_linear_speed=args.max_linear_speed,
                    max_angular_speed=args.max_angular_speed)
    sim = URSim(cfg)
    try:
        sim.bind()
    except OSError as e:
        print(f"ursim: cannot serve on {cfg.host}: {e}", file=sys.stderr)
        return 3
    signal.signal(signal.SIGTERM, lambda *_: sim.stopping.set())
    if args.exit_with_parent:
        stop_when_orphaned(sim.stopping)
    print(f"ursim {'.'.join(map(str, cfg.version))} on {cfg.host}: RTDE {RTDE_PORT}, dashboard "
          f"{DASHBOARD_PORT}, script {SCRIPT_PORT}, hooks {cfg.hook_port}; "
          f"{1 / cfg.period:.0f} Hz", flush=True)
    try:
        sim.serve_forever()
    except KeyboardInterrupt:
        sim.shutdown()
    return 0
