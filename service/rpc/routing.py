"""Routing headers: which replica answered, and which world a call belongs to.

Behind a load balancer several ``dqpose serve`` replicas answer one address. State lives in a
replica (a ``StreamFuse`` stream's windows, a named world), so every call that touches one world
carries its name in ``x-dqpose-world`` and the balancer hashes that header onto one replica
(``docker/haproxy.cfg``, ``docker/nginx.conf``, ``deploy/kubernetes/envoy.yaml``); calls without
it are balanced per call. Every answer carries the replica's name in ``x-dqpose-replica``, in its
initial metadata and in its trailers (a call refused before its handler runs has trailers only,
so that retry policies may retry it), so a client sees where its world lives and when it moved.
"""
from __future__ import annotations

import inspect

import grpc

from dqpose.errors import FieldError

WORLD_HEADER = "x-dqpose-world"
REPLICA_HEADER = "x-dqpose-replica"
#: characters a world's name may have: a header value a proxy passes untouched and hashes as is
MAX_WORLD_NAME = 128
#: a host name's length at most (the default replica name is the host's)
MAX_REPLICA_NAME = 253


def check_name(setting: str, name: object, limit: int) -> str:
    """``name`` when it is a string of printable ASCII without spaces of at most ``limit``
    characters (what an HTTP/2 header value carries unchanged); ValueError naming ``setting``."""
    if not isinstance(name, str):
        raise ValueError(f"{setting}: must be a string, got {type(name).__name__}")
    if len(name) > limit:
        raise ValueError(f"{setting}: {len(name)} characters, over the {limit} allowed")
    if not all("!" <= c <= "~" for c in name):
        raise ValueError(f"{setting}: only printable ASCII without spaces, got {name!r}")
    return name


def world_of(context) -> str:
    """The world a call names in ``x-dqpose-world`` ("" when it names none: the default world).
    A malformed name is a :class:`~dqpose.errors.FieldError` naming the header (the servicers'
    call wrapper answers INVALID_ARGUMENT)."""
    for key, value in context.invocation_metadata() or ():
        if key == WORLD_HEADER:
            try:
                return check_name(WORLD_HEADER, value, MAX_WORLD_NAME)
            except ValueError as e:
                raise FieldError(str(e)) from None
    return ""


class ReplicaHeaders(grpc.aio.ServerInterceptor):
    """Puts ``x-dqpose-replica: <name>`` in every answer's initial metadata and trailers. The
    outermost interceptor, so that calls another interceptor refuses carry it too. A method's
    wrapped handler is kept while the handler beneath it stays the same object (the registered
    ones do), so a call costs one dictionary look-up more."""

    def __init__(self, replica: str):
        self.metadata = ((REPLICA_HEADER, replica),)
        self._wrapped: dict[str, tuple] = {}

    async def intercept_service(self, continuation, details):
        handler = await continuation(details)
        if handler is None:
            return None
        kept = self._wrapped.get(details.method)
        if kept is not None and kept[0] is handler:
            return kept[1]
        wrapped = _with_metadata(handler, self.metadata)
        self._wrapped[details.method] = (handler, wrapped)
        return wrapped


def trailers_only(behavior):
    """Marks a handler that refuses its call before any work (shutting down, no token): its
    answer carries the replica in its trailers only. gRPC commits a call once response headers
    arrive and never retries it after that; a refusal without them is retried by a client's
    retry policy, on another replica behind a balancer."""
    behavior.trailers_only = True
    return behavior


def _with_metadata(handler, metadata):
    """``handler`` with ``metadata`` sent first and set as its trailers (``context.abort`` keeps
    trailers set before it); trailers only for a :func:`trailers_only` refusal."""
    kind = ("stream" if handler.request_streaming else "unary",
            "stream" if handler.response_streaming else "unary")
    behavior = getattr(handler, f"{kind[0]}_{kind[1]}")
    refusal = getattr(behavior, "trailers_only", False)

    async def headers(context):
        context.set_trailing_metadata(metadata)
        if not refusal:
            await context.send_initial_metadata(metadata)

    if inspect.isasyncgenfunction(behavior):
        async def answers(request, context):
            await headers(context)
            async for answer in behavior(request, context):
                yield answer
        new = answers
    else:
        async def answer(request, context):
            await headers(context)
            result = behavior(request, context)
            return (await result) if inspect.isawaitable(result) else result
        new = answer
    make = {("unary", "unary"): grpc.unary_unary_rpc_method_handler,
            ("unary", "stream"): grpc.unary_stream_rpc_method_handler,
            ("stream", "unary"): grpc.stream_unary_rpc_method_handler,
            ("stream", "stream"): grpc.stream_stream_rpc_method_handler}[kind]
    return make(new, request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer)
