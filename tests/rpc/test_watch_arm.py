"""``Trajectories.WatchArm`` on the simulated UR (through ur_rtde) and PiPER (through python-can),
each arm in a process of its own, behind a real server on 127.0.0.1: the states follow the arm
through a run (where it is, the run's state, busy), watchers share the arm's readings, bad
requests are refused by field, and the server's shutdown ends the stream UNAVAILABLE."""
from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from dqpose.rpc.arms import MAX_WATCH_HZ, MAX_WATCHERS
from dqpose.rpc.client import Client, InvalidArgument, RpcError
from tests._polling import wait_until
from tests.robustness._arms import (  # noqa: F401 (rigs: rig's fixture)
    SLOW,
    distance,
    offset,
    rig,
    rigs,
    serve,
)


def _off_path(pose, start, goal) -> float:
    """How far ``pose``'s position is from the segment between ``start``'s and ``goal``'s."""
    from dqpose import dq
    p, a, b = (dq.to_pose(x)[1] for x in (pose, start, goal))
    s = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + s * (b - a))))


def test_the_states_follow_the_arm_through_a_run(rig):
    r, c, server = rig
    goal = offset(r.home, dx=0.03)
    states: list = []
    watching = threading.Event()
    done = threading.Event()

    def watch():
        with Client(server.target) as w:
            it = w.watch_arm(r.name, rate_hz=25.0)
            for st in it:
                states.append(st)
                watching.set()
                if done.is_set() and not st.busy:
                    break
            it.close()

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    assert watching.wait(30)
    feedback = list(c.execute(r.name, [r.home, goal], SLOW))
    done.set()
    t.join(30)
    assert not t.is_alive()
    assert feedback[-1].state == "FINISHED", feedback[-1].message
    first, last = states[0], states[-1]
    assert first.arm == r.name and first.faults == () and first.state in ("", "FINISHED")
    assert distance(first.pose, r.home) < 1e-3
    working = [s for s in states if s.state == "WORKING"]
    assert working and all(s.busy for s in working)
    # on the way: the arm's actual poses lie on the planned line, and it moved along it
    assert max(_off_path(s.pose, r.home, goal) for s in working) < 2e-3
    assert max(distance(s.pose, r.home) for s in working) > 0.005
    assert last.state == "FINISHED" and not last.busy
    assert distance(last.pose, goal) < 1e-3
    assert last.limits == c.get_arm(r.name).limits


def test_watchers_share_the_arms_readings(rig):
    r, c, server = rig
    arm = r.arm         # the object the server reads (ServerConfig.arms)
    reads = []
    real = arm.state

    def counted():
        reads.append(1)
        return real()

    arm.state = counted
    states = []
    lock = threading.Lock()

    def watch():
        with Client(server.target) as w:
            it = w.watch_arm(r.name, rate_hz=MAX_WATCH_HZ)
            for k, _ in enumerate(it):
                with lock:
                    states.append(1)
                if k == 40:
                    break
            it.close()

    try:
        threads = [threading.Thread(target=watch, daemon=True) for _ in range(10)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
    finally:
        del arm.state
    assert len(states) == 10 * 41
    # one reading per watcher and state would be 410; shared, about a tenth of that
    assert 0 < len(reads) * 3 < len(states), (len(reads), len(states))


def test_bad_watches_are_refused_by_field(rigs):
    by_name, server = rigs
    with Client(server.target) as c:
        with pytest.raises(InvalidArgument, match=r"^arm: unknown arm 'kuka' \(this server's "
                                                  r"arms: piper, ur\)$"):
            next(c.watch_arm("kuka"))
        for bad in (-1.0, float("nan"), float("inf")):
            with pytest.raises(InvalidArgument, match=r"^rate_hz: must be finite and >= 0"):
                next(c.watch_arm("ur", rate_hz=bad))
        with pytest.raises(RpcError) as e:
            next(c.watch_arm("ur", rate_hz=1000.0))
        assert e.value.code.name == "RESOURCE_EXHAUSTED"
        assert e.value.details == "rate_hz: 1000 Hz is above WatchArm's most, 100 Hz"


def test_watches_beyond_the_servers_most_are_refused(rigs, monkeypatch):
    by_name, server = rigs
    peers = server.running.calls.peers      # one peer may hold them all here
    monkeypatch.setattr(peers, "limits", dataclasses.replace(
        peers.limits, max_peer_subscriptions=MAX_WATCHERS + 1, max_peer_streams=MAX_WATCHERS + 1))
    with Client(server.target) as c:
        open_ = [c.watch_arm("ur", rate_hz=1.0) for _ in range(MAX_WATCHERS)]
        try:
            for it in open_:
                next(it)
            with pytest.raises(RpcError) as e:
                next(c.watch_arm("piper"))
            assert e.value.code.name == "RESOURCE_EXHAUSTED"
            assert e.value.details == (f"WatchArm: {MAX_WATCHERS} watches are open, the "
                                       f"server's most")
        finally:
            for it in open_:
                it.close()
        # closed watches are counted out: a new one is taken again
        assert wait_until(lambda: _watch_once(c), timeout=10)


def _watch_once(c: Client) -> bool:
    it = c.watch_arm("piper")
    try:
        next(it)
        return True
    except RpcError:
        return False
    finally:
        it.close()


def test_the_servers_shutdown_ends_a_watch_unavailable(rigs):
    by_name, _ = rigs
    server = serve(list(by_name.values()))
    try:
        with Client(server.target) as c:
            it = c.watch_arm("ur", rate_hz=10.0)
            next(it)
            stopper = threading.Thread(target=server.stop, args=(10.0,), daemon=True)
            stopper.start()
            with pytest.raises(RpcError) as e:
                for _ in it:
                    pass
            stopper.join(30)
        assert e.value.code.name == "UNAVAILABLE"
        assert e.value.details == "the server is shutting down"
    finally:
        server.stop()

