"""The dqpose gRPC server (``dqpose serve``): what is server-wide.

Config, start and graceful stop, bearer-token auth, TLS and mTLS, Prometheus metrics, the health
service, reflection and the call log (:mod:`service.rpc.calls`). The services themselves are the
servicers of ``SERVICERS``, one module each (:mod:`service.rpc.blending`,
:mod:`service.rpc.fusion`); each turns messages into NumPy arrays for the domain
(:mod:`service.dq`, :mod:`service.fusion`, ...) and names bad input by its proto field.
"""
from __future__ import annotations

import asyncio
import dataclasses
import errno
import hmac
import json
import signal
import socket

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import _async as reflection_aio
from grpc_reflection.v1alpha import reflection, reflection_pb2_grpc

from service.rpc import DEFAULT_MAX_MESSAGE_BYTES, DEFAULT_MAX_POSES
from service.rpc.blending import Blending
from service.rpc.calls import Calls, log
from service.rpc.fusion import Fusion

# The services this server offers: each class takes (config, calls), has NAME (the full proto
# service name) and register(server).
SERVICERS = (Blending, Fusion)
SERVICE_NAMES = tuple(s.NAME for s in SERVICERS) + (
    health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME)


@dataclasses.dataclass
class ServerConfig:
    host: str = "127.0.0.1"
    port: int = 50051                  # 0 picks a free port
    tls_cert: bytes | None = None      # PEM chain; with tls_key enables TLS
    tls_key: bytes | None = None
    client_ca: bytes | None = None     # PEM; requires and verifies client certificates (mTLS)
    token: str | None = None           # bearer token required on every RPC except health
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_poses: int = DEFAULT_MAX_POSES  # per request: poses, keyframes and sampled times
    keepalive_s: float = 60.0
    grace_s: float = 10.0              # drain time on SIGTERM before in-flight calls are cancelled
    metrics_port: int | None = None


# --------------------------------------------------------------------------- the adapter

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

    def __init__(self, server, health_servicer, port: int, calls: Calls):
        self.server = server
        self.health = health_servicer
        self.port = port
        self.calls = calls
        self.metrics = calls.metrics

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


class AddressInUse(OSError):
    """Another process listens on the address; ``setting`` is the ``ServerConfig`` field that
    names it (``"port"`` or ``"metrics_port"``)."""

    def __init__(self, what: str, address: str, setting: str):
        super().__init__(f"cannot {what} {address}: address already in use")
        self.errno = errno.EADDRINUSE
        self.setting = setting


def _bind_error(host: str, port: int) -> OSError | None:
    """Why gRPC could not bind ``host:port``, found by binding a plain socket as gRPC does
    (SO_REUSEADDR, no SO_REUSEPORT); gRPC itself only says that it failed."""
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM,
                                   flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        return OSError(e.strerror)
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(addr)
            except OSError as e:
                return e
    return None


def _listen_error(address: str, host: str, port: int) -> OSError | None:
    e = _bind_error(host, port)
    if e is None:
        return None
    if e.errno == errno.EADDRINUSE:
        return AddressInUse("listen on", address, "port")
    return OSError(f"cannot listen on {address}: {(e.strerror or str(e)).lower()}")


async def start(cfg: ServerConfig) -> Running:
    """Build, bind and start a server. Raises ``OSError`` when the address cannot be bound
    (:class:`AddressInUse` when another process listens there)."""
    address = f"{cfg.host}:{cfg.port}"
    # Checked before gRPC tries: its failed bind logs a line of its own on standard error.
    if cfg.port and (problem := _listen_error(address, cfg.host, cfg.port)) is not None:
        raise problem
    interceptors = [BearerTokenAuth(cfg.token)] if cfg.token else []
    server = grpc.aio.server(options=server_options(cfg), interceptors=interceptors)
    try:
        metrics = _Metrics(cfg.host, cfg.metrics_port) if cfg.metrics_port is not None else None
    except OSError as e:
        where = f"{cfg.host}:{cfg.metrics_port}"
        if e.errno == errno.EADDRINUSE:
            raise AddressInUse("serve metrics on", where, "metrics_port") from None
        raise OSError(f"cannot serve metrics on {where}: {(e.strerror or str(e)).lower()}") from None
    calls = Calls(metrics)
    for cls in SERVICERS:
        cls(cfg, calls).register(server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection_pb2_grpc.add_ServerReflectionServicer_to_server(_Reflection(SERVICE_NAMES), server)
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
    except (RuntimeError, ValueError) as e:  # grpc reports a failed bind as RuntimeError
        if metrics is not None:
            metrics.close()
        if isinstance(e, ValueError):
            raise
        raise (_listen_error(address, cfg.host, cfg.port)
               or OSError(f"cannot listen on {address}: {e}")) from None
    if port == 0:
        raise OSError(f"cannot listen on {address}")
    await server.start()
    await health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    for cls in SERVICERS:
        await health_servicer.set(cls.NAME, health_pb2.HealthCheckResponse.SERVING)
    return Running(server, health_servicer, port, calls)


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
    flusher = asyncio.create_task(running.calls.flush_periodically(0.25))
    await stop.wait()
    running.calls.flush()
    log.info(json.dumps({"event": "shutting_down", "grace_s": cfg.grace_s}))
    await running.stop(cfg.grace_s)
    flusher.cancel()
    running.calls.flush()
    log.info(json.dumps({"event": "stopped"}))
    return 0
