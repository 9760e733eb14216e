"""dqpose.rpc.fusion_convert: a fused pose through its message and back."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dqpose import dq, fusion, lie
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc.fusion_convert import fused_from_msg, fused_to_msg
from dqpose.rpc.geometry import dq_to_pose

PROBABILITY, MAX_SKEW = 0.99, 0.25


def _fused() -> fusion.Fused:
    """A fit over time with every field filled: a rejected outlier, a measurement dropped for
    skew, an estimated latency, the twist."""
    rng = np.random.default_rng(4)
    X0, V = lie.se3_exp(rng.normal(size=6) * 0.3), rng.normal(size=6) * 0.2
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    sources = [fusion.Source("cam", latency=0.03, latency_sigma=0.01), fusion.Source("arm")]
    names, times, Z = [], [], []
    for k in range(12):
        s = sources[k % 2]
        t = k / 30.0
        X = dq.mul(X0, lie.se3_exp((t - s.latency) * V))
        Z.append(dq.mul(X, lie.se3_exp(rng.multivariate_normal(np.zeros(6), cov))))
        names.append(s.name)
        times.append(t)
    Z[5] = dq.mul(Z[5], lie.se3_exp(np.array([0.3, 0, 0, 0.05, 0, 0])))    # an outlier
    times[0] -= 1.0                                                          # too old
    return fusion.fuse(np.array(Z), np.array([cov] * 12), names=names, sources=sources,
                       robust=True, probability=PROBABILITY, times=np.array(times),
                       max_skew=MAX_SKEW)


def test_a_fused_pose_reads_back_from_its_bytes_field_by_field():
    f = _fused()
    assert f.rejected and f.dropped and f.latencies and f.twist is not None
    back = fused_from_msg(fpb.FusedPose.FromString(fused_to_msg(f, "box", f.time)
                                                   .SerializeToString()),
                          PROBABILITY, MAX_SKEW)
    np.testing.assert_allclose(back.mean, f.mean, rtol=0, atol=1e-15)   # via q and t
    for name in ("covariance", "residuals", "distances", "nis", "tested", "inliers", "twist",
                 "twist_covariance"):
        a, b = getattr(back, name), getattr(f, name)
        assert a.shape == b.shape and a.dtype.kind == b.dtype.kind, name
        assert a.tobytes() == b.tobytes(), name                         # to the bit
    assert [(r.index, r.source) for r in back.rejected] == [(r.index, r.source)
                                                             for r in f.rejected]
    for name in ("status", "chi2", "dof", "iterations", "sources", "time", "extrapolation",
                 "dropped", "latencies"):
        assert getattr(back, name) == getattr(f, name), name


# ---- the C writer of a FusedPose (service/csrc/fused_wire.c) against protobuf's ----------------

DOUBLES = st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1e-300, 5e-324]),
                    st.floats(allow_nan=False, allow_infinity=False, width=64))
NAMES = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=6)
COUNTS = st.integers(0, 2**32 - 1)


@st.composite
def fits(draw) -> fusion.Fused:
    """A :class:`fusion.Fused` of any shape: zeros, -0.0, empty fields, long names."""
    n = draw(st.integers(0, 6))

    def doubles(shape):
        return np.array(draw(st.lists(DOUBLES, min_size=int(np.prod(shape)),
                                      max_size=int(np.prod(shape))))).reshape(shape)

    pose = draw(st.sampled_from([np.array([1.0, 0, 0, 0, 0, 0, 0, 0]),
                                 lie.se3_exp(np.array([0.3, -0.2, 0.1, 1.5, -2.0, 0.25]))]))
    rejected = tuple(fusion.Rejection(draw(st.integers(0, 300)), draw(NAMES),
                                      draw(st.floats(0, 1e9)), draw(st.floats(0, 1e3)),
                                      draw(st.floats(0.5, 0.9999)))
                     for _ in range(draw(st.integers(0, 3))))
    sources = tuple(fusion.SourceStats(draw(NAMES), draw(COUNTS), draw(COUNTS), draw(DOUBLES),
                                       draw(DOUBLES), draw(DOUBLES),
                                       draw(st.sampled_from(list(fusion.Verdict))))
                    for _ in range(draw(st.integers(0, 3))))
    dropped = tuple(fusion.Dropped(draw(st.integers(0, 2**32 - 1)), draw(NAMES), draw(DOUBLES),
                                   draw(st.floats(0, 10)))
                    for _ in range(draw(st.integers(0, 2))))
    latencies = tuple(fusion.Latency(draw(NAMES), *(draw(DOUBLES) for _ in range(4)))
                      for _ in range(draw(st.integers(0, 2))))
    twist = draw(st.booleans())
    return fusion.Fused(
        status=draw(st.sampled_from(list(fusion.Status))), mean=pose, covariance=doubles((6, 6)),
        residuals=doubles((n, 6)), distances=doubles((n,)), nis=doubles((n,)),
        tested=np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype=bool),
        inliers=np.array(draw(st.lists(st.integers(0, 2**32 - 1), max_size=n)), np.int64),
        rejected=rejected, chi2=draw(DOUBLES), dof=draw(COUNTS), iterations=draw(COUNTS),
        sources=sources, time=draw(DOUBLES), twist=doubles((6,)) if twist else None,
        twist_covariance=doubles((6, 6)) if twist else None, extrapolation=draw(DOUBLES),
        dropped=dropped, latencies=latencies)


@settings(max_examples=300, deadline=None)
@given(fits(), NAMES, DOUBLES, COUNTS, st.lists(st.integers(0, 2**64 - 1), max_size=5),
       st.booleans())
def test_the_c_writer_writes_the_bytes_protobuf_writes(f, body, time, request, ids, relative):
    from dqpose.rpc.wire import fused_pose_bytes

    msg = fused_to_msg(f, body, time)
    msg.request = request
    msg.measurements.extend(ids)
    pose = cov = None
    if relative:    # a World answer relative to another body: its pose, the fit's diagnostics
        pose = lie.se3_exp(np.array([-0.5, 0.25, 2.0, 0.0, 3.0, -1.0]))
        cov = np.arange(36.0).reshape(6, 6) - 17.0
        msg.ClearField("pose")
        del msg.covariance[:]
        dq_to_pose(pose, msg.pose)
        msg.covariance.extend(cov.ravel().tolist())
    assert fused_pose_bytes(f, body, time, request, ids, pose, cov) == msg.SerializeToString()


def test_the_c_writer_writes_a_real_fit_with_every_field_as_protobuf():
    from dqpose.rpc.wire import fused_pose_bytes

    f = _fused()
    msg = fused_to_msg(f, "box", f.time)
    msg.request, msg.measurements[:] = 7, [3, 300, 2**40]
    assert fused_pose_bytes(f, "box", f.time, 7, [3, 300, 2**40]) == msg.SerializeToString()


def test_a_source_keeps_its_parent_through_its_message():
    from dqpose.rpc.fusion_convert import source_msgs, sources_from_msg
    cam = fusion.Source("cam", extrinsic=lie.se3_exp(np.array([0, 0, 0.1, 0.05, 0, 0.02])),
                        extrinsic_covariance=np.eye(6) * 1e-6, parent="tool")
    msg = fpb.FusionOptions()
    source_msgs([cam, fusion.Source("arm")], msg.sources)
    assert [s.parent for s in msg.sources] == ["tool", ""]
    back = sources_from_msg(fpb.FusionOptions.FromString(msg.SerializeToString()).sources)
    assert [s.parent for s in back] == ["tool", ""]
    np.testing.assert_allclose(back[0].extrinsic, cam.extrinsic, atol=1e-15)
