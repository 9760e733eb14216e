"""03 — Start the gRPC server and call it from Python.

Starts `dqpose serve` on a free port (as `make run` does on 50051), blends and interpolates
through `dqpose.rpc.client.Client`, shows the error a bad request gets, then stops the server with
SIGTERM, which drains calls in flight and exits 0.

    .venv/bin/python examples/03_server_and_client.py
"""
import json
import signal
import subprocess
import sys

import numpy as np

from dqpose import dq
from dqpose.rpc.client import Client

server = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0"],
                          stderr=subprocess.PIPE, text=True)
address = json.loads(server.stderr.readline())["address"]   # the first log line says where
print("server on", address)
try:
    rng = np.random.default_rng(3)
    q = rng.normal(size=(5, 4))
    poses = dq.from_pose(q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(-1, 1, (5, 3)))
    with Client(address, timeout=5) as c:
        print("health:", c.health())
        mean, steps, residual = c.blend(poses, method="dib", return_info=True)
        print(f"Blend: {steps} DIB steps, residual {residual:.1e}")
        assert np.allclose(mean, dq.dib(poses), atol=1e-12)      # the same core, over the wire
        path = c.interpolate([0.0, 1.0], poses[:2], np.linspace(0, 1, 5))
        # The same poses as the keyframes (a sample may come back as -q: the same rotation).
        ends_ok = np.allclose(dq.to_matrix(path[[0, -1]]), dq.to_matrix(poses[:2]), atol=1e-12)
        print("Interpolate: 5 poses, the first and last are the keyframes:", ends_ok)
        assert ends_ok
        bad = poses.copy()
        bad[2, :4] = 0.0                                          # a zero quaternion
        try:
            c.blend(bad)
        except ValueError as e:                                   # INVALID_ARGUMENT, named
            print("bad request:", e)
            assert "poses[2].orientation" in str(e)
finally:
    server.send_signal(signal.SIGTERM)
    code = server.wait(timeout=30)
print("server exit code after SIGTERM:", code)
assert code == 0
