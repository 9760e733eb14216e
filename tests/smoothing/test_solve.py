"""service/smoothing/: limits measured from the returned samples, accuracy against a known path,
fidelity when asked for it, and bad input rejected with the argument named."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from dqpose import dq, smoothing
from dqpose.smoothing import Infeasible, Limits, peaks, smooth


# ---- the synthetic recording (the benchmark uses the same) ---------------------------------------
def _rotations(w: np.ndarray) -> np.ndarray:
    x = np.zeros(w.shape[:-1] + (6,))
    x[..., :3] = 0.5 * w
    return dq.exp(x)


def teleop_path(seed: int = 0, n: int = 500, rate_hz: float = 100.0):
    """A teleoperation-like path: times (n,), poses (n, 8). At rest at both ends (a sin^3
    window), in between sines of 0.2-0.7 Hz on each position axis (5-15 cm) and each axis of a
    rotation vector (0.2-0.6 rad) about a fixed start orientation."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    env = np.sin(np.pi * t / t[-1]) ** 3
    wave = lambda amp, f: env[:, None] * amp * np.sin(2 * np.pi * f * t[:, None]  # noqa: E731
                                                       + rng.uniform(0, 2 * np.pi, 3))
    p = np.array([0.4, 0.0, 0.3]) + wave(rng.uniform(0.05, 0.15, 3), rng.uniform(0.2, 0.7, 3))
    w = wave(rng.uniform(0.2, 0.6, 3), rng.uniform(0.2, 0.5, 3))
    r0 = _rotations(np.array([math.pi, 0.0, 0.0]))          # tool pointing down
    r = dq.mul(r0, _rotations(w))
    return t, dq.from_pose(r[:, :4], p)


def noisy(poses: np.ndarray, seed: int = 1, mm: float = 1.0, deg: float = 0.5) -> np.ndarray:
    """Isotropic Gaussian noise whose norm has the rms ``mm`` / ``deg`` (per axis / sqrt 3),
    orientation noise as a body perturbation ``R Exp(xi)``."""
    rng = np.random.default_rng(seed)
    q, p = dq.to_pose(poses)
    r = np.zeros_like(poses)
    r[:, :4] = q
    xi = rng.normal(scale=math.radians(deg) / math.sqrt(3), size=(poses.shape[0], 3))
    q = dq.mul(r, _rotations(xi))[:, :4]
    return dq.from_pose(q, p + rng.normal(scale=mm * 1e-3 / math.sqrt(3), size=p.shape))


def errors(poses: np.ndarray, truth: np.ndarray):
    """Translation (m) and rotation (rad) error of each pose."""
    qa, pa = dq.to_pose(poses)
    qb, pb = dq.to_pose(truth)
    cos = np.clip(np.abs(np.einsum("ij,ij->i", qa, qb)), 0.0, 1.0)
    return np.linalg.norm(pa - pb, axis=1), 2 * np.arccos(cos)


def limits_from(pk, factor: float = 1.0, **kw) -> Limits:
    return Limits(pk.linear_velocity * factor, pk.angular_velocity * factor,
                  pk.linear_acceleration * factor, pk.angular_acceleration * factor, **kw)


def assert_within(times, poses, limits: Limits):
    pk = peaks(times, poses)
    for name in ("linear_velocity", "angular_velocity", "linear_acceleration",
                 "angular_acceleration", "linear_jerk", "angular_jerk"):
        limit = getattr(limits, "max_" + name)
        if limit > 0:
            assert getattr(pk, name) <= limit * (1 + 1e-9), (name, getattr(pk, name), limit)


# ---- what the result must do ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def recording():
    t, truth = teleop_path()
    return t, truth, noisy(truth)


@pytest.mark.parametrize("rate_hz", [0.0, 500.0, 37.0])
def test_limits_hold_on_the_returned_samples_and_error_is_below_the_noise(recording, rate_hz):
    t, truth, y = recording
    # The limits are the true path's own peaks: the noisy samples break them by far and the
    # unconstrained smoothing by a little, so the QP has work to do.
    limits = limits_from(peaks(t, truth))
    raw = peaks(t, y)
    assert raw.linear_acceleration > 10 * limits.max_linear_acceleration
    out_t, out = smooth(t, y, limits, rate_hz=rate_hz)
    assert out_t[0] == t[0] and out_t[-1] == t[-1]
    assert np.all(np.diff(out_t) > 0)
    if rate_hz:
        assert np.allclose(np.diff(out_t)[:-1], 1 / rate_hz)
    assert_within(out_t, out, limits)
    if rate_hz == 0:
        np.testing.assert_array_equal(out_t, t)
        et, er = errors(out, truth)
        nt, nr = errors(y, truth)
        assert np.sqrt(np.mean(et ** 2)) < 0.5 * np.sqrt(np.mean(nt ** 2))
        assert np.sqrt(np.mean(er ** 2)) < 0.5 * np.sqrt(np.mean(nr ** 2))


def test_tight_limits_bind_and_still_hold(recording):
    t, truth, y = recording
    limits = limits_from(peaks(t, truth), 0.7)
    out_t, out = smooth(t, y, limits, rate_hz=250.0)
    assert_within(out_t, out, limits)
    pk = peaks(out_t, out)
    # binding: the result goes up to (the inscribed box of) the velocity limits
    assert pk.linear_velocity > 0.95 * limits.max_linear_velocity
    assert pk.angular_velocity > 0.95 * limits.max_angular_velocity


def test_jerk_limits_are_kept_when_given(recording):
    t, truth, y = recording
    pk = peaks(t, truth)
    limits = limits_from(pk, 1.0, max_linear_jerk=pk.linear_jerk * 0.8,
                         max_angular_jerk=pk.angular_jerk * 0.8)
    out_t, out = smooth(t, y, limits)
    assert_within(out_t, out, limits)


def test_starts_and_ends_at_rest(recording):
    t, truth, y = recording
    out_t, out = smooth(t, y, limits_from(peaks(t, truth)), rate_hz=1000.0)
    for sl in (slice(0, 3), slice(-3, None)):
        pk = peaks(out_t[sl], out[sl])
        assert pk.linear_velocity < 1e-6 and pk.angular_velocity < 1e-5


def test_a_path_within_the_limits_comes_back_as_it_was_when_fidelity_dominates(recording):
    t, truth, _ = recording
    limits = limits_from(peaks(t, truth), 1.5)
    previous = (np.inf, np.inf)
    for s in (1.0, 0.3, 0.0):
        _, out = smooth(t, truth, limits, smoothing=s)
        et, er = errors(out, truth)
        assert et.max() < previous[0] and er.max() < previous[1]
        previous = (et.max(), er.max())
    assert previous[0] < 1e-6 and previous[1] < 1e-5


def test_smoothing_sets_the_cutoff():
    # A 1 Hz sine is kept at smoothing 1 (cutoff 2 Hz: gain 1/(1+2^-6)) and halved at
    # smoothing 2 (cutoff 1 Hz), as the module docstring says.
    t = np.arange(1000) / 100.0
    window = np.sin(np.pi * t / t[-1]) ** 2
    p = np.zeros((t.size, 3))
    p[:, 0] = 0.01 * window * np.sin(2 * np.pi * 1.0 * t)
    poses = dq.from_pose(np.tile([1.0, 0, 0, 0], (t.size, 1)), p)
    limits = Limits(10, 10, 100, 100)
    mid = slice(400, 600)
    gain = {}
    for s in (1.0, 2.0):
        _, out = smooth(t, poses, limits, smoothing=s)
        gain[s] = np.abs(dq.to_pose(out)[1][mid, 0]).max() / np.abs(p[mid, 0]).max()
    assert gain[1.0] == pytest.approx(1 / (1 + 0.5 ** 6), abs=0.01)
    assert gain[2.0] == pytest.approx(0.5, abs=0.03)


def test_sign_of_the_quaternions_and_jittered_stamps(recording):
    t, truth, y = recording
    limits = limits_from(peaks(t, truth))
    _, a = smooth(t, y, limits)
    flipped = y.copy()
    flipped[::3] *= -1
    _, b = smooth(t, flipped, limits)
    et, er = errors(a, b)
    assert et.max() < 1e-9 and er.max() < 1e-7
    # stamps jittered by up to 2 ms (a teleoperation link): still within the limits
    rng = np.random.default_rng(5)
    tj = t + rng.uniform(-0.002, 0.002, t.size)
    tj[0], tj[-1] = t[0], t[-1]
    out_t, out = smooth(tj, y, limits, rate_hz=100.0)
    assert_within(out_t, out, limits)


def test_turns_past_pi_are_followed():
    # two full turns about z in 8 s: the increments, not a global rotation vector, carry it
    t = np.arange(800) / 100.0
    s = (t / t[-1]) ** 3 * (10 - 15 * (t / t[-1]) + 6 * (t / t[-1]) ** 2)
    w = np.zeros((t.size, 3))
    w[:, 2] = 4 * np.pi * s
    r = _rotations(w)
    truth = dq.from_pose(r[:, :4], np.zeros((t.size, 3)))
    pk = peaks(t, truth)
    limits = Limits(0.1, 1.2 * pk.angular_velocity, 1.0, 1.2 * pk.angular_acceleration)
    out_t, out = smooth(t, noisy(truth), limits)
    assert_within(out_t, out, limits)
    _, er = errors(out, truth)
    assert er.max() < math.radians(0.5)


def test_near_ipopts_optimum_of_the_nonlinear_problem():
    # The benchmark's IPOPT peer solves the exact problem (increments and residuals on SO(3),
    # |Q|^2 <= L^2); with limits that bind hard, ours stays near its optimum: a small share of
    # what the limits move the path by.
    casadi = pytest.importorskip("casadi")
    if not casadi.has_nlpsol("ipopt"):
        pytest.skip("casadi without IPOPT")
    from tests.bench.bench_smoothing import Ipopt

    t, truth = teleop_path(seed=3, n=80, rate_hz=50.0)
    y = noisy(truth, seed=7)
    limits = limits_from(peaks(t, truth), 0.8)
    _, status, optimum = Ipopt(t, y, limits).solve()
    assert status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    _, ours = smooth(t, y, limits)
    free = smooth(t, y, limits_from(peaks(t, y), 10.0))[1]        # limits far away
    moved_t, moved_r = errors(optimum, free)
    et, er = errors(ours, optimum)
    assert moved_t.max() > 3e-3                                    # the limits do bind
    assert et.max() < 0.1 * moved_t.max() and er.max() < 0.1 * moved_r.max()


def test_peaks_of_a_constant_twist():
    t = np.arange(50) * 0.01
    w = np.outer(t, [0.0, 0.0, 2.0])
    poses = dq.from_pose(_rotations(w)[:, :4], np.outer(t, [0.3, 0.4, 0.0]))
    pk = peaks(t, poses)
    assert pk.linear_velocity == pytest.approx(0.5)
    assert pk.angular_velocity == pytest.approx(2.0)
    assert pk.linear_acceleration < 1e-9 and pk.angular_acceleration < 1e-9


# ---- what it refuses -----------------------------------------------------------------------------
def test_ends_too_far_apart_for_the_duration_are_infeasible():
    t = np.arange(100) / 100.0
    s = np.clip((t - 0.1) / 0.8, 0, 1)
    p = np.outer(s ** 3 * (10 - 15 * s + 6 * s ** 2), [1.0, 0.0, 0.0])    # 1 m in 0.99 s
    poses = dq.from_pose(np.tile([1.0, 0, 0, 0], (t.size, 1)), p)
    with pytest.raises(Infeasible) as info:
        smooth(t, poses, Limits(0.1, 1.0, 1.0, 1.0))
    m = re.match(r"^times: the path moves ([\d.]+) m between its ends in 0\.99 s, which needs "
                 r"at least ([\d.]+) s from rest to rest under the limits", str(info.value))
    assert m, str(info.value)
    dist = float(m.group(1))            # where the smoothing puts the ends: ~1 m (the filter rings)
    assert dist == pytest.approx(1.0, abs=0.03)
    assert float(m.group(2)) == pytest.approx(dist / 0.1 + 0.1, rel=1e-5)   # cruise + ramps
    assert issubclass(Infeasible, ValueError)


def test_a_move_the_spline_cannot_make_on_this_clock_is_infeasible():
    # 6 cm in 0.49 s passes the closed-form rest-to-rest bound (0.4899 s) but not on the spline's
    # 49 spans with rest at both ends: the QP finds no point, reported, not returned.
    t = np.arange(50) * 0.01
    p = np.zeros((50, 3))
    p[25:, 0] = 0.06
    with pytest.raises(Infeasible, match=r"^poses: no path within the limits keeps this clock"):
        smooth(t, dq.from_pose(np.tile([1.0, 0, 0, 0], (50, 1)), p), Limits(0.5, 1, 1, 1),
               smoothing=0.0)


GOOD_T = np.arange(6) * 0.01
GOOD = np.tile(dq.identity(), (6, 1))


def _with(index, value):
    a = GOOD.copy()
    a[index] = value
    return a


@pytest.mark.parametrize("times, poses, message", [
    (GOOD_T[:3], GOOD[:3], r"^poses: need at least 4 poses, got 3"),
    (np.r_[0, 0.01, 0.01, 0.03, 0.04, 0.05], GOOD, r"^times\[2\]: 0\.01 is not after times\[1\]"),
    (np.r_[0, 0.01, np.nan, 0.03, 0.04, 0.05], GOOD, r"^times\[2\]: nan is not finite"),
    (GOOD_T, _with((4, 0), 1.5), r"^poses\[4\]: .*not unit"),
    (GOOD_T, _with((1, 5), np.nan), r"^poses\[1\]"),
    (GOOD_T, GOOD[:5], r"^poses: 5 poses for 6 times"),
    (GOOD_T, GOOD[:, :7], r"^poses: expected shape \(N, 8\)"),
    (GOOD_T.reshape(2, 3), GOOD, r"^times: expected a 1-D array"),
])
def test_bad_samples_are_rejected_by_name(times, poses, message):
    with pytest.raises(ValueError, match=message):
        smooth(times, poses, Limits(1, 1, 1, 1))


@pytest.mark.parametrize("kwargs, message", [
    (dict(smoothing=-1.0), r"^smoothing: -1\.0 must be finite and >= 0"),
    (dict(smoothing=float("nan")), r"^smoothing: nan must be"),
    (dict(rate_hz=-5.0), r"^rate_hz: -5\.0 must be finite and >= 0"),
    (dict(limits=(1, 1, 1, 1)), r"^limits: expected a Limits, got tuple"),
])
def test_bad_options_are_rejected_by_name(kwargs, message):
    args = dict(limits=Limits(1, 1, 1, 1))
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        smooth(GOOD_T, GOOD, **args)


# Limits checks itself (issue 10's contract: a ValueError starting with the field's path); the
# wording after the path is dqpose.trajectory's.
@pytest.mark.parametrize("field, value, message", [
    ("max_linear_velocity", 0.0, r"^limits\.max_linear_velocity: "),
    ("max_angular_acceleration", -1.0, r"^limits\.max_angular_acceleration: "),
    ("max_angular_velocity", float("nan"), r"^limits\.max_angular_velocity: "),
    ("max_linear_jerk", -1.0, r"^limits\.max_linear_jerk: "),
])
def test_bad_limits_are_rejected_by_name(field, value, message):
    kw = dict(max_linear_velocity=1, max_angular_velocity=1, max_linear_acceleration=1,
              max_angular_acceleration=1)
    kw[field] = value
    with pytest.raises(ValueError, match=message):
        Limits(**kw)


def test_module_constants_match_the_docstring():
    assert smoothing.CUTOFF_HZ == 2.0 and "2 Hz" in smoothing.__doc__
