"""dqpose.lookup: a Lookup in one C call (``_dqcore.lookup``, service/csrc/lookup.c) is the
answer of the tracker's fits (to within their tol) for bodies fitted alone or together (a shared
uncertain extrinsic, a shared estimated latency), against the world frame either way, after
warm starts near and far from the answer; rows of one instant and times beyond
max_extrapolation are the fits' (their answers and errors bit for bit); its relative covariance
is honest over time (NEES through a shared uncertain mount); bad rows are refused by name; its
answer's RelativePose bytes written in C are protobuf's."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dqpose import _dqcore, dq, lie
from dqpose.fusion import Measurement, Source
from dqpose.rpc.world_convert import relative_msg, relative_pose_bytes
from dqpose.world import BodyPose, OutOfRange, World, WorldOptions
from tests.fusion._scenes import random_pose
from tests.test_world import same_fit

NOISE = np.diag([np.deg2rad(0.3)] * 3 + [1e-3] * 3) ** 2
MOUNT = np.diag([np.deg2rad(1.0)] * 3 + [5e-3] * 3) ** 2

#: name -> (each source's keywords, which sources see body "b" (all see "a"))
SCENES = {
    "exact, each body its own cameras": ([{}, {"latency": 0.02}, {}], [2]),
    "a shared uncertain mount": ([{"extrinsic_covariance": MOUNT}, {}, {}], [0, 2]),
    "a shared estimated latency": ([{"latency": 0.03, "latency_sigma": 0.02}, {}, {}], [0, 2]),
    "an uncertain mount of one body alone": ([{"extrinsic_covariance": MOUNT}, {}, {}], [2]),
}


def moving(rng, kws, sees_b, ticks: int = 31, window: float = 1.0, twist=None):
    """Bodies "a" and "b" on screws, seen at 30 Hz: every camera sees "a", ``sees_b`` "b"; the
    world, a function publishing tick k, and the truth T_world_body at t."""
    sources = [Source(f"cam{k}", random_pose(rng), **kw) for k, kw in enumerate(kws)]
    world = World(sources=sources, options=WorldOptions(window=window, buffer=10.0,
                                                        twist_covariance=twist))
    E = {s.name: dq.mul(s.extrinsic, lie.se3_exp(rng.multivariate_normal(np.zeros(6), MOUNT)))
         if s.extrinsic_covariance is not None else s.extrinsic for s in sources}
    X0 = {b: random_pose(rng, 0.3) for b in "ab"}
    V = {b: rng.normal(size=6) * 0.2 for b in "ab"}

    def truth(b, t):
        return dq.mul(X0[b], lie.se3_exp(t * V[b]))

    def publish(k):
        t = k / 30.0
        ms = []
        for j, s in enumerate(sources):
            for b in "ab" if j in sees_b else "a":
                z = dq.mul(dq.mul(dq.conj(E[s.name]), truth(b, t - 0.02 * (s.latency > 0))),
                           lie.se3_exp(rng.multivariate_normal(np.zeros(6), NOISE)))
                ms.append(Measurement(s.name, b, t + s.latency, z, NOISE))
        assert world.publish(ms).accepted == len(ms)
    for k in range(ticks):
        publish(k)
    return world, publish, truth


def both_paths(world, target, source, at=None):
    """The Lookup in C (None where it is another path's) and through the tracker's fits."""
    if at is None:
        at = min(world.newest(b) for b in (target, source) if b)
    with world.lock.read():
        return (world.lookups._in_c(target, source, at),
                world.lookups._fitted(target, source, at))


@pytest.mark.parametrize("scene", list(SCENES))
def test_a_lookup_in_c_is_the_fits_answer_cold_and_warm(scene):
    kws, sees_b = SCENES[scene]
    rng = np.random.default_rng(3)
    world, publish, _ = moving(rng, kws, sees_b)
    for k in range(31, 35):        # the first cold, then each from the one before
        for target, source in (("a", "b"), ("", "b"), ("a", ""), ("b", "a")):
            c, f = both_paths(world, target, source)
            assert c is not None
            same_fit(c.pose, c.covariance, f.pose, f.covariance)
            assert c.time == f.time
        publish(k)


@pytest.mark.parametrize("shared", [True, False])
def test_a_warm_start_far_from_the_answer_ends_at_the_answer(shared):
    """A warm start half a radian and a metre off or not finite (no record), and a record of the
    last fit whose normal equations are wrong: the fit ends where the cold one does (converging
    from it, or started again cold)."""
    kws, sees_b = SCENES["a shared uncertain mount" if shared else "exact, each body its own "
                                                                  "cameras"]
    world, publish, _ = moving(np.random.default_rng(4), kws, sees_b)
    lookups = world.lookups
    for k in range(31, 36):
        both_paths(world, "a", "b")
        assert lookups._records       # the fits' records, from which the next ones start
        publish(k)
        if k < 33:      # far and non-finite warm starts
            off = np.r_[0.5, 0, 0, 1.0, 0, 0] if k == 31 else np.full(6, np.nan)
            lookups._records.clear()
            for b in "ab":
                warm = lookups._warm[b].copy()
                warm[1:9] = dq.mul(warm[1:9], lie.se3_exp(off)) if k == 31 else np.nan
                lookups._warm[b] = warm
        else:           # the records' H and g scaled, or made not finite
            for key, rec in lookups._records.items():
                dim = int(rec[0])
                rec = rec.copy()
                rec[-dim * dim - dim:] *= 1e3 if k == 33 else np.nan
                lookups._records[key] = rec
        c, f = both_paths(world, "a", "b")
        assert c is not None
        same_fit(c.pose, c.covariance, f.pose, f.covariance)


@pytest.mark.parametrize("scene", ["exact, each body its own cameras", "a shared uncertain mount"])
def test_a_fit_of_the_same_rows_at_the_same_time_is_its_records(scene):
    """A Lookup whose fits' records hold the same rows at the same time (another pair with the
    same bodies, a body against the world frame) takes the records' state and covariance
    outright: the fit's answer, and the records as they were."""
    world, _, _ = moving(np.random.default_rng(8), *SCENES[scene])
    assert world.newest("a") == world.newest("b")
    first = world.relative("a", "b")
    lookups = world.lookups
    kept = {k: r.copy() for k, r in lookups._records.items()}
    for target, source in (("", "b"), ("a", ""), ("b", "a")):
        c, f = both_paths(world, target, source)
        same_fit(c.pose, c.covariance, f.pose, f.covariance)
    if scene.startswith("exact"):      # each body's fit alone: its record made again as it was
        for k in (("a",), ("b",)):
            assert lookups._records[k].tobytes() == kept[k].tobytes()
    again = world.lookups._in_c("a", "b", first.time)
    assert again.pose.tobytes() == first.pose.tobytes()
    assert again.covariance.tobytes() == first.covariance.tobytes()


def test_the_warm_starts_and_records_are_bounded_as_a_worlds_fits_are(monkeypatch):
    """Every pair looked up leaves a record: they are kept as a world's fits are (dqpose.answers'
    bounds, here 1 entry), so Lookups of many pairs do not grow them."""
    from dqpose import answers
    monkeypatch.setattr(answers, "_CACHED", 1)
    world, _, _ = moving(np.random.default_rng(9), *SCENES["exact, each body its own cameras"])
    for target, source in (("a", "b"), ("b", "a"), ("", "a"), ("", "b"), ("a", ""), ("b", "")):
        world.relative(target, source)
        assert len(world.lookups._records) <= 1 and len(world.lookups._warm) <= 1


def test_one_instant_and_a_time_beyond_max_extrapolation_are_the_fits_answers():
    rng = np.random.default_rng(5)
    kws, sees_b = SCENES["a shared uncertain mount"]
    world, _, _ = moving(rng, kws, sees_b, ticks=1)        # one instant each
    c, f = both_paths(world, "a", "b")
    assert c is None
    r = world.relative("a", "b")
    assert r.pose.tobytes() == f.pose.tobytes()
    world, _, _ = moving(rng, kws, sees_b)
    newest = world.newest("a")
    with pytest.raises(OutOfRange, match="max_extrapolation"):
        world.relative("", "a", newest + 0.5)


def test_the_relative_covariance_through_a_shared_mount_is_honest_over_time():
    """The mount's error drawn per trial, the bodies moving: the mean NEES of the Lookup (the
    joint fit in C, warm-started over the last ticks) is 6 within its spread over 150 trials."""
    rng = np.random.default_rng(6)
    kws, sees_b = SCENES["a shared uncertain mount"]
    nees = []
    for _ in range(150):
        world, publish, truth = moving(rng, kws, sees_b, ticks=12, window=0.4)
        for k in range(12, 15):
            publish(k)
            r = world.relative("a", "b")
        T = dq.mul(dq.conj(truth("a", r.time)), truth("b", r.time))
        e = lie.se3_log(dq.mul(dq.conj(r.pose), T))
        nees.append(float(e @ np.linalg.solve(r.covariance, e)))
    assert 5.3 <= np.mean(nees) <= 6.7, np.mean(nees)


def test_rows_that_are_not_the_stores_are_refused_by_name():
    world, _, _ = moving(np.random.default_rng(7), *SCENES["a shared uncertain mount"])
    lookups, t = world.lookups, world.tracker
    table = lookups._table(t)
    L, E = lookups._starts(t, len(table[0]))
    s = t.store
    for bad in (np.array([s.n]), np.array([-1])):
        with pytest.raises(ValueError, match=r"rows_a\[0\]"):
            _dqcore.lookup(s.ids, s.wposes, s.covs, s.times[:s.n], s.codes, *table[:5], bad,
                           None, None, None, None, L, E, None, None, None, 1.0, np.inf, 1e-12,
                           100)


_DOUBLE = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(st.lists(st.floats(-50, 50), min_size=6, max_size=6), st.sampled_from([0.0, 1e-9, 1.0]),
       st.booleans(), st.lists(_DOUBLE, min_size=36, max_size=36),
       st.one_of(_DOUBLE, st.sampled_from([0.0, -0.0])))
def test_a_lookups_bytes_are_protobufs(xi, scale, flip, cov, time):
    """The RelativePose a Lookup answers, written in C (the server's encoder), is the message
    relative_msg makes, serialized by protobuf: any pose (identity, tiny, the quaternion's sign
    flipped), any covariance values (NaN, infinities, -0.0) and time (-0.0 and 0.0 included)."""
    X = lie.se3_exp(np.array(xi) * scale)
    X = -X if flip else X
    p = BodyPose("b", time, X, np.array(cov).reshape(6, 6), None)
    assert relative_pose_bytes(p) == relative_msg(p).SerializeToString()
