"""Trajectories on SE(3): waypoints in, a time-scaled pose stream out, every Cartesian limit kept.

A path through waypoints is one segment per pair, in one of two modes (:data:`INTERPOLATIONS`):

* ``"tool_linear"``: the tool point on the straight line, the orientation slerped (MoveIt/Pilz LIN);
* ``"screw"``: ScLERP per segment, the tool point on a helix.

Each segment's progress ``s`` in [0, 1] rises over a jerk-limited S-curve ramp, cruises and falls
over another. A waypoint with a ``blend_radius`` is not stopped at: each neighbouring segment slows
to a corner speed (as much as the radius needs), then the next segment's ramp-up runs during this
one's ramp-down with the same shape (time blending, as UR and Pilz blend), so the velocity there
is a convex combination of the two corner velocities and the tool point stays within the radius
of the corner. On a blended or SCREW segment (or the first one, moving at ``start_velocity``)
orientation and position follow the one parameter ``s`` (Pilz LIN semantics). A TOOL_LINEAR
segment at rest at both ends gives each its own: the tool point's progress along the line and
the slerp's are each the time-optimal 1-D S-curve under their own limits, the faster one
stretched to the slower one's duration (Ruckig's time synchronisation; equal durations on
straight moves, docs/benchmarks/trajectories.md#planning); the path is the same line and slerp. The
limits on the tool point's linear velocity, acceleration and jerk and on the tool's angular
velocity, acceleration and jerk are met by construction: the C planner
(``service/csrc/trajectory.c``, where the bounds are derived) sizes every ramp by upper bounds of
these quantities, and ``tests/test_trajectory.py`` checks them on the samples themselves.

Velocities (``Samples.linear_velocity``, ``angular_velocity``) are those of the tool point and of
the tool, both in the base frame, as UR reports TCP speed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple, Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose import dq
from dqpose.errors import FieldError, FieldInfeasible, rename

__all__ = ["INTERPOLATIONS", "Limits", "Waypoint", "Segment", "Samples", "Trajectory",
           "Infeasible", "plan", "Derivatives", "derivatives", "Peaks", "peaks"]

INTERPOLATIONS = ("tool_linear", "screw")   # proto Interpolation: TOOL_LINEAR=1, SCREW=2
MAX_SAMPLES = 100_000_000                   # at_rate's refusal: 2.4 GB of output
_MODE = {"tool_linear": 1, "screw": 2}       # trajectory.h: DQ_TRAJ_LINEAR, DQ_TRAJ_SCREW
# codes of dq_traj_plan
_E_TIME, _E_START, _E_STUCK = 20, 21, 22


class Infeasible(FieldInfeasible):
    """The limits cannot meet the request (a waypoint's time, the start velocity): gRPC's
    FAILED_PRECONDITION."""


#: what a limit may be (m, rad, s): a plan at 5e-324 m/s lasts longer than a double holds
LIMIT_RANGE = (1e-9, 1e9)


@dataclass(frozen=True)
class Limits:
    """Cartesian limits of the tool point (linear) and the tool (angular). Velocities and
    accelerations are required, within ``LIMIT_RANGE``; a jerk of 0 means no jerk limit."""
    max_linear_velocity: float        # m/s
    max_angular_velocity: float       # rad/s
    max_linear_acceleration: float    # m/s^2
    max_angular_acceleration: float   # rad/s^2
    max_linear_jerk: float = 0.0      # m/s^3
    max_angular_jerk: float = 0.0     # rad/s^3

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise FieldError(f"limits.{f.name}: must be a number, got {v!r}") from None
            jerk = f.name.endswith("jerk")
            if not (math.isfinite(v) and (v >= 0 if jerk else v > 0)):
                need = "finite and >= 0 (0: no limit)" if jerk else "finite and > 0"
                raise FieldError(f"limits.{f.name}: must be {need}, got {v!r}")
            lo, hi = LIMIT_RANGE
            if (v or not jerk) and not lo <= v <= hi:
                raise FieldError(f"limits.{f.name}: {v:.6g} is outside [{lo:g}, {hi:g}] (SI "
                                 f"units): the times and samples of a motion at such a limit "
                                 f"do not fit a double")
            object.__setattr__(self, f.name, v)

    def as_array(self) -> np.ndarray:
        """``[v, w, a, alpha, j, jerk_w]``: the order of the C core's dq_traj_limits."""
        return np.array([getattr(self, name) for name in LIMIT_FIELDS])


#: the fields of :class:`Limits`, in the order of the proto's and the C core's
LIMIT_FIELDS = tuple(f.name for f in fields(Limits))
# trajectory.h's DQ_BIND_* in order: what decided a segment's cruise
_BINDINGS = LIMIT_FIELDS + ("time",)


@dataclass(frozen=True)
class Waypoint:
    """A pose ``T_base_tool`` (8,) to pass through. ``time`` > 0: the time (s from the start) it
    must be reached (at a blend: the middle of the blend); 0: as soon as the limits allow.
    ``blend_radius`` > 0: pass the corner without stopping, the tool point within this distance
    (m) of it; the segments slow down near the corner as much as the radius needs (a radius far
    too small for the turn, as at a reversal, comes down to a stop)."""
    pose: np.ndarray
    time: float = 0.0
    blend_radius: float = 0.0


class Segment(NamedTuple):
    """Segment k, from waypoint k to k+1: when it starts moving, how long it moves (a blended
    segment overlaps its neighbours), and the Limits field (or ``"time"``) that decided its speed
    (with separate translation and rotation laws: that of the slower one)."""
    start: float
    duration: float
    binding: str


class Samples(NamedTuple):
    """Poses and velocities at ``time`` (N,): ``pose`` (N, 8), ``linear_velocity`` (N, 3) of the
    tool point and ``angular_velocity`` (N, 3) of the tool, both in the base frame."""
    time: np.ndarray
    pose: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray


class Trajectory:
    """A planned trajectory (see :func:`plan`); evaluating it costs one ScLERP/slerp per sample."""

    def __init__(self, table: bytes, mode: int, duration: float, segments: tuple[Segment, ...]):
        self._table, self._mode = table, mode
        self.duration = duration
        self.segments = segments

    def sample(self, times) -> Samples:
        """The trajectory at ``times`` (any order; sorted ones are evaluated side by side, several
        times faster), each within ``[0, duration]``."""
        t = np.ascontiguousarray(times, dtype=np.float64)
        if t.ndim != 1:
            raise FieldError(f"times: expected a 1-D array, got shape {t.shape}")
        bad = np.flatnonzero(~((t >= 0) & (t <= self.duration)))
        if bad.size:
            raise FieldError(f"times[{bad[0]}]: {float(t[bad[0]])!r} is outside "
                             f"[0, {self.duration!r}]")
        return Samples(t, *_c.traj_eval(self._table, self._mode, self.duration, t))

    def at_rate(self, rate_hz: float) -> Samples:
        """Samples every ``1 / rate_hz`` s from 0, and the last one at ``duration`` exactly."""
        r = float(rate_hz)
        if not (math.isfinite(r) and r > 0):
            raise FieldError(f"rate_hz: must be finite and > 0, got {rate_hz!r}")
        n = math.ceil(self.duration * r)
        if n > MAX_SAMPLES:
            raise FieldError(f"rate_hz: {r!r} Hz over {self.duration!r} s is {n} samples, more "
                             f"than {MAX_SAMPLES}")
        t = np.arange(n) / r
        t = np.append(t[t < self.duration], self.duration)
        return Samples(t, *_c.traj_eval(self._table, self._mode, self.duration, t))


def _numbers(wps, name: str) -> np.ndarray:
    """The field `name` of every waypoint, each finite and >= 0."""
    try:
        v = np.array([getattr(w, name) for w in wps], dtype=np.float64)
    except (TypeError, ValueError):
        for i, w in enumerate(wps):
            try:
                float(getattr(w, name))
            except (TypeError, ValueError):
                raise FieldError(f"waypoints[{i}].{name}: must be a number, "
                                 f"got {getattr(w, name)!r}") from None
        raise
    bad = np.flatnonzero(~(np.isfinite(v) & (v >= 0)))
    if bad.size:
        i = bad[0]
        raise FieldError(f"waypoints[{i}].{name}: must be finite and >= 0, got {float(v[i])!r}")
    return v


def _waypoints(waypoints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses (K, 8) (each in the previous one's hemisphere), times, radii; errors name the index."""
    wps = list(waypoints)
    if len(wps) < 2:
        raise FieldError(f"waypoints: need at least 2, got {len(wps)}")
    bad = next((i for i, w in enumerate(wps) if not isinstance(w, Waypoint)), None)
    if bad is not None:
        raise FieldError(f"waypoints[{bad}]: expected a Waypoint, got {type(wps[bad]).__name__}")
    # whole arrays first (the common case, one conversion each); a failure is then located
    try:
        poses = np.array([w.pose for w in wps], dtype=np.float64)
    except (TypeError, ValueError):
        poses = None
    if poses is None or poses.shape != (len(wps), 8):
        for i, w in enumerate(wps):
            shape = np.shape(w.pose)
            if shape != (8,):
                raise FieldError(f"waypoints[{i}].pose: expected shape (8,), got {shape}")
        raise FieldError("waypoints: poses are not arrays of 8 numbers")
    times, radius = (_numbers(wps, name) for name in ("time", "blend_radius"))
    try:
        dq.to_pose(poses)                 # checks each pose is a unit dual quaternion
    except ValueError as e:
        raise rename(e, {"a": "waypoints{}.pose"}) from None
    poses = dq.normalize(poses)
    # one hemisphere along the path, so the stream never flips sign
    flip = np.cumprod(np.where(np.einsum("ij,ij->i", poses[1:, :4], poses[:-1, :4]) < 0, -1.0, 1.0))
    poses[1:] *= flip[:, None]
    if times[0] != 0:
        raise FieldError(f"waypoints[0].time: the first waypoint is the start (time 0), "
                         f"got {float(times[0])!r}")
    timed = np.flatnonzero(times)
    for a, b in zip(timed[:-1], timed[1:]):
        if times[b] <= times[a]:
            raise FieldError(f"waypoints[{b}].time: {float(times[b])!r} is not after "
                             f"waypoints[{a}].time {float(times[a])!r} (times must increase)")
    for i in (0, len(wps) - 1):
        if radius[i] > 0:
            raise FieldError(f"waypoints[{i}].blend_radius: the first and last waypoints are "
                             f"not blended, got {float(radius[i])!r}")
    return poses, times, radius


def _path_lengths(poses: np.ndarray, mode: int) -> tuple[np.ndarray, np.ndarray]:
    """Per segment: the tool point's path length and the rotation angle."""
    half = dq.log(dq.mul(dq.conj(poses[:-1]), poses[1:]))   # half the body twist of each segment
    angle = 2 * np.linalg.norm(half[:, :3], axis=1)
    if mode == _MODE["screw"]:
        return 2 * np.linalg.norm(half[:, 3:], axis=1), angle
    t = dq.to_pose(poses)[1]
    return np.linalg.norm(np.diff(t, axis=0), axis=1), angle


def _start_vector(v0) -> np.ndarray:
    v0 = np.asarray(v0, dtype=np.float64)
    if v0.shape != (6,) or not np.all(np.isfinite(v0)):
        raise FieldError(f"start_velocity: expected 6 finite numbers [vx vy vz wx wy wz], "
                         f"got {v0!r}")
    return v0


def _start_rate(v0: np.ndarray, poses, mode) -> float | None:
    """The start velocity as a rate ds/dt of segment 0, or None when it does not point along
    it (the one-parameter profile can start moving only along its path)."""
    if not v0.any():
        return 0.0
    # the path's velocity per unit ds/dt at waypoint 0, base frame: the body twist of segment 0
    # (2 log(T0* T1)) turned by T0's rotation; on a line the tool point moves along T1 - T0
    twist = 2 * dq.log(dq.mul(dq.conj(poses[0]), poses[1]))
    turn = dq.from_pose(poses[0, :4], np.zeros(3))
    lin = (dq.transform(turn, twist[3:]) if mode == _MODE["screw"]
           else np.diff(dq.to_pose(poses[:2])[1], axis=0)[0])
    u = np.concatenate([lin, dq.transform(turn, twist[:3])])
    rate = float(v0 @ u / (u @ u))
    if rate < 0 or np.linalg.norm(v0 - rate * u) > 1e-9 * max(1.0, float(np.linalg.norm(v0))):
        return None
    return rate


# A start velocity slower than this (m/s, rad/s) is rest to the planner: braking from it would
# take a time that underflows.
_AT_REST = 1e-12

# How far past its braking point (in the braking's own time) the redirect segment reaches, and
# how many times that reach may double when the planner's bounds need more room.
_REDIRECT_REACH = 0.625
_REDIRECT_TRIES = 6


def _redirect(start: np.ndarray, v0: np.ndarray, limits: Limits, mode: int, reach: float):
    """A pose on the motion the start velocity is on (the line and the turn about w in
    TOOL_LINEAR, the screw of the twist in SCREW), as far as ``reach`` times the longest of the
    linear and angular S-curve stops from that velocity (trajectory.c's ramps are at most that
    long) would carry it at that velocity; and ds/dt at the start of the segment to it."""
    stop = 0.0
    for V, A, J in ((np.linalg.norm(v0[:3]), limits.max_linear_acceleration,
                     limits.max_linear_jerk),
                    (np.linalg.norm(v0[3:]), limits.max_angular_acceleration,
                     limits.max_angular_jerk)):
        if V > 0:
            stop = max(stop, V / (A * 0.95) + (A / J if J > 0 else 0.0))
    tau = reach * stop
    if np.linalg.norm(v0[3:]) * tau >= math.pi:
        # a slerp takes the short way: the segment cannot hold half a turn or more
        raise Infeasible(f"start_velocity: the turn it is on needs "
                         f"{math.degrees(np.linalg.norm(v0[3:]) * tau):.0f} degrees to be "
                         f"brought into the path under the limits (less than 180 are supported)")
    q0, p0 = dq.to_pose(start)
    if mode == _MODE["screw"]:
        # T0 Exp(tau xi) with the body twist xi of the start velocity (the tool point is the
        # tool frame's origin); log is half the twist
        back = dq.conj(dq.from_pose(q0, np.zeros(3)))
        half = 0.5 * tau * np.concatenate([dq.transform(back, v0[3:]), dq.transform(back, v0[:3])])
        return dq.mul(start, dq.exp(half)), 1.0 / tau
    turn = dq.exp(np.concatenate([0.5 * tau * v0[3:], np.zeros(3)]))     # base frame
    return (dq.from_pose(dq.mul(turn, dq.from_pose(q0, np.zeros(3)))[:4], p0 + tau * v0[:3]),
            1.0 / tau)


def plan(waypoints, limits: Limits, interpolation: str = "tool_linear", *,
         start_velocity=None) -> Trajectory:
    """The fastest trajectory through ``waypoints`` (a sequence of :class:`Waypoint`) that this
    planner's profile allows under ``limits``, at rest at the end and at rest (or moving at
    ``start_velocity``, (6,) ``[vx vy vz wx wy wz]`` of the tool point and the tool, base frame)
    at the start. A start velocity along the first segment is taken up by its time law; any other
    (replanning while moving) first follows the motion it is on, blended into the first segment
    as at a corner (``_plan_redirected``), so the path leaves waypoint 0 the way the tool moves.

    Errors: ``ValueError`` (:class:`~dqpose.errors.FieldError`) naming the field, e.g.
    ``waypoints[3].blend_radius: ...`` or ``limits.max_linear_velocity: ...``; :class:`Infeasible`
    when a waypoint's time or the start velocity cannot be met under the limits.
    """
    if not isinstance(limits, Limits):
        raise FieldError(f"limits: expected a Limits, got {type(limits).__name__}")
    if interpolation not in _MODE:
        raise FieldError(f"interpolation: unknown {interpolation!r}; expected one of "
                         f"{', '.join(INTERPOLATIONS)}")
    mode = _MODE[interpolation]
    poses, times, radius = _waypoints(waypoints)
    length, angle = _path_lengths(poses, mode)
    still = np.flatnonzero((length == 0) & (angle == 0))
    if still.size:
        i = still[0] + 1
        raise FieldError(f"waypoints[{i}].pose: the same pose as waypoints[{i - 1}] (no motion)")
    # a blend uses at most `radius` of path on each side; more than half a segment would let the
    # blends at its two ends overlap
    half_len = np.minimum(np.append(np.inf, length), np.append(length, np.inf)) / 2
    over = np.flatnonzero(radius > half_len)
    if over.size:
        i = over[0]
        raise FieldError(f"waypoints[{i}].blend_radius: {float(radius[i])!r} m is more than half a "
                         f"neighbouring segment ({float(half_len[i])!r} m)")
    sigma0: Optional[float] = 0.0
    v0 = None
    if start_velocity is not None:
        v0 = _start_vector(start_velocity)
        if math.hypot(*v0) < _AT_REST:
            v0 = np.zeros(6)
        for v, name in ((math.hypot(*v0[:3]), "max_linear_velocity"),
                        (math.hypot(*v0[3:]), "max_angular_velocity")):
            if v > getattr(limits, name) * (1 + 1e-12):
                raise Infeasible(f"start_velocity: {v:.6g} is over limits.{name} "
                                 f"{getattr(limits, name):.6g}")
        sigma0 = _start_rate(v0, poses, mode)
    if sigma0 is not None:
        code, bad, table, duration, segs = _c.traj_plan(poses, mode, radius, times,
                                                       limits.as_array(), sigma0)
    else:
        assert v0 is not None           # only a start velocity has no rate along the path
        code, bad, table, duration, segs = _plan_redirected(poses, mode, radius, times, limits, v0)
    if code == _E_TIME:
        raise Infeasible(f"waypoints[{bad}].time: {float(times[bad])!r} s cannot be met under the "
                         f"limits")
    if code == _E_START:
        raise Infeasible("start_velocity: cannot be brought to rest within the first segment "
                         "under the limits")
    if code:
        raise Infeasible(f"waypoints[{bad}]: no speed satisfies the limits around this waypoint")
    segments = tuple(Segment(s, d, _BINDINGS[int(b)]) for s, d, b in segs.tolist())
    return Trajectory(table, mode, float(duration), segments)


def _plan_redirected(poses, mode, radius, times, limits: Limits, v0: np.ndarray):
    """A start velocity off the first segment (replanning while moving): a segment along the
    motion it is on, to a pose somewhat past where that motion could stop, blended into the
    first segment (the planner lowers that corner's speed as far as its radius and the limits
    need: at worst a stop there). Waypoint indices and segments are reported as the caller's:
    the redirect and the first segment are one segment 0."""
    code = _E_START
    for k in range(_REDIRECT_TRIES):
        via, sigma0 = _redirect(poses[0], v0, limits, mode, _REDIRECT_REACH * 2 ** k)
        path = np.insert(poses, 1, via, axis=0)
        length, _ = _path_lengths(path, mode)
        # blends at most half of each segment, the caller's at waypoint 1 too (its segment is new)
        rad = np.insert(radius, 1, 0.5 * min(length[0], length[1]) * (1 - 1e-9))
        rad[2] = min(rad[2], 0.5 * length[1] * (1 - 1e-9))
        code, bad, table, duration, segs = _c.traj_plan(
            path, mode, rad, np.insert(times, 1, 0.0), limits.as_array(), sigma0)
        if code != _E_START:
            break
    if code:
        return code, max(bad - 1, 0), None, 0.0, None
    first = np.array([[0.0, segs[1, 0] + segs[1, 1], segs[1, 2]]])
    return code, 0, table, duration, np.concatenate([first, segs[2:]])


class Derivatives(NamedTuple):
    """The motion of sampled poses by finite differences (what an observer of the samples
    sees, whatever produced them): positions and rotation vectors from the first orientation
    (N, 3); velocities (N-1, 3), accelerations (N-2, 3) and jerks (N-3, 3) of the tool point and
    of the tool, base frame, each at the centre of the samples it differences."""
    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    acceleration: np.ndarray
    angular_acceleration: np.ndarray
    jerk: np.ndarray
    angular_jerk: np.ndarray


def _rate(x: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Differences of ``x`` sampled at ``at`` over the time between, and their centres."""
    return np.diff(x, axis=0) / np.diff(at)[:, None], (at[1:] + at[:-1]) / 2


def derivatives(times, poses) -> Derivatives:
    """:class:`Derivatives` of ``poses`` ``(N, 8)`` at strictly increasing ``times`` ``(N,)``.
    The angular velocity between two samples is the rotation vector of ``R_{k+1} R_k^T`` over
    the time step: the true one for a constant rate in between, not the derivative of some
    orientation coordinates (which is not an angular velocity)."""
    t = np.asarray(times, dtype=np.float64)
    q, p = dq.to_pose(dq.normalize(np.asarray(poses, dtype=np.float64).reshape(-1, 8)))
    r = np.concatenate([q, np.zeros_like(q)], axis=1)
    # dq.log is half the twist; the relative rotations are taken in the base frame (left)
    turn = 2.0 * dq.log(dq.mul(r[1:], dq.conj(r[:-1])))[:, :3]
    rotation = 2.0 * dq.log(dq.mul(r, dq.conj(r[:1])))[:, :3]
    v, m1 = _rate(p, t)
    w = turn / np.diff(t)[:, None]
    a, m2 = _rate(v, m1)
    alpha, _ = _rate(w, m1)
    j, _ = _rate(a, m2)
    zeta, _ = _rate(alpha, m2)
    return Derivatives(p, rotation, v, w, a, alpha, j, zeta)


class Peaks(NamedTuple):
    """The largest norms over sampled poses (:func:`peaks`): m/s, rad/s, m/s^2, ..."""
    linear_velocity: float
    angular_velocity: float
    linear_acceleration: float
    angular_acceleration: float
    linear_jerk: float
    angular_jerk: float


def peaks(times, poses) -> Peaks:
    """The largest velocity, acceleration and jerk norms of sampled poses, by finite differences
    (:func:`derivatives`): what a controller receiving them sees, whatever produced them; 0 where
    there are too few samples for that order."""
    d = derivatives(times, poses)
    top = lambda x: float(np.linalg.norm(x, axis=1).max(initial=0.0))   # noqa: E731
    return Peaks(top(d.velocity), top(d.angular_velocity), top(d.acceleration),
                 top(d.angular_acceleration), top(d.jerk), top(d.angular_jerk))
