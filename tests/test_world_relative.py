"""dqpose.world's relative poses: the covariance of two bodies through a shared extrinsic or a
shared latency against Monte Carlo, the inverse and the world frame, the hand-eye covariance
flowing into a pose, GTSAM's joint marginal, joint fits' starts, the bound of measurements a
body, a robust relative pose."""
import numpy as np
import pytest

from dqpose import dq, handeye, lie
from dqpose.fusion import Measurement, Source
from dqpose.fusion.alignment import Start
from dqpose.fusion.extrinsics import relative_covariance
from dqpose.lookup import composed_independent
from dqpose.world import OutOfRange, World, WorldBounds, WorldOptions
from tests import _handeye
from tests.fusion._scenes import random_cov, random_pose
from tests.test_world import EXTRINSIC, NOISE, fuse_of, same_fit, stream


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
