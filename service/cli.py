"""The ``dqpose`` command line: one subcommand per module, each registering itself.

A module that adds a subcommand defines ``add_parser(subparsers)`` which creates its parser and
sets ``func`` (taking the parsed ``argparse.Namespace`` and returning an exit code). Add the
module's import path to ``COMMANDS``; it is imported lazily, only when its command runs... except
for building the parser, which imports each module's ``add_parser`` (keep those imports light).
"""
from __future__ import annotations

import argparse
import importlib
import sys

# module paths, in the order the help lists them
COMMANDS = [
    "service.demo",
    "service.properties",
    "service.cli_grpc",
    "drivers.sim.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dqpose",
        description="Average, fuse and interpolate rigid poses with dual quaternions.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for path in COMMANDS:
        importlib.import_module(path).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
