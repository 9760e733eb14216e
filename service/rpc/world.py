"""The ``dqpose.v1.World`` service: named worlds (``x-dqpose-world``, the default world ""), each a
:class:`dqpose.world.World` fed by any number of ``Publish`` streams and read by ``Subscribe``
streams and ``Lookup``.

A world is made by the first Configure, Publish or Subscribe that names it, at most
:data:`MAX_WORLDS` named ones a server; a Lookup (or a Plan's waypoint frame) naming a world this
server does not hold is NOT_FOUND. Streams make their world because behind a load balancer a
world moves to another replica when its replica leaves: its producers and subscribers reopen
there in any order (:mod:`dqpose.rpc.resume`) and must find it, as a Subscribe finds a body that
has no measurement yet; a point query has nothing to answer from an empty world.

Arrival order is each world's one order: each Publish request is applied under its world's lock
in the worker pool, and the Subscribe answers it makes due (:mod:`dqpose.world_ticks`) are fused
there and then, under the same lock, and queued to their subscribers in that order. So the
answers depend on the sequence of requests the world received, never on when a subscriber
reads, and a recording of the arrivals replays to the same answers.
"""
from __future__ import annotations

import asyncio
import logging
import math
import threading
from typing import Any, Callable

import grpc
import numpy as np
from google.protobuf.message import DecodeError

from dqpose import limits as _limits
from dqpose import world as domain
from dqpose.errors import FieldError
from dqpose.names import name_problem
from dqpose.rpc import DEFAULT_MAX_POSES, world_record
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.calls import Calls, readable, refused
from dqpose.rpc.checks import over_count
from dqpose.rpc.fusion_convert import measurements_to_arrays
from dqpose.rpc.peers import SUBSCRIPTION, FellBehind, Slot, exhausted
from dqpose.rpc.routing import WORLD_HEADER, world_of
from dqpose.rpc.wire import messages_wire, publish_from_wire, wire_rows
from dqpose.rpc.world_convert import (
    body_pose_bytes,
    config_from_msg,
    config_msg,
    published_errors,
    subscribe_names,
)
from dqpose.rpc.world_ready import Ready
from dqpose.world_ticks import Ticks, tick_phase

log = logging.getLogger("dqpose.server")

#: answers queued for one subscriber, and their bytes (an answer lists its window's
#: measurements: ~2 kB at 300, up to ~80 kB); a subscriber that falls further behind is ended
#: with RESOURCE_EXHAUSTED at once, its queue and slots freed (its answers would otherwise grow
#: without bound). How many are open: dqpose.rpc.peers.
MAX_QUEUED = 4096
MAX_QUEUED_BYTES = 8 << 20
#: bytes of answers in one SubscribeBatches message at most (gRPC clients receive 4 MiB by
#: default); an answer larger than this goes alone
MAX_BATCH_BYTES = 1 << 20
#: producer names a world remembers (each one's acked_through); the oldest-acked is forgotten
#: beyond
MAX_PRODUCERS = 4096
#: named worlds one server holds (the default world "" besides them): each has its own tables
#: (bodies within its bounds, MAX_PRODUCERS acks), so their number is what bounds a server's
#: memory; a call that would make one more is RESOURCE_EXHAUSTED before anything is made. A
#: cluster's worlds spread over its replicas, and a replica keeps a world it held until it
#: restarts (a moved world's state is soft), so size it to the worlds of the whole cluster.
MAX_WORLDS = 256


class UnknownWorld(LookupError):
    """A Lookup (or a Plan's frame) naming a world the server does not hold: NOT_FOUND."""


class TooManyWorlds(Exception):
    """A call that would make a world past :data:`MAX_WORLDS`: RESOURCE_EXHAUSTED."""


def status_of(e: Exception, rpc: str = "World") -> tuple[grpc.StatusCode, str]:
    """The status a World call ends with for ``e``: the domain's NotFound is NOT_FOUND, its
    OutOfRange FAILED_PRECONDITION, WorldError INVALID_ARGUMENT, anything else as every
    servicer (:func:`refused`)."""
    if isinstance(e, (domain.NotFound, UnknownWorld)):
        return grpc.StatusCode.NOT_FOUND, readable(str(e).strip("'\""))
    if isinstance(e, TooManyWorlds):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, readable(str(e))
    if isinstance(e, domain.OutOfRange):
        return grpc.StatusCode.FAILED_PRECONDITION, readable(str(e).strip("'\""))
    return refused(rpc, e)         # rpc: how a log line names the call (and its world)


def _named(rpc: str, world: str) -> str:
    """How a log line names a World call: the RPC and its world."""
    return f"World/{rpc} in world {world!r}"


def _recorded_world(context) -> str:
    """The world a recorded call is in; a malformed header records "" (the call itself is
    refused with the header's error where its world is looked up)."""
    try:
        return world_of(context)
    except FieldError:
        return ""


class Subscription:
    """One Subscribe stream: its bodies (None: all), pacing per body, and the queue of its
    answers (serialized ``FusedPose`` messages, filled by the publishing thread through the
    event loop, in arrival order), at most :data:`MAX_QUEUED` answers and
    :data:`MAX_QUEUED_BYTES` bytes. ``ended`` says why the server ended it (None: open)."""

    def __init__(self, bodies, rate: float, relative_to: str, loop, max_delay: float,
                 window: float):
        self.bodies = set(bodies) if bodies else None
        self.rate, self.relative_to = rate, relative_to
        self.loop = loop
        self.max_delay, self.window = max_delay, window
        self.ticks: dict[str, Ticks] = {}
        self.queue: asyncio.Queue = asyncio.Queue()
        self.queued = 0                     # bytes in the queue
        self.ended: str | None = None
        # called once when ended (its slots freed)
        self.on_end: Callable[[], None] | None = None

    def wants(self, body: str) -> bool:
        return self.bodies is None or body in self.bodies

    def due(self, body: str, source: str, taken: float) -> list[float]:
        t = self.ticks.get(body)
        if t is None:
            t = self.ticks[body] = Ticks(self.rate, self.max_delay,
                                         tick_phase(body) if self.rate else 0.0, self.window)
        return t.arrive(source, taken)

    def deliver(self, answers: list) -> None:
        """On the event loop: queue ``answers``; past a bound the subscription is ended."""
        if self.ended is not None:
            return
        size = sum(map(len, answers))
        if self.queue.qsize() + len(answers) > MAX_QUEUED:
            self.end(f"this subscriber fell {MAX_QUEUED} answers behind the world (MAX_QUEUED)")
        elif self.queued + size > MAX_QUEUED_BYTES:
            self.end(f"this subscriber fell {MAX_QUEUED_BYTES} bytes of answers behind the "
                     f"world (MAX_QUEUED_BYTES)")
        else:
            self.queued += size
            for a in answers:
                self.queue.put_nowait(a)

    def end(self, why: str) -> None:
        """On the event loop: ends the subscription at once: its queue emptied, its slots
        freed (``on_end``), its reader woken by a None."""
        if self.ended is not None:
            return
        self.ended = why
        while not self.queue.empty():
            self.queue.get_nowait()
        self.queued = 0
        self.queue.put_nowait(None)
        if self.on_end is not None:
            self.on_end()

    def take(self) -> bytes | None:
        """The next answer queued (there is one); None once ended."""
        return self._taken(self.queue.get_nowait())

    async def next(self) -> bytes | None:
        """The next answer, once there is one; None once ended."""
        return self._taken(await self.queue.get())

    def _taken(self, a: bytes | None) -> bytes | None:
        if a is not None:
            self.queued -= len(a)
        return a


def _ready(first: bytes, sub: Subscription) -> tuple[list, bytes | None]:
    """``first`` and the answers queued behind it, up to MAX_BATCH_BYTES: one SubscribeBatches
    message; and the answer that did not fit."""
    answers, size = [first], len(first)
    while sub.ended is None and not sub.queue.empty():
        a = sub.take()
        assert a is not None            # a None is queued only once ended
        if size + len(a) > MAX_BATCH_BYTES:
            return answers, a
        size += len(a)
        answers.append(a)
    return answers, None


class Cell:
    """One world of the server: its :class:`dqpose.world.World` (made at first use), its
    producers' acks, its subscriptions and its counters, all under its one lock; the World RPCs'
    work, request in, response out, no transport."""

    def __init__(self, name: str, limits=None, max_poses: int = DEFAULT_MAX_POSES):
        self.name = name
        self.limits, self.max_poses = limits, max_poses
        self._world: domain.World | None = None
        self._making = threading.Lock()      # not self.lock: first used while it is held
        self.lock = threading.Lock()
        self.acked: dict[str, int] = {}      # producer -> acked_through
        self.subscriptions: set[Subscription] = set()
        self.requests = 0                    # Publish requests, in arrival order
        self.measurements = 0                # measurements numbered in arrival order
        self.ready = Ready()                 # Lookups answered on the event loop

    @property
    def world(self) -> domain.World:
        """The domain world, made on first use (a server that never uses it pays nothing)."""
        if self._world is None:
            with self._making:
                if self._world is None:
                    self._world = domain.World(tracker=_limits.tracker_bounds(
                        self.limits or _limits.DEFAULT))
        return self._world

    # -- request -> response, no transport

    def configure(self, request: pb.WorldConfig) -> pb.WorldConfig:
        sources, arms, options = config_from_msg(request)
        with self.lock:
            try:
                self.world.configure(sources=sources, arms=arms, options=options)
            except domain.WorldError as e:
                raise FieldError(e.named("config")) from None
            return config_msg(self.world.sources, self.world.arms, self.world.options)

    def lookup(self, request: pb.LookupRequest) -> bytes:
        """A ``RelativePose``, serialized (:mod:`dqpose.rpc.world_ready` keeps it)."""
        if not math.isfinite(request.time):
            raise FieldError(f"time: must be finite (0: the newest both are known at), got "
                             f"{request.time!r}")
        # Not under the cell's lock, which a Publish request holds while its Subscribe answers
        # are fitted: the world is read beside them (dqpose.world's read/write lock). It sees
        # whole requests (each ingested in one write), and a fit is a function of the data
        # alone, so neither answer depends on the timing.
        return self.ready.lookup(self.world, request)

    def publish(self, request: pb.PublishRequest, r: int, producer: str,
                data: bytes | None = None) -> pb.PublishAck:
        """Request ``r`` of a Publish call (``producer``: its key for acks): applied to the world,
        its Subscribe answers made and queued, its ack returned; never raises for bad input.
        ``data``: the request's bytes, whose measurements are then read in C."""
        ack = pb.PublishAck()
        field = f"requests[{r}].measurements"

        def error(i: int, text: str) -> None:
            ack.errors.add(request=r, measurement=i, details=readable(text))

        named = name_problem(request.producer, empty=True)     # "": anonymous, one per call
        with self.lock:
            if named is not None:
                self.requests += 1
                error(-1, f"requests[{r}].producer: {named}; none of it was used")
                return ack
            seq = request.sequence
            known = self.acked.get(producer)
            last = known or 0
            ack.acked_through = last
            if seq and seq <= last:
                error(-1, f"requests[{r}]: sequence {seq} already in the world (acked through "
                          f"{last}); not fused again")
                return ack
            # a producer's first request names no gap: the world may have moved here from a
            # replica that holds the producer's earlier requests (docs/deploy.md)
            if known is not None and seq > last + 1:
                error(-1, f"requests[{r}]: sequences {last + 1}..{seq - 1} of producer "
                          f"{producer!r} never arrived")
            too_many = over_count(field, len(request.measurements), self.max_poses,
                                  "measurements")
            if too_many is None:
                self._apply(request, field, error, data, producer)
            else:
                error(-1, f"{too_many}; none was used")
            self.requests += 1
            if seq:
                self.acked[producer] = ack.acked_through = seq
                if len(self.acked) > MAX_PRODUCERS:
                    del self.acked[min(self.acked, key=self.acked.__getitem__)]
        return ack

    def publish_bytes(self, data: bytes, r: int, anonymous: str) -> pb.PublishAck:
        """:meth:`publish` of request ``r``'s bytes (``anonymous``: the producer key of a
        request that names none); bytes that are not a PublishRequest are an ack error."""
        try:
            request = pb.PublishRequest.FromString(data)
        except DecodeError:
            with self.lock:
                self.requests += 1
            ack = pb.PublishAck()
            ack.errors.add(request=r, measurement=-1, details=(
                f"requests[{r}]: not a valid dqpose.v1.PublishRequest message; none of it was "
                f"used"))
            return ack
        return self.publish(request, r, request.producer or anonymous, data)

    def _apply(self, request: pb.PublishRequest, field: str, error,
               data: bytes | None = None, producer: str | None = None) -> None:
        """Under the lock: the request's measurements (of ``producer``) into the world, then the
        answers they make due. From ``data`` its measurements are decoded and checked in C
        where they are plain (the same rows and texts; the rows C passed are not checked
        again)."""
        w = None if data is None else publish_from_wire(data)
        errors: list = []
        codes = None
        if data is None or w is None:
            m = measurements_to_arrays(request.measurements, field, errors)
        else:
            m, errors, codes = wire_rows(data, w, field)
        for i, e in errors:
            error(i, str(e))
        ids = self.measurements + m.index
        self.measurements += len(request.measurements)
        if not len(m.index):
            return
        published = self.world.ingest(m.bodies, m.sources, m.times, m.poses, m.covariances,
                                      codes, producer)
        bad = published_errors(published, m.index, field)
        for i, text in bad:
            error(i, text)
        self._answer_subscriptions(m, ids, {i for i, _ in bad})
        self.ready.refresh(self.world, published.bodies)

    def _answer_subscriptions(self, m, ids, refused_rows: set) -> None:
        """The Subscribe answers the request's rows (``m``, numbered ``ids``) make due, within
        the request's :class:`dqpose.limits.Budget` (all subscriptions together), fitted and
        queued to their subscribers."""
        if not self.subscriptions:
            return
        latency = {s.name: s.latency for s in self.world.sources}
        cache: dict[tuple[str, float, str], Any] = {}
        budget = _limits.Budget(self.world.tracker_bounds)
        for sub in list(self.subscriptions):
            if sub.ended is not None:       # ended on the event loop, not yet taken out
                continue
            due: list[tuple[str, float, int]] = []
            for k in range(len(m.index)):
                body = m.bodies[k]
                if int(m.index[k]) in refused_rows or not sub.wants(body):
                    continue
                source = m.sources[k]
                taken = float(m.times[k]) - latency.get(source, 0.0)
                due += [(body, t, int(ids[k])) for t in sub.due(body, source, taken)]
            due, answers = self._affordable(due, sub.relative_to, cache, budget)
            for body, t, last in due:
                key = (body, t, sub.relative_to)
                if key not in cache:
                    # written once here for every subscriber it goes to
                    cache[key] = self._answer(body, t, sub.relative_to, last)
                answers.append(cache[key])
            if answers:
                sub.loop.call_soon_threadsafe(sub.deliver, answers)

    def _affordable(self, due: list, relative_to: str, cache: dict,
                    budget: _limits.Budget) -> tuple[list, list]:
        """``due`` ``(body, tick, id)`` less the ticks the request's ``budget`` cannot afford, and
        an error entry (serialized) per body with ticks skipped: a fit not in ``cache`` costs
        what it fuses (with ``relative_to``, the relative pose's fits besides), a body's oldest
        ticks are skipped and its latest kept."""
        new: dict[str, list[int]] = {}
        for j, (b, t, _) in enumerate(due):
            if (b, t, relative_to) not in cache:
                new.setdefault(b, []).append(j)
        world, options = self.world, self.world.options
        correlated = options.acceleration_psd is not None and bool(
            np.any(options.acceleration_psd))
        skip: set[int] = set()
        errors = []
        r = self.requests
        for b, js in new.items():
            lo, hi = min(due[j][1] for j in js), max(due[j][1] for j in js)
            rows = world.rows_near(b, lo, hi)
            if relative_to:
                rows += rows + world.rows_near(relative_to, lo, hi)
            take, cost = budget.take(len(js), rows, options.robust, correlated)
            if take < len(js):
                gone = js[:len(js) - take]
                skip.update(gone)
                e = budget.skipped(f"request {r}", b, f"{len(gone)} ticks from "
                                   f"{due[gone[0]][1]:.6g} s to {due[gone[-1]][1]:.6g} s", cost)
                errors.append(fpb.FusedPose(body=b, request=r, error=fpb.FuseError(
                    request=r, measurement=-1, details=readable(str(e)))).SerializeToString())
        if skip:
            due = [d for j, d in enumerate(due) if j not in skip]
        return due, errors

    def _answer(self, body: str, t: float, relative_to: str, last_id: int) -> bytes:
        """Body ``body`` at tick ``t`` (relative to ``relative_to`` when set), or an error
        entry naming why it cannot be answered: a ``FusedPose``'s bytes."""
        r = self.requests
        try:
            p = self.world.pose(body, t)
            if relative_to:
                rel = self.world.relative(relative_to, body, t)
                p = domain.BodyPose(body, rel.time, rel.pose, rel.covariance, p.fused)
        except (ValueError, LookupError) as e:
            return fpb.FusedPose(body=body, time=t, request=r, error=fpb.FuseError(
                request=r, measurement=-1, details=readable(f"body {body!r} at {t:.6g} s: {e}"))
            ).SerializeToString()
        return body_pose_bytes(p, r, [last_id])


class World:
    """The ``dqpose.v1.World`` service: the server's worlds by name (:class:`Cell` each; the
    Trajectories service resolves ``Waypoint.frame`` through the one its call names)."""

    NAME = pb.DESCRIPTOR.services_by_name["World"].full_name

    def __init__(self, cfg=None, calls: Calls | None = None):
        self.max_poses = cfg.max_poses if cfg is not None else DEFAULT_MAX_POSES
        self.limits = cfg.limits if cfg is not None else None
        self.replica = getattr(cfg, "replica_name", "")
        self.calls = calls or Calls()
        self.cells: dict[str, Cell] = {}
        self._making = threading.Lock()

    def cell(self, name: str, make: bool = False) -> Cell:
        """World ``name`` ("" the default, made at first use): made when ``make`` (Configure,
        Publish, Subscribe), else :class:`UnknownWorld`; past :data:`MAX_WORLDS` named ones,
        :class:`TooManyWorlds` before anything is made."""
        cell = self.cells.get(name)
        if cell is not None:
            return cell
        if name and not make:
            raise UnknownWorld(f"{WORLD_HEADER}: no world {name!r} on replica {self.replica!r} "
                               f"(a world is made by the first Configure, Publish or Subscribe "
                               f"naming it)")
        with self._making:
            cell = self.cells.get(name)
            made = cell is None
            if cell is None:
                named = len(self.cells) - ("" in self.cells)
                if name and named >= MAX_WORLDS:
                    raise TooManyWorlds(f"{WORLD_HEADER}: world {name!r} would be named world "
                                        f"{named + 1} on replica {self.replica!r}, above its "
                                        f"{MAX_WORLDS} (MAX_WORLDS)")
                cell = self.cells[name] = Cell(name, self.limits, self.max_poses)
        if made:        # a recorded world records every body (the recorder's own subscriber)
            world_record.follow(cell, self.calls.recorder)
        return cell

    def called(self, context, make: bool = False) -> Cell:
        """The world a call names (:func:`routing.world_of`)."""
        return self.cell(world_of(context), make)

    def domain_world(self, name: str) -> domain.World:
        """World ``name``'s :class:`dqpose.world.World`, for a Plan's waypoint frames."""
        return self.cell(name).world

    # -- RPCs

    def register(self, server) -> None:
        handlers: dict[str, grpc.RpcMethodHandler[Any, Any]] = {
            "Configure": grpc.unary_unary_rpc_method_handler(
                self.Configure, request_deserializer=pb.WorldConfig.FromString,
                response_serializer=pb.WorldConfig.SerializeToString),
            "Publish": grpc.stream_stream_rpc_method_handler(
                self.Publish, request_deserializer=None,
                response_serializer=pb.PublishAck.SerializeToString),
            # answers are FusedPose messages serialized when made (_apply)
            "Subscribe": grpc.unary_stream_rpc_method_handler(
                self.Subscribe, request_deserializer=pb.SubscribeRequest.FromString,
                response_serializer=None),
            "SubscribeBatches": grpc.unary_stream_rpc_method_handler(
                self.SubscribeBatches, request_deserializer=pb.SubscribeRequest.FromString,
                response_serializer=None),
            # answers are RelativePose messages serialized when made (world_ready)
            "Lookup": grpc.unary_unary_rpc_method_handler(
                self.Lookup, request_deserializer=pb.LookupRequest.FromString,
                response_serializer=None),
        }
        generic = grpc.method_handlers_generic_handler(self.NAME, handlers)
        server.add_generic_rpc_handlers((generic,))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def _unary(self, rpc: str, fn, request, context, make: bool = False):
        world = _recorded_world(context)
        return await self.calls.unary(
            rpc, lambda r: self.calls.work(fn, self.called(context, make), r), request, context,
            status=lambda _, e: status_of(e, _named(rpc, world)), world=world)

    async def Configure(self, request, context):
        # recording (dqpose.rpc.world_record)
        rec = self.calls.recorder.call(f"{self.NAME}/Configure", pb.WorldConfig, pb.WorldConfig,
                                       _recorded_world(context))
        return await self._unary(
            "Configure", lambda cell, r: world_record.configure(cell, rec, r), request, context,
            make=True)

    async def Lookup(self, request, context):
        world = _recorded_world(context)
        return await self.calls.unary("Lookup", lambda r: self._lookup(r, context), request,
                                      context, status=lambda _, e: status_of(
                                          e, _named("Lookup", world)), world=world)

    async def _lookup(self, request, context) -> bytes:
        cell = self.called(context)
        # a kept answer that is still the answer: a dict read and a stamp, on the loop
        kept = cell.ready.answer(cell.world, request)
        if kept is not None:
            return kept
        return await self.calls.work(Cell.lookup, cell, request)

    async def Publish(self, request_iterator, context):
        t0 = self.calls.begin()
        code, r = "OK", 0
        anonymous = f"\0call{id(context)}"
        cell = None
        world = _recorded_world(context)
        # recording (dqpose.rpc.world_record)
        rec = self.calls.recorder.call(f"{self.NAME}/Publish", pb.PublishRequest, pb.PublishAck,
                                       world)
        try:
            try:
                cell = self.called(context, make=True)
            except Exception as e:
                status, details = status_of(e, _named("Publish", world))
                code = status.name
                await context.abort(status, details)
            if self.calls.open_stream("Publish", context) is None:
                code = "RESOURCE_EXHAUSTED"
                return
            # Registered without a deserializer: each request is parsed with its work in the
            # worker pool (publish_bytes), never on the event loop.
            async for data in request_iterator:
                await context.write(await self.calls.work(world_record.publish, cell, rec, data,
                                                          r, anonymous))
                r += 1
        except grpc.aio.AbortError:
            raise
        except Exception as e:
            code = self.calls.failure_code(e)
            await self.calls.failed(_named("Publish", world), e, context)
        except BaseException:
            code = "CANCELLED"
            raise
        finally:
            if cell is not None and anonymous in cell.acked:
                with cell.lock:
                    cell.acked.pop(anonymous, None)
            rec.end(code)       # recording
            self.calls.done("Publish", code, t0, context, messages=r, world=world)

    async def Subscribe(self, request, context):
        await self._subscribe("Subscribe", request, context)

    async def SubscribeBatches(self, request, context):
        await self._subscribe("SubscribeBatches", request, context)

    async def _subscribe(self, rpc: str, request, context):
        """Subscribe, or SubscribeBatches (``rpc``): the answers ready at each write in one
        FusedPoseBatch. Both are recorded as Subscribe: the same answers in the same order."""
        t0 = self.calls.begin()
        code, sent = "OK", 0
        sub = added = cell = None
        world = _recorded_world(context)
        # recording (dqpose.rpc.world_record)
        rec = self.calls.recorder.call(f"{self.NAME}/Subscribe", pb.SubscribeRequest,
                                       fpb.FusedPose, world)
        try:
            cell, problem = self._admit(request, context, _named(rpc, world))
            if problem is not None:
                code = problem[0].name
                await context.abort(problem[0], problem[1])
            assert cell is not None
            slot = self.calls.open_stream(rpc, context, SUBSCRIPTION, cell.name)
            if slot is None:
                code = "RESOURCE_EXHAUSTED"
                return
            options = cell.world.options
            sub = Subscription(request.bodies, request.rate_hz, request.relative_to,
                               asyncio.get_running_loop(), options.max_delay, options.window)
            sub.on_end = slot.end
            # In the world at once when its lock is free, with nothing since the headers went
            # that yields to another call (dqpose.rpc.replay_remote waits for the headers);
            # else in the pool, never waiting on the event loop for a Publish request's fits.
            added = _at_once(cell, sub, rec, request) or asyncio.ensure_future(
                self.calls.work(_subscribed, cell, sub, rec, request))
            await asyncio.shield(added)
            sent, code = await self._answers(rpc, sub, slot, context, rec)
        except asyncio.CancelledError:
            code = "CANCELLED"
            raise
        finally:
            try:
                if added is not None:
                    assert sub is not None and cell is not None
                    sub.end(sub.ended or "the call ended")
                    await asyncio.shield(self._leave(added, cell, sub, rec, code))
                else:
                    rec.end(code)               # recording
            finally:
                self.calls.done(rpc, code, t0, context, messages=sent, world=world)

    def _admit(self, request, context, named: str) -> tuple[Cell | None, tuple | None]:
        """The world a Subscribe request names, or why it is refused before it takes a slot:
        ``(cell, None)`` or ``(None or cell, (status, details))`` (``named``: the call, as a
        log line names it)."""
        if not (math.isfinite(request.rate_hz) and request.rate_hz >= 0.0):
            return None, (grpc.StatusCode.INVALID_ARGUMENT,
                          f"rate_hz: must be finite and >= 0 (0: every update), got "
                          f"{request.rate_hz!r}")
        if self.limits is not None and request.rate_hz > self.limits.max_output_rate:
            return None, (grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"rate_hz: {request.rate_hz:.6g} Hz, over the server's limit "
                          f"max_output_rate = {self.limits.max_output_rate:.6g} Hz")
        try:
            cell = self.called(context, make=True)
        except Exception as e:
            return None, status_of(e, named)
        too_many = over_count("bodies", len(request.bodies), cell.world.bounds.max_bodies,
                              "bodies")
        if too_many is not None:
            return cell, (grpc.StatusCode.RESOURCE_EXHAUSTED, too_many)
        bad = subscribe_names(request)
        return cell, None if bad is None else (grpc.StatusCode.INVALID_ARGUMENT, bad)

    async def _leave(self, added, cell: Cell, sub: Subscription, rec, code: str) -> None:
        """``sub`` out of its world once it is in (the pool may run both at once)."""
        await added
        await self.calls.work(_unsubscribed, cell, sub, rec, code)

    async def _answers(self, rpc: str, sub: Subscription, slot: Slot, context,
                       rec) -> tuple[int, str]:
        """Writes ``sub``'s answers until the server ends it (its client fell behind a bound:
        RESOURCE_EXHAUSTED, not waiting for the client to read it); ``(answers sent, the
        status's name)``."""
        batched = rpc == "SubscribeBatches"
        carry, sent = None, 0
        while sub.ended is None:
            first = carry if carry is not None else await sub.next()
            if first is None:
                break
            answers, carry = _ready(first, sub) if batched else ([first], None)
            try:
                await self.calls.peers.write(
                    context, messages_wire(answers) if batched else first, rpc)
            except FellBehind as e:
                sub.end(str(e))
                return sent, await exhausted(context, str(e), slot)
            for answer in answers:
                rec.fused(answer)       # recording
            sent += len(answers)
        return sent, await exhausted(context, f"{rpc}: {sub.ended}; subscribe to fewer bodies "
                                              f"or a lower rate_hz", slot)


def _subscribed(cell: Cell, sub: Subscription, rec, request, wait: bool = True) -> bool:
    """Under the world's lock: ``sub`` answered from the next Publish request on; False when
    not ``wait`` and the lock (or the recording's order, dqpose.rpc.world_record) is held."""
    order = world_record.ORDER if rec.alive else None
    if order is not None and not order.acquire(wait):
        return False
    try:
        if not cell.lock.acquire(wait):
            return False
        try:
            cell.subscriptions.add(sub)
            rec.measurements(request)       # recording
        finally:
            cell.lock.release()
    finally:
        if order is not None:
            order.release()
    return True


def _at_once(cell: Cell, sub: Subscription, rec, request) -> asyncio.Future | None:
    """:func:`_subscribed` without waiting: a done future, or None when the lock is held."""
    if not _subscribed(cell, sub, rec, request, wait=False):
        return None
    done = asyncio.get_running_loop().create_future()
    done.set_result(True)
    return done


def _unsubscribed(cell: Cell, sub: Subscription, rec, code: str) -> None:
    with world_record.ordered(rec), cell.lock:
        cell.subscriptions.discard(sub)
        rec.end(code)                   # recording
