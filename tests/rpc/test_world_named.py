"""Named worlds on one real server (``x-dqpose-world``): two worlds keep their bodies, acks,
configurations and counters apart; the number of worlds is bounded; a world never made is
NOT_FOUND for Lookup and a Plan's frame; a malformed header is refused by every World RPC."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.rpc import routing
from dqpose.rpc import world as world_service
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client import Client, RpcError
from dqpose.trajectory import Limits, Waypoint
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_world_service import SOURCES, TWIST, Collector, measurements


@pytest.fixture
def server():
    with ServerThread(replica_name="replica-n") as s:
        yield s


def _cells(server):
    return server.running.servicers[0].hubs


def test_two_worlds_on_one_server_do_not_see_each_others_bodies(server):
    with Client(server.target, world="hall-a") as a, Client(server.target, world="hall-b") as b, \
            Client(server.target) as default:
        config_a = a.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
        assert b.configure_world(SOURCES, window=2.0).options.window == 2.0
        assert config_a.options.window == 10.0        # b's Configure left a's alone
        sub_a = Collector(server.target, world="hall-a")
        sub_b = Collector(server.target, world="hall-b")
        assert wait_until(lambda: all(_cells(server)[w].subscriptions
                                      for w in ("hall-a", "hall-b")), timeout=10)
        # one producer name in both worlds: each world acks its own sequence 1
        assert list(a.publish([measurements("cam1", [0.0, 0.01], 1)], producer="p")) == [(1, ())]
        assert list(b.publish([measurements("cam1", [0.0, 0.01], 2, body="cup")],
                              producer="p")) == [(1, ())]
        assert a.lookup("", "box").time == 0.01
        for client, absent in ((a, "cup"), (b, "box"), (default, "box")):
            with pytest.raises(RpcError) as e:
                client.lookup("", absent)
            assert e.value.code == grpc.StatusCode.NOT_FOUND and repr(absent) in e.value.details
        assert wait_until(lambda: sub_a.answers and sub_b.answers, timeout=30)
        answers_a, answers_b = sub_a.stop(), sub_b.stop()
    assert {x.body for x in answers_a} == {"box"} and {x.body for x in answers_b} == {"cup"}
    # each world numbers its own requests from 0
    assert answers_a[0].request == 0 and answers_b[0].request == 0
    assert set(_cells(server)) == {"", "hall-a", "hall-b"}


def test_a_plans_frame_resolves_through_the_world_its_call_names(server):
    with Client(server.target, world="hall-a") as a, Client(server.target) as default, \
            Client(server.target, world="never-made") as unknown:
        a.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
        list(a.publish([measurements("cam1", [0.0, 0.01, 0.02], 1)], producer="p"))
        limits = Limits(0.5, 1.0, 1.0, 2.0)
        above = dq.from_pose([1.0, 0, 0, 0], [0.0, 0.0, 0.1])
        start = dq.from_pose([1.0, 0, 0, 0], [0.3, 0.0, 0.3])
        waypoints = [Waypoint(start), Waypoint(above)]
        planned = a.plan(waypoints, limits, 100.0, frames=["", "box"])
        want = dq.mul(a.lookup("", "box").pose, above)
        pose = planned.resolved[0][3]
        np.testing.assert_allclose(pose * np.sign(pose[0] * want[0]), want, atol=1e-12)
        # the default world has no box; a world never made is named
        with pytest.raises(RpcError) as e:
            default.plan(waypoints, limits, 100.0, frames=["", "box"])
        assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "waypoints[1].frame: body 'box'" in e.value.details
        with pytest.raises(RpcError) as e:
            unknown.plan(waypoints, limits, 100.0, frames=["", "box"])
        assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert e.value.details.startswith(
            "waypoints[1].frame: x-dqpose-world: no world 'never-made' on replica 'replica-n'")
    assert "never-made" not in _cells(server)


def test_lookup_in_a_world_never_made_is_not_found_and_makes_none(server):
    with Client(server.target, world="never-made") as c:
        with pytest.raises(RpcError) as e:
            c.lookup("", "box")
    assert e.value.code == grpc.StatusCode.NOT_FOUND
    assert e.value.details.startswith("x-dqpose-world: no world 'never-made' on replica "
                                      "'replica-n'")
    assert "never-made" not in _cells(server)


def test_publish_and_subscribe_make_their_world(server):
    """A world's producers and subscribers may reach a replica before its Configure (a world
    that moved): both find it there."""
    with Client(server.target, world="moved") as c:
        sub = Collector(server.target, world="moved")
        assert wait_until(lambda: "moved" in _cells(server)
                          and _cells(server)["moved"].subscriptions, timeout=10)
        assert list(c.publish([measurements("cam1", [0.0], 1)], producer="p", first_sequence=7)) \
            == [(7, ())]     # a producer's first request here names no gap before it
        assert wait_until(lambda: sub.answers, timeout=30)
        sub.stop()
        assert c.lookup("", "box").time == 0.0


def test_worlds_past_the_bound_are_refused_before_any_is_made(server, monkeypatch):
    monkeypatch.setattr(world_service, "MAX_WORLDS", 2)
    for name in ("w0", "w1"):
        with Client(server.target, world=name) as c:
            c.configure_world(SOURCES)
    made = set(_cells(server))
    with Client(server.target, world="w2") as c:
        with pytest.raises(RpcError) as e:
            c.configure_world(SOURCES)
        assert e.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert e.value.details == ("x-dqpose-world: world 'w2' would be named world 3 on replica "
                                   "'replica-n', above its 2 (MAX_WORLDS)")
        with pytest.raises(RpcError) as e:
            list(c.publish([measurements("cam1", [0.0], 1)], producer="p"))
        assert e.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
        with pytest.raises(RpcError) as e:
            next(c.subscribe())
        assert e.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert set(_cells(server)) == made
    # the default world is not one of them, and the worlds made go on
    with Client(server.target) as default, Client(server.target, world="w1") as w1:
        assert list(default.publish([measurements("cam1", [0.0], 1)], producer="p")) == [(1, ())]
        assert list(w1.publish([measurements("cam1", [0.0], 1)], producer="p")) == [(1, ())]


@pytest.mark.parametrize("value, problem", [
    ("a b", "x-dqpose-world: only printable ASCII without spaces, got 'a b'"),
    ("w" * 129, "x-dqpose-world: 129 characters, over the 128 allowed")])
def test_a_malformed_world_header_is_refused_by_every_rpc(server, value, problem):
    md = [(routing.WORLD_HEADER, value)]
    with grpc.insecure_channel(server.target) as ch:
        calls = {
            "Configure": lambda: ch.unary_unary("/dqpose.v1.World/Configure")(
                wpb.WorldConfig().SerializeToString(), metadata=md, timeout=10),
            "Lookup": lambda: ch.unary_unary("/dqpose.v1.World/Lookup")(
                wpb.LookupRequest().SerializeToString(), metadata=md, timeout=10),
            "Publish": lambda: list(ch.stream_stream("/dqpose.v1.World/Publish")(
                iter([wpb.PublishRequest().SerializeToString()]), metadata=md, timeout=10)),
            "Subscribe": lambda: list(ch.unary_stream("/dqpose.v1.World/Subscribe")(
                wpb.SubscribeRequest().SerializeToString(), metadata=md, timeout=10)),
            "Plan": lambda: list(ch.unary_stream("/dqpose.v1.Trajectories/Plan")(
                _framed_plan(), metadata=md, timeout=10)),
        }
        for rpc, call in calls.items():
            with pytest.raises(grpc.RpcError) as e:
                call()
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, rpc
            assert e.value.details() == problem, rpc
    assert set(_cells(server)) <= {""}


def _framed_plan() -> bytes:
    from dqpose.rpc.trajectories_convert import plan_msg
    start = dq.from_pose([1.0, 0, 0, 0], [0.3, 0.0, 0.3])
    msg: tpb.PlanRequest = plan_msg([Waypoint(start), Waypoint(start)],
                                    Limits(0.5, 1.0, 1.0, 2.0), 100.0, "tool_linear", None,
                                    ["", "box"])
    return msg.SerializeToString()
