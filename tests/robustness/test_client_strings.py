"""Every string a client sends is a name within dqpose.names' rule (1-128 bytes of UTF-8, no
control character, no "/"), refused naming its field otherwise, and no refusal's text grows with
what a client sent (at most calls.MAX_DETAILS bytes): against a real server on 127.0.0.1, on
each RPC that takes a name. Before the bound one 1 MB body name made every NOT_FOUND Lookup of
its world reach the client as RESOURCE_EXHAUSTED ("received metadata size exceeds hard
limit")."""
from __future__ import annotations

import itertools

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.fusion import Source
from dqpose.rpc.calls import MAX_DETAILS
from dqpose.rpc.client import Batch, Client, RpcError
from dqpose.trajectory import Limits, Waypoint
from tests.rpc._grpc_server import ServerThread

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
# a name over the byte bound in ASCII (the C decoder's) and in UTF-8 (protobuf's), one with "/"
# (a recording's topics), one with a control character
BAD = {"1MB": "x" * 10**6, "129B": "\u00e9" * 64 + "x", "slash": "a/stats",
       "control": "a\x00b"}
WORLDS = itertools.count()


def batch(body: str = "box", source: str = "cam", t: float = 0.0) -> Batch:
    return Batch(IDENTITY[None], np.eye(6)[None] * 1e-4, None, [source], [body], np.array([t]))


def short(details: str) -> str:
    assert len(details.encode()) <= MAX_DETAILS, len(details.encode())
    return details


def refused(call, code=grpc.StatusCode.INVALID_ARGUMENT) -> str:
    with pytest.raises(RpcError) as e:
        call()
    assert e.value.code == code, (e.value.code, e.value.details[:200])
    return short(e.value.details)


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


@pytest.fixture
def client(server):
    """A client of a world of its own on the module's server."""
    with Client(server.target, world=f"s{next(WORLDS)}") as c:
        c.configure_world()
        yield c


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD)
@pytest.mark.parametrize("field", ["body", "source"])
def test_publish_refuses_a_measurements_name_and_keeps_the_others(client, bad, field):
    named = batch(**{field: bad})
    [ack] = client.publish([Batch(*(np.concatenate([a, b]) if isinstance(a, np.ndarray)
                                    else None if a is None else list(a) + list(b)
                                    for a, b in zip(named, batch(t=0.01))))], producer="p")
    [(r, m, details)] = ack.errors
    assert (r, m) == (0, 0) and short(details).startswith(f"requests[0].measurements[0].{field}: ")
    assert client.lookup("", "box").time == 0.01        # its neighbour was used
    # a NOT_FOUND names the world's bodies: none of them can be the long one
    assert "nobody" in refused(lambda: client.lookup("", "nobody"), grpc.StatusCode.NOT_FOUND)


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD)
def test_publish_refuses_a_producers_name_and_uses_none_of_its_request(client, bad):
    [ack] = client.publish([batch()], producer=bad)
    [(r, m, details)] = ack.errors
    assert (r, m) == (0, -1) and short(details).startswith("requests[0].producer: ")
    refused(lambda: client.lookup("", "box"), grpc.StatusCode.NOT_FOUND)


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD)
def test_lookup_subscribe_and_configure_refuse_a_name_naming_the_field(client, bad):
    assert refused(lambda: client.lookup(bad, "")).startswith("target: ")
    assert refused(lambda: client.lookup("", bad)).startswith("source: ")
    assert refused(lambda: next(client.subscribe([bad]))).startswith("bodies[0]: ")
    assert refused(lambda: next(client.subscribe([], relative_to=bad))).startswith(
        "relative_to: ")
    assert refused(lambda: client.configure_world([Source(bad)])).startswith(
        "config.sources[0].name: ")
    assert refused(lambda: client.configure_world([Source("cam")], arms={bad: "cam"})).startswith(
        "config.arms: ")


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD)
def test_fusion_refuses_a_name_naming_the_field(client, bad):
    poses = IDENTITY[None]
    assert refused(lambda: client.fuse(poses, body=bad)).startswith("measurements[0].body: ")
    assert refused(lambda: client.fuse(poses, names=[bad])).startswith(
        "measurements[0].source: ")
    assert refused(lambda: client.fuse(poses, sources=[Source(bad)])).startswith(
        "options.sources[0].name: ")
    answers = list(client.stream_fuse([batch(), batch(body=bad, t=0.01), batch(source=bad)]))
    errors = [(short(a.error), a.body) for a in answers if a.error is not None]
    assert [(e.split(":")[0], body) for e, body in errors] == [
        ("requests[1].measurements[0].body", ""),          # not sent back
        ("requests[2].measurements[0].source", "box")]


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD)
def test_trajectories_arms_and_health_refuse_a_name_naming_the_field(client, bad):
    start = dq.from_pose([1.0, 0, 0, 0], [0.3, 0.0, 0.3])
    plan = [Waypoint(start), Waypoint(IDENTITY)]
    assert refused(lambda: client.plan(plan, Limits(0.5, 1.0, 1.0, 2.0), 100.0,
                                       frames=["", bad])).startswith("waypoints[1].frame: ")
    assert refused(lambda: client.get_arm(bad)).startswith("arm: ")
    assert refused(lambda: client.health(bad), grpc.StatusCode.NOT_FOUND).startswith(
        "service: ")


def test_a_refusals_text_is_bounded_whatever_it_quotes():
    from dqpose.rpc.calls import readable
    text = readable("x: " + "\u00e9" * 10**6)
    assert len(text.encode()) <= MAX_DETAILS and text.endswith("...")
    assert readable("x: 1.2345678901234 and 0.5") == "x: 1.23457 and 0.5"
