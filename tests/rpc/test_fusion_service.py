"""The dqpose.v1.Fusion service against a real server on 127.0.0.1: Fuse equals
service.fusion.fuse in process; bad input is INVALID_ARGUMENT naming the measurement; StreamFuse
answers per body, and survives a bad measurement with an error entry for it."""
from __future__ import annotations

import numpy as np
import pytest

from service import dq, fusion, lie
from service.fusion import Source, Status, Verdict
from service.rpc import convert
from service.rpc.client import Batch, Client, InvalidArgument
from service.rpc.fusion import Fusion
from service.rpc._proto.dqpose.v1 import fusion_pb2 as pb

from _grpc_server import ServerThread


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
    return dq.from_pose(*convert.pose_arrays(np.asarray(Z)))


def local(Z, *args, **kw):
    """service.fusion.fuse in process, of the poses the server received."""
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
    O = lie.se3_exp(np.array([0.0, 0.0, 0.2, 0.0, 0.0, 0.1]))
    E, O = wire(E), wire(O)
    sources = [Source("cam1", extrinsic=E), Source("cam2"), Source("arm", E, O)]
    _, Z, S = scene(1, outliers=2 if robust else 0)
    # each measurement in its source's frame: cam1 and the arm's flange seen from E
    Z[:2] = dq.mul(dq.conj(E), Z[:2])
    Z[4] = dq.mul(dq.mul(dq.conj(E), Z[4]), dq.conj(O))
    S[4] = lie.adjoint(O) @ S[4] @ lie.adjoint(O).T
    want = local(Z, S, names=NAMES, robust=robust,
                 sources=[Source("cam1", extrinsic=E), Source("cam2"), Source("arm", E, O)])
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
    ms = convert.measurement_msgs(Z, S, names=["a", "b", "a"], bodies=["box"] * 3,
                                  times=[1.0, 2.5, 2.0])
    r = client.fuse_request(pb.FuseRequest(measurements=ms))
    assert r.body == "box" and r.time == 2.5          # time 0: the newest measurement's
    assert r.status == pb.FUSION_STATUS_CONVERGED and r.dof == 12 and len(r.covariance) == 36
    assert [s.name for s in r.sources] == ["a", "b"] and len(r.residuals) == 18
    r = client.fuse_request(pb.FuseRequest(measurements=ms, options=pb.FusionOptions(time=7.0)))
    assert r.time == 7.0


def _request(Z, S, **kw):
    return pb.FuseRequest(measurements=convert.measurement_msgs(Z, S, **kw))


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
    (lambda r: setattr(r.options, "max_skew", 0.1), "options.max_skew: time alignment is not"),
    (lambda r: setattr(r.options.sources[1], "latency", 0.04),
     "options.sources[1].latency: time alignment is not"),
    (lambda r: setattr(r.options, "probability", 1.5), "options.probability: must be within"),
    (lambda r: r.ClearField("measurements"), "measurements: empty request: no measurements"),
])
def test_fuse_bad_input_is_invalid_argument_naming_it(client, edit, message):
    _, Z, S = scene(4)
    r = _request(Z, S, names=NAMES, bodies=["box"] * 6)
    r.options.sources.add(name="cam1", extrinsic=convert.dq_to_pose(Z[0]))
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


# ---- StreamFuse --------------------------------------------------------------------------------
def test_stream_answers_per_body_many_bodies_in_one_message(client):
    _, A, SA = scene(10, n=4)
    _, B, SB = scene(11, n=3)
    Z, S = np.concatenate([A, B]), np.concatenate([SA, SB])
    bodies = ["box", "cup", "box", "box", "cup", "box", "cup"]
    order = [0, 4, 1, 2, 5, 3, 6]     # interleaved: box gets A, cup gets B
    Zm, Sm = Z[order], S[order]
    times = np.arange(7) * 0.01
    answers = list(client.stream_fuse([Batch(Zm, Sm, bodies=bodies, times=times),
                                       Batch(B, SB, bodies=["cup"] * 3)]))
    assert [(a.request, a.body) for a in answers] == [(0, "box"), (0, "cup"), (1, "cup")]
    box, cup, cup2 = answers
    assert_same(box.fused, local(A, SA))
    assert_same(cup.fused, local(B, SB))
    assert_same(cup2.fused, local(B, SB))
    assert box.measurements.tolist() == [0, 2, 3, 5] and cup.measurements.tolist() == [1, 4, 6]
    assert cup2.measurements.tolist() == [7, 8, 9]      # numbered over the whole stream
    assert box.time == pytest.approx(0.05) and cup.time == pytest.approx(0.06)


def test_stream_survives_bad_measurements(client):
    _, Z, S = scene(12, n=5)
    bad = S.copy()
    bad[1, 0, 0] = -1.0                       # not positive definite
    Zbad = Z.copy()
    Zbad[3, :4] = 0.0                         # zero quaternion
    answers = list(client.stream_fuse([
        Batch(Z, S, bodies=["box"] * 5),
        Batch(Zbad, bad, bodies=["box"] * 5),
        Batch(Z[:1], bad[1:2], bodies=["cup"]),   # a body whose only measurement is bad
        Batch(Z, S, bodies=["box"] * 5),
    ]))
    errors = [(a.request, a.measurement, a.error) for a in answers if a.error]
    assert [e[:2] for e in errors] == [(1, 1), (1, 3), (2, 0)]
    assert errors[0][2] == "requests[1].measurements[1].covariance: not positive definite"
    assert errors[1][2].startswith("requests[1].measurements[3].pose.orientation: ")
    poses = [a for a in answers if a.fused is not None]
    assert [(a.request, a.body) for a in poses] == [(0, "box"), (1, "box"), (3, "box")]
    assert_same(poses[0].fused, local(Z, S))
    keep = [0, 2, 4]                          # the good ones of request 1 are fused
    q, t = convert.pose_arrays(Zbad)           # as the client wrote them
    assert_same(poses[1].fused, fusion.fuse(dq.from_pose(q[keep], t[keep]), S[keep]))
    assert poses[1].measurements.tolist() == [5, 7, 9]
    assert_same(poses[2].fused, local(Z, S))


def test_stream_unknown_source_and_late_options_are_error_entries(server):
    _, Z, S = scene(13, n=3)
    first = pb.FuseStreamRequest(options=pb.FusionOptions(sources=[pb.Source(name="cam")]))
    first.measurements.extend(convert.measurement_msgs(Z, S, names=["cam", "cma", "cam"]))
    late = pb.FuseStreamRequest(options=pb.FusionOptions(robust=True))
    late.measurements.extend(convert.measurement_msgs(Z, S, names=["cam"] * 3))
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
    assert list(answers[3].measurements) == [3, 4, 5]


def test_stream_bad_options_end_it(client):
    _, Z, S = scene(14, n=2)
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].options.sources\[1\]: source "
                                              r"'a' given twice"):
        list(client.stream_fuse([Batch(Z, S)], sources=[Source("a"), Source("a")]))
    with pytest.raises(InvalidArgument, match=r"^requests\[0\].output_rate: must be finite"):
        list(client.stream_fuse([Batch(Z, S)], output_rate=-1.0))


def test_stream_batch_that_cannot_be_sent_raises_after_the_answers(client):
    _, Z, S = scene(15, n=2)
    it = client.stream_fuse([Batch(Z, S), Batch(Z, S[:1])])
    assert next(it).fused is not None
    with pytest.raises(ValueError, match=r"^batches\[1\].covariances: expected \(2, 6, 6\)"):
        next(it)


def test_server_offers_fusion_health_and_reflection(server, client):
    assert client.health("dqpose.v1.Fusion") == "SERVING"
