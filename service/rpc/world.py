"""The ``dqpose.v1.World`` service: named worlds (``x-dqpose-world``, the default world ""), each a
:class:`dqpose.Hub` (its :class:`dqpose.world.World` and its order) fed by any number of
``Publish`` streams and read by ``Subscribe`` streams and ``Lookup``; here each call's request is
decoded, handed to its world and its answers encoded and written.

A world is made by the first Configure, Publish or Subscribe that names it, at most
:data:`MAX_WORLDS` named ones a server; a Lookup (or a Plan's waypoint frame) naming a world this
server does not hold is NOT_FOUND. Streams make their world because behind a load balancer a
world moves to another replica when its replica leaves: its producers and subscribers reopen
there in any order (:mod:`dqpose.rpc.resume`) and must find it, as a Subscribe finds a body that
has no measurement yet; a point query has nothing to answer from an empty world.

Arrival order is each world's one order: each Publish request is one step of its hub in the
worker pool, and the Subscribe answers it makes due are fused there and then, under the hub's
lock, and queued to their subscribers in that order; a recorded call records its steps in that
order (the hooks the hub runs under its lock). So the answers depend on the sequence of requests
the world received, never on when a subscriber reads, and a recording of the arrivals replays to
the same answers.
"""
from __future__ import annotations

import asyncio
import logging
import math
import threading
from typing import Any, Callable

import grpc

from dqpose import limits as _limits
from dqpose import record
from dqpose import world as domain
from dqpose.errors import FieldError, Infeasible, WorldInfeasible
from dqpose.fusion.bounds import TrackerBounds
from dqpose.hub import Hub, Interest, Subscription
from dqpose.rpc import DEFAULT_MAX_POSES, world_publish, world_wait
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.calls import Call, Calls, readable, refused
from dqpose.rpc.checks import over_count
from dqpose.rpc.peers import SUBSCRIPTION, FellBehind, ReadAhead, Slot, exhausted, read_all
from dqpose.rpc.routing import WORLD_HEADER, world_of
from dqpose.rpc.wire import messages_wire
from dqpose.rpc.world_convert import (
    Encoder,
    config_from_msg,
    config_msg,
    frames_from_msg,
    frames_msgs,
    subscribe_names,
)
from dqpose.rpc.world_frames import list_frames

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
#: Publish requests one call reads ahead of its acks, and their bytes (a request may be
#: max_message_bytes): those read while earlier ones are applied are applied in one pool job
PUBLISH_READ_AHEAD = 16
PUBLISH_READ_AHEAD_BYTES = 1 << 20
#: named worlds one server holds (the default world "" besides them): each has its own tables
#: (bodies within its bounds, hub.MAX_PRODUCERS acks), so their number is what bounds a server's
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
    if isinstance(e, world_wait.Stopped):
        return grpc.StatusCode.UNAVAILABLE, str(e)
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


class Subscriber:
    """One Subscribe stream's side of the event loop: the queue of its answers (serialized
    ``FusedPose`` messages, handed over by its world's steps through the loop, in the world's
    order), at most :data:`MAX_QUEUED` answers and :data:`MAX_QUEUED_BYTES` bytes, and its
    subscription of the world (``handle``). ``ended`` says why the server ended it (None:
    open)."""

    def __init__(self, interest: Interest, loop):
        self.loop = loop
        self.handle = Subscription(interest, self._handed)
        self.queue: asyncio.Queue = asyncio.Queue()
        self.queued = 0                     # bytes in the queue
        self.ended: str | None = None
        # called once when ended (its slots freed)
        self.on_end: Callable[[], None] | None = None
        # answers handed over and not yet on the loop: steps that follow each other before the
        # loop takes them are taken in one callback (one wake-up of the loop, not one a step)
        self._handing: list = []
        self._hand = threading.Lock()

    def _handed(self, answers: list) -> None:
        """In the world's step (its lock held): the answers, to the event loop."""
        with self._hand:
            wake = not self._handing
            self._handing += answers
        if wake:
            self.loop.call_soon_threadsafe(self._arrived)

    def _arrived(self) -> None:
        with self._hand:
            answers, self._handing = self._handing, []
        self.deliver(answers)

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
        """On the event loop: ends the subscription at once: no more answers made for it, its
        queue emptied, its slots freed (``on_end``), its reader woken by a None."""
        if self.ended is not None:
            return
        self.ended = why
        self.handle.closed = True
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


def _ready(first: bytes, sub: Subscriber) -> tuple[list, bytes | None]:
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


class World:
    """The ``dqpose.v1.World`` service: the server's worlds by name (a :class:`dqpose.Hub`
    each; the Trajectories service resolves ``Waypoint.frame`` through the one its call names).
    Its calls' work, request in, response out, no transport: :meth:`configure`,
    :meth:`lookup`, :meth:`publish_bytes` (what a replay feeds too)."""

    NAME = pb.DESCRIPTOR.services_by_name["World"].full_name

    def __init__(self, cfg=None, calls: Calls | None = None):
        self.max_poses = cfg.max_poses if cfg is not None else DEFAULT_MAX_POSES
        self.limits = cfg.limits if cfg is not None else None
        self.replica = getattr(cfg, "replica_name", "")
        self.calls = calls or Calls()
        self.hubs: dict[str, Hub] = {}
        self.waits = world_wait.Waits(self.limits or _limits.DEFAULT, self.calls.peers)
        self._making = threading.Lock()

    def hub(self, name: str, make: bool = False) -> Hub:
        """World ``name`` ("" the default, made at first use): made when ``make`` (Configure,
        Publish, Subscribe), else :class:`UnknownWorld`; past :data:`MAX_WORLDS` named ones,
        :class:`TooManyWorlds` before anything is made."""
        found = self.hubs.get(name)
        if found is not None:
            return found
        if name and not make:
            raise UnknownWorld(f"{WORLD_HEADER}: no world {name!r} on replica {self.replica!r} "
                               f"(a world is made by the first Configure, Publish or Subscribe "
                               f"naming it)")
        with self._making:
            found = self.hubs.get(name)
            if found is not None:
                return found
            named = len(self.hubs) - ("" in self.hubs)
            if name and named >= MAX_WORLDS:
                raise TooManyWorlds(f"{WORLD_HEADER}: world {name!r} would be named world "
                                    f"{named + 1} on replica {self.replica!r}, above its "
                                    f"{MAX_WORLDS} (MAX_WORLDS)")
            made = self.hubs[name] = Hub(
                name, Encoder(), TrackerBounds.of(self.limits or _limits.DEFAULT))
        _follow(made, self.calls.recorder)
        return made

    def called(self, context, make: bool = False) -> Hub:
        """The world a call names (:func:`routing.world_of`)."""
        return self.hub(world_of(context), make)

    def domain_world(self, name: str) -> domain.World:
        """World ``name``'s :class:`dqpose.world.World`, for a Plan's waypoint frames."""
        return self.hub(name).world

    # -- request -> response, no transport

    def configure(self, world: Hub, request: pb.WorldConfig,
                  rec=record.NULL_CALL) -> pb.WorldConfig:
        """Configure's answer (or its refusal), recorded with its request as one step of the
        world."""
        try:
            sources, arms, options = config_from_msg(request)
            statics, static_bodies = frames_from_msg(request)
        except Exception as e:
            rec.request(request)
            _ended(rec, e)
            raise
        try:
            world.configure(sources, arms, options, hook=lambda: rec.request(request),
                            statics=statics, static_bodies=static_bodies)
        except domain.WorldError as e:      # a bound's (e.limit) is RESOURCE_EXHAUSTED
            error = (WorldInfeasible if isinstance(e, Infeasible) else domain.WorldError)(
                None, e.path("config"), e.text, e.limit)
            _ended(rec, error)
            raise error from None
        answer = frames_msgs(world.world.tree, config_msg(
            world.world.sources, world.world.arms, world.world.options))
        rec.answer(answer)
        rec.end("OK")
        return answer

    @staticmethod
    def lookup(world: Hub, request: pb.LookupRequest) -> bytes:
        """A ``RelativePose``, serialized (:func:`world_wait.answer`); at time 0 watched
        (:class:`dqpose.answers.Answers`). Beside the world's steps, which hold its lock while
        their answers are fitted: it reads whole requests, and a fit is a function of the data
        alone, so neither answer depends on the timing."""
        return world_wait.answer(world, request)

    def publish_bytes(self, world: Hub, data: bytes, r: int, anonymous: str,
                      rec=record.NULL_CALL) -> pb.PublishAck:
        """Request ``r``'s bytes applied to ``world`` as one step, its ack
        (:func:`world_publish.publish_bytes`): what a Publish call and a replay feed."""
        return world_publish.publish_bytes(world, data, r, anonymous, self.max_poses, rec)

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
            # answers are RelativePose messages serialized when made (dqpose.answers)
            "Lookup": grpc.unary_unary_rpc_method_handler(
                self.Lookup, request_deserializer=pb.LookupRequest.FromString,
                response_serializer=None),
            "ListFrames": grpc.unary_unary_rpc_method_handler(     # serialized: list_frames
                self.ListFrames, request_deserializer=pb.ListFramesRequest.FromString,
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
        # recording: in the world's order (configure)
        rec = self.calls.recorder.call(f"{self.NAME}/Configure", pb.WorldConfig, pb.WorldConfig,
                                       _recorded_world(context))
        return await self._unary(
            "Configure", lambda world, r: self.configure(world, r, rec), request, context,
            make=True)

    async def ListFrames(self, request, context):
        return await self._unary("ListFrames", list_frames, request, context)

    async def Lookup(self, request, context):
        world = _recorded_world(context)
        return await self.calls.unary("Lookup", lambda r: self._lookup(r, context), request,
                                      context, status=lambda _, e: status_of(
                                          e, _named("Lookup", world)), world=world)

    async def _lookup(self, request, context) -> bytes:
        world_wait.check(request)
        world = self.called(context)
        # a kept answer that is still the answer: a dict read and a stamp, on the loop
        kept = (world.kept(request.target, request.source)
                if request.time == 0.0 and world_wait.plain(request) else None)
        if kept is not None:
            return kept
        return await self.waits.lookup(world, request, context,
                                       lambda: self.calls.work(self.lookup, world, request))

    def stopping(self, seconds: float) -> None:
        """The server stops: waiting Lookups answered UNAVAILABLE (:mod:`world_wait`)."""
        self.waits.stop()

    async def Publish(self, request_iterator, context):
        anonymous = f"\0call{id(context)}"
        world = _recorded_world(context)
        # recording: in the world's order (publish_bytes)
        rec = self.calls.recorder.call(f"{self.NAME}/Publish", pb.PublishRequest, pb.PublishAck,
                                       world)
        async with self.calls.stream("Publish", context, rec, world,
                                     _named("Publish", world)) as call:
            # the slot first: a call refused for its peer's streams makes no world
            if call.open() is None:
                return
            try:
                hub_ = self.called(context, make=True)
            except Exception as e:
                await call.refuse(*status_of(e, _named("Publish", world)))
            call.on_end(lambda: hub_.forget(anonymous))
            # Registered without a deserializer: each request is parsed with its work in the
            # worker pool (publish_bytes), never on the event loop. Requests are read while
            # earlier ones are applied (PUBLISH_READ_AHEAD), and those read meanwhile go to the
            # pool together, each its own step: a producer's requests do not each wait for
            # a round trip through the event loop and the pool (which made a producer's rate
            # that round trip's inverse).
            pending = ReadAhead(PUBLISH_READ_AHEAD, PUBLISH_READ_AHEAD_BYTES)
            call.on_end(asyncio.ensure_future(read_all(context, pending)).cancel)
            while True:
                taken = await pending.take()
                data = [d for d in taken if isinstance(d, bytes)]
                acks, failure = ((), None) if not data else await self.calls.work(
                    world_publish.publish_all, hub_, data, call.messages, anonymous,
                    self.max_poses, rec)
                for ack in acks:
                    await context.write(ack)
                    call.messages += 1
                if failure is not None:
                    raise failure
                if isinstance(taken[-1], Exception):
                    raise taken[-1]
                if taken[-1] is grpc.aio.EOF:
                    break

    async def Subscribe(self, request, context):
        await self._subscribe("Subscribe", request, context)

    async def SubscribeBatches(self, request, context):
        await self._subscribe("SubscribeBatches", request, context)

    async def _subscribe(self, rpc: str, request, context):
        """Subscribe, or SubscribeBatches (``rpc``): the answers ready at each write in one
        FusedPoseBatch. Both are recorded as Subscribe: the same answers in the same order."""
        world = _recorded_world(context)
        # recording: in the world's order (the hub's subscribe and unsubscribe)
        rec = self.calls.recorder.call(f"{self.NAME}/Subscribe", pb.SubscribeRequest,
                                       fpb.FusedPose, world)
        async with self.calls.stream(rpc, context, rec, world, _named(rpc, world)) as call:
            hub_, problem = self._admit(request, context, _named(rpc, world))
            if problem is not None:
                await call.refuse(*problem)
            assert hub_ is not None
            slot = call.open(SUBSCRIPTION, hub_.name)
            if slot is None:
                return
            sub = Subscriber(interest(request), asyncio.get_running_loop())
            sub.on_end = slot.end

            def hook():
                rec.request(request)

            # In the world at once when its lock is free, with nothing since the headers went
            # that yields to another call (dqpose.rpc.replay_remote waits for the headers);
            # else in the pool, never waiting on the event loop for a Publish request's fits.
            added = _at_once(hub_, sub.handle, hook) or asyncio.ensure_future(
                self.calls.work(hub_.subscribe, sub.handle, hook))
            call.on_end(lambda: self._leave(added, hub_, sub, call.handed_over()))
            await asyncio.shield(added)
            await self._answers(rpc, sub, slot, call)

    def _admit(self, request, context, named: str) -> tuple[Hub | None, tuple | None]:
        """The world a Subscribe request names, or why it is refused before it takes a slot:
        ``(hub, None)`` or ``(None or hub, (status, details))`` (``named``: the call, as a
        log line names it)."""
        if not (math.isfinite(request.rate_hz) and request.rate_hz >= 0.0):
            return None, (grpc.StatusCode.INVALID_ARGUMENT,
                          f"rate_hz: must be finite and >= 0 (0: every update), got "
                          f"{request.rate_hz!r}")
        if self.limits is not None and request.rate_hz > self.limits.max_output_rate:
            return None, (grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"rate_hz: {request.rate_hz:.6g} Hz, over the server's limit "
                          f"max_output_rate = {self.limits.max_output_rate:.6g} Hz")
        bad = subscribe_names(request)      # before the world is made: a refusal makes none
        if bad is not None:
            return None, (grpc.StatusCode.INVALID_ARGUMENT, bad)
        try:
            found = self.called(context, make=True)
        except Exception as e:
            return None, status_of(e, named)
        too_many = over_count("bodies", len(request.bodies), found.world.bounds.max_bodies,
                              "bodies")
        return found, None if too_many is None else (grpc.StatusCode.RESOURCE_EXHAUSTED, too_many)

    async def _leave(self, added, world: Hub, sub: Subscriber, ended) -> None:
        """``sub`` out of its world once it is in (the pool may run both at once), its
        recording ``ended`` in the world's order."""
        sub.end(sub.ended or "the call ended")
        await asyncio.shield(self._unsubscribe(added, world, sub, ended))

    async def _unsubscribe(self, added, world: Hub, sub: Subscriber, ended) -> None:
        await added
        await self.calls.work(world.unsubscribe, sub.handle, ended)

    async def _answers(self, rpc: str, sub: Subscriber, slot: Slot, call: Call) -> None:
        """Writes ``sub``'s answers until the server ends it (its client fell behind a bound:
        RESOURCE_EXHAUSTED, not waiting for the client to read it), counted in ``call``."""
        batched = rpc == "SubscribeBatches"
        carry = None
        context = call.context
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
                call.code = await exhausted(context, str(e), slot)
                return
            for answer in answers:
                call.rec.answer(answer)       # recording
            call.messages += len(answers)
        call.code = await exhausted(context, f"{rpc}: {sub.ended}; subscribe to fewer bodies "
                                             f"or a lower rate_hz", slot)


def interest(request: pb.SubscribeRequest) -> Interest:
    """What a SubscribeRequest asks of its world."""
    return Interest(frozenset(request.bodies) or None, request.rate_hz, request.relative_to)


def _at_once(world: Hub, sub: Subscription, hook) -> asyncio.Future | None:
    """``sub`` into ``world`` without waiting: a done future, or None when its lock is held."""
    if not world.subscribe(sub, hook, wait=False):
        return None
    done = asyncio.get_running_loop().create_future()
    done.set_result(True)
    return done


def _ended(rec, e: Exception) -> None:
    """A refused call's end, recorded with its status."""
    status, details = status_of(e)
    rec.end(status.name, details)


def _follow(world: Hub, recorder) -> None:
    """``world`` (just made) followed by the recorder's own subscription to every body at
    ``recorder.world_rate`` Hz of measurement time, when it records worlds: every body of a
    recorded world is recorded, subscribed or not, its answers fitted and recorded in the
    world's step like a client subscriber's (a Subscribe call marked ``internal``), and replayed
    like any other. The recorder ends it when it closes."""
    if recorder.world_rate is None:
        return
    rec = recorder.call(f"{World.NAME}/Subscribe", pb.SubscribeRequest, fpb.FusedPose,
                        world.name, internal=True)
    if not rec.alive:       # dropped (the recording behind): its answers could not replay
        return

    def deliver(answers: list) -> None:
        for answer in answers:
            rec.answer(answer)

    request = pb.SubscribeRequest(rate_hz=recorder.world_rate)
    world.subscribe(Subscription(interest(request), deliver, internal=True),
                    hook=lambda: rec.request(request))
