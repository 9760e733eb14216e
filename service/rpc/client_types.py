"""What the Python client (:mod:`dqpose.rpc.client`) returns and raises: the typed records of
its answers, read from the server's messages, and its errors."""
from __future__ import annotations

import contextlib
import re
from typing import Iterator, NamedTuple, Optional, Sequence

import grpc
import numpy as np

from dqpose import dq, fusion, lie, trajectory
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc.geometry import pose_to_dq
from dqpose.rpc.resume import replica_of


class Planned(NamedTuple):
    """What :meth:`Client.plan` returns: the samples and the plan's duration and segments."""
    time: np.ndarray              # (N,)
    pose: np.ndarray              # (N, 8)
    linear_velocity: np.ndarray   # (N, 3) tool point, base frame, m/s
    angular_velocity: np.ndarray  # (N, 3) tool, base frame, rad/s
    duration: float
    segments: tuple[trajectory.Segment, ...]
    # per waypoint given in a body's frame: (index, frame, time, T_base_tool (8,), covariance
    # (6, 6)) as the server resolved it
    resolved: tuple = ()


class Feedback(NamedTuple):
    """One ``ExecutionFeedback`` of :meth:`Client.execute`."""
    time: float
    commanded: Optional[np.ndarray]
    actual: Optional[np.ndarray]
    state: str          # "WORKING", "FINISHED", "LIMITED", "STALLED", "STOPPED", ...
    message: str


class ArmState(NamedTuple):
    """What :meth:`Client.get_arm` and :meth:`Client.list_arms` return for one arm."""
    arm: str
    pose: Optional[np.ndarray]        # (8,) actual T_base_tool; None when it cannot be read
    linear_velocity: np.ndarray       # (3,) tool point, base frame, m/s
    angular_velocity: np.ndarray      # (3,) tool, base frame, rad/s
    state: str          # of its current or last run ("WORKING", "FINISHED", ...); "" before any
    limits: trajectory.Limits         # the arm's own, in the planner's names (jerk 0: none)
    faults: tuple                     # why it cannot move now; empty when healthy
    busy: bool                        # running a plan, or braking from one


def state_name(code: int) -> str:
    return "" if code == 0 else tpb.ExecutionState.Name(code).removeprefix("EXECUTION_")


def arm_state(m) -> ArmState:
    v, w = m.linear_velocity, m.angular_velocity
    return ArmState(m.arm, pose_or_none(m, "pose"), np.array([v.x, v.y, v.z]),
                    np.array([w.x, w.y, w.z]), state_name(m.state),
                    trajectory.Limits(**{f: getattr(m.limits, f)
                                         for f in trajectory.LIMIT_FIELDS}),
                    tuple(m.faults), m.busy)


def pose_or_none(msg, field: str) -> Optional[np.ndarray]:
    if not msg.HasField(field):
        return None
    return pose_to_dq(getattr(msg, field))


class RpcError(Exception):
    """A call the server (or the channel) failed: ``code`` is the ``grpc.StatusCode``,
    ``details`` the message; ``feedback``, for :meth:`Client.execute`, the run's last record
    (how it ended), if one came."""

    feedback: Optional["Feedback"] = None

    def __init__(self, code: grpc.StatusCode, details: str):
        super().__init__(f"{code.name}: {details}")
        self.code = code
        self.details = details


class InvalidArgument(RpcError, ValueError):
    """``INVALID_ARGUMENT``: the input is wrong; the text is the server's message naming it."""

    def __str__(self) -> str:
        return self.details


class Batch(NamedTuple):
    """One ``StreamFuse`` request's measurements (a plain tuple in this order works too):
    ``poses`` ``(n, 8)`` (``T_frame_body``), ``covariances`` ``(n, 6, 6)`` or ``weights`` ``(n,)``
    or neither (identity), and per measurement its source ``names``, ``bodies`` and ``times``."""
    poses: np.ndarray
    covariances: Optional[np.ndarray] = None
    weights: Optional[np.ndarray] = None
    names: Optional[Sequence[str]] = None
    bodies: Optional[Sequence[str]] = None
    times: Optional[np.ndarray] = None


class StreamAnswer(NamedTuple):
    """One ``StreamFuse`` answer, after request ``request``: the fused pose of ``body`` at
    ``time`` (``fused``; its per-measurement arrays index ``measurements``, the stream-wide
    numbers of the fused measurements), or an error entry: ``fused`` None, ``error`` the
    server's message naming ``measurement`` of that request (-1: the request itself)."""
    request: int
    body: str
    time: float
    fused: Optional[fusion.Fused]
    measurements: np.ndarray
    error: Optional[str] = None
    measurement: int = -1


class Ack(NamedTuple):
    """One ``PublishAck``: every request of the producer up to sequence ``acked_through`` is in
    the world; ``errors`` ``(request, measurement, details)`` name what was not used
    (``measurement`` -1: the request itself, e.g. a repeated sequence)."""
    acked_through: int
    errors: tuple[tuple[int, int, str], ...] = ()


class Relative(NamedTuple):
    """``Lookup``'s answer: ``pose`` ``T_target_source`` ``(8,)`` at ``time``, its ``covariance``
    ``(6, 6)`` (rotation first, right perturbation); the pose's other forms and its one-sigma
    figures (:func:`dqpose.lie.cov_sigmas`) as properties."""
    pose: np.ndarray
    covariance: np.ndarray
    time: float

    @property
    def dq(self) -> np.ndarray:
        """The pose as a dual quaternion ``(8,)`` (``pose`` itself)."""
        return self.pose

    @property
    def position(self) -> np.ndarray:
        """The translation ``(3,)``, m."""
        return dq.to_pose(self.pose)[1]

    @property
    def quaternion(self) -> np.ndarray:
        """The rotation ``(4,)``, w first."""
        return dq.to_pose(self.pose)[0]

    @property
    def matrix(self) -> np.ndarray:
        """The homogeneous transform ``(4, 4)``."""
        return dq.to_matrix(self.pose)

    @property
    def sigma_position(self) -> float:
        """One sigma of position along the least certain direction, m."""
        return float(lie.cov_sigmas(self.covariance)[1])

    @property
    def sigma_rotation(self) -> float:
        """One sigma of rotation about the least certain axis, rad."""
        return float(lie.cov_sigmas(self.covariance)[0])


class RequestTooLarge(ValueError):
    """An input the client cannot split under the server's limits (e.g. more keyframes than
    ``max_poses``)."""


def rpc_error(e: grpc.RpcError, field: str = "", offset: int = 0) -> RpcError:
    """Ours from grpc's; ``field[i]`` in the message is renumbered by ``offset`` (the position of
    a split call's first item in the whole input)."""
    code = e.code() if callable(getattr(e, "code", None)) else grpc.StatusCode.UNKNOWN
    details = (e.details() if callable(getattr(e, "details", None)) else None) or str(e)
    if field and offset:
        details = re.sub(rf"^{re.escape(field)}\[(\d+)\]",
                         lambda m: f"{field}[{int(m.group(1)) + offset}]", details)
    cls = InvalidArgument if code == grpc.StatusCode.INVALID_ARGUMENT else RpcError
    return cls(code, details)


@contextlib.contextmanager
def rpc_errors(seen=None) -> Iterator[None]:
    """grpc's errors raised inside as ours (:func:`rpc_error`); ``seen(replica)`` told first
    which replica refused (``dqpose.rpc.resume.replica_of``), when given."""
    try:
        yield
    except grpc.RpcError as e:
        if seen is not None:
            seen(replica_of(e))
        raise rpc_error(e) from None
