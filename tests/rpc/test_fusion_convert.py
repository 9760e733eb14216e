"""dqpose.rpc.fusion_convert: a fused pose through its message and back."""
from __future__ import annotations

import numpy as np

from dqpose import dq, fusion, lie
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc.fusion_convert import fused_from_msg, fused_to_msg

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
