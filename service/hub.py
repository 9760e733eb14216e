"""One world's engine: the order its steps are applied in, and what each step does.

A :class:`Hub` holds a :class:`dqpose.world.World` and everything a world's calls share: its one
lock (the world's order), its producers' sequences and acks, its subscriptions (in the order
they came), its request and measurement numbering, and its watched Lookups
(:class:`dqpose.answers.Answers`). A Publish request is one step under the lock
(:meth:`Hub.publish`): its sequence checked, its rows into the world, the ticks they make due for
every subscription (:mod:`dqpose.world_ticks`), the request's :class:`dqpose.limits.Budget`
(all subscriptions together, a fit made once for all), the answers fitted and handed to each
subscription's ``deliver`` in that order, the watched Lookups made again. A step's ``hook`` runs
first under the same lock: where a recording writes the step, so a recording holds each world's
steps in the world's order and replays to the same answers.

No transport: the answers are bytes an :class:`Encoder` writes (the server's protobuf messages),
and ``deliver`` is any callable (a server's event-loop queue, a replay's list, a recording).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import sys
import threading
from typing import Any, Callable, NamedTuple, Optional, Protocol

import numpy as np

from dqpose import limits as _limits
from dqpose.answers import Answers
from dqpose.errors import WorldError
from dqpose.fusion.bounds import TrackerBounds
from dqpose.names import name_problem
from dqpose.world import BodyPose, TickWindow, World, WorldOptions
from dqpose.world_bounds import DEFAULT as DEFAULT_BOUNDS
from dqpose.world_bounds import WorldBounds
from dqpose.world_ticks import Schedule

#: producer names a world remembers (each one's acked_through); the oldest-acked is forgotten
#: beyond
MAX_PRODUCERS = 4096

Hook = Optional[Callable[[], None]]


class Encoder(Protocol):
    """How a hub's answers are written: a body's fit at a tick (``request``: the step's number,
    ``measurements``: the ids the answer names), an error entry, a Lookup's relative pose. One
    whose ``wire`` attribute is True writes :func:`dqpose.rpc.wire.fused_pose_bytes`' bytes, which
    a tick's one C call (:meth:`dqpose.world.World.tick_wire`) writes too."""

    def fused(self, p: BodyPose, request: int, measurements: list[int]) -> bytes: ...

    def error(self, body: str, time: float, request: int, text: str) -> bytes: ...

    def relative(self, p: BodyPose) -> bytes: ...

    def fit_error(self, e: Exception) -> str: ...


class Interest(NamedTuple):
    """What a subscription asks for: its ``bodies`` (None: all), ``rate`` (Hz of measurement
    time; 0: every update) and the frame its answers are ``relative_to`` ("" the world)."""
    bodies: Optional[frozenset]
    rate: float
    relative_to: str = ""


class Subscription:
    """One subscription of a hub: its :class:`Interest`, its ticks (a
    :class:`~dqpose.world_ticks.Schedule` at a rate > 0) and ``deliver``, called under the hub's
    lock once a step with that step's answers in order (it must not block, raise or call the
    hub). Its owner sets ``closed`` when it ends: no answer is made for it after that. An
    ``internal`` one (the recorder's) is served after every client's within a request's
    budget, so that recording a world never takes a client's answers."""

    def __init__(self, interest: Interest, deliver: Callable[[list], None],
                 internal: bool = False):
        self.interest, self.deliver, self.internal = interest, deliver, internal
        self.closed = False
        self.schedule = Schedule(interest.rate) if interest.rate else None
        self.capped: set[str] = set()       # bodies said to hold more than their fits take

    def due(self, body: str, window: TickWindow, most: int) -> tuple[list, int, list]:
        """``body``'s ticks due after a step (its :class:`~dqpose.world.TickWindow` then):
        at a rate, those its horizon reached; at rate 0, one at its newest measurement (None).
        ``(times, cut, ends)``: the latest ``most`` listed, the ``cut`` older ones counted (a
        body whose time leapt: a billion ticks are a range, never a list), ``ends`` the times of
        the first and the last of those."""
        schedule = self.schedule
        if schedule is None:
            return [None], 0, []
        ks = schedule.due(body, window.horizon, window.floor)
        if len(ks) <= most:     # the common case: a tick or two
            return [schedule.time(body, k) for k in ks], 0, []
        cut = len(ks) - most
        time = functools.partial(schedule.time, body)
        return [time(k) for k in ks[cut:]], cut, [time(ks[0]), time(ks[cut - 1])]


class Rows(NamedTuple):
    """A Publish request's measurements as arrays, ``index[k]`` the request's measurement of row
    ``k``, ``codes`` what a decoder's checks said of each row (None: not checked)."""
    # shadows tuple.index(), which no caller uses, as Measurements' does
    index: np.ndarray  # type: ignore[assignment]
    bodies: tuple
    sources: tuple
    times: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray
    codes: Optional[np.ndarray]


class Applied(NamedTuple):
    """What one Publish step did: its number in the world's order (``request``), the producer's
    ``acked_through``, ``notes`` about the request as a whole and ``errors`` about its
    measurements (``index``: the request's measurement); ``used`` False when none of it was
    (a repeated sequence, a producer's name that is not one); ``cost``: what its answers fuse
    (:class:`dqpose.limits.Budget`)."""
    request: int
    acked_through: int
    notes: tuple
    errors: tuple
    used: bool
    cost: int = 0


def _run(hook: Hook) -> None:
    if hook is not None:
        hook()


class Hub:
    """One world (see the module's docstring). ``tracker``: the server's bounds of a stream;
    ``encoder``: how answers are written; ``where``: how an answer names request r
    (``request 4``); ``bounds``: the world's. A ``stream`` hub has one producer (its rows name
    no origin) and fits its answers when they are taken, after its step (:meth:`stream`)."""

    def __init__(self, name: str, encoder: Encoder, tracker: Optional[TrackerBounds] = None,
                 where: str = "request {}", bounds: WorldBounds = DEFAULT_BOUNDS,
                 stream: bool = False):
        self.name, self.encoder, self.stream = name, encoder, stream
        self._wire = bool(getattr(encoder, "wire", False))
        self.where = where.format
        self.world = World(bounds=bounds, tracker=tracker)
        self.lock = threading.Lock()
        self._acked: dict[str, int] = {}         # producer -> acked_through
        self._subscriptions: dict[int, Subscription] = {}     # in the order they came
        self._came = 0
        self.requests = 0                        # Publish requests, in the world's order
        self.measurements = 0                    # measurements numbered in that order
        self.answers = Answers(encoder.relative)
        # called after each Publish step with the bodies it brought, under the lock (they must
        # not block: dqpose.rpc.world_wait's waiting Lookups hand them to their event loop)
        self.listeners: set[Callable[[tuple], None]] = set()

    @classmethod
    def open_stream(cls, sources, options: WorldOptions, rate: float, tracker: TrackerBounds,
                    encoder: Encoder) -> tuple["Hub", list]:
        """StreamFuse's private world: one producer, its window the buffer, a tick never
        waiting (``max_delay`` 0), bounded by the stream's ``tracker`` bounds alone; and the
        list its one subscription (every body at ``rate``) hands its answers to, each step's
        (bytes, or a callable that fits and writes one: see :class:`Hub`). Configured from
        ``options`` (``buffer`` and ``max_delay`` set here); a ``WorldError`` names the
        option."""
        bounds = WorldBounds(max_bodies=sys.maxsize, max_sources=sys.maxsize,
                             max_measurements_per_body=tracker.max_window, max_buffer=math.inf,
                             max_measurements=tracker.max_rows)
        made = cls("", encoder, tracker, "requests[{}]", bounds, stream=True)
        made.configure(sources, {}, dataclasses.replace(options, buffer=options.window,
                                                         max_delay=0.0))
        answers: list = []
        made.subscribe(Subscription(Interest(None, rate), answers.extend))
        return made, answers

    @property
    def subscriptions(self) -> tuple[Subscription, ...]:
        return tuple(self._subscriptions.values())

    def configure(self, sources, arms, options, hook: Hook = None, statics=(),
                  static_bodies=()) -> None:
        """:meth:`dqpose.world.World.configure` as a step (a ``WorldError`` leaves the world as
        it was)."""
        with self.lock:
            _run(hook)
            self.world.configure(sources=sources, arms=arms, options=options, statics=statics,
                                 static_bodies=static_bodies)

    def count(self, hook: Hook = None) -> None:
        """A request the transport could not read: numbered in the world's order, unused."""
        with self.lock:
            _run(hook)
            self.requests += 1

    def publish(self, producer: str, anonymous: str, sequence: int, rows: Optional[Rows],
                offered: int, hook: Hook = None) -> Applied:
        """A Publish request of ``offered`` measurements as one step: from ``producer`` ("":
        the call's own key ``anonymous``) with ``sequence`` (0: none), its ``rows`` into the
        world (None: refused whole by the transport, counted and acked), its answers made and
        delivered. Its measurements are numbered in the world's order whatever becomes of them.
        Never raises for bad input: what was refused is in the :class:`Applied`."""
        with self.lock:
            _run(hook)
            r, first = self.requests, self.measurements
            self.measurements += offered
            named = name_problem(producer, empty=True)
            if named is not None:
                self.requests += 1
                return Applied(r, 0, (WorldError(None, "producer",
                                                 f"{named}; none of it was used"),), (), False)
            key = producer or anonymous
            known = self._acked.get(key)
            last = known or 0
            if sequence and sequence <= last:
                return Applied(r, last, (WorldError(
                    None, "", f"sequence {sequence} already in the world (acked through {last}); "
                              f"not fused again"),), (), False)
            # a producer's first request names no gap: the world may have moved here from a
            # replica that holds the producer's earlier requests (docs/deploy.md)
            notes = () if known is None or sequence <= last + 1 else (WorldError(
                None, "", f"sequences {last + 1}..{sequence - 1} of producer {key!r} never "
                          f"arrived"),)
            errors, cost = ((), 0) if rows is None else self._apply(
                rows, None if self.stream else key, first, offered)
            self.requests += 1
            if sequence:
                self._acked[key] = sequence
                if len(self._acked) > MAX_PRODUCERS:
                    del self._acked[min(self._acked, key=self._acked.__getitem__)]
            return Applied(r, sequence or last, notes, errors, True, cost)

    def forget(self, anonymous: str) -> None:
        """The acks of a call's own key ``anonymous`` (its call ended)."""
        with self.lock:
            self._acked.pop(anonymous, None)

    def subscribe(self, sub: Subscription, hook: Hook = None, wait: bool = True) -> bool:
        """``sub`` answered from the next step on; False (nothing done) when not ``wait`` and
        the lock is held."""
        if not self.lock.acquire(wait):
            return False
        try:
            _run(hook)
            self._subscriptions[self._came] = sub
            self._came += 1
        finally:
            self.lock.release()
        return True

    def unsubscribe(self, sub: Subscription, hook: Hook = None) -> None:
        """``sub`` answered no more (a step: ``hook`` where a recording ends it)."""
        with self.lock:
            for k, s in self._subscriptions.items():
                if s is sub:
                    del self._subscriptions[k]
                    break
            _run(hook)

    def lookup(self, target: str, source: str, time: float) -> bytes:
        """A Lookup fitted beside the steps (the world's read lock; a fit is a function of the
        data alone): at time 0 its pair watched (:class:`dqpose.answers.Answers`)."""
        return self.answers.lookup(self.world, target, source, time)

    def kept(self, target: str, source: str) -> Optional[bytes]:
        """A Lookup at time 0 answered from a kept answer, without a lock; None: fit it."""
        return self.answers.kept(self.world, target, source)

    # -- a Publish step, under the lock

    def _apply(self, rows: Rows, producer: Optional[str], first: int,
               offered: int) -> tuple[tuple, int]:
        """``rows`` into the world (from ``producer``, numbered from ``first``, ``offered`` in
        the request), then the answers they make due: the rows' errors and what the answers
        cost."""
        if not len(rows.index):
            return (), 0
        # every row of the request (its index 0 .. offered - 1): numbered by the first alone
        ids = first if len(rows.index) == offered else first + rows.index
        published = self.world.ingest(rows.bodies, rows.sources, rows.times, rows.poses,
                                      rows.covariances, rows.codes, producer, ids)
        errors = tuple(e.at(int(rows.index[e.index])) for e in published.errors
                       ) if published.errors else ()
        cost = self._answer_subscriptions(published.bodies)
        self.answers.refresh(self.world, published.bodies)
        for listener in tuple(self.listeners):
            listener(published.bodies)
        return errors, cost

    def _answer_subscriptions(self, bodies: tuple) -> int:
        """The answers due after a step that brought measurements of ``bodies`` (in order of
        their first measurement), within the request's budget (all subscriptions together,
        the earlier first, each fit made once for all), delivered to each subscription; what
        they cost. A stream hub's fits are made when its subscription takes them (each answer
        a callable that makes it)."""
        if not self._subscriptions:
            return 0
        made: dict[tuple, Any] = {}
        budget = _limits.Budget(self.world.tracker_bounds.max_fused_per_request)
        psd = self.world.options.acceleration_psd
        correlated = psd is not None and bool(np.any(psd))
        windows: dict[str, TickWindow] = {}
        horizons: dict[str, float] = {}
        # a body's horizon is never past its newest measurement: most steps, its next tick is
        # beyond that, and neither its horizon nor its window is looked at
        tops = self.world.newest_of(bodies)
        # a body's answers for a subscription that asks what an earlier one asked, its next
        # tick and its capped note where that one's were: the same answers, the same next tick
        # (kept only when the budget took every answer: fits made are free, so it does again)
        same: dict[tuple, tuple] = {}
        # clients in the order they came, then the internal ones (sorted() keeps the order)
        for sub in sorted(self._subscriptions.values(), key=lambda s: s.internal):
            if sub.closed:          # ended by its owner, not yet taken out
                continue
            answers: list = []
            wanted = sub.interest.bodies
            # a body's next tick's time (rate 0: none, every step is due)
            schedule = sub.schedule
            paced = schedule is not None
            at: dict[str, float] = schedule.next_time if schedule is not None else {}
            for body, top in zip(bodies, tops):
                if wanted is not None and body not in wanted or at.get(body, -math.inf) > top:
                    continue
                h = None
                if paced:
                    h = horizons.get(body)
                    if h is None:
                        h = horizons[body] = self.world.horizon(body)
                    if at.get(body, -math.inf) > h:
                        continue
                key = (sub.interest, body, None if schedule is None else schedule.next.get(body),
                       body in sub.capped)
                if key in same:
                    out, after, capped = same[key]
                    if after is not None and schedule is not None:
                        schedule.next[body], schedule.next_time[body] = after
                    if capped:
                        sub.capped.add(body)
                    answers += out
                    continue
                w = windows.get(body) or windows.setdefault(body,
                                                            self.world.tick_window(body, h))
                out, whole = self._due(sub, body, w, made, budget, correlated)
                if whole:
                    same[key] = (out, (schedule.next[body], schedule.next_time[body])
                                 if schedule is not None else None,
                                 not key[3] and body in sub.capped)
                answers += out
            if answers:
                sub.deliver(answers)
        return budget.spent

    def _due(self, sub: Subscription, body: str, w: TickWindow, made: dict,
             budget: _limits.Budget, correlated: bool) -> tuple[list, bool]:
        """``sub``'s answers of ``body`` due in this step, StreamFuse's order: that its window
        is capped (once), the ticks its budget skips (a body's oldest, named), the answers; and
        whether the budget took every one. A fit not ``made`` yet costs what it fuses (relative
        to another body, that body's window and its own again besides; ``correlated``: the
        world's fits are)."""
        options = self.world.options
        # no more can be answered than the budget has left (an answer costs its own window at
        # least) and what is made already
        most = (budget.left // _limits.answer_cost(w.rows, options.robust, correlated)
                + len(made))
        times, cut, ends = sub.due(body, w, most)
        if not times:
            return [], True
        r, out = self.requests, []
        if w.capped and body not in sub.capped:
            sub.capped.add(body)
            out.append(self.encoder.error(body, 0.0, r, f"{self.where(r)}: " + _limits.over_text(
                f"body {body!r}: its window holds more measurements than its fits take "
                f"({self.world.cap}); the oldest are left out", "max_window",
                self.world.tracker_bounds.max_window)))
        rel = sub.interest.relative_to
        rows = w.rows + (w.rows + self.world.tick_window(rel).rows if rel else 0)
        new = [t for t in times if (body, t, rel) not in made]
        take, cost = budget.take(len(new), rows, options.robust, correlated)
        skip = new[:len(new) - take]
        if skip or cut:
            what = (f"{cut + len(skip)} ticks from {ends[0] if cut else skip[0]:.6g} s to "
                    f"{skip[-1] if skip else ends[1]:.6g} s" if sub.schedule is not None
                    else "its newest measurement")
            out.append(self.encoder.error(body, 0.0, r, str(budget.skipped(
                self.where(r), body, what, cost))))
            skipped = set(skip)
            times = [t for t in times if t not in skipped]
        # the window's rows are the tick's (none of its refusals possible) in [floor, horizon]
        picked = None if self.stream else w.picked
        for t in times:
            key = (body, t, rel)
            if key not in made:
                made[key] = (functools.partial(self._answer, body, t, rel, r) if self.stream
                             else self._answer(body, t, rel, r, picked if t is None or
                                               w.floor <= t <= w.horizon else None))
            out.append(made[key])
        return out, not (skip or cut)

    def _answer(self, body: str, t: Optional[float], relative_to: str, r: int,
                picked: Optional[np.ndarray] = None) -> bytes:
        """Body ``body`` at tick ``t`` (None: its newest measurement's time; relative to
        ``relative_to`` when set) as request ``r``'s answer, or an error entry naming why it
        cannot be answered (``picked``: its rows, :meth:`World.tick_wire`'s)."""
        try:
            if self._wire:     # the common case: one C call
                data = self.world.tick_wire(body, t, r, relative_to, picked)
                if data is not None:
                    return data
            p, ids = self.world.tick(body, t)
            if relative_to:
                rel = self.world.relative(relative_to, body, p.time)
                p = BodyPose(body, rel.time, rel.pose, rel.covariance, p.fused)
        except (ValueError, LookupError) as e:
            at = f"{t!r} s" if t is not None else "its newest measurement"
            return self.encoder.error(body, 0.0, r, f"{self.where(r)}: body {body!r} at {at}: "
                                                    f"{self.encoder.fit_error(e)}")
        return self.encoder.fused(p, r, ids.tolist())
