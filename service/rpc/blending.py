"""The ``dqpose.v1.Blending`` service: Blend, BlendStream and BlendBatch answered bytes to bytes
by the C fast path (``service/csrc/wire.c``) when a request is plain and valid, else through
protobuf and :mod:`dqpose.dq`, whose errors name the proto field; and Interpolate."""
from __future__ import annotations

import asyncio
import math
from typing import Any

import grpc
import numpy as np
from google.protobuf.message import DecodeError

from dqpose import dq, limits
from dqpose.errors import FieldError, rename
from dqpose.interpolate import interpolate
from dqpose.rpc import BATCH_POSE_FACTOR, DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_POSES
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc.blending_convert import METHOD_NAMES
from dqpose.rpc.calls import Calls, fit, readable, refusal
from dqpose.rpc.checks import check_count, field_named
from dqpose.rpc.geometry import (
    arrays_to_stamped,
    dq_to_pose,
    flat_to_dqs,
    interpolation_named,
    poses_to_flat,
    stamped_to_arrays,
)
from dqpose.rpc.peers import ReadAhead, read_all
from dqpose.rpc.wire import blend_batch_wire, blend_wire, decode_blend_request

DEFAULT_TOLERANCE = 1e-12
DEFAULT_MAX_ITERATIONS = 100
STREAM_READ_AHEAD = 64         # requests a BlendStream reads ahead of its replies
STREAM_READ_AHEAD_BYTES = 1 << 20   # and their bytes (a request may be max_message_bytes)
#: Interpolate's mode for INTERPOLATION_UNSPECIFIED (blending.proto says so)
INTERPOLATE_INTERPOLATION = "screw"


class Blending(pb_grpc.BlendingServicer):
    """The ``dqpose.v1.Blending`` service. ``blend``/``interpolate_request`` are plain functions of
    a request (no gRPC context), so the benchmark can time the adapter without the transport."""

    NAME = pb.DESCRIPTOR.services_by_name["Blending"].full_name

    def __init__(self, cfg=None, calls: Calls | None = None):
        """``cfg`` is the server's ``ServerConfig`` (its defaults when None)."""
        self.max_poses = cfg.max_poses if cfg is not None else DEFAULT_MAX_POSES
        # gRPC refuses to send more (server_options); the *_wire answers are checked against it.
        self.max_message_bytes = (cfg.max_message_bytes if cfg is not None
                                  else DEFAULT_MAX_MESSAGE_BYTES)
        self.calls = calls or Calls()
        self.limits = cfg.limits if cfg is not None else limits.DEFAULT

    # -- request -> response, no transport

    def blend(self, request: pb.BlendRequest) -> pb.BlendResponse:
        return self._blend(poses_to_flat(request.poses), request.weights, request.method,
                           request.tolerance, request.max_iterations)

    def blend_bytes(self, data: bytes) -> pb.BlendResponse:
        """The hot path: a serialized BlendRequest decoded in C, no protobuf objects per pose."""
        fields = decode_blend_request(data)
        if fields is None:
            try:
                request = pb.BlendRequest.FromString(data)
            except DecodeError:
                raise FieldError("request: not a valid dqpose.v1.BlendRequest message") from None
            return self.blend(request)
        return self._blend(*fields)

    def blend_wire(self, data: bytes) -> bytes:
        """What Blend and BlendStream serve: ``BlendResponse`` bytes for request bytes, from the
        C fast path when the request is plain and valid, else from :meth:`blend_bytes` (which
        raises the FieldError naming the problem). Both give identical bytes."""
        out = blend_wire(data, self.max_poses, DEFAULT_TOLERANCE, DEFAULT_MAX_ITERATIONS,
                         self.limits.max_iterations)
        if out is None:
            out = self.blend_bytes(data).SerializeToString()
        return fit(out, self.max_message_bytes, "request", 1, "request")

    def _blend(self, flat, weights, method_code: int, tolerance: float,
               max_iterations: int) -> pb.BlendResponse:
        check_count("poses", len(flat), self.max_poses, "poses", empty=True)
        dqs = flat_to_dqs(flat, "poses")
        weights = np.asarray(weights, dtype=np.float64) if len(weights) else None
        method = METHOD_NAMES.get(method_code)
        if method is None:
            raise FieldError(f"method: unknown Method value {method_code}")
        tol = tolerance or DEFAULT_TOLERANCE
        if not (math.isfinite(tol) and tol > 0):
            raise FieldError(f"tolerance: must be finite and >= 0 (0 means {DEFAULT_TOLERANCE}), "
                             f"got {tolerance!r}")
        max_iter = max_iterations or DEFAULT_MAX_ITERATIONS
        if max_iter > self.limits.max_iterations:
            raise limits.over("max_iterations", f"{max_iter}", self.limits, "max_iterations")
        iterations, residual = 0, 0.0
        try:
            if method == "dib":
                mean, iterations, residual = dq.dib(dqs, weights, tol, max_iter, return_info=True)
                iterations, residual = int(iterations), float(residual)
            else:
                mean = dq.blend(dqs, weights, method, tol, max_iter)
        except ValueError as e:
            raise field_named(rename(e, {"dqs": "poses{}", "weights": "weights{}"}),
                              ("poses", "weights", "method", "tolerance", "max_iterations"),
                              "poses") from None
        if not (np.isfinite(mean).all() and math.isfinite(residual)):
            # Never hand a NaN to a robot: say which input made the mean undefined.
            raise FieldError(f"poses: the {method} blend of these poses is undefined "
                             f"(rotations cancel out); use other weights or method DIB")
        response = pb.BlendResponse(iterations=iterations, residual=residual)
        dq_to_pose(mean, response.pose)
        return response

    def blend_batch_wire(self, data: bytes) -> tuple[bytes, int]:
        """What BlendBatch serves: ``(BlendBatchResponse bytes, number of requests)``, from C
        when every request is plain and valid, else from :meth:`blend_batch` (which raises the
        FieldError naming the request and the problem)."""
        out = blend_batch_wire(data, self.max_poses, BATCH_POSE_FACTOR * self.max_poses,
                               self.max_poses, DEFAULT_TOLERANCE, DEFAULT_MAX_ITERATIONS,
                               self.limits.max_iterations)
        if out is None:
            try:
                request = pb.BlendBatchRequest.FromString(data)
            except DecodeError:
                raise FieldError("request: not a valid dqpose.v1.BlendBatchRequest "
                                 "message") from None
            out = self.blend_batch(request).SerializeToString(), len(request.requests)
        return fit(out[0], self.max_message_bytes, "requests", out[1], "requests"), out[1]

    def blend_batch(self, request: pb.BlendBatchRequest) -> pb.BlendBatchResponse:
        requests = request.requests
        check_count("requests", len(requests), self.max_poses, "requests", empty=True)
        total = sum(len(r.poses) for r in requests)
        if total > BATCH_POSE_FACTOR * self.max_poses:
            raise FieldError(f"requests: {total} poses in all exceed the server limit of "
                             f"{BATCH_POSE_FACTOR * self.max_poses} per batch")
        responses = []
        for i, r in enumerate(requests):
            try:
                responses.append(self.blend_bytes(r.SerializeToString()))
            except FieldError as e:
                raise type(e)(f"requests[{i}].{e}") from None
        return pb.BlendBatchResponse(responses=responses)

    def interpolate_request(self, request: pb.InterpolateRequest) -> pb.InterpolateResponse:
        k, n = len(request.keyframes), len(request.times)
        check_count("keyframes", k, self.max_poses, "keyframes", empty=True)
        if k < 2:
            raise FieldError(f"keyframes: need at least 2 keyframes, got {k}")
        check_count("times", n, self.max_poses, "times", empty=True)
        mode = interpolation_named(request.interpolation, INTERPOLATE_INTERPOLATION)
        times_k, dqs_k = stamped_to_arrays(request.keyframes, "keyframes")
        times = np.array(request.times, dtype=np.float64)
        try:
            out = interpolate(times_k, dqs_k, times, mode)
        except ValueError as e:
            raise field_named(rename(e, {"times_k": "keyframes{}.time", "dqs_k": "keyframes{}.pose",
                                         "times": "times{}"}),
                              ("keyframes", "times", "interpolation"), "keyframes") from None
        if not np.isfinite(out).all():
            raise FieldError("keyframes: interpolation produced non-finite poses")
        return pb.InterpolateResponse(samples=arrays_to_stamped(times, out))

    def interpolate_wire(self, data: bytes) -> bytes:
        """What Interpolate serves: ``InterpolateResponse`` bytes for request bytes."""
        try:
            request = pb.InterpolateRequest.FromString(data)
        except DecodeError:
            raise FieldError("request: not a valid dqpose.v1.InterpolateRequest message") from None
        return fit(self.interpolate_request(request).SerializeToString(), self.max_message_bytes,
                   "times", len(request.times), "times")

    def _served(self, handle):
        """``handle`` (bytes in) as a call's handler: on the event loop for a request of at
        most ``limits.INLINE_BYTES`` (work linear in its size, under ~1 ms), else in the
        server's worker pool."""
        def serve(request: bytes):
            if len(request) <= limits.INLINE_BYTES:
                return handle(request)
            return self.calls.work(handle, request)
        return serve

    # -- RPCs

    def register(self, server) -> None:
        """``add_BlendingServicer_to_server`` except that every RPC takes and returns bytes:
        Blend, BlendStream and BlendBatch turned into each other by the ``*_wire`` methods
        without protobuf objects, Interpolate parsed there; so each can check its answer's size
        and do its work off the event loop when it is large."""
        raw = dict(request_deserializer=None, response_serializer=None)
        handlers: dict[str, grpc.RpcMethodHandler[Any, Any]] = {
            "Blend": grpc.unary_unary_rpc_method_handler(self.Blend, **raw),
            "Interpolate": grpc.unary_unary_rpc_method_handler(self.Interpolate, **raw),
            "BlendStream": grpc.stream_stream_rpc_method_handler(self.BlendStream, **raw),
            "BlendBatch": grpc.unary_unary_rpc_method_handler(self.BlendBatch, **raw),
        }
        generic = grpc.method_handlers_generic_handler(self.NAME, handlers)
        server.add_generic_rpc_handlers((generic,))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def Blend(self, request: bytes, context):
        # Registered without a deserializer (register): the request arrives as bytes.
        return await self.calls.unary("Blend", self._served(self.blend_wire), request, context)

    async def BlendBatch(self, request: bytes, context):
        # Registered without a deserializer, like Blend.
        return await self.calls.unary("BlendBatch", self._served(self.blend_batch_wire), request,
                                      context, counted=True)

    async def Interpolate(self, request: bytes, context):
        return await self.calls.unary("Interpolate", self._served(self.interpolate_wire),
                                      request, context)

    async def BlendStream(self, request_iterator, context) -> None:
        # Reading runs ahead of writing (a reader task feeding a queue of STREAM_READ_AHEAD
        # requests, STREAM_READ_AHEAD_BYTES at most): in grpc.aio every read and every write is
        # a round trip through gRPC's poller thread, and overlapping the two is worth ~1.5x in
        # blends/s (docs/benchmarks/grpc.md#server-choices-measured). The bounds keep HTTP/2
        # flow control as the client's backpressure, and what a client that stops reading
        # leaves here small. request_iterator stays unused: the reader takes the messages with
        # context.read().
        async with self.calls.stream("BlendStream", context) as call:
            if call.open() is None:
                return
            pending = ReadAhead(STREAM_READ_AHEAD, STREAM_READ_AHEAD_BYTES)
            call.on_end(asyncio.ensure_future(read_all(context, pending)).cancel)
            while True:
                request = await pending.get()
                if request is grpc.aio.EOF:
                    break
                if isinstance(request, Exception):
                    raise request
                try:
                    response = (self.blend_wire(request) if len(request) <= limits.INLINE_BYTES
                                else await self.calls.work(self.blend_wire, request))
                except Exception as e:
                    status = refusal(e)
                    if status is None:
                        raise
                    await call.refuse(status, readable(f"requests[{call.messages}].{e}"))
                await context.write(response)
                call.messages += 1
