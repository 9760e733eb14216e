"""dqpose.world: the world's fused pose is fuse's over the same measurements, many producers at
once, lookups at past times and their refusals, the bounds, the relative pose's covariance
through shared extrinsics against Monte Carlo, the hand-eye covariance flowing into a pose, arm
bases."""
import threading

import numpy as np
import pytest

from dqpose import dq, fusion, handeye, lie
from dqpose.fusion import Measurement, Source
from dqpose.fusion.alignment import Start
from dqpose.fusion.extrinsics import relative_covariance
from dqpose.lookup import composed_independent
from dqpose.world import (
    NotFound,
    OutOfRange,
    World,
    WorldBounds,
    WorldError,
    WorldOptions,
)
from tests import _handeye
from tests.fusion._scenes import random_cov, random_pose

V = np.array([0.1, -0.2, 0.05, 0.1, 0.02, -0.05])


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


def shared_scene(rng, world, sources, SE):
    """One camera ("top", extrinsic uncertain) sees both bodies twice, a second ("side", exact)
    sees a third body "c"; the true extrinsic of "top" drawn once per trial. Returns the true
    T_a_b."""
    E_true = dq.mul(sources[0].extrinsic, lie.se3_exp(rng.multivariate_normal(np.zeros(6), SE)))
    truth = {"top": E_true, "side": sources[1].extrinsic}
    Xa, Xb, Xc = random_pose(rng, 0.3), random_pose(rng, 0.3), random_pose(rng, 0.3)
    ms = []
    for src, body, X in (("top", "a", Xa), ("top", "b", Xb), ("side", "c", Xc)):
        for _ in range(2):
            c = NOISE
            z = dq.mul(dq.mul(dq.conj(truth[src]), X),
                       lie.se3_exp(-rng.multivariate_normal(np.zeros(6), c)))
            ms.append(Measurement(src, body, 1.0, z, c))
    assert world.publish(ms).accepted == len(ms)
    return dq.mul(dq.conj(Xa), Xb)


NOISE = np.diag([np.deg2rad(0.1)] * 3 + [0.5e-3] * 3) ** 2
EXTRINSIC = np.diag([np.deg2rad(1.0)] * 3 + [5e-3] * 3) ** 2


def relative_nees(trials: int, seed: int = 0):
    """Mean NEES of World.relative("a", "b") and of the composition of the two marginals over
    ``trials`` draws of the shared extrinsic's error and the measurements' noise."""
    rng = np.random.default_rng(seed)
    sources = [Source("top", random_pose(rng), extrinsic_covariance=EXTRINSIC),
               Source("side", random_pose(rng))]
    joint, composed = [], []
    for _ in range(trials):
        world = World(sources=sources)
        T = shared_scene(rng, world, sources, EXTRINSIC)
        r = world.relative("a", "b")
        c = composed_independent("a", "b", r.time, {b: (p.pose, p.covariance) for b, p in
                                          ((b, world.pose(b, r.time)) for b in "ab")})
        for est, out in ((r, joint), (c, composed)):
            e = lie.se3_log(dq.mul(dq.conj(est.pose), T))
            out.append(float(e @ np.linalg.solve(est.covariance, e)))
    return float(np.mean(joint)), float(np.mean(composed))


def test_relative_nees_with_a_shared_extrinsic():
    """A camera with a 1 deg / 5 mm mount uncertainty sees both bodies: the relative pose is
    far better known than either absolute pose. The joint fit's covariance says so (mean NEES
    6 over 500 trials); composing the two marginals ignores the shared error (NEES far below
    6: it claims much less than it knows)."""
    joint, composed = relative_nees(500)
    assert 5.3 <= joint <= 6.7
    assert composed < 1.0


def latency_errors(trials: int, seed: int = 0):
    """One camera, whose latency is uncertain (prior 30 ms +- 20 ms, the truth drawn from it
    per trial), sees two bodies moving together at 0.5 m/s and 0.5 rad/s for 1 s at 30 Hz: a
    latency error moves both poses alike, which cancels in the relative pose. Per trial the
    error of World.relative("a", "b") against the truth; the mean covariance it claims, and the
    one the composition of the two marginals claims."""
    rng = np.random.default_rng(seed)
    cam = Source("cam", random_pose(rng), latency=0.03, latency_sigma=0.02)
    V = np.array([0.3, -0.4, 0.0, 0.5, 0.0, 0.0])
    Xa, C = random_pose(rng, 0.3), random_pose(rng, 0.3)     # b rides on a: X_b = X_a C
    errors, joint, composed = [], [], []
    for _ in range(trials):
        world = World(sources=[cam], options=WorldOptions(window=1.0))
        lag = 0.03 + 0.02 * rng.normal()
        ms = []
        for t in np.arange(31) / 30.0:
            Xt = dq.mul(Xa, lie.se3_exp((t - lag) * V))
            for body, X in (("a", Xt), ("b", dq.mul(Xt, C))):
                z = dq.mul(dq.mul(dq.conj(cam.extrinsic), X),
                           lie.se3_exp(-rng.multivariate_normal(np.zeros(6), NOISE)))
                ms.append(Measurement("cam", body, float(t), z, NOISE))
        assert world.publish(ms).accepted == len(ms)
        r = world.relative("a", "b")
        c = composed_independent("a", "b", r.time, {b: (p.pose, p.covariance) for b, p in
                                          ((b, world.pose(b, r.time)) for b in "ab")})
        errors.append(lie.se3_log(dq.mul(dq.conj(r.pose), C)))
        joint.append(r.covariance)
        composed.append(c.covariance)
    return np.array(errors), np.mean(joint, axis=0), np.mean(composed, axis=0)


def _whitened_spread(errors, cov):
    """The eigenvalues of the errors' second moment whitened by ``cov``: all 1 when ``cov`` is
    their covariance."""
    L = np.linalg.cholesky(cov)
    w = np.linalg.solve(L, errors.T)
    return np.linalg.eigvalsh(w @ w.T / errors.shape[0])


def test_relative_with_a_shared_latency_against_monte_carlo():
    """The joint fit's covariance is the spread of its errors in every direction (300 draws:
    the extreme eigenvalues of a 6-d sample covariance lie within about 0.74-1.30); the
    composition of the marginals claims the latency's error, which cancels, in one direction,
    overstating that variance many times."""
    errors, joint, composed = latency_errors(300)
    spread = _whitened_spread(errors, joint)
    assert 0.6 <= spread.min() and spread.max() <= 1.5, spread
    assert _whitened_spread(errors, composed).min() < 0.05


def test_relative_is_the_inverse_and_world_frame_composition():
    rng = np.random.default_rng(6)
    sources = [Source("top", random_pose(rng), extrinsic_covariance=EXTRINSIC),
               Source("side", random_pose(rng))]
    world = World(sources=sources)
    shared_scene(rng, world, sources, EXTRINSIC)
    ab, ba = world.relative("a", "b"), world.relative("b", "a")
    assert np.abs(dq.mul(ab.pose, ba.pose) - [1, 0, 0, 0, 0, 0, 0, 0]).max() < 1e-12
    np.testing.assert_allclose(lie.cov_inverse(ab.pose, ab.covariance), ba.covariance,
                               rtol=0, atol=1e-9 * np.abs(ba.covariance).max())
    wa = world.relative("", "a")
    pa = world.pose("a")
    same_fit(wa.pose, wa.covariance, pa.pose, pa.covariance)
    for t, s in (("", ""), ("a", "a")):
        same = world.relative(t, s, 1.0)
        assert same.pose.tolist() == [1, 0, 0, 0, 0, 0, 0, 0] and not same.covariance.any()
    aw = world.relative("a", "")
    np.testing.assert_allclose(aw.covariance, lie.cov_inverse(pa.pose, pa.covariance),
                               rtol=0, atol=1e-9 * np.abs(aw.covariance).max())


def test_handeye_covariance_flows_into_a_fused_pose():
    """An eye-to-hand camera's mount from HandEye calibrate (T_base_camera and its covariance)
    as the source's extrinsic: one measurement's fused covariance is the measurement's plus the
    mount's carried to the body, Ad(Z⁻¹) Σ_X Ad(Z⁻¹)ᵀ."""
    s = _handeye.scene(12, "eye_to_hand", seed=3)
    cal = handeye.calibrate(s.base_flange, s.camera_target, "eye_to_hand",
                            camera_covariance=_handeye.covariance((0.1, 0.5)))
    assert np.linalg.eigvalsh(cal.covariance_x).min() > 0
    rng = np.random.default_rng(7)
    z = dq.mul(random_pose(rng, 0.2), lie.se3_exp(np.array([0, 0, 0, 0, 0, 0.8])))
    c = random_cov(rng)
    plain = World(sources=[Source("cam", cal.x)])
    mount = World(sources=[Source("cam", cal.x, extrinsic_covariance=cal.covariance_x)],
                  arms={"ur": "cam"})
    for w in (plain, mount):
        w.publish([Measurement("cam", "box", 0.0, z, c)])
    a, b = plain.pose("box"), mount.pose("box")
    A = lie.adjoint(dq.conj(z))
    np.testing.assert_allclose(a.covariance, c, rtol=1e-12)
    np.testing.assert_allclose(b.covariance - a.covariance, A @ cal.covariance_x @ A.T,
                               rtol=1e-9, atol=1e-18)
    assert a.pose.tobytes() == b.pose.tobytes() or np.abs(a.pose - b.pose).max() < 1e-15
    base = mount.arm_base("ur")
    assert base.body == "arm:ur"
    np.testing.assert_allclose(base.covariance, cal.covariance_x, rtol=1e-12)


def test_relative_equals_gtsam_joint_marginal():
    """The shared-camera scene as GTSAM's graph (a prior on the camera's extrinsic, a
    BetweenFactorPose3 per measurement): its optimum and the joint marginal of both bodies,
    carried to T_a_b, are World.relative's."""
    gtsam = pytest.importorskip("gtsam")
    from tests import _gtsam
    rng = np.random.default_rng(9)
    sources = [Source("top", random_pose(rng), extrinsic_covariance=EXTRINSIC),
               Source("side", random_pose(rng))]
    world = World(sources=sources)
    shared_scene(rng, world, sources, EXTRINSIC)
    # "side" measures "b" too, with an exact extrinsic
    Xb = world.pose("b").pose
    z = dq.mul(dq.conj(sources[1].extrinsic), Xb)
    world.publish([Measurement("side", "b", 1.0, z, NOISE * 4)])
    r = world.relative("a", "b")

    P3, noise = gtsam.Pose3, lambda c: gtsam.noiseModel.Gaussian.Covariance(c, False)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    E = sources[0].extrinsic
    graph.add(gtsam.PriorFactorPose3(2, P3(dq.to_matrix(E)), noise(EXTRINSIC)))
    values.insert(2, P3(dq.to_matrix(E)))
    for key, body in ((0, "a"), (1, "b")):
        for m in world.tracker.measurements(body):
            if m.source == "top":
                graph.add(gtsam.BetweenFactorPose3(2, key, P3(dq.to_matrix(m.pose)),
                                                   noise(m.covariance)))
            else:
                graph.add(gtsam.PriorFactorPose3(key, P3(dq.to_matrix(dq.mul(
                    sources[1].extrinsic, m.pose))), noise(m.covariance)))
        values.insert(key, P3(dq.to_matrix(world.pose(body).pose)))
    result = _gtsam.lm(graph, values)
    for _ in range(100):
        delta = graph.linearize(result).optimize()
        result = result.retract(delta)
        if max(np.linalg.norm(delta.at(k)) for k in (0, 1, 2)) < 1e-13:
            break
    Xa = dq.from_matrix(result.atPose3(0).matrix())
    Xb = dq.from_matrix(result.atPose3(1).matrix())
    keys = gtsam.KeyVector([0, 1])
    P = gtsam.Marginals(graph, result).jointMarginalCovariance(keys).fullMatrix()
    T = dq.mul(dq.conj(Xa), Xb)
    assert np.linalg.norm(lie.se3_log(dq.mul(dq.conj(r.pose), T))) < 1e-10
    J = np.hstack([-lie.adjoint(dq.conj(T)), np.eye(6)])
    expected = J @ P @ J.T
    assert np.abs(r.covariance - expected).max() <= 1e-8 * np.abs(expected).max()


def _two_moving_bodies_one_uncertain_camera() -> World:
    """Bodies "a" and "b" over 0.45 s, both seen by camera "top" (its extrinsic uncertain) and
    by "side"."""
    rng = np.random.default_rng(12)
    sources = [Source("top", random_pose(rng), extrinsic_covariance=EXTRINSIC),
               Source("side", random_pose(rng))]
    world = World(sources=sources, options=WorldOptions(window=1.0))
    ms, _ = stream(rng, sources, ["a", "b"], np.arange(10) * 0.05)
    assert world.publish(ms).accepted == len(ms)
    return world


def test_a_lookup_between_moving_bodies_starts_them_where_their_own_joint_fits_start():
    """Between two moving bodies that an uncertain camera sees, the joint fit starts each body
    from its constant-twist fit (where its own joint fit starts), not from that joint fit: the
    same optimum, to 1e-12, as the joint fit started from the bodies' own fits."""
    world = _two_moving_bodies_one_uncertain_camera()
    at = 0.45
    r = world.relative("a", "b", at)
    rows = [world.rows_for(b, at) for b in "ab"]
    starts = {b: world.tracker.estimate(None, at, rows=r, nis=False, joint=False)
              for b, r in zip("ab", rows)}
    own = {b: world.fit_at(b, at, nis=False) for b in "ab"}
    # the starts are not the bodies' own (joint) fits: this Lookup took the shorter way
    assert min(np.abs(starts[b].mean - own[b].mean).max() for b in "ab") > 1e-9
    (Xa, Xb), P = world.tracker.joint(rows, [own["a"], own["b"]], at)
    T = dq.mul(dq.conj(Xa), Xb)
    assert np.abs(dq.mul(dq.conj(r.pose), T) - [1, 0, 0, 0, 0, 0, 0, 0]).max() < 1e-12
    C = relative_covariance(Xa, Xb, P)
    assert np.abs(r.covariance - C).max() <= 1e-11 * np.abs(C).max()


def test_a_joint_fit_from_a_bodys_lean_start_is_the_one_from_its_full_fit_bit_for_bit():
    """Tracker.estimate's fit="start" gives a body's start for a joint fit without the rest of an
    answer (rejections, verdicts, latencies); the joint fit from it is the joint fit from the full
    constant-twist fit, to the last bit."""
    world = _two_moving_bodies_one_uncertain_camera()
    at = 0.45
    rows = [world.rows_for(b, at) for b in "ab"]
    lean = [world.tracker.estimate(None, at, rows=r, fit="start") for r in rows]
    full = [world.tracker.estimate(None, at, rows=r, nis=False, joint=False) for r in rows]
    assert all(isinstance(s, Start) for s in lean)
    (Xa, Xb), P = world.tracker.joint(rows, lean, at)
    (Ya, Yb), Q = world.tracker.joint(rows, full, at)
    assert (Xa.tobytes(), Xb.tobytes(), P.tobytes()) == (Ya.tobytes(), Yb.tobytes(), Q.tobytes())


def test_measurements_per_body_bound_keeps_the_newest():
    rng = np.random.default_rng(10)
    sources = [Source("cam", random_pose(rng))]
    ms, _ = stream(rng, sources, ["box"], np.arange(10) * 0.1)
    world = World(sources=sources, options=WorldOptions(window=1.0),
                  bounds=WorldBounds(max_measurements_per_body=4))
    assert world.publish(ms).accepted == 10
    p = world.pose("box")
    assert p.fused is not None and len(p.fused.inliers) == 4
    f = fuse_of(ms[6:], "box", 0.9, 1.0, sources)
    assert np.abs(p.pose - f.mean).max() <= 1e-12
    with pytest.raises(OutOfRange, match=r"'box' is known from 0\.6 to 0\.9"):
        world.pose("box", 0.3)


def test_robust_relative_leaves_the_outlier_out_of_the_joint_fit():
    rng = np.random.default_rng(11)
    sources = [Source("top", random_pose(rng), extrinsic_covariance=EXTRINSIC),
               Source("side", random_pose(rng))]
    robust = World(sources=sources, options=WorldOptions(robust=True))
    clean = World(sources=sources)
    state = rng.bit_generator.state
    shared_scene(rng, robust, sources, EXTRINSIC)
    rng.bit_generator.state = state
    shared_scene(rng, clean, sources, EXTRINSIC)
    # one more view of "a" by the top camera, 20 deg and 10 cm off
    z = dq.mul(dq.mul(dq.conj(sources[0].extrinsic), clean.pose("a").pose),
               lie.se3_exp(np.array([0.35, 0, 0, 0.1, 0, 0])))
    for w in (robust, clean):
        w.publish([Measurement("top", "a", 1.0, z, NOISE)])
    assert [r.index for r in robust.pose("a").fused.rejected] == [2]
    a = robust.relative("a", "b")
    clean_world = World(sources=sources)
    rng.bit_generator.state = state
    shared_scene(rng, clean_world, sources, EXTRINSIC)
    b = clean_world.relative("a", "b")
    assert np.abs(a.pose - b.pose).max() < 1e-12
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9,
                               atol=1e-12 * np.abs(b.covariance).max())
