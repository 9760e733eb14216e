"""World.Publish within the server's limits, against a real server on 127.0.0.1: times beyond
``max_time`` refused as StreamFuse refuses them, a body's time jump confirmed only by another
producer, on both of Publish's decoders (the C one for plain requests, protobuf's for the rest:
a name that is not ASCII); a request's Subscribe answers within its budget."""
from __future__ import annotations

import itertools

import grpc
import numpy as np
import pytest

from dqpose.limits import Limits, answer_cost
from dqpose.rpc.client import Batch, Client, RpcError
from dqpose.rpc.wire import publish_from_wire, publish_request_wire
from dqpose.world_ticks import Schedule
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_world_service import Collector

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
# "box" takes the C decoder, "bóx" protobuf's (the C one leaves names that are not ASCII to it)
BODIES = ["box", "b\u00f3x"]


def batch(body: str, *times: float) -> Batch:
    n = len(times)
    return Batch(np.repeat(IDENTITY[None], n, 0), np.repeat(np.eye(6)[None] * 1e-4, n, 0), None,
                 ["cam"] * n, [body] * n, np.array(times))


def publish(client, producer: str, *batches) -> list:
    """Each batch's ack errors, ``(request, measurement, details)``."""
    return [a.errors for a in client.publish(batches, producer=producer, first_sequence=0)]


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


WORLDS = itertools.count()


@pytest.fixture
def client(server):
    """A client of a world of its own on the module's server."""
    with Client(server.target, world=f"w{next(WORLDS)}") as c:
        c.configure_world(window=1.0, buffer=10.0)
        yield c


@pytest.mark.parametrize("body", BODIES)
def test_the_decoders_are_the_ones_named(body):
    plain = publish_from_wire(publish_request_wire(batch(body, 0.0), "p", 1)) is not None
    assert plain == (body == "box")


@pytest.mark.parametrize("body", BODIES)
@pytest.mark.parametrize("t", [1e300, 1e11, -1e11])
def test_a_first_measurement_beyond_max_time_is_refused_and_moves_nothing(client, body, t):
    [[(r, m, details)]] = publish(client, "far", batch(body, t))
    assert (r, m) == (0, 0)
    assert details.startswith("requests[0].measurements[0].time: "), details
    assert "max_time" in details and "--max-time" in details, details
    with pytest.raises(RpcError) as e:
        client.lookup("", body)
    assert e.value.code == grpc.StatusCode.NOT_FOUND
    # every other producer's ordinary measurements are the body's
    assert publish(client, "near", batch(body, 0.0, 0.01), batch(body, 0.02)) == [(), ()]
    assert client.lookup("", body).time == 0.02


@pytest.mark.parametrize("body", BODIES)
def test_one_producer_cannot_move_a_body_that_another_feeds(client, body):
    assert publish(client, "a", batch(body, 0.0)) == [()]
    assert publish(client, "b", batch(body, 0.01)) == [()]
    # "a"'s clock leaps: its second measurement there does not confirm its own jump
    jumped = publish(client, "a", batch(body, 1000.0), batch(body, 1000.01))
    for (_, _, details), in jumped:
        assert "max_time_jump" in details and "from another producer" in details, details
    assert publish(client, "b", batch(body, 0.02)) == [()]
    assert client.lookup("", body).time == 0.02
    # within max_time, a jump that another producer confirms moves the body
    assert publish(client, "c", batch(body, 1000.02)) == [()]
    assert client.lookup("", body).time == 1000.02
    # beyond it, even two producers agreeing move nothing
    for producer in ("a", "c"):
        [[(_, _, details)]] = publish(client, producer, batch(body, 2e10))
        assert "max_time" in details and "max_time_jump" not in details, details
    assert client.lookup("", body).time == 1000.02


def test_a_body_only_its_producer_feeds_follows_that_producers_jump(client):
    """A body seen again after a pause, by the one producer that sees it: its own second
    measurement confirms the jump (it moves nothing another producer fed)."""
    assert publish(client, "a", batch("cup", 0.0)) == [()]
    [[(_, _, details)]] = publish(client, "a", batch("cup", 1000.0))
    assert "max_time_jump" in details and "another producer" not in details, details
    assert publish(client, "a", batch("cup", 1000.01)) == [()]
    assert client.lookup("", "cup").time == 1000.01


@pytest.mark.parametrize("robust", [False, True])
def test_the_costliest_legal_publish_answers_what_its_budget_affords_in_each_world(server,
                                                                                 robust):
    """One request of 1,000 measurements of one body over 1 s, within the window, and a
    subscriber at 1 kHz: ~1,000 ticks fall due, each fusing all 1,000. The request answers what
    ``max_fused_per_request`` affords (limits.Budget, StreamFuse's rule), the latest, and names
    the ticks it skipped; another world's request has a budget of its own. (Before the budget:
    every answer fitted, 6.4 s of CPU, 26.7 s robust, under the world's lock.)"""
    n = 1000
    fits = Limits().max_fused_per_request // answer_cost(n, robust)
    times = np.arange(n) * 1e-3
    schedule = Schedule(1000.0)
    ticks = [schedule.time("box", k) for k in schedule.due("box", times[-1], 0.0)]
    worlds = [f"w{next(WORLDS)}", f"w{next(WORLDS)}"]
    subs = []
    for world in worlds:
        with Client(server.target, world=world) as c:
            c.configure_world(window=1.0, buffer=10.0, robust=robust)
        subs.append(Collector(server.target, world=world, rate_hz=1000.0))
    cells = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World").hubs
    assert wait_until(lambda: all(cells[w].subscriptions for w in worlds), timeout=10)
    for sub in subs:
        with Client(server.target, world=sub.client.world) as c:
            assert publish(c, "p", batch("box", *times)) == [()]
    for sub in subs:
        assert wait_until(lambda: len(sub.answers) == fits + 1, timeout=60)
        answers = sub.stop()
        [skip] = [a.error for a in answers if a.error is not None]
        assert f"body 'box': {len(ticks) - fits} ticks from {ticks[0]:.6g} s to " in skip, skip
        assert "max_fused_per_request" in skip, skip
        assert [a.time for a in answers if a.error is None] == ticks[len(ticks) - fits:]
