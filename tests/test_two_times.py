"""tf2's advanced lookup (dqpose.two_times): the target at one time, the source at another,
through a fixed frame, with a covariance that knows what the two fits share."""
import numpy as np
import pytest

from dqpose import dq, lie, two_times
from dqpose.world import Measurement, NotFound, OutOfRange, Source, World, WorldError, WorldOptions

NOISE = np.diag([np.deg2rad(0.2)] * 3 + [1e-3] * 3) ** 2
#: the body's constant body twist (rad/s, m/s), rotation first
TWIST = np.array([0.2, -0.1, 0.3, 0.3, 0.1, -0.2])
RATE = 30.0


def moving_world(rng, T0, seconds: float = 2.0, bodies=("arm",)) -> World:
    """Bodies moving at ``TWIST`` from ``T0`` (each its own start: T0 then shifted), seen by one
    camera at ``RATE`` Hz for ``seconds``, the noise ``NOISE`` (X = Z Exp(xi))."""
    world = World(sources=[Source("cam")], options=WorldOptions(window=1.0, buffer=10.0))
    ms = []
    for t in np.arange(int(seconds * RATE) + 1) / RATE:
        for k, b in enumerate(bodies):
            X = truth(T0, t, k)
            z = dq.mul(X, lie.se3_exp(-rng.multivariate_normal(np.zeros(6), NOISE)))
            ms.append(Measurement("cam", b, float(t), z, NOISE))
    assert world.publish(ms).accepted == len(ms)
    return world


def truth(T0, t: float, k: int = 0) -> np.ndarray:
    start = dq.mul(T0, lie.se3_exp(np.array([0, 0, 0, 0.5 * k, 0, 0])))
    return dq.mul(start, lie.se3_exp(t * TWIST * (1 - 0.5 * k)))


def nees(pose, cov, T) -> float:
    e = lie.se3_log(dq.mul(dq.conj(pose), T))
    return float(e @ np.linalg.solve(cov, e))


def two_time_nees(trials: int, seed: int = 0, t: float = 1.2, s: float = 1.5):
    """Mean NEES of T_arm(t)_arm(s) (the fits' windows share most rows) over ``trials``: with
    the shared rows' cross-covariance, and with the fits taken as independent."""
    rng = np.random.default_rng(seed)
    T0 = lie.se3_exp(rng.normal(size=6) * 0.5)
    joint, naive = [], []
    for _ in range(trials):
        world = moving_world(rng, T0)
        r = world.relative_at("arm", t, "arm", s)
        T = dq.mul(dq.conj(truth(T0, t)), truth(T0, s))
        a, b = two_times._fit(world, "arm", t), two_times._fit(world, "arm", s)
        _, independent = two_times._compose([(a, True), (b, False)], shared=False)
        joint.append(nees(r.pose, r.covariance, T))
        naive.append(nees(r.pose, independent, T))
    return float(np.mean(joint)), float(np.mean(naive))


def test_nees_is_six_where_both_times_share_measurements():
    """A body's fits at 1.2 s and 1.5 s (1 s windows: 70% of their rows shared): mean NEES 6
    over 200 seeded trials with the cross-covariance of the shared rows; composing the two as
    independent claims far more uncertainty than there is (NEES well below 6)."""
    joint, naive = two_time_nees(200)
    assert 6.0 - 0.7 <= joint <= 6.0 + 0.7
    assert naive < 4.0


def test_one_time_is_the_lookup_and_disjoint_windows_are_independent():
    rng = np.random.default_rng(3)
    T0 = lie.se3_exp(rng.normal(size=6) * 0.5)
    world = moving_world(rng, T0, seconds=4.0, bodies=("arm", "box"))
    at = world.relative_at("arm", 1.0, "box", 0.0)       # source_time 0: time
    one = world.relative("arm", "box", 1.0)
    np.testing.assert_array_equal(at.pose, one.pose)
    np.testing.assert_array_equal(at.covariance, one.covariance)
    # windows [0.5, 1.5] and [2.5, 3.5]: nothing shared, the independent composition
    a, b = two_times._fit(world, "arm", 1.0), two_times._fit(world, "arm", 3.0)
    np.testing.assert_array_equal(two_times.cross_covariance(a, b), np.zeros((6, 6)))
    r = world.relative_at("arm", 1.0, "arm", 3.0)
    expect = lie.cov_compose(lie.cov_inverse(a.pose, a.covariance), b.pose, b.covariance)
    np.testing.assert_allclose(r.covariance, expect, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(r.pose, dq.mul(dq.conj(a.pose), b.pose), atol=1e-12)


def test_a_fixed_frame_composes_through_it_and_time_zero_is_the_newest_both_know():
    rng = np.random.default_rng(4)
    T0 = lie.se3_exp(rng.normal(size=6) * 0.5)
    world = moving_world(rng, T0, seconds=2.0, bodies=("arm", "box"))
    # through the world: T_arm(t)_w T_w_box(s); through box itself: T_arm_box(t) (box held)
    via_world = world.relative_at("arm", 1.2, "box", 1.5)
    Ta, Tb = world.pose("arm", 1.2), world.pose("box", 1.5)
    np.testing.assert_allclose(via_world.pose, dq.mul(dq.conj(Ta.pose), Tb.pose), atol=1e-12)
    via_box = world.relative_at("arm", 1.2, "box", 1.5, fixed="box")
    rel = world.relative("arm", "box", 1.2)
    np.testing.assert_allclose(via_box.pose, rel.pose, atol=1e-9)
    assert via_box.time == 1.2
    # time 0: the newest both are known at (2 s), source_time 1.5
    r0 = world.relative_at("arm", 0.0, "box", 1.5)
    assert r0.time == pytest.approx(2.0)
    # the world to a body at another time: the body's own pose
    w = world.relative_at("", 1.2, "box", 1.5)
    np.testing.assert_allclose(w.pose, Tb.pose, atol=1e-12)
    np.testing.assert_allclose(w.covariance, Tb.covariance, rtol=1e-9, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(via_box.covariance) > 0)


def test_refusals_name_the_field():
    rng = np.random.default_rng(5)
    world = moving_world(rng, lie.se3_exp(np.zeros(6)), seconds=1.0)
    with pytest.raises(NotFound, match="'ghost'"):
        world.relative_at("arm", 0.5, "arm", 0.8, fixed="ghost")
    with pytest.raises(OutOfRange, match="past the newest measurement"):
        world.relative_at("arm", 0.5, "arm", 3.0)
    with pytest.raises(WorldError, match="source_time"):
        world.relative_at("arm", 0.5, "arm", float("nan"))
    with pytest.raises(WorldError, match="fixed_frame"):
        world.relative_at("arm", 0.5, "arm", 0.8, fixed="a/b")


def test_frames_of_the_tree_at_two_times():
    """A static "corner" on a static body "table", a camera riding on "arm": the table held
    still, the corner at any time is where it is now; a frame fixed on a body holds that body
    still; its offset cancels."""
    from dqpose.frames import Static

    rng = np.random.default_rng(6)
    T0 = lie.se3_exp(rng.normal(size=6) * 0.5)
    world = moving_world(rng, T0, seconds=2.0, bodies=("arm", "table"))
    corner = lie.se3_exp(np.array([0.0, 0.0, 0.3, 0.2, 0.1, 0.0]))
    world.configure(sources=[Source("cam"), Source("wrist", corner, parent="arm")], arms={},
                    options=WorldOptions(window=1.0, buffer=10.0),
                    statics=[Static("table", "corner", corner, NOISE)], static_bodies=["table"])
    via_table = world.relative_at("arm", 1.2, "corner", 1.6, fixed="table")
    now = world.relative("arm", "corner", 1.2)
    np.testing.assert_allclose(via_table.pose, now.pose, atol=1e-12)
    np.testing.assert_allclose(via_table.covariance, now.covariance, rtol=1e-9, atol=1e-15)
    # through the camera on arm: arm held still, the same answer as through arm itself
    via_wrist = world.relative_at("corner", 1.2, "arm", 1.6, fixed="wrist")
    via_arm = world.relative_at("corner", 1.2, "arm", 1.6, fixed="arm")
    np.testing.assert_allclose(via_wrist.pose, via_arm.pose, atol=1e-12)
    np.testing.assert_allclose(via_wrist.covariance, via_arm.covariance, rtol=1e-9, atol=1e-15)
    # the wrist camera at two times against the world: arm's two fits and its offset
    w = world.relative_at("", 1.2, "wrist", 1.6)
    np.testing.assert_allclose(w.pose, world.frame_pose("wrist", 1.6).pose, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(w.covariance) > 0)
    # a body seen by the camera on arm (a rider): its fits at two times taken as independent
    box = lie.se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.4, 0.0]))
    assert world.publish([Measurement("wrist", "box", float(tk), box, NOISE)
                          for tk in np.arange(61) / RATE]).accepted == 61
    r = world.relative_at("box", 1.2, "box", 1.6)
    a, b = world.pose("box", 1.2), world.pose("box", 1.6)
    expect = lie.cov_compose(lie.cov_inverse(a.pose, a.covariance), b.pose, b.covariance)
    np.testing.assert_allclose(r.covariance, expect, rtol=1e-9, atol=1e-15)


EXTRINSIC = np.diag([np.deg2rad(1.0)] * 3 + [5e-3] * 3) ** 2


def mounted_nees(trials: int, seed: int = 0, t: float = 1.2, s: float = 1.6):
    """Mean NEES of T_arm(t)_arm(s) seen by a camera whose mount is uncertain (1 deg, 5 mm; the
    true mount drawn per trial): both fits estimate the same mount error, which cancels in the
    relative pose; with the shared rows and the shared prior, and with the rows alone."""
    rng = np.random.default_rng(seed)
    T0 = lie.se3_exp(rng.normal(size=6) * 0.5)
    E = lie.se3_exp(rng.normal(size=6) * 0.5)
    cam = Source("cam", E, extrinsic_covariance=EXTRINSIC)
    joint, rows_only = [], []
    for _ in range(trials):
        E_true = dq.mul(E, lie.se3_exp(rng.multivariate_normal(np.zeros(6), EXTRINSIC)))
        world = World(sources=[cam], options=WorldOptions(window=1.0, buffer=10.0))
        ms = []
        for tk in np.arange(int(2.0 * RATE) + 1) / RATE:
            z = dq.mul(dq.mul(dq.conj(E_true), truth(T0, tk)),
                       lie.se3_exp(-rng.multivariate_normal(np.zeros(6), NOISE)))
            ms.append(Measurement("cam", "arm", float(tk), z, NOISE))
        assert world.publish(ms).accepted == len(ms)
        r = world.relative_at("arm", t, "arm", s)
        T = dq.mul(dq.conj(truth(T0, t)), truth(T0, s))
        a, b = two_times._fit(world, "arm", t), two_times._fit(world, "arm", s)
        _, without = two_times._compose([(a._replace(priors=()), True),
                                         (b._replace(priors=()), False)])
        joint.append(nees(r.pose, r.covariance, T))
        rows_only.append(nees(r.pose, without, T))
    return float(np.mean(joint)), float(np.mean(rows_only))


def test_nees_is_six_where_both_times_share_an_uncertain_mount():
    """The mount's error is one error both fits estimate: with its prior's shared term the
    covariance is honest (mean NEES 6 over 200 trials); with the shared rows alone it keeps
    the mount's uncertainty that cancels, far more than there is."""
    joint, rows_only = mounted_nees(200)
    assert 6.0 - 0.7 <= joint <= 6.0 + 0.7
    assert rows_only < 3.0
