"""A recording (:func:`dqpose.record.reader.read`) as what the viewer draws: each body's fused
poses (answers that carry a pose, error entries left out) with their covariances, each plan, and
each arm's actual poses (its Execute feedback and its WatchArm states), all on one clock (the
recording's arrival time, ns), looked up by time."""
from __future__ import annotations

import dataclasses

import numpy as np
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

from dqpose.record.views import ARM_STATE, EXECUTE_REQUEST, EXECUTION_FEEDBACK, pose_of

FUSED_POSE = "dqpose.v1.FusedPose"


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
class Timeline:
    start: int                  # ns of the first message drawn
    end: int
    tracks: dict[str, Track]
    plans: list[tuple[str, int, np.ndarray]]    # (name, ns, positions (n, 3))
    arms: dict[str, Path] = dataclasses.field(default_factory=dict)

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
        m = cls.FromString(e.data)       # type: ignore[union-attr]
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
        msg = PosesInFrame.FromString(data)
        plans.append((name, ns, np.array([(p.position.x, p.position.y, p.position.z)
                                          for p in msg.poses]).reshape(-1, 3)))
    arms = arm_paths(rec)
    drawn: list[Track | Path] = [*tracks.values(), *arms.values()]
    times = [int(t.ns[0]) for t in drawn] + [ns for _, ns, _ in plans]
    ends = [int(t.ns[-1]) for t in drawn] + [ns for _, ns, _ in plans]
    return Timeline(min(times, default=0), max(ends, default=0), tracks, plans, arms)


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
                arm_of[e.call] = classes[EXECUTE_REQUEST].FromString(e.data).arm
            continue
        m = classes[kind].FromString(e.data)
        if kind == ARM_STATE:
            arm, field = m.arm, "pose"
        else:
            arm, field = arm_of.get(e.call), "actual"
        if arm is not None and m.HasField(field):
            rows.setdefault(arm, []).append((e.ns, *pose_of(getattr(m, field))))
    return {arm: Path(np.array([r[0] for r in rs], dtype=np.int64), np.array([r[1] for r in rs]),
                      np.array([r[2] for r in rs]))
            for arm, rs in rows.items()}
