"""The world's frame tree, tf2's with covariance: world, bodies, static bodies, sources, statics.

Convention: a frame's pose ``T_parent_frame`` maps points from the frame to its parent (bodies
and static bodies: fused in the world frame ""; sources: their extrinsic; statics: their pose),
each with a covariance 6x6, rotation first, a right perturbation ``T·Exp(ξ)`` (GTSAM's Pose3).

:class:`FrameTree` is one configuration's namespace and parents (checked: names, clashes, the
reserved "world", cycles, bounds); :func:`relative` resolves ``T_target_source`` of any two
frames through their lowest common ancestor, as tf2 does, so the part of the chain they share
cancels exactly; two bodies at the roots keep the world's joint fit (:mod:`dqpose.lookup`).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Mapping, NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq, lie
from dqpose.body_pose import BodyPose
from dqpose.errors import WorldError
from dqpose.fusion import Fused
from dqpose.fusion.results import DOF, read_only
from dqpose.fusion.sources import Source, pose_covariance
from dqpose.fusion.validation import checked_pose
from dqpose.lookup import composed_independent
from dqpose.names import name_problem, quoted
from dqpose.world_bounds import DEFAULT, WorldBounds, over

if TYPE_CHECKING:
    from dqpose.world import World

__all__ = ["Static", "FrameTree", "FrameKind", "FrameInfo", "RESERVED"]

#: the name no frame may have: the CLI's word for "", the world frame
RESERVED = "world"
_IDENT = dq.identity()
_ZERO = np.zeros((DOF, DOF))


class FrameKind(enum.IntEnum):
    """A frame's kind (the numbers of ``dqpose.v1.FrameKind``)."""
    UNSPECIFIED = 0
    WORLD = 1
    BODY = 2
    STATIC_BODY = 3
    SOURCE = 4
    STATIC = 5


@dataclass(frozen=True)
class Static:
    """``child`` fixed in ``parent`` ("" the world, a body, a source or another static) at
    ``pose`` ``(8,)`` = ``T_parent_child`` with ``covariance`` ``(6, 6)`` (None: exact), valid at
    every time (tf2's ``/tf_static``)."""
    parent: str
    child: str
    pose: np.ndarray
    covariance: Optional[np.ndarray] = None


@dataclass(frozen=True)
class FrameInfo:
    """One frame of :meth:`dqpose.world.World.frames`: its ``parent`` ("" for the world, bodies
    and static bodies), ``kind``, the span of its kept measurements ``oldest``..``newest`` (0
    for statics, sources and the world), ``rate_hz`` (measurements a second of measurement time
    over the second before ``newest``) and the ``sources`` that measured it."""
    name: str
    parent: str
    kind: FrameKind
    oldest: float = 0.0
    newest: float = 0.0
    rate_hz: float = 0.0
    sources: tuple[str, ...] = ()


def _named(name, field: str, empty: bool = False) -> str:
    problem = name_problem(name, empty)
    if problem is None and name == RESERVED:
        problem = (f"{RESERVED!r} is reserved (the world frame is \"\")")
    if problem is not None:
        raise WorldError(None, field, problem)
    return name


def _checked_static(s, k: int) -> Static:
    if not isinstance(s, Static):
        raise WorldError(None, f"statics[{k}]", f"expected a Static, got {type(s).__name__}")
    parent = _named(s.parent, f"statics[{k}].parent", empty=True)
    child = _named(s.child, f"statics[{k}].child")
    try:
        pose = checked_pose(s.pose, f"statics[{k}].pose")
        cov = pose_covariance(s.covariance, f"statics[{k}].covariance")
    except ValueError as e:
        raise WorldError.of(e) from None
    return Static(parent, child, read_only(pose), None if cov is None else read_only(cov))


class FrameTree:
    """One configuration's frames besides the bodies: ``sources`` (checked
    :class:`~dqpose.fusion.Source` by name), ``statics``, ``static_bodies``; every check a
    :class:`WorldError` naming the field (``statics[3].child``), the bounds'
    RESOURCE_EXHAUSTED (:func:`dqpose.world_bounds.over`)."""

    def __init__(self, sources: Mapping[str, Source], statics: Iterable[Static] = (),
                 static_bodies: Iterable[str] = (), bounds: WorldBounds = DEFAULT):
        statics, static_bodies = tuple(statics), tuple(static_bodies)
        if len(statics) > bounds.max_statics:
            raise over("statics", len(statics), "max_statics", bounds.max_statics)
        if len(static_bodies) > bounds.max_static_bodies:
            raise over("static_bodies", len(static_bodies), "max_static_bodies",
                       bounds.max_static_bodies)
        field: dict[str, str] = {}       # each configured name -> the field that gave it
        for k, name in enumerate(sources):
            _named(name, f"sources[{k}].name")
            field[name] = f"sources[{k}]"
        self.statics = tuple(_checked_static(s, k) for k, s in enumerate(statics))
        for k, s in enumerate(self.statics):
            _clash(field, s.child, f"statics[{k}].child", f"statics[{k}]")
        for k, b in enumerate(static_bodies):
            _clash(field, _named(b, f"static_bodies[{k}]"), f"static_bodies[{k}]",
                   f"static_bodies[{k}]")
        self.static_bodies = frozenset(static_bodies)
        self.sources = frozenset(sources)
        self.kinds: dict[str, FrameKind] = {n: FrameKind.SOURCE for n in sources}
        self.kinds.update((s.child, FrameKind.STATIC) for s in self.statics)
        self.kinds.update((b, FrameKind.STATIC_BODY) for b in static_bodies)
        # name -> (parent, T_parent_name, its covariance or None) of sources and statics
        self.links: dict[str, tuple[str, np.ndarray, Optional[np.ndarray]]] = {
            n: (s.parent, _IDENT if s.extrinsic is None else s.extrinsic,
                s.extrinsic_covariance) for n, s in sources.items()}
        self.links.update((s.child, (s.parent, s.pose, s.covariance)) for s in self.statics)
        for k, name in enumerate(sources):
            _named(sources[name].parent, f"sources[{k}].parent", empty=True)
        _acyclic(self.links, field)
        self.riders = {n: self.chain(n)[1:] for n, s in sources.items() if s.parent}
        # a Publish checks its rows' names only when a name could clash or a source rides
        self.checks = bool(self.statics or self.riders)
        self.static_body_names = tuple(static_bodies)      # in their configured order
        # the world's, the sources' and the statics': the same objects until a configuration
        self.fixed = ([FrameInfo("", "", FrameKind.WORLD)],
                      [FrameInfo(n, self.links[n][0], FrameKind.SOURCE) for n in sources]
                      + [FrameInfo(s.child, s.parent, FrameKind.STATIC) for s in self.statics])

    def kind(self, name: str) -> FrameKind:
        """``name``'s kind: "" the world, a configured one's, else a body."""
        return FrameKind.WORLD if not name else self.kinds.get(name, FrameKind.BODY)

    def chain(self, name: str) -> list[str]:
        """``name`` and its ancestors up to its root: "", a body or a static body."""
        out = [name]
        while name in self.links:
            name = self.links[name][0]
            out.append(name)
        return out

    def root(self, name: str) -> str:
        return self.chain(name)[-1] if name in self.links else name

    def clashes(self, held: Mapping[str, object]) -> None:
        """A configured static (or, in a world with statics or riders, a source: as
        :meth:`refuse`) that is a body the world holds measurements of: a WorldError naming
        it."""
        for name in held:
            kind = self.kinds.get(name)
            if kind == FrameKind.STATIC or (kind == FrameKind.SOURCE and self.checks):
                raise WorldError(None, "statics" if kind == FrameKind.STATIC else "sources",
                                 f"{quoted(name)} is a body with measurements in the world "
                                 f"(bodies, sources and statics share one namespace)")

    def refuse(self, bodies: Sequence[str], sources: Sequence[str], errors: dict) -> None:
        """Rows (not refused yet) whose body is "world", a source or a static, or whose source
        rides on the body it measures, refused in ``errors``."""
        seen: dict[tuple, Optional[WorldError]] = {}
        for k, pair in enumerate(zip(bodies, sources)):
            if k in errors:
                continue
            if pair not in seen:
                seen[pair] = self._refusal(*pair)
            e = seen[pair]
            if e is not None:
                errors[k] = e.at(k)

    def _refusal(self, body, source) -> Optional[WorldError]:
        if body == RESERVED:
            return WorldError(0, "body", f"{RESERVED!r} is reserved (the world frame is \"\")")
        kind = self.kinds.get(body) if isinstance(body, str) else None
        if kind == FrameKind.SOURCE:
            return WorldError(0, "body", f"{quoted(body)} is a source (config.sources)")
        if kind == FrameKind.STATIC:
            return WorldError(0, "body", f"{quoted(body)} is a static (config.statics)")
        if body and body in self.riders.get(source, ()):
            return WorldError(0, "source", f"source {quoted(source)} rides on body "
                                           f"{quoted(body)} (its parent chain reaches it): it "
                                           f"cannot measure the body it rides on")
        return None

    def offset(self, frame: str, ancestor: str) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """``T_ancestor_frame`` composed down the chain, with its covariance (None: exact)."""
        links = []
        while frame != ancestor:
            parent, X, P = self.links[frame]
            links.append((X, P))
            frame = parent
        X, P = _IDENT, None
        for Xb, Pb in reversed(links):
            X, P = _compose(X, P, Xb, Pb)
        return X, P


def _clash(field: dict[str, str], name: str, path: str, giver: str) -> None:
    if name in field:
        raise WorldError(None, path, f"{quoted(name)} is {field[name]}'s name already (bodies, "
                                     f"sources, statics and static bodies share one namespace)")
    field[name] = giver


def _acyclic(links: Mapping[str, tuple], field: Mapping[str, str]) -> None:
    """A cycle among the configured parents: a WorldError naming its frames."""
    done: set = set()
    for start in links:
        path: list[str] = []
        name = start
        while name in links and name not in done:
            if name in path:
                cycle = path[path.index(name):] + [name]
                raise WorldError(None, f"{field[name]}.parent", "the frames " + " -> ".join(
                    map(quoted, cycle)) + " form a cycle (each the parent of the one before)")
            path.append(name)
            name = links[name][0]
        done.update(path)


def _compose(Xa, Pa, Xb, Pb) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """``T_a·T_b`` of independent estimates and its covariance (None: both exact)."""
    X = dq.normalize(dq.mul(Xa, Xb))
    return X, (None if Pa is None and Pb is None else lie.cov_compose(Pa, Xb, Pb))


def _inverse(X, P) -> tuple[np.ndarray, Optional[np.ndarray]]:
    return dq.conj(X), None if P is None else lie.cov_inverse(X, P)


# ---- the world's answers (its read lock held) --------------------------------------------------

def static_fit(world: "World", body: str) -> Fused:
    """Static body ``body``'s one constant pose from all its kept measurements (the tracker's
    one-instant fit), kept until its version changes."""
    t = world.tracker
    world.check_known(body)
    key = (body, None, None)
    version = world.riders.version(body)
    hit = world.fits.get(key)
    if hit is not None and hit[0] == version:
        return hit[1]
    rows = t.rows_ending(body, t.newest(body), t.window)
    f, ids = world.fit_of(body, rows,
                           lambda r: t.estimate(rows=r, fit="static", ids=True))
    world.fits.keep(key, (version, f, True, ids), len(f.distances))
    return f


def static_tick(world: "World", body: str, time: Optional[float]) -> tuple[BodyPose, np.ndarray]:
    """Static body ``body``'s tick at ``time`` (None: its newest measurement's): its one pose,
    with the ids of the measurements fused."""
    f = static_fit(world, body)
    return (BodyPose(body, world.tick_time(body, time), f.mean, f.covariance, f),
            world.fits[(body, None, None)][3])


def _root_pose(world: "World", root: str, at: float) -> tuple[np.ndarray, np.ndarray]:
    if root in world.tree.static_bodies:
        f = static_fit(world, root)
        return f.mean, f.covariance
    return world.pose_only(root, at)


def relative(world: "World", target: str, source: str, time: float) -> BodyPose:
    """``T_target_source`` at ``time`` of any two frames (0: the newest time both roots'
    bodies are known at; statics, static bodies and the world alone: 0, valid at every time)."""
    tree, t = world.tree, world.tracker
    # a body with measurements is that body (a source's name only where no static or rider
    # makes the names one namespace, Publish refusing them there)
    ct = [target] if t.has(target) else tree.chain(target)
    cs = [source] if t.has(source) else tree.chain(source)
    roots = (ct[-1], cs[-1])
    for r in roots:
        if r and not t.has(r):
            world.check_known(r)         # raises, naming what is known
    moving = [r for r in roots if r and r not in tree.static_bodies]
    if time == 0.0:
        at = min(t.newest(r) for r in moving) if moving else 0.0
    else:
        at = world.fit_time("", time)
    if roots[0] == roots[1]:
        common = set(cs)
        lca = next(f for f in ct if f in common)
        if lca == roots[0] and moving:
            world.pose_only(lca, at)       # known at that time
        Xt, Pt = tree.offset(target, lca)
        Xs, Ps = tree.offset(source, lca)
        X, P = _compose(*_inverse(Xt, Pt), Xs, Ps)
        return BodyPose(source, at, read_only(X), read_only(_ZERO if P is None else P), None)
    rel = _roots(world, roots[0], roots[1], at)
    if len(ct) == 1 and len(cs) == 1:
        return rel
    Xt, Pt = tree.offset(target, roots[0])
    Xs, Ps = tree.offset(source, roots[1])
    X, P = _compose(*_inverse(Xt, Pt), rel.pose, rel.covariance)
    X, P = _compose(X, P, Xs, Ps)
    assert P is not None
    return BodyPose(source, at, read_only(X), read_only(P), None)


def _roots(world: "World", target: str, source: str, at: float) -> BodyPose:
    """``T_target_source`` of two different roots ("", bodies, static bodies): two bodies'
    Lookup (their joint fit where they share an uncertain source), kept until either
    changes; a static body's own pose composed."""
    statics = world.tree.static_bodies
    if target in statics or source in statics:
        return composed_independent(target, source, at,
                         {b: _root_pose(world, b, at) for b in (target, source) if b})
    key = (target, source, at)
    versions = (world.riders.version(target), world.riders.version(source))
    hit = world.kept_relatives.get(key)
    if hit is not None and hit[0] == versions:
        return hit[1]
    answer = world.lookups.relative(target, source, at)
    world.kept_relatives.keep(key, (versions, answer))
    return answer


def frame_pose(world: "World", frame: str, at: float) -> BodyPose:
    """``T_world_frame`` at ``at`` with its covariance; a body's and a static body's own fit
    (``fused``), any other frame composed."""
    if frame in world.tree.static_bodies:
        f = static_fit(world, frame)
        return BodyPose(frame, at, f.mean, f.covariance, f)
    if frame and world.tree.kind(frame) == FrameKind.BODY:
        f = world.fit_at(frame, at, nis=False)
        assert f.time is not None
        return BodyPose(frame, f.time, f.mean, f.covariance, f)
    p = relative(world, "", frame, at)
    return BodyPose(frame, p.time, p.pose, p.covariance, None)


class BodyColumns(NamedTuple):
    """The bodies' and static bodies' frames as columns: ``names``, ``kinds``, ``spans``
    ``(n, 3)`` (oldest, newest, rate_hz; zeros for a static body not measured yet) and the
    ``sources`` that measured each."""
    names: list[str]
    kinds: list[FrameKind]
    spans: np.ndarray
    sources: list[tuple[str, ...]]


def body_columns(world: "World") -> BodyColumns:
    """The bodies' frames (:class:`BodyColumns`), the measured ones' spans, rates and sources
    from one pass over the store's rows (``Tracker.spans``)."""
    t, tree = world.tracker, world.tree
    held = list(t.held)
    names = held + [b for b in tree.static_body_names if not t.has(b)]
    spans = np.zeros((len(names), 3))
    sources: list[tuple[str, ...]] = [()] * len(names)
    if held:
        oldest, newest, near, fed = t.spans(held, 1.0)
        spans[:len(held)] = np.stack([oldest, newest, near], axis=1)
        before = world.fed_before      # sources that fed a body under earlier configurations
        sources[:len(held)] = [
            f + tuple(s for s in before[b] if s not in f) if b in before else f
            for b, f in zip(held, fed)]
    statics = tree.static_bodies
    kinds = [FrameKind.STATIC_BODY if b in statics else FrameKind.BODY for b in names]
    return BodyColumns(names, kinds, spans, sources)


def frames(world: "World") -> list[FrameInfo]:
    """The world's frames: the world "", the bodies with measurements, the static bodies, the
    sources, the statics."""
    c = body_columns(world)
    return (list(world.tree.fixed[0])
            + [FrameInfo(n, "", k, lo, hi, rate, src)
               for n, k, (lo, hi, rate), src in zip(c.names, c.kinds, c.spans.tolist(),
                                                    c.sources)]
            + world.tree.fixed[1])
