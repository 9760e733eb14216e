"""Piecewise SCREW / TOOL_LINEAR interpolation, checked against pytransform3d (independent code)."""
import re

import numpy as np
import pytest
from pytransform3d import rotations as pr
from pytransform3d import transformations as pt

from dqpose import dq
from dqpose.interpolate import interpolate


def _keyframes(rng, k=4):
    q = rng.normal(size=(k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = rng.uniform(-0.5, 0.5, size=(k, 3))
    times = np.cumsum(rng.uniform(0.1, 1.0, size=k))
    return times, dq.from_pose(q, t), q, t


def _same_pose(a, b, atol=1e-9):
    """Dual quaternions up to the q ~ -q sign."""
    a, b = np.asarray(a), np.asarray(b)
    s = np.sign(np.sum(a[..., :4] * b[..., :4], axis=-1, keepdims=True))
    np.testing.assert_allclose(a * s, b, atol=atol)


@pytest.mark.parametrize("mode", ["screw", "tool_linear"])
def test_keyframes_are_hit_exactly_at_their_times(mode):
    times_k, dqs_k, _, _ = _keyframes(np.random.default_rng(1))
    _same_pose(interpolate(times_k, dqs_k, times_k, mode), dqs_k, atol=1e-12)


def test_screw_matches_pytransform3d_sclerp_per_segment():
    rng = np.random.default_rng(2)
    times_k, dqs_k, _, _ = _keyframes(rng, 5)
    times = rng.uniform(times_k[0], times_k[-1], 200)  # unsorted on purpose
    out = interpolate(times_k, dqs_k, times)
    for t, got in zip(times, out):
        i = min(np.searchsorted(times_k, t, side="right") - 1, len(times_k) - 2)
        tau = (t - times_k[i]) / (times_k[i + 1] - times_k[i])
        a, b = dqs_k[i], dqs_k[i + 1]
        if np.dot(a[:4], b[:4]) < 0:  # pytransform3d does not pick the short way itself
            b = -b
        _same_pose(got, pt.dual_quaternion_sclerp(a, b, tau))


def test_tool_linear_moves_the_tool_point_on_a_line_and_slerps_orientation():
    rng = np.random.default_rng(3)
    times_k, dqs_k, q_k, t_k = _keyframes(rng, 3)
    times = np.linspace(times_k[0], times_k[-1], 101)
    q, t = dq.to_pose(interpolate(times_k, dqs_k, times, "tool_linear"))
    for s, qi, ti in zip(times, q, t):
        i = min(np.searchsorted(times_k, s, side="right") - 1, 1)
        tau = (s - times_k[i]) / (times_k[i + 1] - times_k[i])
        np.testing.assert_allclose(ti, t_k[i] + tau * (t_k[i + 1] - t_k[i]), atol=1e-12)
        ref = pr.quaternion_slerp(q_k[i], pr.pick_closest_quaternion(q_k[i + 1], q_k[i]), tau)
        np.testing.assert_allclose(qi * np.sign(qi @ ref), ref, atol=1e-9)


def test_screw_and_tool_linear_differ_when_rotating_while_translating():
    # 90 degrees about z while moving 0.3 m: the screw path leaves the straight line.
    k = dq.from_pose([[1, 0, 0, 0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]],
                     [[0, 0, 0], [0.3, 0, 0]])
    mid_screw = dq.to_pose(interpolate([0, 1], k, [0.5], "screw"))[1][0]
    mid_line = dq.to_pose(interpolate([0, 1], k, [0.5], "tool_linear"))[1][0]
    np.testing.assert_allclose(mid_line, [0.15, 0, 0], atol=1e-12)
    assert np.linalg.norm(mid_screw - mid_line) > 0.02


def test_antipodal_keyframe_gives_the_same_motion():
    rng = np.random.default_rng(4)
    times_k, dqs_k, _, _ = _keyframes(rng, 3)
    flipped = dqs_k.copy()
    flipped[1] *= -1
    times = np.linspace(times_k[0], times_k[-1], 50)
    for mode in ("screw", "tool_linear"):
        _same_pose(interpolate(times_k, flipped, times, mode),
                   interpolate(times_k, dqs_k, times, mode))


@pytest.mark.parametrize("times_k, times, message", [
    ([0.0, 1.0, 1.0], [0.5], "times_k[2]: 1.0 is not after the previous keyframe time 1.0"),
    ([0.0, 2.0, 1.0], [0.5], "times_k[2]: 1.0 is not after the previous keyframe time 2.0"),
    ([0.0, np.nan, 2.0], [0.5], "times_k[1]: contains NaN or infinity"),
    ([0.0, 1.0, 2.0], [0.5, 2.5], "times[1]: 2.5 is outside the keyframe range [0.0, 2.0]"),
    ([0.0, 1.0, 2.0], [-1e-9], "times[0]: -1e-09 is outside the keyframe range"),
    ([0.0, 1.0, 2.0], [np.inf], "times[0]: contains NaN or infinity"),
    ([-1e308, 1e308, 1.5e308], [1e308],
     "times_k[1]: the span from the previous keyframe time -1e+308 to 1e+308 overflows a float64"),
])
def test_bad_times_name_the_argument(times_k, times, message):
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        interpolate(times_k, dq.identity((3,)), times)


def test_other_bad_input():
    k = dq.identity((2,))
    with pytest.raises(ValueError, match=r"^times_k: need at least 2 keyframes, got 1"):
        interpolate([0.0], k[:1], [0.0])
    with pytest.raises(ValueError,
                       match=r"^times_k: length 3 does not match the number of keyframes \(2\)"):
        interpolate([0.0, 1.0, 2.0], k, [0.0])
    with pytest.raises(ValueError, match=r"^mode: unknown interpolation 'cubic'"):
        interpolate([0.0, 1.0], k, [0.5], "cubic")
    bad = k.copy()
    bad[1, :4] = 0
    with pytest.raises(ValueError, match=r"^dqs_k\[1\]: zero quaternion"):
        interpolate([0.0, 1.0], bad, [0.5])


def test_a_keyframe_far_from_the_origin_still_gives_rigid_poses_and_the_last_keyframe_exactly():
    """Found by the fuzz (Interpolate with a keyframe at z = 3.6e13 m): ScLERP from that keyframe
    back to one near the origin cancelled to a dual part 1e-3 off orthogonal, which the server's
    answer encoding refused as not a rigid motion (INTERNAL)."""
    q = np.array([0.98877108, 0.0, 0.0, -0.14943813])
    k = np.stack([dq.from_pose([1.0, 0, 0, 0], [0.1, 0, 0]),
                  dq.from_pose(q / np.linalg.norm(q), [0.2, 0.04, 3.6472413570864e13]),
                  dq.from_pose(q / np.linalg.norm(q), [0.2, 0.2, 0.1])])
    out = interpolate([0.0, 0.1, 0.2], k, [0.0, 0.05, 0.15, 0.2, 0.2 - 1e-15])
    dq.to_pose(out)                                  # rigid: raises otherwise
    assert np.array_equal(out[3], k[2]) and np.array_equal(out[0], k[0])
