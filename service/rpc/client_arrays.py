"""The client's array side: arrays checked and shaped into what a request carries (pose rows, the
pose sets of BlendBatch, a method's enum), and answers read back into arrays (Blend, BlendBatch,
Interpolate, a stream's ``FusedPose``)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose import dq
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc.blending_convert import METHOD_ENUMS
from dqpose.rpc.client_types import StreamAnswer
from dqpose.rpc.fusion_convert import DEFAULT_PROBABILITY, fused_from_msg
from dqpose.rpc.geometry import pose_to_dq, poses_to_flat
from dqpose.rpc.wire import blend_responses_from_wire

# Largest answer per item, to keep answers under the message limit too: BlendBatchResponse item
# = tag, length, BlendResponse {pose (2 + 67), iterations (1 + up to 5), residual (1 + 8)};
# InterpolateResponse item = tag, length, StampedPose {time (1 + 8), pose (2 + 67)}.
BLEND_ANSWER_MAX = 2 + 69 + 6 + 9
SAMPLE_ANSWER_MAX = 2 + 9 + 69


def method_code(method: str) -> int:
    if method not in METHOD_ENUMS:
        raise ValueError(f"method: unknown blending method {method!r}; expected one of "
                         f"{', '.join(METHOD_ENUMS)}")
    return METHOD_ENUMS[method]


def dq_rows(dqs, name: str) -> np.ndarray:
    a = np.asarray(dqs, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 8:
        raise ValueError(f"{name}: expected shape (n, 8), got {a.shape}")
    return a


def flat_to_dqs(flat: np.ndarray) -> np.ndarray:
    return dq.from_pose(flat[:, :4], flat[:, 4:7])


def blend_answer(data: bytes) -> tuple[np.ndarray, int, float]:
    r = pb.BlendResponse.FromString(data)
    return pose_to_dq(r.pose), r.iterations, r.residual


def blend_batch_answer(data: bytes) -> np.ndarray:
    fast = blend_responses_from_wire(data)
    if fast is not None:
        return flat_to_dqs(fast[0])
    r = pb.BlendBatchResponse.FromString(data)   # a layout the fast reader does not take
    return flat_to_dqs(poses_to_flat([x.pose for x in r.responses]))


def interpolate_answer(data: bytes) -> np.ndarray:
    r = pb.InterpolateResponse.FromString(data)
    return flat_to_dqs(poses_to_flat([s.pose for s in r.samples]))


def stream_answer(data: bytes | fpb.FusedPose, probability: float = DEFAULT_PROBABILITY,
                   max_skew: Optional[float] = None,
                   request: Optional[int] = None) -> StreamAnswer:
    """A ``FusedPose`` of a stream (StreamFuse's, Subscribe's), or its bytes, as a
    :class:`StreamAnswer`; ``request``: the caller's number of the request it answers (a
    resumed stream renumbers them), else the message's own."""
    a = fpb.FusedPose.FromString(data) if isinstance(data, bytes) else data
    index = a.request if request is None else request
    if a.HasField("error"):
        return StreamAnswer(index, a.body, a.time, None, np.empty(0, np.int64),
                            a.error.details, a.error.measurement)
    return StreamAnswer(index, a.body, a.time, fused_from_msg(a, probability, max_skew),
                        np.array(a.measurements, dtype=np.int64))


def sets(dqs, weights):
    """``(m, n, 8)`` or a list of ``(n_i, 8)``, and weights ``(m, n)``, a list, or None, to the
    flat arrays of :func:`blend_batch_items_wire`."""
    if isinstance(dqs, np.ndarray) and dqs.dtype != object:
        a = np.asarray(dqs, dtype=np.float64)
        if a.ndim != 3 or a.shape[2] != 8:
            raise ValueError(f"dqs: expected shape (m, n, 8) or a list of (n, 8) arrays, "
                             f"got {a.shape}")
        sets = list(a)
        flat, counts = a.reshape(-1, 8), np.full(len(a), a.shape[1])
    else:
        sets = [dq_rows(d, f"dqs[{i}]") for i, d in enumerate(dqs)]
        flat = np.concatenate(sets) if sets else np.empty((0, 8))
        counts = np.array([len(d) for d in sets], dtype=np.int64)
    m = len(sets)
    if weights is None:
        return flat, counts, np.empty(0), np.zeros(m, np.int64)
    if isinstance(weights, np.ndarray) and weights.dtype != object and weights.ndim == 2:
        ws = list(weights)
    else:
        ws = list(weights)
    if len(ws) != m:
        raise ValueError(f"weights: {len(ws)} weight sets for {m} pose sets")
    ws = [np.empty(0) if w is None else np.asarray(w, dtype=np.float64).ravel() for w in ws]
    w_counts = np.array([len(w) for w in ws], dtype=np.int64)
    return flat, counts, (np.concatenate(ws) if ws else np.empty(0)), w_counts
