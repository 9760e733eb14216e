"""dqpose.cli.readout: the rows people read. A rotation passing through 180 degrees reads on
without a jump, each row agreeing with an independent reader (scipy) up to whole turns."""
from __future__ import annotations

import numpy as np

from dqpose import dq, fusion
from dqpose.cli.readout import Readout
from dqpose.rpc.client_types import StreamAnswer


def _answer(t: float, pose: np.ndarray, sources=("b", "a")) -> StreamAnswer:
    cov = np.diag([1e-4, 4e-4, 1e-4, 1e-6, 9e-6, 4e-6])
    fused = fusion.fuse(np.stack([pose, pose]), np.stack([cov, cov]), names=list(sources))
    return StreamAnswer(0, "box", t, fused, np.arange(2))


def _columns(row: str) -> np.ndarray:
    return np.array([float(v) for v in row.split()[2:13]])


def test_angles_are_unwrapped_against_the_row_before_and_agree_with_scipy_up_to_turns():
    from scipy.spatial.transform import Rotation

    # yaw from 170 to 190 deg about a tilted axis near z; roll near 180 as well
    table = Readout(start=100.0)
    rows = []
    for k, deg in enumerate(np.linspace(170.0, 190.0, 11)):
        r = Rotation.from_euler("xyz", [179.0 + 0.2 * k, 5.0, deg], degrees=True)
        q = r.as_quat()[[3, 0, 1, 2]]
        row = _columns(table.row(_answer(100.0 + 0.1 * k, dq.from_pose(q, [0.5, -0.2, 0.3]))))
        rows.append(row)
        np.testing.assert_allclose(row[:3], [500.0, -200.0, 300.0], atol=0.01)
        turns = (row[6:9] - r.as_euler("xyz", degrees=True)) / 360.0
        np.testing.assert_allclose(turns, np.round(turns), atol=1e-4)
        angle = np.linalg.norm(row[3:6])
        same = Rotation.from_rotvec(row[3:6], degrees=True) * r.inv()
        assert same.magnitude() < 1e-3 and angle > 0
    steps = np.abs(np.diff(np.array(rows)[:, 3:9], axis=0))
    assert steps.max() < 5.0, steps          # 2 deg of yaw a row: no jump by a turn
    # the raw readings did jump: yaw wraps at 180
    raw = [Rotation.from_euler("xyz", [179, 5, d], degrees=True).as_euler("xyz", degrees=True)[2]
           for d in (178.0, 182.0)]
    assert abs(raw[1] - raw[0]) > 300.0


def test_times_are_since_the_start_sigma_the_worst_direction_and_sources_in_name_order():
    table = Readout()
    first = table.row(_answer(1234.5, dq.identity()))
    later = table.row(_answer(1235.0, dq.identity(), sources=("c", "a")))
    assert first.split()[0] == "0.000" and later.split()[0] == "0.500"
    assert [c.split(":")[0] for c in first.split()[-2:]] == ["a", "b"]
    assert [c.split(":")[0] for c in later.split()[-2:]] == ["a", "c"]
    # the fused covariance of two equal measurements is half of one: worst axis y
    sigma_mm, sigma_deg = _columns(first)[9:11]
    np.testing.assert_allclose([sigma_mm, sigma_deg],
                               [np.sqrt(9e-6 / 2) * 1e3, np.degrees(np.sqrt(4e-4 / 2))],
                               rtol=1e-3)
    assert "σ mm" in table.header() and table.header().split()[:2] == ["t", "s"]
