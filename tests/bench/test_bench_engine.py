"""bench_engine's harness, small: both sides answer one scene alike (dqpose's tick and GTSAM's
newest key agree within their covariances, each near the truth), and the rows time real answers
(the tick rows count the ticks the scene makes due). The --serve rows' runs are
world_publish.run's, which tests/bench/test_bench_world.py checks against a real server and the
relay."""
import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.fusion.chi2 import chi2_quantile

pytest.importorskip("gtsam", reason="the [test] extra")
from tests.bench import bench_engine as be  # noqa: E402  (after the skip: it imports gtsam)

GATE = chi2_quantile(0.999, 6)


def mahalanobis(a, b, cov) -> float:
    xi = lie.se3_log(dq.mul(dq.conj(a), b))
    return float(xi @ np.linalg.solve(cov, xi))


def test_dqpose_and_gtsam_answer_one_scene_alike():
    got = be.tick_agreement(bodies=4, seconds=1.0)
    ours, cov = got["dqpose"]
    for name in ("IFLS", "ISAM2"):
        pose, marginal = got[name]
        assert np.all(np.linalg.eigvalsh(marginal) > 0), name
        # the same pose to within both covariances (their estimators differ, their data not)
        assert mahalanobis(ours, pose, cov + marginal) < GATE, name
        assert mahalanobis(pose, got["truth"], marginal) < GATE, name
        # a body seen 200 times a second: both far tighter than one measurement (1 mm)
        assert np.sqrt(marginal[3:, 3:].diagonal()).max() < 1e-3, name
    assert mahalanobis(ours, got["truth"], cov) < GATE
    assert np.sqrt(cov[3:, 3:].diagonal()).max() < 1e-3


def test_tick_rows_time_the_ticks_the_scene_makes_due():
    rows = be.tick_rows(rounds=2, seconds=0.1, ticks=10, bodies=10, history=0.5)
    assert [r[0].split(" ")[0] for r in rows] == ["tick", "tick", "ingest", "in"]
    # 10 bodies at 30 Hz over 2 rounds of 0.1 s: ~60 ticks answered
    ticks = int(rows[0][-1].split("; ")[1].split(" dqpose")[0])
    assert 40 <= ticks <= 80, rows[0]
    for r in rows:
        assert r[5] in ("yes", "no", "—"), r
    ratio = float(rows[0][3].split("×")[0])
    assert 0.0 < ratio < 1000.0, rows[0]


def test_lookup_rows_time_both_scenes():
    rows = be.lookup_rows(rounds=2, ticks=5)
    assert len(rows) == 2 and "shared uncertain mount" in rows[1][0]
    for r in rows:
        assert 0.0 < float(r[3].split("×")[0]) < 1000.0, r
        assert r[-1].startswith("62 measurements a body"), r     # 2 cameras × 31 ticks in 1 s

