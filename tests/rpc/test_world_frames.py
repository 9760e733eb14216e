"""The world's frame tree over gRPC, a real server on 127.0.0.1: Configure's statics and static
bodies (echoed, refused by field path, bounded), Lookup of statics and static bodies against a
moving body, Publish's namespace refusals, ListFrames and its NOT_FOUND."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.frames import FrameKind, Static
from dqpose.fusion import Source
from dqpose.rpc.client import Batch, Client, RpcError
from tests.rpc._grpc_server import ServerThread

SIGMA = np.diag([1e-3] * 6) ** 2
TABLE = dq.from_pose([np.cos(0.3), 0, 0, np.sin(0.3)], [1.0, 0.5, 0.0])
TABLE_COV = np.diag([1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 3e-3])
TIP = dq.from_pose([1.0, 0, 0, 0], [0.0, 0.0, 0.1])


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


def client(server, world: str, **kw) -> Client:
    c = Client(server.target, world=world)
    c.configure_world([Source("cam")], window=0.5, statics=[
        Static("", "table", TABLE, TABLE_COV), Static("box", "tip", TIP)],
        static_bodies=["shelf"], **kw)
    return c


def box(times, seed=0, body="box") -> Batch:
    """``body`` moving along x at 0.1 m/s, measured by ``cam`` (the world frame) at ``times``."""
    rng = np.random.default_rng(seed)
    poses = np.array([dq.mul(dq.from_pose([1.0, 0, 0, 0], [0.1 * t, 0.2, 0.3]),
                             lie.se3_exp(rng.multivariate_normal(np.zeros(6), SIGMA)))
                      for t in times])
    n = len(times)
    return Batch(poses, np.repeat(SIGMA[None], n, 0), None, ["cam"] * n, [body] * n,
                 np.asarray(times, dtype=np.float64))


def test_configure_echoes_the_frames_and_refuses_them_by_field_path(server):
    with client(server, "f-configure") as c:
        got = c.configure_world([Source("cam")], statics=[Static("", "table", TABLE, TABLE_COV)],
                                static_bodies=["shelf"])
        assert [(s.parent, s.child, len(s.covariance)) for s in got.statics] == [
            ("", "table", 36)]
        assert list(got.static_bodies) == ["shelf"]
        for statics, code, text in [
            ([Static("", "t", TABLE, -TABLE_COV)], grpc.StatusCode.INVALID_ARGUMENT,
             "config.statics[0].covariance: "),
            ([Static("", "cam", TABLE)], grpc.StatusCode.INVALID_ARGUMENT,
             "config.statics[0].child: 'cam' is sources[0]'s name already"),
            ([Static("b", "a", TABLE), Static("a", "b", TABLE)], grpc.StatusCode.INVALID_ARGUMENT,
             "config.statics[0].parent: the frames 'a' -> 'b' -> 'a' form a cycle"),
            ([Static("", f"s{k}", TABLE) for k in range(1001)],
             grpc.StatusCode.RESOURCE_EXHAUSTED,
             "config.statics: 1001 is above the world's max_statics 1000"),
        ]:
            with pytest.raises(RpcError) as e:
                c.configure_world([Source("cam")], statics=statics)
            assert e.value.code == code and e.value.details.startswith(text), e.value.details
        from dqpose.rpc.world_convert import world_config
        for mutate, text in [(lambda m: m.statics.add(child="t"),
                              "config.statics[1].pose: required (T_parent_child)"),
                             (lambda m: m.statics[0].covariance.extend([1.0] * 3),
                              "config.statics[0].covariance: expected 36 values"),
                             (lambda m: m.static_bodies.append("a/b"),
                              "config.static_bodies[1]: 'a/b' has '/'")]:
            msg = world_config([Source("cam")], statics=[Static("", "table", TABLE, TABLE_COV)],
                               static_bodies=["shelf"])
            mutate(msg)
            with pytest.raises(RpcError) as e:
                c.configure_world_msg(msg)
            assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
            assert e.value.details.startswith(text), e.value.details
        # the world kept its frames
        assert {f.name for f in c.frames()} == {"", "cam", "table", "shelf"}


def test_lookup_resolves_statics_and_a_static_body_against_a_moving_body(server):
    with client(server, "f-lookup") as c:
        assert not any(a.errors for a in c.publish([box(np.arange(20) * 0.05)]))
        assert not any(a.errors for a in c.publish([box([30.0], 1, "shelf")]))
        for at in (0.2, 0.9):
            body = c.lookup("", "box", at)
            r = c.lookup("table", "box", at)
            np.testing.assert_allclose(r.pose, dq.mul(dq.conj(TABLE), body.pose), atol=1e-9)
            np.testing.assert_allclose(
                r.covariance, lie.cov_compose(lie.cov_inverse(TABLE, TABLE_COV), body.pose,
                                              body.covariance), rtol=1e-6, atol=1e-15)
            shelf = c.lookup("", "shelf", at)
            np.testing.assert_allclose(c.lookup("shelf", "box", at).pose,
                                       dq.mul(dq.conj(shelf.pose), body.pose), atol=1e-9)
            tip = c.lookup("box", "tip", at)      # the shared body cancels: exact
            np.testing.assert_allclose(tip.pose, TIP, atol=1e-12)
            assert not tip.covariance.any()
        assert c.lookup("", "table").time == 0.0


def test_publish_refuses_a_static_as_a_body(server):
    with client(server, "f-publish") as c:
        acks = list(c.publish([box([0.0], 0, "table")]))
        assert [e[2] for e in acks[0].errors] == [
            "requests[0].measurements[0].body: 'table' is a static (config.statics)"]
    with Client(server.target, world="f-plain") as c:      # no statics: "world" still refused
        acks = list(c.publish([box([0.0, 0.1], 0, "world")]))
        assert [e[2] for e in acks[0].errors] == [
            f"requests[0].measurements[{i}].body: 'world' is reserved (the world frame is \"\")"
            for i in range(2)]


def test_list_frames_names_every_frame_and_an_unknown_world_is_not_found(server):
    with client(server, "f-list") as c:
        list(c.publish([box(np.arange(48) / 32)]))     # exact binary times
        frames = {f.name: f for f in c.frames()}
        assert [frames[n].kind for n in ("", "box", "shelf", "cam", "table", "tip")] == [
            FrameKind.WORLD, FrameKind.BODY, FrameKind.STATIC_BODY, FrameKind.SOURCE,
            FrameKind.STATIC, FrameKind.STATIC]
        b = frames["box"]
        # measurement time [15/32, 47/32]: 33 measurements in the second before the newest
        assert (b.oldest, b.newest, b.rate_hz, b.sources) == (0.0, 47 / 32, 33.0, ("cam",))
        assert frames["tip"].parent == "box"
        list(c.publish([box([2.0], 1)]))       # a frame's bytes kept only while it holds
        again = {f.name: f for f in c.frames()}
        assert (again["box"].newest, again["box"].rate_hz) == (2.0, 17.0)
        assert again["table"] == frames["table"]
    with Client(server.target, world="f-nowhere") as c:
        with pytest.raises(RpcError) as e:
            c.frames()
        assert e.value.code == grpc.StatusCode.NOT_FOUND
