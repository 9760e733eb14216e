"""dqpose.world: the world's fused pose is fuse's over the same measurements, many producers at
once, lookups at past times and their refusals, the bounds, configurations (relative poses:
test_world_relative.py)."""
import threading

import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Measurement, Source
from dqpose.lookup import composed_independent
from dqpose.world import (
    NotFound,
    OutOfRange,
    World,
    WorldBounds,
    WorldError,
    WorldOptions,
)
from tests.fusion._scenes import random_cov, random_pose

V = np.array([0.1, -0.2, 0.05, 0.1, 0.02, -0.05])
NOISE = np.diag([np.deg2rad(0.1)] * 3 + [0.5e-3] * 3) ** 2
EXTRINSIC = np.diag([np.deg2rad(1.0)] * 3 + [5e-3] * 3) ** 2


def stream(rng, sources, bodies, times, truth_extrinsic=None):
    """Each source measures each body at each time; bodies move with twist V from random
    poses. Returns (measurements, truth poses at t=0 per body)."""
    X0 = {b: random_pose(rng, 0.5) for b in bodies}
    E = truth_extrinsic or {s.name: s.extrinsic for s in sources}
    out = []
    for t in times:
        for s in sources:
            for b in bodies:
                Xt = dq.mul(X0[b], lie.se3_exp(t * V))
                c = random_cov(rng)
                z = dq.mul(dq.mul(dq.conj(E[s.name]), Xt),
                           lie.se3_exp(-rng.multivariate_normal(np.zeros(6), c)))
                out.append(Measurement(s.name, b, float(t), z, c))
    return out, X0


def fuse_of(ms, body, time, window, sources, **kw):
    """fuse over ``body``'s measurements a Lookup at ``time`` fits: those taken in the
    ``window`` ending half a window after ``time``, or at the newest if sooner (no latencies
    here: taken is the stamp)."""
    newest = max(m.time for m in ms if m.body == body)
    end = min(newest, time + 0.5 * window)
    mine = [m for m in ms if m.body == body and end - window <= m.time <= end]
    return fusion.fuse(np.array([m.pose for m in mine]), np.array([m.covariance for m in mine]),
                       names=[m.source for m in mine], times=[m.time for m in mine],
                       time=time, sources=sources, **kw)


def same_fit(pose, covariance, mean, cov) -> None:
    """A Lookup's pose and covariance are those of the fit ``(mean, cov)`` to within what the
    fit's tol (1e-12 on a step) leaves: a Lookup's fit may start elsewhere (its warm start,
    service/lookup.py), so its last bits are not pinned."""
    np.testing.assert_allclose(pose, mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(covariance, cov, rtol=0, atol=1e-8 * np.abs(cov).max())


def test_a_lookup_leaves_out_the_nis_and_a_pose_still_has_them():
    """A Lookup (``relative``) answers a body's fit without its leave-one-out NIS, the pose and
    covariance fuse gives (to within its tol); ``pose`` afterwards (what a Subscribe answer
    carries) has fuse's NIS and verdicts, not the Lookup's fit kept without them."""
    rng = np.random.default_rng(11)
    sources = [Source(f"cam{k}", random_pose(rng)) for k in range(2)]
    ms, _ = stream(rng, sources, ["box", "cup"], np.arange(20) * 0.03)
    world = World(sources=sources, options=WorldOptions(window=0.3))
    assert world.publish(ms).accepted == len(ms)
    at = world.newest("box")
    f = fuse_of(ms, "box", at, 0.3, sources)
    assert f.tested.any()
    looked = world.relative("", "box")
    assert looked.time == at
    same_fit(looked.pose, looked.covariance, f.mean, f.covariance)
    p = world.pose("box")
    assert p.fused is not None
    np.testing.assert_array_equal(p.fused.nis, f.nis)
    np.testing.assert_array_equal(p.fused.tested, f.tested)
    assert p.fused.sources == f.sources
    # and the other way round: a kept fit with its NIS serves a Lookup
    world.pose("cup")
    cup = world.relative("", "cup")
    assert cup.pose.tobytes() == world.pose("cup").pose.tobytes()


_LOOKUP_CASES = {
    # the Lookup's own lane: the constant-twist fit straight from the rows
    "exact sources with latencies": ({}, {}),
    "a twist prior": ({}, {"twist_covariance": np.eye(6) * 0.01}),
    # each of the other fits, through the full one
    "a latency estimated": ({"latency_sigma": 0.01}, {}),
    "an uncertain extrinsic": ({"extrinsic_covariance": np.eye(6) * 1e-6}, {}),
    "robust": ({}, {"robust": True}),
    "max_skew": ({}, {"max_skew": 0.2}),
    "acceleration_psd": ({}, {"acceleration_psd": np.eye(6) * 0.1}),
}


@pytest.mark.parametrize("case", list(_LOOKUP_CASES))
def test_a_lookup_of_a_body_is_fuses_pose_and_covariance_whichever_fit_runs(case):
    """A Lookup of one body computes its pose and covariance alone where the constant-twist fit
    applies (in C, to within its tol), and through the full fit where another one does (the
    same bits): either way fuse's, and the body's pose afterwards is fuse's bit for bit."""
    source_kw, option_kw = _LOOKUP_CASES[case]
    rng = np.random.default_rng(12)
    sources = [Source("cam0", random_pose(rng), latency=0.02),
               Source("cam1", random_pose(rng), latency=0.01, **source_kw)]
    ms, _ = stream(rng, sources, ["box"], np.arange(12) * 0.03)
    world = World(sources=sources, options=WorldOptions(window=0.3, **option_kw))
    assert world.publish(ms).accepted == len(ms)
    latency = {s.name: s.latency for s in sources}
    newest = world.newest("box")
    for at in (newest, newest - 0.05, newest - 0.2):
        # a Lookup's window: taken (stamp less latency) in the 0.3 s ending 0.15 s after the
        # time, or at the newest
        end = min(newest, at + 0.15)
        mine = [m for m in ms if end - 0.3 <= m.time - latency[m.source] <= end]
        f = fuse_of(mine, "box", at, np.inf, sources, **option_kw)
        looked = world.relative("", "box", at)
        same_fit(looked.pose, looked.covariance, f.mean, f.covariance)
        if "robust" in option_kw or "max_skew" in option_kw or "acceleration_psd" in option_kw:
            assert looked.pose.tobytes() == f.mean.tobytes()
            assert looked.covariance.tobytes() == f.covariance.tobytes()
        assert world.pose("box", at).covariance.tobytes() == f.covariance.tobytes()


@pytest.mark.parametrize("uncertain", [False, True])
def test_a_lookup_between_bodies_that_share_no_error_composes_their_poses(uncertain):
    """Two bodies whose sources share no uncertain extrinsic or latency: the relative pose is
    the composition of the two bodies' poses (to within the fit's tol), whether every source of
    the world is exact or another body's camera is uncertain."""
    rng = np.random.default_rng(14)
    sources = [Source("cam0", random_pose(rng), latency=0.02),
               Source("cam1", random_pose(rng), latency=0.01),
               Source("cam2", random_pose(rng), extrinsic_covariance=(
                   np.eye(6) * 1e-6 if uncertain else None))]
    ms, _ = stream(rng, sources[:2], ["box", "cup"], np.arange(12) * 0.03)
    seen, _ = stream(rng, sources[2:], ["jar"], np.arange(12) * 0.03)
    world = World(sources=sources, options=WorldOptions(window=0.3))
    assert world.publish(ms + seen).accepted == len(ms) + len(seen)
    at = min(world.newest("box"), world.newest("cup"))
    r = world.relative("box", "cup")
    poses = {b: (p.pose, p.covariance) for b, p in ((b, world.pose(b, at)) for b in ("box", "cup"))}
    c = composed_independent("box", "cup", at, poses)
    same_fit(r.pose, r.covariance, c.pose, c.covariance)


def test_a_lookup_of_one_instant_and_out_of_range_answers_as_the_full_fit():
    """Measurements all taken at one instant (the static fit) and a time beyond
    max_extrapolation: a Lookup of the body answers fuse's pose, or refuses naming what is
    known, as the full fit does."""
    rng = np.random.default_rng(13)
    sources = [Source(f"cam{k}", random_pose(rng)) for k in range(2)]
    ms, _ = stream(rng, sources, ["box"], [1.0])
    world = World(sources=sources, options=WorldOptions(window=0.3, max_extrapolation=0.1))
    world.publish(ms)
    f = fuse_of(ms, "box", 1.0, 0.3, sources)
    assert world.relative("", "box").pose.tobytes() == f.mean.tobytes()
    with pytest.raises(OutOfRange, match="max_extrapolation"):
        world.relative("", "box", 1.5)
    with pytest.raises(WorldError, match="time"):
        world.relative("", "box", float("nan"))


def test_pose_equals_fuse_with_producers_on_threads():
    rng = np.random.default_rng(1)
    sources = [Source(f"cam{k}", random_pose(rng), latency=0.0) for k in range(3)]
    sources[1] = Source("cam1", sources[1].extrinsic, extrinsic_covariance=random_cov(rng) / 4)
    ms, _ = stream(rng, sources, ["box", "cup"], np.arange(30) * 0.02)
    world = World(sources=sources, options=WorldOptions(window=0.2))
    # one producer per source, each on its own thread, publishing in chunks
    chunks = {s.name: [m for m in ms if m.source == s.name] for s in sources}
    results = []

    def produce(name):
        mine = chunks[name]
        for k in range(0, len(mine), 7):
            results.append(world.publish(mine[k:k + 7]))

    threads = [threading.Thread(target=produce, args=(s.name,)) for s in sources]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(r.accepted for r in results) == len(ms)
    assert not any(r.errors for r in results)
    assert set(world.bodies) == {"box", "cup"}
    for body in ("box", "cup"):
        for time in (None, 0.3, 0.41):
            p = world.pose(body, time)
            at = 0.58 if time is None else time
            f = fuse_of(ms, body, at, 0.2, sources)
            assert p.time == at
            assert np.abs(p.pose - f.mean).max() <= 1e-12
            assert np.abs(p.covariance - f.covariance).max() <= 1e-12 * np.abs(
                f.covariance).max()
            assert p.fused is not None and len(p.fused.inliers) == len(f.inliers)
    assert sorted(world.sources_of("box")) == ["cam0", "cam1", "cam2"]
    # an answer kept for repeated lookups gives way to new measurements
    before = world.pose("box", 0.58)
    more, _ = stream(rng, sources, ["box"], [0.57])
    world.publish(more)
    after = world.pose("box", 0.58)
    f = fuse_of(ms + more, "box", 0.58, 0.2, sources)
    assert np.abs(after.pose - f.mean).max() <= 1e-12
    assert np.abs(after.pose - before.pose).max() > 1e-9
    assert world.newest("box", "cam2") == pytest.approx(0.58)


def test_lookups_out_of_range_and_not_found():
    rng = np.random.default_rng(2)
    sources = [Source("cam", random_pose(rng))]
    ms, _ = stream(rng, sources, ["box"], np.arange(10) * 0.1 + 100.0)
    world = World(sources=sources, options=WorldOptions(window=0.5, buffer=0.5,
                                                        max_extrapolation=0.1))
    assert world.publish(ms).accepted == len(ms)
    # the buffer keeps 0.5 s: 100.4 .. 100.9
    with pytest.raises(OutOfRange, match=r"before the oldest measurement kept; 'box' is known "
                                         r"from 100\.4 to 100\.9"):
        world.pose("box", 100.2)
    with pytest.raises(OutOfRange, match=r"0\.3 s past the newest measurement, beyond "
                                         r"max_extrapolation 0\.1 s"):
        world.pose("box", 101.2)
    with pytest.raises(NotFound, match=r"^body: 'cup' is not in the world \(1 bodies: 'box'\)"):
        world.pose("cup")
    with pytest.raises(NotFound, match=r"^arm: 'ur' has no source"):
        world.arm_base("ur")
    assert world.pose("box", 100.95).time == 100.95


def test_publish_answers_each_bad_measurement_and_keeps_the_others():
    rng = np.random.default_rng(3)
    sources = [Source("cam", random_pose(rng))]
    ms, _ = stream(rng, sources, ["box"], [0.0, 0.1, 0.2])
    bad = list(ms)
    bad[1] = Measurement("cam", "box", 0.1, ms[1].pose, -np.eye(6))
    bad.insert(2, Measurement("cam", "box", float("nan"), ms[1].pose))
    bad.append(Measurement("cam", "box", 0.3, np.zeros(7)))
    world = World(sources=sources)
    r = world.publish(bad)
    assert r.accepted == 2
    assert [e.index for e in r.errors] == [1, 2, 4]
    assert [e.field for e in r.errors] == ["covariance", "time", "pose"]
    assert str(r.errors[0]).startswith("measurements[1].covariance: not positive definite")
    assert str(r.errors[1]).startswith("measurements[2].time: must be finite")
    assert str(r.errors[2]).startswith("measurements[4].pose: expected shape (8,)")
    assert r.bodies == ("box",)


def test_ingest_of_arrays_answers_as_publish_does():
    # The server's path (arrays parsed from the request) and the objects' path: the same
    # errors, the same fused pose to the last bit.
    rng = np.random.default_rng(4)
    sources = [Source("cam", random_pose(rng)), Source("arm", random_pose(rng))]
    ms, _ = stream(rng, sources, ["box", "cup"], [0.0, 0.05, 0.1, 0.15])
    ms[3] = Measurement("cam", "box", ms[3].time, ms[3].pose, -np.eye(6))
    ms[5] = Measurement("arm", "cup", float("inf"), ms[5].pose, ms[5].covariance)
    ms[6] = Measurement("arm", "", ms[6].time, ms[6].pose, ms[6].covariance)
    by_objects, by_arrays = World(sources=sources), World(sources=sources)
    a = by_objects.publish(ms)
    b = by_arrays.ingest([m.body for m in ms], [m.source for m in ms], [m.time for m in ms],
                         np.array([m.pose for m in ms]), np.array([m.covariance for m in ms]))
    assert a == b and [e.index for e in b.errors] == [3, 5, 6]
    for body in ("box", "cup"):
        pa, pb = by_objects.pose(body, 0.1), by_arrays.pose(body, 0.1)
        assert np.array_equal(pa.pose, pb.pose) and np.array_equal(pa.covariance, pb.covariance)
    with pytest.raises(WorldError, match=r"^poses: expected shape \(16, 8\), got \(16, 7\)"):
        by_arrays.ingest(["box"] * 16, ["cam"] * 16, np.zeros(16), np.zeros((16, 7)),
                         np.zeros((16, 6, 6)))


def test_bounds_refused_naming_the_limit():
    rng = np.random.default_rng(4)
    world = World(bounds=WorldBounds(max_bodies=2, max_sources=2))
    p = random_pose(rng)
    r = world.publish([Measurement("a", f"b{k}", 0.0, p) for k in range(3)])
    assert r.accepted == 2
    assert [(e.index, str(e)) for e in r.errors] == [
        (2, "measurements[2].body: 'b2' would be body 3, above the world's max_bodies 2")]
    r = world.publish([Measurement(s, "b0", 0.0, p) for s in ("b", "c")])
    assert [(e.index, str(e)) for e in r.errors] == [
        (1, "measurements[1].source: 'c' would be source 3, above the world's max_sources 2")]
    with pytest.raises(WorldError, match=r"^sources: 3 is above the world's max_sources 2"):
        world.configure(sources=[Source(n) for n in "xyz"], arms={}, options=WorldOptions())
    with pytest.raises(WorldError, match=r"^options.buffer: 90 s is above the world's "
                                         r"max_buffer 60 s"):
        world.configure(sources=[], arms={}, options=WorldOptions(buffer=90.0))
    with pytest.raises(WorldError, match=r"^sources\[0\]\.extrinsic_covariance: not positive"):
        world.configure(sources=[Source("x", extrinsic_covariance=-np.eye(6))], arms={},
                        options=WorldOptions())
    with pytest.raises(WorldError, match=r"^options.max_delay: 0.5 s is longer than "
                                         r"options.window 0.2 s"):
        world.configure(sources=[], arms={}, options=WorldOptions(window=0.2, max_delay=0.5))
    with pytest.raises(WorldError, match=r"^arms\['ur'\]: source 'q' is not among"):
        world.configure(sources=[Source("x")], arms={"ur": "q"}, options=WorldOptions())
    assert world.bodies == ("b0", "b1")     # refused configurations changed nothing



def test_a_row_refused_for_its_source_takes_no_body_slot():
    """A row over max_sources names a new body too: the refusal must leave the body's place
    for the next row that brings it."""
    p = random_pose(np.random.default_rng(4))
    world = World(bounds=WorldBounds(max_bodies=2, max_sources=1))
    r = world.publish([Measurement("a", "b0", 0.0, p), Measurement("z", "b1", 0.0, p),
                       Measurement("a", "b2", 0.0, p)])
    assert [e.index for e in r.errors] == [1]
    assert world.bodies == ("b0", "b2")

def test_configure_keeps_the_measurements_and_refits_with_the_new_sources():
    rng = np.random.default_rng(5)
    sources = [Source("cam", random_pose(rng))]
    ms, _ = stream(rng, sources, ["box"], np.arange(5) * 0.05)
    world = World(sources=sources)
    world.publish(ms)
    SE = random_cov(rng)
    new = [Source("cam", sources[0].extrinsic, extrinsic_covariance=SE)]
    world.configure(sources=new, arms={"ur": "cam"}, options=WorldOptions())
    p = world.pose("box")
    f = fuse_of(ms, "box", 0.2, 1.0, new)
    assert np.abs(p.covariance - f.covariance).max() <= 1e-12 * np.abs(f.covariance).max()
    base = world.arm_base("ur")
    assert base.pose.tobytes() == new[0].extrinsic.tobytes()
    np.testing.assert_array_equal(base.covariance, 0.5 * (SE + SE.T))


def test_a_bodys_sources_are_those_that_ever_fed_it_across_configurations():
    """Each source's newest measurement of a body (its horizon's input): kept through a new
    configuration whose buffer no longer holds it, the new tracker's own newer one winning."""
    rng = np.random.default_rng(6)
    world = World(sources=[Source("cam0"), Source("cam1")],
                  options=WorldOptions(window=0.5, buffer=5.0, max_delay=0.0))
    for src, t in (("cam0", 0.1), ("cam1", 0.2), ("cam0", 3.0)):
        assert world.publish([Measurement(src, "box", t, random_pose(rng),
                                          NOISE)]).accepted == 1
    assert world.newest("box", "cam0") == 3.0 and world.newest("box", "cam1") == 0.2
    # a buffer of 1 s: cam1's 0.2 is not brought into the new tracker, yet it fed the body
    world.configure(sources=[Source("cam0"), Source("cam1"), Source("cam2")], arms={},
                    options=WorldOptions(window=0.5, buffer=1.0, max_delay=0.0))
    assert world.publish([Measurement("cam2", "box", 3.1, random_pose(rng), NOISE)]).accepted
    assert sorted(world.sources_of("box")) == ["cam0", "cam1", "cam2"]
    assert (world.newest("box", "cam0"), world.newest("box", "cam1"),
            world.newest("box", "cam2")) == (3.0, 0.2, 3.1)
    with pytest.raises(NotFound, match="source: 'cam3' never fed body 'box'"):
        world.newest("box", "cam3")
