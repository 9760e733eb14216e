"""The shared world: named bodies fed by many producers, each body's pose at any time within the
buffer, the pose of any body relative to any other, and an arm's base, all with covariances.

A :class:`World` holds one :class:`dqpose.fusion.Tracker` whose window is the ``buffer`` (the
history kept for lookups at past times). A fit is :func:`dqpose.fusion.fuse` over the
measurements taken in a ``window`` (the tracker's rows: ``fuse``'s answer to the last bit): a
tick's (:meth:`World.tick`) ends at the body's newest measurement, StreamFuse's rows; a
Lookup's at ``time`` (:meth:`World.pose`, :meth:`World.relative`) half a window after it, or at
the newest if sooner. What changes the world (publish, ingest, configure) has it alone, what
reads it runs beside other readers (:class:`dqpose.readwrite.ReadWrite`), each answer a function
of the measurements alone, so a reader never waits for another's fit.

Correlations: two bodies measured by the same source share its extrinsic error ``ε`` (the
source's ``extrinsic_covariance``) and, when its latency is estimated (``latency_sigma``), its
latency error. :meth:`World.relative` fits both bodies jointly, with one ``ε`` and one latency
per such source, so the relative pose's covariance carries their cross-covariance (a body's own
pose, :meth:`World.pose`, is its own fit, which estimates the latency from its measurements
alone). Not modelled: errors of a source's ``body_offset``, correlated noises of one image."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq
from dqpose import frames as _frames
from dqpose import limits as _limits
from dqpose.answers import Kept
from dqpose.body_pose import BodyPose, body_name
from dqpose.errors import NotFound, NotYet, OutOfRange, WorldError
from dqpose.errors import known_from as _known_from
from dqpose.errors import seconds_text as _s
from dqpose.fusion import (
    DEFAULT_MAX_EXTRAPOLATION,
    DEFAULT_PROBABILITY,
    Fused,
    Measurement,
    Source,
    Tracker,
)
from dqpose.fusion.bounds import TrackerBounds
from dqpose.fusion.measurements import Rows, rows_of
from dqpose.fusion.results import DOF
from dqpose.fusion.sources import source_table
from dqpose.fusion.tick import WireTicks
from dqpose.fusion.validation import checked_seconds, finite_shape
from dqpose.lookup import Lookups
from dqpose.names import name_problem, quoted
from dqpose.readwrite import ReadWrite
from dqpose.riders import Riders
from dqpose.world_bounds import DEFAULT as DEFAULT_BOUNDS
from dqpose.world_bounds import WorldBounds, over, over_bounds
from dqpose.world_ticks import horizon

__all__ = ["WorldOptions", "WorldBounds", "WorldError", "NotFound", "OutOfRange", "Published",
           "BodyPose", "World", "Measurement", "Source", "Fused"]


@dataclass(frozen=True)
class WorldOptions:
    """What the world's fusion runs with besides its sources and arms (the options of
    :func:`dqpose.fusion.fuse`), and how much time it keeps: ``window`` seconds of measurements
    in one body's fit, ``buffer`` seconds of history for lookups at past times, ``max_delay``
    seconds of measurement time a tick waits for slower sources."""
    robust: bool = False
    probability: float = DEFAULT_PROBABILITY
    max_skew: Optional[float] = None
    max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION
    twist_covariance: Optional[np.ndarray] = None
    acceleration_psd: Optional[np.ndarray] = None
    window: float = 1.0
    buffer: float = 10.0
    max_delay: float = 0.1


@dataclass(frozen=True)
class Published:
    """What one :meth:`World.publish` did: ``accepted`` measurements fused into the world,
    ``errors`` a :class:`WorldError` about each of the others (its ``index`` in the request's
    measurements), the ``bodies`` the request touched."""
    accepted: int
    errors: tuple[WorldError, ...]
    bodies: tuple[str, ...]


class TickWindow(NamedTuple):
    """What a body's ticks would fit now: its ``horizon`` (:func:`dqpose.world_ticks.horizon`),
    its window's oldest measurement (``floor``), the ``rows`` a tick fits (with a rider's, its
    parent's fits: :meth:`dqpose.riders.Riders.cost`), and ``capped``: its
    window holds more than those; ``picked``: those rows (a tick's in ``[floor, horizon]``,
    for :meth:`World.tick_wire`, until the world changes)."""
    horizon: float
    floor: float
    rows: int
    capped: bool
    picked: Optional[np.ndarray] = None


def _checked_times(options: WorldOptions, b: WorldBounds) -> float:
    """``options``' window, buffer and max_delay checked (a ``WorldError`` naming the field);
    the buffer in seconds."""
    if not isinstance(options, WorldOptions):
        raise WorldError(None, "options", f"expected WorldOptions, got {type(options).__name__}")
    try:
        window = checked_seconds(options.window, "window", "positive")
        buffer = checked_seconds(options.buffer, "buffer", "positive")
        checked_seconds(options.max_delay, "max_delay", "nonnegative")
    except ValueError as e:
        raise WorldError.of(e, under="options") from None
    if buffer > b.max_buffer:
        raise over("options.buffer", buffer, "max_buffer", b.max_buffer, "s")
    if window > buffer:
        raise WorldError(None, "options.window",
                         f"{window:.6g} s is longer than options.buffer {buffer:.6g} s (a "
                         f"fit uses measurements the buffer keeps)")
    if options.max_delay > window:
        raise WorldError(None, "options.max_delay",
                         f"{options.max_delay:.6g} s is longer than options.window "
                         f"{window:.6g} s (a tick waits at most that long for slower "
                         f"sources, its window then holding its data)")
    return buffer


def _checked_arms(arms: Mapping[str, str], sources: Sequence[Source]) -> dict[str, str]:
    """``arms`` (arm -> the source that sees its base) as a dict, each arm's name and source
    checked (a ``WorldError`` naming the field)."""
    names = {s.name for s in sources if isinstance(s, Source)}
    arms = dict(arms)
    for arm, src in arms.items():
        problem = name_problem(arm)
        if problem is not None:
            raise WorldError(None, "arms", problem)
        if src not in names:
            raise WorldError(None, f"arms[{arm!r}]",
                             f"source {quoted(src)} is not among the world's sources")
    return arms


class World:
    """Named bodies and sources; see the module's docstring. Every public method takes the
    world's lock, to write or to read, so producers and readers may call from any thread."""

    def __init__(self, *, sources: Sequence[Source] = (), arms: Mapping[str, str] = {},
                 options: WorldOptions = WorldOptions(), bounds: WorldBounds = DEFAULT_BOUNDS,
                 tracker: Optional[TrackerBounds] = None):
        self.bounds = bounds
        # a server's bounds of a stream (its Limits'); a body's buffer and the rows of all
        # bodies are the world's own (bounds)
        self.tracker_bounds = (tracker if tracker is not None
                               else TrackerBounds.of(_limits.DEFAULT))
        self.lock = ReadWrite()
        # body -> source -> newest taken, of the sources that fed it under earlier
        # configurations (the tracker's own, Tracker.by_source, win)
        self.fed_before: dict[str, dict[str, float]] = {}
        self._tracker: Optional[Tracker] = None
        # answers kept until their bodies change (each body's version, Tracker.version, grows
        # with every request that brought it measurements); fits by (body, time), relatives by
        # (target, source, time)
        self._generation = 0              # configurations made, for stamp()
        self._named: set = set()          # the configured sources and those that fed a body
        self.fits = Kept()
        self.kept_relatives = Kept()
        self.lookups = Lookups(self)
        self.configure(sources=sources, arms=arms, options=options)

    def configure(self, *, sources: Sequence[Source], arms: Mapping[str, str],
                  options: WorldOptions, statics: Sequence[_frames.Static] = (),
                  static_bodies: Sequence[str] = ()) -> None:
        """Replace the sources, arms, options, statics and static bodies (the frame tree,
        :class:`dqpose.frames.FrameTree`; all checked first: a ``WorldError`` naming the field
        leaves the world as it was); the measurements kept that still fit the new buffer and
        bounds stay, re-fused under the new sources."""
        sources = tuple(sources)
        b = self.bounds
        if len(sources) > b.max_sources:
            raise over("sources", len(sources), "max_sources", b.max_sources)
        buffer = _checked_times(options, b)
        arms = _checked_arms(arms, sources)
        # the tracker's window is the buffer, which holds a body's measurements up to the
        # world's bound (not a stream's max_window)
        bounds = self.tracker_bounds.holding(
            b.max_measurements_per_body,
            b.max_measurements or b.max_bodies * b.max_measurements_per_body)
        try:
            table = source_table(sources)
        except ValueError as e:
            raise WorldError.of(e) from None
        Riders.check(table, arms, options.acceleration_psd)
        tree = _frames.FrameTree(table, statics, static_bodies, b)
        try:        # the sources passed: what the tracker refuses is an option
            tracker = Tracker(buffer, sources=sources, robust=options.robust,
                              probability=options.probability, max_skew=options.max_skew,
                              max_extrapolation=options.max_extrapolation,
                              twist_covariance=options.twist_covariance,
                              acceleration_psd=options.acceleration_psd, bounds=bounds)
        except ValueError as e:
            raise WorldError.of(e, under="options") from None
        with self.lock.write():
            if self._tracker is not None:
                tree.clashes(self._t.held)
            old, self.tree = self._tracker, tree
            self._tracker, self._wire = tracker, WireTicks(tracker)
            self.riders = Riders(self, tracker.table)
            tracker.riders = self.riders if self.riders.parents else None
            self.fits.clear()
            self.kept_relatives.clear()
            self._generation += 1
            self._named = {s.name for s in sources}
            self.sources, self.arms, self.options = sources, arms, options
            if old is None:
                return
            fed = {body: self.fed(body, old) for body in old.bodies}
            fed.update((b, seen) for b, seen in self.fed_before.items() if b not in fed)
            self.fed_before = {}
            for body in old.bodies:
                w = old.window_of(body)
                n = len(w.ids)
                self._admit([body] * n, list(w.sources), w.times, w.poses, w.covariances,
                            ids=w.ids)
            # a body's sources are those that ever fed it, across configurations
            self.fed_before = fed

    @property
    def bodies(self) -> tuple[str, ...]:
        with self.lock.read():
            return self._t.bodies

    @property
    def tracker(self) -> Tracker:
        """The tracker holding the world's measurements (its window the buffer)."""
        return self._t

    @property
    def cap(self) -> Optional[int]:
        """Measurements one fit of a body takes at most (the last of its window)."""
        return self._t.cap

    @property
    def _t(self) -> Tracker:
        assert self._tracker is not None    # set by __init__'s configure
        return self._tracker

    def publish(self, measurements: Sequence[Measurement], producer=None) -> Published:
        """Add measurements (thread-safe); a bad one is answered in ``errors`` as
        ``(index, message)``, the message naming ``measurements[k]``; never raised.
        ``producer``: who sent them (a body's time jump is confirmed by another producer than
        the one that made it, ``Tracker``'s origins; None: any)."""
        rows, bad = rows_of(measurements)      # a row refused already: its body ""
        with self.lock.write():
            errors = self._admit(*rows, bad, producer=producer)
        return _published(rows.bodies, errors)

    def ingest(self, bodies: Sequence[str], sources: Sequence[str], times, poses,
               covariances, codes=None, producer=None, ids=None) -> Published:
        """:meth:`publish` of measurements given as arrays (a server's parsed request):
        ``bodies`` and ``sources`` one name each, ``times`` ``(n,)``, ``poses`` ``(n, 8)``,
        ``covariances`` ``(n, 6, 6)``; checked together in NumPy, the same checks and answers
        as :meth:`publish` without a :class:`Measurement` per row; ``ids`` ``(n,)``: the
        numbers the answers name them by (an int: the first of consecutive ones; default: their
        index). ``codes`` ``(n,)``: the rows were checked by a decoder already
        (``Tracker.ingest``'s ``checked``: 0 a good row, not checked again). ``producer``: as
        :meth:`publish` takes it. Arrays of the wrong shape are a ``WorldError`` for the call."""
        n = len(bodies)
        if len(sources) != n:
            raise WorldError(None, "sources", f"expected {n} names, got {len(sources)}")
        try:
            times = finite_shape(times, "times", (n,))
            poses = finite_shape(poses, "poses", (n, 8))
            covs = finite_shape(covariances, "covariances", (n, DOF, DOF))
        except ValueError as e:
            raise WorldError.of(e) from None
        if codes is not None:
            codes = np.asarray(codes)
            if codes.shape != (n,):
                raise WorldError(None, "codes", f"expected shape {(n,)}, got {codes.shape}")
        with self.lock.write():
            errors = self._admit(bodies, sources, times, poses, covs, codes=codes,
                                 producer=producer, ids=ids)
            touched = self._t.touched if len(errors) < n else ()
        return Published(n - len(errors), tuple(errors[k] for k in sorted(errors)), touched)

    def _admit(self, bodies, sources, times, poses, covs, bad=None, codes=None,
               producer=None, ids=None) -> dict[int, WorldError]:
        """Rows into the tracker under the world's bounds (the lock held); ``codes`` and
        ``producer``: as :meth:`ingest` takes them."""
        errors: dict[int, WorldError] = dict(bad or {})
        known, named, b = self._t.held, self._named, self.bounds
        if (len(known) + len(bodies) > b.max_bodies
                or len(named) + len(sources) > b.max_sources):     # else none can be over
            over_bounds(bodies, sources, errors, known, named, b)
        if self.tree.checks or _frames.RESERVED in bodies:     # dqpose.frames' namespace
            self.tree.refuse(bodies, sources, errors)
        n = len(bodies)
        use = [k for k in range(n) if k not in errors] if errors else range(n)
        if not use:
            return errors
        ids = 0 if ids is None else ids     # an int: the first of consecutive ids
        if isinstance(ids, int) and (len(use) < n or codes is None):
            ids = ids + np.arange(n)
        if len(use) == n:       # the common case: every row offered, no copies
            rows = (bodies, sources, times, poses, covs)
            numbers = ids if isinstance(ids, int) else np.asarray(ids, np.int64)
            checks = codes
        else:
            idx = np.array(use)
            rows = ([bodies[k] for k in use], [sources[k] for k in use], times[idx],
                    poses[idx], covs[idx])
            numbers = np.asarray(ids, np.int64)[idx]
            checks = None if codes is None else codes[idx]
        refused = self._t.ingest(Rows(*rows), ids=numbers, origin=producer, checked=checks)
        for j, e in refused:
            errors[use[j]] = e.at(use[j])
        if not named.issuperset(sources):       # a source new to the world fed a body
            named.update(sources[k] for k in use if k not in errors)
        return errors

    def fed(self, body: str, tracker: Optional[Tracker] = None) -> dict[str, float]:
        """Source -> when ``body``'s newest measurement of it was taken, of every source that
        ever fed it (the lock held)."""
        t = self._t if tracker is None else tracker
        seen = t.by_source(body) if t.has(body) else {}
        for src, at in self.fed_before.get(body, {}).items():
            seen.setdefault(src, at)
        return seen

    def sources_of(self, body: str) -> tuple[str, ...]:
        """The sources that ever fed ``body``."""
        with self.lock.read():
            self.check_known(body)
            return tuple(self.fed(body))

    def newest(self, body: str, source: Optional[str] = None) -> float:
        """When ``body``'s newest measurement (of ``source``) was taken."""
        with self.lock.read():
            self.check_known(body)
            if source is None:
                return self._t.newest(body)
            seen = self.fed(body)
            if source not in seen:
                raise NotFound(f"source: {source!r} never fed body {body!r} (its sources: "
                               f"{', '.join(map(repr, seen)) or 'none'})")
            return seen[source]

    def horizon(self, body: str) -> float:
        """``body``'s horizon (:func:`dqpose.world_ticks.horizon`) as :meth:`tick_window` has it."""
        with self.lock.read():
            return horizon(self.riders.waited(body), self.options.max_delay)

    def newest_of(self, bodies: Sequence[str]) -> list[float]:
        """When each of ``bodies`` (held) had its newest measurement taken, in one look."""
        with self.lock.read():
            return self._t.newest_of(bodies)

    def tick_window(self, body: str, known: Optional[float] = None) -> TickWindow:
        """What ``body``'s ticks would fit now (:meth:`tick`; none for a body not held);
        ``known``: its :meth:`horizon`, when the caller has it."""
        with self.lock.read():
            if not self._t.has(body):
                return TickWindow(-math.inf, math.inf, 0, False)
            t = self._t
            newest, window = t.newest(body), self.options.window
            rows = t.rows_ending(body, newest, window)
            return TickWindow(horizon(self.riders.waited(body), self.options.max_delay)
                              if known is None else known, float(t.taken_of(rows).min()),
                              self.riders.cost(body, rows),
                              t.capped(body, window), rows)

    def tick(self, body: str, time: Optional[float]) -> tuple[BodyPose, np.ndarray]:
        """``body`` at tick ``time`` (None: its newest measurement's time) from its tick window
        (:meth:`_tick_rows`: StreamFuse's rows), with the fused measurements' ids."""
        with self.lock.read():
            if body in self.tree.static_bodies:        # its one constant pose
                return _frames.static_tick(self, body, time)
            rows = self._tick_rows(body, time)
            f, ids = self.fit_of(body, rows,
                                  lambda r: self._t.estimate(None, time, rows=r, ids=True))
        assert f.time is not None            # a fit over time
        return BodyPose(body, f.time, f.mean, f.covariance, f), ids

    def tick_wire(self, body: str, time: Optional[float], request: int,
                  relative_to: str = "", picked: Optional[np.ndarray] = None) -> Optional[bytes]:
        """:meth:`tick`'s answer to ``request`` as ``FusedPose`` bytes made in one C call
        (:class:`dqpose.fusion.tick.WireTicks`), with :meth:`relative`'s pose and covariance at
        the fit's time when ``relative_to`` names a body; or None: ask :meth:`tick` (then
        :meth:`relative`, whose refusal comes after the fit's). ``picked``: the rows of
        :meth:`tick_window`, unchanged since, when ``time`` is in its ``[floor, horizon]`` (the
        tick's rows, none of its refusals possible)."""
        if self.riders.parents and self.riders.rides(body, relative_to):
            return None     # composed in Python (dqpose.riders)
        if body in self.tree.static_bodies:
            return None         # tick's
        if picked is not None and not relative_to:
            with self.lock.read():
                return self._wire(picked, time, body, request)
        rel = None
        if relative_to:
            with self.lock.read():
                at = self.tick_time(body, time)
            try:
                rel = self.relative(relative_to, body, at)
            except (ValueError, LookupError):
                return None
        with self.lock.read():
            rows = self._tick_rows(body, time)
            if rel is None:
                return self._wire(rows, time, body, request)
            if rel.time != self.tick_time(body, time):   # time 0, or the world moved
                return None
            return self._wire(rows, time, body, request, rel.pose, rel.covariance)

    def tick_time(self, body: str, time: Optional[float]) -> float:
        """A tick's fusion time (the lock held): ``time``, or its rows' newest taken."""
        return float(time) if time is not None else float(
            self._t.taken_of(self._tick_rows(body, time)).max())

    def _tick_rows(self, body: str, time: Optional[float]) -> np.ndarray:
        """A tick's rows (the lock held): those taken within ``window`` of ``body``'s newest,
        the last the tracker's cap of them."""
        self.check_known(body)
        end = self._t.newest(body)
        return self.rows_for(body, end if time is None else time, end)

    def check_known(self, body) -> None:
        body = body_name(body)
        if not self._t.has(body):
            some = list(self._t.bodies)[:5]
            raise NotFound(f"body: {body!r} is not in the world (" + (
                f"{len(self._t.bodies)} bodies: {', '.join(map(repr, some))}"
                + (", ..." if len(self._t.bodies) > 5 else "") if some else "no bodies yet")
                + ")")

    def window_end(self, body: str, at: float) -> float:
        """Where a Lookup's window of ``body`` at ``at`` ends: half a window past ``at``, or at
        its newest (a tick's window when ``at`` is in its newer half)."""
        return min(self._t.newest(body), at + 0.5 * self.options.window)

    def fit_at(self, body: str, time: Optional[float], nis: bool = True) -> Fused:
        """``body``'s fit at ``time`` from the measurements of the window :meth:`window_end` ends
        (the lock held), or ``OutOfRange`` naming what is known. Without ``nis`` (a Lookup, which
        answers the pose and its covariance) the fit may leave out the leave-one-out NIS
        (:meth:`Tracker.estimate`); a kept fit with them serves both."""
        at = self.fit_time(body, time)
        end = self.window_end(body, at)
        key = (body, at, end)
        hit = self.fits.get(key)
        version = self.riders.version(body)
        if hit is not None and hit[0] == version and (hit[2] or not nis):
            return hit[1]       # no new data: it was in range then
        f, ids = self._fitted(body, at, lambda rows: self._t.estimate(None, at, rows=rows, nis=nis,
                                                                      ids=True))
        self.fits.keep(key, (version, f, nis, ids), len(f.distances))
        return f

    def pose_only(self, body: str, at: float) -> tuple[np.ndarray, np.ndarray]:
        """The known ``body``'s pose and covariance at the checked time ``at`` (the lock held),
        as :meth:`fit_at` would give them: a kept fit's, else only those (``Tracker.estimate``'s
        ``fit="pose"``)."""
        kept = self.kept_pose(body, at)
        if kept is not None:
            return kept
        return self._fitted(body, at,
                            lambda rows: self._t.estimate(None, at, rows=rows, fit="pose"))

    def kept_pose(self, body: str, at: float) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """A kept fit's pose and covariance of ``body`` at ``at`` if it is current, else None."""
        hit = self.fits.get((body, at, self.window_end(body, at)))
        if hit is not None and hit[0] == self.riders.version(body):
            return hit[1].mean, hit[1].covariance
        return None

    def fit_time(self, body: str, time: Optional[float]) -> float:
        """The time of a fit of ``body`` (checked to be known; "" the world frame): ``time``
        checked, None its newest."""
        if body:
            self.check_known(body)
        if time is None:
            return self._t.newest(body)
        try:
            return checked_seconds(time, "time")
        except ValueError as e:
            raise WorldError.of(e) from None

    def _fitted(self, body: str, at: float, fit):
        """``fit(rows)`` of ``body``'s rows of a Lookup at ``at``, or ``OutOfRange``."""
        return self.fit_of(body, self.rows_for(body, at), fit)

    def rows_for(self, body: str, at: float, end: Optional[float] = None) -> np.ndarray:
        """``body``'s rows of a fit at ``at``: taken in ``[end - window, end]`` (``end``: a
        Lookup's, :meth:`window_end`; a tick's, its newest), or ``OutOfRange`` naming what is
        known."""
        t = self._t
        newest = t.newest(body)
        end = self.window_end(body, at) if end is None else end
        rows = t.rows_ending(body, end, self.options.window)
        limit = self.options.max_extrapolation
        # the buffer's oldest is looked for only when the rows do not show it older than ``at``
        if not len(rows) or (limit is not None and at > newest + limit) or (
                at < t.taken_of(rows).min() and at < t.oldest(body)):
            raise self._out_of_range(body, at, t.oldest(body), newest, end)
        return rows

    def fit_of(self, body: str, rows: np.ndarray, fit):
        """``fit(rows)``, or ``OutOfRange`` naming why and what is known."""
        try:
            return fit(rows)
        except ValueError as e:
            known = _known_from(body, self._t.oldest(body), self._t.newest(body))
            raise OutOfRange(f"{e}; {known}") from e      # the fit's own words kept

    def _out_of_range(self, body: str, at: float, oldest: float, newest: float,
                      end: float) -> OutOfRange:
        """Why :meth:`fit_at` cannot fit ``body`` at ``at``, naming what is known."""
        known = _known_from(body, oldest, newest)
        if at < oldest:
            return OutOfRange(f"time: {_s(at)} is before the oldest measurement kept; {known} "
                              f"(buffer {self.options.buffer:g} s)")
        limit = self.options.max_extrapolation
        if limit is not None and at > newest + limit:
            return NotYet(f"time: {_s(at)} is {at - newest:.6g} s past the newest "
                              f"measurement, beyond max_extrapolation {limit:g} s; {known}")
        return OutOfRange(f"time: no measurement of {body!r} in the window "
                          f"{self.options.window:g} s ending at {_s(end)}; {known}")

    def pose(self, body: str, time: Optional[float] = None) -> BodyPose:
        """``T_world_body`` at ``time`` (None: the body's newest): :func:`dqpose.fusion.fuse`
        over its measurements taken in the ``window`` that ends half a window after ``time``,
        or at its newest measurement if sooner."""
        with self.lock.read():
            f = self.fit_at(body, time)
        assert f.time is not None            # a fit over time
        return BodyPose(body, f.time, f.mean, f.covariance, f)

    def relative(self, target: str, source: str, time: float = 0.0) -> BodyPose:
        """``T_target_source`` at ``time`` (0: the newest time both are known at) of any two
        frames ("" the world; :func:`dqpose.frames.relative`). Bodies that share a source with
        an ``extrinsic_covariance`` or an estimated latency are fitted together (one error per
        such source), so the covariance has their cross-covariance (:mod:`dqpose.lookup`)."""
        target, source = body_name(target, "target"), body_name(source, "source")
        with self.lock.read():
            return _frames.relative(self, target, source, time)

    def frame_pose(self, frame: str, at: float) -> BodyPose:
        """``T_world_frame`` at ``at`` and its covariance (:func:`dqpose.frames.frame_pose`)."""
        frame = body_name(frame, "frame")
        with self.lock.read():
            return _frames.frame_pose(self, frame, at)

    def frames(self, columns: bool = False):
        """The world's frames (:func:`dqpose.frames.frames`); ``columns``: the world's, the
        bodies' (:func:`dqpose.frames.body_columns`), the sources' and statics'."""
        with self.lock.read():
            return ((self.tree.fixed[0][0], _frames.body_columns(self), self.tree.fixed[1])
                    if columns else _frames.frames(self))

    def relative_at(self, target, time, source, source_time=0.0, fixed="") -> BodyPose:
        """tf2's advanced lookup through ``fixed`` (:func:`dqpose.two_times.relative_at`)."""
        from dqpose.two_times import relative_at
        return relative_at(self, target, time, source, source_time, fixed)

    def stamp(self, *bodies: str) -> tuple[int, ...]:
        """What an answer about ``bodies`` depends on: the configuration's number and each
        body's version, both only ever growing. Read without the lock (each is one dict or
        attribute read, whole under the interpreter lock), so an event loop may call it: an
        answer made between two equal stamps is the answer for as long as the stamp stays
        equal (no measurement of those bodies, no configuration came in)."""
        t, tree = self.riders, self.tree
        return (self._generation,) + tuple(t.version(tree.root(b)) for b in bodies)

    def arm_base(self, arm: str) -> BodyPose:
        """``T_world_base`` of ``arm``: the extrinsic of the source ``arms`` names, with its
        ``extrinsic_covariance`` (zeros when exact); it does not move, so ``time`` is 0."""
        with self.lock.read():
            if arm not in self.arms:
                raise NotFound(f"arm: {arm!r} has no source in the world's arms (" + (
                    ", ".join(map(repr, self.arms)) or "none configured") + ")")
            src = self._t.table[self.arms[arm]]
        cov = src.extrinsic_covariance
        return BodyPose(f"arm:{arm}", 0.0, dq.identity() if src.extrinsic is None else
                        src.extrinsic, np.zeros((DOF, DOF)) if cov is None else cov, None)


def _published(bodies, errors: Mapping[int, WorldError]) -> Published:
    if not errors:          # the common case
        return Published(len(bodies), (), tuple(dict.fromkeys(bodies)))
    touched = dict.fromkeys(b for k, b in enumerate(bodies) if k not in errors)
    return Published(len(bodies) - len(errors), tuple(errors[k] for k in sorted(errors)),
                     tuple(touched))
