"""The folder ``dqpose handeye capture`` writes and ``dqpose handeye solve`` reads: its file
names, a capture in it to continue (``--resume``), saving one, and a simulation's truth."""
from __future__ import annotations

import glob
import json
import os

POSE_FILES = ("poses.json", "poses.csv")
#: what a capture writes into DIR (and solve, next to it): what --force removes
CAPTURE_FILES = ("poses.json", "intrinsics.json", "board.json", "truth.json",
                 "handeye_report.txt", "handeye.png", "handeye.json")


def find(folder: str, names) -> str | None:
    """The first of the files ``names`` that ``folder`` holds, or None."""
    for n in names:
        path = os.path.join(folder, n)
        if os.path.isfile(path):
            return path
    return None


def view_files(folder: str) -> list[str]:
    """The images a capture took, in order."""
    return sorted(glob.glob(os.path.join(folder, "view_*.png")))


class Previous:
    """A capture in DIR to continue (``--resume``): its images, flange poses and setup, and the
    intrinsics and board files it was taken with."""

    def __init__(self, folder: str):
        from dqpose.cli.posefile import read_robot_poses
        poses = os.path.join(folder, "poses.json")
        if not os.path.isfile(poses):
            raise ValueError(f"--resume: {folder!r} has views but no poses.json (the capture "
                             f"was killed before it saved them); --force starts over")
        robot = read_robot_poses(poses, "m")
        missing = [im for im in robot.images if im is None or
                   not os.path.isfile(os.path.join(folder, im))]
        if missing:
            raise ValueError(f"--resume: {poses} names images not in {folder!r}: "
                             f"{', '.join(map(str, missing[:5]))}; --force starts over")
        self.images = list(robot.images)
        self.flanges = list(robot.base_flange)
        self.setup = robot.setup
        self.intrinsics = find(folder, ("intrinsics.json",))
        self.board = find(folder, ("board.json",))


def save(args, images, flanges, intr, board, truth) -> None:
    """The folder ``solve`` reads: ``poses.json``, the intrinsics, the board and, for a
    simulation, the truth ``(x, z)``."""
    import numpy as np

    from dqpose.cli.posefile import pose_json, robot_poses_json
    with open(os.path.join(args.dir, "poses.json"), "w", encoding="utf-8") as f:
        f.write(robot_poses_json(images, np.array(flanges), args.setup))
    with open(os.path.join(args.dir, "intrinsics.json"), "w", encoding="utf-8") as f:
        json.dump({"K": intr.K.tolist(), "dist": intr.dist.tolist(),
                   "image_size": list(intr.size)}, f, indent=1)
    with open(os.path.join(args.dir, "board.json"), "w", encoding="utf-8") as f:
        json.dump({"kind": board.kind, "squares": list(board.squares),
                   "square_length": board.square_length, "marker_length": board.marker_length,
                   "dictionary_name": board.dictionary_name}, f, indent=1)
    if truth is not None:
        with open(os.path.join(args.dir, "truth.json"), "w", encoding="utf-8") as f:
            json.dump({"setup": args.setup, "x": pose_json(truth[0]), "z": pose_json(truth[1])},
                      f, indent=1)


def read_truth(folder: str, setup: str):
    """``(x, z)`` of a simulated capture (its truth.json), when it is one of this setup."""
    from dqpose import dq
    from dqpose.cli.inputs import pose
    path = os.path.join(folder, "truth.json")
    if not os.path.isfile(path):
        return None
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if doc.get("setup") != setup:
        return None
    rows = [pose(f"{path}: {k}", doc[k]) for k in ("x", "z")]
    return tuple(dq.from_pose(r[:4], r[4:]) for r in rows)
