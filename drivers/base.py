"""The two driver interfaces: ``PoseSource`` (cameras, trackers, arms reporting where they are)
and ``Arm`` (anything we command).

Like python-can's ``BusABC``, each backend is one module (``dqpose.drivers.ur``,
``dqpose.drivers.piper``, ``dqpose.drivers.camera``) with a real implementation, and
``dqpose.drivers.sim`` holds simulators that speak the same protocol. Poses cross this boundary
as unit dual quaternions, NumPy ``(8,)``, in the project's convention (``[w, x, y, z, w', x',
y', z']``, metres, seconds); a tool pose is ``T_base_tool``.
"""
from __future__ import annotations

import abc
import dataclasses
import math
import numbers
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterator, Optional

import numpy as np

from dqpose import dq, trajectory
from dqpose.drivers.rotvec import rotvec_from_quat

if TYPE_CHECKING:
    from dqpose.drivers.run import Run


@dataclass(frozen=True)
class Measurement:
    """One pose measurement, in the convention :func:`dqpose.fusion.fuse` and the Fusion service
    take.

    ``pose`` is ``T_frame_body`` as a unit dual quaternion (a camera's ``T_camera_board``, an
    arm's ``T_base_tool``); ``time`` is when it was taken, in seconds of ``time.time()`` (Unix
    time), the one clock every driver stamps with. ``covariance`` is 6x6, row-major, **rotation
    first** ``[wx wy wz vx vy vz]`` (radians, then metres), of a **right (body-frame)
    perturbation** with the SE(3) exponential: the true pose is ``pose * Exp(xi)``,
    ``xi ~ N(0, covariance)``, ``Exp`` = :func:`dqpose.lie.se3_exp` (GTSAM's ``Pose3``
    convention, ``retract`` = compose with ``Expmap``). When it is unknown (None), ``weight``
    says how much to trust the pose: the covariance is then ``I / weight``."""
    source: str
    time: float
    pose: np.ndarray
    covariance: Optional[np.ndarray] = None
    weight: float = 1.0


class PoseSource(abc.ABC):
    """Anything that measures poses."""

    name: str = "source"

    @abc.abstractmethod
    def read(self, timeout: Optional[float] = None) -> Optional[Measurement]:
        """The next measurement, or None if there was none within ``timeout`` seconds or the
        view was rejected (see the backend for the reason)."""

    def __iter__(self) -> Iterator[Measurement]:
        while True:
            m = self.read()
            if m is None:
                return
            yield m

    def close(self) -> None:  # noqa: B027 (a source with nothing to release keeps it)
        """Release the device."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: an arm whose tool moves slower than these counts as at rest (:attr:`ArmState.at_rest`); above
#: what a resting arm's feedback shows (a PiPER's 0.001 mm steps differenced over 5 ms: 2e-4 m/s)
REST_LINEAR_SPEED = 1e-3     # m/s
REST_ANGULAR_SPEED = 1e-2    # rad/s


@dataclass
class ArmState:
    """What an arm says about itself. :meth:`Arm.status` fills the health (``connected``, the
    stop flags, ``faults``: one text per fault, empty when healthy; ``extra``: the backend's
    details); :meth:`Arm.state` adds the motion: ``stamp`` (``time.time()`` of the reading),
    ``pose`` ``T_base_tool`` (8,), ``linear_velocity`` of the tool point and
    ``angular_velocity`` of the tool (3,), m/s and rad/s in the base frame (None where the arm
    could not be read)."""
    connected: bool = False
    protective_stop: bool = False
    emergency_stop: bool = False
    faults: tuple = ()
    extra: dict = field(default_factory=dict)
    stamp: float = math.nan
    pose: Optional[np.ndarray] = None
    linear_velocity: Optional[np.ndarray] = None
    angular_velocity: Optional[np.ndarray] = None

    @property
    def error(self) -> str:
        """The faults in one text ("" when healthy)."""
        return "; ".join(self.faults)

    @property
    def ok(self) -> bool:
        return self.connected and not (self.protective_stop or self.emergency_stop) \
            and not self.faults

    @property
    def at_rest(self) -> bool:
        """The tool moves slower than :data:`REST_LINEAR_SPEED` and :data:`REST_ANGULAR_SPEED`
        (False when its velocity is unknown)."""
        if self.linear_velocity is None or self.angular_velocity is None:
            return False
        return bool(np.linalg.norm(self.linear_velocity) < REST_LINEAR_SPEED
                    and np.linalg.norm(self.angular_velocity) < REST_ANGULAR_SPEED)


class ArmError(RuntimeError):
    """The arm cannot do what was asked (lost connection, protective stop, refused command)."""


class LimitError(ArmError):
    """A command was refused because it breaks a safety limit. ``limit`` names the field of
    :class:`Limits` (``"max_linear_velocity"``, ``"workspace"``, ...), ``value`` is what the command
    asked for and ``bound`` the limit, both in the units of that field. A refused ``servo()``
    set-point has also brought the arm to a controlled stop; a refused ``move()`` sent nothing."""

    def __init__(self, message: str, limit: str, value, bound):
        super().__init__(message)
        self.limit, self.value, self.bound = limit, value, bound

    def __reduce__(self):       # whole across a process boundary (drivers.armproc)
        return type(self), (str(self), self.limit, self.value, self.bound)


def _positive(name: str, v) -> float:
    if isinstance(v, bool) or not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: must be a positive finite number, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class Limits(trajectory.Limits):
    """What a command may ask of any arm, in the tool frame's motion relative to the base: the
    planner's :class:`dqpose.trajectory.Limits` (the proto's names, checked by its rules), with
    defaults, and the arm's own bounds.

    ``servo()`` set-points are one ``period`` apart: the step between two of them is checked
    against ``max_linear_step``/``max_angular_step`` and, divided by the period, against the
    velocities; the change of step against the accelerations. Every target lies in the box
    ``workspace_min``..``workspace_max`` (base frame). An arm bounds no jerk: its jerk limits
    stay 0 (the planner's "no limit"), as the Trajectories service reports them. The defaults
    suit a UR5e on an open bench; each backend may have its own defaults
    (``PiperArm.DEFAULT_LIMITS``); set the box to your cell."""
    max_linear_velocity: float = 0.25       # m/s
    max_angular_velocity: float = 1.0       # rad/s
    max_linear_acceleration: float = 2.0    # m/s^2
    max_angular_acceleration: float = 4.0   # rad/s^2
    workspace_min: tuple = (-1.0, -1.0, -0.2)   # m, base frame
    workspace_max: tuple = (1.0, 1.0, 1.2)
    max_linear_step: float = 0.02       # m per set-point
    max_angular_step: float = math.radians(5)   # rad per set-point

    def __post_init__(self):
        # The shared fields by the planner's rules (one home for them): its own check, on its
        # own fields only (its __post_init__ would take this class's box for a number).
        motion = trajectory.Limits(**{n: getattr(self, n) for n in trajectory.LIMIT_FIELDS})
        for name in trajectory.LIMIT_FIELDS:
            object.__setattr__(self, name, getattr(motion, name))
        for name in ("max_linear_jerk", "max_angular_jerk"):
            if getattr(self, name):
                raise ValueError(f"limits.{name}: an arm bounds no jerk (its servo check does "
                                 f"not measure it): must be 0, got {getattr(self, name)!r}")
        for name in ("max_linear_step", "max_angular_step"):
            object.__setattr__(self, name, _positive(f"limits.{name}", getattr(self, name)))
        try:
            lo, hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        except (TypeError, ValueError):
            lo = hi = np.zeros(0)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
            raise ValueError("limits.workspace_min/max: expected three finite numbers each")
        if np.any(lo >= hi):
            raise ValueError(f"limits.workspace_min: {lo.tolist()} is not below "
                             f"workspace_max {hi.tolist()}")
        object.__setattr__(self, "workspace_min", tuple(lo.tolist()))
        object.__setattr__(self, "workspace_max", tuple(hi.tolist()))

    def check_workspace(self, name: str, t, consequence: str) -> None:
        """Raise :class:`LimitError` if the position ``t`` (m) is outside the box."""
        t = np.asarray(t, dtype=float)
        if np.any(t < self.workspace_min) or np.any(t > self.workspace_max):
            raise LimitError(f"{name}: position {np.round(t, 4).tolist()} m is outside "
                             f"limits.workspace {list(self.workspace_min)}.."
                             f"{list(self.workspace_max)} m; {consequence}", "workspace",
                             tuple(t.tolist()), (self.workspace_min, self.workspace_max))

    def check_move(self, pose: np.ndarray, speed, accel) -> None:
        """The arguments of ``Arm.move``: speed and acceleration within (0, limit] (else
        ``ValueError``), the target in the workspace (else :class:`LimitError`)."""
        for name, v, hi in (("speed", speed, self.max_linear_velocity),
                            ("accel", accel, self.max_linear_acceleration)):
            if isinstance(v, bool) or not (isinstance(v, numbers.Real) and math.isfinite(v)
                                           and 0 < v <= hi):
                raise ValueError(f"{name}: must be within (0, {hi:g}], got {v!r}")
        self.check_workspace("pose", dq.to_pose(pose)[1], "the move was not sent")

    def check_servo(self, target: np.ndarray, prev: np.ndarray, prev_step: np.ndarray,
                    period: float) -> np.ndarray:
        """Check one servo set-point ``target`` (unit dual quaternion) that follows ``prev`` by
        one ``period``, whose own step from the one before was ``prev_step`` (zeros from rest).

        Returns this step, ``[dx, dy, dz, rx, ry, rz]`` (translation, then the rotation vector
        of ``target * prev^-1``, both in the base frame); raises :class:`LimitError` for the
        first limit broken, in the order workspace, step, speed, acceleration. The caller must
        stop the arm before passing the error on: the message says it was stopped."""
        stop = "the arm was stopped"
        self.check_workspace("pose", dq.to_pose(target)[1], stop)
        step = servo_step(target, prev)
        lin, ang = float(np.linalg.norm(step[:3])), float(np.linalg.norm(step[3:]))
        ms = 1e3 * period
        dv = float(np.linalg.norm(step[:3] - prev_step[:3])) / period ** 2
        dw = float(np.linalg.norm(step[3:] - prev_step[3:])) / period ** 2
        # A small tolerance: a stream planned exactly at a limit must pass despite rounding.
        checks = (
            ("max_linear_step", lin, 1e-9, "m", "step"),
            ("max_angular_step", ang, 1e-9, "rad", "turn"),
            ("max_linear_velocity", lin / period, 1e-9, "m/s",
             f"speed over one {ms:g} ms period"),
            ("max_angular_velocity", ang / period, 1e-9, "rad/s",
             f"angular speed over one {ms:g} ms period"),
            ("max_linear_acceleration", dv, 1e-6, "m/s^2", "acceleration"),
            ("max_angular_acceleration", dw, 1e-6, "rad/s^2", "angular acceleration"),
        )
        for limit, value, tol, unit, what in checks:
            bound = getattr(self, limit)
            if value > bound * (1 + tol):
                raise LimitError(f"pose: set-point needs a {what} of {value:.4g} {unit}, above "
                                 f"limits.{limit} = {bound:g} {unit}; {stop}", limit, value, bound)
        return step


def servo_step(target: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """The step from set-point ``prev`` to ``target`` as :meth:`Limits.check_servo` measures it:
    ``[dx, dy, dz, rx, ry, rz]``, the translation and the rotation vector of
    ``target * prev^-1``, both in the base frame."""
    return np.concatenate([dq.to_pose(target)[1] - dq.to_pose(prev)[1],
                           rotvec_from_quat(dq.mul(target, dq.conj(prev))[:4])])


def unit_pose(pose, name: str = "pose") -> np.ndarray:
    """``pose`` as a float64 (8,) unit dual quaternion, else ``ValueError`` naming ``name``."""
    a = np.asarray(pose, dtype=np.float64)
    if a.shape != (8,):
        raise ValueError(f"{name}: expected a dual quaternion of shape (8,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinity")
    n = float(np.linalg.norm(a[:4]))
    if abs(n - 1.0) > dq.UNIT_TOL:
        raise ValueError(f"{name}: quaternion norm {n:.6g} is not unit (tolerance {dq.UNIT_TOL})")
    return dq.normalize(a)


def pose_delta(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation distance in m, rotation angle in rad) from unit pose ``a`` to ``b``."""
    qa, ta = dq.to_pose(a)
    qb, tb = dq.to_pose(b)
    c = abs(float(np.dot(qa, qb)))
    return float(np.linalg.norm(tb - ta)), 2.0 * math.acos(min(1.0, c))


def tool_line(a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    """The pose a fraction ``f`` of the way from ``a`` to ``b`` on the path of a tool-space
    linear move (straight line in translation, slerp in rotation)."""
    from dqpose.interpolate import interpolate
    return interpolate([0.0, 1.0], np.stack([a, b]), [float(f)], "tool_linear")[0]


def pose_covariance(rotation_sigma: float, translation_sigma: float) -> np.ndarray:
    """The isotropic 6x6 covariance ``diag(rs^2, rs^2, rs^2, ts^2, ts^2, ts^2)`` (rad, m) in the
    :class:`Measurement` convention; each sigma positive and finite, else ``ValueError``."""
    rs = _positive("rotation_sigma", rotation_sigma)
    ts = _positive("translation_sigma", translation_sigma)
    return np.diag([rs * rs] * 3 + [ts * ts] * 3)


class Pacer:
    """Cycle deadlines for a servo stream, one ``period`` apart on an absolute schedule, so a
    stream keeps the controller's rate instead of drifting by the caller's overhead every cycle
    (a loop that waits a period from each call's start runs ~1 % slow at 500 Hz, and the
    controller then sees a cycle without a set-point every ~100 cycles). A call late by less than
    a period keeps the schedule (the next wait is shorter); later than that, the stream restarts
    from now."""

    def __init__(self, period: float):
        self.period = float(period)
        self._next: Optional[float] = None

    def cycle(self, now: float) -> float:
        """The start of the cycle a set-point sent at ``now`` belongs to; the caller waits until
        that start plus one period."""
        start = self._next if self._next is not None and 0 <= now - self._next < self.period \
            else now
        self._next = start + self.period
        return start


class ServoStream:
    """An arm's stream of ``servo()`` set-points as its :class:`Limits` judge it: the last
    set-point sent (None: the next one starts a stream, from rest at the measured pose) and its
    step, and for the watchdog whether a stream is under way and when its last set-point went.
    Any thread may call it; its lock is held for no call out."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.setpoint: Optional[np.ndarray] = None
        self.step = np.zeros(6)
        self.active = False
        self.sent_at = -math.inf        # time.monotonic()

    def previous(self) -> tuple[Optional[np.ndarray], np.ndarray]:
        with self._lock:
            return self.setpoint, self.step.copy()

    def sent(self, target: np.ndarray, step: np.ndarray, ok: bool = True) -> None:
        """``target`` went out with ``step``; not ``ok`` (the controller refused it): the stream
        is no longer watched and the last set-point sent stays the one before."""
        with self._lock:
            if ok:
                self.setpoint, self.step = target, step
            self.active = ok
            self.sent_at = time.monotonic()

    def end(self, forget: bool = True) -> bool:
        """No stream under way any more (a stop, a hold, a move, a fault), hence nothing for the
        watchdog; with ``forget`` the next set-point starts from rest. Whether one was."""
        with self._lock:
            was, self.active = self.active, False
            if forget:
                self.setpoint = None
            return was

    def forget(self) -> bool:
        """The next set-point starts from rest (the arm was stopped, or moved by other means);
        whether a set-point was kept."""
        with self._lock:
            kept, self.setpoint = self.setpoint is not None, None
            return kept

    def stalled(self, watchdog: float) -> bool:
        """A stream under way whose last set-point is more than ``watchdog`` s old: no longer
        watched, and True (the arm is the caller's to stop)."""
        with self._lock:
            if self.active and time.monotonic() - self.sent_at > watchdog:
                self.active = False
                return True
            return False


class Arm(abc.ABC):
    """An arm commanded in tool space.

    Every backend takes ``limits=`` (:class:`Limits`) and applies them the same way: ``servo()``
    set-points go through :meth:`Limits.check_servo`, and one that breaks a limit brings the arm
    to a controlled stop and raises :class:`LimitError`; a set-point is never changed to fit.
    ``move()`` arguments go through :meth:`Limits.check_move`. ``servo()`` returns at the end of
    its cycle on the :class:`Pacer` schedule, so a loop of ``servo()`` calls streams at
    ``period`` without drifting; ``servo_nowait()`` sends the same set-point and returns that end
    instead, for a caller that waits on something else meanwhile (the executor waits on a
    cancel)."""

    #: controller period in seconds (servo commands are sent once per period)
    period: float = 0.008
    limits: Limits = Limits()
    #: the source name of this arm's measurements
    name: str = "arm"
    #: (rotation rad, translation m): the 1-sigma per axis of a reported tool pose, the
    #: covariance :meth:`measure` attaches. Each backend's default is its vendor's pose
    #: repeatability (ISO 9283, taken as 3 sigma); an uncalibrated arm's absolute accuracy is
    #: far worse (millimetres): set ``pose_sigma`` to it when fusing with other sources.
    pose_sigma: tuple[float, float] = (1e-4, 1e-4)

    #: the arm-spec keys (:data:`dqpose.drivers.spec.ARM_KEYS`) this arm runs with, each also an
    #: attribute of the same name (``stale_after``, ``max_tracking``, ``heartbeat``, ...)
    options: dict = {}

    #: the servo stream :meth:`_checked_setpoint` judges (made by a backend that servos)
    _stream: ServoStream

    def _set_options(self, kind: str, given: dict) -> None:
        """The keys of :data:`~drivers.spec.ARM_KEYS` from ``given`` (checked), the defaults of
        ``kind`` for the rest, as :attr:`options` and attributes."""
        from dqpose.drivers.spec import resolve
        self.options = resolve(kind, given)
        for name, value in self.options.items():
            setattr(self, name, value)

    @classmethod
    def process_problem(cls, channel: str) -> Optional[str]:
        """Why an arm on ``channel`` cannot be opened in a process of its own (its connection
        does not reach across processes), or None."""
        return None

    def open_run(self, settings, busy_timeout: float, outcome) -> Optional["Run"]:
        """Where a run of the control loop goes, asked once by each
        :class:`~dqpose.drivers.executor.Executor` made on this arm (with its
        :class:`~dqpose.drivers.control.Settings`, ``busy_timeout``, and the
        :class:`~dqpose.drivers.run.Outcome` the run reports to): None by default, a thread of
        this process (the executor's :class:`~dqpose.drivers.run.LocalRun`: run.py imports this
        module, so this one names no run); an arm in its own process runs it there
        (:class:`~dqpose.drivers.armproc.ArmProcess`)."""
        return None

    @abc.abstractmethod
    def tool_pose(self) -> tuple[float, np.ndarray]:
        """(``time.time()`` in seconds when the pose was read, T_base_tool as a dual
        quaternion)."""

    def measure(self, covariance: Optional[np.ndarray] = None) -> Measurement:
        """The tool pose as a :class:`Measurement` (source ``name``, the time it was read), with
        ``covariance`` or, by default, the isotropic one of ``pose_sigma``."""
        stamp, pose = self.tool_pose()
        if covariance is None:
            covariance = pose_covariance(*self.pose_sigma)
        else:
            covariance = np.asarray(covariance, dtype=np.float64)
            if covariance.shape != (6, 6) or not np.all(np.isfinite(covariance)):
                raise ValueError(f"covariance: expected a finite 6x6 matrix, got shape "
                                 f"{covariance.shape}")
        return Measurement(source=self.name, time=stamp, pose=pose, covariance=covariance)

    def _checked_setpoint(self, target: np.ndarray,
                          here: Callable[[], np.ndarray]) -> np.ndarray:
        """The step of servo set-point ``target`` by :meth:`Limits.check_servo`, from the last
        set-point of the stream under way (:class:`ServoStream`, ``self._stream``, which a
        backend that servos makes), or from rest at ``here()``, the measured pose, when it
        starts one. A set-point over a limit ends the stream, stops the arm
        (:meth:`_refused`) and raises the :class:`LimitError`. The backend records what it
        sends (``self._stream.sent``)."""
        prev, prev_step = self._stream.previous()
        if prev is None:
            prev, prev_step = here(), np.zeros(6)
        try:
            return self.limits.check_servo(target, prev, prev_step, self.period)
        except LimitError:
            self._refused(self._stream.end())
            raise

    def _refused(self, streaming: bool) -> None:
        """Bring the arm to a controlled stop after a refused set-point (``streaming``: a stream
        was under way)."""
        if streaming:
            self.stop()

    def servo(self, pose: np.ndarray) -> None:
        """Send one set-point and return at the end of its cycle; call once per ``period``."""
        self.wait_cycle(self.servo_nowait(pose))

    @abc.abstractmethod
    def servo_nowait(self, pose: np.ndarray) -> float:
        """Send one set-point (checked as :meth:`servo` checks it) and return, without waiting,
        when its cycle ends on the :class:`Pacer` schedule (``time.monotonic()`` seconds): the
        next set-point is due then."""

    def wait_cycle(self, end: float) -> None:
        """Wait until ``end`` (``time.monotonic()`` seconds), the end of a servo cycle."""
        delay = end - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    @abc.abstractmethod
    def move(self, pose: np.ndarray, speed: float, accel: float) -> None:
        """Blocking tool-space move to ``pose`` (m/s, m/s^2)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now."""

    @abc.abstractmethod
    def status(self) -> ArmState:
        """Connection and safety state (the health fields of :class:`ArmState`)."""

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """(linear m/s of the tool point, angular rad/s of the tool), both (3,) in the base
        frame; :class:`ArmError` when the arm cannot be read."""
        raise ArmError(f"{type(self).__name__}: no velocity feedback")

    def state(self) -> ArmState:
        """:meth:`status` with the pose and velocities (None where they cannot be read; the
        fault says why)."""
        st = self.status()
        try:
            stamp, pose = self.tool_pose()
            lin, ang = self.velocity()
        except ArmError:
            return st
        return dataclasses.replace(st, stamp=stamp, pose=pose, linear_velocity=lin,
                                   angular_velocity=ang)

    def close(self) -> None:  # noqa: B027 (an arm with nothing to release keeps it)
        """Stop and disconnect."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
