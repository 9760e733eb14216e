"""False alarms of the hand-eye solver on healthy data:
`nice -n 10 .venv/bin/python -m tests.bench.bench_handeye_false_alarms [--seeds N]`.

Every scene of tests/_handeye.py's grid (both geometries, both setups, ``--seeds`` seeds each,
20 poses) at a moderate and a high camera noise, robot noise 0.02° / 0.1 mm, solved with the
noise estimated and given (the generator's true covariances). Nothing in these scenes is wrong,
so every alarm is a false one. Per noise level and mode: the genuine samples the χ² gate
rejected (nominal rate ``1 − outliers._GATE``, 0.1 %), the scenes rescaled (the camera-scale
test, :mod:`dqpose.handeye.scale`), the scenes warned that a fixed part is near the robot
base, and the scenes with any warning.
"""
from __future__ import annotations

import argparse

from dqpose import handeye
from tests import _handeye
from tests.bench._table import markdown

NOISES = ((0.1, 0.5), (0.5, 5.0))      # camera (deg, mm) per axis
ROBOT = (0.02, 0.1)
POSES = 20


def run(seeds: int) -> list[list[str]]:
    rows = []
    for noise in NOISES:
        for mode in ("estimated", "given"):
            rejected = scenes = rescaled = base = warned = 0
            for geometry in _handeye.GEOMETRIES:
                for setup in handeye.SETUPS:
                    for seed in range(seeds):
                        s = _handeye.scene(POSES, setup, geometry, camera_noise=noise,
                                           robot_noise=ROBOT, seed=seed)
                        kw = {} if mode == "estimated" else dict(
                            camera_covariance=s.camera_covariance,
                            robot_covariance=s.robot_covariance)
                        cal = handeye.calibrate(s.base_flange, s.camera_target, setup, **kw)
                        scenes += 1
                        rejected += len(cal.rejected)
                        rescaled += any("scaled by" in w for w in cal.warnings)
                        base += any("from the robot base" in w for w in cal.warnings)
                        warned += bool(cal.warnings)
            n = scenes * POSES
            rows.append([f"{noise[0]}° / {noise[1]} mm", mode, f"{scenes}",
                         f"{rejected} / {n} = {100 * rejected / n:.3f} %",
                         f"{rescaled} = {100 * rescaled / scenes:.2f} %",
                         f"{base}", f"{warned} = {100 * warned / scenes:.1f} %"])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50, help="scenes per geometry and setup")
    args = ap.parse_args()
    print(markdown(["camera noise", "noise", "scenes", "genuine samples rejected",
                    "rescaled", "near-base warning", "any warning"], run(args.seeds)))


if __name__ == "__main__":
    main()
