"""``dqpose fuse --local`` computes with the domain in this process: no gRPC is imported, and the
answer is :func:`dqpose.fusion.fuse`'s."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from dqpose import dq, fusion

PROBE = """
import sys
from dqpose.cli import main
code = main(["fuse", "--local", "--format", "json", sys.argv[1]])
print("grpc imported" if "grpc" in sys.modules else "no grpc", file=sys.stderr)
sys.exit(code)
"""


def test_local_fuse_imports_no_grpc_and_answers_the_domains_fuse(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("source,time,x,y,z,qw,qx,qy,qz,weight\n"
                    "a,0,0.10,0,0,1,0,0,0,1\nb,0,0.12,0,0.01,1,0,0,0,3\n")
    res = subprocess.run([sys.executable, "-c", PROBE, str(path)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip().splitlines()[-1] == "no grpc"
    doc = json.loads(res.stdout)
    want = fusion.fuse(dq.from_pose(np.tile([1.0, 0, 0, 0], (2, 1)),
                                    [[0.10, 0, 0], [0.12, 0, 0.01]]), weights=[1.0, 3.0])
    p, o = doc["pose"]["position"], doc["pose"]["orientation"]
    got = dq.from_pose([o.get(k, 0.0) for k in "wxyz"], [p.get(k, 0.0) for k in "xyz"])
    np.testing.assert_allclose(got * np.sign(got[0] * want.mean[0]), want.mean, atol=1e-12)
    np.testing.assert_allclose(np.reshape(doc["covariance"], (6, 6)), want.covariance,
                               atol=1e-15)
