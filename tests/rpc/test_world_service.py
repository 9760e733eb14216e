"""The dqpose.v1.World service against a real server on 127.0.0.1: producers in their own
processes feed one world; its answers equal Fuse over the union of their measurements; a
producer's garbage or disconnection leaves the others' alone; acks, sequences, bounds, Lookup's
status codes, replay determinism and Waypoint.frame."""
from __future__ import annotations

import multiprocessing
import re
import threading

import grpc
import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client import Batch, Client, InvalidArgument, RpcError
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread, read_in_thread

T_BOX = dq.from_pose([np.cos(0.2), 0.0, 0.0, np.sin(0.2)], [0.5, 0.1, 0.3])
EXTRINSICS = {"cam1": dq.from_pose([1.0, 0, 0, 0], [0.0, -1.0, 1.0]),
              "cam2": dq.from_pose([np.cos(0.5), np.sin(0.5), 0, 0], [1.0, 1.0, 1.0])}
SOURCES = [Source(name, T) for name, T in EXTRINSICS.items()]
SIGMA = np.diag(np.concatenate([np.full(3, 1e-3), np.full(3, 1e-3)]) ** 2)
TWIST = np.diag([0.1] * 3 + [0.1] * 3) ** 2


def measurements(source: str, times, seed: int, body: str = "box") -> Batch:
    """``source``'s noisy views of the static box at ``times`` (T_frame_box)."""
    rng = np.random.default_rng(seed)
    T_frame_box = dq.mul(dq.conj(EXTRINSICS[source]), T_BOX)
    poses = np.array([dq.mul(T_frame_box, lie.se3_exp(rng.multivariate_normal(np.zeros(6), SIGMA)))
                      for _ in times])
    n = len(times)
    return Batch(poses, np.repeat(SIGMA[None], n, 0), None, [source] * n, [body] * n,
                 np.asarray(times, dtype=np.float64))


def joined(*batches) -> Batch:
    """One batch of the measurements of ``batches``, in order."""
    return Batch(*(None if x[0] is None else np.concatenate(x) if isinstance(x[0], np.ndarray)
                   else sum(map(list, x), []) for x in zip(*batches)))


def part(b: Batch, rows) -> Batch:
    """Rows ``rows`` of batch ``b``."""
    return Batch(*(None if x is None else np.asarray(x)[rows] if isinstance(x, np.ndarray)
                   else [x[i] for i in rows] for x in b))


def produce(target: str, source: str, seed: int, requests: int, per: int, out) -> None:
    """A producer process: ``requests`` requests of ``per`` measurements each, 10 ms apart in
    measurement time, then its acks through ``out``."""
    batches = [measurements(source, 0.01 * (k * per + np.arange(per)) + (seed % 7) * 1e-3,
                            seed * 1000 + k) for k in range(requests)]
    with Client(target) as c:
        acks = list(c.publish(batches, producer=source))
    out.put((source, [(a.acked_through, a.errors) for a in acks], batches))


@pytest.fixture
def server():
    with ServerThread() as s:
        yield s


@pytest.fixture
def client(server):
    with Client(server.target) as c:
        c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
        yield c


class Collector:
    """A subscriber (of ``world``) in a thread: every answer it gets, until :meth:`stop`."""

    def __init__(self, target: str, world: str | None = None, **kw):
        self.client = Client(target, world=world)
        self.answers: list = []
        self.error: Exception | None = None
        self.stream = self.client.subscribe(**kw)
        self.thread = read_in_thread(self.stream, self.answers, RpcError, self._ended)

    def _ended(self, e: RpcError) -> None:
        if e.code != grpc.StatusCode.CANCELLED:
            self.error = e

    def stop(self) -> list:
        self.client.close()
        self.thread.join(10)
        return self.answers


def fuse_union(client, batches, time):
    """Fuse (the Fusion service) over the union of ``batches``, at ``time``."""
    poses = np.concatenate([b.poses for b in batches])
    covs = np.concatenate([b.covariances for b in batches])
    names = sum((list(b.names) for b in batches), [])
    times = np.concatenate([b.times for b in batches])
    return client.fuse(poses, covs, names=names, sources=SOURCES, times=times, time=time,
                       body="box", twist_covariance=TWIST)


def test_two_producer_processes_and_a_subscriber(server, client):
    sub = Collector(server.target, bodies=["box"])
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    procs = [ctx.Process(target=produce, args=(server.target, s, k + 1, 5, 4, out))
             for k, s in enumerate(EXTRINSICS)]
    for p in procs:
        p.start()
    results = {}
    for _ in procs:
        source, acks, batches = out.get(timeout=120)
        results[source] = (acks, batches)
    for p in procs:
        p.join(30)
        assert p.exitcode == 0
    for source, (acks, _) in results.items():
        assert [a for a, _ in acks] == [1, 2, 3, 4, 5], source
        assert all(not errors for _, errors in acks), source
    everything = [b for _, batches in results.values() for b in batches]
    newest = max(float(b.times.max()) for b in everything)
    # one request of both cameras well after the rest: the ticks still pending fall due in it,
    # fused over every measurement (all in the world by then)
    closing = joined(measurements("cam1", [newest + 0.5], 7),
                     measurements("cam2", [newest + 0.5], 8))
    assert list(client.publish([closing], producer="closer")) == [(1, ())]
    everything.append(closing)
    assert wait_until(lambda: any(a.request == 10 for a in sub.answers), timeout=30)
    answers = sub.stop()
    assert sub.error is None
    assert all(a.error is None for a in answers)
    # rate 0: one answer a request that brought the box, at its newest measurement (in order; a
    # request of a camera behind the other answers the newest again), the last the closing one
    times = [a.time for a in answers]
    assert times == sorted(times) and times[-1] == newest + 0.5
    assert len(answers) == len({a.request for a in answers})
    final = [a for a in answers if a.request == 10]
    for a in final:
        local = fuse_union(client, everything, a.time)
        np.testing.assert_allclose(a.fused.mean * np.sign(a.fused.mean[0] * local.mean[0]),
                                   local.mean, atol=1e-12)
        np.testing.assert_allclose(a.fused.covariance, local.covariance, rtol=1e-9, atol=1e-18)
    # and Lookup of the box in the world frame at the newest time is the same pose
    local = fuse_union(client, everything, newest)
    r = client.lookup("", "box", newest)
    np.testing.assert_allclose(r.pose * np.sign(r.pose[0] * local.mean[0]), local.mean,
                               atol=1e-12)


def test_garbage_and_a_disconnect_do_not_disturb_another_producer(server, client):
    good = [measurements("cam1", [0.0, 0.01], 1), measurements("cam1", [0.02, 0.03], 2)]
    bad = measurements("cam2", [0.0, 0.01], 3)
    covs = bad.covariances.copy()
    covs[1] = -covs[1]                          # not positive definite
    bad = bad._replace(covariances=covs)
    acks = list(client.publish([bad], producer="cam2"))
    assert acks[0].acked_through == 1
    [(r, m, details)] = acks[0].errors
    assert (r, m) == (0, 1) and details.startswith("requests[0].measurements[1].covariance")
    # bytes that are no PublishRequest: an ack error, the stream goes on
    raw = client.channel.stream_stream("/dqpose.v1.World/Publish")
    answers = [wpb.PublishAck.FromString(a) for a in raw(iter([
        b"\xff\xff\xff", wpb.PublishRequest(producer="junk", sequence=1).SerializeToString()]))]
    assert "not a valid dqpose.v1.PublishRequest" in answers[0].errors[0].details
    assert answers[1].acked_through == 1
    # a producer that leaves in the middle of its stream
    hold = threading.Event()

    def one_then_wait():
        yield measurements("cam2", [0.05], 4)
        hold.wait(30)            # the producer leaves while its stream is open
        yield measurements("cam2", [0.06], 5)

    with Client(server.target) as leaver:
        stream = leaver.publish(one_then_wait(), producer="leaver")
        assert next(stream) == (1, ())
    hold.set()
    assert [a.acked_through for a in client.publish(good, producer="cam1")] == [1, 2]
    # the good producer's measurements are all in, with the bad one's usable one
    r = client.lookup("", "box", 0.03)
    local = fuse_union(client, good + [part(bad, [0]), measurements("cam2", [0.05], 4)], 0.03)
    np.testing.assert_allclose(r.pose * np.sign(r.pose[0] * local.mean[0]), local.mean,
                               atol=1e-12)


def test_sequence_repeats_are_not_fused_twice_and_gaps_are_named(client):
    b = [measurements("cam1", [0.0], 1)]
    assert list(client.publish(b, producer="p", first_sequence=1))[0] == (1, ())
    again = list(client.publish(b, producer="p", first_sequence=1))[0]
    assert again.acked_through == 1
    assert "sequence 1 already in the world" in again.errors[0][2]
    gap = list(client.publish([measurements("cam1", [0.01], 2)], producer="p",
                              first_sequence=4))[0]
    assert gap.acked_through == 4 and "sequences 2..3" in gap.errors[0][2]


def test_lookup_status_codes(client):
    list(client.publish([measurements("cam1", [10.0, 10.01], 1)], producer="p"))
    with pytest.raises(RpcError) as e:
        client.lookup("", "nobody")
    assert e.value.code == grpc.StatusCode.NOT_FOUND and "nobody" in e.value.details
    for t in (-1000.0, 1000.0):
        with pytest.raises(RpcError) as e:
            client.lookup("", "box", t)
        assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "10" in e.value.details            # names what is known
    r = client.lookup("box", "box")
    np.testing.assert_allclose(abs(r.pose[0]), 1.0, atol=1e-12)


def test_a_lookup_is_answered_while_a_publish_request_holds_the_world(server, client):
    """A Publish request holds its world's cell while its Subscribe answers are fitted (within
    its budget, limits.Budget); a Lookup does not wait for that, only for the world's own
    lock, which each fit takes on its own."""
    list(client.publish([measurements("cam1", [10.0, 10.01], 1)], producer="p"))
    world = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World")
    cell = world.hub("")
    with Client(server.target, timeout=5.0) as c, cell.lock:
        held = c.lookup("", "box")
    after = client.lookup("", "box")
    assert np.array_equal(held.pose, after.pose)
    assert np.array_equal(held.covariance, after.covariance)


def test_bounds_and_bad_configuration_are_refused_with_their_field(client):
    with pytest.raises(InvalidArgument, match=r"^config\.buffer: must be finite"):
        client.configure_world(SOURCES, buffer=-1.0)
    with pytest.raises(RpcError, match="config.sources"):
        client.configure_world([Source(f"s{k}") for k in range(1000)])
    with pytest.raises(RpcError) as e:
        next(client.subscribe(["box"], rate_hz=1e9))
    assert e.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and "max_output_rate" in str(e.value)
    with pytest.raises(grpc.RpcError) as raw:
        client._configure_world(wpb.WorldConfig(sources=[fusion_source_msg("cam1", [1.0] * 5)]))
    assert raw.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert raw.value.details().startswith("config.sources[0].extrinsic_covariance: expected 36")


def fusion_source_msg(name, extrinsic_covariance):
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    return fpb.Source(name=name, extrinsic_covariance=extrinsic_covariance)


def arrivals():
    """Two producers' requests in one interleaved order (cam2 lags cam1 by 40 ms)."""
    out = []
    for k in range(12):
        out.append(("cam1", measurements("cam1", [0.01 * k], 100 + k)))
        if k >= 4:
            out.append(("cam2", measurements("cam2", [0.01 * (k - 4)], 200 + k)))
    return out


def replay(rate_hz: float) -> list:
    with ServerThread() as s, Client(s.target) as c:
        c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0, max_delay=0.02)
        sub = Collector(s.target, bodies=["box"], rate_hz=rate_hz)
        wait_until(lambda: s.running.servicers[0].hub("").subscriptions, timeout=10)
        seq = {"cam1": 0, "cam2": 0}
        for source, batch in arrivals():
            seq[source] += 1
            list(c.publish([batch], producer=source, first_sequence=seq[source]))
        # rate 0: one answer a request (20); 50 Hz: 0, 0.02..0.08, up to cam2's 0.07 and
        # max_delay
        wait_until(lambda: len(sub.answers) >= (20 if rate_hz == 0 else 4), timeout=30)
        return [(a.time, a.request, a.fused.mean.tobytes(), a.fused.covariance.tobytes())
                for a in sub.stop()]


@pytest.mark.parametrize("rate_hz", [0.0, 50.0])
def test_a_recording_of_arrivals_replays_to_the_same_answers(rate_hz):
    first, second = replay(rate_hz), replay(rate_hz)
    n = min(len(first), len(second))
    assert n >= (20 if rate_hz == 0 else 4) and first[:n] == second[:n]
    if rate_hz:     # paced on the slower camera: no tick past what cam2 (or max_delay) covered
        assert max(t for t, *_ in first) <= 0.07 + 0.02 + 1e-9
    else:           # each request answered at the box's newest measurement then
        newest = np.maximum.accumulate([float(b.times.max()) for _, b in arrivals()])
        assert [t for t, *_ in first] == newest.tolist()


def test_a_waypoint_in_a_bodys_frame_is_resolved_through_the_world(server, client):
    from dqpose.trajectory import Limits, Waypoint
    list(client.publish([measurements("cam1", [0.0, 0.01, 0.02], 1)], producer="p"))
    limits = Limits(0.5, 1.0, 1.0, 2.0)
    above = dq.from_pose([1.0, 0, 0, 0], [0.0, 0.0, 0.1])     # 10 cm above the box
    start = dq.from_pose([1.0, 0, 0, 0], [0.3, 0.0, 0.3])
    planned = client.plan([Waypoint(start), Waypoint(above)], limits, 100.0,
                          frames=["", "box"])
    [(index, frame, _, pose, cov)] = planned.resolved
    box = client.lookup("", "box")
    want = dq.mul(box.pose, above)
    assert (index, frame) == (1, "box")
    np.testing.assert_allclose(pose * np.sign(pose[0] * want[0]), want, atol=1e-12)
    np.testing.assert_allclose(planned.pose[-1] * np.sign(planned.pose[-1][0] * want[0]), want,
                               atol=1e-9)
    np.testing.assert_allclose(cov, lie.cov_compose(box.covariance, above, None), rtol=1e-9)
    with pytest.raises(RpcError) as e:
        client.plan([Waypoint(start), Waypoint(above)], limits, 100.0, frames=["", "cup"])
    assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
    assert "waypoints[1].frame: body 'cup'" in e.value.details


def test_fusion_source_extrinsic_covariance_round_trips():
    from dqpose.rpc.fusion_convert import options_msg, sources_from_msg
    c = np.diag(np.arange(1.0, 7.0)) * 1e-6
    msg = options_msg(sources=[Source("cam", extrinsic_covariance=c)])
    [back] = sources_from_msg(msg.sources)
    np.testing.assert_array_equal(back.extrinsic_covariance, c)
    assert fusion.Source("x").latency == 0.0


def test_a_time_jump_makes_due_what_the_requests_budget_affords_the_latest_kept():
    from dqpose.limits import Limits, answer_cost
    fits = 1024         # the box's two measurements fused at each tick
    with ServerThread(limits=Limits(max_fused_per_request=fits * answer_cost(2))) as server, \
            Client(server.target) as client:
        client.configure_world(SOURCES, twist_covariance=TWIST, window=60.0, buffer=60.0,
                               max_extrapolation=None)
        sub = Collector(server.target, bodies=["box"], rate_hz=30.0)
        assert wait_until(lambda: server.running.servicers[0].hub("").subscriptions, timeout=10)
        list(client.publish([measurements("cam1", [0.0], 1), measurements("cam1", [60.0], 2)],
                            producer="p"))
        assert wait_until(lambda: len(sub.answers) > fits, timeout=60)   # + the error
        answers = sub.stop()
    [skip] = [a for a in answers if a.error is not None]
    n = int(re.search(r"(\d+) ticks from", skip.error)[1])
    assert "max_fused_per_request" in skip.error, skip.error
    assert f"({answer_cost(2)} measurements fused an answer)" in skip.error, skip.error
    fused = [a for a in answers if a.error is None]
    assert len(fused) == fits     # "box"'s first tick is after 0 (its phase)
    assert n + fits == round(60.0 * 30.0)
    assert fused[-1].time == pytest.approx(60.0, abs=1 / 30)   # the newest ticks were kept


def test_subscribe_relative_to_answers_what_lookup_does(server, client):
    sub = Collector(server.target, bodies=["box"], relative_to="cup")
    assert wait_until(lambda: server.running.servicers[0].hub("").subscriptions, timeout=10)
    # the cup first, so that it is known at the box's ticks
    for k in range(3):
        list(client.publish([measurements("cam1", [0.01 * k], 10 + k, body="cup"),
                             measurements("cam1", [0.01 * k], 20 + k)], producer="p",
                            first_sequence=2 * k + 1))
    assert wait_until(lambda: len(sub.answers) >= 3, timeout=30)
    answers = sub.stop()
    last = answers[-1]
    assert last.error is None and last.time == pytest.approx(0.02)
    want = client.lookup("cup", "box", 0.02)
    got = last.fused
    np.testing.assert_allclose(got.mean * np.sign(got.mean[0] * want.pose[0]), want.pose,
                               atol=1e-12)
    np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-9, atol=1e-18)
    assert got.sources and got.sources[0].name == "cam1"     # the box's own fit's diagnostics
