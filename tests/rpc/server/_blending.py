"""Shared by the server's tests: its limits, Blending requests and poses as messages."""
from __future__ import annotations

import os

import grpc
import numpy as np

from dqpose import dq
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo

MAX_POSES = 200
MAX_BYTES = 64 * 1024
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))


def random_poses(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q, rng.uniform(-1, 1, size=(n, 3))


def pose_msg(q, t):
    return geo.Pose(position=geo.Vector3(x=t[0], y=t[1], z=t[2]),
                    orientation=geo.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))


def msg_to_dq(p):
    o, t = p.orientation, p.position
    return dq.from_pose([o.w, o.x, o.y, o.z], [t.x, t.y, t.z])


def same_pose(a, b, atol=1e-9):
    s = np.sign(np.dot(a[:4], b[:4]))
    np.testing.assert_allclose(s * a, b, atol=atol)


def blend_req(q, t, weights=(), method=pb.METHOD_UNSPECIFIED, **kw):
    return pb.BlendRequest(poses=[pose_msg(a, b) for a, b in zip(q, t)], weights=list(weights),
                           method=method, **kw)


def _poses(n, fix=None):
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    t = np.zeros((n, 3))
    for (i, what), v in (fix or {}).items():
        (q if what == "q" else t)[i] = v
    return q, t


NAN = float("nan")


class socket_free_port:
    def __enter__(self):
        import socket

        with socket.socket() as so:
            so.bind(("127.0.0.1", 0))
            return so.getsockname()[1]

    def __exit__(self, *exc):
        pass


def _blend_ok(channel, metadata=None):
    return pb_grpc.BlendingStub(channel).Blend(blend_req(*_poses(2)), timeout=5, metadata=metadata)


def _code(fn):
    try:
        fn()
    except grpc.RpcError as e:
        return e.code(), e.details()
    return grpc.StatusCode.OK, ""
