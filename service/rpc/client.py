"""Python client for the dqpose gRPC server: NumPy in, NumPy out, like :mod:`dqpose.dq`.

>>> with Client("127.0.0.1:50051") as c:                      # doctest: +SKIP
...     mean = c.blend(dqs, weights=[1, 3])                   # (8,)
...     fused = c.fuse(dqs, covariances, names=["cam1", "arm"])  # dqpose.fusion.Fused
...     path = c.interpolate([0, 1], dqs[:2], np.linspace(0, 1, 50), mode="tool_linear")
...     cal = c.calibrate(base_flange, camera_target, "eye_in_hand")  # dqpose.handeye.Calibration

Every failed call raises :class:`RpcError` with the status ``code`` and the server's ``details``.
``INVALID_ARGUMENT`` is :class:`InvalidArgument`, also a ``ValueError`` whose text is the server's
message alone (it names the proto field, e.g. ``poses[3].orientation: zero quaternion``), like
the ``ValueError`` of the same input computed locally.

Requests are written as protobuf wire bytes straight from the arrays and sent through the channel
as bytes; BlendBatch answers are read back the same way (:mod:`dqpose.rpc.wire`), so no
message object is made per pose. ``blend_batch`` and ``interpolate`` split what is larger than
the server takes in one message (``max_message_bytes``, ``max_poses``: the server's
``--max-message-bytes`` and ``--max-poses``) into several calls, two in flight at a time.
"""
from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Iterable, Iterator, Optional, Sequence

import grpc
import numpy as np

from dqpose import dq, fusion, handeye, trajectory
from dqpose.rpc import BATCH_POSE_FACTOR, DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_POSES
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc.checks import over_count
from dqpose.rpc.client_arrays import (
    BLEND_ANSWER_MAX,
    SAMPLE_ANSWER_MAX,
    blend_answer,
    blend_batch_answer,
    dq_rows,
    interpolate_answer,
    method_code,
    sets,
    stream_answer,
)
from dqpose.rpc.client_types import (  # noqa: F401 (Batch, Planned, RequestTooLarge: the API)
    Ack,
    ArmState,
    Batch,
    Feedback,
    InvalidArgument,
    Planned,
    Relative,
    RequestTooLarge,
    RpcError,
    StreamAnswer,
    arm_state,
    pose_or_none,
    rpc_error,
    rpc_errors,
    state_name,
)
from dqpose.rpc.client_world import WORLD, WorldCalls
from dqpose.rpc.fusion_convert import (
    DEFAULT_MAX_EXTRAPOLATION,
    DEFAULT_PROBABILITY,
    DEFAULT_WINDOW,
    fused_from_msg,
    measurement_msgs,
    options_msg,
)
from dqpose.rpc.geometry import (
    INTERPOLATION_ENUMS,
    pose_arrays,
    pose_to_dq,
    poses_to_arrays,
    stamped_msgs,
)
from dqpose.rpc.handeye_convert import calibrate_msg, calibration_from_msg
from dqpose.rpc.resume import Resuming, replica_of, retry_config
from dqpose.rpc.routing import MAX_WORLD_NAME, WORLD_HEADER, check_name
from dqpose.rpc.trajectories_convert import (
    PLAN_INTERPOLATION,
    limits_msg,
    plan_msg,
    samples_from_msgs,
)
from dqpose.rpc.wire import (
    blend_batch_items_wire,
    blend_request_wire,
    interpolate_request_wire,
    measurements_wire,
    stamped_poses_wire,
)

DEFAULT_TARGET = "127.0.0.1:50051"
SERVICE = pb.DESCRIPTOR.services_by_name["Blending"].full_name
FUSION = fpb.DESCRIPTOR.services_by_name["Fusion"].full_name
TRAJECTORIES = tpb.DESCRIPTOR.services_by_name["Trajectories"].full_name
HANDEYE = hpb.DESCRIPTOR.services_by_name["HandEye"].full_name
SERVICES = (SERVICE, FUSION, TRAJECTORIES, HANDEYE, WORLD)
_IN_FLIGHT = 2          # calls of one split request outstanding: the next is sent while one is read
if TYPE_CHECKING:   # the stubs' generics: grpc's own classes take no parameters at run time
    _Unary = grpc.UnaryUnaryMultiCallable[bytes, bytes]
    _Streams = grpc.StreamStreamMultiCallable[bytes, bytes]
class Client(WorldCalls):
    """A channel to one server. ``tls=True`` uses the system roots; pass ``root_certificates``
    (PEM bytes) for a private CA and ``certificate_chain``/``private_key`` for mTLS. ``token`` is
    sent as ``authorization: Bearer <token>``. ``timeout`` (seconds) is the deadline of every
    call. ``max_message_bytes`` and ``max_poses`` are the server's limits (its
    ``--max-message-bytes`` and ``--max-poses``; the defaults are the server's): calls are split
    to stay within them. ``world`` names the world every call belongs to (``x-dqpose-world``:
    a load balancer sends all of one world's calls to one replica, docs/deploy.md).
    ``reconnect`` (s): how long a broken stream (its replica gone) keeps being reopened with
    backoff, its unanswered requests sent again (:mod:`dqpose.rpc.resume`); with it, a unary call
    refused before any answer (UNAVAILABLE, CANCELLED) is retried by gRPC's retry policy
    (:func:`~dqpose.rpc.resume.retry_config`). 0: neither, the error is raised at once.
    Poses in and out are ``(..., 8)`` dual quaternions, w first (:mod:`dqpose.dq`'s convention;
    :func:`dqpose.dq.from_pose` takes a quaternion ``[w, x, y, z]``)."""

    def __init__(self, target: str = DEFAULT_TARGET, *, token: str | None = None,
                 tls: bool = False, root_certificates: bytes | None = None,
                 certificate_chain: bytes | None = None, private_key: bytes | None = None,
                 timeout: float = 10.0, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 max_poses: int = DEFAULT_MAX_POSES, options: list | None = None,
                 world: str | None = None, reconnect: float = 0.0):
        if max_message_bytes < 1024 or max_poses < 1:
            raise ValueError(f"max_message_bytes, max_poses: must be at least 1024 and 1, got "
                             f"{max_message_bytes} and {max_poses}")
        if not (isinstance(reconnect, (int, float)) and 0 <= reconnect < float("inf")):
            raise ValueError(f"reconnect: must be a finite number of seconds >= 0, got "
                             f"{reconnect!r}")
        opts = [("grpc.max_receive_message_length", 64 * 1024 * 1024)] + list(options or [])
        if reconnect > 0:
            opts.append(("grpc.service_config", retry_config(reconnect, SERVICES)))
        if tls or root_certificates or certificate_chain:
            creds = grpc.ssl_channel_credentials(root_certificates, private_key, certificate_chain)
            self.channel = grpc.secure_channel(target, creds, options=opts)
        else:
            self.channel = grpc.insecure_channel(target, options=opts)
        # No (de)serializers: requests go out as the bytes wire.py writes, answers come back
        # as bytes for the readers above.
        self._blend: _Unary = self.channel.unary_unary(f"/{SERVICE}/Blend")
        self._blend_batch: _Unary = self.channel.unary_unary(f"/{SERVICE}/BlendBatch")
        self._blend_stream: _Streams = self.channel.stream_stream(f"/{SERVICE}/BlendStream")
        self._interpolate: _Unary = self.channel.unary_unary(f"/{SERVICE}/Interpolate")
        self._fuse: _Unary = self.channel.unary_unary(f"/{FUSION}/Fuse")
        self._stream_fuse: _Streams = self.channel.stream_stream(f"/{FUSION}/StreamFuse")
        self._plan = self.channel.unary_stream(
            f"/{TRAJECTORIES}/Plan", request_serializer=tpb.PlanRequest.SerializeToString,
            response_deserializer=tpb.TrajectorySample.FromString)
        self._smooth: _Unary = self.channel.unary_unary(f"/{TRAJECTORIES}/Smooth")
        self._execute = self.channel.unary_stream(
            f"/{TRAJECTORIES}/Execute", request_serializer=tpb.ExecuteRequest.SerializeToString,
            response_deserializer=tpb.ExecutionFeedback.FromString)
        self._get_arm: _Unary = self.channel.unary_unary(f"/{TRAJECTORIES}/GetArm")
        self._watch_arm = self.channel.unary_stream(
            f"/{TRAJECTORIES}/WatchArm", request_serializer=tpb.GetArmRequest.SerializeToString,
            response_deserializer=tpb.ArmState.FromString)
        self._list_arms: _Unary = self.channel.unary_unary(f"/{TRAJECTORIES}/ListArms")
        self._calibrate: _Unary = self.channel.unary_unary(f"/{HANDEYE}/Calibrate")
        self._world_stubs()
        self.timeout = timeout
        self.max_message_bytes = max_message_bytes
        self.max_poses = max_poses
        metadata = [("authorization", f"Bearer {token}")] if token else []
        if world is not None:
            metadata.append((WORLD_HEADER, check_name("world", world, MAX_WORLD_NAME)))
        self.world = world
        self.metadata = tuple(metadata) or None
        self.reconnect = reconnect
        #: the replica that answered the last call (its x-dqpose-replica; a stream's as its
        #: answers come, and again when it moves), None when no dqpose server answered it
        self.last_replica: Optional[str] = None

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _seen(self, replica: Optional[str]) -> None:
        self.last_replica = replica

    def _call(self, method, request):
        with rpc_errors(self._seen):
            answer, call = method.with_call(request, timeout=self.timeout,
                                            metadata=self.metadata)
        self.last_replica = replica_of(call)
        return answer

    def frames(self) -> list:
        """The world's frames (``ListFrames``), :class:`dqpose.frames.FrameInfo` s: the world
        "", its bodies, static bodies, sources and statics, each with its parent, kind, span of
        measurements, rate and the sources that measured it; an unknown world is NOT_FOUND."""
        from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
        from dqpose.rpc.world_frames import frames_of
        stub = self.channel.unary_unary(
            f"/{WORLD}/ListFrames", request_serializer=wpb.ListFramesRequest.SerializeToString,
            response_deserializer=wpb.FrameList.FromString)
        return frames_of(self._call(stub, wpb.ListFramesRequest()))

    def _split_calls(self, method, requests, field: str, read) -> list:
        """``read`` of each answer to ``requests`` (``(first item, bytes)`` pairs), in order,
        with up to ``_IN_FLIGHT`` calls outstanding; an error names the item in the whole
        input."""
        pending: deque = deque()
        out = []
        try:
            for first, data in requests:
                pending.append((first, method.future(data, timeout=self.timeout,
                                                     metadata=self.metadata)))
                while len(pending) >= _IN_FLIGHT:
                    out.append(self._answer(pending.popleft(), field, read))
            while pending:
                out.append(self._answer(pending.popleft(), field, read))
        finally:
            for _, f in pending:
                f.cancel()
        return out

    def _answer(self, pending, field: str, read):
        first, future = pending
        try:
            answer = future.result()
        except grpc.RpcError as e:
            self.last_replica = replica_of(e)
            raise rpc_error(e, field, first) from None
        self.last_replica = replica_of(future)
        return read(answer)

    def _stamped(self, times, dqs, times_name: str, dqs_name: str, what: str):
        """``(times (n,), poses (n, 8))`` of time-stamped poses to send, one time per pose and
        within the server's count; ValueError naming the argument otherwise."""
        t = np.asarray(times, dtype=np.float64).ravel()
        a = dq_rows(dqs, dqs_name)
        if len(t) != len(a):
            raise ValueError(f"{times_name}: length {len(t)} does not match the number of {what} "
                             f"({len(a)})")
        self._check_count(dqs_name, len(a), what)
        return t, a

    def _check_count(self, field: str, n: int, what: str) -> None:
        """The server's count check (:func:`~dqpose.rpc.checks.over_count`) before sending."""
        text = over_count(field, n, self.max_poses, what)
        if text is not None:
            raise RequestTooLarge(f"{text} (Client max_poses, the server's --max-poses)")

    def blend(self, dqs, weights=None, method: str = "dib", tolerance: float = 0.0,
              max_iterations: int = 0, *, return_info: bool = False):
        """Blend ``(n, 8)`` poses on the server; ``(8,)``, or ``(mean, iterations, residual)``
        with ``return_info``. Zero ``tolerance``/``max_iterations`` mean the server defaults."""
        a = dq_rows(dqs, "dqs")
        self._check_count("dqs", len(a), "poses")
        data = blend_request_wire(*pose_arrays(a), weights, method_code(method), tolerance,
                                  max_iterations)
        mean, iterations, residual = blend_answer(self._call(self._blend, data))
        return (mean, iterations, residual) if return_info else mean

    def blend_stream(self, batches: Iterable[tuple], method: str = "dib") -> Iterator[np.ndarray]:
        """Stream ``(dqs, weights)`` pairs (weights may be None); yields one ``(8,)`` per pair, in
        order. The stream has no deadline. A pair that cannot be sent (wrong shape) ends the
        stream and raises its ``ValueError`` after the answers to the pairs before it."""
        code = method_code(method)
        refused: list[Exception] = []

        def requests():
            try:
                for i, (d, w) in enumerate(batches):
                    yield blend_request_wire(*pose_arrays(dq_rows(d, f"batches[{i}] dqs")), w,
                                             code)
            except Exception as e:   # raised to the caller below, not lost in grpc's thread
                refused.append(e)

        call = self._blend_stream(requests(), metadata=self.metadata)
        with rpc_errors(self._seen):
            for k, data in enumerate(call):
                if k == 0:
                    self.last_replica = replica_of(call)
                yield blend_answer(data)[0]
        if refused:
            raise refused[0]

    def blend_batch(self, dqs, weights=None, method: str = "dib") -> np.ndarray:
        """Blend many independent sets: ``dqs`` ``(m, n, 8)`` or a list of ``(n_i, 8)`` arrays,
        ``weights`` ``(m, n)``, a list (of arrays or None), or None -> ``(m, 8)``. Any number of
        sets: they go in as many calls as the server's limits need."""
        code = method_code(method)
        flat, counts, weights, w_counts = sets(dqs, weights)
        q, t = pose_arrays(flat)
        buf, offsets = blend_batch_items_wire(q, t, counts, weights, w_counts, code)
        cum = np.concatenate([[0], np.cumsum(counts)])
        m = len(counts)
        per_call = max(1, min(self.max_poses, self.max_message_bytes // BLEND_ANSWER_MAX))

        def chunks():
            i = 0
            while True:
                j = min(m, i + per_call,
                        int(np.searchsorted(offsets, offsets[i] + self.max_message_bytes,
                                            "right")) - 1,
                        int(np.searchsorted(cum, cum[i] + BATCH_POSE_FACTOR * self.max_poses,
                                            "right")) - 1)
                j = max(j, min(m, i + 1))      # one set too large alone: the server says so
                yield i, buf[offsets[i]:offsets[j]].tobytes()
                if j >= m:
                    return
                i = j

        parts = self._split_calls(self._blend_batch, chunks(), "requests", blend_batch_answer)
        return np.concatenate(parts).reshape(-1, 8)

    def interpolate(self, times_k, dqs_k, times, mode: str = "screw") -> np.ndarray:
        """Poses ``(N, 8)`` at ``times`` between keyframes ``dqs_k`` ``(K, 8)`` at ``times_k``;
        ``mode`` is ``"screw"`` or ``"tool_linear"`` (see :mod:`dqpose.interpolate`). Any number
        of times: they go in as many calls as the server's limits need, each with the keyframes."""
        if mode not in INTERPOLATION_ENUMS:
            raise ValueError(f"mode: unknown interpolation {mode!r}; expected one of "
                             f"{', '.join(INTERPOLATION_ENUMS)}")
        tk, a = self._stamped(times_k, dqs_k, "times_k", "dqs_k", "keyframes")
        keyframes = stamped_poses_wire(tk, *pose_arrays(a))
        times = np.asarray(times, dtype=np.float64).ravel()
        room = self.max_message_bytes - len(keyframes) - 16     # 16: the times field's header
        per_call = min(self.max_poses, room // 8, self.max_message_bytes // SAMPLE_ANSWER_MAX)
        if per_call < 1:
            raise RequestTooLarge(f"dqs_k: {len(a)} keyframes fill the server's message limit "
                                  f"of {self.max_message_bytes} bytes (Client max_message_bytes)")
        code = INTERPOLATION_ENUMS[mode]
        chunks = ((i, interpolate_request_wire(keyframes, times[i:i + per_call], code))
                  for i in range(0, max(len(times), 1), per_call))
        parts = self._split_calls(self._interpolate, chunks, "times", interpolate_answer)
        return np.concatenate(parts).reshape(-1, 8)

    def fuse(self, poses, covariances=None, *, weights=None,
             names: Optional[Sequence[str]] = None,
             sources: Optional[Iterable[fusion.Source]] = None, robust: bool = False,
             probability: float = DEFAULT_PROBABILITY, body: str = "", times=None,
             time: Optional[float] = None, max_skew: Optional[float] = None,
             max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION,
             twist_covariance=None, acceleration_psd=None) -> fusion.Fused:
        """:func:`dqpose.fusion.fuse` on the server (same arguments, same result), for one
        ``body``. The server always fuses with times (``times`` None: all 0): measurements
        taken at one instant give the static fusion, exactly; ``time`` None (or 0) is the
        newest instant a measurement was taken."""
        n = len(np.asarray(poses))
        request = fpb.FuseRequest(
            measurements=measurement_msgs(poses, covariances, weights, names, [body] * n, times),
            options=options_msg(robust, time or 0.0, sources, probability, max_skew,
                                max_extrapolation, twist_covariance=twist_covariance,
                                acceleration_psd=acceleration_psd))
        return fused_from_msg(self.fuse_request(request), probability, max_skew)

    def fuse_request(self, request: fpb.FuseRequest) -> fpb.FusedPose:
        """Fuse as messages, for a caller that holds a ``FuseRequest`` (``dqpose fuse``)."""
        return fpb.FusedPose.FromString(self._call(self._fuse, request.SerializeToString()))

    def stream_fuse(self, batches: Iterable, *, sources: Optional[Iterable[fusion.Source]] = None,
                    robust: bool = False, probability: float = DEFAULT_PROBABILITY,
                    output_rate: float = 0.0, window: float = DEFAULT_WINDOW,
                    max_skew: Optional[float] = None,
                    max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION,
                    twist_covariance=None,
                    acceleration_psd=None) -> Iterator[StreamAnswer]:
        """Stream :class:`Batch` es (measurements of any bodies each) to ``StreamFuse``; yields
        :class:`StreamAnswer` s as they come: fused poses of each body over its sliding
        ``window`` (seconds) at its ticks ``(k + phase) / output_rate`` of the measurements'
        time, ``phase`` in [0, 1) fixed by the body's name (0: one
        per body after each batch that carried it; see the proto), and error entries for
        measurements the server could not use (the stream goes on). The stream has no
        deadline; options the server refuses end it with :class:`InvalidArgument`. A batch that
        cannot be sent (wrong shape) ends the stream and raises its ``ValueError`` after the
        answers before it."""
        first = fpb.FuseStreamRequest(
            options=options_msg(robust, 0.0, sources, probability, max_skew, max_extrapolation,
                                window, twist_covariance, acceleration_psd),
            output_rate=output_rate)

        def requests():
            for i, b in enumerate(batches):
                b = b if isinstance(b, Batch) else Batch(*b)
                try:
                    yield measurements_wire(*b)
                except ValueError as e:
                    raise ValueError(f"batches[{i}].{e}") from None

        # a message's fields in any order parse as one: the options, then a batch
        stream = Resuming(self._stream_fuse, requests(), first.SerializeToString(),
                          lambda data: fpb.FusedPose.FromString(data).request,
                          metadata=self.metadata, reconnect=self.reconnect, seen=self._seen)
        with rpc_errors():
            for index, data in stream.answers():
                yield stream_answer(data, probability, max_skew, index)
        if stream.failed:
            raise stream.failed[0]

    def plan(self, waypoints, limits, rate_hz: float, interpolation: str = PLAN_INTERPOLATION, *,
             start_velocity=None, frames: Optional[Sequence[str]] = None) -> Planned:
        """:func:`dqpose.trajectory.plan` on the server, sampled at ``rate_hz``: the samples
        (first at 0 on the first waypoint, last on the last one) with the plan's duration and
        segments. ``waypoints``: :class:`~dqpose.trajectory.Waypoint` s or ``(8,)`` poses. The
        stream has no deadline (a long plan is many samples). ``frames``: per waypoint the body
        of the server's world its pose is given in ("" the base; see ``Waypoint.frame``)."""
        request = plan_msg(waypoints, limits, rate_hz, interpolation, start_velocity, frames)
        call = self._plan(request, metadata=self.metadata)
        with rpc_errors(self._seen):
            msgs = list(call)
        self.last_replica = replica_of(call)
        info = msgs[0].plan
        segments = tuple(trajectory.Segment(s.start, s.duration, s.binding)
                         for s in info.segments)
        resolved = tuple((r.index, r.frame, r.time, pose_to_dq(r.pose),
                          np.array(r.covariance, dtype=np.float64).reshape(6, 6))
                         for r in info.resolved)
        return Planned(*samples_from_msgs(msgs), duration=info.duration, segments=segments,
                       resolved=resolved)

    def smooth(self, times, poses, limits, smoothing: float = 1.0,
               rate_hz: float = 0.0, free_ends: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """:func:`dqpose.smoothing.smooth` on the server: ``(times (M,), poses (M, 8))``."""
        times, a = self._stamped(times, poses, "times", "poses", "poses")
        request = tpb.SmoothRequest(poses=stamped_msgs(times, a), limits=limits_msg(limits),
                                    smoothing=smoothing, rate_hz=rate_hz,
                                    free_ends=bool(free_ends))
        answer = tpb.SmoothResponse.FromString(self._call(self._smooth,
                                                          request.SerializeToString()))
        q, t = poses_to_arrays([p.pose for p in answer.samples])
        out = dq.from_pose(q, t) if len(answer.samples) else np.zeros((0, 8))
        return np.array([p.time for p in answer.samples], dtype=np.float64), out

    def execute(self, arm: str, waypoints, limits, interpolation: str = PLAN_INTERPOLATION, *,
                from_current: bool = False) -> Iterator[Feedback]:
        """Runs a plan on the server's arm ``arm`` (see ``dqpose serve --arm``), yielding
        :class:`Feedback` as the server streams it: the arm's state, commanded and actual poses.
        ``from_current``: the plan starts at the arm's actual pose (it must be at rest) and
        ``waypoints`` follow it; else ``waypoints[0]`` must be where the arm is. A run that
        ends in any state but FINISHED yields its last record, then raises :class:`RpcError`
        (ABORTED, UNAVAILABLE, ...; see the proto) whose ``feedback`` is that record. Closing
        the iterator (or the client going away) stops the arm within one period."""
        request = tpb.ExecuteRequest(arm=arm, plan=plan_msg(waypoints, limits, 0.0,
                                                            interpolation),
                                     from_current=from_current)
        call = self._execute(request, metadata=self.metadata)
        last = None
        try:
            for m in call:
                if last is None:
                    self.last_replica = replica_of(call)
                last = Feedback(m.time, pose_or_none(m, "commanded"), pose_or_none(m, "actual"),
                                state_name(m.state), m.message)
                yield last
        except grpc.RpcError as e:
            self.last_replica = replica_of(e)
            err = rpc_error(e)
            err.feedback = last
            raise err from None
        finally:
            call.cancel()

    def get_arm(self, arm: str) -> ArmState:
        """The server's arm ``arm`` now: where it is, how fast it moves, its run's state, its
        limits and faults (:class:`ArmState`)."""
        answer = tpb.ArmState.FromString(self._call(
            self._get_arm, tpb.GetArmRequest(arm=arm).SerializeToString()))
        return arm_state(answer)

    def watch_arm(self, arm: str, rate_hz: float = 0.0, *,
                  timeout: Optional[float] = None) -> Iterator[ArmState]:
        """The server's arm ``arm`` as :meth:`get_arm` gives it, ``rate_hz`` times a second (0:
        the server's default, 50) until the iterator is closed (which cancels the call) or
        ``timeout`` s have passed; the stream has no deadline unless ``timeout``."""
        call = self._watch_arm(tpb.GetArmRequest(arm=arm, rate_hz=rate_hz), timeout=timeout,
                               metadata=self.metadata)
        try:
            with rpc_errors(self._seen):
                for k, m in enumerate(call):
                    if k == 0:
                        self.last_replica = replica_of(call)
                    yield arm_state(m)
        finally:
            call.cancel()

    def list_arms(self) -> list[ArmState]:
        """Every arm of the server, in name order."""
        answer = tpb.ListArmsResponse.FromString(self._call(
            self._list_arms, tpb.ListArmsRequest().SerializeToString()))
        return [arm_state(m) for m in answer.arms]

    def calibrate(self, base_flange, camera_target, setup: str = handeye.EYE_IN_HAND, *,
                  robust: bool = True, camera_covariance=None, robot_covariance=None,
                  corners=None, refine_focal: bool = False,
                  pixel_sigma: Optional[float] = None) -> handeye.Calibration:
        """:func:`dqpose.handeye.calibrate` on the server (same arguments, same result but for
        the noise model's matrices): ``base_flange`` ``(n, 8)`` ``T_base_flange``,
        ``camera_target`` ``(n, 8)`` ``T_camera_target``; ``corners`` as the domain takes them,
        with one camera matrix for all views. Unusable data is an :class:`RpcError` with code
        ``FAILED_PRECONDITION`` and the solver's reason, naming the pairs."""
        self._check_count("base_flange", len(np.asarray(base_flange)), "pose pairs")
        request = calibrate_msg(base_flange, camera_target, setup, robust, camera_covariance,
                                robot_covariance, corners, refine_focal, pixel_sigma)
        answer = hpb.CalibrateResponse.FromString(self._call(self._calibrate,
                                                             request.SerializeToString()))
        return calibration_from_msg(answer, setup)

    def health(self, service: str = "") -> str:
        """The health status name (``"SERVING"``, ``"NOT_SERVING"``, ...)."""
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        with rpc_errors(self._seen):
            r, call = health_pb2_grpc.HealthStub(self.channel).Check.with_call(
                health_pb2.HealthCheckRequest(service=service), timeout=self.timeout)
        self.last_replica = replica_of(call)
        return health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)
