"""``dqpose handeye capture`` and ``dqpose handeye solve``: hand-eye calibration from the shell.

``capture DIR`` (:mod:`dqpose.cli.handeye_capture`) drives an arm through informative views of
a ChArUco board and saves the folder (:mod:`dqpose.cli.handeye_folder`) that ``solve``
(:mod:`dqpose.cli.handeye_solve`) reads: it detects the board in each image, solves on a server
(the ``dqpose.v1.HandEye`` service) or ``--local``ly by the same code, and writes a report
(:mod:`dqpose.cli.handeye_report`).
"""
from __future__ import annotations

from dqpose.cli import handeye_capture, handeye_solve
from dqpose.cli.common import missing_extra
from dqpose.cli.handeye_folder import read_truth
from dqpose.cli.handeye_views import CHOICES

__all__ = ["CHOICES", "configure", "read_truth"]


def configure(name: str, p) -> None:
    p.description = ("Hand-eye calibration: capture views of a ChArUco board on an arm, and "
                     "solve for the camera's pose on the flange (eye-in-hand) or in the cell "
                     "(eye-to-hand) from a folder of images and robot poses.")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    handeye_capture.add_parser(sub)
    handeye_solve.add_parser(sub)
    p.set_defaults(func=_run)


def _run(args) -> int:
    action = {"capture": handeye_capture.capture, "solve": handeye_solve.solve}[args.action]
    try:
        return action(args)
    except ModuleNotFoundError as e:    # OpenCV, ur_rtde: the [devices] extra
        return missing_extra(f"handeye {args.action}", e)
