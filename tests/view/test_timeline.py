"""The viewer's timeline: a recording's fused poses by body with their covariances, error entries
left out, looked up by time; plans by name, the last one made by then."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the [record] extra")


def test_poses_and_plans_are_found_by_time(tmp_path):
    from dqpose.record.reader import read
    from dqpose.view.timeline import timeline
    from tests.view.test_page import record

    rec = read(record(tmp_path))
    tl = timeline(rec)
    assert sorted(tl.tracks) == ["box", "cup"]
    box = tl.tracks["box"]
    assert box.at(tl.start - 1) is None
    i = box.at(tl.end)
    assert i == len(box.ns) - 1
    np.testing.assert_allclose(box.t[i], [0.005, 0.0, 0.3], atol=1e-9)
    # two equal measurements: half the covariance
    np.testing.assert_allclose(np.diag(box.cov[i])[3:], np.array([0.08, 0.05, 0.03]) ** 2 / 2,
                               rtol=1e-6)
    (name, ns, path), = tl.plans
    assert tl.plan_at("Plan", ns - 1) is None
    np.testing.assert_allclose(tl.plan_at("Plan", ns)[[0, -1]], [[0, -0.3, 0.3], [0.6, -0.3,
                                                                                   0.3]])
