"""The dqpose gRPC server (``dqpose serve``): what is server-wide.

Start and graceful stop (its settings: :mod:`dqpose.rpc.server_config`), bearer-token auth, TLS
and mTLS, Prometheus metrics, the health service, reflection and the call log
(:mod:`dqpose.rpc.calls`). The services themselves are the
servicers of ``SERVICERS``, one module each (:mod:`dqpose.rpc.blending`,
:mod:`dqpose.rpc.fusion`); each turns messages into NumPy arrays for the domain
(:mod:`dqpose.dq`, :mod:`dqpose.fusion`, ...) and names bad input by its proto field.
"""
from __future__ import annotations

import asyncio
import errno
import gc
import json
import signal
import socket

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import _async as reflection_aio
from grpc_reflection.v1alpha import reflection, reflection_pb2_grpc

from dqpose import record, tokens
from dqpose.limits import OverLimit
from dqpose.names import quoted
from dqpose.rpc import routing
from dqpose.rpc.blending import Blending
from dqpose.rpc.calls import Calls, log, readable
from dqpose.rpc.fusion import Fusion
from dqpose.rpc.handeye import HandEye
from dqpose.rpc.peers import Peers
from dqpose.rpc.server_config import (  # noqa: F401 (ConfigError: the server's API)
    INT32_MAX,
    ConfigError,
    ServerConfig,
)
from dqpose.rpc.trajectories import Trajectories
from dqpose.rpc.world import World

# The services this server offers: each class takes (config, calls), has NAME (the full proto
# service name) and register(server). World comes first: Trajectories resolves Waypoint.frame
# through its world (one per server), handed over in start().
SERVICERS = (World, Blending, Fusion, Trajectories, HandEye)
SERVICE_NAMES = tuple(s.NAME for s in SERVICERS) + (
    health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME)


# ------------------------------------------------------------------ gate, auth, health, metrics

OPEN_PREFIXES = ("/grpc.health.v1.Health/",)   # what no interceptor refuses


def _rpc_name(details) -> str:
    return details.method.rsplit("/", 1)[-1]


class Gate(grpc.aio.ServerInterceptor):
    """Once closed (SIGTERM), every new call but health is UNAVAILABLE ("server is shutting
    down"), recorded like any call. UNAVAILABLE is what retry policies retry, on another server
    where there is one; gRPC's own stop can leave a call that arrives at that moment CANCELLED,
    which they do not. Health stays open so that it can say NOT_SERVING."""

    DETAILS = "server is shutting down"

    def __init__(self, calls: Calls):
        self.closed = False
        self._calls = calls

    async def intercept_service(self, continuation, details):
        if not self.closed or details.method.startswith(OPEN_PREFIXES):
            return await continuation(details)
        return _refusing_handler(await continuation(details), self._calls, _rpc_name(details),
                                 grpc.StatusCode.UNAVAILABLE, self.DETAILS)


class BearerTokenAuth(grpc.aio.ServerInterceptor):
    """Requires ``authorization: Bearer <token>`` metadata; the health service stays open so
    load balancers and the Docker HEALTHCHECK need no secret."""

    def __init__(self, token: str, calls: Calls):
        self._token = token
        self._calls = calls

    async def intercept_service(self, continuation, details):
        if details.method.startswith(OPEN_PREFIXES):
            return await continuation(details)
        got = None
        for key, value in details.invocation_metadata or ():
            if key == "authorization":
                got = value
                break
        if tokens.bearer_matches(got, self._token):
            return await continuation(details)
        reason = ("authorization: missing bearer token (send metadata 'authorization: Bearer "
                  "<token>')" if got is None else "authorization: invalid bearer token")
        return _refusing_handler(await continuation(details), self._calls, _rpc_name(details),
                                 grpc.StatusCode.UNAUTHENTICATED, reason)


def _refusing_handler(handler, calls: Calls, rpc: str, code: grpc.StatusCode, details: str):
    """A handler of the same shape as ``handler`` that fails every call with ``code``."""
    @routing.trailers_only
    async def refuse(request_or_iterator, context):
        await calls.refuse(rpc, context, code, details)

    if handler is None:
        return None
    kw = dict(request_deserializer=handler.request_deserializer,
              response_serializer=handler.response_serializer)
    if handler.request_streaming and handler.response_streaming:
        return grpc.stream_stream_rpc_method_handler(refuse, **kw)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(refuse, **kw)
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(refuse, **kw)
    return grpc.unary_unary_rpc_method_handler(refuse, **kw)


class Health(health_pb2_grpc.HealthServicer):
    """The standard ``grpc.health.v1`` service. Unlike grpc_health's reference servicer, its
    Watch streams end (after their last status) once the server closes: an open watch would
    otherwise hold the shutdown for the whole grace period."""

    def __init__(self, peers: Peers | None = None) -> None:
        self._status: dict[str, int] = {}
        self._changed = asyncio.Condition()
        self._closed = self._stopping = False
        # a Watch is a stream of its host (open to clients without a token: bounded all the same,
        # and apart from the token holders' streams)
        self._peers = peers if peers is not None else Peers()

    async def set(self, service: str, status: int) -> None:
        async with self._changed:
            if not self._stopping:
                self._status[service] = status
                self._changed.notify_all()

    async def follow(self, recorder) -> None:
        """``dqpose.record``: SERVING while the recording's files are written, NOT_SERVING while
        they fail (``recorder.failure``), whichever thread of the recorder's hears it."""
        loop = asyncio.get_running_loop()
        ok, failing = health_pb2.HealthCheckResponse.SERVING, \
            health_pb2.HealthCheckResponse.NOT_SERVING

        def status() -> int:
            return ok if recorder.failure is None else failing

        def changed() -> None:      # the state when the loop gets to it: the last one wins
            loop.call_soon_threadsafe(
                lambda: asyncio.ensure_future(self.set(record.HEALTH_SERVICE, status())))

        recorder.watch(changed)
        await self.set(record.HEALTH_SERVICE, status())

    async def not_serving(self) -> None:
        """Every service NOT_SERVING, for good: the server is shutting down."""
        async with self._changed:
            self._stopping = True
            for service in self._status:
                self._status[service] = health_pb2.HealthCheckResponse.NOT_SERVING
            self._changed.notify_all()

    async def close(self) -> None:
        """Ends every Watch, once it has sent the current status."""
        async with self._changed:
            self._closed = True
            self._changed.notify_all()

    async def Check(self, request, context):
        status = self._status.get(request.service)
        if status is None:
            await context.abort(grpc.StatusCode.NOT_FOUND,
                                readable(f"service: unknown service {quoted(request.service)}"))
        return health_pb2.HealthCheckResponse(status=status)

    async def Watch(self, request, context):
        try:
            self._peers.open("Watch", context, authenticated=False)
        except OverLimit as e:
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(e))
        unknown = health_pb2.HealthCheckResponse.SERVICE_UNKNOWN
        sent = None
        while True:
            async with self._changed:
                # the predicate runs within this pass of the loop, on this pass's `sent`
                await self._changed.wait_for(
                    lambda sent=sent: (self._closed
                                       or self._status.get(request.service, unknown) != sent))
                status, closed = self._status.get(request.service, unknown), self._closed
            if status != sent:     # written without the lock: a slow watcher holds up no one
                await context.write(health_pb2.HealthCheckResponse(status=status))
                sent = status
            if closed:
                return


class _Metrics:
    """Prometheus call counter and latency histogram, served on their own HTTP port (``host``:
    the loopback unless told otherwise), which asks for the server's bearer ``token`` when it has
    one."""

    def __init__(self, host: str, port: int, token: str | None = None):
        import prometheus_client as prom

        self._registry = prom.CollectorRegistry()
        self._calls = prom.Counter("dqpose_grpc_calls", "RPCs handled", ["rpc", "code"],
                                   registry=self._registry)
        self._seconds = prom.Histogram(
            "dqpose_grpc_call_seconds", "Server-side handling time of an RPC", ["rpc"],
            buckets=(1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 5e-2, 0.25, 1.0),
            registry=self._registry)
        self._children: dict = {}
        self.server, self.thread = _serve_metrics(host, port, prom.make_wsgi_app(self._registry),
                                                  token)

    def observe(self, rpc: str, code: str, seconds: float) -> None:
        key = (rpc, code)
        child = self._children.get(key)
        if child is None:  # labels() is a dict lookup plus a lock; cache the children
            child = self._children[key] = (self._calls.labels(rpc, code),
                                           self._seconds.labels(rpc))
        child[0].inc()
        child[1].observe(seconds)

    def watch(self, recorder) -> None:
        """``dqpose_record_messages_total{outcome="written"|"dropped"|"failed"}``, read from
        ``recorder`` when scraped."""
        from prometheus_client.core import CounterMetricFamily

        class Collector:
            def collect(self):
                c = CounterMetricFamily("dqpose_record_messages", "Messages recorded, dropped "
                                        "because the recording fell behind, or failed because "
                                        "its files could not be written", labels=["outcome"])
                c.add_metric(["written"], recorder.written)
                c.add_metric(["dropped"], recorder.dropped)
                c.add_metric(["failed"], recorder.failed)
                yield c

        self._registry.register(Collector())

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _serve_metrics(host: str, port: int, app, token: str | None):
    """``app`` on ``host:port`` in a thread (prometheus_client's server, quiet), a request without
    ``Authorization: Bearer <token>`` answered 401 when there is a token."""
    import threading
    from wsgiref.simple_server import WSGIRequestHandler, make_server

    from prometheus_client.exposition import ThreadingWSGIServer

    class Quiet(WSGIRequestHandler):
        def log_message(self, format, *args):
            pass

    class Server(ThreadingWSGIServer):
        address_family = socket.getaddrinfo(host.strip("[]"), port,
                                            type=socket.SOCK_STREAM)[0][0]

    def guarded(environ, start_response):
        if token is None or tokens.bearer_matches(environ.get("HTTP_AUTHORIZATION"), token):
            return app(environ, start_response)
        start_response("401 Unauthorized", [("WWW-Authenticate", 'Bearer realm="dqpose"'),
                                            ("Content-Type", "text/plain; charset=utf-8")])
        return [b"authorization: missing or invalid bearer token (send 'Authorization: Bearer "
                b"<token>', the server's --token-file)\n"]

    httpd = make_server(host.strip("[]"), port, guarded, Server, handler_class=Quiet)
    thread = threading.Thread(target=httpd.serve_forever, name="dqpose-metrics", daemon=True)
    thread.start()
    return httpd, thread


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

    def __init__(self, server, health_servicer: Health, gate: Gate, port: int, calls: Calls,
                 servicers: tuple = ()):
        self.server = server
        self.servicers = servicers
        self.health = health_servicer
        self.gate = gate
        self.port = port
        self.calls = calls
        self.metrics = calls.metrics

    async def stop(self, grace: float | None, drain: float = 0.0) -> None:
        """Health NOT_SERVING and new calls UNAVAILABLE at once; after ``drain`` s (for load
        balancers that poll health) the listener closes and health watches end; calls in flight
        get ``grace`` s more to finish (None: none), then are cancelled. Returns once every call
        is recorded: its log line flushed and its metric counted. A servicer with a
        ``stopping(seconds)`` hook hears at once how long calls have left (an arm's run that
        cannot finish by then is brought to a controlled stop)."""
        self.gate.closed = True
        for servicer in self.servicers:
            if hasattr(servicer, "stopping"):
                servicer.stopping(drain + (grace or 0.0))
        await self.health.not_serving()
        if drain > 0:
            await asyncio.sleep(drain)
        await self.health.close()
        grace = grace or 0.0
        # The grace period is timed here, on the calls this server counts, so that a stream cut
        # by it is known as cut (Calls.cut); gRPC's own limit is only a backstop for the calls
        # it alone sees (reflection).
        stopping = asyncio.ensure_future(self.server.stop(grace + 1.0))
        if not await self.calls.settled(grace):
            self.calls.cut = True
            await self.server.stop(None)    # a later stop(None) cancels what is left at once
        await stopping
        # Cancelled handlers record themselves as they unwind, after gRPC's stop returned.
        if not await self.calls.settled(5.0):
            log.warning(json.dumps({"event": "calls_not_recorded", "open": self.calls.open}))
        self.calls.flush()
        self.calls.close()
        self.calls.recorder.close()     # what it holds written, its file finished
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
    """Build, bind and start a server. Raises :class:`ConfigError` for a value the server cannot
    start with, ``OSError`` when the address cannot be bound (:class:`AddressInUse` when another
    process listens there)."""
    cfg.check()          # again: the fields may have changed since the config was made
    address = f"{cfg.host}:{cfg.port}"
    # Checked before gRPC tries: its failed bind logs a line of its own on standard error.
    if cfg.port and (problem := _listen_error(address, cfg.host, cfg.port)) is not None:
        raise problem
    try:
        metrics = (_Metrics(cfg.metrics_host, cfg.metrics_port, cfg.token)
                   if cfg.metrics_port is not None else None)
    except OSError as e:
        where = f"{cfg.metrics_host}:{cfg.metrics_port}"
        if e.errno == errno.EADDRINUSE:
            raise AddressInUse("serve metrics on", where, "metrics_port") from None
        why = (e.strerror or str(e)).lower()
        raise OSError(f"cannot serve metrics on {where}: {why}") from None
    calls = Calls(metrics, cfg.limits.workers,
                  record.NULL if cfg.recorder is None else cfg.recorder,
                  Peers(cfg.limits, cfg.token))
    if metrics is not None and cfg.recorder is not None:
        metrics.watch(cfg.recorder)
    gate = Gate(calls)
    # ReplicaHeaders first (outermost): refused calls carry the replica's name too
    interceptors = [routing.ReplicaHeaders(cfg.replica_name), gate] + (
        [BearerTokenAuth(cfg.token, calls)] if cfg.token else [])
    server = grpc.aio.server(options=server_options(cfg), interceptors=interceptors)
    world = World(cfg, calls)
    servicers = tuple(world if cls is World else cls(cfg, calls) for cls in SERVICERS)
    for s in servicers:
        if isinstance(s, Trajectories):
            s.world = world.domain_world       # made when a waypoint first names a frame
    for servicer in servicers:
        servicer.register(server)
    health_servicer = Health(calls.peers)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection_pb2_grpc.add_ServerReflectionServicer_to_server(_Reflection(SERVICE_NAMES), server)
    try:
        if cfg.tls_cert:            # cfg.check(): with its key, and both load
            assert cfg.tls_key is not None
            creds = grpc.ssl_server_credentials(
                [(cfg.tls_key, cfg.tls_cert)], root_certificates=cfg.client_ca or None,
                require_client_auth=bool(cfg.client_ca))
            port = server.add_secure_port(address, creds)
        else:
            port = server.add_insecure_port(address)
    except RuntimeError as e:  # grpc reports a failed bind as RuntimeError
        if metrics is not None:
            metrics.close()
        raise (_listen_error(address, cfg.host, cfg.port)
               or OSError(f"cannot listen on {address}: {e}")) from None
    if port == 0:
        raise OSError(f"cannot listen on {address}")
    await server.start()
    await health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    for cls in SERVICERS:
        await health_servicer.set(cls.NAME, health_pb2.HealthCheckResponse.SERVING)
    if cfg.recorder is not None:
        await health_servicer.follow(cfg.recorder)
    return Running(server, health_servicer, gate, port, calls, servicers)


#: s calls in flight get to finish after a Ctrl-C (SIGINT), at most (``grace_s`` if shorter)
INTERRUPT_GRACE = 0.25


async def serve(cfg: ServerConfig, ready=None) -> int:
    """Run until SIGTERM/SIGINT, then shut down gracefully (:meth:`Running.stop`): after SIGTERM
    with the config's drain and grace; after SIGINT (a Ctrl-C at a terminal, where no load
    balancer polls health) without the drain and with a grace of :data:`INTERRUPT_GRACE` at most,
    and a second SIGINT raises ``KeyboardInterrupt`` at once. Returns the exit code (0)."""
    running = await start(cfg)
    # What the imports and the start made lives as long as the process: kept out of the garbage
    # collector's reach, a full collection scans only what came since. Else one (~50k objects,
    # 10-40 ms here) now and then stalls every stream the loop serves.
    gc.freeze()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    interrupted = False

    def closing(sig):
        nonlocal interrupted
        # At once, in the signal's own callback: a call that gRPC hands over after this one is
        # refused, whatever else the loop has queued.
        running.gate.closed = True
        if sig == signal.SIGINT:
            interrupted = interrupted or not stop.is_set()
            loop.remove_signal_handler(signal.SIGINT)   # the next one is Python's own
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, closing, sig)
    log.info(json.dumps({"event": "serving", "address": f"{cfg.host}:{running.port}",
                         "tls": bool(cfg.tls_cert), "mtls": bool(cfg.client_ca),
                         "auth": "bearer" if cfg.token else "none",
                         "metrics_port": cfg.metrics_port, "replica": cfg.replica_name}))
    if ready is not None:
        ready(running)
    flusher = asyncio.create_task(running.calls.flush_periodically(0.25))
    await stop.wait()
    running.calls.flush()
    drain, grace = (0.0, min(cfg.grace_s, INTERRUPT_GRACE)) if interrupted else \
        (cfg.drain_s, cfg.grace_s)
    log.info(json.dumps({"event": "shutting_down", "drain_s": drain, "grace_s": grace}))
    await running.stop(grace, drain)
    flusher.cancel()
    log.info(json.dumps({"event": "stopped"}))
    return 0
