""":func:`smooth`: its arguments checked, the banded start (the unconstrained solution), one QP
per channel that breaks a limit, and the samples measured and limits tightened until they hold
(:mod:`dqpose.smoothing`'s docstring, "The solver").
"""
from __future__ import annotations

import math

import numpy as np

from dqpose import dq
from dqpose.errors import Infeasible, rename
from dqpose.smoothing.qp import PIQP, TOL, breaks, solve_qp
from dqpose.smoothing.spline import MIN_POSES, Problem, increments, quat_rot, rot_dq, rotvec
from dqpose.trajectory import Limits, peaks

CUTOFF_HZ = 2.0

_LINEARISATIONS = 3       # orientation QPs about successive solutions at most
_ROTATION_MARGIN = 0.005
_CHECKS = 4               # solves with limits tightened by what the samples measured


def _check(times, poses, limits, smoothing, rate_hz):
    try:
        t = np.asarray(times, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"times: expected numbers, got {type(times).__name__}") from None
    if t.ndim != 1:
        raise ValueError(f"times: expected a 1-D array, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"times[{bad[0]}]: {float(t[bad[0]])!r} is not finite")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(f"times[{i}]: {float(t[i])!r} is not after times[{i - 1}] = "
                         f"{float(t[i - 1])!r} (times must be strictly increasing)")
    try:
        x = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"poses: expected numbers, got {type(poses).__name__}") from None
    if x.ndim != 2 or x.shape[1] != 8:
        raise ValueError(f"poses: expected shape (N, 8), got {x.shape}")
    if x.shape[0] != t.shape[0]:
        raise ValueError(f"poses: {x.shape[0]} poses for {t.shape[0]} times")
    if t.shape[0] < MIN_POSES:
        raise ValueError(f"poses: need at least {MIN_POSES} poses, got {t.shape[0]}")
    try:
        q, p = dq.to_pose(x)
    except ValueError as e:
        raise rename(e, {"a": "poses{}"}) from None
    if not isinstance(limits, Limits):
        raise ValueError(f"limits: expected a Limits, got {type(limits).__name__}")
    for name, v in (("smoothing", smoothing), ("rate_hz", rate_hz)):
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name}: expected a number, got {v!r}") from None
        if not (math.isfinite(f) and f >= 0):
            raise ValueError(f"{name}: {v!r} must be finite and >= 0")
    return t, q, p, float(smoothing), float(rate_hz)


def _rest_to_rest_time(dist: float, v: float, a: float) -> float:
    """Shortest rest-to-rest time over ``dist`` with speed ``v`` and acceleration ``a``."""
    if dist <= v * v / a:
        return 2.0 * math.sqrt(dist / a)
    return dist / v + v / a


def _check_ends(duration: float, dist: float, angle: float, limits: Limits) -> None:
    for what, x, v, a, unit in (
            ("moves", dist, limits.max_linear_velocity, limits.max_linear_acceleration, "m"),
            ("turns", angle, limits.max_angular_velocity, limits.max_angular_acceleration, "rad")):
        need = _rest_to_rest_time(x, v, a)
        if need > duration:
            raise Infeasible(f"times: the path {what} {x:.6g} {unit} between its ends in "
                             f"{duration:.6g} s, which needs at least {need:.6g} s from rest to "
                             f"rest under the limits ({v:g} {unit}/s, {a:g} {unit}/s^2)")


def smooth(times, poses, limits: Limits, smoothing: float = 1.0, rate_hz: float = 0.0,
           free_ends: bool = False):
    """A smooth path through noisy time-stamped poses, within ``limits``.

    ``times`` (N,) strictly increasing seconds, ``poses`` (N, 8) unit dual quaternions
    ``T_base_tool``, N >= 4. ``smoothing`` >= 0 sets the cutoff ``2 / smoothing`` Hz
    (:mod:`dqpose.smoothing`); ``rate_hz`` 0 returns the path at ``times``, else at
    ``times[0] + k / rate_hz`` and at ``times[-1]``. Returns ``(times (M,), poses (M, 8))``,
    starting and ending at rest (velocity and acceleration zero, so the ends move off the data as
    far as the data moves there), or, with ``free_ends``, following the data's motion at both
    ends.

    ``limits``: issue 10's ``Limits`` (velocity and acceleration required; a jerk limit of 0 is
    none). Errors: ``ValueError`` naming the argument and index; :class:`Infeasible` (a
    ``ValueError``) when the limits cannot be met on this clock.
    """
    t, q, p, smoothing, rate_hz = _check(times, poses, limits, smoothing, rate_hz)
    if not isinstance(free_ends, (bool, np.bool_)):
        raise ValueError(f"free_ends: expected True or False, got {free_ends!r}")
    return smooth_checked(t, q, p, limits, smoothing, rate_hz, rest=not free_ends)


def unconstrained(t: np.ndarray, q: np.ndarray, p: np.ndarray, smoothing: float,
                   rest: bool = True):
    """The banded start: the problem, position and orientation control points, the samples'
    rotations."""
    prob = Problem(t, smoothing / (2 * math.pi * CUTOFF_HZ), rest)
    r_meas = quat_rot(q)
    # Position: exact in one banded solve.
    c = prob.fit(p)
    # Orientation: chordal smoothing of the sign-aligned quaternions as a reference, then one
    # Gauss-Newton step of the geodesic cost about it with the same factor.
    flip = np.cumsum(np.r_[0, np.einsum("ij,ij->i", q[1:], q[:-1]) < 0]) % 2
    rc = quat_rot(prob.fit(np.where(flip[:, None] == 1, -q, q)))
    m = prob.rotation_model(rc, r_meas, t, jacobian=False)
    return prob, c, dq.mul(rc, rot_dq(prob.gauss_newton(m.r, m.d))), r_meas


def evaluate(prob: Problem, c: np.ndarray, rc: np.ndarray, times: np.ndarray) -> np.ndarray:
    rot = prob.s.rotations(rc, times)
    return dq.from_pose(rot[:, :4], prob.s.positions(c, times))


def smooth_checked(t, q, p, limits: Limits, smoothing: float, rate_hz: float,
            solver=("piqp", PIQP), verify: bool = True, rest: bool = True):
    """:func:`smooth` after the checks; ``solver`` and ``verify=False`` (one pass, the samples
    not measured) are for the benchmark's peers."""
    prob, c, rc, r_meas = unconstrained(t, q, p, smoothing, rest)
    h = prob.s.h
    if rest:
        _check_ends(t[-1] - t[0], float(np.linalg.norm(c[-1] - c[0])),
                    float(np.linalg.norm(rotvec(dq.mul(dq.conj(rc[0]), rc[-1])))), limits)

    lin = [limits.max_linear_velocity, limits.max_linear_acceleration, limits.max_linear_jerk]
    ang = [limits.max_angular_velocity, limits.max_angular_acceleration, limits.max_angular_jerk]
    out_t = _output_times(t, rate_hz)
    for _ in range(_CHECKS):
        if breaks(np.diff(c, axis=0), h, lin):
            c = c + solve_qp(prob, prob.position_model(c, p, t), lin, "poses", solver)
        for _ in range(_LINEARISATIONS):
            if not breaks(increments(rc), h, ang):
                break
            # The increments are linearised: held back by their second-order error (~0.5 % of
            # the limit for corrections of a few degrees), one linearisation usually suffices.
            rc = dq.mul(rc, rot_dq(solve_qp(prob, prob.rotation_model(rc, r_meas, t),
                                     [L * (1 - _ROTATION_MARGIN) for L in ang], "poses", solver)))
        out = evaluate(prob, c, rc, out_t)
        if not verify:
            return out_t, out
        # The control points obey the limits; the samples do too for the position (convex
        # hull) and to first order in the rotation per span for the orientation. What the
        # caller gets is measured, and a limit the samples break is tightened by that ratio.
        pk = peaks(out_t, out)
        measured = [[pk.linear_velocity, pk.linear_acceleration, pk.linear_jerk],
                    [pk.angular_velocity, pk.angular_acceleration, pk.angular_jerk]]
        ok = True
        for held, given, seen in zip((lin, ang), _limit_rows(limits), measured):
            for i, (L, v) in enumerate(zip(given, seen)):
                if L > 0 and v > L * (1 + TOL):
                    # squared: the angular jerk of the samples (base frame) exceeds that of the
                    # increments (body frame) by w x alpha, which does not shrink with the limit
                    held[i] = min(held[i], held[i] * (L / v) ** 2 * (1 - 1e-3))
                    ok = False
        if ok:
            return out_t, out
    raise Infeasible("poses: the smoothed samples still break the limits after "
                     f"{_CHECKS} tightenings")


def _limit_rows(limits: Limits):
    return ((limits.max_linear_velocity, limits.max_linear_acceleration, limits.max_linear_jerk),
            (limits.max_angular_velocity, limits.max_angular_acceleration,
             limits.max_angular_jerk))


def _output_times(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """``times``, or ``times[0] + k / rate_hz`` before ``times[-1]`` and then ``times[-1]``."""
    if rate_hz <= 0:
        return t.copy()
    k = np.arange(int(math.floor((t[-1] - t[0]) * rate_hz * (1 + 1e-12))) + 1)
    out_t = t[0] + k / rate_hz
    return np.append(out_t[out_t < t[-1] - 1e-9 / rate_hz], t[-1])
