"""The dqpose gRPC server (``dqpose serve``): a thin adapter over :mod:`service.dq`.

Messages in -> NumPy arrays (:mod:`service.messages`) -> domain functions (:mod:`service.dq`,
:mod:`service.interpolate`) -> messages out. Every invalid input becomes ``INVALID_ARGUMENT`` with
a message that starts with the proto field path; anything unexpected becomes ``INTERNAL`` and is
logged, and the server keeps running.
"""
from __future__ import annotations

import asyncio
import dataclasses
import hmac
import json
import logging
import math
import signal
import time

import grpc
import numpy as np
from google.protobuf.message import DecodeError
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import _async as reflection_aio
from grpc_reflection.v1alpha import reflection, reflection_pb2_grpc

from service import dq
from service.errors import FieldError, rename
from service.messages import (INTERPOLATION_NAMES, METHOD_NAMES, arrays_to_stamped,
                              blend_batch_wire, blend_wire, decode_blend_request, dq_to_pose,
                              flat_to_dqs, poses_to_flat, stamped_to_arrays)
from service.interpolate import interpolate
from service._proto.dqpose.v1 import blending_pb2 as pb
from service._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc

log = logging.getLogger("dqpose.server")
call_log = logging.getLogger("dqpose.calls")

SERVICE_NAMES = (pb.DESCRIPTOR.services_by_name["Blending"].full_name,
                 health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
                 reflection.SERVICE_NAME)

DEFAULT_TOLERANCE = 1e-12
DEFAULT_MAX_ITERATIONS = 100
STREAM_READ_AHEAD = 64         # requests a BlendStream reads ahead of its replies
# DIB converges in a handful of steps; the cap keeps one request from holding the event loop
# (10k poses x 1000 steps is ~0.2 s of core time).
MAX_ITERATIONS_LIMIT = 1000


@dataclasses.dataclass
class ServerConfig:
    host: str = "127.0.0.1"
    port: int = 50051                  # 0 picks a free port
    tls_cert: bytes | None = None      # PEM chain; with tls_key enables TLS
    tls_key: bytes | None = None
    client_ca: bytes | None = None     # PEM; requires and verifies client certificates (mTLS)
    token: str | None = None           # bearer token required on every RPC except health
    max_message_bytes: int = 4 * 1024 * 1024
    max_poses: int = 10_000            # per request: poses, keyframes and sampled times
    keepalive_s: float = 60.0
    grace_s: float = 10.0              # drain time on SIGTERM before in-flight calls are cancelled
    metrics_port: int | None = None


# --------------------------------------------------------------------------- the adapter

class Blending(pb_grpc.BlendingServicer):
    """The ``dqpose.v1.Blending`` service. ``blend``/``interpolate_request`` are plain functions of
    a request (no gRPC context), so the benchmark can time the adapter without the transport."""

    def __init__(self, max_poses: int = 10_000, metrics: "_Metrics | None" = None):
        self.max_poses = max_poses
        self._metrics = metrics
        self._log_calls = call_log.isEnabledFor(logging.INFO)

    # -- request -> response, no transport

    def _check_count(self, field: str, n: int, what: str) -> None:
        if n == 0:
            raise FieldError(f"{field}: empty request: no {what}")
        if n > self.max_poses:
            raise FieldError(f"{field}: {n} {what} exceed the server limit of {self.max_poses}")

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
                         MAX_ITERATIONS_LIMIT)
        return out if out is not None else self.blend_bytes(data).SerializeToString()

    def _blend(self, flat, weights, method_code: int, tolerance: float,
               max_iterations: int) -> pb.BlendResponse:
        self._check_count("poses", len(flat), "poses")
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
        if max_iter > MAX_ITERATIONS_LIMIT:
            raise FieldError(f"max_iterations: {max_iter} exceeds the limit of "
                             f"{MAX_ITERATIONS_LIMIT}")
        iterations, residual = 0, 0.0
        try:
            if method == "dib":
                mean, iterations, residual = dq.dib(dqs, weights, tol, max_iter, return_info=True)
                iterations, residual = int(iterations), float(residual)
            else:
                mean = dq.blend(dqs, weights, method, tol, max_iter)
        except ValueError as e:
            raise rename(e, {"dqs": "poses{}", "weights": "weights{}"}) from None
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
        out = blend_batch_wire(data, self.max_poses, 10 * self.max_poses, self.max_poses,
                               DEFAULT_TOLERANCE, DEFAULT_MAX_ITERATIONS, MAX_ITERATIONS_LIMIT)
        if out is not None:
            return out
        try:
            request = pb.BlendBatchRequest.FromString(data)
        except DecodeError:
            raise FieldError("request: not a valid dqpose.v1.BlendBatchRequest message") from None
        return self.blend_batch(request).SerializeToString(), len(request.requests)

    def blend_batch(self, request: pb.BlendBatchRequest) -> pb.BlendBatchResponse:
        requests = request.requests
        self._check_count("requests", len(requests), "requests")
        total = sum(len(r.poses) for r in requests)
        if total > 10 * self.max_poses:
            raise FieldError(f"requests: {total} poses in all exceed the server limit of "
                             f"{10 * self.max_poses} per batch")
        responses = []
        for i, r in enumerate(requests):
            try:
                responses.append(self.blend_bytes(r.SerializeToString()))
            except FieldError as e:
                raise FieldError(f"requests[{i}].{e}") from None
        return pb.BlendBatchResponse(responses=responses)

    def interpolate_request(self, request: pb.InterpolateRequest) -> pb.InterpolateResponse:
        k, n = len(request.keyframes), len(request.times)
        self._check_count("keyframes", k, "keyframes")
        if k < 2:
            raise FieldError(f"keyframes: need at least 2 keyframes, got {k}")
        self._check_count("times", n, "times")
        mode = INTERPOLATION_NAMES.get(request.interpolation)
        if mode is None:
            raise FieldError(f"interpolation: unknown Interpolation value {request.interpolation}")
        times_k, dqs_k = stamped_to_arrays(request.keyframes, "keyframes")
        times = np.array(request.times, dtype=np.float64)
        try:
            out = interpolate(times_k, dqs_k, times, mode)
        except ValueError as e:
            raise rename(e, {"times_k": "keyframes{}.time", "dqs_k": "keyframes{}.pose",
                             "times": "times{}"}) from None
        if not np.isfinite(out).all():
            raise FieldError("keyframes: interpolation produced non-finite poses")
        return pb.InterpolateResponse(samples=arrays_to_stamped(times, out))

    # -- RPCs

    async def _unary(self, rpc: str, handle, request, context, counted: bool = False):
        """One unary call: the response of ``handle(request)``, INVALID_ARGUMENT for a FieldError,
        INTERNAL (logged) for anything else, and one log line and metric either way. With
        ``counted``, ``handle`` returns ``(response, messages)`` and the log line counts them."""
        t0 = time.perf_counter()
        code = "OK"
        messages = None
        try:
            response = handle(request)
            if counted:
                response, messages = response
            return response
        except FieldError as e:
            code = "INVALID_ARGUMENT"
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
        except Exception:
            code = "INTERNAL"
            log.exception("%s failed", rpc)
            await context.abort(grpc.StatusCode.INTERNAL, "internal error (see the server log)")
        finally:
            self._done(rpc, code, t0, context, messages)

    async def Blend(self, request: bytes, context):
        # Registered without a deserializer (add_blending): the request arrives as bytes.
        return await self._unary("Blend", self.blend_wire, request, context)

    async def BlendBatch(self, request: bytes, context):
        # Registered without a deserializer, like Blend.
        return await self._unary("BlendBatch", self.blend_batch_wire, request, context,
                                 counted=True)

    async def Interpolate(self, request, context):
        return await self._unary("Interpolate", self.interpolate_request, request, context)

    async def BlendStream(self, request_iterator, context):
        # Reading runs ahead of writing (a reader task feeding a queue of STREAM_READ_AHEAD):
        # in grpc.aio every read and every write is a round trip through gRPC's poller thread,
        # and overlapping the two is worth ~1.5x in blends/s (BENCHMARKS.md). The bound keeps
        # HTTP/2 flow control as the client's backpressure. request_iterator stays unused: the
        # reader takes the messages with context.read().
        t0 = time.perf_counter()
        code = "OK"
        i = 0
        pending: asyncio.Queue = asyncio.Queue(maxsize=STREAM_READ_AHEAD)
        reader = asyncio.ensure_future(_read_all(context, pending))
        try:
            while True:
                request = await pending.get()
                if request is grpc.aio.EOF:
                    break
                if isinstance(request, Exception):
                    raise request
                try:
                    response = self.blend_wire(request)
                except FieldError as e:
                    code = "INVALID_ARGUMENT"
                    await context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"requests[{i}].{e}")
                await context.write(response)
                i += 1
        except asyncio.CancelledError:
            code = "CANCELLED"
            raise
        except grpc.aio.AbortError:
            raise
        except Exception:
            code = "INTERNAL"
            log.exception("BlendStream failed")
            await context.abort(grpc.StatusCode.INTERNAL, "internal error (see the server log)")
        finally:
            reader.cancel()
            self._done("BlendStream", code, t0, context, messages=i)

    def _done(self, rpc: str, code: str, t0: float, context, messages: int | None = None) -> None:
        dt = time.perf_counter() - t0
        if self._metrics is not None:
            self._metrics.observe(rpc, code, dt)
        if self._log_calls:
            # A logging record per call costs more than the rest of the adapter, so lines are
            # queued here and go through logging in batches (_flush_call_log). Hand-built JSON:
            # the values are our own names, numbers and an address (quoted through json).
            extra = "" if messages is None else f', "messages": {messages}'
            _pending_calls.append(
                f'{{"t": {time.time():.6f}, "rpc": "{rpc}", "code": "{code}", '
                f'"ms": {dt * 1e3:.3f}, "peer": {json.dumps(context.peer())}{extra}}}')
            if len(_pending_calls) >= 1024:  # bounded even where nothing flushes periodically
                _flush_call_log()


# Call log lines waiting for the next flush (the event loop is single-threaded: no lock needed).
_pending_calls: list[str] = []


def _flush_call_log() -> None:
    """Hands the queued call lines to the ``dqpose.calls`` logger as one record."""
    if _pending_calls:
        lines = "\n".join(_pending_calls)
        _pending_calls.clear()
        call_log.info(lines)


async def _flush_periodically(period: float) -> None:
    while True:
        await asyncio.sleep(period)
        _flush_call_log()


async def _read_all(context, pending: asyncio.Queue) -> None:
    """Puts every request of a stream into ``pending``, then ``grpc.aio.EOF``; a read that
    fails puts its exception instead, for the writer to raise."""
    try:
        while True:
            request = await context.read()
            await pending.put(request)
            if request is grpc.aio.EOF:
                return
    except Exception as e:   # the writer is still consuming, so this put finds room
        await pending.put(e)


def add_blending(servicer: Blending, server) -> None:
    """``add_BlendingServicer_to_server`` with one difference: Blend and BlendStream take and
    return bytes, which ``Blending.blend_wire`` turns into each other without protobuf objects."""
    raw = dict(request_deserializer=None, response_serializer=None)
    handlers = {
        "Blend": grpc.unary_unary_rpc_method_handler(servicer.Blend, **raw),
        "Interpolate": grpc.unary_unary_rpc_method_handler(
            servicer.Interpolate, request_deserializer=pb.InterpolateRequest.FromString,
            response_serializer=pb.InterpolateResponse.SerializeToString),
        "BlendStream": grpc.stream_stream_rpc_method_handler(servicer.BlendStream, **raw),
        "BlendBatch": grpc.unary_unary_rpc_method_handler(
            servicer.BlendBatch, request_deserializer=None,
            response_serializer=None),
    }
    name = pb.DESCRIPTOR.services_by_name["Blending"].full_name
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(name, handlers),))
    server.add_registered_method_handlers(name, handlers)


# --------------------------------------------------------------------------- auth, metrics

class BearerTokenAuth(grpc.aio.ServerInterceptor):
    """Requires ``authorization: Bearer <token>`` metadata; the health service stays open so
    load balancers and the Docker HEALTHCHECK need no secret."""

    OPEN_PREFIXES = ("/grpc.health.v1.Health/",)

    def __init__(self, token: str):
        self._expected = ("Bearer " + token).encode()

    async def intercept_service(self, continuation, details):
        if details.method.startswith(self.OPEN_PREFIXES):
            return await continuation(details)
        got = None
        for key, value in details.invocation_metadata or ():
            if key == "authorization":
                got = value.encode() if isinstance(value, str) else value
                break
        # compare_digest: the time taken must not reveal how much of the token matched.
        if got is not None and hmac.compare_digest(got, self._expected):
            return await continuation(details)
        reason = ("authorization: missing bearer token (send metadata 'authorization: Bearer "
                  "<token>')" if got is None else "authorization: invalid bearer token")
        return _abort_handler(await continuation(details), grpc.StatusCode.UNAUTHENTICATED, reason)


def _abort_handler(handler, code: grpc.StatusCode, details: str):
    """A handler of the same shape as ``handler`` that fails every call with ``code``."""
    async def abort(request_or_iterator, context):
        await context.abort(code, details)

    if handler is None:
        return None
    kw = dict(request_deserializer=handler.request_deserializer,
              response_serializer=handler.response_serializer)
    if handler.request_streaming and handler.response_streaming:
        return grpc.stream_stream_rpc_method_handler(abort, **kw)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(abort, **kw)
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(abort, **kw)
    return grpc.unary_unary_rpc_method_handler(abort, **kw)


class _Metrics:
    """Prometheus call counter and latency histogram, served on their own HTTP port."""

    def __init__(self, host: str, port: int):
        import prometheus_client as prom

        self._registry = prom.CollectorRegistry()
        self._calls = prom.Counter("dqpose_grpc_calls", "RPCs handled", ["rpc", "code"],
                                   registry=self._registry)
        self._seconds = prom.Histogram(
            "dqpose_grpc_call_seconds", "Server-side handling time of an RPC", ["rpc"],
            buckets=(1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 5e-2, 0.25, 1.0),
            registry=self._registry)
        self._children: dict = {}
        self.server, self.thread = prom.start_http_server(port, addr=host, registry=self._registry)

    def observe(self, rpc: str, code: str, seconds: float) -> None:
        key = (rpc, code)
        child = self._children.get(key)
        if child is None:  # labels() is a dict lookup plus a lock; cache the children
            child = self._children[key] = (self._calls.labels(rpc, code),
                                           self._seconds.labels(rpc))
        child[0].inc()
        child[1].observe(seconds)

    def close(self) -> None:
        self.server.shutdown()


class _Reflection(reflection_aio.ReflectionServicer):
    """Server reflection that also resolves method symbols (``dqpose.v1.Blending.Blend``), which
    ghz asks for and protobuf's Python descriptor pool cannot find: a method lives in the file of
    its service."""

    def _file_containing_symbol(self, request, fully_qualified_name):
        response = super()._file_containing_symbol(request, fully_qualified_name)
        if response.HasField("error_response") and "." in fully_qualified_name:
            parent = fully_qualified_name.rsplit(".", 1)[0]
            return super()._file_containing_symbol(request, parent)
        return response


# --------------------------------------------------------------------------- lifecycle

class Running:
    """A started server: its bound port, health servicer and a graceful ``stop``."""

    def __init__(self, server, health_servicer, port: int, metrics: _Metrics | None):
        self.server = server
        self.health = health_servicer
        self.port = port
        self.metrics = metrics

    async def stop(self, grace: float | None) -> None:
        # NOT_SERVING first, so health watchers and load balancers stop sending new calls,
        # then drain what is in flight.
        await self.health.enter_graceful_shutdown()
        await self.server.stop(grace)
        if self.metrics is not None:
            self.metrics.close()


def server_options(cfg: ServerConfig) -> list[tuple[str, int]]:
    keepalive_ms = int(cfg.keepalive_s * 1000)
    return [
        # gRPC enables SO_REUSEPORT by default: a second server would silently share the port.
        ("grpc.so_reuseport", 0),
        ("grpc.max_receive_message_length", cfg.max_message_bytes),
        ("grpc.max_send_message_length", cfg.max_message_bytes),
        ("grpc.keepalive_time_ms", keepalive_ms),
        ("grpc.keepalive_timeout_ms", 20_000),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
        ("grpc.http2.max_pings_without_data", 0),
    ]


async def start(cfg: ServerConfig) -> Running:
    """Build, bind and start a server. Raises ``OSError`` when the address cannot be bound."""
    interceptors = [BearerTokenAuth(cfg.token)] if cfg.token else []
    server = grpc.aio.server(options=server_options(cfg), interceptors=interceptors)
    metrics = _Metrics(cfg.host, cfg.metrics_port) if cfg.metrics_port is not None else None
    add_blending(Blending(cfg.max_poses, metrics), server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection_pb2_grpc.add_ServerReflectionServicer_to_server(_Reflection(SERVICE_NAMES), server)
    address = f"{cfg.host}:{cfg.port}"
    try:
        if cfg.tls_cert or cfg.tls_key:
            if not (cfg.tls_cert and cfg.tls_key):
                raise ValueError("tls: both a certificate and a key are needed")
            creds = grpc.ssl_server_credentials(
                [(cfg.tls_key, cfg.tls_cert)], root_certificates=cfg.client_ca,
                require_client_auth=cfg.client_ca is not None)
            port = server.add_secure_port(address, creds)
        else:
            if cfg.client_ca:
                raise ValueError("client_ca: mTLS needs a server certificate and key (TLS)")
            port = server.add_insecure_port(address)
    except RuntimeError as e:  # grpc reports a failed bind as RuntimeError
        if metrics is not None:
            metrics.close()
        raise OSError(f"cannot listen on {address}: {e}") from None
    if port == 0:
        raise OSError(f"cannot listen on {address}")
    await server.start()
    await health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    await health_servicer.set(SERVICE_NAMES[0], health_pb2.HealthCheckResponse.SERVING)
    return Running(server, health_servicer, port, metrics)


async def serve(cfg: ServerConfig, ready=None) -> int:
    """Run until SIGTERM/SIGINT, then shut down gracefully; returns the exit code (0)."""
    running = await start(cfg)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    log.info(json.dumps({"event": "serving", "address": f"{cfg.host}:{running.port}",
                         "tls": bool(cfg.tls_cert), "mtls": bool(cfg.client_ca),
                         "auth": "bearer" if cfg.token else "none",
                         "metrics_port": cfg.metrics_port}))
    if ready is not None:
        ready(running)
    flusher = asyncio.create_task(_flush_periodically(0.25))
    await stop.wait()
    _flush_call_log()
    log.info(json.dumps({"event": "shutting_down", "grace_s": cfg.grace_s}))
    await running.stop(cfg.grace_s)
    flusher.cancel()
    _flush_call_log()
    log.info(json.dumps({"event": "stopped"}))
    return 0
