"""dqpose.frames: the world's frame tree. Statics, static bodies and sources as Lookup frames
(their shared chain cancelling exactly, covariances by composition), the namespace, cycles and
bounds refused by name, Publish's refusals, a static body's one constant pose, World.frames."""
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.frames import FrameKind, Static
from dqpose.fusion import Measurement, Source
from dqpose.world import NotFound, World, WorldBounds, WorldError, WorldOptions
from tests.fusion._scenes import random_cov, random_pose

V = np.array([0.1, -0.2, 0.05, 0.1, 0.02, -0.05])
TIMES = np.arange(40) * 0.05          # the moving body's span: 0 .. 1.95 s


def moving(rng, body="box", source="cam", times=TIMES):
    """``body`` moving with twist V, measured by ``source`` (the world frame) at ``times``."""
    X0 = random_pose(rng, 0.5)
    out = []
    for t in times:
        c = random_cov(rng)
        z = dq.mul(dq.mul(X0, lie.se3_exp(t * V)),
                   lie.se3_exp(rng.multivariate_normal(np.zeros(6), c)))
        out.append(Measurement(source, body, float(t), z, c))
    return out


CAM = (Source("cam"),)


def world_of(rng, statics=(), static_bodies=(), sources=CAM, **kw) -> World:
    world = World(sources=sources, options=WorldOptions(window=0.5, **kw))
    world.configure(sources=sources, arms={}, options=world.options, statics=statics,
                    static_bodies=static_bodies)
    return world


def composed(Xa, Pa, Xb, Pb):
    """``T_a^-1 · T_b`` of independent estimates by lie's formulas."""
    Ai = dq.conj(Xa)
    return dq.mul(Ai, Xb), lie.cov_compose(lie.cov_inverse(Xa, Pa), Xb, Pb)


def test_a_static_on_a_body_against_the_body_is_its_own_pose_and_covariance():
    """A static on body ``tool`` looked up against ``tool`` (and the reverse): the static's
    pose and covariance exactly, no body uncertainty (the shared chain cancels); two statics on
    the same body: their own composition, again without the body's."""
    rng = np.random.default_rng(1)
    S, P = random_pose(rng), random_cov(rng)
    S2, P2 = random_pose(rng), random_cov(rng)
    world = world_of(rng, statics=[Static("tool", "tip", S, P), Static("tool", "grip", S2, P2)])
    world.publish(moving(rng, "tool"))
    for at in (0.0, 0.3, 1.95):
        r = world.relative("tool", "tip", at)
        np.testing.assert_allclose(r.pose, S, atol=1e-15)
        np.testing.assert_allclose(r.covariance, P, atol=1e-15)
    back = world.relative("tip", "tool", 0.5)
    np.testing.assert_allclose(dq.mul(back.pose, S), [1, 0, 0, 0, 0, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(back.covariance, lie.cov_inverse(S, P), atol=1e-15)
    X, C = composed(S, P, S2, P2)
    r = world.relative("tip", "grip", 1.0)
    np.testing.assert_allclose(r.pose, X, atol=1e-12)
    np.testing.assert_allclose(r.covariance, C, rtol=1e-12, atol=1e-15)


def test_a_static_of_the_world_against_a_moving_body_at_any_time():
    """A StaticTransform child of the world looked up against a body at any time in its span:
    ``S^-1 · T_world_box(t)``, its covariance the composition of the two (cov_compose); at
    time 0 with only statics involved the answer is at time 0."""
    rng = np.random.default_rng(2)
    S, P = random_pose(rng), random_cov(rng)
    world = world_of(rng, statics=[Static("", "table", S, P)])
    world.publish(moving(rng))
    for at in (0.0, 0.4, 1.0, 1.95):
        box = world.pose("box", at) if at else world.pose("box")
        r = world.relative("table", "box", at)
        X, C = composed(S, P, box.pose, box.covariance)
        assert r.time == box.time
        np.testing.assert_allclose(r.pose, X, atol=1e-12)
        np.testing.assert_allclose(r.covariance, C, rtol=1e-9, atol=1e-15)
    alone = world.relative("", "table")
    assert alone.time == 0.0
    np.testing.assert_allclose(alone.pose, S, atol=1e-15)
    np.testing.assert_allclose(alone.covariance, P, atol=1e-15)
    f = world.frame_pose("table", 123.0)
    np.testing.assert_allclose(f.covariance, P, atol=1e-15)


def test_a_static_body_seen_once_against_a_moving_body_at_any_time_in_its_span():
    """A static body measured once (at 100 s, long after the moving body's span) looked up
    against a moving body at any time of the moving body's span, both ways: its one pose
    composed with the body's fit (covariances independent: composition)."""
    rng = np.random.default_rng(3)
    world = world_of(rng, static_bodies=["shelf"])
    world.publish(moving(rng))
    T, C = random_pose(rng), random_cov(rng)
    world.publish([Measurement("cam", "shelf", 100.0, T, C)])
    for at in (0.05, 0.25, 1.0, 1.95):
        box = world.pose("box", at)
        r = world.relative("shelf", "box", at)
        X, P = composed(T, C, box.pose, box.covariance)
        np.testing.assert_allclose(r.pose, X, atol=1e-12)
        np.testing.assert_allclose(r.covariance, P, rtol=1e-9, atol=1e-15)
        back = world.relative("box", "shelf", at)
        np.testing.assert_allclose(dq.mul(back.pose, r.pose), [1, 0, 0, 0, 0, 0, 0, 0],
                                   atol=1e-12)
    # time 0: the moving body's newest; the static body alone: at any time
    assert world.relative("shelf", "box").time == TIMES[-1]
    p = world.frame_pose("shelf", -5.0)
    np.testing.assert_allclose(p.pose, T, atol=1e-12)
    np.testing.assert_allclose(p.covariance, C, rtol=1e-9)


def test_a_static_body_is_the_one_instant_fit_of_all_its_measurements():
    """A static body's pose is fuse's without times over all its kept measurements (no twist),
    at every time, and a tick (a Subscribe answer) answers that pose."""
    rng = np.random.default_rng(4)
    world = world_of(rng, static_bodies=["shelf"])
    T = random_pose(rng)
    ms = []
    for t in np.arange(10) * 0.7:
        c = random_cov(rng)
        ms.append(Measurement("cam", "shelf", float(t),
                              dq.mul(T, lie.se3_exp(rng.multivariate_normal(np.zeros(6), c))), c))
    world.publish(ms)
    f = fusion.fuse(np.array([m.pose for m in ms]), np.array([m.covariance for m in ms]))
    for at in (-100.0, 3.0, 1e4):
        p = world.relative("", "shelf", at)
        np.testing.assert_allclose(p.pose, f.mean, atol=1e-15)
        np.testing.assert_allclose(p.covariance, f.covariance, atol=1e-15)
    tick, ids = world.tick("shelf", None)
    np.testing.assert_allclose(tick.pose, f.mean, atol=1e-15)
    assert tick.time == ms[-1].time and len(ids) == len(ms)
    assert world.tick_wire("shelf", None, 0) is None        # the tick's own path


def test_a_source_frame_is_its_parent_composed_with_its_extrinsic():
    """A source's frame is ``T_world_parent · extrinsic`` with its extrinsic covariance; a
    static on the source composes on it; the source against the body it measures."""
    rng = np.random.default_rng(5)
    E, PE = random_pose(rng), random_cov(rng)
    S, PS = random_pose(rng), random_cov(rng)
    cam = Source("cam", E, extrinsic_covariance=PE)
    world = world_of(rng, statics=[Static("cam", "lens", S, PS)], sources=(cam, Source("w")))
    world.publish(moving(rng, source="w"))
    p = world.frame_pose("cam", 1.0)
    np.testing.assert_allclose(p.pose, E, atol=1e-15)
    np.testing.assert_allclose(p.covariance, PE, atol=1e-15)
    lens = world.frame_pose("lens", 1.0)
    np.testing.assert_allclose(lens.pose, dq.mul(E, S), atol=1e-12)
    np.testing.assert_allclose(lens.covariance, lie.cov_compose(PE, S, PS), atol=1e-15)
    box = world.pose("box", 1.0)
    r = world.relative("lens", "box", 1.0)
    X, C = composed(lens.pose, lens.covariance, box.pose, box.covariance)
    np.testing.assert_allclose(r.pose, X, atol=1e-12)
    np.testing.assert_allclose(r.covariance, C, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("statics, bodies, match", [
    ([Static("", "t", [2.0, 0, 0, 0, 0, 0, 0, 0])], (),
     r"^statics\[0\]\.pose: "),
    ([Static("", "t", [1.0, 0, 0, 0, 0, 0, 0, 0], -np.eye(6))], (),
     r"^statics\[0\]\.covariance: "),
    ([Static("", "t", [1.0, 0, 0, 0, 0, 0, 0, 0], np.eye(3))], (),
     r"^statics\[0\]\.covariance: expected shape \(6, 6\)"),
    ([Static("", "", [1.0, 0, 0, 0, 0, 0, 0, 0])], (), r"^statics\[0\]\.child: empty"),
    ([Static("", "world", [1.0, 0, 0, 0, 0, 0, 0, 0])], (),
     r"^statics\[0\]\.child: 'world' is reserved"),
    ([Static("world", "t", [1.0, 0, 0, 0, 0, 0, 0, 0])], (),
     r"^statics\[0\]\.parent: 'world' is reserved"),
    ([Static("", "cam", [1.0, 0, 0, 0, 0, 0, 0, 0])], (),
     r"^statics\[0\]\.child: 'cam' is sources\[0\]'s name already"),
    ([Static("", "t", [1.0, 0, 0, 0, 0, 0, 0, 0])], ("t",),
     r"^static_bodies\[0\]: 't' is statics\[0\]'s name already"),
    ([], ("s", "s"), r"^static_bodies\[1\]: 's' is static_bodies\[0\]'s name already"),
    ([Static("b", "a", [1.0, 0, 0, 0, 0, 0, 0, 0]), Static("c", "b", [1.0, 0, 0, 0, 0, 0, 0, 0]),
      Static("a", "c", [1.0, 0, 0, 0, 0, 0, 0, 0])], (),
     r"^statics\[0\]\.parent: the frames 'a' -> 'b' -> 'c' -> 'a' form a cycle"),
    (["not a static"], (), r"^statics\[0\]: expected a Static, got str"),
])
def test_configure_refuses_bad_frames_by_name_and_keeps_the_world(statics, bodies, match):
    rng = np.random.default_rng(6)
    world = world_of(rng)
    world.publish(moving(rng))
    with pytest.raises(WorldError, match=match):
        world.configure(sources=world.sources, arms={}, options=world.options, statics=statics,
                        static_bodies=bodies)
    assert world.tree.statics == () and world.bodies == ("box",)


def test_the_frames_bounds_name_their_field_and_a_source_cycle_names_its_frames():
    rng = np.random.default_rng(7)
    world = World(bounds=WorldBounds(max_statics=2, max_static_bodies=1))
    one = [1.0, 0, 0, 0, 0, 0, 0, 0]
    with pytest.raises(WorldError, match=r"^statics: 3 is above the world's max_statics 2") as e:
        world.configure(sources=(), arms={}, options=world.options,
                        statics=[Static("", f"s{k}", one) for k in range(3)])
    assert e.value.limit == "max_statics"
    with pytest.raises(WorldError, match=r"^static_bodies: 2 is above the world's "
                                         r"max_static_bodies 1"):
        world.configure(sources=(), arms={}, options=world.options, static_bodies=["a", "b"])
    with pytest.raises(WorldError, match=r"the frames 'cam' -> 'mount' -> 'cam' form a cycle"):
        world.configure(sources=[Source("cam", parent="mount")], arms={}, options=world.options,
                        statics=[Static("cam", "mount", one)])
    world.publish(moving(rng))
    with pytest.raises(WorldError, match=r"^statics: 'box' is a body with measurements"):
        world.configure(sources=[Source("cam")], arms={}, options=world.options,
                        statics=[Static("", "box", one)])


def test_publish_refuses_a_static_or_source_as_a_body_and_a_source_measuring_its_carrier():
    rng = np.random.default_rng(8)
    one = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
    world = world_of(rng, statics=[Static("", "table", one)],
                     sources=(Source("cam"), Source("eye", parent="tool"),
                              Source("tip", parent="hand")))
    world.configure(sources=world.sources, arms={}, options=world.options,
                    statics=[Static("", "table", one), Static("tool", "hand", one)])
    got = world.publish([Measurement("cam", "table", 0.0, one), Measurement("cam", "eye", 0.0, one),
                         Measurement("eye", "tool", 0.0, one), Measurement("tip", "tool", 0.0, one),
                         Measurement("eye", "box", 0.0, one),
                         Measurement("cam", "world", 0.0, one)])
    assert [e.named() for e in got.errors] == [
        "measurements[0].body: 'table' is a static (config.statics)",
        "measurements[1].body: 'eye' is a source (config.sources)",
        "measurements[2].source: source 'eye' rides on body 'tool' (its parent chain reaches "
        "it): it cannot measure the body it rides on",
        "measurements[3].source: source 'tip' rides on body 'tool' (its parent chain reaches "
        "it): it cannot measure the body it rides on",
        "measurements[5].body: 'world' is reserved (the world frame is \"\")"]
    assert got.accepted == 1 and world.bodies == ("box",)
    # without statics or riders too
    plain = world_of(rng)
    assert [e.named() for e in plain.publish([Measurement("cam", "world", 0.0, one)]).errors
            ] == ["measurements[0].body: 'world' is reserved (the world frame is \"\")"]


def test_unknown_frames_are_not_found():
    rng = np.random.default_rng(9)
    one = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
    world = world_of(rng, statics=[Static("arm", "tcp", one)], static_bodies=["shelf"])
    world.publish(moving(rng))
    for target in ("tcp", "shelf", "nothing"):
        with pytest.raises(NotFound):
            world.relative(target, "box", 1.0)


def test_frames_lists_every_frame_with_its_kind_parent_span_rate_and_sources():
    rng = np.random.default_rng(10)
    one = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
    world = world_of(rng, statics=[Static("box", "tip", one)], static_bodies=["shelf", "bin"],
                     sources=(Source("cam"), Source("w", parent="tip")))
    world.publish(moving(rng))
    world.publish([Measurement("cam", "shelf", 3.0, one)])
    got = {f.name: f for f in world.frames()}
    assert [f.name for f in world.frames()] == ["", "box", "shelf", "bin", "cam", "w", "tip"]
    assert got[""].kind == FrameKind.WORLD
    box = got["box"]
    assert (box.kind, box.parent, box.oldest, box.newest, box.sources) == (
        FrameKind.BODY, "", 0.0, TIMES[-1], ("cam",))
    # measurements taken in [newest - 1, newest]: 21 of one every 0.05 s
    assert box.rate_hz == np.count_nonzero(TIMES >= TIMES[-1] - 1.0)
    assert (got["shelf"].kind, got["shelf"].oldest, got["shelf"].newest) == (
        FrameKind.STATIC_BODY, 3.0, 3.0)
    assert (got["bin"].kind, got["bin"].newest, got["bin"].sources) == (
        FrameKind.STATIC_BODY, 0.0, ())
    assert (got["w"].kind, got["w"].parent) == (FrameKind.SOURCE, "tip")
    assert (got["tip"].kind, got["tip"].parent, got["tip"].newest) == (FrameKind.STATIC, "box",
                                                                       0.0)


def test_a_static_body_seen_by_a_camera_riding_on_a_moving_tool():
    """A static body measured by a camera on the tool (a rider): each row composed with the
    tool's fit at its time, then the one-instant fit: without noise the box itself to 1e-9 at
    any time (before the measurements too); its covariance carries the hand-eye X's."""
    from tests.test_riders import BOX, COV_X, scene
    from tests.test_riders import world as rider_world
    w = rider_world()
    w.configure(sources=w.sources, arms={}, options=w.options, static_bodies=["box"])
    assert w.publish(scene()).accepted == len(scene())
    for at in (0.0, 10.1, 500.0):
        p = w.frame_pose("box", at)
        np.testing.assert_allclose(p.pose * np.sign(p.pose[0]), BOX, rtol=0, atol=1e-9)
    tick, ids = w.tick("box", None)
    np.testing.assert_allclose(tick.pose * np.sign(tick.pose[0]), BOX, rtol=0, atol=1e-9)
    # the camera's mount error is shared by every row: it stays in the covariance
    # (the rotation block's trace: rotated, never averaged away)
    assert np.trace(tick.covariance[:3, :3]) >= np.trace(COV_X[:3, :3]) * (1 - 1e-9)


def test_subscribe_answers_relative_to_a_static_and_a_static_bodys_one_pose():
    """A hub's Subscribe answers (the server's FusedPose bytes) relative to a static: the body's
    tick composed with the static; a static body's answer: its one pose."""
    from dqpose.hub import Hub, Interest, Rows, Subscription
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc.world_convert import Encoder
    rng = np.random.default_rng(12)
    S = random_pose(rng)
    hub = Hub("", Encoder())
    hub.configure([Source("cam")], {}, WorldOptions(window=0.5), statics=[
        Static("", "table", S)], static_bodies=["shelf"])
    got: list = []
    hub.subscribe(Subscription(Interest(None, 0.0, "table"), got.extend))
    ms = moving(rng) + [Measurement("cam", "shelf", 0.3, random_pose(rng), random_cov(rng))]
    ms.sort(key=lambda m: m.time)
    for m in ms:
        rows = Rows(np.arange(1), (m.body,), (m.source,), np.array([m.time]), m.pose[None],
                    m.covariance[None], None)
        hub.publish("p", "a", 0, rows, 1)
    answers = [fpb.FusedPose.FromString(a) for a in got]
    assert not [a.error.details for a in answers if a.error.details]
    last = {a.body: a for a in answers}
    for body in ("box", "shelf"):
        a = last[body]
        want = hub.world.relative("table", body, a.time)
        pose = dq.from_pose([a.pose.orientation.w, a.pose.orientation.x, a.pose.orientation.y,
                             a.pose.orientation.z],
                            [a.pose.position.x, a.pose.position.y, a.pose.position.z])
        np.testing.assert_allclose(pose * np.sign(pose[0] * want.pose[0]), want.pose,
                                   atol=1e-9)
        np.testing.assert_allclose(np.reshape(a.covariance, (6, 6)), want.covariance,
                                   rtol=1e-9, atol=1e-15)
    assert last["shelf"].time == 0.3 and last["box"].time == TIMES[-1]


def test_a_world_without_statics_or_riders_keeps_a_body_named_as_a_source():
    """Without statics or riders a body may share a source's name, as before the frame tree:
    Publish and Configure take it, a Lookup of the name is the body's."""
    rng = np.random.default_rng(13)
    world = world_of(rng, sources=(Source("cam"), Source("ur", random_pose(rng))))
    assert world.publish(moving(rng, body="ur")).accepted == len(TIMES)
    world.configure(sources=world.sources, arms={}, options=world.options)
    np.testing.assert_allclose(world.relative("", "ur", 1.0).pose, world.pose("ur", 1.0).pose,
                               atol=1e-12)


def test_a_watched_lookup_of_a_static_on_a_body_is_made_again_by_the_bodys_publish():
    """A pair polled at time 0 whose frame is a static on a body: the Publish step that brings
    the body's measurements makes its answer again (the hub's kept answer, no fit when asked)."""
    from dqpose.hub import Hub, Rows
    from dqpose.rpc.world_convert import Encoder
    rng = np.random.default_rng(14)
    hub = Hub("", Encoder())
    hub.configure([Source("cam")], {}, WorldOptions(window=0.5),
                  statics=[Static("box", "tip", random_pose(rng))])

    def publish(m):
        hub.publish("p", "a", 0, Rows(np.arange(1), (m.body,), (m.source,), np.array([m.time]),
                                      m.pose[None], m.covariance[None], None), 1)

    ms = moving(rng)
    for m in ms[:-1]:
        publish(m)
    first = hub.lookup("", "tip", 0.0)
    assert hub.kept("", "tip") == first
    publish(ms[-1])
    again = hub.kept("", "tip")
    assert again is not None and again != first
    assert again == hub.answers.encode(hub.world.relative("", "tip", 0.0))
