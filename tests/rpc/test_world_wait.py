"""World Lookups that wait (LookupRequest.wait) and that span two times (source_time,
fixed_frame) against a real server on 127.0.0.1; the client's answer object."""
from __future__ import annotations

import concurrent.futures
import math

import grpc
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose import world as domain
from dqpose.limits import Limits
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client import Batch, Client, InvalidArgument, RpcError
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread

SIGMA = np.diag([1e-3] * 6) ** 2
TWIST = np.array([0.1, 0.0, 0.2, 0.3, -0.1, 0.0])


def batch(body: str, times, seed: int = 0) -> Batch:
    """Noisy views of ``body`` moving at ``TWIST`` from the identity, by one camera."""
    rng = np.random.default_rng(seed)
    times = np.asarray(times, dtype=np.float64)
    poses = np.array([dq.mul(lie.se3_exp(t * TWIST),
                             lie.se3_exp(rng.multivariate_normal(np.zeros(6), SIGMA)))
                      for t in times])
    n = len(times)
    return Batch(poses, np.repeat(SIGMA[None], n, 0), None, ["cam"] * n, [body] * n, times)


@pytest.fixture(scope="module")
def server():
    limits = Limits(max_peer_waits=2, max_world_waits=1)
    with ServerThread(ServerConfig(port=0, limits=limits)) as s:
        yield s


def servicer(server):
    return next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World")


def waiting(server) -> int:
    return sum(n for (scope, _), n in servicer(server).waits.count.items() if scope == "peer")


def refusal(c: Client, *args, **kw) -> RpcError:
    with pytest.raises(RpcError) as e:
        c.lookup(*args, **kw)
    return e.value


def test_wait_is_checked_and_named(server):
    with Client(server.target, world="checks") as c:
        for bad in (-1.0, math.nan, 10.5):
            with pytest.raises(InvalidArgument, match=r"^wait: must be between 0 and 10 s, got"):
                c.lookup("", "", wait=bad)
        with pytest.raises(InvalidArgument, match=r"^source_time: must be finite"):
            c.lookup("", "", source_time=math.inf)


def test_a_waiting_lookup_is_answered_by_the_publish_that_brings_its_body(server):
    with Client(server.target, world="late") as c, \
            concurrent.futures.ThreadPoolExecutor(1) as pool:
        list(c.publish([batch("other", [0.0, 0.1])]))
        pending = pool.submit(c.lookup, "", "box", 0.0, 10.0)
        assert wait_until(lambda: waiting(server) == 1, 10.0)
        list(c.publish([batch("other", [0.2])]))        # not its body: it waits on
        assert waiting(server) == 1 and not pending.done()
        list(c.publish([batch("box", [1.0, 1.1], seed=1)]))
        got = pending.result(30)
        want = c.lookup("", "box")
        np.testing.assert_array_equal(got.pose, want.pose)
        np.testing.assert_array_equal(got.covariance, want.covariance)
        assert waiting(server) == 0
        # a time past the newest: answered by the request that brings it within reach
        pending = pool.submit(c.lookup, "", "box", 2.0, 10.0)
        assert wait_until(lambda: waiting(server) == 1, 10.0)
        list(c.publish([batch("box", np.arange(1.2, 2.05, 0.1), seed=2)]))
        assert pending.result(30).time == 2.0


def test_after_wait_the_error_it_would_have_had(server):
    """Unknown body, a time past the newest: after waiting, the same status and text. Waiting
    Lookups are bounded by world and by peer; an error more data cannot mend (a time before
    the buffer) is answered without waiting: it takes no waiting slot, which are full."""
    with Client(server.target, world="never") as c:
        list(c.publish([batch("box", [5.0, 5.1])]))
        for args in (("", "ghost"), ("", "box", 9.0)):
            without = refusal(c, *args)
            after = refusal(c, *args, wait=0.2)
            assert (after.code, after.details) == (without.code, without.details)
            assert without.code in (grpc.StatusCode.NOT_FOUND,
                                    grpc.StatusCode.FAILED_PRECONDITION)
        request = wpb.LookupRequest(source="ghost", wait=10.0)
        holders = [c._lookup.future(request, timeout=30, metadata=c.metadata)]
        try:
            assert wait_until(lambda: waiting(server) == 1, 10.0)
            full = refusal(c, "", "box", 9.0, wait=1.0)
            assert full.code == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert full.details.startswith("wait: world 'never' has 1 Lookups waiting")
            assert "max_world_waits = 1" in full.details
            with Client(server.target, world="other") as o:
                list(o.publish([batch("box", [5.0, 5.1])]))
                holders.append(o._lookup.future(request, timeout=30, metadata=o.metadata))
                assert wait_until(lambda: waiting(server) == 2, 10.0)
                full = refusal(o, "", "box", 9.0, wait=1.0)
            assert full.code == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "max_peer_waits = 2" in full.details and full.details.startswith("wait: ")
            before = refusal(c, "", "box", 1.0, wait=10.0)
            assert before.code == grpc.StatusCode.FAILED_PRECONDITION
            assert "before the oldest measurement" in before.details
        finally:
            for h in holders:
                h.cancel()
        # a cancelled call stops waiting: its slot freed
        assert wait_until(lambda: waiting(server) == 0, 10.0)
        assert not servicer(server).hub("never").listeners


def test_the_servers_stop_answers_a_waiting_lookup_unavailable():
    with ServerThread() as s, Client(s.target) as c:
        list(c.publish([batch("box", [0.0, 0.1])]))
        pending = c._lookup.future(wpb.LookupRequest(source="ghost", wait=10.0), timeout=30,
                                   metadata=c.metadata)
        assert wait_until(lambda: waiting(s) == 1, 10.0)
        s.stop(grace=5.0)
        with pytest.raises(grpc.RpcError) as e:
            pending.result(30)
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE


def test_two_times_and_a_fixed_frame_answer_what_the_domain_does(server):
    with Client(server.target, world="two") as c:
        times = np.arange(0.0, 2.01, 1 / 30)
        list(c.publish([batch("arm", times, 3), batch("table", times, 4)]))
        here = domain.World(options=domain.WorldOptions())
        for b, seed in (("arm", 3), ("table", 4)):
            x = batch(b, times, seed)
            here.publish([domain.Measurement("cam", b, float(t), p, s)
                          for t, p, s in zip(x.times, x.poses, x.covariances)])
        for fixed in ("", "table"):
            got = c.lookup("arm", "arm", 1.2, source_time=1.6, fixed_frame=fixed)
            want = here.relative_at("arm", 1.2, "arm", 1.6, fixed)
            np.testing.assert_allclose(got.pose, want.pose, atol=1e-12)
            np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-9, atol=1e-18)
            assert got.time == 1.2
        # the answer in every form
        np.testing.assert_array_equal(got.dq, got.pose)
        q, p = dq.to_pose(got.pose)
        np.testing.assert_array_equal(got.position, p)
        np.testing.assert_array_equal(got.quaternion, q)
        M = got.matrix
        assert M.shape == (4, 4)
        np.testing.assert_allclose(M[:3, 3], p, atol=1e-15)
        assert got.covariance.shape == (6, 6)
        s_rot, s_pos = lie.cov_sigmas(got.covariance)
        assert (got.sigma_rotation, got.sigma_position) == (s_rot, s_pos)
        assert 0 < got.sigma_position < 1e-2 and 0 < got.sigma_rotation < 1e-2


def test_a_static_on_a_body_is_waited_for_through_its_body(server):
    """A Lookup of a static fixed on a body not measured yet waits for that body's data."""
    from dqpose.frames import Static

    tip = lie.se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.1]))
    with Client(server.target, world="tip") as c, \
            concurrent.futures.ThreadPoolExecutor(1) as pool:
        c.configure_world(statics=[Static("arm", "tip", tip)])
        pending = pool.submit(c.lookup, "", "tip", 0.0, 10.0)
        assert wait_until(lambda: waiting(server) == 1, 10.0)
        list(c.publish([batch("arm", [0.0, 0.1])]))
        got = pending.result(30)
        np.testing.assert_allclose(got.pose, dq.mul(c.lookup("", "arm").pose, tip), atol=1e-12)
