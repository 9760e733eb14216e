"""08 — Hand-eye calibration through the server, from rendered and detected board images.

A camera on a robot's flange (eye-in-hand) looks at a ChArUco board on the table from 12 robot
poses. Each view is rendered by the simulated camera and detected by the real detector
(`dqpose.drivers.camera.CharucoCamera`), and the flange poses and detections go to the HandEye
service, each view weighed by its detector covariance. The answer comes with a covariance: the
true camera mount lies within it. Then the same service refuses a data set it cannot solve (every
rotation about one axis) and says why, rather than answering. `dqpose handeye capture|solve` is
the same on the UR simulator, from the shell.

    .venv/bin/python examples/08_hand_eye_calibration.py
"""
import json
import math
import signal
import subprocess
import sys

import numpy as np

from dqpose import dq, lie
from dqpose.drivers.camera import BoardSpec, CharucoCamera
from dqpose.drivers.rotvec import pose_from_rotvec
from dqpose.drivers.sim.camera import DEFAULT_INTRINSICS, BoardRenderer, random_view
from dqpose.rpc.client import Client, RpcError

board = BoardSpec()                                             # 7x5, 40 mm squares
X = pose_from_rotvec([0.06, -0.02, 0.04, 0.08, -0.12, 1.4])     # T_flange_camera: the unknown
Z = pose_from_rotvec([0.40, 0.10, 0.0, math.pi, 0.0, 0.0])      # T_base_target: board face up
renderer, camera = BoardRenderer(board), CharucoCamera(DEFAULT_INTRINSICS, board)
rng = np.random.default_rng(8)

flanges, detections = [], []
while len(detections) < 12:
    view = random_view(rng, board, max_tilt_deg=40, max_roll_deg=60)   # T_camera_target
    flange = dq.mul(dq.mul(Z, dq.inv(view)), dq.inv(X))               # where the robot goes
    d = camera.detect(renderer.render(view, blur=0.6, noise=2.0, rng=rng))
    if d.ok:
        flanges.append(flange)
        detections.append(d)
base_flange = np.array(flanges)
camera_target = np.array([d.pose for d in detections])
print(f"{len(detections)} views detected")

server = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0"],
                          stderr=subprocess.PIPE, text=True)
address = json.loads(server.stderr.readline())["address"]
try:
    with Client(address, timeout=10) as c:
        cal = c.calibrate(base_flange, camera_target, "eye_in_hand",
                          camera_covariance=np.array([d.covariance for d in detections]))
        xi = lie.se3_log(dq.mul(dq.inv(cal.x), X))               # X = cal.x * Exp(xi)
        nees = float(xi @ np.linalg.solve(cal.covariance_x, xi))
        sigma = np.sqrt(np.diag(cal.covariance_x))
        print(f"X off by {math.degrees(np.linalg.norm(xi[:3])):.4f} deg and "
              f"{1e3 * np.linalg.norm(xi[3:]):.3f} mm; 1 sigma up to "
              f"{math.degrees(sigma[:3].max()):.4f} deg / {1e3 * sigma[3:].max():.3f} mm; "
              f"NEES {nees:.2f} (6 expected)")
        assert nees < 22.46                      # the chi-squared(6) bound at 99.9 %
        print("warnings:", list(cal.warnings) or "none")

        # Turning about the tool's z axis only: X's translation along it cannot be known.
        turns = np.array([dq.mul(flanges[0], pose_from_rotvec([0, 0, 0, 0, 0, a]))
                          for a in np.radians([-60, -30, 0, 30, 60])])
        seen = np.array([dq.mul(dq.mul(dq.inv(X), dq.inv(f)), Z) for f in turns])
        try:
            c.calibrate(turns, seen, "eye_in_hand")
            raise AssertionError("a degenerate data set was solved")
        except RpcError as e:
            print(f"refused: {e.code.name}: {e.details}")
            assert e.code.name == "FAILED_PRECONDITION" and "parallel" in e.details
finally:
    server.send_signal(signal.SIGTERM)
    server.wait(timeout=30)
