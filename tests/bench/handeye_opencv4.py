"""OpenCV 4.x hand-eye solvers on pose sets, run by the OpenCV 4 environment's own Python:

    tests/bench/_build/opencv4/bin/python tests/bench/handeye_opencv4.py IN.npz OUT.npz

Not part of the dqpose package and imports nothing of it (that environment has only OpenCV 4.x and
NumPy): ``bench_handeye`` creates the environment, writes the inputs already in OpenCV's
conventions and reads the answers back. OpenCV 5.0's wheel lacks both functions (opencv#29565).

IN (4×4 homogeneous matrices, ``k`` problems of ``n`` poses each):
    ``gripper2base``  (k, n, 4, 4)  calibrateHandEye's R_gripper2base / t_gripper2base
    ``target2cam``    (k, n, 4, 4)  calibrateHandEye's R_target2cam / t_target2cam, and
                                    calibrateRobotWorldHandEye's R_world2cam / t_world2cam
    ``base2gripper``  (k, n, 4, 4)  calibrateRobotWorldHandEye's R_base2gripper / t_base2gripper
OUT, per method ``M`` (TSAI, PARK, HORAUD, ANDREFF, DANIILIDIS, SHAH, LI):
    ``M.X``  (k, 4, 4)  calibrateHandEye's cam2gripper; for SHAH and LI, gripper2cam
    ``M.Z``  (k, 4, 4)  SHAH and LI only: base2world
    ``M.seconds`` (k,)  wall time of the one call
    ``M.error``   (k,)  the cv2.error text of a call that raised ("" otherwise; its X/Z are NaN)
and ``version``. What OpenCV returns is passed through untouched (NaN, non-orthogonal R and all):
judging it is the benchmark's job.
"""
import sys
import time

import cv2
import numpy as np

HAND_EYE = ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS")
ROBOT_WORLD = ("SHAH", "LI")


def _homogeneous(R, t):
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = np.ravel(t)
    return M


def _split(T):
    return [m[:3, :3].copy() for m in T], [m[:3, 3:].copy() for m in T]


def solve(gripper2base, target2cam, base2gripper):
    k = len(gripper2base)
    out = {"version": np.array(cv2.__version__)}
    for name in HAND_EYE + ROBOT_WORLD:
        robot_world = name in ROBOT_WORLD
        X = np.full((k, 4, 4), np.nan)
        Z = np.full((k, 4, 4), np.nan)
        seconds = np.zeros(k)
        errors = [""] * k
        for i in range(k):
            R_cam, t_cam = _split(target2cam[i])
            try:
                if robot_world:
                    R_rob, t_rob = _split(base2gripper[i])
                    method = getattr(cv2, "CALIB_ROBOT_WORLD_HAND_EYE_" + name)
                    t0 = time.perf_counter()
                    # method= by keyword: a positional method is ignored in some 4.x (#27625)
                    R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(
                        R_cam, t_cam, R_rob, t_rob, method=method)
                    seconds[i] = time.perf_counter() - t0
                    X[i], Z[i] = _homogeneous(R_gc, t_gc), _homogeneous(R_bw, t_bw)
                else:
                    R_rob, t_rob = _split(gripper2base[i])
                    method = getattr(cv2, "CALIB_HAND_EYE_" + name)
                    t0 = time.perf_counter()
                    R, t = cv2.calibrateHandEye(R_rob, t_rob, R_cam, t_cam, method=method)
                    seconds[i] = time.perf_counter() - t0
                    X[i] = _homogeneous(R, t)
            except cv2.error as e:
                errors[i] = str(e).strip().splitlines()[-1]
        out[name + ".X"] = X
        out[name + ".seconds"] = seconds
        out[name + ".error"] = np.array(errors)
        if robot_world:
            out[name + ".Z"] = Z
    return out


def main(argv):
    if len(argv) != 3:
        sys.exit(f"usage: {argv[0]} IN.npz OUT.npz")
    with np.load(argv[1]) as f:
        out = solve(f["gripper2base"], f["target2cam"], f["base2gripper"])
    np.savez(argv[2], **out)


if __name__ == "__main__":
    main(sys.argv)
