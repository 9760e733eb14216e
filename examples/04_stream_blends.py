"""04 — Many blends over one stream, and many in one call.

A fusion loop blends a fresh set of measurements many times a second. `BlendStream` keeps one
call open and answers each request in order; `BlendBatch` sends many sets in one message, the
fastest way when the sets are known together. Both give what the in-process core gives.

    .venv/bin/python examples/04_stream_blends.py
"""
import json
import signal
import subprocess
import sys
import time

import numpy as np

from dqpose import dq
from dqpose.rpc.client import Client

rng = np.random.default_rng(4)
true = dq.from_pose([1.0, 0, 0, 0], [0.5, 0.0, 0.2])


def measurements(n=6):
    """n noisy measurements of `true` (1 deg, 2 mm) and their weights."""
    twist = np.concatenate([rng.normal(size=(n, 3)) * np.radians(1) / 2,
                            rng.normal(size=(n, 3)) * 0.002 / 2], axis=1)
    return dq.mul(true, dq.exp(twist)), rng.uniform(0.5, 2.0, n)


sets = [measurements() for _ in range(2000)]
server = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                           "--no-call-log"], stderr=subprocess.PIPE, text=True)
address = json.loads(server.stderr.readline())["address"]
try:
    with Client(address, timeout=30) as c:
        t0 = time.perf_counter()
        streamed = np.array(list(c.blend_stream(sets)))
        dt_stream = time.perf_counter() - t0
        t0 = time.perf_counter()
        batched = c.blend_batch([d for d, _ in sets], [w for _, w in sets])
        dt_batch = time.perf_counter() - t0
finally:
    server.send_signal(signal.SIGTERM)
    server.wait(timeout=30)

local = np.array([dq.dib(d, w) for d, w in sets])
print(f"BlendStream: {len(sets)} blends in {dt_stream * 1e3:.0f} ms "
      f"({len(sets) / dt_stream:.0f}/s from this Python client)")
print(f"BlendBatch:  {len(sets)} blends in {dt_batch * 1e3:.0f} ms ({len(sets) / dt_batch:.0f}/s)")
for name, got in (("stream", streamed), ("batch", batched)):
    err = np.abs(dq.to_matrix(got) - dq.to_matrix(local)).max()
    print(f"{name}: largest difference from the in-process DIB {err:.1e}")
    assert err < 1e-12
