"""A StreamFuse run the recording tests share: two moving bodies seen by two sources, its
requests as wire bytes and the answers the Fusion servicer gives them in process."""
from __future__ import annotations

import numpy as np

from dqpose import dq, lie
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.client_types import Batch
from dqpose.rpc.fusion import Fusion
from dqpose.rpc.wire import measurements_wire

BODIES = ("box", "cup")
RATE = 20.0          # answers per body per second of measurement time


def batches(n: int = 40, per: int = 4, seed: int = 5) -> list[Batch]:
    """``n`` requests of ``per`` measurements each, bodies and sources alternating, 10 ms of
    measurement time apart; the bodies turn and move, the noise has a covariance."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = 0.01 * i
        poses, covs, names, bodies, times = [], [], [], [], []
        for j in range(per):
            body = BODIES[j % 2]
            true = lie.se3_exp(np.array([0.3 * t, 0.1, -0.2 * t, 1.0 + t, 0.5 * j, 0.2]))
            S = np.diag([1e-4, 2e-4, 1e-4, 4e-6, 1e-6, 2e-6])
            noisy = dq.mul(true, lie.se3_exp(rng.multivariate_normal(np.zeros(6), S)))
            poses.append(noisy)
            covs.append(S)
            names.append(("cam", "arm")[(i + j) % 2])
            bodies.append(body)
            times.append(t + 0.001 * j)
        out.append(Batch(np.array(poses), np.array(covs), None, names, bodies, np.array(times)))
    return out


def first_request(rate: float = RATE, window: float = 0.2) -> pb.FuseStreamRequest:
    return pb.FuseStreamRequest(
        output_rate=rate, options=pb.FusionOptions(
            window=window, sources=[pb.Source(name="cam"), pb.Source(name="arm")]))


def requests(n: int = 40, rate: float = RATE, window: float = 0.2) -> list[bytes]:
    """The stream's requests as the client sends them: the first with the options."""
    data = [measurements_wire(*b) for b in batches(n)]
    data[0] = first_request(rate, window).SerializeToString() + data[0]
    return data


def answers(data: list[bytes]) -> list[list[pb.FusedPose]]:
    """The answers of each request, from the servicer in process."""
    servicer = Fusion()
    state = None
    out, next_id = [], 0
    for r, d in enumerate(data):
        if state is None:
            state, first, n = servicer.start_stream(d)
        else:
            first, n = servicer.stream_answers_wire(state, d, r, next_id)
        got = [pb.FusedPose.FromString(a) for a in first]     # served as bytes
        out.append(got)
        next_id += n
    return out
