"""``dqpose sim <device> [options]``: start a device simulator from the shell.

Each simulator owns its options: ``SIMULATORS`` maps a device name to ``"module:function"``, and
that function takes the remaining command-line arguments (``main(argv) -> exit code``). Modules
are imported only when their simulator runs.
To add a simulator, add one entry here.
"""
from __future__ import annotations

import argparse
import importlib

from dqpose.cli.common import missing_extra

SIMULATORS = {
    "ur": "dqpose.drivers.sim.ur:main",
    "piper": "dqpose.drivers.sim.piper:main",
    "camera": "dqpose.drivers.sim.camera:main",
}


def configure(name: str, p) -> None:
    p.description = "Run a device simulator; `dqpose sim DEVICE --help` lists its options."
    p.add_argument("device", choices=sorted(SIMULATORS), help="which simulator")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the simulator's own options")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    module, function = SIMULATORS[args.device].split(":")
    try:
        simulator = getattr(importlib.import_module(module), function)
    except ModuleNotFoundError as e:
        return missing_extra(f"sim {args.device}", e)
    return int(simulator(args.args) or 0)
