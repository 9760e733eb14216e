"""``dqpose properties``: Table 1 of Kavan et al. measured on this build
(:mod:`dqpose.properties`)."""
from __future__ import annotations

import argparse
import sys


def _main(args: argparse.Namespace) -> int:
    from dqpose.properties import format_table, measure

    # ~0.5 ms per trial: a bar only where the wait becomes noticeable, and only for a person
    table = measure(trials=args.trials, seed=args.seed, tol=args.tol,
                    progress=args.trials >= 5000 and sys.stderr.isatty())
    print(format_table(table, verbose=args.verbose))
    return 1 if table.mismatches() else 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 8:
        raise argparse.ArgumentTypeError(f"must be >= 8, got {value}")
    return value


def configure(name: str, p) -> None:
    from dqpose.properties import DEFAULT_TOL

    p.description = ("Measure rigidity, bi-invariance, coordinate invariance, n > 2, "
                     "constant speed and shortest path of every blending method, "
                     "compare with the paper's Table 1, exit 1 on any disagreement.")
    p.add_argument("--trials", type=_positive_int, default=200,
                   help="random input sets per property (default 200)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--tol", type=float, default=DEFAULT_TOL,
                   help=f"largest deviation for a property to hold (default {DEFAULT_TOL:g})")
    p.add_argument("-v", "--verbose", action="store_true", help="print each cell's reason")
    p.set_defaults(func=_main)
