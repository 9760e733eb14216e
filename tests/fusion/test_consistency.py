"""dqpose.fusion.consistency: per-source NIS verdicts."""
import numpy as np
import pytest

from dqpose import fusion
from dqpose.fusion import Verdict
from tests.fusion._scenes import (
    measure,
    random_cov,
    random_pose,
)

gtsam = pytest.importorskip("gtsam")


# ---- consistency -------------------------------------------------------------------------------
def test_a_source_claiming_ten_times_too_small_a_covariance_is_flagged():
    """Four sources of five measurements each; source 'c' reports a covariance 10x smaller than
    its noise. Its NIS stands out; the honest sources stay consistent."""
    rng = np.random.default_rng(41)
    flags = {s: 0 for s in "abcd"}
    trials = 40
    for _ in range(trials):
        X = random_pose(rng)
        S_true = np.repeat(np.array([random_cov(rng) for _ in range(4)]), 5, axis=0)
        names = [s for s in "abcd" for _ in range(5)]
        Z = measure(rng, X, S_true)
        S_claimed = S_true.copy()
        S_claimed[10:15] /= 10.0
        f = fusion.fuse(Z, S_claimed, names=names)
        stats = {s.name: s for s in f.sources}
        assert [s.name for s in f.sources] == list("abcd")
        assert all(s.count == 5 and s.rejected == 0 for s in f.sources)
        # counts are ints: a wire message's uint32 fields take nothing else
        assert all(type(s.count) is int and type(s.rejected) is int for s in f.sources)
        for s in "abcd":
            flags[s] += stats[s].verdict != Verdict.CONSISTENT
        assert stats["c"].verdict == Verdict.OPTIMISTIC and stats["c"].nis_mean > stats["c"].high
    assert flags["c"] == trials
    assert flags["a"] + flags["b"] + flags["d"] <= 0.05 * 3 * trials


def test_nis_of_consistent_sources_averages_six():
    rng = np.random.default_rng(42)
    values = []
    for _ in range(300):
        S = np.array([random_cov(rng) for _ in range(4)])
        f = fusion.fuse(measure(rng, random_pose(rng), S), S)
        assert f.tested.all()
        values.extend(f.nis)
    assert 5.7 <= np.mean(values) <= 6.3


def test_a_source_claiming_too_large_a_covariance_is_pessimistic():
    rng = np.random.default_rng(43)
    S_true = np.array([random_cov(rng) for _ in range(12)])
    names = ["a"] * 6 + ["b"] * 6
    S_claimed = S_true.copy()
    S_claimed[6:] *= 10.0
    f = fusion.fuse(measure(rng, random_pose(rng), S_true), S_claimed, names=names)
    verdicts = {s.name: s.verdict for s in f.sources}
    assert verdicts == {"a": Verdict.CONSISTENT, "b": Verdict.PESSIMISTIC}
