"""A recording (:func:`dqpose.record.reader.read`) as what the viewer draws: each body's fused
poses (answers that carry a pose, error entries left out) with their covariances, each plan, and
each arm's actual poses (its Execute feedback and its WatchArm states), each arm's base in the
world (the World's configuration, ``WorldConfig.arms``), the frames fixed in their parents (its
statics and sources: the frame tree), all on one clock (the recording's arrival time, ns),
looked up by time."""
from __future__ import annotations

import dataclasses

import numpy as np
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

from dqpose import dq
from dqpose.record.types import (
    ARM_STATE,
    EXECUTE_REQUEST,
    EXECUTION_FEEDBACK,
    FUSED_POSE,
    WORLD_CONFIG,
)
from dqpose.record.views import pose_of


@dataclasses.dataclass
class Track:
    """One body's fused poses in arrival order: ``ns (n,)``, ``t (n, 3)``, ``q (n, 4)``
    (scalar first), ``cov (n, 6, 6)`` (NaN where an answer had none)."""
    ns: np.ndarray
    t: np.ndarray
    q: np.ndarray
    cov: np.ndarray

    def at(self, ns: int) -> int | None:
        """The index of the last pose at or before ``ns``, ``None`` before the first."""
        i = int(np.searchsorted(self.ns, ns, side="right")) - 1
        return None if i < 0 else i


@dataclasses.dataclass
class Path:
    """One arm's actual poses in arrival order: ``ns (n,)``, ``t (n, 3)``, ``q (n, 4)``."""
    ns: np.ndarray
    t: np.ndarray
    q: np.ndarray

    def upto(self, ns: int) -> int:
        """How many of the poses arrived at or before ``ns``."""
        return int(np.searchsorted(self.ns, ns, side="right"))


@dataclasses.dataclass
class Bases:
    """One arm's base in the world as each configuration in force set it: ``ns (n,)``,
    ``pose (n, 8)`` (``T_world_base``)."""
    ns: np.ndarray
    pose: np.ndarray

    def at(self, ns: int) -> np.ndarray:
        """The base in force at ``ns``; before the first configuration, the first (an arm's
        path recorded before its world was configured is drawn where the world later put it)."""
        return self.pose[max(int(np.searchsorted(self.ns, ns, side="right")) - 1, 0)]


@dataclasses.dataclass
class Fixed:
    """The frames fixed in their parents (a World's statics and sources) as each configuration
    in force set them: ``ns (n,)`` and, for each, ``frames``: name -> ``(parent,
    T_parent_frame (8,))``; ``bases``: the sources that are arms' bases (drawn as the arm's
    base, not again)."""
    ns: np.ndarray
    frames: list[dict[str, tuple[str, np.ndarray]]]
    bases: list[frozenset[str]]

    def at(self, ns: int) -> int:
        """The configuration in force at ``ns``; before the first, the first (as
        :class:`Bases`)."""
        return max(int(np.searchsorted(self.ns, ns, side="right")) - 1, 0)


def resolve(frames: dict[str, tuple[str, np.ndarray]],
            known: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``T_world_frame`` of each of ``frames`` (name -> ``(parent, T_parent_frame)``) whose
    chain of parents ends in one of ``known`` (name -> ``T_world_name``; ``""``, the world, is
    the identity): composed along the chain; a frame whose chain reaches an unknown name (a
    body not fused yet) or loops (a recording is not trusted to hold a valid tree) is left
    out."""
    out = {"": dq.identity(), **known}
    for name in frames:
        chain: list[str] = []
        at = name
        while at not in out and at in frames and len(chain) <= len(frames):
            chain.append(at)
            at = frames[at][0]
        if at not in out:
            continue
        for child in reversed(chain):
            out[child] = dq.mul(out[frames[child][0]], frames[child][1])
    return {name: out[name] for name in frames if name in out}


def tree(frames: dict[str, tuple[str, np.ndarray]], bases: frozenset[str],
         known: dict[str, np.ndarray]) -> tuple[dict, list]:
    """The frame tree to draw (``Scene.draw_tree``'s arguments): each body of ``known`` (name
    -> ``T_world_body``, those drawn now) linked from the world, each of ``frames`` (statics
    and sources: name -> ``(parent, T_parent_frame)``) from its parent at the pose its chain
    gives (:func:`resolve`; ``None`` while not known); the names drawn as frames of their own:
    ``frames`` but ``bases`` (arms' base sources, drawn as the arm's base)."""
    world = resolve(frames, known)
    links: dict = {b: ("", T) for b, T in known.items()}
    links.update({n: (p, world.get(n)) for n, (p, _) in frames.items()})
    return links, [n for n in frames if n not in bases]


@dataclasses.dataclass
class Timeline:
    start: int                  # ns of the first message drawn
    end: int
    tracks: dict[str, Track]
    plans: list[tuple[str, int, np.ndarray]]    # (name, ns, positions (n, 3))
    arms: dict[str, Path] = dataclasses.field(default_factory=dict)
    bases: dict[str, Bases] = dataclasses.field(default_factory=dict)
    fixed: Fixed | None = None

    def plan_at(self, name: str, ns: int) -> np.ndarray | None:
        """The positions of the last plan ``name`` made at or before ``ns``."""
        last = None
        for n, at, p in self.plans:
            if n == name and at <= ns:
                last = p
        return last


def timeline(rec) -> Timeline:
    """The :class:`Timeline` of a :class:`~dqpose.record.reader.Recording`."""
    fused = {c.id for c in rec.calls.values() if c.answer_type == FUSED_POSE}
    cls = rec.message_class(FUSED_POSE) if fused else None
    rows: dict[str, list] = {}
    for e in rec.events:
        if e.kind != "answer" or e.call not in fused:
            continue
        m = rec.decode(cls, e.data, e.ns, e.file)
        if m.HasField("error") or not m.HasField("pose"):
            continue
        p, o = m.pose.position, m.pose.orientation
        cov = (np.asarray(m.covariance, dtype=np.float64).reshape(6, 6)
               if len(m.covariance) == 36 else np.full((6, 6), np.nan))
        rows.setdefault(m.body, []).append((e.ns, (p.x, p.y, p.z), (o.w, o.x, o.y, o.z), cov))
    tracks = {body: Track(np.array([r[0] for r in rs], dtype=np.int64),
                          np.array([r[1] for r in rs]), np.array([r[2] for r in rs]),
                          np.array([r[3] for r in rs]))
              for body, rs in rows.items()}
    plans = []
    for name, ns, data in rec.plans:
        msg = rec.decode(PosesInFrame, data, ns)
        plans.append((name, ns, np.array([(p.position.x, p.position.y, p.position.z)
                                          for p in msg.poses]).reshape(-1, 3)))
    arms = arm_paths(rec)
    drawn: list[Track | Path] = [*tracks.values(), *arms.values()]
    times = [int(t.ns[0]) for t in drawn] + [ns for _, ns, _ in plans]
    ends = [int(t.ns[-1]) for t in drawn] + [ns for _, ns, _ in plans]
    configs = configurations(rec)
    return Timeline(min(times, default=0), max(ends, default=0), tracks, plans, arms,
                    arm_bases(configs), fixed_frames(configs))


def arm_paths(rec) -> dict[str, Path]:
    """Each arm's actual poses: the ``actual`` of its Execute feedback (the arm named by the
    call's request) and the ``pose`` of its WatchArm states, in arrival order."""
    kinds = {c.id: c.answer_type for c in rec.calls.values()
             if c.answer_type in (EXECUTION_FEEDBACK, ARM_STATE)}
    if not kinds:
        return {}
    classes = {name: rec.message_class(name) for name in set(kinds.values())}
    if EXECUTION_FEEDBACK in classes:
        classes[EXECUTE_REQUEST] = rec.message_class(EXECUTE_REQUEST)
    arm_of: dict[int, str] = {}
    rows: dict[str, list] = {}
    for e in rec.events:
        kind = kinds.get(e.call)
        if kind is None:
            continue
        if e.kind == "request":
            if kind == EXECUTION_FEEDBACK:
                arm_of[e.call] = rec.decode(classes[EXECUTE_REQUEST], e.data, e.ns, e.file).arm
            continue
        m = rec.decode(classes[kind], e.data, e.ns, e.file)
        if kind == ARM_STATE:
            arm, field = m.arm, "pose"
        else:
            arm, field = arm_of.get(e.call), "actual"
        if arm is not None and m.HasField(field):
            rows.setdefault(arm, []).append((e.ns, *pose_of(getattr(m, field))))
    return {arm: Path(np.array([r[0] for r in rs], dtype=np.int64), np.array([r[1] for r in rs]),
                      np.array([r[2] for r in rs]))
            for arm, rs in rows.items()}


def configurations(rec) -> dict[str, list]:
    """Each world's configurations in force (a ``Configure`` call's answer, a
    ``dqpose.v1.WorldConfig``) in arrival order: world -> ``[(ns, config)]``."""
    calls = {c.id: c.world for c in rec.calls.values()
             if c.answer_type == WORLD_CONFIG and c.rpc.endswith("/Configure")}
    if not calls:
        return {}
    cls = rec.message_class(WORLD_CONFIG)
    out: dict[str, list] = {}
    for e in rec.events:
        if e.kind == "answer" and e.call in calls:
            out.setdefault(calls[e.call], []).append((e.ns, rec.decode(cls, e.data, e.ns,
                                                                       e.file)))
    return out


def _pose(msg, given: bool) -> np.ndarray:
    """A ``Pose`` field as ``(8,)``; unset: the identity (fusion.proto, world.proto)."""
    if not given:
        return dq.identity()
    t, q = pose_of(msg)
    return dq.from_pose(q, t)


def fixed_frames(configs: dict[str, list]) -> Fixed | None:
    """The frames fixed in their parents of the default world's configurations, else of the
    first world's (in name order): each static at its pose, each named source at its
    extrinsic; ``None`` when no world was configured."""
    if not configs:
        return None
    got = configs[min(configs)]          # "" (the default world) sorts first
    frames = [{**{s.child: (s.parent, _pose(s.pose, s.HasField("pose"))) for s in c.statics},
               **{s.name: (s.parent, _pose(s.extrinsic, s.HasField("extrinsic")))
                  for s in c.sources if s.name}} for _, c in got]
    return Fixed(np.array([n for n, _ in got], dtype=np.int64), frames,
                 [frozenset(a.source for a in c.arms) for _, c in got])


def arm_bases(configs: dict[str, list]) -> dict[str, Bases]:
    """Each arm's base in the world: ``T_world_base`` = the extrinsic of the source that the
    World's configuration in force (:func:`configurations`) names for it. An arm named in
    several worlds' configurations is placed by the default world's, else by the first world
    (in name order) naming it."""
    rows: dict[str, dict[str, list]] = {}         # arm -> world -> [(ns, T_world_base)]
    for world, got in configs.items():
        for ns, config in got:
            sources = {s.name: s for s in config.sources}
            for a in config.arms:
                src = sources.get(a.source)
                if src is not None:
                    pose = _pose(src.extrinsic, src.HasField("extrinsic"))
                    rows.setdefault(a.arm, {}).setdefault(world, []).append((ns, pose))
    out = {}
    for arm, worlds in rows.items():
        got = worlds[min(worlds)]          # "" (the default world) sorts first
        out[arm] = Bases(np.array([n for n, _ in got], dtype=np.int64),
                         np.array([p for _, p in got]))
    return out
