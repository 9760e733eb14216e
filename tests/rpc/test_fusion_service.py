"""The dqpose.v1.Fusion service against a real server on 127.0.0.1: Fuse equals
dqpose.fusion.fuse in process; bad input is INVALID_ARGUMENT naming the measurement; StreamFuse
answers per body, and survives a bad measurement with an error entry for it."""
from __future__ import annotations

import zlib

import numpy as np
import pytest

from dqpose import dq, fusion, lie
from dqpose.fusion import Source
from dqpose.rpc import fusion_convert, geometry
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.client import Batch, Client, InvalidArgument
from dqpose.rpc.fusion import Fusion
from dqpose.world_ticks import tick_phase
from tests.rpc._grpc_server import ServerThread


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


@pytest.fixture(scope="module")
def client(server):
    with Client(server.target) as c:
        yield c


def random_cov(rng):
    s = np.concatenate([np.deg2rad(rng.uniform(0.2, 2.0, 3)), rng.uniform(0.5e-3, 5e-3, 3)])
    return s[:, None] * s[None] * np.corrcoef(rng.normal(size=(6, 12)))


def scene(seed, n=6, outliers=0):
    """A body seen n times with anisotropic covariances; the first ``outliers`` flipped."""
    rng = np.random.default_rng(seed)
    X = lie.se3_exp(rng.normal(size=6))
    S = np.array([random_cov(rng) for _ in range(n)])
    xi = np.array([rng.multivariate_normal(np.zeros(6), c) for c in S])
    Z = dq.mul(X, lie.se3_exp(-xi))
    for i in range(outliers):
        Z[i] = dq.mul(Z[i], lie.se3_exp(np.array([2.0, 0, 0, 0.3, 0, 0])))
    return X, Z, S


def wire(Z):
    """The poses as the server receives them: a Pose (quaternion, translation) per measurement,
    as the client writes it."""
    return dq.from_pose(*geometry.pose_arrays(np.asarray(Z)))


def local(Z, *args, **kw):
    """dqpose.fusion.fuse in process, of the poses the server received."""
    return fusion.fuse(wire(Z), *args, **kw)


def assert_same(got: fusion.Fused, want: fusion.Fused):
    s = np.sign(got.mean[:4] @ want.mean[:4])
    np.testing.assert_allclose(s * got.mean, want.mean, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(got.covariance, want.covariance)
    for name in ("residuals", "distances", "nis", "tested", "inliers"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert (got.status, got.chi2, got.dof, got.iterations) == (
        want.status, want.chi2, want.dof, want.iterations)
    assert got.rejected == want.rejected and got.sources == want.sources


NAMES = ["cam1", "cam1", "cam2", "cam2", "arm", "cam2"]


@pytest.mark.parametrize("robust", [False, True])
def test_fuse_equals_the_domain_in_process(client, robust):
    E = lie.se3_exp(np.array([0.1, -0.2, 0.3, 0.5, 0.1, -0.4]))
    offset = lie.se3_exp(np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.1]))
    E, offset = wire(E), wire(offset)
    sources = [Source("cam1", extrinsic=E), Source("cam2"), Source("arm", E, offset)]
    _, Z, S = scene(1, outliers=2 if robust else 0)
    # each measurement in its source's frame: cam1 and the arm's flange seen from E
    Z[:2] = dq.mul(dq.conj(E), Z[:2])
    Z[4] = dq.mul(dq.mul(dq.conj(E), Z[4]), dq.conj(offset))
    S[4] = lie.adjoint(offset) @ S[4] @ lie.adjoint(offset).T
    want = local(Z, S, names=NAMES, robust=robust,
                 sources=[Source("cam1", extrinsic=E), Source("cam2"), Source("arm", E, offset)])
    got = client.fuse(Z, S, names=NAMES, sources=sources, robust=robust, body="box")
    assert_same(got, want)
    if robust:   # the flipped ones are out, with the domain's reasons
        assert [r.index for r in got.rejected] == [0, 1]
        assert got.rejected[0].source == "cam1" and "beyond the gate" in got.rejected[0].reason


def test_fuse_weights_and_the_isotropic_default(client):
    _, Z, _ = scene(2, n=4)
    assert_same(client.fuse(Z, weights=[1, 2, 3, 4]), local(Z, weights=[1, 2, 3, 4]))
    assert_same(client.fuse(Z), local(Z))


def test_fuse_message_fields(client):
    _, Z, S = scene(3, n=3)
    ms = fusion_convert.measurement_msgs(Z, S, names=["a", "b", "a"], bodies=["box"] * 3,
                                  times=[2.5, 2.5, 2.5])
    r = client.fuse_request(pb.FuseRequest(measurements=ms))
    # one instant: the static fusion, no twist
    assert r.body == "box" and r.time == 2.5 and not r.twist and r.extrapolation == 0.0
    assert r.status == pb.FUSION_STATUS_CONVERGED and r.dof == 12 and len(r.covariance) == 36
    assert [s.name for s in r.sources] == ["a", "b"] and len(r.residuals) == 18
    for m, t in zip(ms, [1.0, 2.5, 2.0]):
        m.time = t
    # three instants: time alignment, with the twist estimated from the data (6 dof less)
    r = client.fuse_request(pb.FuseRequest(measurements=ms))
    assert r.time == 2.5 and r.dof == 6 and len(r.twist) == 6 and len(r.twist_covariance) == 36
    r = client.fuse_request(pb.FuseRequest(measurements=ms,
                                           options=pb.FusionOptions(time=2.55)))
    assert r.time == 2.55 and r.extrapolation == pytest.approx(0.05)
    with pytest.raises(InvalidArgument, match=r"^options.time: 7.0 is 4.5 s outside the span "
                                              r"\[1.0, 2.5\] .* beyond max_extrapolation 0.1 s"):
        client.fuse_request(pb.FuseRequest(measurements=ms, options=pb.FusionOptions(time=7.0)))
    r = client.fuse_request(pb.FuseRequest(measurements=ms, options=pb.FusionOptions(
        time=7.0, max_extrapolation=float("inf"))))
    assert r.time == 7.0 and r.extrapolation == 4.5


def test_one_instant_is_the_static_fusion_exactly(client):
    """What the demo sends (every measurement stamped with the arm's time): bit for bit the
    fusion without times, also with latencies estimated (one instant shows none)."""
    _, Z, S = scene(6, n=5)
    names = ["cam1", "cam1", "arm", "cam2", "arm"]
    sources = [Source("cam1", latency_sigma=0.01), Source("cam2"), Source("arm")]
    got = client.fuse(Z, S, names=names, sources=sources, times=[3.25] * 5, time=3.25,
                      max_skew=0.05, body="box")
    assert_same(got, local(Z, S, names=names, sources=sources))
    assert got.time == 3.25 and got.twist is None and got.dropped == ()
    assert got.latencies == (fusion.Latency("cam1", 0.0, 0.01, 0.0, 0.01),)


def _request(Z, S, **kw):
    return pb.FuseRequest(measurements=fusion_convert.measurement_msgs(Z, S, **kw))


@pytest.mark.parametrize("edit, message", [
    (lambda r: setattr(r.measurements[3], "body", "cup"),
     "measurements[3].body: 'cup' differs from measurements[0].body 'box'"),
    (lambda r: r.measurements[2].covariance.__setitem__(7, float("nan")),
     "measurements[2].covariance: contains NaN or infinity"),
    (lambda r: r.measurements[1].covariance.__setitem__(0, -1.0),
     "measurements[1].covariance: not positive definite"),
    (lambda r: r.measurements[4].covariance.__setitem__(1, 1.0),
     "measurements[4].covariance: not symmetric"),
    (lambda r: r.measurements[0].covariance.pop(),
     "measurements[0].covariance: expected 36 values (6x6, row-major, rotation first) or none, "
     "got 35"),
    (lambda r: setattr(r.measurements[5].pose.orientation, "w", float("nan")),
     "measurements[5].pose.orientation: "),
    (lambda r: setattr(r.measurements[5].pose.position, "x", float("inf")),
     "measurements[5].pose.position: "),
    (lambda r: r.measurements[2].ClearField("pose"), "measurements[2].pose.orientation: "),
    (lambda r: setattr(r.measurements[3], "time", float("nan")),
     "measurements[3].time: must be finite"),
    (lambda r: setattr(r.measurements[3], "weight", 2.0),
     "measurements[3].weight: give a covariance or a weight, not both"),
    (lambda r: r.options.sources.add(name="cam3"),
     "measurements[4].source: 'arm' is not among options.sources (cam1, cam2, cam3)"),
    (lambda r: r.options.sources.add(name="cam1"),
     "options.sources[3]: source 'cam1' given twice"),
    (lambda r: r.options.sources[0].extrinsic.orientation.__setattr__("w", 0.0),
     "options.sources[0].extrinsic.orientation: "),
    (lambda r: setattr(r.options, "max_skew", -0.1), "options.max_skew: must be nonnegative"),
    (lambda r: setattr(r.options, "max_extrapolation", -1.0),
     "options.max_extrapolation: must be nonnegative"),
    (lambda r: setattr(r.options, "time", 100.0),
     "options.time: 100.0 is 100 s outside the span [0.0, 0.0] of the measurements"),
    (lambda r: setattr(r.options, "window", 0.5), "options.window: Fuse keeps no window"),
    (lambda r: setattr(r.options.sources[1], "latency_sigma", -0.01),
     "options.sources[1].latency_sigma: must be positive"),
    (lambda r: setattr(r.options.sources[1], "latency", float("inf")),
     "options.sources[1].latency: must be finite"),
    (lambda r: setattr(r.options.sources[1], "parent", "tool"),
     "options.sources[1].parent: only a world resolves a parent"),
    (lambda r: r.options.twist_covariance.extend([1.0] * 35),
     "options.twist_covariance: expected 36 values"),
    (lambda r: r.options.twist_covariance.extend((-np.eye(6)).ravel().tolist()),
     "options.twist_covariance: not positive definite"),
    (lambda r: r.options.acceleration_psd.extend([1.0] * 35),
     "options.acceleration_psd: expected 36 values"),
    (lambda r: r.options.acceleration_psd.extend((-np.eye(6)).ravel().tolist()),
     "options.acceleration_psd: not positive semidefinite"),
    (lambda r: setattr(r.options, "probability", 1.5), "options.probability: must be within"),
    (lambda r: r.ClearField("measurements"), "measurements: empty request: no measurements"),
])
def test_fuse_bad_input_is_invalid_argument_naming_it(client, edit, message):
    _, Z, S = scene(4)
    r = _request(Z, S, names=NAMES, bodies=["box"] * 6)
    r.options.sources.add(name="cam1", extrinsic=geometry.dq_to_pose(Z[0]))
    r.options.sources.add(name="cam2")
    if "arm" not in message:
        r.options.sources.add(name="arm")
    edit(r)
    with pytest.raises(InvalidArgument) as e:
        client.fuse_request(r)
    assert str(e.value).startswith(message), str(e.value)
    # the same text in process, with no server (what `dqpose fuse --local` answers)
    with pytest.raises(ValueError, match="^" + __import__("re").escape(message)):
        Fusion().fuse(r)


def test_fuse_weight_checks(client):
    _, Z, _ = scene(5, n=3)
    with pytest.raises(InvalidArgument, match=r"^measurements\[1\].weight: must be positive"):
        client.fuse(Z, weights=[1.0, -2.0, 1.0])


# ---- a moving body -----------------------------------------------------------------------------
TWIST = np.array([0.3, -0.2, 0.5, 0.2, 0.1, -0.15])   # rad/s, m/s
CAM = np.diag(np.r_[np.full(3, np.deg2rad(0.2)), 0.6e-3, 0.6e-3, 4e-3] ** 2)
ARM = np.diag(np.r_[np.full(3, np.deg2rad(0.5)), np.full(3, 2e-3)] ** 2)
CAM_LATENCY, ARM_LATENCY = 0.04, 0.004
E_CAM = wire(lie.se3_exp(np.array([0.2, 0.1, -0.3, 0.4, -0.2, 1.0])))    # T_world_cam
SOURCES = [Source("cam", extrinsic=E_CAM, latency=CAM_LATENCY),
           Source("arm", latency=ARM_LATENCY, latency_sigma=0.005)]
LATENCY = {"cam": CAM_LATENCY, "arm": ARM_LATENCY}


def moving(seed, start=0.0, end=0.2, body="box"):
    """A body on the screw T(t) = X0 Exp(t V) seen by a 30 Hz camera (40 ms latency, in its own
    frame) and a 100 Hz arm (4 ms): poses in the source's frame, covariances, sources, bodies,
    stamps in time order, and the truth T(t)."""
    rng = np.random.default_rng(seed)
    X0 = lie.se3_exp(rng.normal(size=6))

    def T(t):
        return dq.mul(X0, lie.se3_exp(np.atleast_1d(t)[:, None] * TWIST))

    rows = []
    for name, rate, C in (("cam", 30.0, CAM), ("arm", 100.0, ARM)):
        for t in np.arange(start + rng.uniform(0, 1 / rate), end, 1 / rate):
            xi = rng.multivariate_normal(np.zeros(6), C)
            Z = dq.mul(T(t - LATENCY[name]), lie.se3_exp(-xi))[0]
            if name == "cam":
                Z = dq.mul(dq.conj(E_CAM), Z)
            rows.append((t, name, Z, C))
    rows.sort(key=lambda r: r[0])
    return (wire(np.array([r[2] for r in rows])), np.array([r[3] for r in rows]),
            [r[1] for r in rows], [body] * len(rows), np.array([r[0] for r in rows]), T)


def nees(X_hat, P, X):
    e = lie.se3_log(dq.mul(dq.conj(X_hat), X))
    return float(e @ np.linalg.solve(P, e))


CHI2_6_999 = fusion.chi2_quantile(0.999, 6)


def test_fuse_a_moving_body_at_the_query_time(client):
    Z, S, names, _, stamps, T = moving(20)
    t = stamps.max() - 0.03        # between the newest camera and arm measurements
    got = client.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=t, body="box")
    want = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=t)
    assert got.time == want.time == t
    s = np.sign(got.mean[:4] @ want.mean[:4])
    np.testing.assert_allclose(s * got.mean, want.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-12, atol=0)
    np.testing.assert_allclose(got.twist, want.twist, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.twist_covariance, want.twist_covariance, rtol=1e-12, atol=0)
    (a,), (b,) = got.latencies, want.latencies
    assert a.name == "arm" and (a.configured, a.prior_sigma) == (ARM_LATENCY, 0.005)
    assert a.value == pytest.approx(b.value, abs=1e-12) and a.sigma == pytest.approx(b.sigma)
    assert got.dof == want.dof and got.chi2 == pytest.approx(want.chi2, rel=1e-12)
    assert got.extrapolation == 0.0
    # the truth lies within the covariance: pose at t, and the twist
    assert nees(got.mean, got.covariance, T(t)[0]) < CHI2_6_999
    e = got.twist - TWIST
    assert e @ np.linalg.solve(got.twist_covariance, e) < CHI2_6_999
    assert abs(got.latencies[0].value - ARM_LATENCY) < 3 * got.latencies[0].sigma


def test_fuse_acceleration_psd_as_in_process(client):
    """The random-walk twist through the server: the domain's answer, and a covariance that
    grows with it (the same data without it is claimed to be known better)."""
    Z, S, names, _, stamps, T = moving(22)
    Q = np.diag([0.5, 0.5, 0.5, 0.05, 0.05, 0.05])
    t = stamps.max() - 0.03
    got = client.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=t,
                      acceleration_psd=Q)
    want = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=t,
                       acceleration_psd=Q)
    s = np.sign(got.mean[:4] @ want.mean[:4])
    np.testing.assert_allclose(s * got.mean, want.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-12, atol=0)
    plain = client.fuse(Z, S, names=names, sources=SOURCES, times=stamps, time=t)
    assert np.linalg.det(got.covariance) > 1.5 * np.linalg.det(plain.covariance)


def test_fuse_max_skew_drops_with_a_reason(client):
    Z, S, names, _, stamps, T = moving(21)
    got = client.fuse(Z, S, names=names, sources=SOURCES, times=stamps, max_skew=0.1)
    want = fusion.fuse(Z, S, names=names, sources=SOURCES, times=stamps, max_skew=0.1)
    taken = stamps - np.array([LATENCY[n] for n in names])
    old = np.flatnonzero(got.time - taken > 0.1)
    assert old.size > 0 and [d.index for d in got.dropped] == old.tolist()
    assert got.dropped == want.dropped
    for d in got.dropped:
        assert d.source == names[d.index] and "beyond max_skew 0.1 s" in d.reason
    assert not set(old) & set(got.inliers.tolist())
    np.testing.assert_allclose(got.mean * np.sign(got.mean[0] * want.mean[0]), want.mean,
                               rtol=0, atol=1e-12)
    msg = client.fuse_request(pb.FuseRequest(
        measurements=fusion_convert.measurement_msgs(Z, S, names=names, times=stamps),
        options=fusion_convert.options_msg(sources=SOURCES, max_skew=0.1)))
    assert [d.index for d in msg.dropped] == old.tolist()
    assert msg.dropped[0].reason == want.dropped[0].reason
    assert msg.dropped[0].source == names[old[0]]


# ---- StreamFuse --------------------------------------------------------------------------------
def messages(*scenes, size=10):
    """The measurements of several scenes merged in stamp order, cut into Batches of ``size``."""
    Z = np.concatenate([sc[0] for sc in scenes])
    S = np.concatenate([sc[1] for sc in scenes])
    names = sum((sc[2] for sc in scenes), [])
    bodies = sum((sc[3] for sc in scenes), [])
    stamps = np.concatenate([sc[4] for sc in scenes])
    order = np.argsort(stamps, kind="stable")
    out = []
    for k in range(0, len(order), size):
        o = order[k:k + size]
        out.append(Batch(Z[o], S[o], names=[names[i] for i in o], bodies=[bodies[i] for i in o],
                         times=stamps[o]))
    return out


def test_stream_answers_each_body_at_its_output_ticks(client):
    rate, window = 20.0, 0.2
    scenes = {"box": moving(30, end=0.6, body="box"), "cup": moving(31, start=0.1, end=0.5,
                                                                     body="cup")}
    batches = messages(*scenes.values())
    answers = list(client.stream_fuse(batches, sources=SOURCES, output_rate=rate, window=window))
    assert not [a.error for a in answers if a.error]
    for body, (_Z, _S, names, _, stamps, T) in scenes.items():
        taken = stamps - np.array([LATENCY[n] for n in names])
        # each body on its own grid: (k + phase) / rate, the phase from its name
        phase = tick_phase(body)
        assert phase == zlib.crc32(body.encode()) / 2**32 and 0 < phase < 1
        k = np.arange(np.ceil(taken.min() * rate - phase), np.floor(taken.max() * rate - phase)
                      + 1)
        ticks = (k + phase) / rate
        assert taken.min() <= ticks[0] and ticks[-1] <= taken.max()
        mine = [a for a in answers if a.body == body]
        assert [a.time for a in mine] == ticks.tolist()      # every tick once, in order
        # each answered after the request whose measurements first reached its tick
        reached = np.maximum.accumulate([max((t - LATENCY[n] for t, n, o in
                                              zip(b.times, b.names, b.bodies) if o == body),
                                             default=-np.inf) for b in batches])
        assert [a.request for a in mine] == [int(np.argmax(reached >= t)) for t in ticks]
        for a in mine:
            assert nees(a.fused.mean, a.fused.covariance, T(a.time)[0]) < CHI2_6_999
    # the same answers as the domain's tracker fed the same requests, up to each answer's request
    replay = fusion.Tracker(window, sources=SOURCES)
    for r, b in enumerate(batches):
        replay.ingest(fusion.Rows(b.bodies, b.names, b.times, b.poses, b.covariances))
        for a in (a for a in answers if a.request == r):
            want = replay.estimate(a.body, a.time)
            s = np.sign(a.fused.mean[:4] @ want.mean[:4])
            np.testing.assert_allclose(s * a.fused.mean, want.mean, rtol=0, atol=1e-12)
            np.testing.assert_allclose(a.fused.covariance, want.covariance, rtol=1e-12)
            # numbered over the stream, as the tracker numbers what it is offered
            assert a.measurements.tolist() == replay.window_of(a.body).ids.tolist()
def test_stream_without_output_rate_answers_each_body_after_each_request_carrying_it(client):
    _, A, SA = scene(10, n=4)
    _, B, SB = scene(11, n=3)
    Z, S = np.concatenate([A, B]), np.concatenate([SA, SB])
    bodies = ["box", "cup", "box", "box", "cup", "box", "cup"]
    order = [0, 4, 1, 2, 5, 3, 6]     # interleaved: box gets A, cup gets B
    answers = list(client.stream_fuse([Batch(Z[order], S[order], bodies=bodies),
                                       Batch(B, SB, bodies=["cup"] * 3)]))
    assert [(a.request, a.body) for a in answers] == [(0, "box"), (0, "cup"), (1, "cup")]
    box, cup, cup2 = answers
    # one instant (time 0): the static fusion of each body's window, which keeps the first
    # request's measurements of cup for the second
    assert_same(box.fused, local(A, SA))
    assert_same(cup.fused, local(B, SB))
    assert_same(cup2.fused, local(np.concatenate([B, B]), np.concatenate([SB, SB])))
    assert box.measurements.tolist() == [0, 2, 3, 5] and cup.measurements.tolist() == [1, 4, 6]
    assert cup2.measurements.tolist() == [1, 4, 6, 7, 8, 9]   # numbered over the whole stream
    assert box.time == cup.time == 0.0


def test_stream_survives_bad_measurements_and_uses_the_rest_of_their_message(client):
    Z, S, names, bodies, stamps, T = moving(40, end=0.4)
    batches = messages((Z, S, names, bodies, stamps, T))
    b = batches[2]
    poses, covs, srcs, times = b.poses.copy(), b.covariances.copy(), list(b.names), b.times.copy()
    poses[1, 4] = np.nan                          # 1: a NaN in the pose
    covs[3, 0, 0] = -1.0                          # 3: not positive definite
    srcs[5] = "cma"                               # 5: a source the options do not list
    times[7] = times[6] - 0.5                     # 7: half a second back, beyond the window
    covs[8, 2, 4] = covs[8, 4, 2] = np.nan        # 8: a NaN in the covariance
    batches[2] = Batch(poses, covs, names=srcs, bodies=b.bodies, times=times)
    first = sum(len(x.poses) for x in batches[:2])
    answers = list(client.stream_fuse(batches, sources=SOURCES, window=0.2))
    errors = [a for a in answers if a.error]
    assert [(a.request, a.measurement) for a in errors] == [(2, 1), (2, 3), (2, 5), (2, 7), (2, 8)]
    assert all(a.body == "box" for a in errors)
    assert errors[0].error.startswith("requests[2].measurements[1].pose.")
    assert errors[1].error == "requests[2].measurements[3].covariance: not positive definite"
    assert errors[2].error == ("requests[2].measurements[5].source: 'cma' is not among "
                               "options.sources (cam, arm)")
    assert errors[3].error.startswith(f"requests[2].measurements[7] (body 'box', source "
                                      f"'{srcs[7]}', time {float(times[7]):.6g}): taken at ")
    assert errors[3].error.endswith("beyond the window 0.2 s")
    assert errors[4].error == "requests[2].measurements[8].covariance: contains NaN or infinity"
    poses_after = [a for a in answers if a.fused is not None]
    assert [a.request for a in poses_after] == list(range(len(batches)))   # one each, none lost
    window = set(poses_after[2].measurements.tolist())
    good = {first + i for i in (0, 2, 4, 6, 9)}
    assert good <= window and not window & {first + i for i in (1, 3, 5, 7, 8)}
    for a in poses_after:
        assert nees(a.fused.mean, a.fused.covariance, T(a.time)[0]) < CHI2_6_999


def test_stream_tick_that_cannot_be_fused_is_an_error_entry(client):
    Z, S, names, bodies, stamps, T = moving(41, end=0.3)
    batches = messages((Z, S, names, bodies, stamps, T))
    # the arm's samples are 10 ms apart with a phase that keeps them > 1 ms from every tick
    answers = list(client.stream_fuse(batches, sources=SOURCES, output_rate=50.0,
                                      max_skew=0.001))
    assert answers and all(a.error and a.measurement == -1 and a.body == "box" for a in answers)
    assert answers[0].error.startswith(f"requests[{answers[0].request}]: body 'box' at ")
    assert "options.max_skew: every measurement was taken more than 0.001 s" in answers[0].error
    assert answers[-1].request == len(batches) - 1    # every tick, to the end of the stream


def test_stream_unknown_source_and_late_options_are_error_entries(server):
    _, Z, S = scene(13, n=3)
    first = pb.FuseStreamRequest(options=pb.FusionOptions(sources=[pb.Source(name="cam")]))
    first.measurements.extend(fusion_convert.measurement_msgs(Z, S, names=["cam", "cma", "cam"],
                                                       bodies=["box"] * 3))
    late = pb.FuseStreamRequest(options=pb.FusionOptions(robust=True))
    late.measurements.extend(fusion_convert.measurement_msgs(Z, S, names=["cam"] * 3,
                                                      bodies=["box"] * 3))
    import grpc
    with grpc.insecure_channel(server.target) as ch:
        call = ch.stream_stream("/dqpose.v1.Fusion/StreamFuse",
                                request_serializer=pb.FuseStreamRequest.SerializeToString,
                                response_deserializer=pb.FusedPose.FromString)
        answers = list(call(iter([first, late]), timeout=30))
    assert answers[0].error.details == (
        "requests[0].measurements[1].source: 'cma' is not among options.sources (cam)")
    assert answers[1].HasField("pose") and list(answers[1].measurements) == [0, 2]
    assert answers[2].error.measurement == -1
    assert answers[2].error.details.startswith("requests[1].options: only the first request")
    assert list(answers[3].measurements) == [0, 2, 3, 4, 5]   # the window keeps request 0's


def test_stream_bad_options_end_it(client):
    _, Z, S = scene(14, n=2)
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].options.sources\[1\]: source "
                                              r"'a' given twice"):
        list(client.stream_fuse([Batch(Z, S)], sources=[Source("a"), Source("a")]))
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].output_rate: must be finite"):
        list(client.stream_fuse([Batch(Z, S)], output_rate=-1.0))
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].options.window: must be "
                                              r"positive"):
        list(client.stream_fuse([Batch(Z, S)], window=-1.0))
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].options.max_skew: must be "
                                              r"nonnegative"):
        list(client.stream_fuse([Batch(Z, S)], max_skew=-1.0))


def test_stream_measurement_without_a_body_is_an_error_entry(client):
    _, Z, S = scene(16, n=2)
    answers = list(client.stream_fuse([Batch(Z, S, bodies=["", "box"])]))
    assert answers[0].error == ("requests[0].measurements[0].body: empty (every measurement "
                                "names its body)")
    assert answers[1].body == "box" and answers[1].measurements.tolist() == [1]


def test_stream_batch_that_cannot_be_sent_raises_after_the_answers(client):
    _, Z, S = scene(15, n=2)
    it = client.stream_fuse([Batch(Z, S, bodies=["box"] * 2), Batch(Z, S[:1])])
    assert next(it).fused is not None
    with pytest.raises(ValueError, match=r"^batches\[1\].covariances: expected \(2, 6, 6\)"):
        next(it)


def test_server_offers_fusion_health_and_reflection(server, client):
    assert client.health("dqpose.v1.Fusion") == "SERVING"


def test_fuse_and_stream_fuse_pass_the_extrinsic_covariance(client):
    """Source.extrinsic_covariance (field 6) reaches dqpose.fusion: Fuse and StreamFuse answer
    what fusion.fuse computes with it, which differs from the fit without it."""
    _, Z, S = scene(11, n=4)
    mount = np.diag([1e-4] * 3 + [4e-6] * 3)
    E = lie.se3_exp(np.array([0.1, 0.2, -0.1, 0.3, 0.0, 1.0]))
    with_cov = [Source("cam", extrinsic=E, extrinsic_covariance=mount)]
    names = ["cam"] * len(Z)
    want = fusion.fuse(Z, S, names=names, sources=with_cov)
    without = fusion.fuse(Z, S, names=names, sources=[Source("cam", extrinsic=E)])
    assert not np.allclose(want.covariance, without.covariance, rtol=0.1)
    got = client.fuse(Z, S, names=names, sources=with_cov)
    np.testing.assert_allclose(got.covariance, want.covariance, rtol=1e-9)
    [answer] = list(client.stream_fuse([Batch(Z, S, None, names, ["box"] * len(Z),
                                              np.zeros(len(Z)))], sources=with_cov))
    np.testing.assert_allclose(answer.fused.covariance, want.covariance, rtol=1e-9)
