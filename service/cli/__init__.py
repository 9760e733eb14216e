"""The ``dqpose`` command line.

``COMMANDS`` maps each command to the module that owns it and its one-line help. ``dqpose --help``
imports none of those modules (so no NumPy, C core or grpc: it answers in milliseconds); running
or asking for the help of one command imports only its module, whose ``configure(name, parser)``
adds the arguments and sets ``func`` (parsed ``argparse.Namespace`` -> exit code). Command modules
keep their top level light and import the heavy parts inside the command.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from dqpose.cli.shell import PIPE_CLOSED, Parser, PipeClosed, guarded_stdout, silence_stdout

# command -> (module, help); in the order the help lists them
COMMANDS = {
    "serve": ("dqpose.cli.serve", "run the gRPC server"),
    "health": ("dqpose.cli.serve", "check a server's gRPC health (exit 0 when SERVING)"),
    "blend": ("dqpose.cli.blend", "blend poses from a JSON, YAML or CSV file"),
    "interpolate": ("dqpose.cli.blend",
                    "interpolate between time-stamped keyframes from a JSON, YAML or CSV file"),
    "fuse": ("dqpose.cli.fuse", "fuse measurements of one body from a JSON, YAML or CSV file"),
    "replay": ("dqpose.cli.replay", "feed a recording (serve --record) again and compare every "
                                    "answer with the recorded one"),
    "view": ("dqpose.cli.view", "a recording on a local web page: frames, covariance "
                                "ellipsoids, plans, a time slider (the [view] extra)"),
    "export": ("dqpose.cli.export", "a recording as a ROS 2 bag (PoseWithCovarianceStamped, /tf, "
                                    "Path)"),
    "world": ("dqpose.cli.world", "a server's shared world: publish measurements, watch fused "
                                  "poses, look up one body relative to another"),
    "plan": ("dqpose.cli.trajectory",
             "plan a limit-respecting motion through waypoints from a JSON, YAML or CSV file"),
    "smooth": ("dqpose.cli.trajectory",
               "smooth a noisy recorded path under limits from a JSON, YAML or CSV file"),
    "cluster": ("dqpose.cli.cluster", "replicas of the server behind HAProxy on this machine "
                                      "(make cluster): scale-out tried without Docker"),
    "arm": ("dqpose.cli.arm", "the arms a server drives: where each is, its state, limits "
                               "and faults"),
    "handeye": ("dqpose.cli.handeye",
                "hand-eye calibration: capture views on an arm, solve from images and robot poses"),
    "demo": ("dqpose.cli.demo", "the demos: blending sample poses (default), live fusion, a "
                                "trajectory on a simulated arm, a shared world"),
    "properties": ("dqpose.cli.properties", "measure Table 1 of Kavan et al. on this build"),
    "sim": ("dqpose.cli.sim", "run a device simulator that speaks the real protocol"),
}


def _chosen(argv: list[str]) -> str | None:
    """The command named in ``argv`` (the top-level parser takes no options but ``-h``)."""
    for a in argv:
        if not a.startswith("-"):
            return a
    return None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser, with the arguments of the command in ``argv`` (of every command when
    ``argv`` is None: for documentation and tests)."""
    parser = Parser(
        prog="dqpose",
        description="Average, fuse and interpolate rigid poses with dual quaternions.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    chosen = None if argv is None else _chosen(argv)
    for name, (module, help) in COMMANDS.items():
        p = sub.add_parser(name, help=help, description=help[:1].upper() + help[1:] + ".")
        if argv is None or name == chosen:
            importlib.import_module(module).configure(name, p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    before = guarded_stdout()
    try:
        args = build_parser(argv).parse_args(argv)
        code = int(args.func(args) or 0)
        sys.stdout.flush()      # what is still buffered: a closed pipe is found here, not at exit
        return code
    except KeyboardInterrupt:
        return 130
    except PipeClosed:
        return PIPE_CLOSED
    finally:
        sys.stdout = before


def run() -> None:
    """The ``dqpose`` program: :func:`main`, then the process's end. Where a UR's ur_rtde
    connections were left to that end (``drivers.ur_connection.kept_to_exit``), the process
    ends without the interpreter's teardown, which their threads can crash (SIGSEGV after a
    clean stop)."""
    code = main()
    if code == PIPE_CLOSED:
        silence_stdout()
    ur = sys.modules.get("dqpose.drivers.ur_connection")
    if ur is not None and ur.kept_to_exit():
        import logging
        import os
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
