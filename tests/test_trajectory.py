"""service/trajectory.py: every limit holds on the samples themselves, the path is the one asked
for (straight lines, ScLERP, blends within their radius), the ends are exact, bad input is
refused naming the field, and straight moves are as fast as Ruckig's."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dqpose import dq
from dqpose.trajectory import INTERPOLATIONS, Infeasible, Limits, Waypoint, plan
from tests._kinematics import NOISE_1KHZ, derivatives, peaks, violation

LIMITS = Limits(max_linear_velocity=1.0, max_angular_velocity=2.0, max_linear_acceleration=2.0,
                max_angular_acceleration=4.0, max_linear_jerk=10.0, max_angular_jerk=20.0)
RATE = 1000.0
TOL = 1e-9     # relative, on top of the finite differences' rounding (NOISE_1KHZ)


def pose(q, t) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return dq.from_pose(q / np.linalg.norm(q), np.asarray(t, dtype=float))


def translation(p) -> np.ndarray:
    return dq.to_pose(p)[1]


def same_pose(a, b, tol=1e-12) -> bool:
    return min(np.abs(a - b).max(), np.abs(a + b).max()) <= tol


def uniform(tr):
    """Samples at RATE without the last one (which lands at `duration`, off the grid)."""
    s = tr.at_rate(RATE)
    return s.time[:-1], s.pose[:-1], s


@st.composite
def paths(draw, max_points=6):
    """Random waypoints (unit quaternion, position within 1 m) with random blend radii."""
    k = draw(st.integers(2, max_points))
    coords = st.floats(-0.6, 0.6)
    poses = []
    for _ in range(k):
        q = np.array(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
        t = np.array(draw(st.lists(coords, min_size=3, max_size=3)))
        if np.linalg.norm(q) < 0.1:
            q = np.array([1.0, 0, 0, 0])
        poses.append(pose(q, t))
    # at least 5 mm between consecutive points, so every segment moves the tool point
    for i in range(1, k):
        if np.linalg.norm(translation(poses[i]) - translation(poses[i - 1])) < 5e-3:
            poses[i] = dq.mul(dq.from_pose([1.0, 0, 0, 0], [0.05, 0, 0]), poses[i])
    wps = []
    for i, p in enumerate(poses):
        r = 0.0
        if 0 < i < k - 1 and draw(st.booleans()):
            near = min(np.linalg.norm(translation(p) - translation(poses[j]))
                       for j in (i - 1, i + 1))
            r = draw(st.floats(0.0, 0.49)) * near   # half a segment is the most allowed
        wps.append(Waypoint(p, blend_radius=r))
    return wps


limits_st = st.builds(
    Limits, st.floats(0.05, 2.0), st.floats(0.1, 4.0), st.floats(0.1, 5.0), st.floats(0.2, 10.0),
    st.one_of(st.just(0.0), st.floats(0.5, 50.0)), st.one_of(st.just(0.0), st.floats(1.0, 100.0)))

slow = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---- limits ---------------------------------------------------------------------------------

@slow
@given(paths(), limits_st, st.sampled_from(INTERPOLATIONS))
def test_limits_hold_on_every_sample(wps, limits, mode):
    tr = plan(wps, limits, mode)
    t, poses, s = uniform(tr)
    assert violation(peaks(t, poses), limits, NOISE_1KHZ) <= TOL
    # the reported velocities too, and they are the derivatives of the poses
    assert (np.linalg.norm(s.linear_velocity, axis=1).max()
            <= limits.max_linear_velocity * (1 + 1e-12))
    assert (np.linalg.norm(s.angular_velocity, axis=1).max()
            <= limits.max_angular_velocity * (1 + 1e-12))
    (v, _, j), (w, _, jw) = derivatives(t, poses)
    mid_v = 0.5 * (s.linear_velocity[:-2] + s.linear_velocity[1:-1])
    mid_w = 0.5 * (s.angular_velocity[:-2] + s.angular_velocity[1:-1])

    # the mean over a step differs from the trapezoid rule by at most dt^2/12 max |jerk|
    def bound(jerk):
        return 2 * np.linalg.norm(jerk, axis=1).max() / RATE**2 / 12 + 1e-9

    assert np.abs(v - mid_v).max() <= bound(j)
    assert np.abs(w - mid_w).max() <= bound(jw)


def test_acceleration_is_continuous_without_a_jerk_limit():
    """Jerk 0 means no jerk limit, yet the ramps keep the acceleration continuous (C2 poses)."""
    lim = Limits(1.0, 2.0, 2.0, 4.0)
    wps = [Waypoint(pose([1, 0, 0, 0], [0, 0, 0])),
           Waypoint(pose([1, 0, 0, 0.3], [0.6, 0, 0]), blend_radius=0.1),
           Waypoint(pose([1, 0.2, 0, 0.3], [0.6, 0.6, 0]))]
    t, poses, _ = uniform(plan(wps, lim))
    (_, _, j), (_, _, jw) = derivatives(t, poses)
    # a step in acceleration would show as a jerk of ~ a / dt = 2000
    assert np.linalg.norm(j, axis=1).max() < 500 and np.linalg.norm(jw, axis=1).max() < 1000


@pytest.mark.parametrize("mode", INTERPOLATIONS)
def test_start_velocity_along_the_first_segment(mode):
    a, b = pose([1, 0, 0, 0], [0, 0, 0]), pose([1, 0, 0, 0.5], [0.8, 0.4, 0])
    # the path's own velocity at a, by a central difference of its first 1e-6 of s
    eps, rate = 1e-6, 0.5
    if mode == "screw":
        ends = dq.sclerp(a, b, np.array([-eps, eps]))
        dp = (translation(ends[1]) - translation(ends[0])) / (2 * eps)
    else:
        dp = translation(b) - translation(a)
    w = 2 * dq.log(dq.mul(b, dq.conj(a)))[:3]          # base-frame rotation vector of a -> b
    v0 = rate * np.concatenate([dp, w])
    tr = plan([Waypoint(a), Waypoint(b)], LIMITS, mode, start_velocity=v0)
    s = tr.sample([0.0])
    assert np.allclose(np.concatenate([s.linear_velocity[0], s.angular_velocity[0]]), v0, atol=1e-8)
    t, poses, _ = uniform(tr)
    assert violation(peaks(t, poses), LIMITS, NOISE_1KHZ) <= TOL
    # moving already, it arrives sooner than from rest
    assert tr.duration < plan([Waypoint(a), Waypoint(b)], LIMITS, mode).duration


@slow
@given(paths(4), limits_st, st.sampled_from(INTERPOLATIONS),
       st.lists(st.floats(-1, 1), min_size=6, max_size=6), st.floats(0.05, 1.0))
def test_start_velocity_in_any_direction(wps, limits, mode, direction, share):
    """Replanning while moving: a start velocity off the first segment is followed from the
    start (the samples begin at waypoint 0 moving at exactly that velocity), then blended into
    the path, every limit held, the end exact, one segment per waypoint pair as before."""
    u = np.array(direction)
    if np.linalg.norm(u[:3]) < 1e-3 or np.linalg.norm(u[3:]) < 1e-3:
        u[:3] += [0.3, 0, 0]
    v0 = share * np.concatenate([
        u[:3] / np.linalg.norm(u[:3]) * limits.max_linear_velocity,
        u[3:] / max(np.linalg.norm(u[3:]), 1e-3) * limits.max_angular_velocity])
    try:
        tr = plan(wps, limits, mode, start_velocity=v0)
    except Infeasible as e:
        # fast turns under small angular limits: more than half a turn to stop
        assert "less than 180 are supported" in str(e), e
        return
    s = tr.sample([0.0, tr.duration])
    assert np.allclose(np.concatenate([s.linear_velocity[0], s.angular_velocity[0]]), v0, atol=1e-9)
    assert same_pose(s.pose[0], wps[0].pose) and same_pose(s.pose[1], wps[-1].pose)
    assert len(tr.segments) == len(wps) - 1
    t, poses, _ = uniform(tr)
    assert violation(peaks(t, poses), limits, NOISE_1KHZ) <= TOL


def test_start_velocity_too_fast_to_stop_is_infeasible():
    a, b = pose([1, 0, 0, 0], [0, 0, 0]), pose([1, 0, 0, 0], [0.01, 0, 0])
    with pytest.raises(Infeasible, match=r"^start_velocity: cannot be brought to rest"):
        plan([Waypoint(a), Waypoint(b)], LIMITS, start_velocity=[0.9, 0, 0, 0, 0, 0])


# ---- the path ----------------------------------------------------------------------------------

@slow
@given(paths(), st.sampled_from(INTERPOLATIONS))
def test_endpoints_exact(wps, mode):
    tr = plan(wps, LIMITS, mode)
    s = tr.at_rate(RATE)
    assert s.time[0] == 0.0 and s.time[-1] == tr.duration
    assert same_pose(s.pose[0], dq.normalize(wps[0].pose), 0.0)
    assert same_pose(s.pose[-1], dq.normalize(wps[-1].pose), 0.0)
    assert not s.linear_velocity[[0, -1]].any() and not s.angular_velocity[[0, -1]].any()


def _planned_no_blend(wps, mode: str):
    """The plan through ``wps``' poses without their blends, and its samples at RATE."""
    tr = plan([Waypoint(w.pose) for w in wps], LIMITS, mode)
    return tr, tr.at_rate(RATE)


@slow
@given(paths())
def test_tool_linear_is_straight(wps):
    tr, s = _planned_no_blend(wps, "tool_linear")
    p = translation(s.pose)
    worst = 0.0
    for k, seg in enumerate(tr.segments):
        inside = (s.time >= seg.start) & (s.time <= seg.start + seg.duration)
        a, b = translation(wps[k].pose), translation(wps[k + 1].pose)
        d = (b - a) / np.linalg.norm(b - a)
        rel = p[inside] - a
        off = rel - np.outer(rel @ d, d)
        worst = max(worst, np.linalg.norm(off, axis=1).max())
    assert worst <= 1e-9


@slow
@given(paths())
def test_screw_equals_sclerp(wps):
    tr, s = _planned_no_blend(wps, "screw")
    for k, seg in enumerate(tr.segments):
        inside = (s.time >= seg.start) & (s.time <= seg.start + seg.duration)
        a, b = dq.normalize(wps[k].pose), dq.normalize(wps[k + 1].pose)
        if a[:4] @ b[:4] < 0:
            b = -b
        x = s.pose[inside]
        step = dq.log(dq.mul(dq.conj(a), b))
        tau = dq.log(dq.mul(dq.conj(a)[None], x)) @ step / (step @ step)
        ref = dq.sclerp(a, b, tau)
        assert np.abs(np.where((ref * x).sum(1, keepdims=True) < 0, -ref, ref) - x).max() <= 1e-12


def test_screw_leaves_the_line_tool_linear_does_not():
    """The issue's example: 0.3 m with 90 degrees of rotation; ScLERP bulges by ~62 mm."""
    a = pose([1, 0, 0, 0], [0, 0, 0])
    b = pose([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], [0.3, 0, 0])
    off = {}
    for mode in INTERPOLATIONS:
        p = translation(plan([Waypoint(a), Waypoint(b)], LIMITS, mode).at_rate(RATE).pose)
        off[mode] = np.abs(p[:, 1:]).max()
    assert off["tool_linear"] <= 1e-12 and 0.05 < off["screw"] < 0.07


@slow
@given(paths(), st.sampled_from(INTERPOLATIONS))
def test_blends_stay_within_their_radius(wps, mode):
    tr = plan(wps, LIMITS, mode)
    s = tr.at_rate(RATE)
    p = translation(s.pose)
    for k in range(1, len(wps) - 1):
        r = wps[k].blend_radius
        if r == 0:
            continue
        prev, seg = tr.segments[k - 1], tr.segments[k]
        inside = (s.time >= seg.start) & (s.time <= prev.start + prev.duration)
        corner = translation(wps[k].pose)
        assert np.linalg.norm(p[inside] - corner, axis=1).max(initial=0.0) <= r * (1 + 1e-9) + 1e-12


def test_blending_is_faster_than_stopping():
    pts = [[0, 0, 0], [0.4, 0, 0], [0.4, 0.4, 0], [0.0, 0.4, 0.1]]
    stop = plan([Waypoint(pose([1, 0, 0, 0], p)) for p in pts], LIMITS)
    blend = plan([Waypoint(pose([1, 0, 0, 0], p), blend_radius=0.0 if i in (0, 3) else 0.1)
                  for i, p in enumerate(pts)], LIMITS)
    assert blend.duration < stop.duration - 0.2


def test_zero_radius_stops_at_the_waypoint():
    pts = [[0, 0, 0], [0.4, 0, 0], [0.4, 0.4, 0]]
    tr = plan([Waypoint(pose([1, 0, 0, 0], p)) for p in pts], LIMITS)
    t = tr.segments[1].start
    s = tr.sample([t])
    assert same_pose(s.pose[0], pose([1, 0, 0, 0], pts[1]), 1e-15)
    assert not s.linear_velocity.any()


# ---- time and binding limits ----------------------------------------------------------------

def test_binding_limit_is_reported():
    a = pose([1, 0, 0, 0], [0, 0, 0])
    long_move = plan([Waypoint(a), Waypoint(pose([1, 0, 0, 0], [2.0, 0, 0]))], LIMITS)
    spin = plan([Waypoint(a), Waypoint(pose([0, 0, 0, 1], [0.01, 0, 0]))], LIMITS)
    short = plan([Waypoint(a), Waypoint(pose([1, 0, 0, 0], [0.05, 0, 0]))], LIMITS)
    assert long_move.segments[0].binding == "max_linear_velocity"
    assert spin.segments[0].binding == "max_angular_velocity"
    assert short.segments[0].binding in ("max_linear_acceleration", "max_linear_jerk")


def test_straight_move_is_as_long_as_its_slower_part():
    """A stop-to-stop TOOL_LINEAR move takes as long as the slower of its translation alone and
    its rotation alone, and reports that part's binding limit: each part has its own time law."""
    for a, b, limits in random_straight_moves(60, seed=7):
        qb, tb = dq.to_pose(b)
        parts = [plan([Waypoint(a), Waypoint(p)], limits).segments[0]
                 for p in (pose([1, 0, 0, 0], tb), pose(qb, translation(a))) if not same_pose(a, p)]
        both = plan([Waypoint(a), Waypoint(b)], limits).segments[0]
        slower = max(parts, key=lambda s: s.duration)
        assert both.duration == pytest.approx(slower.duration, rel=1e-12)
        assert both.binding == slower.binding


def test_waypoint_times_are_met():
    pts = [[0, 0, 0], [0.3, 0, 0], [0.3, 0.3, 0]]
    free = plan([Waypoint(pose([1, 0, 0, 0], p)) for p in pts], LIMITS)
    want = (2.0 * free.segments[1].start, 3.0 * free.duration)
    for radius in (0.0, 0.05):
        wps = [Waypoint(pose([1, 0, 0, 0], pts[0])),
               Waypoint(pose([1, 0, 0, 0], pts[1]), time=want[0], blend_radius=radius),
               Waypoint(pose([1, 0, 0, 0], pts[2]), time=want[1])]
        tr = plan(wps, LIMITS)
        assert tr.duration == pytest.approx(want[1], rel=1e-9)
        assert [s.binding for s in tr.segments] == ["time", "time"]
        if radius == 0:
            assert tr.segments[1].start == pytest.approx(want[0], rel=1e-9)
            s = tr.sample([want[0]])
            assert np.linalg.norm(translation(s.pose[0]) - pts[1]) < 1e-6
        t, poses, _ = uniform(tr)
        assert violation(peaks(t, poses), LIMITS, NOISE_1KHZ) <= TOL


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(paths(5), st.lists(st.floats(1.0, 3.0), min_size=5, max_size=5),
       st.sampled_from(INTERPOLATIONS))
def test_random_waypoint_times_are_met(wps, stretch, mode):
    """Times later than the free plan's arrivals (stretched, kept increasing) are met exactly."""
    free = plan(wps, LIMITS, mode)
    arrive = [0.0]
    for k, seg in enumerate(free.segments[1:], start=1):
        # a waypoint is reached at the middle of its blend (0 long at a stop)
        prev = free.segments[k - 1]
        arrive.append(0.5 * (seg.start + prev.start + prev.duration) if wps[k].blend_radius > 0
                      else seg.start)
    arrive.append(free.duration)
    want = np.maximum.accumulate(np.array(arrive) * np.cumprod([1.0] + stretch[:len(arrive) - 1]))
    timed = [Waypoint(w.pose, time=float(t) if i else 0.0, blend_radius=w.blend_radius)
             for i, (w, t) in enumerate(zip(wps, want))]
    tr = plan(timed, LIMITS, mode)
    assert tr.duration == pytest.approx(want[-1], rel=1e-8)
    t, poses, _ = uniform(tr)
    assert violation(peaks(t, poses), LIMITS, NOISE_1KHZ) <= TOL


@pytest.mark.parametrize("mode", INTERPOLATIONS)
def test_many_timed_waypoints_are_each_met(mode):
    """30 waypoints, blends and stops mixed, every time 1.1-1.5x the free plan's arrival: each
    interval is slowed by its own factor, found by a root search per interval over sweeps."""
    rng = np.random.default_rng(5)
    pts = np.cumsum(rng.uniform(-0.15, 0.15, (30, 3)), axis=0)
    poses = [pose(rng.normal(size=4) * 0.1 + [1, 0, 0, 0], p) for p in pts]
    near = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    radius = ([0.0] + [0.4 * min(near[i - 1], near[i]) if i % 3 else 0.0 for i in range(1, 29)]
              + [0.0])

    def arrivals(tr):
        s = tr.segments
        return np.array([0.0] + [0.5 * (s[k].start + s[k - 1].start + s[k - 1].duration)
                                 if radius[k] > 0 else s[k].start for k in range(1, 29)]
                        + [tr.duration])

    free = plan([Waypoint(p, blend_radius=r) for p, r in zip(poses, radius)], LIMITS, mode)
    want = np.cumsum(np.r_[0.0, np.diff(arrivals(free)) * rng.uniform(1.1, 1.5, 29)])
    tr = plan([Waypoint(p, time=float(t), blend_radius=r) for p, t, r in zip(poses, want, radius)],
              LIMITS, mode)
    assert np.allclose(arrivals(tr), want, rtol=1e-8, atol=0)
    assert all(s.binding == "time" for s in tr.segments)
    t, got, _ = uniform(tr)
    assert violation(peaks(t, got), LIMITS, NOISE_1KHZ) <= TOL


def test_sample_takes_times_in_any_order():
    wps = [Waypoint(A), Waypoint(B, blend_radius=0.1), Waypoint(pose([1, 0, 0, 1], [0.5, 0.5, 0]))]
    tr = plan(wps, LIMITS)
    t = np.random.default_rng(0).uniform(0, tr.duration, 500)
    got, order = tr.sample(t), np.argsort(t)
    ref = tr.sample(t[order])
    assert np.array_equal(got.pose[order], ref.pose)
    assert np.array_equal(got.angular_velocity[order], ref.angular_velocity)


@slow
@given(paths(), limits_st, st.sampled_from(INTERPOLATIONS), st.integers(0, 2**32 - 1))
def test_batch_evaluation_equals_one_time_at_a_time(wps, limits, mode, seed):
    """The evaluation groups sorted times into runs (one segment, blend state and phase of each
    time law) evaluated side by side; a time put in the wrong run would take another phase's
    law. Times alone cannot share a run, so each is its own reference, with the segment starts
    and ends (phase boundaries) among them."""
    tr = plan(wps, limits, mode)
    edges = [x for s in tr.segments for x in (s.start, s.start + s.duration)]
    t = np.sort(np.concatenate([np.random.default_rng(seed).uniform(0, tr.duration, 300), edges,
                                np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf),
                                [0, tr.duration]]))
    t = np.clip(t, 0.0, tr.duration)
    got = tr.sample(t)
    for i in range(len(t)):
        one = tr.sample(t[i:i + 1])
        for a, b in zip(got[1:], one[1:]):
            assert np.abs(a[i] - b[0]).max() <= 1e-15, (i, t[i])


def test_unmeetable_time_is_infeasible_naming_the_waypoint():
    wps = [Waypoint(pose([1, 0, 0, 0], [0, 0, 0])),
           Waypoint(pose([1, 0, 0, 0], [0.3, 0, 0]), time=5.0),
           Waypoint(pose([1, 0, 0, 0], [1.3, 0, 0]), time=5.5)]
    with pytest.raises(Infeasible, match=r"^waypoints\[2\]\.time: 5\.5 s cannot be met"):
        plan(wps, LIMITS)
    assert isinstance(Infeasible("x"), ValueError)


# ---- against Ruckig ---------------------------------------------------------------------------

def ruckig_duration(a, b, limits: Limits) -> float:
    """Ruckig on [xyz, rotation vector] relative to a, with the per-axis limits scaled by the
    direction of the move (phase synchronisation then keeps the norm within the limits)."""
    ruckig = pytest.importorskip("ruckig")
    dp = translation(b) - translation(a)
    rv = 2 * dq.log(dq.mul(b, dq.conj(a)))[:3]
    goal = np.concatenate([dp, rv])
    # time-optimal for the one coupled limit: each axis's share of its norm
    ul = np.abs(dp) / max(np.linalg.norm(dp), 1e-300)
    ua = np.abs(rv) / max(np.linalg.norm(rv), 1e-300)

    # no jerk limit: Ruckig's infinite jerk on every axis of that group
    def scale(u_l, u_a, ll, la):
        return list(np.concatenate([u_l * ll if ll < math.inf else u_l + ll,
                                    u_a * la if la < math.inf else u_a + la]) + 1e-12)

    otg = ruckig.Ruckig(6)
    inp = ruckig.InputParameter(6)
    inp.current_position, inp.target_position = [0.0] * 6, list(goal)
    inp.max_velocity = scale(ul, ua, limits.max_linear_velocity, limits.max_angular_velocity)
    inp.max_acceleration = scale(ul, ua, limits.max_linear_acceleration,
                                 limits.max_angular_acceleration)
    inp.max_jerk = scale(ul, ua, limits.max_linear_jerk or math.inf,
                         limits.max_angular_jerk or math.inf)
    inp.synchronization = ruckig.Synchronization.Phase
    traj = ruckig.Trajectory(6)
    assert otg.calculate(inp, traj) in (ruckig.Result.Working, ruckig.Result.Finished)
    return traj.duration


def random_straight_moves(n: int, seed: int):
    """n rest-to-rest moves: random direction, length (1 mm to 3 m), rotation (none in a third)
    and limits (jerk none in a tenth), so that every pairing of deciding limits occurs."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        jerk = [0.0 if rng.random() < 0.1 else rng.uniform(1, 100) for _ in range(2)]
        limits = Limits(*rng.uniform(0.1, 3, 4), *jerk)
        d, axis = rng.normal(size=3), rng.normal(size=3)
        angle = rng.uniform(0, 3.1) if rng.random() < 2 / 3 else 0.0
        a = pose([1, 0, 0, 0], rng.uniform(-0.5, 0.5, 3))
        q = np.concatenate([[math.cos(angle / 2)],
                            math.sin(angle / 2) * axis / np.linalg.norm(axis)])
        b = pose(q, translation(a) + 10 ** rng.uniform(-3, 0.5) * d / np.linalg.norm(d))
        yield a, b, limits


def test_straight_moves_as_fast_as_ruckig():
    """Ruckig is time-optimal on a straight rest-to-rest move; with jerk limits ours matches it
    (translation and rotation each on its own 1-D time-optimal law, synchronised as Ruckig's
    time synchronisation does); without one ours keeps short jerk phases (BETA_FREE), whose
    ramps are 1/(1 - BETA_FREE) longer, a move at most sqrt of that (2.6 %)."""
    for a, b, limits in random_straight_moves(150, seed=3):
        ours = plan([Waypoint(a), Waypoint(b)], limits).duration
        theirs = ruckig_duration(a, b, limits)
        jerk = limits.max_linear_jerk > 0 and limits.max_angular_jerk > 0
        assert ours <= theirs * (1 + 1e-6 if jerk else 1.026), (limits, a, b, ours, theirs)


# ---- bad input ---------------------------------------------------------------------------------

A, B = pose([1, 0, 0, 0], [0, 0, 0]), pose([1, 0, 0, 0], [0.5, 0, 0])


@pytest.mark.parametrize("field", ["max_linear_velocity", "max_angular_velocity",
                                   "max_linear_acceleration", "max_angular_acceleration"])
@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_impossible_limits_are_refused(field, value):
    kw = dict(max_linear_velocity=1, max_angular_velocity=1, max_linear_acceleration=1,
              max_angular_acceleration=1)
    kw[field] = value
    with pytest.raises(ValueError, match=rf"^limits\.{field}: must be finite and > 0"):
        Limits(**kw)


@pytest.mark.parametrize("value", [-1.0, float("nan")])
def test_bad_jerk_is_refused(value):
    with pytest.raises(ValueError, match=r"^limits\.max_angular_jerk: must be finite and >= 0"):
        Limits(1, 1, 1, 1, 0, value)


@pytest.mark.parametrize("wps,message", [
    ([Waypoint(A)], r"^waypoints: need at least 2"),
    ([Waypoint(A), Waypoint(2 * B)], r"^waypoints\[1\]\.pose: .*not unit"),
    ([Waypoint(A), Waypoint(np.full(8, np.nan))], r"^waypoints\[1\]\.pose: .*NaN"),
    ([Waypoint(A), Waypoint(B[:7])], r"^waypoints\[1\]\.pose: expected shape \(8,\)"),
    ([Waypoint(A), Waypoint(A)], r"^waypoints\[1\]\.pose: the same pose as waypoints\[0\]"),
    ([Waypoint(A, time=1.0), Waypoint(B)], r"^waypoints\[0\]\.time: the first waypoint"),
    ([Waypoint(A), Waypoint(B, time=2.0), Waypoint(A, time=2.0)],
     r"^waypoints\[2\]\.time: 2\.0 is not after waypoints\[1\]\.time"),
    ([Waypoint(A), Waypoint(B, time=float("nan"))], r"^waypoints\[1\]\.time: must be finite"),
    ([Waypoint(A), Waypoint(B, time=-1.0)], r"^waypoints\[1\]\.time: must be finite and >= 0"),
    ([Waypoint(A), Waypoint(B, blend_radius=0.3), Waypoint(A)],
     r"^waypoints\[1\]\.blend_radius: 0\.3 m is more than half a neighbouring segment"),
    ([Waypoint(A), Waypoint(B, blend_radius=float("nan")), Waypoint(A)],
     r"^waypoints\[1\]\.blend_radius: must be finite"),
    ([Waypoint(A), Waypoint(B, blend_radius=0.1)],
     r"^waypoints\[1\]\.blend_radius: the first and last"),
    (["nope", Waypoint(B)], r"^waypoints\[0\]: expected a Waypoint"),
])
def test_bad_waypoints_are_refused(wps, message):
    with pytest.raises(ValueError, match=message):
        plan(wps, LIMITS)


def test_bad_interpolation_and_times_are_refused():
    with pytest.raises(ValueError, match=r"^interpolation: unknown 'spline'"):
        plan([Waypoint(A), Waypoint(B)], LIMITS, "spline")
    tr = plan([Waypoint(A), Waypoint(B)], LIMITS)
    with pytest.raises(ValueError, match=r"^times\[1\]: .* is outside"):
        tr.sample([0.0, tr.duration + 1.0])
    with pytest.raises(ValueError, match=r"^rate_hz: must be finite and > 0"):
        tr.at_rate(0)
