"""Lookups answered without a fit (dqpose.answers, a hub's) against a real server on
127.0.0.1: a polled pair's answer, made again when its data arrive, is the fit's answer (to
within the fit's tol: a Lookup's fit starts where the world's last one left the body, this
process's world starts it cold), and a kept answer the one made, to the bit; new data, a new
configuration or a time other than 0 are never answered from a kept answer; watched pairs are
bounded and expire."""
from __future__ import annotations

import numpy as np

from dqpose import answers
from dqpose import world as domain
from dqpose.fusion import Source
from dqpose.rpc.fusion_convert import measurement_msgs, measurements_to_arrays
from dqpose.rpc.geometry import pose_to_dq
from dqpose.rpc.world_convert import relative_msg
from tests.rpc.test_world_service import (  # noqa: F401 (the fixtures server and client)
    EXTRINSICS,
    SOURCES,
    TWIST,
    client,
    joined,
    measurements,
    server,
)

OPTIONS = dict(twist_covariance=TWIST, window=10.0)     # the client fixture's world


def hub(server):
    """The server's default world (its servicer's hub)."""
    world = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World")
    return world.hub("")


def ready(server) -> answers.Answers:
    return hub(server).answers


def fitted(batches, target: str, source: str, sources=SOURCES):
    """``T_target_source`` at time 0 by a world of this process fed the same measurements, as
    the server gets them (sent as messages, read back)."""
    w = domain.World(sources=sources, options=domain.WorldOptions(**OPTIONS))
    for b in batches:
        m = measurements_to_arrays(measurement_msgs(*b), "measurements")
        w.ingest(m.bodies, m.sources, m.times, m.poses, m.covariances)
    return w.relative(target, source, 0.0)


def same(answer, want) -> None:
    """``answer`` (the client's) is ``want`` (a BodyPose of this process) sent as the server
    sends it, to within the fit's tol (1e-12 on a step; its start is not pinned)."""
    sent = relative_msg(want)
    assert answer.time == sent.time
    np.testing.assert_allclose(answer.pose, pose_to_dq(sent.pose), rtol=0, atol=1e-10)
    cov = np.array(sent.covariance)
    np.testing.assert_allclose(answer.covariance.ravel(), cov, rtol=0,
                               atol=1e-8 * np.abs(cov).max())


def test_a_polled_pair_is_answered_on_the_loop_with_the_fits_bits(server, client):
    sent = [joined(measurements("cam1", [0.0, 0.01], 1), measurements("cam2", [0.005], 2),
                   measurements("cam1", [0.0, 0.01], 3, body="cup"))]
    list(client.publish(sent, producer="p"))
    r = ready(server)
    same(client.lookup("cup", "box"), fitted(sent, "cup", "box"))     # fitted: now watched
    assert r.hits == 0
    for k in range(3):
        more = measurements("cam2", [0.02 + 0.01 * k], 10 + k)
        sent.append(more)
        list(client.publish([more], producer="p", first_sequence=2 + k))
        # the box's new measurement made the pair's answer again in the Publish request
        same(client.lookup("cup", "box"), fitted(sent, "cup", "box"))
        assert r.hits == k + 1
    made = client.lookup("cup", "box")
    assert r.hits == 4
    kept = client.lookup("cup", "box")      # no new data: the answer kept, to the bit
    assert r.hits == 5
    assert np.array_equal(kept.pose, made.pose)
    assert np.array_equal(kept.covariance, made.covariance)


def test_data_that_bypass_the_refresh_and_a_new_configuration_are_fitted(server, client):
    sent = [measurements("cam1", [0.0, 0.01, 0.02], 1)]
    list(client.publish(sent, producer="p"))
    r = ready(server)
    first = client.lookup("", "box")
    # a measurement that reaches the world without a Publish request's refresh: the kept
    # answer's stamp no longer holds, so the Lookup fits
    more = measurements("cam2", [0.03], 2)
    sent.append(more)
    m = measurements_to_arrays(measurement_msgs(*more), "measurements")
    hub(server).world.ingest(m.bodies, m.sources, m.times, m.poses, m.covariances)
    after = client.lookup("", "box")
    assert r.hits == 0 and after.time > first.time
    same(after, fitted(sent, "", "box"))
    # a new configuration (cam2 moved) changes every answer: not served from before
    moved = [Source("cam1", EXTRINSICS["cam1"]),
             Source("cam2", EXTRINSICS["cam1"])]
    client.configure_world(moved, **OPTIONS)
    again = client.lookup("", "box")
    assert r.hits == 0
    same(again, fitted(sent, "", "box", moved))
    assert not np.array_equal(again.pose, after.pose)


def test_a_lookup_at_a_time_is_fitted_and_watches_nothing(server, client):
    list(client.publish([measurements("cam1", [0.0, 0.01], 1)], producer="p"))
    r = ready(server)
    for _ in range(2):
        client.lookup("", "box", 0.01)
    assert r.hits == 0 and not r._watched and not r._answers


def test_watched_pairs_are_bounded_and_expire(server, client, monkeypatch):
    bodies = [f"b{k}" for k in range(answers.MAX_WATCHED + 3)]
    list(client.publish([joined(*(measurements("cam1", [0.0, 0.01], k, body=b)
                                  for k, b in enumerate(bodies)))], producer="p"))
    r = ready(server)
    for b in bodies:
        client.lookup("", b)
    # the pairs watched longest ago gave way, their answers with them
    assert list(r._watched) == [("", b) for b in bodies[-answers.MAX_WATCHED:]]
    assert set(r._answers) == set(r._watched)
    # a Publish request after their watch ran out forgets them
    later = answers._clock() + answers.WATCH_FOR + 1.0
    monkeypatch.setattr(answers, "_clock", lambda: later)
    list(client.publish([measurements("cam1", [0.02], 99, body=bodies[0])], producer="p",
                        first_sequence=2))
    assert not r._watched and not r._answers
