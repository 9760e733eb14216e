"""The viewer's timeline: a recording's fused poses by body with their covariances, error entries
left out, looked up by time; plans by name, the last one made by then; an arm's actual path
from its Execute feedback and its WatchArm states, and the slider's scene at a time."""
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


def test_an_arms_actual_path_comes_from_its_feedback_and_its_states(tmp_path):
    from dqpose.record.reader import read
    from dqpose.view.page import Page
    from dqpose.view.timeline import timeline
    from tests.view.test_page import record_arm

    tl = timeline(read(record_arm(tmp_path)))
    assert list(tl.arms) == ["ur"]
    path = tl.arms["ur"]
    assert len(path.ns) == 30 + 2 and np.all(np.diff(path.ns) >= 0)
    np.testing.assert_allclose(path.t[:30, 0], np.linspace(0.0, 0.6, 30), atol=1e-12)
    np.testing.assert_allclose(path.t[:, 1], 0.32, atol=1e-12)    # the actual, not commanded
    (name, planned_ns, planned), = tl.plans
    assert name == "ur" and planned_ns < path.ns[0]
    page = Page(tl, port=0)
    try:
        page.show(path.ns[14])
        assert page.tools["ur"].visible
        np.testing.assert_allclose(page.tools["ur"].position, path.t[14], atol=1e-12)
        page.show(path.ns[0] - 1)
        assert not page.tools["ur"].visible and not page.paths.get("ur", page.tools["ur"]).visible
    finally:
        page.close()
