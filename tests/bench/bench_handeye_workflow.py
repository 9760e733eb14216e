"""Hand-eye calibration end to end on the simulators, as `dqpose handeye capture` and `solve` run
it: the UR simulator driven through ur_rtde, the board rendered by the simulated camera (2 grey
levels of noise, 0.6 px blur) and detected by drivers.camera, solved by dqpose.handeye; the
answer against the simulation's truth.

    .venv/bin/python -m tests.bench.bench_handeye_workflow               # 5 seeds (~8 min)
    .venv/bin/python -m tests.bench.bench_handeye_workflow --seeds 2 --views 8

Rows: how the views were chosen (`capture --choose`: the solver's next-best pose after a spread
of rotations, the spread rule throughout, or the random candidates as they come: a user's
arbitrary poses), each solved four ways: every view weighed by its detector covariance (the
`solve` default), the noise estimated from the residuals (`--estimate-noise`, what a solver
given poses alone can do), and on the corners' reprojection (`--corners`, with and without
`--refine-focal`). Columns: median and worst error of X over the seeds (the angle of
X̂⁻¹X; the distance between the positions), the mean NEES of X (6 for an honest covariance), and
the median of X's largest 1-sigma position deviation.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import sys
import tempfile

import numpy as np

from dqpose import dq, handeye, lie
from dqpose.cli import main
from dqpose.cli.handeye import CHOICES, read_truth


def _pose(doc) -> np.ndarray:
    return dq.from_pose([doc["orientation"][c] for c in "wxyz"],
                        [doc["position"][c] for c in "xyz"])


SOLVES = {"detector covariances": [], "estimated": ["--estimate-noise"],
          "corner level": ["--corners"], "corner level + focal": ["--corners", "--refine-focal"]}


def _solve(folder: str, how: str, setup: str):
    argv = ["handeye", "solve", folder, "--local"] + SOLVES[how]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = main(argv)
    if code != 0:
        return None
    with open(os.path.join(folder, "handeye.json")) as f:
        got = json.load(f)
    x_true, _ = read_truth(folder, setup)
    x, cov = _pose(got["x"]), np.array(got["covariance_x"]).reshape(6, 6)
    xi = lie.se3_log(dq.mul(dq.inv(x), x_true))
    d = dq.mul(dq.inv(x), x_true)
    angle = math.degrees(2 * math.atan2(np.linalg.norm(d[1:4]), abs(d[0])))
    dist = 1e3 * float(np.linalg.norm(dq.to_pose(x)[1] - dq.to_pose(x_true)[1]))
    return angle, dist, float(xi @ np.linalg.solve(cov, xi)), 1e3 * np.sqrt(np.diag(cov)[3:]).max()


def main_(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--setup", choices=handeye.SETUPS, default="eye_in_hand")
    args = p.parse_args(argv)
    rows: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for choose in CHOICES:
            for seed in range(args.seeds):
                folder = os.path.join(tmp, f"{choose}_{seed}")
                said = io.StringIO()
                with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(said):
                    code = main(["handeye", "capture", folder, "--setup", args.setup,
                                 "--views", str(args.views), "--choose", choose,
                                 "--seed", str(seed)])
                if code != 0:
                    print(f"capture {choose} seed {seed} failed: "
                          f"{said.getvalue().strip().splitlines()[-1:]}", file=sys.stderr)
                    continue
                for how in SOLVES:
                    rows.setdefault((choose, how), []).append(_solve(folder, how, args.setup))
                print(f"{choose} seed {seed}: done", file=sys.stderr, flush=True)
    print(f"\n{args.setup}, {args.views} views, {args.seeds} seeds (capture --seed 0..)\n")
    print("| views chosen by | noise | X error deg, median / worst | X error mm, median / worst "
          "| mean NEES of X | median largest 1-sigma, mm | refused |")
    print("|---|---|---|---|---|---|---|")
    for (choose, noise), results in rows.items():
        ok = np.array([r for r in results if r is not None]).reshape(-1, 4)
        refused = len(results) - len(ok)
        if not len(ok):
            print(f"| {choose} | {noise} | — | — | — | — | {refused} |")
            continue
        print(f"| {choose} | {noise} | {np.median(ok[:, 0]):.4f} / {ok[:, 0].max():.4f} | "
              f"{np.median(ok[:, 1]):.3f} / {ok[:, 1].max():.3f} | {ok[:, 2].mean():.1f} | "
              f"{np.median(ok[:, 3]):.3f} | {refused} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_())
